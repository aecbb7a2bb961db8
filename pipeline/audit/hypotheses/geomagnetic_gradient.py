"""The geomagnetic gradient candidate: the ground's gradient at the calibration site, fitted
as position columns and measured along the calibration legs (rules G1, G2 of docs/audit.md)."""

from __future__ import annotations

import numpy as np

from pipeline.audit.context import AuditContext
from pipeline.audit.crossval import jackknife_ci95
from pipeline.audit.evidence.calibration_legs import legs_gradient, main_field_gradient
from pipeline.audit.evidence.survey_side import crossover_heading
from pipeline.audit.extended import FittedModel, ModelSpec
from pipeline.audit.legs import LegGradient
from pipeline.audit.result import Evaluation

EFFECT = "geomagnetic_gradient"


def keys(ctx: AuditContext, current: ModelSpec) -> list[str]:
    """The candidate when ``current`` has no gradient (fitted or measured) and the flight
    has positions."""
    if current.gradient or current.known_gradient_nT_per_m is not None:
        return []
    return [EFFECT] if ctx.data.enu_m is not None else []


def without(spec: ModelSpec, key: str) -> ModelSpec:
    """``spec`` with no gradient, fitted or measured."""
    return spec.with_(gradient=False, known_gradient_nT_per_m=None)


def evaluate(ctx: AuditContext, current: ModelSpec, key: str) -> Evaluation:
    """A horizontal gradient of the ground's field at the calibration site: the position
    columns on the calibration, the calibration legs' ramps (:func:`_by_the_legs`), the
    survey's heading levels before and after, and the main field's own gradient beside it."""
    ext = current.with_(gradient=True)
    test = ctx._nested(current, ext_spec=ext)
    held = ctx.heldout(current, lambda train, k: ext)

    def gradient(fm: FittedModel) -> dict[str, float]:
        c = dict(zip(fm.names, fm.theta, strict=True))
        return {
            "east_nT_per_m": float(c["pos_e"]),
            "north_nT_per_m": float(c["pos_n"]),
            "up_nT_per_m": float(c["pos_up"]),
        }

    est = gradient(ctx.fit(ext, None, "all"))
    folds = [gradient(ctx.fit(ext, tr, f"fold{k}")) for k, (tr, _) in enumerate(ctx.folds)]
    ev = Evaluation(
        "geomagnetic_gradient", key, est, test, held, ext, ci95=jackknife_ci95(est, folds)
    )
    main = main_field_gradient(ctx)  # IGRF's (east, north, up), nT/m, or None
    _by_the_legs(ctx, ev, current, main)
    # independent evidence: a gradient during calibration biases the heading terms, which
    # the survey's crossovers show as heading levels (and levels that change across the
    # survey); the extended model should flatten them
    before, after = crossover_heading(ctx, current), crossover_heading(ctx, ev.spec)
    if before is not None and after is not None:
        survey = {
            "survey_heading_spread_before_nT": before.spread_nT,
            "survey_heading_spread_after_nT": after.spread_nT,
            "survey_heading_p_value": before.p_value,
            "survey_heading_position_p_value": before.position_p_value,
        }
        ev.estimate.update(survey)
        ev.ci95.update({k: None for k in survey})
    # the fitted gradient is the total field's: the main field's own (IGRF) is part of it
    if main is not None:
        for axis, v in zip(("east", "north", "up"), main, strict=True):
            ev.estimate[f"main_field_{axis}_nT_per_m"] = float(v)
            # computed, not estimated: its interval is the value itself
            ev.ci95[f"main_field_{axis}_nT_per_m"] = [float(v), float(v)]
    return ev


def _by_the_legs(
    ctx: AuditContext, ev: Evaluation, current: ModelSpec, main: np.ndarray | None
) -> None:
    """The direct evidence, below the fit band: the compensated field's ramps along the
    straight legs, far more precise than the band-passed position terms (which see the
    gradient only through the manoeuvres' small moves), so it is the reported estimate (the
    fit's own values stay as ``fit_*``). A gradient the legs show beyond the main field's
    (:func:`leg_gradient_verdict`) decides; else ``ev`` is held back."""
    held = ev.heldout
    legs = legs_gradient(ctx, current)
    if legs is not None:
        for k in ("east_nT_per_m", "north_nT_per_m", "up_nT_per_m"):
            ev.estimate[f"fit_{k}"] = ev.estimate.pop(k)
            ev.ci95[f"fit_{k}"] = ev.ci95.pop(k)
        ci = legs.ci95()
        for i, k in enumerate(("east_nT_per_m", "north_nT_per_m", "up_nT_per_m")):
            ev.estimate[k] = float(legs.gradient_nT_per_m[i])
            ev.ci95[k] = [float(ci[i, 0]), float(ci[i, 1])]
        ev.estimate["calibration_legs_p_value"] = legs.p_value
        ev.estimate["calibration_legs_ramp_rms_nT"] = legs.ramp_rms_nT
        ev.estimate["calibration_legs_blocks"] = legs.blocks
        # part of the interval: the crust's own gradient, measured on the survey
        ev.estimate["calibration_legs_crust_se_nT_per_m"] = legs.crust_se_nT_per_m
        for k in ("p_value", "ramp_rms_nT", "blocks", "crust_se_nT_per_m"):
            ev.ci95[f"calibration_legs_{k}"] = None
        excess, p_excess, why_not = leg_gradient_verdict(ctx, legs, main)
        ev.estimate["calibration_legs_excess_ramp_rms_nT"] = excess
        ev.estimate["calibration_legs_excess_p_value"] = p_excess
        ev.ci95["calibration_legs_excess_ramp_rms_nT"] = None
        ev.ci95["calibration_legs_excess_p_value"] = None
        if why_not:
            ev.held_back, ev.reason = True, why_not
        if not ev.held_back:
            ev.confirm_p = p_excess
            # the legs measured a gradient that matters (beyond the regional, ramping
            # along the legs); the band-passed calibration sees it only through the
            # manoeuvres' small moves, so it need only not contradict it
            ev.decided_outside = True
            # the legs measured the gradient: it can also be taken out of the reading
            # instead of fitted as position columns, which see it only through the
            # manoeuvres' moves and may extrapolate between blocks; the form that
            # lowers the held-out residual more is the extension
            known = with_legs_gradient(current, legs)
            held_known = ctx.heldout(current, lambda train, k: known)
            if held_known.reduction > held.reduction:
                ev.spec, ev.heldout = known, held_known


def leg_gradient_verdict(
    ctx: AuditContext, legs: LegGradient, main: np.ndarray | None
) -> tuple[float, float, str | None]:
    """(ramp RMS of the legs' gradient beyond the main field's, nT; p of its excess over
    the main field's; why it is no gradient effect to model, or None).

    A gradient that is the main field's own (IGRF: ~0.005 nT/m, 0.7 nT along a 500 m
    leg) is no effect to model; a recording made without it (a flat main field) shows
    none, so both the gradient and its excess over IGRF must be large and ramp, and the
    excess must be significant beside the crust's own gradient at the box
    (:meth:`LegGradient.excess_p_value` < alpha), which the survey must measure.
    """
    igrf = main[:2] if main is not None else np.zeros(2)
    horizontal = legs.gradient_nT_per_m[:2]
    excess = legs.ramp_rms_for(horizontal - igrf)
    size = min(float(np.hypot(*horizontal)), float(np.hypot(*(horizontal - igrf))))
    ramp = min(legs.ramp_rms_nT, excess)
    p_excess = legs.excess_p_value(igrf)
    why_not = None
    if legs.crust_se_nT_per_m is None:
        # nothing on the legs tells a gradient effect from the ground's own gradient at
        # the box; the survey measures how much that varies (too few line windows here)
        why_not = (
            "the crust's own gradient cannot be measured on this survey (too few windows "
            "along its lines): the calibration legs' gradient may be the ground's"
        )
    elif p_excess >= ctx.s.alpha:
        # the size below is a point estimate: with a few blocks per leg, or nuisance
        # columns that share the ramps, it can exceed the threshold by its error alone
        why_not = (
            "the calibration legs' gradient is not distinguishable from the main field's "
            f"(p {p_excess:.2g} >= {ctx.s.alpha:g})"
        )
    elif size < ctx.s.min_excess_gradient_nT_per_m:
        why_not = (
            f"the calibration legs' gradient beyond the main field's, {1e3 * size:.2f} "
            f"nT/km, is a regional one (< {1e3 * ctx.s.min_excess_gradient_nT_per_m:g}"
            " nT/km): not a gradient effect to model"
        )
    elif ramp < ctx.s.min_leg_ramp_nT:
        # the legs measure a gradient far better than the position columns do; when
        # they see none beyond the main field's, the columns' gain is something else
        # they happen to fit (a current, second-order terms)
        why_not = (
            "the calibration legs show no gradient beyond the main field's (ramp "
            f"{ramp:.2f} nT RMS < "
            f"{ctx.s.min_leg_ramp_nT:g}): the position terms fit something else"
        )
    return excess, p_excess, why_not


def with_legs_gradient(spec: ModelSpec, legs: LegGradient) -> ModelSpec:
    """``spec`` with the legs' horizontal gradient taken out of the reading (their
    vertical component is not evidence, :mod:`pipeline.audit.legs`)."""
    g_e, g_n, _ = (float(g) for g in legs.gradient_nT_per_m)
    return spec.with_(known_gradient_nT_per_m=(g_e, g_n, 0.0))


def gradient_from_legs(ctx: AuditContext, spec: ModelSpec) -> ModelSpec | None:
    """``spec`` with the horizontal gradient the calibration legs measure taken out of
    the reading, when they measure one that matters (p < alpha and no reason against
    it in :func:`leg_gradient_verdict`, which tests its excess over the main field's,
    as for the gradient's own candidate); else None."""
    legs = legs_gradient(ctx, spec)
    if legs is None:
        return None
    if leg_gradient_verdict(ctx, legs, main_field_gradient(ctx))[2]:
        return None
    return with_legs_gradient(spec, legs)
