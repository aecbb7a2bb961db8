"""Navigability of a map: the position accuracy a vehicle can reach flying into each cell.

For a cell, a vehicle flies a straight line at ``speed_mps`` that ends at the cell's centre,
``window_s`` long (sized to the map: :func:`line_window_s`), with an INS whose position is
known to ``start_sigma_m`` when it starts (a navigator that has been dead-reckoning, not one
fresh from GNSS); the value is the posterior CRLB's DRMS (m) at the cell, from the map's
gradients along that line, the map's own error (its 1-sigma grid or one value, with the
correlation inflation ``aeromag navigate`` uses) and the sensor's noise. With several
headings the value is the DRMS over them (the square root of the mean of the bound's trace).
Lines leaving the map lose the updates off it, so cells near the edge read worse, as a
vehicle there would.

The INS model, the CRLB recursion and the measurement are those of ``aeromag navigate``
(:mod:`pipeline.navigation.crlb`); the transition matrices depend on the line's shape only, so
they are computed once per heading and every cell reuses them. Headings are from the map's
grid north (the meridian convergence, a few degrees, is ignored here).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.interpolate import RegularGridInterpolator

from pipeline.maps.grid import Grid
from pipeline.navigation.crlb import crlb_final
from pipeline.navigation.ekf import MeasurementModel, correlated_error_scale
from pipeline.navigation.ins import GRADES, InsErrorModel, Trajectory
from pipeline.navigation.map_model import MapModel


@dataclass
class NavigabilitySettings:
    """Speed (m/s), headings (deg from grid north), the line's duration (s) and sampling
    (Hz), the INS position sigma at its start (m), the INS grade, the stride (cells) of the
    cells computed (the others interpolated), the latitude (deg) and the map error's
    correlation length (m)."""

    speed_mps: float = 60.0
    headings_deg: tuple[float, ...] = (0.0, 45.0, 90.0, 135.0)
    window_s: float | None = None  # None: sized to the map (line_window_s)
    rate_hz: float = 1.0
    start_sigma_m: float = 500.0
    grade: str = "navigation"
    stride_cells: int = 4
    lat_deg: float = 45.0
    map_error_length_m: float = 200.0


# bounds of the line's duration, s: past MAX_WINDOW_S the bound of a navigation-grade INS over
# a map with gradients is at its steady state (a longer line changes it little and costs
# time); under MIN_WINDOW_S (20 updates at 1 Hz) the start sigma, not the map, would set it
MAX_WINDOW_S, MIN_WINDOW_S = 120.0, 20.0


def line_window_s(grid: Grid, speed_mps: float, heading_deg: float | None = None) -> float:
    """The line's duration (s): the time to fly, at ``speed_mps``, from the centre of the
    map's covered area (its finite cells' bounding box, centre to centre) to its edge along
    ``heading_deg`` (from grid north; None: half the box's shorter side, the shortest of
    these), within [``MIN_WINDOW_S``, ``MAX_WINDOW_S``].

    That is the longest line on that heading that ends at the map's centre and stays on the
    map: a cell's value then measures the map around it, not the updates a longer line would
    miss off the map (on a survey a few kilometres across, a fixed 120 s line at survey speed
    starts off the map for most cells, and its INS drifts there with nothing to correct it).
    Along the long axis of an elongated block the line is longer than across it. Cells nearer
    an edge still read worse on the headings coming from that edge, as a vehicle arriving
    from there would.
    """
    ok = np.isfinite(grid.values)
    if not ok.any():
        return MIN_WINDOW_S
    rows, cols = np.flatnonzero(ok.any(axis=1)), np.flatnonzero(ok.any(axis=0))
    half_n = 0.5 * grid.cell_m * (rows[-1] - rows[0])  # centre to centre
    half_e = 0.5 * grid.cell_m * (cols[-1] - cols[0])
    if heading_deg is None:
        reach_m = min(half_n, half_e)
    else:
        h = np.radians(heading_deg)
        c, s = abs(np.cos(h)), abs(np.sin(h))
        reach_m = min(half_n / c if c > 1e-9 else np.inf, half_e / s if s > 1e-9 else np.inf)
    return float(np.clip(reach_m / speed_mps, MIN_WINDOW_S, MAX_WINDOW_S))


def _line(s: NavigabilitySettings, heading_deg: float, window_s: float):
    """A straight line ending at (0, 0): time (s), north, east offsets (m), transitions and
    process noise of the INS along it."""
    t = np.arange(0.0, window_s + 1e-9, 1.0 / s.rate_hz)
    along = s.speed_mps * (t - t[-1])
    h = np.radians(heading_deg)
    north, east = along * np.cos(h), along * np.sin(h)
    traj = Trajectory.from_track(t, north, east, np.zeros_like(t), np.full(t.size, s.lat_deg))
    model = InsErrorModel(GRADES[s.grade])
    phi = model.transitions(traj)
    qd = model.process_noise(np.diff(t, prepend=t[0]))
    return north, east, phi, qd, model.initial_covariance(s.start_sigma_m)


def line_s(grid: Grid, s: NavigabilitySettings, heading_deg: float) -> float:
    """The line's duration on a heading (s): ``s.window_s``, else :func:`line_window_s`."""
    return s.window_s if s.window_s is not None else line_window_s(grid, s.speed_mps, heading_deg)


def navigability(
    grid: Grid,
    sensor_nT: float,
    sigma: Grid | float,
    settings: NavigabilitySettings | None = None,
) -> Grid:
    """The navigability map (m, DRMS of the position CRLB at each cell; NaN where the map is).

    Parameters
    ----------
    grid : Grid
        The anomaly map, nT, east/north metres.
    sensor_nT : float
        The magnetometer's white noise, nT (1 sigma).
    sigma : Grid or float
        The map's 1-sigma error, nT: a grid on the map's cells (``/map/uncertainty``) or one
        value.
    settings : NavigabilitySettings, optional
        ``window_s`` None: :func:`line_window_s` on each heading.
    """
    s = settings or NavigabilitySettings()
    mm = MapModel(grid)
    scale = correlated_error_scale(s.map_error_length_m, s.speed_mps / s.rate_hz)
    if isinstance(sigma, Grid):
        meas = MeasurementModel(mm, sigma=MapModel(sigma, method="linear"), map_var_scale=scale)
    else:
        meas = MeasurementModel(mm, map_sigma_nT=float(sigma), map_var_scale=scale)
    ce, cn = grid.coordinates()
    iy = np.arange(0, grid.shape[0], s.stride_cells)
    ix = np.arange(0, grid.shape[1], s.stride_cells)
    if iy[-1] != grid.shape[0] - 1:
        iy = np.append(iy, grid.shape[0] - 1)
    if ix[-1] != grid.shape[1] - 1:
        ix = np.append(ix, grid.shape[1] - 1)
    var = np.zeros(iy.size * ix.size)
    cy, cx = (a.ravel() for a in np.meshgrid(cn[iy], ce[ix], indexing="ij"))
    for heading in s.headings_deg:
        north, east, phi, qd, p0 = _line(s, heading, line_s(grid, s, heading))
        e, n = cx[:, None] + east[None, :], cy[:, None] + north[None, :]
        bound = crlb_final(phi, qd, p0, e, n, meas, sensor_nT**2)  # every cell at once
        var += np.trace(bound, axis1=1, axis2=2)
    var = var.reshape(iy.size, ix.size)
    coarse = np.sqrt(var / len(s.headings_deg))
    itp = RegularGridInterpolator((cn[iy], ce[ix]), np.log(coarse))
    gy, gx = np.meshgrid(cn, ce, indexing="ij")
    values = np.exp(itp((gy, gx)))  # log: the bound spans decades between rich and flat areas
    values[~np.isfinite(grid.values)] = np.nan
    return grid.with_values(values)


def track_speed_mps(flight, geomap) -> float:
    """The median ground speed (m/s) of a flight's track in a map's frame, over the epochs
    that move (> 1 m/s); NaN when none does."""
    d = flight.data
    lat, lon = d["lat_deg"].to_numpy(float), d["lon_deg"].to_numpy(float)
    ok = np.isfinite(lat) & np.isfinite(lon)
    e, n = (np.asarray(v, float) for v in geomap.to_local(lat[ok], lon[ok]))
    t = d["time_s"].to_numpy(float)[ok]
    v = np.hypot(np.diff(e), np.diff(n)) / np.maximum(np.diff(t), 1e-9)
    return float(np.median(v[v > 1.0])) if (v > 1.0).any() else float("nan")


def navigability_map(
    flight,
    geomap,
    sensor_nT: float,
    nav,
    speed_mps: float,
    headings: tuple[float, ...] = (0.0, 45.0, 90.0, 135.0),
) -> tuple[Any, dict[str, Any]]:
    """The navigability grid of ``geomap`` (m; :func:`navigability`) and its summary
    (``aeromag navigability``'s JSON, the post-flight summary's ``navigability``).

    The map's error is its ``sigma`` grid, else ``nav.default_map_sigma_nT``; its correlation
    length ``geomap.error_length_m``, else ``nav.map_error_length_m``; the latitude the
    track's median.
    """
    lat = flight.data["lat_deg"].to_numpy(float)
    sigma = geomap.sigma if geomap.sigma is not None else nav.default_map_sigma_nT
    s = NavigabilitySettings(
        speed_mps=float(speed_mps),
        headings_deg=tuple(headings),
        lat_deg=float(np.nanmedian(lat)),
        map_error_length_m=geomap.error_length_m or nav.map_error_length_m,
    )
    grid = navigability(geomap.grid, float(sensor_nT), sigma, s)
    v = grid.values[np.isfinite(grid.values)]
    return grid, {
        "channel": "/map/navigability",
        "speed_mps": float(speed_mps),
        "headings_deg": list(headings),
        "line_s": [line_s(geomap.grid, s, h) for h in headings],
        "start_sigma_m": s.start_sigma_m,
        "sensor_sigma_nT": float(sensor_nT),
        "map_sigma": "grid" if geomap.sigma is not None else nav.default_map_sigma_nT,
        "drms_m": {
            "median": float(np.median(v)),
            "p10": float(np.percentile(v, 10)),
            "p90": float(np.percentile(v, 90)),
        },
    }
