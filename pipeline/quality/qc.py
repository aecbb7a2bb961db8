"""Survey QC checks that acquisition contracts ask for: noise, height, spacing, speed, diurnal.

Every check takes plain arrays and returns a JSON-ready dict with the figure, the tolerance
and the lines or time spans that exceed it. Positions are local east/north/up metres.
"""

from __future__ import annotations

import numpy as np

from pipeline.noise import white_noise_nT
from pipeline.quality.overlap import Track


def line_noise(tracks: list[Track], field: np.ndarray, threshold_nT: float) -> dict:
    """Normalised 4th-difference noise of every line (nT) and the lines above ``threshold_nT``.

    For white noise Var(Δ⁴x) = 70 σ², so σ = std(Δ⁴x)/√70; geology sampled every few metres
    hardly contributes to the 4th difference.
    """
    per_line = {t.line_id: white_noise_nT(field[t.index]) for t in tracks}
    vals = np.array([v for v in per_line.values() if np.isfinite(v)])
    return {
        "per_line_nT": {
            k: (None if not np.isfinite(v) else round(float(v), 5)) for k, v in per_line.items()
        },
        "median_nT": float(np.median(vals)) if vals.size else None,
        "max_nT": float(vals.max()) if vals.size else None,
        "threshold_nT": threshold_nT,
        "lines_over": sorted(k for k, v in per_line.items() if v > threshold_nT),
    }


def flight_height(tracks: list[Track], up_m: np.ndarray, tolerance_m: float) -> dict:
    """Height deviation of each line from the survey's median flying height.

    Only the ellipsoidal height is recorded (no terrain model), so this checks the drape
    against a constant surface: fine over flat ground, the customary check for UAV blocks.
    """
    all_up = np.concatenate([up_m[t.index] for t in tracks]) if tracks else np.zeros(0)
    if all_up.size == 0:
        return {"nominal_m": None, "tolerance_m": tolerance_m, "lines_over": []}
    nominal = float(np.nanmedian(all_up))
    per_line = {}
    for t in tracks:
        dev = up_m[t.index] - nominal
        per_line[t.line_id] = {
            "mean_m": round(float(np.nanmean(dev)), 3),
            "max_abs_m": round(float(np.nanmax(np.abs(dev))), 3),
        }
    return {
        "nominal_m": nominal,
        "tolerance_m": tolerance_m,
        "per_line": per_line,
        "max_abs_deviation_m": max(v["max_abs_m"] for v in per_line.values()),
        "lines_over": sorted(k for k, v in per_line.items() if v["max_abs_m"] > tolerance_m),
    }


def line_spacing(
    tracks: list[Track], heading_deg: float, tolerance_fraction: float, bin_m: float = 50.0
) -> dict:
    """Spacing between neighbouring parallel lines, along the lines in ``bin_m`` bins.

    The nominal spacing is the median over the block; a pair of lines is flagged where the
    spacing departs from it by more than ``tolerance_fraction`` of the nominal.
    """
    h = np.radians(heading_deg)
    along_u, across_u = np.array([np.sin(h), np.cos(h)]), np.array([np.cos(h), -np.sin(h)])
    prof = []
    for t in tracks:
        a = t.east_m * along_u[0] + t.north_m * along_u[1]
        c = t.east_m * across_u[0] + t.north_m * across_u[1]
        prof.append((float(np.median(c)), t.line_id, a, c))
    prof.sort(key=lambda p: p[0])
    if len(prof) < 2:
        return {"nominal_m": None, "tolerance_fraction": tolerance_fraction, "pairs_over": []}
    gaps, worst = [], []
    for (_, ida, aa, ca), (_, idb, ab, cb) in zip(prof, prof[1:], strict=False):
        lo, hi = max(aa.min(), ab.min()), min(aa.max(), ab.max())
        if hi - lo < bin_m:
            continue
        edges = np.arange(lo, hi + bin_m, bin_m)
        ma = np.histogram(aa, edges, weights=ca)[0] / np.maximum(np.histogram(aa, edges)[0], 1)
        mb = np.histogram(ab, edges, weights=cb)[0] / np.maximum(np.histogram(ab, edges)[0], 1)
        ok = (np.histogram(aa, edges)[0] > 0) & (np.histogram(ab, edges)[0] > 0)
        gaps.append((ida, idb, (mb - ma)[ok]))
    if not gaps:
        return {"nominal_m": None, "tolerance_fraction": tolerance_fraction, "pairs_over": []}
    nominal = float(np.median(np.concatenate([g[2] for g in gaps])))
    over = []
    for ida, idb, g in gaps:
        dev = np.abs(g - nominal) / nominal
        worst.append(float(dev.max()))
        if dev.max() > tolerance_fraction:
            over.append(f"{ida}-{idb}")
    return {
        "nominal_m": nominal,
        "tolerance_fraction": tolerance_fraction,
        "max_deviation_fraction": max(worst),
        "pairs_over": over,
    }


def speed_excursions(
    tracks: list[Track], time_s: np.ndarray, tolerance_fraction: float, window_s: float = 5.0
) -> dict:
    """Ground speed on the lines (m/s, over ``window_s``) and spans off the median speed."""
    speeds, spans = [], []
    for t in tracks:
        tt = time_s[t.index]
        if tt.size < 3 or tt[-1] - tt[0] < 2 * window_s:
            continue
        grid = np.arange(tt[0], tt[-1] - window_s, window_s / 2)
        dist = np.interp(grid + window_s, tt, t.along_m) - np.interp(grid, tt, t.along_m)
        v = dist / window_s
        speeds.append((t.line_id, grid, v))
    if not speeds:
        return {"median_m_s": None, "tolerance_fraction": tolerance_fraction, "spans": []}
    med = float(np.median(np.concatenate([s[2] for s in speeds])))
    for lid, grid, v in speeds:
        bad = np.abs(v - med) > tolerance_fraction * med
        for k in np.flatnonzero(bad & ~np.r_[False, bad[:-1]]):
            end = k
            while end + 1 < bad.size and bad[end + 1]:
                end += 1
            spans.append(
                {
                    "line_id": lid,
                    "start_s": round(float(grid[k]), 2),
                    "end_s": round(float(grid[end] + window_s), 2),
                    "speed_m_s": round(float(v[k : end + 1].mean()), 3),
                }
            )
    return {
        "median_m_s": med,
        "tolerance_fraction": tolerance_fraction,
        "min_m_s": float(min(s[2].min() for s in speeds)),
        "max_m_s": float(max(s[2].max() for s in speeds)),
        "spans": spans,
    }


def diurnal_check(
    time_s: np.ndarray, base_nT: np.ndarray, chord_s: float, tolerance_nT: float
) -> dict:
    """Base-station diurnal against the customary chord test.

    Over every window of ``chord_s`` the reading may depart from the straight chord joining
    the window's ends by at most ``tolerance_nT``; the rate (nT/min) is reported too.
    """
    ok = np.isfinite(base_nT)
    t, b = time_s[ok], base_nT[ok]
    if t.size < 2 or t[-1] - t[0] < chord_s:
        return {
            "available": bool(t.size),
            "chord_s": chord_s,
            "tolerance_nT": tolerance_nT,
            "spans_over": [],
        }
    step = chord_s / 4
    grid = np.arange(t[0], t[-1] + 1e-9, min(step, 10.0))
    bg = np.interp(grid, t, b)
    n = max(int(round(chord_s / (grid[1] - grid[0]))), 2)
    worst, spans = 0.0, []
    for k in range(0, grid.size - n, max(n // 4, 1)):
        seg = bg[k : k + n + 1]
        chord = np.linspace(seg[0], seg[-1], seg.size)
        dev = float(np.max(np.abs(seg - chord)))
        worst = max(worst, dev)
        if dev > tolerance_nT:
            spans.append(
                {
                    "start_s": round(float(grid[k]), 1),
                    "end_s": round(float(grid[k + n]), 1),
                    "deviation_nT": round(dev, 3),
                }
            )
    m = max(int(round(60.0 / (grid[1] - grid[0]))), 1)  # rate over one minute: noise-robust
    rate = np.abs(bg[m:] - bg[:-m]) / (grid[m] - grid[0]) * 60.0 if grid.size > m else [0.0]
    return {
        "available": True,
        "chord_s": chord_s,
        "tolerance_nT": tolerance_nT,
        "max_chord_deviation_nT": worst,
        "max_rate_nT_per_min": float(np.max(rate)),
        "range_nT": float(b.max() - b.min()),
        "spans_over": spans,
    }
