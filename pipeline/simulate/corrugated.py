"""A corrugated line survey over a known smooth field: the micro-levelling test bed.

A smooth synthetic anomaly field (15 sources, 60-300 m wide, ~16 nT RMS) is sampled along 21
north-south lines 50 m apart (0.7 m along, 0.5 m cross-track wander, 0.05 nT noise). The
corrugation is a per-line offset plus a slow drift (2.5 km period) that no tie line saw. The
scores are RMS of grid - truth over the block the lines cover, after removing their mean (no
levelling observes a common constant). Local east/north m, nT.
"""

from __future__ import annotations

import numpy as np

from pipeline.maps.grid import minimum_curvature
from pipeline.maps.level import Line
from pipeline.maps.microlevel import microlevel_lines

SPACING_M = 50.0
SIDE_M = 1000.0


def truth_field(seed: int):
    rng = np.random.default_rng(seed)
    src = [
        (
            rng.uniform(-200, 1200),
            rng.uniform(-200, 1200),
            rng.uniform(60, 300),
            rng.normal(0, 40),
        )
        for _ in range(15)
    ]

    def f(e, n):
        out = np.zeros(np.broadcast(e, n).shape)
        for x, y, w, a in src:
            out += a / (1 + ((e - x) ** 2 + (n - y) ** 2) / w**2) ** 1.5
        return out

    return f


def survey(f, seed: int, offset_nT: float = 1.5, drift_nT: float = 1.0) -> list[Line]:
    rng = np.random.default_rng(seed + 1000)
    out = []
    for i, x in enumerate(np.arange(0, SIDE_M + 1, SPACING_M)):
        n = np.arange(0, SIDE_M, 0.7)
        e = x + rng.normal(0, 0.5, n.size)
        if i % 2:
            n = n[::-1]
        phase = rng.uniform(0, 2 * np.pi)
        err = offset_nT * rng.normal() + drift_nT * rng.normal() * np.sin(
            2 * np.pi * n / 2500 + phase
        )
        v = f(e, n) + err + rng.normal(0, 0.05, n.size)
        out.append(Line(f"L{i}", "survey", e, n, np.arange(n.size) / 10.0, v, np.arange(n.size)))
    return out


def grid_of(lines):
    e, n, v = (
        np.concatenate([getattr(ln, k) for ln in lines]) for k in ("east_m", "north_m", "value_nT")
    )
    return minimum_curvature(e, n, v, SPACING_M / 4, mask_distance_m=SPACING_M)


def microlevelled(lines, **kw):
    """(grid, micro-levelled grid, MicroLevel)."""
    g = grid_of(lines)
    m = microlevel_lines(lines, g, 0.0, SPACING_M, **kw)
    fixed = [
        Line(
            ln.line_id,
            ln.kind,
            ln.east_m,
            ln.north_m,
            ln.time_s,
            ln.value_nT - m.corrections[ln.line_id],
            ln.index,
        )
        for ln in lines
    ]
    return g, grid_of(fixed), m


def error_nT(g, f) -> float:
    e, n = np.meshgrid(*g.coordinates())
    d = g.values - f(e, n)
    ok = np.isfinite(d) & (e >= 0) & (e <= SIDE_M) & (n >= 0) & (n <= SIDE_M)
    d = d[ok]
    return float(np.sqrt(np.mean((d - d.mean()) ** 2)))


def stripes_nT(g, f, cut_m: float = 4 * SPACING_M) -> float:
    """RMS of the error's across-line wavelengths shorter than ``cut_m`` (the stripes)."""
    e, n = np.meshgrid(*g.coordinates())
    cols = (e[0] >= 0) & (e[0] <= SIDE_M)
    rows = (n[:, 0] >= 0) & (n[:, 0] <= SIDE_M)
    d = (g.values - f(e, n))[np.ix_(rows, cols)]
    d = np.where(np.isfinite(d), d, 0.0)
    k = np.fft.rfftfreq(d.shape[1], g.cell_m)
    spec = np.fft.rfft(d - d.mean(axis=1, keepdims=True), axis=1)
    spec[:, k < 1 / cut_m] = 0
    return float(np.sqrt(np.mean(np.fft.irfft(spec, n=d.shape[1], axis=1) ** 2)))
