"""The lag estimator: the lag minimising the refitted model's calibration residual, per response
form and beside eddy currents that decay; and the fluxgate's timing along the lines."""

from __future__ import annotations

from functools import partial

import numpy as np
from scipy.optimize import minimize_scalar

from pipeline.audit.context import AuditContext
from pipeline.audit.crossval import jackknife_ci95, widest_ci95
from pipeline.audit.extended import LAG_RESPONSES, ModelSpec, lag_cost
from pipeline.audit.timing import TimingLag, timing_lag

# eddy currents' decay times tried (s): a carrier skin's L/R from a sample to well past
# the manoeuvres' shortest periods
EDDY_TAU_GRID_S = (0.05, 0.1, 0.2, 0.3, 0.5, 0.7, 1.0, 1.5)


def lag_estimate(ctx: AuditContext, current: ModelSpec, keep: np.ndarray | None, key: str) -> float:
    """The lag minimising the refitted model's residual (see :func:`lag_fit`)."""
    return lag_fit(ctx, current, keep, key)[0]


def lag_fit(
    ctx: AuditContext, current: ModelSpec, keep: np.ndarray | None, key: str
) -> tuple[float, float]:
    """(lag s, residual RMS nT at it): a coarse grid over +-``max_lag_s`` (the eddy
    terms absorb part of a lag, so a linearised estimate with the baseline's
    coefficients is biased low), then a bounded 1-D refinement. (0, inf) when the
    calibration is too short to refit. Kept per model and ``key`` (which names ``keep``,
    as for :meth:`AuditContext.fit`): the held-out tests of several hypotheses ask for the
    same fold's lag."""
    ck = (current, key)
    if ck not in ctx.lag_fits:
        costs = _lag_costs(ctx, current, keep, key)
        ctx.lag_fits[ck] = (
            (0.0, np.inf) if costs is None else _least_cost(costs, _span(ctx, current))
        )
    return ctx.lag_fits[ck]


def _lag_costs(ctx: AuditContext, spec: ModelSpec, keep: np.ndarray | None, key: str):
    """:func:`pipeline.audit.extended.lag_cost` of ``spec`` on the calibration (``keep``:
    a fold's training epochs), or None when it is too short to refit."""
    # the L-curve's lambda even in a fold: with cross-validation's (often tiny) lambda
    # the eddy terms absorb part of the lag and bias it low. And the lambda of the model at
    # its own lag: at ``spec``'s, a late sensor's misfit moves the L-curve's corner, and
    # the coefficients shrunk by it leave a residual at the true lag that other columns
    # (a decay) take up, moving the lag with them
    lam = ctx.fit(spec, keep, key, ridge="auto").lambda_
    try:
        costs = lag_cost(
            ctx.data,
            spec,
            ctx.mask,
            ctx.s.band,
            lam,
            ctx.s.max_lag_s,
            keep=keep,
            like=ctx.rows(spec),
        )
        lag = _least_cost(costs, _span(ctx, spec))[0]
        at_lag = spec.with_(lag_s=lag)
        if at_lag == spec:
            return costs
        # the same rows and decomposition, solved at the other lambda
        return partial(costs, ridge_lambda=ctx.fit(at_lag, keep, key, ridge="auto").lambda_)
    except ValueError:
        return None


def _span(ctx: AuditContext, spec: ModelSpec) -> tuple[float, float, float, float]:
    """How the lag of ``spec`` is searched: (low s, high s, grid step s, tolerance s).
    A delay: +-``max_lag_s`` every 0.05 s (a clock may run early; a re-timed record's cost
    has a minimum per manoeuvre period) to 0.1 ms. A sensor filter: 0 to ``max_lag_s``
    every 0.1 s (its time constant is positive; its cost, a filter's gain and phase, varies
    slowly with it) to 0.5 ms, a tenth of the smallest lag that matters (``min_lag_s``):
    each of its costs refits the model on filtered rows."""
    if spec.lag_response == "first_order":
        return 0.0, ctx.s.max_lag_s, 0.1, 5e-4
    return -ctx.s.max_lag_s, ctx.s.max_lag_s, 0.05, 1e-4


def lag_interval(ctx: AuditContext, spec: ModelSpec, lag_s: float) -> list[float] | None:
    """The 95 % interval (s) of the lag ``lag_s`` estimated in ``spec`` (its lag 0): the
    widest of the delete-a-group jackknives (:func:`pipeline.audit.crossval.jackknife_ci95`)
    over :meth:`AuditContext.jackknife_groups`, the lag re-estimated without each kind of
    manoeuvre and without each heading: a late sensor delays its response to every one
    alike, interference the model does not hold (eddy currents that decay, second-order
    induced terms, an unrecorded current) reads as a different lag in each. None when a
    group's refit fails."""
    low, high, step, tolerance = _span(ctx, spec)
    near = (max(low, lag_s - 2 * step), min(high, lag_s + 2 * step), step, tolerance)
    cis = []
    for groups in ctx.jackknife_groups():
        lags = []
        for keep, key in groups:
            costs = _lag_costs(ctx, spec, keep, key)
            if costs is None:
                return None
            # each group's lag lies near the whole calibration's: searched around it
            lags.append({"lag_s": _least_cost(costs, near)[0]})
        cis.append(jackknife_ci95({"lag_s": lag_s}, lags))
    return widest_ci95(cis)["lag_s"]


def _least_cost(costs, span: tuple[float, float, float, float]) -> tuple[float, float]:
    """(lag s, cost) at the least of ``costs`` (a function of an array of lags): a grid
    over ``span`` (low s, high s, step s), then a bounded 1-D refinement to its tolerance
    (s)."""

    def cost(tau: float) -> float:
        return float(costs(np.array([tau]))[0])

    low, high, step, tolerance = span
    grid = np.arange(low, high + step / 2, step)
    best = float(grid[int(np.argmin(costs(grid)))])
    res = minimize_scalar(
        cost,
        bounds=(max(best - step, low), best + step),
        method="bounded",
        options={"xatol": tolerance},
    )
    return float(res.x), float(res.fun)


def decay_profile(ctx: AuditContext, current: ModelSpec) -> tuple[float, float, float]:
    """The eddy decay's time constant (s) each hypothesis takes in the audit's model form
    (decayed eddy columns beside T-L's): without a lag, and beside the lag that fits best
    with it, and that lag (s, on all calibration data); on :data:`EDDY_TAU_GRID_S` and
    ``current``'s own, every candidate on the same calibration rows. The null model's time
    constant was chosen without a lag, so a late sensor's response is in it; with the lag in
    the model the decay keeps only the carrier's own (a likelihood ratio profiles the
    nuisance under each hypothesis). Without a usable candidate: ``current``'s, lag 0."""
    taus = sorted(set(EDDY_TAU_GRID_S) | {current.eddy_tau_s})
    without, beside = {}, {}
    for tau in taus:
        costs = _lag_costs(ctx, current.with_(eddy_tau_s=tau, lag_s=0.0), None, "all")
        if costs is not None:
            without[tau] = float(costs(np.array([0.0]))[0])
            beside[tau] = _least_cost(costs, _span(ctx, current))
    if not without:
        return current.eddy_tau_s, current.eddy_tau_s, 0.0
    tau1 = _refined_beside(ctx, current, taus, beside)
    return min(without, key=without.get), tau1, beside[tau1][0]


def _refined_beside(
    ctx: AuditContext, current: ModelSpec, taus: list[float], beside: dict
) -> float:
    """The time constant (s) with the least cost beside its best lag: the grid's best,
    refined by a bounded search in log tau between its neighbours. The grid's steps (up to
    a factor of two) leave a mismatched decay part of its field, and the lag beside it
    takes that up. ``beside`` (tau -> (lag, cost)) gains the points searched."""
    best = min(beside, key=lambda tau: beside[tau][1])
    i = taus.index(best)
    lo, hi = taus[max(i - 1, 0)], taus[min(i + 1, len(taus) - 1)]
    if not 0.0 < lo < hi:
        return best

    def cost(log_tau: float) -> float:
        tau = float(np.exp(log_tau))
        if tau not in beside:
            costs = _lag_costs(ctx, current.with_(eddy_tau_s=tau, lag_s=0.0), None, "all")
            beside[tau] = (
                (0.0, np.inf) if costs is None else _least_cost(costs, _span(ctx, current))
            )
        return beside[tau][1]

    minimize_scalar(
        cost, bounds=(np.log(lo), np.log(hi)), method="bounded", options={"xatol": 0.05}
    )
    return min(beside, key=lambda tau: beside[tau][1])


def lag_response(ctx: AuditContext, current: ModelSpec) -> tuple[str, float, dict[str, float]]:
    """A pure delay or a first-order sensor filter: the response whose best lag leaves
    the smaller calibration residual (both have one parameter, so no penalty), and that
    lag (s) on all calibration data; beside them, the lag (s) every model form finds
    (each response, with and without eddy currents with a time constant), keyed
    ``<response>`` and ``<response>_eddy_rate``."""
    fits = {r: lag_fit(ctx, current.with_(lag_response=r), None, "all") for r in LAG_RESPONSES}
    best = min(LAG_RESPONSES, key=lambda r: fits[r][1])  # ties: the first, a delay
    forms = {}
    for r in LAG_RESPONSES:
        for rate in (False, True):
            spec = current.with_(lag_response=r, eddy_rate=rate)
            fit = fits[r] if rate == current.eddy_rate else lag_fit(ctx, spec, None, "all")
            forms[f"{r}_eddy_rate" if rate else r] = fit[0]
    return best, fits[best][0], forms


def lag_beside_eddy_decay(ctx: AuditContext, current: ModelSpec) -> dict[str, float]:
    """The lag (s) each response finds beside eddy currents decaying with the best time
    constant (:func:`eddy_decay_tau`), on all calibration data, keyed by response."""
    decay = current.with_(eddy_rate=False, eddy_tau_s=eddy_decay_tau(ctx, current))
    return {r: lag_estimate(ctx, decay.with_(lag_response=r), None, "all") for r in LAG_RESPONSES}


def eddy_decay_tau(ctx: AuditContext, current: ModelSpec) -> float:
    """The time constant (s) of decaying eddy currents (:func:`eddy_decay` columns beside
    the T-L ones) that leaves the smallest calibration residual, on
    :data:`EDDY_TAU_GRID_S` (the null model's, chosen on held-out data, when it has one)."""
    if current.eddy_tau_s > 0:
        return current.eddy_tau_s
    fits = {
        tau: ctx.fit(current.with_(eddy_tau_s=tau), None, "all", ridge="auto")
        for tau in EDDY_TAU_GRID_S
    }
    return min(fits, key=lambda tau: fits[tau].fit_residual_nT)


def fluxgate_timing(ctx: AuditContext, current: ModelSpec) -> TimingLag | None:
    """The lag the fluxgate's record along the lines gives against ``current``'s compensated
    field (:func:`pipeline.audit.timing.timing_lag`); None without it."""
    return timing_lag(
        ctx.data.time_s,
        ctx.compensated(current),
        ctx.data.vector_nT,
        ctx.seg.mask("survey", "tie", "validation"),
        ctx.data.rate_hz,
        ctx.s.max_lag_s,
    )
