"""The lag against eddy currents that decay, when the null model holds no decay.

The eddy-rate columns are the decay's first order in w tau: nine free coefficients that take
up a true lag as well as a decay. Where the null model holds no decaying eddy currents, a lag
held back by them is weighed against eddy currents decaying with the best-fitting time
constant (the alternative whole): the lag released when it predicts held-out calibration data
better than the decay, or adds to it; a tie marked for the timing along the lines to break
(:mod:`pipeline.audit.hypotheses.sensor_lag`). Every weighing is recorded in the finding's
``estimate["eddy_decay"]``. The lag beside a decay the null model already holds is
:mod:`pipeline.audit.hypotheses.lag_decay`'s.
"""

from __future__ import annotations

import numpy as np

from pipeline.audit.context import AuditContext
from pipeline.audit.evidence import HeldOut, significant
from pipeline.audit.evidence.lag import EDDY_TAU_GRID_S, eddy_decay_tau, lag_estimate
from pipeline.audit.extended import ModelSpec
from pipeline.audit.result import Evaluation

# a decay time constant within this ratio of a lag is the same first-order response
SAME_RESPONSE_RATIO = 1.5


def same_response(tau_s: float, lag_s: float) -> bool:
    """Whether eddy currents decaying with ``tau_s`` and a lag of ``lag_s`` are one
    first-order response: a sensor filter of tau and eddy currents decaying with tau
    differ in the calibration only beyond second order in w tau (the T-L eddy columns
    take the first order of either), while eddy currents that do decay read as a lag far
    shorter than their time constant."""
    return abs(np.log(tau_s / max(abs(lag_s), 1e-9))) <= np.log(SAME_RESPONSE_RATIO)


def slower_than_lag(tau_s: float, lag_s: float) -> bool:
    """Whether a decay time constant ``tau_s`` from :data:`EDDY_TAU_GRID_S` is slower
    than a lag of ``lag_s`` by more than the grid resolves: beyond the grid's first value
    at or above the lag (a decay on the grid step next to the lag can be the sensor's own
    first-order response)."""
    above = [g for g in EDDY_TAU_GRID_S if g >= abs(lag_s)]
    return bool(above) and tau_s > above[0]


def decay_explains_lag(
    ctx: AuditContext, ev: Evaluation, current: ModelSpec, held: HeldOut
) -> bool:
    """Whether eddy currents decaying with a fitted time constant predict held-out
    calibration data at least as well as the lag, and the lag, refitted beside them in
    each fold, adds nothing (recorded in ``ev.estimate["eddy_decay"]``).

    The eddy-rate columns are only the decay's first order in w tau: a slow decay can
    pass that test as a short lag. The calibration alone cannot settle it either way
    (a true lag and a decay leave about the same held-out residual), so this only
    marks the tie for the timing along the lines to break. The lag is refitted beside
    the decay because the decay's columns absorb part of it.
    """
    alone, adds = _weigh_lag_beyond_eddy_decay(ctx, ev, current)
    return alone.rms_after_nT <= held.rms_after_nT and not adds


def _weigh_lag_beyond_eddy_decay(
    ctx: AuditContext, ev: Evaluation, current: ModelSpec
) -> tuple[HeldOut, bool]:
    """:func:`_weigh_eddy_decay` of the lag, refitted in each training fold beside the
    decay, against the decay alone (under ``"lag_beyond_decay"``); weighed once per model
    (``ctx.lag_decay_weighings``), recorded in every ``ev`` that asks."""
    if current not in ctx.lag_decay_weighings:
        ctx.lag_decay_weighings[current] = _decay_weighing(
            ctx,
            current,
            lambda decay: decay,
            lambda decay, train, k: decay.with_(lag_s=lag_estimate(ctx, decay, train, f"decay{k}")),
        )
    tau, alone, beyond = ctx.lag_decay_weighings[current]
    _record_decay(ev, tau, alone, beyond, "lag_beyond_decay")
    return alone, significant(beyond, ctx.s.alpha, ctx.s.min_gain)


def lag_adds_to_decay(ctx: AuditContext, ev: Evaluation, current: ModelSpec) -> bool:
    """Whether the lag, refitted in each training fold beside eddy currents decaying with
    the best time constant, lowers held-out data beyond them (p < ``alpha``, at least
    ``min_gain``; :func:`_weigh_lag_beyond_eddy_decay`)."""
    return _weigh_lag_beyond_eddy_decay(ctx, ev, current)[1]


def _weigh_eddy_decay(
    ctx: AuditContext, ev: Evaluation, current: ModelSpec, before, after_for_fold, key: str
) -> tuple[HeldOut, bool]:
    """Eddy currents decaying with the best-fitting time constant against a lag: their
    held-out gain alone, and whether ``after_for_fold(decay, train, k)`` adds to
    ``before(decay)`` (p < alpha, by ``min_gain``); both go into
    ``ev.estimate["eddy_decay"]`` (the second under ``key``)."""
    tau, alone, beyond = _decay_weighing(ctx, current, before, after_for_fold)
    _record_decay(ev, tau, alone, beyond, key)
    return alone, significant(beyond, ctx.s.alpha, ctx.s.min_gain)


def _decay_weighing(
    ctx: AuditContext, current: ModelSpec, before, after_for_fold
) -> tuple[float, HeldOut, HeldOut]:
    """(tau s, the decay alone beside ``current``, ``after_for_fold(decay, train, k)``
    beside ``before(decay)``) for eddy currents decaying with the best time constant."""
    tau = eddy_decay_tau(ctx, current)
    decay = current.with_(eddy_tau_s=tau)
    alone = ctx.heldout(current, lambda train, k: decay)
    beyond = ctx.heldout(before(decay), lambda train, k: after_for_fold(decay, train, k))
    return tau, alone, beyond


def _record_decay(ev: Evaluation, tau: float, alone: HeldOut, beyond: HeldOut, key: str) -> None:
    """Record a weighing against the decay in ``ev.estimate["eddy_decay"]``."""
    ev.estimate.setdefault("eddy_decay", {}).update(
        {"tau_s": tau, "alone": alone.to_dict(), key: beyond.to_dict()}
    )
    ev.ci95["eddy_decay"] = None


def lag_beyond_eddy_decay(ctx: AuditContext, ev: Evaluation, current: ModelSpec) -> bool:
    """Release a lag held back by the eddy-rate alternative when it adds to eddy currents
    decaying with the best time constant (the lag refitted in each training fold; p <
    alpha and at least ``min_gain`` on held-out data): a late sensor beside a carrier
    whose eddy currents decay. Called only when the lag refitted beside that decay stays
    at least ``min_lag_s`` in every response (the decay does not take it).

    The eddy-rate columns are nine free coefficients, the decay's first order in w tau,
    and take up a true lag as well as the decay; the decay's columns with a fitted time
    constant are the alternative whole, and what the lag adds to them is the sensor's.
    """
    adds = _weigh_lag_beyond_eddy_decay(ctx, ev, current)[1]
    if adds:
        ev.held_back = False
        ev.reason = ""
        ev.estimate["beside"] = "eddy currents that decay with a time constant"
        ev.ci95["beside"] = None
    return adds


def lag_over_eddy_decay(
    ctx: AuditContext,
    ev: Evaluation,
    current: ModelSpec,
    held: HeldOut,
    fold_lags: dict[int, float],
    lag: float,
) -> bool:
    """Release a lag held back by the eddy-rate alternative when it predicts held-out data
    better than eddy currents that decay with a time constant, or they better it by less
    than ``min_gain`` or with the lag's own time constant (:func:`same_response`), and they
    add nothing beyond the lag. Returns whether the release was a tie: the lag does not
    predict held-out data better than the decay by the audit's test (p < ``alpha``, by
    ``min_gain``), for the timing along the lines to break or an ambiguity
    (:func:`pipeline.audit.hypotheses.sensor_lag`'s ``_untimed_tie``, as in
    :func:`decay_explains_lag`).

    The eddy-rate columns are the decay's first order in w tau; on a multicopter's brisk
    manoeuvres they mimic a true lag about as well as the lag itself, so that test cannot
    decide. Decaying eddy columns with a fitted time constant can: they add nothing
    beyond a true lag, and predict slowly decaying eddy currents better than a lag does.
    A sensor filter and a decay with about its time constant are one response.
    """
    alone, adds = _weigh_eddy_decay(
        ctx,
        ev,
        current,
        lambda decay: current.with_(lag_s=lag),
        lambda decay, train, k: decay.with_(lag_s=fold_lags[k]),
        "beyond_lag",
    )
    # the decay not better than the lag by min_gain, or with the lag's own time constant
    # (one response, :func:`same_response`): the lag wins, a tie if not outright
    better = alone.rms_after_nT < (1 - ctx.s.min_gain) * held.rms_after_nT
    same = same_response(ev.estimate["eddy_decay"]["tau_s"], lag)
    if (not better or same) and not adds:
        ev.held_back = False
        ev.reason = ""
        ev.estimate["preferred_over"] = "eddy currents that decay with a time constant"
        ev.ci95["preferred_over"] = None
        decay = current.with_(eddy_tau_s=ev.estimate["eddy_decay"]["tau_s"])
        over = ctx.heldout(decay, lambda train, k: current.with_(lag_s=fold_lags[k]))
        ev.estimate["eddy_decay"]["lag_over_decay"] = over.to_dict()
        return not significant(over, ctx.s.alpha, ctx.s.min_gain)
    return False
