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

import numpy as np
from scipy.interpolate import RegularGridInterpolator

from pipeline.maps.grid import Grid
from pipeline.navigation.crlb import crlb
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


def line_window_s(grid: Grid, speed_mps: float) -> float:
    """The line's duration (s): the time to fly half the shorter side of the map's covered
    area (its finite cells' bounding box, centre to centre) at ``speed_mps``, within
    [``MIN_WINDOW_S``, ``MAX_WINDOW_S``].

    Half the shorter side is the longest line that ends at the map's centre from any heading
    and stays on the map: a cell's value then measures the map around it, not the updates a
    longer line would miss off the map (on a survey a few kilometres across, a fixed 120 s
    line at survey speed starts off the map for most cells and every cell reads as if the
    vehicle had just arrived). Cells nearer an edge still read worse on the headings coming
    from that edge, as a vehicle arriving from there would.
    """
    ok = np.isfinite(grid.values)
    if not ok.any():
        return MIN_WINDOW_S
    rows, cols = np.flatnonzero(ok.any(axis=1)), np.flatnonzero(ok.any(axis=0))
    side_m = grid.cell_m * min(rows[-1] - rows[0], cols[-1] - cols[0])  # centre to centre
    return float(np.clip(0.5 * side_m / speed_mps, MIN_WINDOW_S, MAX_WINDOW_S))


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
        ``window_s`` None: :func:`line_window_s`.
    """
    s = settings or NavigabilitySettings()
    window_s = s.window_s if s.window_s is not None else line_window_s(grid, s.speed_mps)
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
    var = np.zeros((iy.size, ix.size))
    for heading in s.headings_deg:
        north, east, phi, qd, p0 = _line(s, heading, window_s)
        for a, j in enumerate(iy):
            for b, i in enumerate(ix):
                bound = crlb(phi, qd, p0, ce[i] + east, cn[j] + north, meas, sensor_nT**2)
                var[a, b] += np.trace(bound[-1])
    coarse = np.sqrt(var / len(s.headings_deg))
    itp = RegularGridInterpolator((cn[iy], ce[ix]), np.log(coarse))
    gy, gx = np.meshgrid(cn, ce, indexing="ij")
    values = np.exp(itp((gy, gx)))  # log: the bound spans decades between rich and flat areas
    values[~np.isfinite(grid.values)] = np.nan
    return grid.with_values(values)
