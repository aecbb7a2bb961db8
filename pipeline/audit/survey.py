"""Survey-side evidence: what the lines themselves say, independent of the calibration fit.

Where lines cross, the same ground is measured twice: the difference of the two compensated
readings is the carrier's (and the day's) error at two times and two headings. Written as an
error model of the compensated field along the flight,

    e(t) = mu_h(t)                              heading error: a level per heading (N/E/S/W)
         + gamma_h(t) [t > t_s]                 a step at t_s (e.g. the carrier's permanent
                                                field changed: a switched load, a moved part)
         + beta t                               a drift (unmodelled diurnal, sensor drift)

each crossover gives d = e(t_a) - e(t_b). A step in the permanent field p changes the reading
by u . dp, which depends on heading, hence a step size per heading. The change point t_s is
scanned over the gaps between lines; its significance is an F-test against the model without
it, corrected for the scan by the scan's own null distribution (the maximum of many F
statistics is not F-distributed; :func:`scan_p_value`). Few points (tens of crossovers) and
a heading-grouped model are outside what change-point libraries' cost functions express,
hence the explicit scan.

Times are seconds from the flight's first epoch; sizes nT.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from pipeline.audit.evidence import HeldOut, f_test_p, least_squares_rss, paired_point_gain

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

    @property
    def size(self) -> int:
        """Number of crossovers."""
        return int(self.difference_nT.size)

    def subset(self, keep: np.ndarray) -> CrossoverSet:
        """The crossovers where ``keep`` (bool per crossover) holds."""
        pos = (None if v is None else np.asarray(v)[keep] for v in (self.east_m, self.north_m))
        return CrossoverSet(
            *(np.asarray(getattr(self, k))[keep] for k in _READING_FIELDS),
            *pos,
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


def _step_columns(x: CrossoverSet, t_s: float) -> tuple[np.ndarray, list[int]]:
    """Design columns of gamma_h for a step at ``t_s`` (s), and their heading classes.

    Only headings read on both sides of ``t_s``: a heading read only after it (tie lines
    all flown after the step) has a step column equal to its level column, and the
    least-squares split between the two is arbitrary (it was reported as a step size)."""
    cols, which = [], []
    for h in range(4):
        t_h = np.r_[x.time_a_s[x.heading_a == h], x.time_b_s[x.heading_b == h]]
        if not (np.any(t_h <= t_s) and np.any(t_h > t_s)):
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


SCAN_SIMULATIONS = 2000  # null draws of the scan's smallest p (p resolved to 5e-4)


def scan_p_value(
    p_min: float, base: np.ndarray, designs: list[np.ndarray], scanned: int, seed: int = 0
) -> float:
    """The smallest of a scan's F-test p-values (``p_min``), corrected for the scan.

    Neighbouring change points differ by one reading, so their F statistics are nearly the
    same test: Bonferroni over the ``scanned`` positions (tens) is far too conservative. The
    scan's own null distribution is exact and cheap instead: under no step with
    independent Gaussian errors every F statistic is free of the error scale and of the
    base model's coefficients, so the smallest p of the same scan over
    :data:`SCAN_SIMULATIONS` standard normal draws (fixed ``seed``: the same result on
    every run) gives the corrected p. Below the simulations' resolution Bonferroni, a
    valid bound, takes over.

    Parameters
    ----------
    p_min : float
        The scan's smallest F-test p.
    base : ndarray
        (n, k0) design without a step.
    designs : list of ndarray
        Each scanned position's design (base and step columns).
    scanned : int
        Positions scanned (Bonferroni's factor).
    seed : int
        Seed of the simulations.

    Returns
    -------
    float
        The scan-corrected p.
    """
    bonferroni = min(1.0, p_min * scanned)
    n = base.shape[0]
    if bonferroni < 1.0 / (SCAN_SIMULATIONS + 1) or not designs:
        return bonferroni
    from scipy.linalg import orth

    e = np.random.default_rng(seed).standard_normal((n, SCAN_SIMULATIONS))

    def rss(a: np.ndarray) -> tuple[np.ndarray, int]:
        q = orth(a) if a.shape[1] else np.zeros((n, 0))
        r = e - q @ (q.T @ e)
        return np.sum(r**2, axis=0), q.shape[1]

    rss0, k0 = rss(base)
    smallest = np.ones(SCAN_SIMULATIONS)
    for a in designs:
        rss1, k1 = rss(a)
        df1, df2 = k1 - k0, n - k1
        if df1 <= 0 or df2 <= 0:
            continue
        f = ((rss0 - rss1) / df1) / (rss1 / df2)
        smallest = np.minimum(smallest, stats.f.sf(f, df1, df2))
    mc = (1.0 + np.count_nonzero(smallest <= p_min)) / (SCAN_SIMULATIONS + 1)
    return float(min(bonferroni, mc))


def survey_events(
    x: CrossoverSet, alpha: float = 0.01, min_size_nT: float = 0.0, min_each_side: int = 2
) -> list[SurveyEvent]:
    """Steps and drifts in the compensated field's error, from crossovers.

    Parameters
    ----------
    x
        Crossover differences (compensated field, reduced for the main field and, when
        modelled, the diurnal), with times (s) and heading classes.
    alpha
        Significance after the scan correction.
    min_size_nT
        Smallest step or drift worth reporting.
    min_each_side
        Readings needed before and after a candidate change point.

    A step is located between two consecutive crossover readings; the event's start and
    end span every such gap the data cannot tell from the likeliest one (a 95 % profile
    likelihood set: n log(RSS(t) / RSS(t_best)) below the chi-square(1) quantile 3.84),
    ``likeliest_start_s``/``_end_s`` in ``detail`` the likeliest gap itself. A line holds
    2-5 crossovers whose differences scatter by about a nT (geology between the
    interpolated readings, the heading error's change over the area), so the likeliest gap
    alone can lie a line away from the step.
    """
    y = np.asarray(x.difference_nT, float)
    n = y.size
    base = heading_levels(x)
    if n < base.shape[1] + 6:
        return []
    rss0, k0, _ = least_squares_rss(base, y)
    out: list[SurveyEvent] = []
    gaps = _candidate_gaps(x, min_each_side)
    scanned = []  # (p, start, end, step per heading, added rank, headings, rss)
    designs = []
    for lo, hi in gaps:
        cols, which = _step_columns(x, 0.5 * (lo + hi))
        if not which:
            continue
        designs.append(np.column_stack([base, cols]))
        rss1, k1, coef = least_squares_rss(designs[-1], y)
        p = f_test_p(rss0, k0, rss1, k1, n)
        scanned.append((p, lo, hi, coef[base.shape[1] :], k1 - k0, which, rss1))
    best = min(scanned, key=lambda c: c[0]) if scanned else None
    if best is not None and best[4] > 0:
        p_adj = scan_p_value(best[0], base, designs, len(gaps))
        size = float(np.max(np.abs(best[3]))) if best[3].size else 0.0
        if p_adj < alpha and size >= min_size_nT:
            chi2_95 = float(stats.chi2.ppf(0.95, 1))
            near = [c for c in scanned if n * np.log(c[6] / best[6]) < chi2_95]
            out.append(
                SurveyEvent(
                    "step",
                    min(c[1] for c in near),
                    max(c[2] for c in near),
                    size,
                    p_adj,
                    {
                        "step_by_heading_nT": {
                            HEADINGS[h]: float(v) for h, v in zip(best[5], best[3], strict=True)
                        },
                        "likeliest_start_s": float(best[1]),
                        "likeliest_end_s": float(best[2]),
                    },
                )
            )
    if not out:  # a drift only when no step explains the trend
        drift = (x.time_a_s - x.time_b_s)[:, None]
        rss1, k1, coef = least_squares_rss(np.column_stack([base, drift]), y)
        p = f_test_p(rss0, k0, rss1, k1, n)
        t_all = np.r_[x.time_a_s, x.time_b_s]
        span = float(t_all.max() - t_all.min())
        size = abs(float(coef[-1])) * span
        if p < alpha and size >= min_size_nT:
            out.append(
                SurveyEvent(
                    "drift",
                    float(t_all.min()),
                    float(t_all.max()),
                    size,
                    p,
                    {"rate_nT_per_h": float(coef[-1]) * 3600.0},
                )
            )
    return out


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


def survey_coupling(x: CrossoverSet, aux_a: np.ndarray, aux_b: np.ndarray) -> SurveyCoupling | None:
    """A channel (a current) that couples into the scalar reading by k nT per unit makes two
    crossing lines disagree by k (I_a - I_b) besides their heading levels: regressing the
    crossover differences on the channel's difference estimates k from the survey alone (k
    as the total field sees it, averaged over the headings)."""
    fit = _regress_on(x, np.asarray(aux_a, float) - np.asarray(aux_b, float))
    return None if fit is None else SurveyCoupling(*fit)


def survey_coupling_gain(x: CrossoverSet, aux_a: np.ndarray, aux_b: np.ndarray) -> HeldOut | None:
    """Does the channel's coupling predict crossovers it was not fitted on? Leave-one-out
    prediction errors of the crossover differences from the heading levels alone and from
    the levels plus the coupling (each crossover predicted by the fit to the others: the
    ordinary residual over one minus its leverage), compared pair by pair
    (:func:`pipeline.audit.evidence.paired_point_gain`). None: too few crossovers."""
    y = np.asarray(x.difference_nT, float)
    g = np.asarray(aux_a, float) - np.asarray(aux_b, float)
    full = np.column_stack([heading_levels(x), g])
    ok = np.all(np.isfinite(full), axis=1) & np.isfinite(y)
    full, y = full[ok], y[ok]
    if full.shape[0] < full.shape[1] + 4 or np.std(full[:, -1]) == 0:
        return None

    def loo_errors(a: np.ndarray) -> np.ndarray:
        q, _ = np.linalg.qr(a)
        h = np.sum(q**2, axis=1)  # leverages
        coef, *_ = np.linalg.lstsq(a, y, rcond=None)
        return (y - a @ coef) / np.clip(1.0 - h, 1e-9, None)

    return paired_point_gain(loo_errors(full[:, :-1]), loo_errors(full))


def _regress_on(
    x: CrossoverSet, g: np.ndarray
) -> tuple[float, tuple[float, float], float, int] | None:
    """Coefficient of ``g`` in crossover differences ~ heading levels + c g: estimate,
    95 % interval, two-sided p against 0, crossovers used."""
    y = np.asarray(x.difference_nT, float)
    a = np.column_stack([heading_levels(x), g])
    ok = np.all(np.isfinite(a), axis=1) & np.isfinite(y)
    a, y = a[ok], y[ok]
    n, k = a.shape
    if n < k + 4 or np.std(a[:, -1]) == 0:
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
