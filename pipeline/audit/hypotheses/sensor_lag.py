"""The sensor lag candidate: a late scalar sensor (a delay or a first-order filter), weighed
against eddy currents with a time constant and judged by the timing along the lines (rules
L0-L9 of docs/audit.md)."""

from __future__ import annotations

from typing import Any

import numpy as np

from pipeline.audit.context import AuditContext
from pipeline.audit.evidence.lag import (
    lag_beside_eddy_decay,
    lag_estimate,
    lag_interval,
    lag_response,
)
from pipeline.audit.evidence.survey_side import crossover_lag, lines_difference_nT
from pipeline.audit.extended import ModelSpec, design
from pipeline.audit.hypotheses.decay_rival import (
    decay_explains_lag,
    lag_adds_to_decay,
    lag_beyond_eddy_decay,
    lag_over_eddy_decay,
    slower_than_lag,
)
from pipeline.audit.hypotheses.lag_decay import (
    lag_beside_decay_nuisance,
    recorded_fluxgate_timing,
    timing_says,
)
from pipeline.audit.hypotheses.rival import beyond
from pipeline.audit.result import Evaluation
from pipeline.audit.timing import combined_interval

EFFECT = "sensor_lag"


def keys(ctx: AuditContext, current: ModelSpec) -> list[str]:
    """The candidate when ``current`` has no lag."""
    return [] if current.lag_s else [EFFECT]


def without(spec: ModelSpec, key: str) -> ModelSpec:
    """``spec`` with no lag (and the response form back to a delay)."""
    return spec.with_(lag_s=0.0, lag_response="delay")


def evaluate(ctx: AuditContext, current: ModelSpec, key: str) -> Evaluation:
    """A late scalar sensor: its lag and response form on the calibration
    (:func:`_on_the_calibration`), weighed against eddy currents that decay (the null model's,
    :func:`pipeline.audit.hypotheses.lag_decay.lag_beside_decay_nuisance`; else the eddy-rate
    columns and a fitted decay, :func:`_against_eddy_currents`), then against the timing
    along the lines (:func:`_by_the_timing`)."""
    ev, current, lags, sl, forms, beside_decay = _on_the_calibration(ctx, current, key)
    if current.eddy_tau_s > 0:  # the null model holds eddy currents that decay
        ev = lag_beside_decay_nuisance(ctx, ev, current, lags, sl)
    else:
        decay_as_well, beside_a_decay = _against_eddy_currents(
            ctx, ev, current, lags, forms, beside_decay
        )
        tl = _by_the_timing(ctx, ev, current, sl, decay_as_well, beside_a_decay, beside_decay)
        _untimed_tie(ctx, ev, current, sl, tl, decay_as_well)
    if not ev.held_back and ev.estimated_in is not None:
        ev.ci95["lag_s"] = lag_interval(ctx, ev.estimated_in, float(ev.estimate["lag_s"]))
    return ev


def _on_the_calibration(
    ctx: AuditContext, current: ModelSpec, key: str
) -> tuple[Evaluation, ModelSpec, dict[int, float], Any, dict[str, float], dict[str, float]]:
    """The lag's tests and estimates on the calibration (the response form the flight's,
    chosen once on all calibration data), with the survey crossovers' lag beside them.

    Returns the evaluation, ``current`` with the response form, the lag of each training
    fold, the crossovers' lag (or None), the lag of every model form and
    the lag beside eddy currents decaying with their best time constant (by response)."""
    response, lag, forms = lag_response(ctx, current)
    current = current.with_(lag_response=response)
    des = design(ctx.data, current)
    dy = np.gradient(des.y, ctx.data.time_s)
    test = ctx._nested(current, extra=dy[:, None])
    lags = {}

    def ext_for(train, k):
        lags[k] = lag_estimate(ctx, current, train, f"fold{k}")
        return current.with_(lag_s=lags[k])

    held = ctx.heldout(current, ext_for)
    # the competing cause of a lag-like residual: eddy currents with a time constant
    # (the carrier's, not the sensor's); a late sensor delays its whole reading, which
    # the extra eddy columns cannot mimic (checked in beyond)
    est = {
        "lag_s": lag,
        "response": current.lag_response,
        "lag_by_fold_s": [lags[k] for k in sorted(lags)],
    }
    sl = crossover_lag(ctx, current)
    if sl is not None:  # independent evidence: the survey's crossovers
        est.update(
            survey_lag_s=sl.lag_s,
            survey_lag_ci95_s=list(sl.ci95_s),
            survey_lag_p_value=sl.p_value,
        )
    # what every model form reads (a delay or a sensor filter; eddy currents that decay or
    # not), and the lag beside eddy currents that decay with their best time constant
    est["lag_by_model_form_s"] = forms
    beside_decay = lag_beside_eddy_decay(ctx, current)
    est["lag_beside_eddy_decay_s"] = beside_decay
    ev = Evaluation(
        "sensor_lag",
        key,
        est,
        test,
        held,
        current.with_(lag_s=lag),
        ci95={k: None for k in est},
        estimated_in=current,
    )
    return ev, current, lags, sl, forms, beside_decay


def _against_eddy_currents(
    ctx: AuditContext,
    ev: Evaluation,
    current: ModelSpec,
    lags: dict[int, float],
    forms: dict[str, float],
    beside_decay: dict[str, float],
) -> tuple[bool, bool]:
    """Weigh the lag against eddy currents with a time constant (the eddy-rate columns,
    then a fitted decay), releasing or holding ``ev`` back. Returns whether a decay
    explains the calibration as well as the lag (a tie for the timing along the lines to
    break), and whether the lag was released beside a decay."""
    lag, held = float(ev.estimate["lag_s"]), ev.heldout
    beyond(
        ctx,
        ev,
        current.with_(eddy_rate=True),
        current.with_(eddy_rate=True, lag_s=lag),
        "eddy currents with a time constant",
        "a late sensor",
    )
    # only a lag every model form agrees on, each at least what the sampling resolves
    # (decaying eddy currents read as a small delay alone, as none beside the rate
    # columns); or a lag that eddy currents decaying with their best time constant, the
    # rate columns' whole form, leave in one response at least: the rate columns' nine
    # free coefficients also take up a true lag
    smallest = ctx.s.min_lag_s
    beside_most = max(beside_decay.values())
    decay_as_well = False
    if (
        ev.held_back
        and not current.eddy_rate
        and abs(lag) >= smallest
        and (min(forms.values()) > smallest or beside_most >= smallest)
    ):
        decay_as_well = lag_over_eddy_decay(ctx, ev, current, held, lags, lag)
    elif not ev.held_back and not current.eddy_rate and not current.eddy_tau_s:
        decay_as_well = decay_explains_lag(ctx, ev, current, held)
    # a decay no slower than the lag is the sensor's own first-order response, no rival
    # cause: there is no tie for the timing along the lines to break
    if decay_as_well and not slower_than_lag(ev.estimate["eddy_decay"]["tau_s"], lag):
        decay_as_well = False
    beside_decay_least = min(beside_decay.values())
    beside_a_decay = False
    if (
        ev.held_back
        and not current.eddy_rate
        and not current.eddy_tau_s
        and abs(lag) >= smallest
        and beside_decay_least >= smallest
    ):
        beside_a_decay = lag_beyond_eddy_decay(ctx, ev, current)
    return decay_as_well, beside_a_decay


def _by_the_timing(
    ctx: AuditContext,
    ev: Evaluation,
    current: ModelSpec,
    sl: Any,
    decay_as_well: bool,
    beside_a_decay: bool,
    beside_decay: dict[str, float],
) -> Any:
    """The timing along the lines (survey crossovers ``sl``, the fluxgate's record) on the
    lag: it releases a lag held back when it holds it, holds back a
    tie with a decay when it says the scalar is not late; and a lag under ``min_lag_s`` is
    held back. Returns the fluxgate's timing (None without it)."""
    lag, smallest = float(ev.estimate["lag_s"]), ctx.s.min_lag_s
    beside_most = max(beside_decay.values())
    tl = recorded_fluxgate_timing(ctx, current, ev)
    # the calibration cannot tell the two apart, the survey can: eddy currents do not
    # move anomalies along track, a late sensor does (against the crossovers, and
    # against the fluxgate's record of the same anomalies)
    for name, other in (("survey crossovers", sl), ("the fluxgate along the lines", tl)):
        if (
            ev.held_back
            and other is not None
            and other.p_value < ctx.s.alpha
            and other.ci95_s[0] <= lag <= other.ci95_s[1]
        ):
            ev.held_back = False
            ev.reason = ""
            ev.estimate["confirmed_by"] = name
    # the calibration cannot tell a late sensor from eddy currents that decay: the
    # timing along the lines breaks the tie when it says the scalar is not late at all:
    # below zero, not merely below the calibration's lag (whose forms can read a true
    # lag high), and only when neither timing's interval holds the lag (one timing can be
    # far off on a small survey)
    timing = combined_interval([o for o in (sl, tl) if o is not None])
    holds_lag = any(o.ci95_s[0] <= lag <= o.ci95_s[1] for o in (sl, tl) if o is not None)
    if (
        (decay_as_well or beside_a_decay)
        and timing is not None
        and timing[2] < 0.0
        and not holds_lag
    ):
        ev.held_back = True
        ev.reason = (
            f"eddy currents that decay with a time constant explain the calibration's "
            f"residual as well as a lag, and the timing along the lines puts the lag at "
            f"{timing[0]:.3f} s [{timing[1]:.3f}, {timing[2]:.3f}]: the scalar sensor is "
            "not late"
        )
    # nor is it late when the decay leaves the lag, refitted beside it, nothing the
    # sampling resolves, unless the timing along the lines says it is late (a true lag
    # keeps a resolvable part of itself beside a slower decay)
    if (
        decay_as_well
        and not ev.held_back
        and beside_most < smallest
        and not (timing is not None and timing[1] > 0.0)
    ):
        ev.held_back = True
        ev.reason = (
            f"eddy currents that decay over {ev.estimate['eddy_decay']['tau_s']:g} s "
            f"explain the calibration's residual as well as a lag, and beside them the lag "
            f"is {1e3 * beside_most:.1f} ms, under {1e3 * smallest:.0f} ms: the decay "
            "is the cause"
        )
    if abs(lag) < smallest:
        ev.held_back = True
        ev.reason = (
            f"a lag of {1e3 * lag:.1f} ms is under {1e3 * smallest:.0f} ms (min_lag_s): "
            "within the resampling's own error, not a lag to model"
        )
    return tl


def _untimed_tie(
    ctx: AuditContext, ev: Evaluation, current: ModelSpec, sl: Any, tl: Any, decay_as_well: bool
) -> None:
    """A tie the timing along the lines does not break is an ambiguity, and nothing is
    named: eddy currents decaying with a time constant explain the calibration as well as
    the lag (``decay_as_well``), the lag refitted beside them adds nothing on held-out
    data, and neither timing along the lines (crossovers ``sl``, fluxgate ``tl``) holds the
    lag. As beside the null model's own decay
    (:func:`pipeline.audit.hypotheses.lag_decay.lag_beside_decay_nuisance`): the calibration
    cannot tell the two apart, and a tie given to either is a coin flip."""
    if ev.held_back or not decay_as_well:
        return
    lag = float(ev.estimate["lag_s"])
    if timing_says(ctx, lag, sl, tl) == "holds":
        return
    if lag_adds_to_decay(ctx, ev, current):
        return
    weighed = ev.estimate["eddy_decay"]
    ev.held_back = True
    ev.reason = (
        f"eddy currents decaying over {weighed['tau_s']:g} s explain the calibration's "
        f"residual as well as a lag of {lag:.3f} s, the lag adds nothing beside them, and "
        "the timing along the lines does not hold the lag: an ambiguity, nothing named"
    )
    ctx.ambiguities = [a for a in ctx.ambiguities if EFFECT not in a["candidates"]]
    ctx.ambiguities.append(
        {
            "candidates": [EFFECT, "eddy_decay"],
            "heldout_gain": {
                EFFECT: float(ev.heldout.reduction),
                "eddy_decay": weighed["alone"]["reduction_pct"] / 100.0,
            },
            "survey_difference_nT": lines_difference_nT(
                ctx, current.with_(lag_s=lag), current.with_(eddy_tau_s=weighed["tau_s"])
            ),
        }
    )
