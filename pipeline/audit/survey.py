"""Survey-side evidence: what the lines themselves say, independent of the calibration fit.

Where lines cross, the same ground is measured twice: the difference of the two compensated
readings is the carrier's (and the day's) error at two times and two headings. Written as an
error model of the compensated field along the flight,

    e(t) = mu_h(t)                              heading error: a level per heading (N/E/S/W)
         + gamma_h(t) [t > t_s]                 a step at t_s (e.g. the carrier's permanent
                                                field changed: a switched load, a moved part)
         + beta t                               a drift (unmodelled diurnal, sensor drift)

each crossover gives d = e(t_a) - e(t_b). A step in the permanent field p changes the reading
by u . dp, which depends on heading, hence a step size per heading. Each flown line also
carries a random level of its own (:mod:`pipeline.audit.line_levels`). The change point t_s
is scanned over the gaps between readings, and the drift tested beside it, as one family:
each candidate's likelihood ratio against the model without it, the smallest pointwise p
corrected for the scan (and the drift) by a parametric bootstrap of the fitted null model
(the extreme of many ratios is not chi-square distributed; :func:`step_scan`). Few
points (tens of crossovers) and a heading-grouped model with crossed line levels are outside
what change-point libraries' cost functions express, hence the explicit scan.

Times are seconds from the flight's first epoch; sizes nT.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from pipeline.audit.evidence import HeldOut, f_test_p, least_squares_rss, paired_point_gain
from pipeline.audit.line_levels import (
    LineLevelModel,
    gls_coefficients,
    line_incidence,
    null_draws,
    scan_statistics,
)

HEADINGS = ("N", "E", "S", "W")  # the heading classes 0..3


@dataclass
class CrossoverSet:
    """Crossover differences with the times and heading classes (0..3: N, E, S, W) of the
    two readings, and where the lines cross (m)."""

    difference_nT: np.ndarray
    time_a_s: np.ndarray
    time_b_s: np.ndarray
    heading_a: np.ndarray
    heading_b: np.ndarray
    east_m: np.ndarray | None = None  # where the lines cross (the survey's local frame)
    north_m: np.ndarray | None = None
    line_a: np.ndarray | None = None  # the two lines' ids (each flown piece its own line)
    line_b: np.ndarray | None = None

    @property
    def size(self) -> int:
        """Number of crossovers."""
        return int(self.difference_nT.size)

    def subset(self, keep: np.ndarray) -> CrossoverSet:
        """The crossovers where ``keep`` (bool per crossover) holds."""
        opt = (
            None if v is None else np.asarray(v)[keep]
            for v in (self.east_m, self.north_m, self.line_a, self.line_b)
        )
        return CrossoverSet(
            *(np.asarray(getattr(self, k))[keep] for k in _READING_FIELDS),
            *opt,
        )


_READING_FIELDS = ("difference_nT", "time_a_s", "time_b_s", "heading_a", "heading_b")


@dataclass
class SurveyEvent:
    """A step or drift in the compensated field that the survey's crossovers show.

    Attributes
    ----------
    kind : str
        ``step`` or ``drift``.
    start_s, end_s : float
        s from the flight's first epoch: for a step, the two crossover readings around it; for
        a drift, the span of the readings.
    size_nT : float
        Step: the largest step over the headings; drift: the change over the survey (nT).
    p_value : float
        Corrected for the scan.
    detail : dict
        Extra report fields (step per heading, nT, and the likeliest gap, s; drift rate,
        nT/h).
    """

    kind: str  # step | drift
    start_s: float
    end_s: float
    size_nT: float  # step: largest step over headings; drift: change over the survey
    p_value: float  # corrected for the scan
    detail: dict

    def to_dict(self, t0_ns: int) -> dict:
        """The event as an unexplained-event record, with absolute times.

        Parameters
        ----------
        t0_ns : int
            The flight's first epoch, ns (the recording's time base).
        """
        detail = dict(self.detail)
        for k in ("likeliest_start", "likeliest_end"):  # times in the recording's base too
            if f"{k}_s" in detail:
                detail[f"{k}_ns"] = int(t0_ns + round(detail.pop(f"{k}_s") * 1e9))
        return {
            "kind": self.kind,
            "start_ns": int(t0_ns + round(self.start_s * 1e9)),
            "end_ns": int(t0_ns + round(self.end_s * 1e9)),
            "size_nT": self.size_nT,
            "p_value": self.p_value,
            "evidence": "survey crossovers",
            **detail,
        }


def heading_levels(x: CrossoverSet) -> np.ndarray:
    """Design columns of mu_h: one per heading class present, the first dropped (only
    differences are observed)."""
    classes = sorted(set(x.heading_a.tolist()) | set(x.heading_b.tolist()))
    cols = [
        (x.heading_a == h).astype(float) - (x.heading_b == h).astype(float) for h in classes[1:]
    ]
    return np.column_stack(cols) if cols else np.zeros((x.size, 0))


def _step_columns(
    x: CrossoverSet, t_s: float, min_each_side: int = 1
) -> tuple[np.ndarray, list[int]]:
    """Design columns of gamma_h for a step at ``t_s`` (s), and their heading classes.

    Only headings read at least ``min_each_side`` times on both sides of ``t_s``: a heading
    read only after it (tie lines all flown after the step) has a step column equal to its
    level column, and the least-squares split between the two is arbitrary (it was
    reported as a step size); one reading on a side makes the column a single reading's
    outlier test, not a step."""
    cols, which = [], []
    for h in range(4):
        t_h = np.r_[x.time_a_s[x.heading_a == h], x.time_b_s[x.heading_b == h]]
        if min(np.sum(t_h <= t_s), np.sum(t_h > t_s)) < max(1, min_each_side):
            continue
        c = ((x.heading_a == h) & (x.time_a_s > t_s)).astype(float) - (
            (x.heading_b == h) & (x.time_b_s > t_s)
        ).astype(float)
        cols.append(c)
        which.append(h)
    return (np.column_stack(cols) if cols else np.zeros((x.size, 0))), which


def _candidate_gaps(x: CrossoverSet, min_each_side: int) -> list[tuple[float, float]]:
    """Candidate change points of :func:`survey_events`: (earlier, later) times (s) of
    consecutive crossover readings, with at least ``min_each_side`` readings each side."""
    times = np.unique(np.r_[x.time_a_s, x.time_b_s])
    return [
        (float(a), float(b))
        for a, b in zip(
            times[min_each_side - 1 : -min_each_side], times[min_each_side:], strict=False
        )
    ]


SCAN_DRAWS = 400  # parametric-bootstrap draws of the scan statistic (p resolved to 2.5e-3)


@dataclass
class StepScan:
    """The change scan of :func:`step_scan`: a step at every candidate gap and a drift.

    ``gaps`` (earlier, later reading time, s), ``which`` the headings of each candidate's
    step columns, ``lr`` 2 x the profile log-likelihood gain over the null of each step,
    ``p_value`` the scan statistic's p under the bootstrap, ``rho`` the best step's
    line-level variance ratio (``drift_rho`` the drift's), ``step_nT`` its step per heading
    (nT), ``drift_is_best`` whether the drift, not a step, is the scan's likeliest change."""

    gaps: list[tuple[float, float]]
    which: list[list[int]]
    lr: np.ndarray
    p_value: float
    rho: float
    step_nT: np.ndarray
    drift_rho: float = 0.0
    drift_is_best: bool = False

    @property
    def best(self) -> int:
        """Index of the likeliest step."""
        return int(np.argmax(self.lr))


def line_model(x: CrossoverSet) -> LineLevelModel:
    """Random line levels when the crossovers name their lines, else independent readings."""
    z = None if x.line_a is None else line_incidence(x.line_a, x.line_b)
    return LineLevelModel.of(z, x.size)


def drift_column(x: CrossoverSet) -> np.ndarray:
    """The drift's design column: the two readings' time difference (s), (n, 1)."""
    return (x.time_a_s - x.time_b_s)[:, None]


def _least_p(lr: np.ndarray, dof: np.ndarray) -> np.ndarray:
    """Each draw's smallest pointwise chi-square log p over the candidates ((cands, draws)
    ratios ``lr`` with ``dof`` columns each): candidates of different sizes on one scale."""
    return np.min(stats.chi2.logsf(lr, dof[:, None]), axis=0)


def step_scan(
    x: CrossoverSet,
    base: np.ndarray,
    min_each_side: int,
    model: LineLevelModel | None = None,
    seed: int = 0,
) -> StepScan | None:
    """Scan every gap between readings for a step per heading, and the survey for a drift,
    beside random line levels (:mod:`pipeline.audit.line_levels`); ``model`` defaults to
    :func:`line_model`. None when neither a gap nor the drift can be tested.

    One family: the statistic is the smallest pointwise chi-square p over all of them (a
    step's degrees of freedom are its headings), its p from :data:`SCAN_DRAWS` draws of the
    fitted null model, the same scan on each (seeded: the same result on every run). A drift
    tested on its own beside the steps' scan would add its level to the scan's.
    """
    y = np.asarray(x.difference_nT, float)
    gaps, extras, which = [], [], []
    for lo, hi in _candidate_gaps(x, min_each_side):
        cols, w = _step_columns(x, 0.5 * (lo + hi), min_each_side)
        if w:
            gaps.append((lo, hi))
            extras.append(cols)
            which.append(w)
    if y.size < base.shape[1] + 3:
        return None
    model = model or line_model(x)
    cands = [*extras, drift_column(x)]
    dof = np.array([c.shape[1] for c in cands], float)
    lr, rho0, rho1 = scan_statistics(model, base, cands, y)
    sim, _, _ = scan_statistics(
        model, base, cands, null_draws(model, float(rho0[0]), SCAN_DRAWS, seed)
    )
    point = stats.chi2.logsf(lr[:, 0], dof)
    p = (1.0 + np.count_nonzero(_least_p(sim, dof) <= point.min())) / (SCAN_DRAWS + 1.0)
    steps_lr = lr[:-1, 0]
    if not gaps:
        return StepScan([], [], steps_lr, float(p), 0.0, np.zeros(0), float(rho1[-1, 0]), True)
    best = int(np.argmax(steps_lr))
    coef = gls_coefficients(model, np.column_stack([base, extras[best]]), y, float(rho1[best, 0]))
    return StepScan(
        gaps,
        which,
        steps_lr,
        float(p),
        float(rho1[best, 0]),
        coef[base.shape[1] :],
        float(rho1[-1, 0]),
        bool(np.argmin(point) == point.size - 1),
    )


def survey_events(
    x: CrossoverSet, alpha: float = 0.01, min_size_nT: float = 0.0, min_each_side: int = 2
) -> list[SurveyEvent]:
    """Steps and drifts in the compensated field's error, from crossovers.

    Parameters
    ----------
    x
        Crossover differences (compensated field, reduced for the main field and, when
        modelled, the diurnal), with times (s), heading classes and, when known, the lines.
    alpha
        Significance of the scan (steps and drift together, :func:`step_scan`).
    min_size_nT
        Smallest step or drift worth reporting.
    min_each_side
        Readings of a heading needed before and after a candidate change point.

    Each line's level is a random effect (:mod:`pipeline.audit.line_levels`): a step is a
    level change the lines after it share beyond their own scatter, and beyond heading
    levels that change across the area (:func:`heading_gradients`). A step is located
    between two consecutive crossover readings; the event's start and end span every such
    gap the data cannot tell from the likeliest one (a 95 % profile-likelihood set: the
    likelihood ratio within the chi-square(1) quantile 3.84 of the best),
    ``likeliest_start_s``/``_end_s`` in ``detail`` the likeliest gap itself. A line holds
    2-5 crossovers whose differences scatter by about a nT (geology between the
    interpolated readings, the heading error's change over the area), so the likeliest gap
    alone can lie a line away from the step. The event is the scan's likeliest change (on
    the pointwise scale): a step, or a drift.
    """
    x = x.subset(np.isfinite(np.asarray(x.difference_nT, float)))  # a NaN would win the scan
    y = np.asarray(x.difference_nT, float)
    base = heading_levels(x)
    if y.size < base.shape[1] + 6:
        return []
    base = np.column_stack([base, heading_gradients(x, base)])
    model = line_model(x)  # one eigendecomposition for the scan and the drift
    scan = step_scan(x, base, min_each_side, model)
    if scan is None or scan.p_value >= alpha:
        return []
    if scan.drift_is_best:
        return _drift(x, base, model, scan, min_size_nT)
    size = float(np.max(np.abs(scan.step_nT))) if scan.step_nT.size else 0.0
    if size < min_size_nT:
        return []
    b = scan.best
    near = np.flatnonzero(scan.lr[b] - scan.lr < float(stats.chi2.ppf(0.95, 1)))
    detail = {
        "step_by_heading_nT": {
            HEADINGS[h]: float(v) for h, v in zip(scan.which[b], scan.step_nT, strict=True)
        },
        "likeliest_start_s": scan.gaps[b][0],
        "likeliest_end_s": scan.gaps[b][1],
        "line_level_variance_ratio": scan.rho,
    }
    lo, hi = min(scan.gaps[i][0] for i in near), max(scan.gaps[i][1] for i in near)
    return [SurveyEvent("step", lo, hi, size, scan.p_value, detail)]


def heading_gradients(x: CrossoverSet, levels: np.ndarray) -> np.ndarray:
    """Columns of heading levels that change across the area (each level column times the
    crossing's east and north, km) when the crossovers say where they are and leave room
    for them; else none.

    Lines are flown one after another across the block, so a reading's time follows its
    place: a heading error that grows across the area (the induced interference scales with
    the field, a lag sees the ground's gradients) would read as a step or a drift. Only the
    ties, read at other times over the same places, separate the two; steps and drifts are
    tested beyond these columns."""
    if x.east_m is None or x.north_m is None or levels.shape[1] == 0:
        return np.zeros((x.size, 0))
    pos = np.column_stack(
        [levels * (np.asarray(v, float)[:, None] / 1e3) for v in (x.east_m, x.north_m)]
    )
    if not np.all(np.isfinite(pos)) or x.size <= levels.shape[1] + pos.shape[1] + 6:
        return np.zeros((x.size, 0))
    return pos


def _drift(
    x: CrossoverSet, base: np.ndarray, model: LineLevelModel, scan: StepScan, min_size_nT: float
) -> list[SurveyEvent]:
    """The drift (a trend no step explains) beside random line levels (``model``, at the
    scan's ``drift_rho``) and the ``base`` columns (:func:`heading_gradients` among them),
    as an event with the scan's p when its change over the survey reaches ``min_size_nT``."""
    y = np.asarray(x.difference_nT, float)
    coef = gls_coefficients(model, np.column_stack([base, drift_column(x)]), y, scan.drift_rho)
    t_all = np.r_[x.time_a_s, x.time_b_s]
    span = float(t_all.max() - t_all.min())
    size = abs(float(coef[-1])) * span
    if size < min_size_nT:
        return []
    return [
        SurveyEvent(
            "drift",
            float(t_all.min()),
            float(t_all.max()),
            size,
            scan.p_value,
            {"rate_nT_per_h": float(coef[-1]) * 3600.0},
        )
    ]


@dataclass
class SurveyLag:
    """Sensor lag estimated from the crossovers alone (:func:`survey_lag`): the lag and its 95 %
    interval (s), the two-sided p against no lag and the crossovers used.
    """

    lag_s: float
    ci95_s: tuple[float, float]
    p_value: float  # against no lag
    crossovers: int


def survey_lag(
    x: CrossoverSet, rate_a_nT_per_s: np.ndarray, rate_b_nT_per_s: np.ndarray
) -> SurveyLag | None:
    """A sensor that reports ``tau`` late reads F(t - tau) ~ F(t) - tau dF/dt: at a crossing
    the two lines disagree by -tau (dF_a/dt - dF_b/dt) besides their heading levels, the
    along-track shift a lag makes, opposite on opposite headings. Regressing the crossover
    differences on the difference of the along-track rates of change estimates tau from
    the survey alone (no calibration fit involved).

    Parameters
    ----------
    rate_a_nT_per_s, rate_b_nT_per_s
        Time derivative of each line's (smoothed) field at its crossing reading.
    """
    g = -(np.asarray(rate_a_nT_per_s, float) - np.asarray(rate_b_nT_per_s, float))
    fit = _regress_on(x, g)
    return None if fit is None else SurveyLag(*fit)


@dataclass
class SurveyCoupling:
    """A channel's coupling into the scalar reading estimated from the crossovers alone
    (:func:`survey_coupling`): nT per unit of the channel and its 95 % interval, the two-sided
    p against no coupling and the crossovers used.
    """

    nT_per_unit: float
    ci95: tuple[float, float]
    p_value: float  # against no coupling
    crossovers: int


def survey_coupling(
    x: CrossoverSet, aux_a: np.ndarray, aux_b: np.ndarray, step_s: float | None = None
) -> SurveyCoupling | None:
    """A channel (a current) that couples into the scalar reading by k nT per unit makes two
    crossing lines disagree by k (I_a - I_b) besides their heading levels: regressing the
    crossover differences on the channel's difference estimates k from the survey alone (k
    as the total field sees it, averaged over the headings). The readings' time difference
    and a step located elsewhere are fitted beside it (:func:`coupling_nuisance`)."""
    g = np.asarray(aux_a, float) - np.asarray(aux_b, float)
    fit = _regress_on(x, g, coupling_nuisance(x, step_s))
    return None if fit is None else SurveyCoupling(*fit)


def coupling_nuisance(x: CrossoverSet, step_s: float | None = None) -> np.ndarray:
    """What a channel's coupling at the crossovers is fitted beside: the readings' time
    difference (:func:`clock_column`) and, with ``step_s`` (s: a step of the carrier's
    permanent field located by other evidence, the fluxgate's), each heading's level change
    there (:func:`_step_columns`). A channel whose level differs before and after the step (a
    payload switched on, a battery's voltage) would otherwise take the step for its
    coupling."""
    clock = clock_column(x)
    if step_s is None:
        return clock
    return np.column_stack([clock, _step_columns(x, float(step_s))[0]])


def clock_column(x: CrossoverSet) -> np.ndarray:
    """The time between a crossover's two readings (h), a column (n, 1). Whatever changes
    the carrier's field with time (a sensor's drift, a step of its permanent field, the part
    of the day's variation the base station misses) changes the crossovers with it, and a
    channel that follows the clock (a battery's voltage, a heater's current) would take it
    for its coupling: the time difference, fitted beside the channel, takes the slow part."""
    return ((np.asarray(x.time_a_s, float) - np.asarray(x.time_b_s, float)) / 3600.0)[:, None]


def survey_coupling_gain(
    x: CrossoverSet, aux_a: np.ndarray, aux_b: np.ndarray, step_s: float | None = None
) -> HeldOut | None:
    """Does the channel's coupling predict crossovers it was not fitted on? Leave-one-out
    prediction errors of the crossover differences from the heading levels alone and from
    the levels plus the coupling (each crossover predicted by the fit to the others: the
    ordinary residual over one minus its leverage), compared pair by pair
    (:func:`pipeline.audit.evidence.paired_point_gain`); :func:`coupling_nuisance` in both.
    None: too few crossovers."""
    y = np.asarray(x.difference_nT, float)
    g = np.asarray(aux_a, float) - np.asarray(aux_b, float)
    full = np.column_stack([heading_levels(x), coupling_nuisance(x, step_s), g])
    ok = np.all(np.isfinite(full), axis=1) & np.isfinite(y)
    full, y = full[ok], y[ok]
    if full.shape[0] < full.shape[1] + 4 or not _identifiable(full):
        return None

    def loo_errors(a: np.ndarray) -> np.ndarray:
        q, _ = np.linalg.qr(a)
        h = np.sum(q**2, axis=1)  # leverages
        coef, *_ = np.linalg.lstsq(a, y, rcond=None)
        return (y - a @ coef) / np.clip(1.0 - h, 1e-9, None)

    return paired_point_gain(loo_errors(full[:, :-1]), loo_errors(full))


def _identifiable(a: np.ndarray) -> bool:
    """Whether the last column of ``a`` has a part the other columns do not span (more
    than 1e-6 of its own size): a channel that only switched at a located step, or not at
    all, says nothing of its coupling beside the step's columns and the levels."""
    g, rest = a[:, -1], a[:, :-1]
    if np.std(g) == 0:
        return False
    left = g - rest @ np.linalg.lstsq(rest, g, rcond=None)[0] if rest.shape[1] else g
    return bool(np.linalg.norm(left) > 1e-6 * np.linalg.norm(g))


def _regress_on(
    x: CrossoverSet, g: np.ndarray, nuisance: np.ndarray | None = None
) -> tuple[float, tuple[float, float], float, int] | None:
    """Coefficient of ``g`` in crossover differences ~ heading levels (+ ``nuisance``
    columns) + c g: estimate, 95 % interval, two-sided p against 0, crossovers used."""
    y = np.asarray(x.difference_nT, float)
    extra = np.zeros((x.size, 0)) if nuisance is None else nuisance
    a = np.column_stack([heading_levels(x), extra, g])
    ok = np.all(np.isfinite(a), axis=1) & np.isfinite(y)
    a, y = a[ok], y[ok]
    n, k = a.shape
    if n < k + 4 or not _identifiable(a):
        return None
    coef, *_ = np.linalg.lstsq(a, y, rcond=None)
    r = y - a @ coef
    s2 = float(r @ r) / (n - k)
    cov = s2 * np.linalg.pinv(a.T @ a)
    se = float(np.sqrt(max(cov[-1, -1], 0.0)))
    c = float(coef[-1])
    half = float(stats.t.ppf(0.975, n - k)) * se
    p = float(2 * stats.t.sf(abs(c) / se, n - k)) if se > 0 else 1.0
    return c, (c - half, c + half), p, int(n)


@dataclass
class SurveyHeading:
    """Heading-dependent levels of a compensated field, from the survey's crossovers.

    ``levels_nT``: the level of each heading class present (N, E, S, W; mean zero), nT;
    ``spread_nT``: their largest minus smallest; ``p_value``: F-test of the levels against
    none; ``position_p_value``: F-test of levels that also change linearly across the
    survey (heading x east/north) against constant levels (None: too few crossovers).
    """

    levels_nT: dict[str, float]
    spread_nT: float
    p_value: float
    position_p_value: float | None
    crossovers: int


def survey_heading(
    x: CrossoverSet, east_km: np.ndarray | None = None, north_km: np.ndarray | None = None
) -> SurveyHeading | None:
    """Heading error seen at the survey's crossovers, independent of the calibration fit.

    A compensation biased by a geomagnetic gradient during calibration (or any heading
    term it got wrong) leaves each heading its own level: two crossing lines then disagree by
    the difference of their headings' levels. When the error also grows across the survey
    (the induced interference scales with the field, which a gradient changes over the
    area), the levels change with the crossover's position (``east_km``, ``north_km``: where
    the lines cross, km).
    """
    y = np.asarray(x.difference_nT, float)
    lv = heading_levels(x)
    ok = np.isfinite(y)
    n = int(ok.sum())
    if lv.shape[1] == 0 or n < lv.shape[1] + 4:
        return None
    rss0, k0, _ = least_squares_rss(np.zeros((n, 0)), y[ok])
    rss1, k1, coef = least_squares_rss(lv[ok], y[ok])
    p = f_test_p(rss0, k0, rss1, k1, n)
    classes = sorted(set(x.heading_a.tolist()) | set(x.heading_b.tolist()))
    levels = np.r_[0.0, coef]
    levels = levels - levels.mean()
    pos_p = None
    if east_km is not None and north_km is not None:
        inter = np.column_stack(
            [lv * np.asarray(east_km, float)[:, None], lv * np.asarray(north_km, float)[:, None]]
        )
        a = np.column_stack([lv, inter])
        good = ok & np.all(np.isfinite(a), axis=1)
        if good.sum() > a.shape[1] + 4:
            r0, q0, _ = least_squares_rss(lv[good], y[good])
            r1, q1, _ = least_squares_rss(a[good], y[good])
            pos_p = f_test_p(r0, q0, r1, q1, int(good.sum()))
    return SurveyHeading(
        {HEADINGS[c]: float(v) for c, v in zip(classes, levels, strict=True)},
        float(np.ptp(levels)),
        p,
        pos_p,
        n,
    )
