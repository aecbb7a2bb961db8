"""A gridded line survey over point-dipole geology, with its truth: the map filter's test bed.

The field is the exact total-field anomaly of randomly placed induced/remanent point dipoles
(:mod:`pipeline.physics.dipoles`), not an ARIMA process, so a filter built on an ARIMA model is
judged on physics it does not assume. Noise: white sensor noise, a random offset and linear
drift per line (corrugation), and cross-track position jitter. Units: m, nT.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.maps.grid import Grid, minimum_curvature
from pipeline.physics.dipoles import DipoleSource, dipole_field_ned_nT, total_field_anomaly_nT

MAIN_FIELD_NED_NT = np.array([20_000.0, 0.0, 45_000.0])  # inclination ~66 deg


@dataclass
class MapSurvey:
    """A simulated gridded line survey with its truth (:func:`line_survey`).

    Attributes
    ----------
    grid : Grid
        Minimum-curvature grid of the noisy lines (local east/north m, nT).
    truth_nT : ndarray
        The anomaly at the cell centres (nT), NaN outside the surveyed block.
    sensor_nT, line_nT : float
        White noise per sample and the per-line offset/drift standard deviation, nT.
    spacing_m : float
        Line spacing, m.
    """

    grid: Grid
    truth_nT: np.ndarray  # the anomaly at the cell centres, NaN outside the surveyed block
    sensor_nT: float
    line_nT: float
    spacing_m: float


def line_survey(
    seed: int,
    sensor_nT: float = 0.05,
    line_nT: float = 0.0,
    spacing_m: float = 50.0,
    width_m: float = 500.0,
    length_m: float = 700.0,
    height_m: float = 60.0,
    step_m: float = 0.7,
    jitter_m: float = 1.0,
    sources: int = 12,
    depth_m: tuple[float, float] = (80.0, 300.0),
    moment_A_m2: tuple[float, float] = (1e5, 1.5e6),
) -> MapSurvey:
    """North-south lines ``spacing_m`` apart over a ``width_m`` x ``length_m`` block, sampled
    every ``step_m`` at ``height_m`` above the datum, gridded by minimum curvature at a
    quarter of the spacing (masked beyond one spacing), as the map stage does.

    Parameters
    ----------
    sensor_nT
        White noise per sample (nT).
    line_nT
        Standard deviation of each line's offset and of its end-to-end linear drift (nT).
    depth_m, moment_A_m2
        Ranges of the sources' depths below the datum (m) and moment magnitudes (A m^2).
    """
    rng = np.random.default_rng(seed)
    src = [
        DipoleSource(
            rng.uniform(-150, width_m + 150),
            rng.uniform(-150, length_m + 150),
            -rng.uniform(*depth_m),
            tuple(rng.normal(0, 1, 3) / np.sqrt(3) * rng.uniform(*moment_A_m2)),
        )
        for _ in range(sources)
    ]

    def field(e, n):
        e, n = np.ravel(e), np.ravel(n)
        return total_field_anomaly_nT(
            dipole_field_ned_nT(src, e, n, np.full(e.size, height_m)), MAIN_FIELD_NED_NT
        )

    es, ns, vs = [], [], []
    for e0 in np.arange(0.0, width_m + 1e-6, spacing_m):
        n = np.arange(0.0, length_m, step_m)
        e = e0 + rng.normal(0, jitter_m, n.size)
        frac = n / length_m - 0.5
        v = (
            field(e, n)
            + rng.normal(0, sensor_nT, n.size)
            + rng.normal(0, line_nT)
            + rng.normal(0, line_nT) * frac
        )
        es.append(e), ns.append(n), vs.append(v)
    g = minimum_curvature(
        np.concatenate(es),
        np.concatenate(ns),
        np.concatenate(vs),
        spacing_m / 4.0,
        mask_distance_m=spacing_m,
    )
    gx, gy = np.meshgrid(*g.coordinates())
    truth = field(gx, gy).reshape(g.shape)
    inside = (gx >= 0) & (gx <= width_m) & (gy >= 0) & (gy <= length_m) & np.isfinite(g.values)
    truth[~inside] = np.nan
    return MapSurvey(g, truth, sensor_nT, line_nT, spacing_m)
