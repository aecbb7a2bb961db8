"""The map's own error, 1 sigma per cell (nT): what a user of the grid, or a navigation filter
reading it, should assume the cell's value is off from the true field at the flight surface.

Three parts, added in quadrature (the first alone when tie lines measure it):

* **interpolation**: a cell between flight lines is a guess from the lines beside it, and the
  guess worsens with the distance ``d`` to the nearest line. Measured directly where the
  survey has them, with **tie lines held out**: the map's gridder is fitted to the survey
  lines alone and predicts every tie-line sample inside the survey lines' hull. A tie crosses
  the survey lines, so its samples sit at every distance from 0 to half a spacing from the
  nearest survey-line sample, at the survey's own spacing; their squared misfits (each tie's
  level removed, the sensor's noise removed) binned by that distance give the error's shape
  and size at once, with no assumption about how the field varies across the lines. That
  misfit holds everything the map carries at a point: what its cells cannot hold of the
  field along the lines (the error is not zero on a line), the survey lines' level errors
  and their noise as the grid averages it; the two terms below are therefore not added.
  Two ties sample a block along two transects only: every n-th interior survey line is also
  held out (the gridder fitted to the other survey lines) and its misfit compared with the
  ties' misfit where they cross it, in the same gap. Where the lines miss by more, the ties
  crossed quieter geology than the block holds, and the error is raised by that ratio;
  never lowered (sigma too small misleads a navigation filter far more than too large).
  Without tie lines the shape is measured along the lines and scaled by **held-out survey
  lines**: each line is thinned to knots one line spacing apart, interpolated between them
  by a cubic spline (the 1-D minimum-curvature interpolant), the squared error binned by the
  distance to the nearest knot, and scaled by every n-th interior survey line left out of
  the grid and predicted by the map's own gridder, against the same along-line measurement
  at the held-out lines' gap (two spacings). That assumes isotropy (the field varies across
  the lines as along them), which fails where the geology is elongated. Either way, a cell
  a whole spacing from the data (a line missing over a stretch, a gap in the recording, a
  block's edge) takes the held-out lines' own error: a held-out line is a line missing.
* **levelling** (survey-line method only): the crossover differences left after levelling,
  over sqrt(2) (each holds two lines' level errors).
* **noise** (survey-line method only): the sensor's white noise, which the grid carries on the
  lines themselves.

The error is that of the map read at a point (bilinearly between cells, as a navigation
filter reads it), not only at the cells' centres. How far along a track it stays the same
(its correlation length, which a navigation filter needs so as not to average it away) is
measured along the held-out survey lines (:func:`error_correlation_length`).

No library gives a cross-validated interpolation error for line data (verde's and harmonica's
cross-validation return a score, not an error model), hence this module. Coordinates are the
grid's metric frame (east, north in m).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.spatial import ConvexHull, Delaunay, QhullError, cKDTree

from pipeline.maps.grid import Grid
from pipeline.maps.gridders import LineData, line_folds, line_masks

N_DISTANCE_BINS = 8
# fewer tie samples than this in a distance bin: the bin's mean squared error is too noisy
# to stand for the error at that distance (about 30 % relative spread at 20 samples)
MIN_BIN_SAMPLES = 20
# the longest lag (in line spacings) over which the map error's autocovariance is summed: an
# error correlated farther than this is a level, which the navigation filter's bias state
# and each line's own level take
MAX_CORRELATION_SPACINGS = 8.0
TIE_METHOD = "tie lines held out"


@dataclass
class MapUncertainty:
    """The fitted error model of one grid.

    Attributes
    ----------
    distance_m, shape_nT2
        Interpolation error against the distance to the nearest line (m, bin centres from 0
        to half a spacing, then a spacing: :func:`_with_missing_line`) and mean squared
        error (nT^2, the sensor's noise removed), before ``scale``.
    scale
        Held-out squared error over the along-line one at the held-out lines' gap.
    level_nT, noise_nT
        Levelling and sensor-noise terms (nT, 1 sigma).
    heldout_rms_nT
        RMS error at the held-out lines (their level removed), nT.
    spacing_m
        Line spacing, m.
    method
        ``"tie lines held out"`` (shape and size measured across the lines; ``scale`` 1) or
        ``"survey lines held out"`` (the along-line shape, scaled).
    correlation_length_m
        The distance along a track over which the map's error stays the same (m): the
        two-sided integral of its autocorrelation, measured along the held-out survey lines
        (:func:`error_correlation_length`); never below ``spacing_m``. NaN: not measured
        (the spacing stands for it).
    """

    distance_m: np.ndarray
    shape_nT2: np.ndarray
    scale: float
    level_nT: float
    noise_nT: float
    heldout_rms_nT: float
    spacing_m: float
    method: str = "survey lines held out"
    correlation_length_m: float = float("nan")

    def interpolation_nT(self, distance_m: np.ndarray) -> np.ndarray:
        """Interpolation error (nT, 1 sigma) at ``distance_m`` from the nearest line; past a
        spacing (outside the block) the largest value holds."""
        e2 = np.interp(np.asarray(distance_m, float), self.distance_m, self.shape_nT2)
        return np.sqrt(np.maximum(self.scale * e2, 0.0))

    @property
    def floor_nT(self) -> float:
        """What :meth:`sigma_nT` adds to the interpolation term in quadrature (nT): the
        levelling and noise terms, unless the tie lines measured them already (a tie sample's
        misfit to the map holds the survey lines' level errors and the noise as the grid
        carries it; the tie's own noise was removed)."""
        if self.method == TIE_METHOD:
            return 0.0
        return float(np.hypot(self.level_nT, self.noise_nT))

    def sigma_nT(self, distance_m: np.ndarray) -> np.ndarray:
        """Total 1-sigma error (nT) at ``distance_m`` from the nearest measurement."""
        return np.hypot(self.interpolation_nT(distance_m), self.floor_nT)

    @property
    def error_length_m(self) -> float:
        """The error's correlation length a navigation filter charges (m): the measured one,
        else the line spacing."""
        c = self.correlation_length_m
        return float(c) if np.isfinite(c) else float(self.spacing_m)

    def describe(self) -> dict[str, float]:
        """JSON-ready figures of the model."""
        return {
            "heldout_rms_nT": self.heldout_rms_nT,
            "correlation_length_m": self.error_length_m,
            "scale": self.scale,
            "level_nT": self.level_nT,
            "noise_nT": self.noise_nT,
            "midway_interpolation_nT": float(self.interpolation_nT(self.spacing_m / 2)),
            "method": self.method,
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


def _with_missing_line(
    d: np.ndarray, e2: np.ndarray, missing_nT2: float, scale: float, spacing_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """The error curve ``(d, e2)``, measured to half a line spacing, continued to a full
    spacing by the held-out survey lines' own squared error ``missing_nT2`` (nT^2, noise
    removed): a held-out line is a line missing, its samples a spacing from the nearest
    data, as a cell is in a hole (a line not flown over a stretch, a gap in the recording)
    or a spacing beyond a block's edge. Divided by ``scale``, which the model multiplies
    back; linear in between, never falling with distance."""
    if not (spacing_m > float(d[-1]) and scale > 0):
        return d, e2
    return np.r_[d, spacing_m], np.maximum.accumulate(np.r_[e2, missing_nT2 / scale])


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
    tie = _tie_model(data, make_gridder, spacing_m, noise_nT)
    if tie is None:
        return _survey_model(data, make_gridder, folds, spacing_m, noise_nT, level_nT)
    e2, ratio, length_m = _heldout_lines(data, make_gridder, folds, spacing_m, noise_nT)
    # a few transects say little of a whole block: where the held-out lines miss by more than
    # the ties at the same place, the ties crossed quieter geology and sigma rises with the
    # ratio; where by less, it stays (a sigma told too small makes a navigation filter read
    # map error as position, one told too large only slows it)
    scale = max(1.0, ratio)
    missing = max(e2 - noise_nT**2, 0.0)
    return MapUncertainty(
        *_with_missing_line(*tie, missing, scale, spacing_m),
        scale,
        float(level_nT),
        float(noise_nT),
        float(np.sqrt(e2)),
        float(spacing_m),
        TIE_METHOD,
        length_m,
    )


def _tie_misfit(
    data: LineData, train: np.ndarray, gridder, reach_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The tie samples' misfit (nT) to ``gridder``, fitted on the samples ``train`` (a mask),
    each tie's level (its median misfit) removed; their distance (m) to the nearest training
    sample; and which of them measure interpolation: inside the training lines' hull (where
    a tie runs past the survey lines the grid extrapolates) and within ``reach_m`` of them."""
    tie = np.asarray(data.kind == "tie")
    xy = np.column_stack([data.east_m[train], data.north_m[train]])
    tie_xy = np.column_stack([data.east_m[tie], data.north_m[tie]])
    d, _ = cKDTree(xy).query(tie_xy)
    try:
        hull = Delaunay(xy[ConvexHull(xy).vertices])
    except QhullError:  # the lines span no area (one track): nothing lies between them
        return data.value_nT[tie] * np.nan, d, np.zeros(d.size, bool)
    inside = (d <= reach_m) & (hull.find_simplex(tie_xy) >= 0)
    pred = gridder.predict(data.east_m[tie], data.north_m[tie], data.up_m[tie])
    r = data.value_nT[tie] - pred
    inside &= np.isfinite(r)
    for m in line_masks(data.line[tie], inside):
        r[m] -= np.median(r[m])  # the tie's level is levelling's error, not this
    return r, d, inside


def _tie_model(
    data: LineData, make_gridder: Callable[[], object], spacing_m: float, noise_nT: float
) -> tuple[np.ndarray, np.ndarray] | None:
    """The interpolation error measured at held-out tie lines (module docstring): distance
    bins (m; their centres, from 0 to half a spacing) and the squared error per bin (nT^2,
    the sensor's noise removed, never falling with distance: farther from the data is on
    average no better). None without enough tie samples between the survey lines."""
    if data.kind is None or np.sum(data.kind == "tie") < 2 * MIN_BIN_SAMPLES:
        return None
    half = 0.5 * spacing_m
    survey = np.asarray(data.kind == "survey")
    g = make_gridder().fit(data.subset(survey))
    r, d, inside = _tie_misfit(data, survey, g, half)
    edges = np.linspace(0.0, half, N_DISTANCE_BINS + 1)
    b = np.clip(np.searchsorted(edges, d[inside], side="right") - 1, 0, N_DISTANCE_BINS - 1)
    counts = np.bincount(b, minlength=N_DISTANCE_BINS)
    sums = np.bincount(b, weights=r[inside] ** 2, minlength=N_DISTANCE_BINS)
    ok = counts >= MIN_BIN_SAMPLES
    if ok.sum() < 2:
        return None
    centre = 0.5 * (edges[1:] + edges[:-1])[ok]
    e2 = _signal_nT2(sums[ok] / counts[ok], counts[ok], noise_nT)
    return centre, np.maximum.accumulate(e2)


def _signal_nT2(mean2_nT2, count, noise_nT: float):
    """A mean squared misfit of ``count`` samples less the samples' own noise (nT^2), no
    smaller than what ``count`` samples resolve: a mean square is known to about
    sqrt(2 / count) of itself (Gaussian misfits), below which it cannot be told from zero."""
    return np.maximum(mean2_nT2 - noise_nT**2, np.sqrt(2.0 / count) * mean2_nT2)


def error_correlation_length(
    series: list[tuple[np.ndarray, np.ndarray]], spacing_m: float, gap_m: float
) -> float:
    """How far along a track the map's error stays the same (m), from held-out lines.

    Parameters
    ----------
    series : list of (distance_m, misfit_nT)
        Each held-out line's misfit to the grid fitted without it (nT, the line's level
        removed) against the distance along the line (m, increasing).
    spacing_m : float
        The map's line spacing (m).
    gap_m : float
        The gap the held-out lines were predicted across (m; twice the spacing when one line
        in every few is left out).

    Returns
    -------
    float
        The two-sided integral of the error's autocorrelation (m), by the trapezoid rule over
        lags up to the first where it is no longer positive or
        :data:`MAX_CORRELATION_SPACINGS`; scaled by ``spacing_m / gap_m`` and never below
        ``spacing_m``. NaN when no two lags can be formed. The misfits are averaged in bins a
        sixteenth of a spacing long (at least one and a half sample steps), the
        autocovariance taken between different bins and its value at zero lag extrapolated
        from the first two lags: the held-out samples' own white noise, which only zero lag
        holds, does not shorten it. The scaling: the error between lines is the field the
        lines do not resolve, on the scale of their gap; measured across twice the map's gap
        it is twice as long where the geology varies along the lines as across them.
    """
    if not (np.isfinite(spacing_m) and spacing_m > 0 and np.isfinite(gap_m) and gap_m > 0):
        return float("nan")
    # a line is cut where it jumps farther than the longest lag summed (a gap in the record,
    # a position glitch): nothing correlates across it, and the distance bins would grow
    # with it
    parts = []
    for d, x in series:
        cut = np.flatnonzero(np.diff(d) > MAX_CORRELATION_SPACINGS * spacing_m) + 1
        parts += zip(np.split(d, cut), np.split(x, cut), strict=True)
    series = [(d, x) for d, x in parts if d.size >= 3 and np.all(np.isfinite(d) & np.isfinite(x))]
    # a position held over several samples is no step
    steps = [float(np.median(np.diff(d)[np.diff(d) > 0])) for d, _ in series if d[-1] > d[0]]
    # bins of several samples where the lines are sampled densely, else of one or two: two
    # bins' means never share a sample
    h = max(spacing_m / 16.0, 1.5 * float(np.median(steps)) if steps else 0.0)
    n_lags = int(MAX_CORRELATION_SPACINGS * spacing_m / h)
    num, lag, cnt = np.zeros(n_lags + 1), np.zeros(n_lags + 1), np.zeros(n_lags + 1)
    for dist, misfit in series:
        b = np.floor((dist - dist[0]) / h).astype(int)
        n = int(b[-1]) + 1
        counts = np.bincount(b, minlength=n)
        have = counts > 0
        c = np.maximum(counts, 1)
        mean = np.bincount(b, weights=misfit, minlength=n) / c
        where = np.bincount(b, weights=dist, minlength=n) / c
        for k in range(1, min(n_lags, n - 1) + 1):
            both = have[:-k] & have[k:]
            num[k] += float(np.sum((mean[:-k] * mean[k:])[both]))
            lag[k] += float(np.sum((where[k:] - where[:-k])[both]))
            cnt[k] += float(both.sum())
    ok = cnt[1:] > 0
    if ok.sum() < 2:
        return float("nan")
    cov, d = (num[1:] / np.maximum(cnt[1:], 1))[ok], (lag[1:] / np.maximum(cnt[1:], 1))[ok]
    # the autocovariance at zero lag, without the noise: the first two lags' line, no lower
    # than the first lag (that lag alone where the two lie too close to draw a line)
    c0 = cov[0]
    if d[1] - d[0] > 0.5 * h:
        c0 = max(c0, cov[0] + (cov[0] - cov[1]) * d[0] / (d[1] - d[0]))
    if c0 <= 0:
        return float("nan")
    rho = np.concatenate([[1.0], cov / c0])
    d = np.concatenate([[0.0], d])
    stop = np.flatnonzero(~(rho > 0))
    end = stop[0] if stop.size else rho.size
    one_sided = float(np.sum(np.diff(d[:end]) * 0.5 * (rho[: end - 1] + rho[1:end])))
    return float(max(spacing_m, 2.0 * one_sided * spacing_m / gap_m))


def _levelled_lines(
    data: LineData, held: np.ndarray, misfit: np.ndarray
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Each held-out line (of at least three predicted samples): its mask within ``held``,
    the distance along it (m) and its misfit with the line's level (median) removed (nT).
    A line's offset is levelling's business, not the gridder's."""
    out = []
    e, n = data.east_m[held], data.north_m[held]
    for m in line_masks(data.line[held], np.isfinite(misfit), 3):
        d = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(e[m]), np.diff(n[m])))])
        out.append((m, d, misfit[m] - np.median(misfit[m])))
    return out


def _heldout_lines(
    data: LineData,
    make_gridder: Callable[[], object],
    folds: list[np.ndarray],
    spacing_m: float,
    noise_nT: float,
) -> tuple[float, float, float]:
    """Held-out survey lines against the ties where they cross them: the lines' mean squared
    misfit (nT^2, each line's level removed, the noise not) and the ratio of their error to
    the ties' error at the same place in the same gap (both midway between lines two
    spacings apart; the noise removed from both). A few tie transects may cross quieter or
    louder geology than the block holds; the ratio carries the ties' error across the block.
    The ratio is 1 where the ties do not cross the held-out lines enough to tell (fewer than
    :data:`MIN_BIN_SAMPLES` samples). Third, the error's correlation length along the lines
    (m, :func:`error_correlation_length`)."""
    lines2, ties2, series = [], [], []
    survey, tie = np.asarray(data.kind == "survey"), np.asarray(data.kind == "tie")
    for held in folds:
        g = make_gridder().fit(data.subset(~held & survey))
        r = data.value_nT[held] - g.predict(data.east_m[held], data.north_m[held], data.up_m[held])
        for _, dist, x in _levelled_lines(data, held, r):
            lines2.append(x**2)
            series.append((dist, x))
        rt, _, inside = _tie_misfit(data, ~held & survey, g, spacing_m)
        near, _ = cKDTree(np.column_stack([data.east_m[held], data.north_m[held]])).query(
            np.column_stack([data.east_m[tie], data.north_m[tie]])
        )
        ties2.append(rt[inside & (near <= spacing_m / 4)] ** 2)
    if not lines2:
        raise ValueError("map uncertainty: no held-out line could be predicted")
    e2 = float(np.mean(np.concatenate(lines2)))
    length_m = error_correlation_length(series, spacing_m, 2.0 * spacing_m)
    t2 = np.concatenate(ties2) if ties2 else np.empty(0)
    if t2.size < MIN_BIN_SAMPLES:
        return e2, 1.0, length_m
    ties_signal = float(_signal_nT2(float(np.mean(t2)), t2.size, noise_nT))
    ratio = max(e2 - noise_nT**2, 0.0) / ties_signal if ties_signal > 0 else 1.0
    return e2, ratio, length_m


def _survey_model(
    data: LineData,
    make_gridder: Callable[[], object],
    folds: list[np.ndarray],
    spacing_m: float,
    noise_nT: float,
    level_nT: float,
) -> MapUncertainty:
    """The along-line shape scaled by held-out survey lines (module docstring)."""
    d1, shape1 = _shape(data, spacing_m, noise_nT)
    d2, shape2 = _shape(data, 2.0 * spacing_m, noise_nT)
    err2, ref2, series = [], [], []
    for held in folds:
        g = make_gridder().fit(data.subset(~held))
        pred = g.predict(data.east_m[held], data.north_m[held], data.up_m[held])
        tree = cKDTree(np.column_stack([data.east_m[~held], data.north_m[~held]]))
        d, _ = tree.query(np.column_stack([data.east_m[held], data.north_m[held]]))
        r = data.value_nT[held] - pred
        for m, dist, x in _levelled_lines(data, held, r):
            err2.append(x**2)
            ref2.append(np.interp(d[m], d2, shape2))
            series.append((dist, x))
    if not err2:
        raise ValueError("map uncertainty: no held-out line could be predicted")
    e2, r2 = np.concatenate(err2), np.concatenate(ref2)
    # held-out samples carry their own white noise as well
    signal = max(float(np.mean(e2)) - noise_nT**2, 0.0)
    scale = signal / float(np.mean(r2)) if np.mean(r2) > 0 else 0.0
    return MapUncertainty(
        *_with_missing_line(d1, shape1, signal, scale, spacing_m),
        scale,
        float(level_nT),
        float(noise_nT),
        float(np.sqrt(np.mean(e2))),
        float(spacing_m),
        correlation_length_m=error_correlation_length(series, spacing_m, 2.0 * spacing_m),
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
