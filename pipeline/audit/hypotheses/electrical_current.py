"""The electrical current candidate: an auxiliary channel's current coupling into the reading
(three body-frame columns), with the survey's crossovers and the channel's switches as evidence
outside the calibration (rules C1-C5 of docs/audit.md)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import stats

from pipeline.audit.context import AuditContext
from pipeline.audit.crossval import jackknife_ci95, widest_ci95
from pipeline.audit.evidence import HeldOut, significant
from pipeline.audit.evidence.survey_side import (
    channel_switch_steps,
    crossover_coupling,
    crossover_coupling_gain,
    survey_spread,
)
from pipeline.audit.extended import FittedModel, ModelSpec
from pipeline.audit.hypotheses.rival import beyond
from pipeline.audit.legs import fisher_combined
from pipeline.audit.result import Evaluation
from pipeline.audit.survey import SurveyCoupling
from pipeline.audit.switching import SwitchCoupling, switch_body_coupling, switch_coupling
from pipeline.compensate.terms import direction_cosines

EFFECT = "electrical_current"


def keys(ctx: AuditContext, current: ModelSpec) -> list[str]:
    """``electrical_current:<name>`` for each auxiliary channel with an electrical unit
    (:func:`_electrical`) not yet in ``current`` that varies over the calibration."""
    out = []
    for name, x in ctx.data.aux.items():
        if (
            name in current.aux
            or name in dict(current.known_aux)
            or not _electrical(ctx.data.aux_units.get(name, ""))
        ):
            continue
        xc = x[ctx.mask]
        if np.isfinite(xc).sum() > 100 and np.nanstd(xc) > 1e-9:
            out.append(f"{EFFECT}:{name}")
    return out


def without(spec: ModelSpec, key: str) -> ModelSpec:
    """``spec`` without channel ``key``'s coupling, fitted or known."""
    name = key.split(":", 1)[1]
    return spec.with_(
        aux=tuple(a for a in spec.aux if a != name),
        known_aux=tuple(a for a in spec.known_aux if a[0] != name),
    )


def _electrical(unit: str) -> bool:
    """A channel that can carry a current coupling: a current or a voltage (a load's
    proxy), or one whose unit the recording does not say. A temperature, a pressure ...
    changes the carrier's field too, but that is not an electrical current."""
    u = unit.strip()
    return u == "" or u in {"A", "mA", "uA", "kA", "V", "mV"}


def evaluate(ctx: AuditContext, current: ModelSpec, key: str) -> Evaluation:
    """A current in auxiliary channel ``key`` (``electrical_current:<name>``) coupling into
    the reading: its three body-frame columns on the calibration, confirmed by the survey's
    crossovers (:func:`_by_the_crossovers`), the channel's switches
    (:func:`_by_the_switches`) or both (:func:`_by_both`), or decided by the survey
    (:func:`_by_the_survey`), and weighed against the second-order terms."""
    name = key.split(":", 1)[1]
    ext = current.with_(aux=current.aux + (name,))
    ev, sc = _on_the_calibration(ctx, current, key, name, ext)
    sg = _by_the_crossovers(ctx, ev, current, name, sc)
    sw = _by_the_switches(ctx, ev, current, name)
    _by_both(ctx, ev, (sc, sg), sw)
    _by_the_survey(ctx, ev, current, name, (sc, sg), sw)
    # a current that follows the manoeuvres (a motor's) can stand in for interference
    # that is not linear in the field or in the rates: the coupling is named only when it
    # explains held-out data better than the second-order terms do
    beyond(
        ctx,
        ev,
        current.with_(second_order=True),
        ext.with_(second_order=True),
        "second-order induced and eddy terms",
        "a current coupling",
    )
    return ev


def _on_the_calibration(
    ctx: AuditContext, current: ModelSpec, key: str, name: str, ext: ModelSpec
) -> tuple[Evaluation, SurveyCoupling | None]:
    """The coupling's tests and estimates on the calibration, with the survey crossovers'
    coupling beside them (and returned, None without enough crossovers)."""
    test = ctx._nested(current, ext_spec=ext)
    held = ctx.heldout(current, lambda train, k: ext)
    u = direction_cosines(ctx.data.vector_nT)
    inside = np.all(np.isfinite(u), axis=1)

    def coupling(fm: FittedModel) -> dict[str, Any]:
        c = fm.coefficient(f"aux_{name}_u")
        mag = float(np.linalg.norm(c))
        # what the scalar sensor sees: the coupling projected on the field direction
        return {
            "channel": f"/aux/{name}",
            "nT_per_unit": mag,
            "total_field_nT_per_unit": float(np.mean(u[inside] @ c)),
            "unit": ctx.data.aux_units.get(name, ""),
            "direction_body": [float(v) for v in c / mag] if mag > 0 else None,
        }

    est = coupling(ctx.fit(ext, None, "all"))
    # refitted without each kind of manoeuvre and each heading: a coupling that takes up
    # interference outside the model moves between them
    ci = widest_ci95(
        [
            jackknife_ci95(est, [coupling(ctx.fit(ext, keep, k)) for keep, k in groups])
            for groups in ctx.jackknife_groups()
        ]
    )
    sc = crossover_coupling(ctx, current, name)
    if sc is not None:  # independent evidence: the survey's crossovers
        est.update(
            survey_total_field_nT_per_unit=sc.nT_per_unit,
            survey_ci95=list(sc.ci95),
            survey_p_value=sc.p_value,
        )
        ci.update(
            {k: None for k in ("survey_total_field_nT_per_unit", "survey_ci95", "survey_p_value")}
        )
    return Evaluation("electrical_current", key, est, test, held, ext, ci95=ci), sc


def _by_the_crossovers(
    ctx: AuditContext, ev: Evaluation, current: ModelSpec, name: str, sc: SurveyCoupling | None
) -> HeldOut | None:
    """The crossovers' leave-one-out gain of the coupling, which confirms the calibration's
    held-out test when the crossovers' coupling ``sc`` is significant and the gain large
    enough; returned (None without it)."""
    sg = crossover_coupling_gain(ctx, current, name)
    if sc is not None and sg is not None:
        ev.estimate["survey_heldout"] = sg.to_dict()
        ev.ci95["survey_heldout"] = None
        # the crossovers are survey data, independent of the calibration's: a coupling
        # they show (p < alpha) and that predicts them leave-one-out by min_gain confirms
        # the calibration's held-out test; its leave-one-out p joins the held-out p
        # (Fisher), the two together must reach alpha
        if sc.p_value < ctx.s.alpha and sg.reduction >= ctx.s.min_gain:
            ev.confirm_p, ev.confirmed_gain = sg.p_value, True
    return sg


def _by_the_switches(
    ctx: AuditContext, ev: Evaluation, current: ModelSpec, name: str
) -> SwitchCoupling | None:
    """The field's steps where the channel switches, over the whole flight: their
    coupling's estimate beside the calibration's, and their own tests, which confirm the
    calibration's; returned (None without switches)."""
    # the steps' errors as this flight's placebo switches spread, not as each window says
    steps, wider = channel_switch_steps(ctx, current, name)
    sw = None if steps is None else switch_coupling(steps, inflation=wider)
    body = None if steps is None else switch_body_coupling(steps, inflation=wider)
    if body is not None:
        ev.estimate.update(
            switch_nT_per_unit=body.nT_per_unit,
            switch_vector_body_nT_per_unit=[float(v) for v in body.vector_nT_per_unit],
        )
        ev.ci95["switch_nT_per_unit"] = list(body.ci95)
        ev.ci95["switch_vector_body_nT_per_unit"] = None
    if sw is not None:
        ev.estimate.update(
            switch_total_field_nT_per_unit=sw.total_field_nT_per_unit,
            switch_p_value=sw.p_value,
            switch_placebo_inflation=wider,
            switches=sw.switches,
            switch_heldout=sw.heldout.to_dict(),
        )
        ev.ci95.update(
            {
                k: None
                for k in (
                    "switch_total_field_nT_per_unit",
                    "switch_p_value",
                    "switch_placebo_inflation",
                    "switches",
                    "switch_heldout",
                )
            }
        )
        # the field's steps where the channel switches, over the whole flight: evidence
        # the calibration's band-pass hardly sees (a rarely switched load); it confirms
        # when the steps predict each other (leave-one-out) significantly, since many
        # switches make a negligible coupling significant too
        if (
            sw.p_value < ctx.s.alpha
            and sw.heldout.p_value < ctx.s.alpha
            and sw.heldout.reduction >= ctx.s.min_gain
        ):
            p = sw.heldout.p_value
            # the better of two confirmations, Bonferroni-corrected for the choice
            ev.confirm_p = p if ev.confirm_p is None else min(1.0, 2 * min(ev.confirm_p, p))
            ev.confirmed_gain = True
    return sw


def _by_both(
    ctx: AuditContext,
    ev: Evaluation,
    crossovers: tuple[SurveyCoupling | None, HeldOut | None],
    sw: SwitchCoupling | None,
) -> None:
    """The crossovers and the switches joined, when each shows the coupling (p < ``alpha``,
    leave-one-out gain >= ``min_gain``) but neither predicts its own data leave-one-out at
    ``alpha`` alone: the two are different data (the lines' intersections, the field's
    steps where the channel switches), so with no coupling their leave-one-out p-values
    are independent and Fisher's combination is uniform. Few switches cannot reach
    ``alpha`` alone (a sign-flip test over n steps has no p below 2^-n)."""
    sc, sg = crossovers
    if sc is None or sg is None or sw is None:
        return
    s = ctx.s
    shown = (
        sc.p_value < s.alpha
        and sg.reduction >= s.min_gain
        and sw.p_value < s.alpha
        and sw.heldout.reduction >= s.min_gain
    )
    alone = sg.p_value < s.alpha or sw.heldout.p_value < s.alpha
    if not shown or alone:
        return
    predicted = fisher_combined(sg.p_value, sw.heldout.p_value)
    ev.estimate["joint_heldout_p_value"] = predicted
    ev.ci95["joint_heldout_p_value"] = None
    if predicted >= s.alpha:
        return
    ev.confirm_p, ev.confirmed_gain = predicted, True


@dataclass(frozen=True)
class SurveyCouplingTest:
    """A channel's coupling as the total field sees it, k nT per unit, from the survey
    outside the calibration (:func:`joined_coupling`)."""

    total_field_nT_per_unit: float  # the inverse-variance mean of the sources' k
    se_nT_per_unit: float
    p_value: float  # two-sided, against no coupling
    sources: tuple[str, ...]


def joined_coupling(
    sc: SurveyCoupling | None, sw: SwitchCoupling | None
) -> SurveyCouplingTest | None:
    """The crossovers' and the switches' estimates of the same k joined: each source's
    two-sided p as a signed normal score, weighted by its inverse standard error (weighted
    Stouffer: with no coupling the scores are independent standard normals, different data,
    and the weights hardly depend on them (the crossovers' se holds their residual spread,
    which is independent of k's estimate under a normal model), so the joined score is one
    too to a few % at the levels used; with a coupling
    it is the inverse-variance mean's z, the most powerful join of two estimates of one
    parameter, and a source that sees little weighs little). None without either."""
    parts = []
    if sc is not None and np.isfinite(sc.nT_per_unit):
        # the crossovers' interval is Student's on many differences: near-normal
        se = (sc.ci95[1] - sc.ci95[0]) / (2 * stats.norm.isf(0.025))
        parts.append(("survey crossovers", sc.nT_per_unit, se, sc.p_value))
    if sw is not None and np.isfinite(sw.total_field_nT_per_unit):
        parts.append(
            ("channel switches", sw.total_field_nT_per_unit, sw.se_nT_per_unit, sw.p_value)
        )
    parts = [p for p in parts if np.isfinite(p[2]) and p[2] > 0]
    if not parts:
        return None
    k = np.array([p[1] for p in parts])
    w = 1.0 / np.array([p[2] for p in parts])
    z = np.sign(k) * stats.norm.isf(np.clip([p[3] for p in parts], 1e-300, 1.0) / 2)
    score = float(w @ z / np.linalg.norm(w))
    return SurveyCouplingTest(
        total_field_nT_per_unit=float(w**2 @ k / np.sum(w**2)),
        se_nT_per_unit=float(1.0 / np.linalg.norm(w)),
        p_value=float(2 * stats.norm.sf(abs(score))),
        sources=tuple(p[0] for p in parts),
    )


def _by_the_survey(
    ctx: AuditContext,
    ev: Evaluation,
    current: ModelSpec,
    name: str,
    crossovers: tuple[SurveyCoupling | None, HeldOut | None],
    sw: SwitchCoupling | None,
) -> None:
    """The survey decides (C3) by one test per channel, which the evidence present picks,
    not its values: with both kinds, the crossovers' and the switches' coupling joined
    (:func:`joined_coupling`); with one, that kind's coupling test, which must also predict
    its own data leave-one-out (p < ``alpha``, by ``min_gain``): one kind of evidence has
    its own confounds (a step or line levels at the crossovers, a channel that drifts with
    time), which its prediction of data it was not fitted on guards against; two
    independent data sets that agree need no such check (a confound of one is not in the
    other). The test must reach :func:`decides_outside` and the coupling matter to the
    lines (``min_survey_effect_nT``). A load that hardly changes during the calibration
    (one pass, a fixed-wing's steady legs) or that the calibration sees switch a few times
    leaves the band-passed calibration blind to its coupling; interference the calibration
    leaves (an unrecorded current, vibration) hides it there too."""
    sc, sg = crossovers
    joined = joined_coupling(sc, sw)
    if joined is None:
        return
    if len(joined.sources) == 2:
        _record_joined(ctx, ev, name, joined)
        test = (joined.p_value, "survey_joined_total_field_nT_per_unit", True)
    elif joined.sources == ("survey crossovers",):
        held = significant(sg, ctx.s.alpha, ctx.s.min_gain)
        test = (sc.p_value, "survey_total_field_nT_per_unit", held)
    else:
        held = significant(sw.heldout, ctx.s.alpha, ctx.s.min_gain)
        test = (sw.p_value, "switch_total_field_nT_per_unit", held)
    p_value, coupling_key, predicts = test
    k = ev.estimate[coupling_key]
    ev.outside = (p_value, k) if predicts and _matters(ctx, name, k) else None
    if ev.outside is not None and decides_outside(ctx, current, p_value):
        ev.estimate["confirmed_by"] = " and ".join(joined.sources)
        ev.ci95["confirmed_by"] = None
        ev.confirmed_gain = True
        _decide_outside(ctx, ev, current, name, coupling_key)


def _record_joined(
    ctx: AuditContext, ev: Evaluation, name: str, joined: SurveyCouplingTest
) -> None:
    """The joined coupling, its interval and what it does to the lines, in ``ev``."""
    ev.estimate.update(
        survey_joined_total_field_nT_per_unit=joined.total_field_nT_per_unit,
        survey_joined_p_value=joined.p_value,
        survey_joined_sources=list(joined.sources),
        survey_effect_nT=survey_effect_nT(ctx, name, joined.total_field_nT_per_unit),
    )
    k, half = joined.total_field_nT_per_unit, stats.norm.isf(0.025) * joined.se_nT_per_unit
    ev.ci95.update(
        survey_joined_total_field_nT_per_unit=[k - half, k + half],
        survey_joined_p_value=None,
        survey_joined_sources=None,
        survey_effect_nT=None,
    )


def _matters(ctx: AuditContext, name: str, k_nT_per_unit: float) -> bool:
    """Whether a coupling of ``k_nT_per_unit`` to channel ``name`` matters to the survey:
    what it does to the lines (:func:`survey_effect_nT`) at least ``min_survey_effect_nT``
    (many crossovers or switches make a negligible coupling significant too)."""
    return survey_effect_nT(ctx, name, k_nT_per_unit) >= ctx.s.min_survey_effect_nT


def survey_effect_nT(ctx: AuditContext, name: str, k_nT_per_unit: float) -> float:
    """What a coupling of ``k_nT_per_unit`` does to the survey lines (nT RMS): k times
    channel ``name``'s spread about its mean there (a constant is a level the levelling
    takes)."""
    return float(abs(k_nT_per_unit)) * survey_spread(ctx, ctx.data.aux[name])


def decides_outside(ctx: AuditContext, current: ModelSpec, p_value: float) -> bool:
    """Whether a channel's coupling test on the survey (:func:`_by_the_survey`: one per
    channel) with ``p_value`` decides: Bonferroni over the channels tested, at
    ``event_alpha``, one of the tests outside the null bootstrap's maximum that share the
    flight's false-finding budget (:data:`pipeline.audit.settings.EVENT_TESTS`)."""
    return p_value * max(1, len(keys(ctx, current))) < ctx.s.event_alpha


def _decide_outside(
    ctx: AuditContext, ev: Evaluation, current: ModelSpec, name: str, coupling_key: str
) -> None:
    """Let channel ``name``'s evidence outside the calibration decide ``ev``
    (``Evaluation.decided_outside``): the calibration's held-out test then only checks that
    the extension does not make the calibration worse. The extension is the form that
    lowers the calibration's held-out residual more: the calibration's three body columns
    (``ev.spec``), or that evidence's total-field coupling (``ev.estimate[coupling_key]``,
    nT per unit) taken out as known (``ModelSpec.known_aux``), which has nothing to fit.
    Three free columns of a channel that the band-passed calibration hardly sees fit other
    residual (ramps along the calibration legs, which a gradient then takes); where the
    calibration does see the current, its columns also hold the coupling's components
    across the field, which the known one lacks. The calibration's fit of the coupling
    stays the reported estimate."""
    coupling = (name, ev.estimate[coupling_key])
    known = current.with_(known_aux=current.known_aux + (coupling,))
    held_known = ctx.heldout(current, lambda train, k: known)
    ev.decided_outside = True
    form = "calibration_columns"
    if ev.heldout is None or held_known.reduction > ev.heldout.reduction:
        ev.spec, ev.heldout = known, held_known
        form = coupling_key
    ev.estimate["compensated_with"] = form
    ev.ci95["compensated_with"] = None
