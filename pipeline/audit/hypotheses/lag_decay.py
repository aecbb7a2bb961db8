"""Decisions between a catalogue effect and a nuisance of the null model that mimics it.

A late sensor and eddy currents that decay with a time constant both leave a residual that
follows the attitude's rate of change. Physics separates them: a lag delays everything the
sensor sees (the permanent and induced interference's response to the attitude, the geology
along the lines, the field the fluxgate predicts), a decay delays only the eddy terms. With
the decay in the null model (its time constant chosen on held-out data), a true lag still
lowers the held-out residual, for the decay cannot delay the permanent and induced terms;
a decay mistaken for a lag does not. Where neither adds to the other on held-out data but
each alone explains the residual, the two are weighed as rivals in the forms the null
model would take them: the lag model (the whole reading delayed) against the decay model
(the decayed eddy columns beside T-L's); the one that predicts held-out calibration data
better by the audit's test is the explanation (held-out prediction weighs the decay's extra
coefficients). When neither wins, the
timing along the lines (survey crossovers, the fluxgate's record of the same anomalies)
decides when it holds the lag and excludes none, or joined with the calibration's
comparison (Fisher's method on the two independent p-values); otherwise the tie is
reported as an ambiguity and nothing is named for it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from scipy.stats import combine_pvalues, norm

from pipeline.audit.context import AuditContext
from pipeline.audit.evidence import HeldOut, significant
from pipeline.audit.evidence.lag import (
    decay_profile,
    fluxgate_timing,
    lag_estimate,
    lag_response,
)
from pipeline.audit.evidence.survey_side import lines_difference_nT
from pipeline.audit.extended import ModelSpec
from pipeline.audit.hypotheses.decay_rival import same_response, slower_than_lag
from pipeline.audit.result import Evaluation
from pipeline.audit.timing import TimingLag, combined_interval

LAG = "sensor_lag"
DECAY = "eddy_decay"


@dataclass
class LagVersusDecay:
    """The held-out comparisons between a lag and the null model's eddy decay.

    Attributes
    ----------
    lag_beyond_null : HeldOut
        The lag beside the null model with the decay in it.
    lag_alone : HeldOut or None
        The lag beside the null model without the decay (None when not weighed).
    decay_alone : HeldOut
        The decay beside the null model without it (the lag out as well).
    decay_beyond_lag : HeldOut
        The decay beside the null model without it plus the lag.
    lag_over_decay, decay_over_lag : HeldOut or None
        The lag model against the decay model (the null model's form), and the reverse
        (None when not weighed: no tie).
    """

    lag_beyond_null: HeldOut
    lag_alone: HeldOut | None  # None: not needed (the lag beats the null with the decay)
    decay_alone: HeldOut
    decay_beyond_lag: HeldOut
    lag_over_decay: HeldOut | None = None
    decay_over_lag: HeldOut | None = None

    def tie(self, alpha: float, min_gain: float) -> bool:
        """Whether each explains the residual alone and the decay adds nothing to the lag."""
        return (
            significant(self.lag_alone, alpha, min_gain)
            and significant(self.decay_alone, alpha, min_gain)
            and not significant(self.decay_beyond_lag, alpha, min_gain)
        )

    def lag_dominates(self, alpha: float, min_gain: float) -> bool:
        """Whether the lag explains what the decay does and more: it lowers held-out data
        beside the decay, and the decay adds nothing beside it."""
        return significant(self.lag_beyond_null, alpha, min_gain) and not significant(
            self.decay_beyond_lag, alpha, min_gain
        )

    def both_present(self, alpha: float, min_gain: float) -> bool:
        """Whether the calibration holds a late sensor's residual beside a decay that adds
        to it: the lag lowers held-out data beside the decay (p < ``alpha``, however
        little) or, the decay out, alone (p < ``alpha``, at least ``min_gain``: the decay
        beside it can take all of a true lag's residual), and the decay lowers them beside
        the lag (p < ``alpha``, at least ``min_gain``)."""
        lag_like = self.lag_beyond_null.p_value < alpha or significant(
            self.lag_alone, alpha, min_gain
        )
        return lag_like and significant(self.decay_beyond_lag, alpha, min_gain)

    def verdict(
        self, alpha: float, min_gain: float, timing: str, timing_p: float | None = None
    ) -> str:
        """``"lag"`` (named), ``"lag_beside_decay"`` (named, with the decay), ``"ambiguous"``
        (a tie the data cannot break) or ``"none"``.

        The lag is named when it lowers held-out data beside the decay. When both are there
        (:meth:`both_present`) but the lag's share of the calibration's residual beside
        the decay is under ``min_gain`` (a decay, fitted freely, takes part or all of a
        true lag's residual), that share does not measure what a late sensor does to a
        survey (a heading error of twice the lag times the along-track rate of change of
        the geology); the lines' timing does, and a decay of the eddy terms does not delay
        the lines: the lag is named beside the decay when the timing's one-sided p that
        the sensor is late (``timing_p``) is under ``alpha``. With no lag that p is
        uniform, so the rate stays within ``alpha``. When the two tie
        (each explains the residual alone, neither adds to the other) the rival that
        predicts held-out data better is the explanation
        (``lag_over_decay``, ``decay_over_lag``); when neither does, the timing along the
        lines decides: ``timing`` is ``"holds"`` (a significant timing lag whose interval holds
        the calibration's), ``"excludes"`` (the timing's interval lies below the lag: the
        sensor is not that late) or ``"silent"``.
        """
        if significant(self.lag_beyond_null, alpha, min_gain):
            return "lag"
        if self.both_present(alpha, min_gain) and timing_p is not None and timing_p < alpha:
            return "lag_beside_decay"
        if not self.tie(alpha, min_gain):
            return "none"
        if timing_p is not None:  # one test of the calibration and the lines together
            if significant(self.decay_over_lag, alpha, min_gain):
                return "none"
            return "lag" if lag_over_decay_with_timing(self, timing_p, alpha) else "ambiguous"
        if significant(self.lag_over_decay, alpha, min_gain):
            return "lag"
        if significant(self.decay_over_lag, alpha, min_gain) or timing == "excludes":
            return "none"
        return "lag" if timing == "holds" else "ambiguous"

    def ambiguity(self) -> dict[str, Any]:
        """The contract's record of the tie: ``{"candidates", "heldout_gain"}`` (fractions
        of the held-out RMS each removes alone, beside the null model without the other)."""
        return {
            "candidates": [LAG, DECAY],
            "heldout_gain": {
                LAG: self.lag_alone.reduction if self.lag_alone is not None else 0.0,
                DECAY: self.decay_alone.reduction,
            },
        }

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: each comparison's figures."""
        return {
            "lag_beyond_null": self.lag_beyond_null.to_dict(),
            "lag_alone": None if self.lag_alone is None else self.lag_alone.to_dict(),
            "decay_alone": self.decay_alone.to_dict(),
            "decay_beyond_lag": self.decay_beyond_lag.to_dict(),
            "lag_over_decay": None
            if self.lag_over_decay is None
            else self.lag_over_decay.to_dict(),
            "decay_over_lag": None
            if self.decay_over_lag is None
            else self.decay_over_lag.to_dict(),
        }


def lag_over_decay_with_timing(vs: LagVersusDecay, timing_p: float, alpha: float) -> bool:
    """Whether the calibration and the lines' timing together favour the lag over the decay.

    The two are independent data: held-out calibration blocks (which rival predicts the
    residual better) and the survey lines (whether the whole reading is delayed, which a
    decay of the eddy terms does not do). With the decay true and no lag, the first p is
    uniform or larger and the timing's one-sided p uniform, so Fisher's combination below
    ``alpha`` names a decay a lag at most at that rate. Both rivals already explain the
    residual by the least gain worth a term. A lag model that predicts the held-out
    calibration worse brings a p above one half into the combination, which the lines'
    timing must then outweigh; no further veto: the combination's level holds without one,
    and the calibration cannot tell a decay from a sensor filter of about its time constant,
    which the lines can.
    """
    h = vs.lag_over_decay
    if h is None:
        return False
    return float(combine_pvalues([h.p_value, timing_p], method="fisher").pvalue) < alpha


def timing_p_late(sl, tl) -> float | None:
    """One-sided p (normal) that the sensor reports late, from the inverse-variance
    combination of the lines' timing estimates (survey crossovers ``sl``, the fluxgate
    ``tl``; :func:`pipeline.audit.timing.combined_interval`); None without one."""
    both = combined_interval([o for o in (sl, tl) if o is not None])
    if both is None:
        return None
    lag, lo, hi = both
    return float(norm.sf(lag / ((hi - lo) / (2 * 1.959964))))


def recorded_fluxgate_timing(
    ctx: AuditContext, current: ModelSpec, ev: Evaluation
) -> TimingLag | None:
    """The fluxgate's timing along the lines (:func:`pipeline.audit.evidence.lag.fluxgate_timing`),
    recorded in ``ev.estimate``; None without it."""
    tl = fluxgate_timing(ctx, current)
    if tl is not None:
        ev.estimate.update(
            fluxgate_lag_s=tl.lag_s,
            fluxgate_lag_ci95_s=list(tl.ci95_s),
            fluxgate_lag_p_value=tl.p_value,
        )
        ev.ci95.update(fluxgate_lag_s=None, fluxgate_lag_ci95_s=None, fluxgate_lag_p_value=None)
    return tl


def timing_says(ctx: AuditContext, lag: float, sl, tl) -> str:
    """What the timing along the lines (survey crossovers ``sl``, the fluxgate ``tl``)
    says of a lag of ``lag`` s: ``"holds"`` (one is significant and its interval holds
    the lag), ``"excludes"`` (their combined interval lies below it) or ``"silent"``."""
    found = [o for o in (sl, tl) if o is not None]
    if any(o.p_value < ctx.s.alpha and o.ci95_s[0] <= lag <= o.ci95_s[1] for o in found):
        return "holds"
    both = combined_interval(found)
    return "excludes" if both is not None and both[2] < lag else "silent"


def lag_beside_decay_nuisance(
    ctx: AuditContext, ev: Evaluation, current: ModelSpec, fold_lags: dict[int, float], sl
) -> Evaluation:
    """The lag against the null model's eddy decay (:class:`LagVersusDecay`): named when
    it lowers held-out data beside the decay, or when the two tie and the timing along the
    lines holds it; a tie the timing cannot break is an ambiguity (``ctx.ambiguities``)
    and nothing is named."""
    s = ctx.s
    smallest = s.min_lag_s
    tl = recorded_fluxgate_timing(ctx, current, ev)
    # the lag's rival model holds no decay, and its response form is a nuisance of that
    # model: chosen beside the decay, a sensor filter of about the decay's time constant
    # reads as a delay (the decay took its shape) and the lag alone is judged in the
    # wrong form
    plain = current.with_(eddy_tau_s=0.0)
    plain = plain.with_(lag_response=lag_response(ctx, plain)[0])
    lag_plain = lag_estimate(ctx, plain, None, "all")
    plain_fold_lags: dict[int, float] = {}

    def lag_model(train, k):
        """The whole reading delayed, its lag estimated on fold ``k``'s training epochs
        (once: the held-out tests and the interval below share it)."""
        if k not in plain_fold_lags:
            plain_fold_lags[k] = lag_estimate(ctx, plain, train, f"plain{k}")
        return plain.with_(lag_s=plain_fold_lags[k])

    current, lagged, fold_lags = _profiled_decay(ctx, ev, current, fold_lags)
    lag = float(ev.estimate["lag_s"])
    ev.test = ctx._lag_profile_test(lagged, lag)
    decay_alone = ctx.heldout(plain, lambda train, k: current)
    decay_beyond = ctx.heldout(
        plain.with_(lag_s=lag_plain), lambda train, k: lagged.with_(lag_s=fold_lags[k])
    )
    lag_alone = None
    if not (ev.heldout.p_value < s.alpha and ev.heldout.reduction >= s.min_gain):
        lag_alone = ctx.heldout(plain, lag_model)
    vs = LagVersusDecay(ev.heldout, lag_alone, decay_alone, decay_beyond)
    if vs.tie(s.alpha, s.min_gain):
        # the rivals as the null model would take each: the whole reading delayed, or the
        # decayed eddy terms beside T-L's (held-out data weigh their sizes)
        vs.lag_over_decay = ctx.heldout(current, lag_model)
        vs.decay_over_lag = ctx.heldout(lag_model, lambda train, k: current)
    timing = timing_says(ctx, lag_plain, sl, tl)
    verdict = vs.verdict(s.alpha, s.min_gain, timing, timing_p_late(sl, tl))
    tau = current.eddy_tau_s
    ev.estimate["eddy_decay"] = {"tau_s": tau, "alone": decay_alone.to_dict()}
    ev.estimate["against_eddy_decay"] = {"verdict": verdict, **vs.to_dict()}
    ev.ci95.update(eddy_decay=None, against_eddy_decay=None)
    ctx.ambiguities = [a for a in ctx.ambiguities if "sensor_lag" not in a["candidates"]]
    if abs(lag_plain) < smallest and abs(lag) < smallest:
        verdict = "none"
    named_plain = False  # whether the lag named is the whole reading's (lag_plain)
    if verdict == "lag" and vs.lag_dominates(s.alpha, s.min_gain):
        _lag_in_place_of_decay(ctx, ev, plain, lag_plain)
        took_the_place_of(ev, tau)
        named_plain = True
    elif verdict == "lag" and lag_alone is not None:  # the tie, broken
        by_physics = significant(vs.lag_over_decay, s.alpha, s.min_gain)
        _lag_breaks_the_tie(ev, plain.with_(lag_s=lag_plain), lag_alone, by_physics, timing)
        took_the_place_of(ev, tau)
        named_plain = True
    elif verdict == "lag_beside_decay":
        _lag_timed_beside_decay(ev)
        named_plain = _lag_of_the_whole_reading(ev, lagged, lag_plain)
    elif verdict == "lag" and timing_says(ctx, lag, sl, tl) == "holds":
        # the lines' timing (what a late sensor delays and a decay does not) confirms it
        ev.estimate["confirmed_by"] = "the timing along the lines"
        ev.decided_outside = True
        named_plain = _lag_of_the_whole_reading(ev, lagged, lag_plain)
    elif verdict == "lag":
        named_plain = _lag_of_the_whole_reading(ev, lagged, lag_plain)
    elif verdict in ("ambiguous", "none"):
        _held_back(ctx, ev, verdict, vs, tau, lag_plain, (current, plain.with_(lag_s=lag_plain)))
    if named_plain:  # the whole reading's delay, estimated without the decay
        ev.estimated_in = plain
    _unresolved(ev, smallest)
    return ev


# the estimate's key of the null model's eddy decay time constant (s) a lag was named in
# place of (:func:`took_the_place_of`)
IN_PLACE_OF_DECAY = "in_place_of_eddy_decay_tau_s"


def took_the_place_of(ev: Evaluation, tau_s: float) -> None:
    """Record that the lag named by ``ev`` takes the place of the null model's eddy decay
    (time constant ``tau_s``, s): its model holds no decay, so the model without the lag
    is the null model with its decay (:func:`pipeline.audit.hypotheses.without`), and a
    re-test of the lag (refine) faces the same null model as the test that named it."""
    ev.estimate[IN_PLACE_OF_DECAY] = float(tau_s)
    ev.ci95[IN_PLACE_OF_DECAY] = None


def _held_back(
    ctx: AuditContext,
    ev: Evaluation,
    verdict: str,
    vs: LagVersusDecay,
    tau_s: float,
    lag_plain_s: float,
    rivals: tuple[ModelSpec, ModelSpec],
) -> None:
    """Hold the lag back on the verdict ``"ambiguous"`` (recorded in ``ctx.ambiguities``,
    with how much the lines' field depends on which of the ``rivals`` holds: the decay's
    model and the lag's) or ``"none"``, saying why."""
    ev.held_back = True
    if verdict == "ambiguous":
        ev.reason = (
            f"eddy currents decaying over {tau_s:.3g} s and a lag of {lag_plain_s:.3f} s "
            "each explain the calibration's residual and neither adds to the other; the "
            "timing along the lines does not decide: an ambiguity, nothing named"
        )
        ctx.ambiguities.append(
            {**vs.ambiguity(), "survey_difference_nT": lines_difference_nT(ctx, *rivals)}
        )
    else:
        ev.reason = (
            f"beside eddy currents decaying over {tau_s:.3g} s the lag lowers held-out data "
            f"by {100 * ev.heldout.reduction:.1f} % (p {ev.heldout.p_value:.2g}): not a "
            "late sensor"
        )


def _unresolved(ev: Evaluation, smallest_s: float) -> None:
    """Hold back a lag named beside a slower decay (which keeps the lag beside it, not the
    whole reading's delay) that is under ``smallest_s`` (``min_lag_s``): within the
    resampling's own error, whatever the delay without the decay was."""
    named = float(ev.estimate["lag_s"])
    if not ev.held_back and abs(named) < smallest_s:
        ev.held_back = True
        ev.reason = (
            f"the lag named beside the decay, {1e3 * named:.1f} ms, is under "
            f"{1e3 * smallest_s:.0f} ms (min_lag_s): within the resampling's own error, "
            "not a lag to model"
        )


def _lag_breaks_the_tie(
    ev: Evaluation, lag_model: ModelSpec, lag_alone: HeldOut, by_physics: bool, timing: str
) -> None:
    """Name the lag of ``lag_model`` (no decay) where it and the decay tied: decided by the
    rivals' held-out comparison (``by_physics``) or the lines' timing."""
    lag_plain = lag_model.lag_s
    ev.estimate.update(
        lag_s=lag_plain,
        confirmed_by="the lag model over the decay model"
        if by_physics
        else "the timing along the lines"
        if timing == "holds"
        else "the lag model over the decay model with the timing along the lines",
    )
    ev.heldout, ev.spec, ev.decided_outside = lag_alone, lag_model, True


def _lag_timed_beside_decay(ev: Evaluation) -> None:
    """Name the lag beside the null's decay on the lines' timing (the verdict
    ``"lag_beside_decay"``): decided outside the calibration."""
    ev.estimate["confirmed_by"] = "the timing along the lines, beside the eddy decay"
    ev.decided_outside = True


def _profiled_decay(
    ctx: AuditContext, ev: Evaluation, current: ModelSpec, fold_lags: dict[int, float]
) -> tuple[ModelSpec, ModelSpec, dict[int, float]]:
    """The decay's time constant profiled under each hypothesis
    (:func:`pipeline.audit.evidence.lag.decay_profile`): the null model without a lag (the
    null's own time constant or the one that fits best without a lag, whichever predicts
    held-out data better) and the decay beside the lag. When either moves, the lag's
    held-out test and estimate (``ev.heldout``, ``ev.estimate["lag_s"]``, ``ev.spec``) are
    those of the lag with its decay against the null with its own. Returns the null model,
    the decay the lag is judged beside (``lag_s`` 0) and the lag of each training fold."""
    tau0, tau1, lag = decay_profile(ctx, current)
    null = current
    if tau0 != current.eddy_tau_s:
        other = current.with_(eddy_tau_s=tau0)
        if ctx.heldout(current, lambda train, k: other).reduction > 0:
            null = other
    lagged = current.with_(eddy_tau_s=tau1)
    if null is current and tau1 == current.eddy_tau_s:
        return current, lagged, fold_lags
    ev.estimate["eddy_decay_beside_lag_tau_s"] = tau1
    ev.ci95["eddy_decay_beside_lag_tau_s"] = None
    if tau1 == current.eddy_tau_s:  # the lag's model as it was: only the null moves
        ev.heldout = ctx.heldout(null, lambda train, k: lagged.with_(lag_s=fold_lags[k]))
        return null, lagged, fold_lags
    lags: dict[int, float] = {}

    def ext_for(train, k):
        lags[k] = lag_estimate(ctx, lagged, train, f"decay{tau1:.3g}fold{k}")
        return lagged.with_(lag_s=lags[k])

    ev.heldout = ctx.heldout(null, ext_for)
    ev.estimate.update(lag_s=lag, lag_by_fold_s=[lags[k] for k in sorted(lags)])
    ev.spec, ev.estimated_in = lagged.with_(lag_s=lag), lagged
    return null, lagged, lags


def _lag_of_the_whole_reading(ev: Evaluation, lagged: ModelSpec, lag_plain_s: float) -> bool:
    """A lag named beside a decay, which stays: unless the decay is slower than the whole
    reading's delay (:func:`slower_than_lag`, not :func:`same_response`), its size is the
    delay of the whole reading, measured without the decay (``lag_plain_s``), and the
    decay's coefficients are refitted at that lag.
    Beside a decay with about the lag's time constant the decayed eddy columns reproduce
    the lag's effect on the eddy terms and part of it on the induced ones, so the lag left
    beside them is what the other columns cannot take, drawn toward zero by any
    interference outside the model; the lag on the lines (the geology's delay) is the
    whole reading's. A slower decay is the carrier's own and leaves the lag its response.
    The lag beside the decay is kept as ``lag_beside_decay_s``.
    Returns whether the lag named is now the whole reading's."""
    lag = float(ev.estimate["lag_s"])
    tau = lagged.eddy_tau_s
    if slower_than_lag(tau, lag_plain_s) and not same_response(tau, lag_plain_s):
        return False
    ev.estimate.update(lag_s=lag_plain_s, lag_beside_decay_s=lag)
    ev.spec = lagged.with_(lag_s=lag_plain_s)
    ev.ci95["lag_beside_decay_s"] = None
    return True


def _lag_in_place_of_decay(
    ctx: AuditContext, ev: Evaluation, plain: ModelSpec, lag_s: float
) -> None:
    """The lag takes the null model's eddy decay's place: it lowers held-out data beside
    the decay and the decay adds nothing beside it, so the null model the data support
    with a late sensor holds no decay; the lag is tested (nested F, held out) and
    estimated against that null model."""
    ev.test = ctx._lag_profile_test(plain, lag_s)
    ev.heldout = ctx.heldout(
        plain, lambda train, k: plain.with_(lag_s=lag_estimate(ctx, plain, train, f"fold{k}"))
    )
    ev.spec = plain.with_(lag_s=lag_s)
    ev.estimate.update(lag_s=lag_s, replaces="eddy_decay")
