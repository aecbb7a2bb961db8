"""The simulator's truth sampled where a product puts its values (tests and benchmarks)."""

from __future__ import annotations

import numpy as np
from scipy.interpolate import RegularGridInterpolator

from pipeline.geo.local import LocalFrame
from pipeline.geo.projected import GridFrame
from pipeline.maps.grid import Grid
from pipeline.physics.dipoles import DipoleSource, dipole_field_ned_nT, total_field_anomaly_nT
from pipeline.simulate.simulator import SimulatedFlight


def truth_on(sim: SimulatedFlight, grid: Grid, frame: GridFrame) -> np.ndarray:
    """The simulator's true anomaly (nT) at the centres of a map's grid cells.

    Parameters
    ----------
    sim : SimulatedFlight
        The simulation (its ``truth["anomaly"]["grid"]`` on the site's local frame).
    grid : Grid
        The map's grid, on ``frame`` (east/north m).
    frame : GridFrame
        The map's frame (its projected CRS).

    Returns
    -------
    ndarray
        Grid-shaped, NaN outside the surveyed block less 25 m (the block the lines cover).
    """
    tg = sim.truth["anomaly"]["grid"]
    site = sim.truth["site"]
    tv = np.array(tg["values_nT"])
    gx, gy = np.meshgrid(*grid.coordinates())
    lat, lon, _ = frame.to_geodetic(gx, gy)
    e, n, _ = LocalFrame(site["latitude_deg"], site["longitude_deg"]).to_enu(lat, lon)
    ri = RegularGridInterpolator(
        (
            tg["north0_m"] + tg["cell_m"] * np.arange(tv.shape[0]),
            tg["east0_m"] + tg["cell_m"] * np.arange(tv.shape[1]),
        ),
        tv,
        bounds_error=False,
    )
    out = ri(np.stack([n, e], -1))
    out[~_inside_block(sim, e, n)] = np.nan  # score the block the lines cover
    return out


def _inside_block(sim: SimulatedFlight, east_m: np.ndarray, north_m: np.ndarray) -> np.ndarray:
    """Which local positions (m) lie inside the surveyed block less 25 m: where the map is
    the lines' data, not the gridder's extrapolation beyond them."""
    s = sim.scenario["survey"]
    return (
        (east_m > s["east_m"] + 25)
        & (east_m < s["east_m"] + s["width_m"] - 25)
        & (north_m > s["north_m"] + 25)
        & (north_m < s["north_m"] + s["length_m"] - 25)
    )


def true_anomaly_grid(
    sim: SimulatedFlight, grid: Grid, frame: GridFrame
) -> tuple[Grid, dict[str, object]]:
    """The simulator's true anomaly on every cell of ``grid``: the exact total-field anomaly of
    its dipoles at the survey height (as its truth grid, which covers the survey block only),
    with the map's datum (offset, east/north plane and gain least-squares fitted to ``grid``
    inside the surveyed block), masked as ``grid``."""
    a = sim.truth["anomaly"]
    site = sim.truth["site"]
    dipoles = [
        DipoleSource(d["east_m"], d["north_m"], d["up_m"], tuple(d["moment_ned_A_m2"]))
        for d in a["dipoles"]
    ]
    gx, gy = np.meshgrid(*grid.coordinates())
    lat, lon, _ = frame.to_geodetic(gx, gy)
    e, n, _ = LocalFrame(site["latitude_deg"], site["longitude_deg"]).to_enu(lat, lon)
    up = np.full(e.size, float(a["grid"]["height_agl_m"]))
    crust = dipole_field_ned_nT(dipoles, e.ravel(), n.ravel(), up)
    b0 = np.asarray(sim.truth["main_field"]["ned_nT"], float)
    t = total_field_anomaly_nT(crust, np.broadcast_to(b0, crust.shape)).reshape(gx.shape)
    # the datum is fitted where the map is data (as tests/test_maps.py scores)
    ok = np.isfinite(grid.values) & _inside_block(sim, e, n)
    x = np.column_stack([np.ones(ok.sum()), gx[ok], gy[ok], t[ok]])
    coef, *_ = np.linalg.lstsq(x, grid.values[ok], rcond=None)
    out = coef[0] + coef[1] * gx + coef[2] * gy + coef[3] * t
    out[~np.isfinite(grid.values)] = np.nan
    return Grid(out, grid.east0_m, grid.north0_m, grid.cell_m), {
        "gain": float(coef[3]),
        "block": ok,
    }
