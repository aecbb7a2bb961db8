"""Synthetic maps and tracks for tests and benchmarks (not the flight simulator's own map).

Two map families: a smooth Gaussian random field (white noise low-passed by a Gaussian kernel,
a stand-in for shallow geology at a chosen correlation length), and the total-field anomaly of
buried dipoles computed by harmonica (a physical field, smooth by construction).
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter

from pipeline.maps.grid import Grid


def random_field_map(
    seed: int,
    size_m: float = 20_000.0,
    cell_m: float = 50.0,
    correlation_m: float = 300.0,
    rms_nT: float = 50.0,
    origin_m: tuple[float, float] = (-10_000.0, -10_000.0),
) -> Grid:
    """A smooth random anomaly grid (nT) on a square of ``size_m``, local metres."""
    rng = np.random.default_rng(seed)
    n = int(size_m / cell_m) + 1
    v = gaussian_filter(rng.standard_normal((n, n)), correlation_m / cell_m, mode="wrap")
    v *= rms_nT / v.std()
    return Grid(v, origin_m[0], origin_m[1], cell_m)


def dipole_map(
    seed: int,
    size_m: float = 6_000.0,
    cell_m: float = 25.0,
    count: int = 60,
    depth_m: tuple[float, float] = (150.0, 600.0),
    height_m: float = 0.0,
    inclination_deg: float = 55.0,
    declination_deg: float = -3.0,
) -> Grid:
    """Total-field anomaly (nT) of ``count`` random induced dipoles below the surface, at
    ``height_m`` above it, computed with harmonica (projected on the main field direction)."""
    import harmonica as hm

    rng = np.random.default_rng(seed)
    half = size_m / 2
    x = np.arange(-half, half + cell_m / 2, cell_m)
    e, n = np.meshgrid(x, x)
    src = (
        rng.uniform(-half, half, count),
        rng.uniform(-half, half, count),
        -rng.uniform(*depth_m, count),
    )
    inc, dec = np.radians(inclination_deg), np.radians(declination_deg)
    # unit main-field direction (east, north, up)
    u = np.array([np.cos(inc) * np.sin(dec), np.cos(inc) * np.cos(dec), -np.sin(inc)])
    moments = rng.uniform(0.5e9, 3e9, count)[:, None] * u[None, :]  # A m^2, induced
    be, bn, bu = hm.dipole_magnetic((e, n, np.full_like(e, height_m)), src, moments.T, field="b")
    total = be * u[0] + bn * u[1] + bu * u[2]
    return Grid(total, float(x[0]), float(x[0]), cell_m)


def racetrack(
    duration_s: float,
    rate_hz: float = 10.0,
    speed_mps: float = 60.0,
    leg_m: float = 6_000.0,
    turn_radius_m: float = 1_000.0,
    center_m: tuple[float, float] = (0.0, 0.0),
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A closed racetrack (two north-south legs joined by half circles), flown repeatedly.

    Returns time (s), east (m), north (m).
    """
    t = np.arange(0.0, duration_s, 1.0 / rate_hz)
    arc = np.pi * turn_radius_m
    lap = 2 * leg_m + 2 * arc
    s = np.mod(speed_mps * t, lap)
    e = np.empty_like(s)
    n = np.empty_like(s)
    r, h = turn_radius_m, leg_m / 2
    a = s < leg_m  # up the east leg
    e[a], n[a] = r, -h + s[a]
    b = (s >= leg_m) & (s < leg_m + arc)  # top turn, east -> west
    th = (s[b] - leg_m) / r
    e[b], n[b] = r * np.cos(th), h + r * np.sin(th)
    c = (s >= leg_m + arc) & (s < 2 * leg_m + arc)  # down the west leg
    e[c], n[c] = -r, h - (s[c] - leg_m - arc)
    d = s >= 2 * leg_m + arc  # bottom turn, west -> east
    th = (s[d] - 2 * leg_m - arc) / r
    e[d], n[d] = -r * np.cos(th), -h - r * np.sin(th)
    return t, e + center_m[0], n + center_m[1]
