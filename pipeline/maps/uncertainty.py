"""The map's own error, 1 sigma per cell (nT): what a user of the grid, or a navigation filter
reading it, should assume the cell's value is off from the true field at the flight surface.

Three parts, added in quadrature:

* **interpolation**: a cell between flight lines is a guess from the lines beside it, and the
  guess worsens with the distance ``d`` to the nearest line in a way that depends on how
  smooth the field is (a smooth field's error grows as ``d^2``, a rough one's as ``d^0.5``).
  That shape is measured on the data where sampling is dense, along the lines: each line is
  thinned to knots one line spacing apart, interpolated between them by a cubic spline (the
  1-D minimum-curvature interpolant), and the squared error is binned by the distance to the
  nearest knot. The size is then set by **held-out lines** (every n-th interior survey line
  left out of the grid and predicted by the map's own gridder, its level removed: levelling
  has its own term), compared with the same along-line measurement at the held-out lines' gap
  (two spacings). Isotropy is assumed: the field varies across the lines as it does along
  them, which any interpolation between lines must assume.
* **levelling**: the crossover differences left after levelling, over sqrt(2) (each holds two
  lines' level errors).
* **noise**: the sensor's white noise, which the grid carries on the lines themselves.

No library gives a cross-validated interpolation error for line data (verde's and harmonica's
cross-validation return a score, not an error model), hence this module. Coordinates are the
grid's metric frame (east, north in m).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.spatial import cKDTree

from pipeline.maps.grid import Grid
from pipeline.maps.gridders import LineData, line_folds

N_DISTANCE_BINS = 8


@dataclass
class MapUncertainty:
    """The fitted error model of one grid.

    Attributes
    ----------
    distance_m, shape_nT2
        Along-line interpolation error between knots one line spacing apart: distance to the
        nearest knot (m, bin centres from 0 to half a spacing) and mean squared error (nT^2,
        the sensor's noise removed).
    scale
        Held-out squared error over the along-line one at the held-out lines' gap.
    level_nT, noise_nT
        Levelling and sensor-noise terms (nT, 1 sigma).
    heldout_rms_nT
        RMS error at the held-out lines (their level removed), nT.
    spacing_m
        Line spacing, m.
    """

    distance_m: np.ndarray
    shape_nT2: np.ndarray
    scale: float
    level_nT: float
    noise_nT: float
    heldout_rms_nT: float
    spacing_m: float

    def interpolation_nT(self, distance_m: np.ndarray) -> np.ndarray:
        """Interpolation error (nT, 1 sigma) at ``distance_m`` from the nearest line; beyond
        half a spacing (outside the block) the largest value holds."""
        e2 = np.interp(np.asarray(distance_m, float), self.distance_m, self.shape_nT2)
        return np.sqrt(np.maximum(self.scale * e2, 0.0))

    def sigma_nT(self, distance_m: np.ndarray) -> np.ndarray:
        """Total 1-sigma error (nT) at ``distance_m`` from the nearest measurement."""
        i = self.interpolation_nT(distance_m)
        return np.sqrt(i**2 + self.level_nT**2 + self.noise_nT**2)

    def describe(self) -> dict[str, float]:
        """JSON-ready figures of the model."""
        return {
            "heldout_rms_nT": self.heldout_rms_nT,
            "scale": self.scale,
            "level_nT": self.level_nT,
            "noise_nT": self.noise_nT,
            "midway_interpolation_nT": float(self.interpolation_nT(self.spacing_m / 2)),
        }


def along_line_interpolation_error(
    data: LineData, gap_m: float, n_bins: int = N_DISTANCE_BINS
) -> tuple[np.ndarray, np.ndarray]:
    """Squared error of cubic-spline interpolation along the lines between knots ``gap_m``
    apart, binned by the distance to the nearest knot.

    Every line is thinned to knots ``gap_m`` apart (at several starting offsets, so every
    sample is predicted), and the samples between the knots are predicted from them.

    Returns
    -------
    distance_m : ndarray
        Bin centres, 0 .. ``gap_m / 2`` (m), the first being 0 (error 0 at a knot).
    error_nT2 : ndarray
        Mean squared error per bin (nT^2); NaN in a bin without samples.
    """
    edges = np.linspace(0.0, gap_m / 2.0, n_bins + 1)
    sums, counts = np.zeros(n_bins), np.zeros(n_bins)
    for name in np.unique(data.line):
        sel = data.line == name
        e, n, v = data.east_m[sel], data.north_m[sel], data.value_nT[sel]
        ok = np.isfinite(v)
        e, n, v = e[ok], n[ok], v[ok]
        s = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(e), np.diff(n)))])
        if v.size < 10 or s[-1] < 4 * gap_m:
            continue
        step = float(np.median(np.diff(s)))
        if step <= 0:
            continue
        for off in np.arange(0.0, gap_m, max(step, gap_m / 8.0)):
            knots_at = np.arange(s[0] + off, s[-1], gap_m)
            k = np.unique(np.searchsorted(s, knots_at).clip(0, s.size - 1))
            if k.size < 4 or np.any(np.diff(s[k]) <= 0):
                continue
            pred = CubicSpline(s[k], v[k], bc_type="natural")(s)
            inner = (s > s[k[0]]) & (s < s[k[-1]])
            d = np.abs(s - s[k][np.clip(np.searchsorted(s[k], s) - 1, 0, k.size - 1)])
            d = np.minimum(d, np.abs(s[k][np.clip(np.searchsorted(s[k], s), 0, k.size - 1)] - s))
            b = np.clip((d / edges[-1] * n_bins).astype(int), 0, n_bins - 1)
            np.add.at(sums, b[inner], (v - pred)[inner] ** 2)
            np.add.at(counts, b[inner], 1.0)
    centre = 0.5 * (edges[1:] + edges[:-1])
    with np.errstate(invalid="ignore", divide="ignore"):
        err = sums / counts
    return np.concatenate([[0.0], centre]), np.concatenate([[0.0], err])


def _shape(data: LineData, gap_m: float, noise_nT: float) -> tuple[np.ndarray, np.ndarray]:
    d, e2 = along_line_interpolation_error(data, gap_m)
    have = np.isfinite(e2)
    if have.sum() < 2:
        raise ValueError("map uncertainty: the lines are too short to measure interpolation")
    # a predicted sample carries its own white noise; the interpolation's share is the rest
    e2 = np.maximum(e2[have] - noise_nT**2, 0.0)
    e2[0] = 0.0
    return d[have], np.maximum.accumulate(e2)


def fit_uncertainty(
    data: LineData,
    make_gridder: Callable[[], object],
    spacing_m: float,
    noise_nT: float,
    level_nT: float,
    n_folds: int = 5,
) -> MapUncertainty:
    """Fit the map's error model (:class:`MapUncertainty`) to levelled line data.

    Parameters
    ----------
    data : LineData
        Levelled samples (m, nT) with their line labels and kinds.
    make_gridder : callable
        Returns an unfitted gridder with ``fit(LineData)`` and ``predict(east_m, north_m,
        up_m)``: the map stage's own, so held-out errors are its errors.
    spacing_m : float
        Survey line spacing, m.
    noise_nT, level_nT : float
        The sensor's white noise and the levelling error (nT, 1 sigma).
    n_folds : int
        Held-out folds of interior survey lines (:func:`pipeline.maps.gridders.line_folds`).

    Raises
    ------
    ValueError
        Fewer than three survey lines (nothing can be held out), or lines too short.
    """
    folds = line_folds(data, n_folds)
    if not folds:
        raise ValueError("map uncertainty needs at least three survey lines")
    d1, shape1 = _shape(data, spacing_m, noise_nT)
    d2, shape2 = _shape(data, 2.0 * spacing_m, noise_nT)
    err2, ref2 = [], []
    for held in folds:
        g = make_gridder().fit(data.subset(~held))
        pred = g.predict(data.east_m[held], data.north_m[held], data.up_m[held])
        tree = cKDTree(np.column_stack([data.east_m[~held], data.north_m[~held]]))
        d, _ = tree.query(np.column_stack([data.east_m[held], data.north_m[held]]))
        r = data.value_nT[held] - pred
        lab = data.line[held]
        for name in np.unique(lab):
            m = (lab == name) & np.isfinite(r)
            if m.sum() < 3:
                continue
            rr = r[m] - np.median(r[m])  # the line's level is levelling's error, not this
            err2.append(rr**2)
            ref2.append(np.interp(d[m], d2, shape2))
    if not err2:
        raise ValueError("map uncertainty: no held-out line could be predicted")
    e2, r2 = np.concatenate(err2), np.concatenate(ref2)
    # held-out samples carry their own white noise as well
    signal = max(float(np.mean(e2)) - noise_nT**2, 0.0)
    scale = signal / float(np.mean(r2)) if np.mean(r2) > 0 else 0.0
    return MapUncertainty(
        d1,
        shape1,
        scale,
        float(level_nT),
        float(noise_nT),
        float(np.sqrt(np.mean(e2))),
        float(spacing_m),
    )


def uncertainty_grid(model: MapUncertainty, grid: Grid, data: LineData) -> Grid:
    """The model's 1-sigma error (nT) on every cell of ``grid`` that holds a value, from each
    cell's distance to the nearest sample."""
    gx, gy = np.meshgrid(*grid.coordinates())
    tree = cKDTree(np.column_stack([data.east_m, data.north_m]))
    d, _ = tree.query(np.column_stack([gx.ravel(), gy.ravel()]))
    sigma = model.sigma_nT(d).reshape(gx.shape)
    sigma[~np.isfinite(grid.values)] = np.nan
    return grid.with_values(sigma)
