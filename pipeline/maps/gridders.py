"""Gridders for levelled line data, and the choice between them by cross-validation.

Two estimators with ``fit`` / ``predict`` (verde's shape):

* :class:`MinimumCurvatureGridder`: the sparse minimum-curvature grid of
  :mod:`pipeline.maps.grid` (interpolates on the flight surface; no continuation);
* :class:`EquivalentSourceGridder`: harmonica's equivalent sources (point sources a fixed
  depth below the data, damped least squares; gradient-boosted for large surveys). A harmonic
  field, so it predicts at any height: a map at a constant height, or draped at a constant
  clearance over a digital elevation model, from data flown at another surface.

:func:`choose_gridder` scores the candidates (minimum curvature and equivalent sources over a
small grid of depths and dampings) by *line-held-out* cross-validation: every k-th interior
survey line is left out in turn (ties and the outermost lines always kept), the gridder is
fitted on the rest and scored at the
left-out line's samples. Holding out whole lines scores the interpolation between lines, which
is what a map asks of a gridder (holding out random samples only tests along-line
interpolation, which every gridder does well).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pipeline.maps.grid import Grid, minimum_curvature

GRIDDERS = ("minimum_curvature", "equivalent_sources", "auto")
# above this many block means the dense equivalent-source Jacobian (n x n floats) is too
# large; the gradient-boosted version fits overlapping windows instead (Soler & Uieda 2021)
DENSE_LIMIT = 6000


@dataclass
class LineData:
    """Levelled samples in the map's local frame: east/north/up in m, value in nT; ``line``
    a label per sample and ``kind`` (``survey`` | ``tie``) per sample."""

    east_m: np.ndarray
    north_m: np.ndarray
    up_m: np.ndarray
    value_nT: np.ndarray
    line: np.ndarray
    kind: np.ndarray

    def subset(self, keep: np.ndarray) -> LineData:
        """The samples selected by ``keep`` (boolean mask or indices)."""
        return LineData(*(getattr(self, f)[keep] for f in self.__dataclass_fields__))


class MinimumCurvatureGridder:
    """Minimum curvature on the flight surface (see :func:`pipeline.maps.grid.minimum_curvature`).

    Parameters
    ----------
    cell_m : float
        Cell size, m.
    mask_distance_m : float, optional
        Cells farther than this from data are masked.
    """

    name = "minimum_curvature"

    def __init__(self, cell_m: float, mask_distance_m: float | None = None):
        self.cell_m, self.mask_distance_m = float(cell_m), mask_distance_m
        self.grid_: Grid | None = None

    def fit(self, data: LineData) -> MinimumCurvatureGridder:
        """Grid the values (nT) at their local east/north positions (m; heights are not used).
        Returns self, with ``grid_`` set.
        """
        self.grid_ = minimum_curvature(
            data.east_m, data.north_m, data.value_nT, self.cell_m, self.mask_distance_m
        )
        return self

    def predict(self, east_m, north_m, up_m=None) -> np.ndarray:
        """Bilinear in the fitted grid (NaN outside it); ``up_m`` is ignored: the grid lives
        on the flight surface."""
        return self.grid_.interpolate(east_m, north_m)

    def describe(self) -> dict[str, Any]:
        """The method's name."""
        return {"method": self.name}


class EquivalentSourceGridder:
    """harmonica's equivalent sources, fitted on block medians of the line data.

    Parameters
    ----------
    depth_m : float
        Depth of the point sources below each block's data point, m (several line spacings
        suit a map: shallower sources reproduce the lines but ring between them).
    damping : float or None
        Damping (ridge) of the source coefficients.
    block_m : float
        Block size of the median reduction before the fit (along-line samples are metres
        apart; one value per block keeps the system small without losing the across-line
        resolution).
    """

    name = "equivalent_sources"

    def __init__(self, depth_m: float, damping: float | None, block_m: float):
        self.depth_m, self.damping, self.block_m = float(depth_m), damping, float(block_m)
        self.model_ = None

    def fit(self, data: LineData) -> EquivalentSourceGridder:
        """Fit equivalent sources to block medians of the samples with a finite value, east and
        up (local east/north/up m, nT). Above ``DENSE_LIMIT`` blocks the gradient-boosted
        version is fitted. Returns self, with ``model_`` set.
        """
        import harmonica as hm
        import verde as vd

        ok = np.isfinite(data.value_nT) & np.isfinite(data.east_m) & np.isfinite(data.up_m)
        reducer = vd.BlockReduce(np.median, spacing=self.block_m, drop_coords=False)
        coords, values = reducer.filter(
            (data.east_m[ok], data.north_m[ok], data.up_m[ok]), data.value_nT[ok]
        )
        if values.size > DENSE_LIMIT:
            span = min(np.ptp(coords[0]), np.ptp(coords[1]))
            window = float(min(20 * self.depth_m, 0.5 * span)) if span > 0 else None
            model = hm.EquivalentSourcesGB(
                depth=self.depth_m, damping=self.damping, window_size=window, random_state=0
            )
        else:
            model = hm.EquivalentSources(depth=self.depth_m, damping=self.damping)
        self.model_ = model.fit(coords, values)
        return self

    def predict(self, east_m, north_m, up_m) -> np.ndarray:
        """The field at the given points (m in the map's local frame), nT."""
        e, n, u = np.broadcast_arrays(
            np.asarray(east_m, float), np.asarray(north_m, float), np.asarray(up_m, float)
        )
        return np.asarray(self.model_.predict((e, n, u)), float).reshape(e.shape)

    def describe(self) -> dict[str, Any]:
        """The method and its parameters (depth m, damping, block m)."""
        return {
            "method": self.name,
            "depth_m": self.depth_m,
            "damping": self.damping,
            "block_m": self.block_m,
        }


def line_folds(data: LineData, n_folds: int) -> list[np.ndarray]:
    """Held-out sample masks: the interior survey lines, in their order across the survey,
    every ``n_folds``-th one per fold. The two outermost lines are never held out (the
    gridder would extrapolate there, not interpolate) and tie lines stay in every training
    set."""
    survey = sorted(set(data.line[data.kind == "survey"].tolist()))
    if len(survey) < 3:
        return []
    centre = np.array(
        [
            [np.median(data.east_m[data.line == s]), np.median(data.north_m[data.line == s])]
            for s in survey
        ]
    )
    # the survey lines' centres lie along the across-line axis: their principal direction
    c = centre - centre.mean(axis=0)
    axis = np.linalg.svd(c, full_matrices=False)[2][0]
    order = [survey[i] for i in np.argsort(c @ axis)][1:-1]
    return [np.isin(data.line, order[k::n_folds]) for k in range(min(n_folds, len(order)))]


def line_masks(line: np.ndarray, keep: np.ndarray, min_count: int = 1) -> list[np.ndarray]:
    """One sample mask per line (``line`` labels, in sorted order): its samples where
    ``keep`` holds, for lines with at least ``min_count`` of them. Held-out misfits are
    judged per line with the line's level (its median misfit) removed: a line's offset is
    levelling's business, not the gridder's."""
    out = []
    for name in np.unique(line):
        m = keep & (line == name)
        if m.sum() >= min_count:
            out.append(m)
    return out


def cross_validated_rms_nT(make, data: LineData, n_folds: int = 5) -> float:
    """RMS misfit (nT) at held-out lines of gridders built by ``make()``; the level of each
    held-out line is removed first (a line's offset is levelling's business, not the
    gridder's)."""
    errs = []
    for held in line_folds(data, n_folds):
        g = make().fit(data.subset(~held))
        pred = g.predict(data.east_m[held], data.north_m[held], data.up_m[held])
        r = data.value_nT[held] - pred
        for m in line_masks(data.line[held], np.isfinite(r)):
            errs.append(r[m] - np.median(r[m]))
    if not errs:
        return float("nan")
    e = np.concatenate(errs)
    return float(np.sqrt(np.mean(e**2)))


@dataclass
class GridderChoice:
    """The chosen gridder and the cross-validation scores of every candidate (nT)."""

    gridder: Any
    scores_nT: dict[str, float] = field(default_factory=dict)

    def describe(self) -> dict[str, Any]:
        """The chosen gridder's description with every candidate's cross-validated RMS (nT)."""
        return {**self.gridder.describe(), "cv_rms_nT": self.scores_nT}


def choose_gridder(
    data: LineData,
    method: str,
    cell_m: float,
    spacing_m: float,
    mask_distance_m: float | None,
    depths_spacings: tuple[float, ...] = (1.0, 2.0, 4.0),
    dampings: tuple[float, ...] = (1e-3, 1e-1),
    n_folds: int = 5,
) -> GridderChoice:
    """The gridder ``method`` names (``minimum_curvature`` | ``equivalent_sources`` | ``auto``),
    with its parameters chosen by line-held-out cross-validation where there is a choice.

    ``equivalent_sources`` tries each depth (in line spacings) and damping; ``auto`` also
    scores minimum curvature and keeps the lowest score.
    """
    if method not in GRIDDERS:
        raise ValueError(f"map.gridder {method!r}: use {', '.join(GRIDDERS)}")

    def mc():
        # unmasked: a held-out line lies two spacings from the nearest kept one, and a masked
        # cell there would drop out of the score instead of counting against it
        return MinimumCurvatureGridder(cell_m, np.inf)

    if method == "minimum_curvature":
        return GridderChoice(MinimumCurvatureGridder(cell_m, mask_distance_m))
    block = max(cell_m / 2.0, 1.0)
    candidates: dict[str, Any] = {}
    for ds in depths_spacings:
        for damp in dampings:
            candidates[f"equivalent_sources depth {ds:g} spacings damping {damp:g}"] = (
                lambda d=ds * spacing_m, dm=damp: EquivalentSourceGridder(d, dm, block)
            )
    if method == "auto":
        candidates["minimum_curvature"] = mc
    scores = {k: cross_validated_rms_nT(make, data, n_folds) for k, make in candidates.items()}
    best = min(scores, key=lambda k: (np.isnan(scores[k]), scores[k]))
    return GridderChoice(candidates[best]().fit(data), scores)


def grid_on(
    choice: GridderChoice,
    data: LineData,
    template: Grid,
    height_m: np.ndarray | float = 0.0,
) -> Grid:
    """The chosen gridder's values on ``template``'s cells (its mask kept), at ``height_m``
    (local up, m; a scalar or one per cell: e.g. a DEM plus a clearance). ``template`` is
    the minimum-curvature grid of ``data``: returned as it is when that gridder was chosen."""
    g = choice.gridder
    if isinstance(g, MinimumCurvatureGridder):
        # the template is the minimum-curvature grid of the same data, with its mask
        return template
    if g.model_ is None:
        g.fit(data)
    gx, gy = np.meshgrid(*template.coordinates())
    up = np.broadcast_to(np.asarray(height_m, float), gx.shape)
    values = g.predict(gx, gy, up)
    values[~np.isfinite(template.values)] = np.nan
    return template.with_values(values)
