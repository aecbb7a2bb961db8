"""The simulator's truth sampled where a product puts its values (tests and benchmarks)."""

from __future__ import annotations

import numpy as np
from scipy.interpolate import RegularGridInterpolator

from pipeline.geo.local import LocalFrame
from pipeline.geo.projected import GridFrame
from pipeline.maps.grid import Grid
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
    s = sim.scenario["survey"]
    inside = (
        (e > s["east_m"] + 25)
        & (e < s["east_m"] + s["width_m"] - 25)
        & (n > s["north_m"] + 25)
        & (n < s["north_m"] + s["length_m"] - 25)
    )
    out[~inside] = np.nan  # score the block the lines cover
    return out
