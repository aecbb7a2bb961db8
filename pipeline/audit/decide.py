"""The selection: forward-stepwise over the candidate effects, with the null model's nuisances."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from pipeline.audit.context import AuditContext
from pipeline.audit.evidence import HeldOut, holm
from pipeline.audit.evidence.lag import eddy_decay_tau, lag_estimate
from pipeline.audit.extended import ModelSpec
from pipeline.audit.hypotheses import candidates, evaluate, without
from pipeline.audit.nuisances import Nuisance
from pipeline.audit.null_calibration import NullCalibration
from pipeline.audit.result import Evaluation
from pipeline.audit.survey_guard import NUISANCE_OFF, guard_nuisances, survey_needs


def select(
    ctx: AuditContext,
    current: ModelSpec,
    progress=None,
    null_calibration: Callable[[], NullCalibration | None] = lambda: None,
) -> tuple[ModelSpec, list[Evaluation], list[list[Evaluation]]]:
    """Forward-stepwise selection of the effects.

    Starts from ``current`` (the null model, with a permanent-field step where the survey
    shows one). Each round tests every candidate, Holm-adjusts the F-test p-values of the
    tested ones and accepts the passing candidate with the largest held-out reduction; it
    stops when none passes. The null's nuisances the findings no longer need are then
    dropped (:func:`prune_nuisances`), so are those the survey's crossovers reject
    (:func:`pipeline.audit.survey_guard.guard_nuisances`), and the accepted effects are
    re-estimated together (:func:`refine`).

    Parameters
    ----------
    progress : callable, optional
        Called with a message before each candidate's test.
    null_calibration : callable
        Gives the null model's bootstrap (:func:`calibrated_gate`), None when not run; asked
        after the first round's tests.

    Returns
    -------
    tuple
        (final model spec, accepted findings in order, every round's evaluations).
    """
    findings: list[Evaluation] = []
    rounds: list[list[Evaluation]] = []
    against: dict[int, ModelSpec] = {}  # the model each finding was accepted against
    while True:
        cands = candidates(ctx, current)
        if not cands:
            break
        evals = []
        for effect, key in cands:
            if progress:
                progress(f"round {len(rounds) + 1}: testing {key}")
            evals.append(evaluate(ctx, current, effect, key))
        tested = [e for e in evals if e.test is not None]
        for e, p in zip(tested, holm([e.test.p_value for e in tested]), strict=True):
            e.p_adjusted = p
        rounds.append(evals)
        calibrated_gate(ctx, evals, null_calibration())
        passing = [e for e in evals if e.passes(ctx.s)]
        for e in evals:
            if not e.passes(ctx.s) and not e.reason:
                e.reason = e.why_not(ctx.s)
        if not passing:
            break
        # the fluxgate's gain is measured on the fluxgate, not on the scalar residual, so
        # it does not compete: a scalar-field effect goes first when one passes
        best = max(passing, key=lambda e: (e.metric == Evaluation.metric, e.heldout.reduction))
        best.accepted = True
        against[id(best)] = current
        findings.append(best)
        for e in passing:
            if e is not best:
                e.reason = "passed; re-tested in the next round with the better one in"
        current = admit_nuisances(ctx, best.spec, best.effect)
    current = guard_nuisances(ctx, prune_nuisances(ctx, current))
    return refine(ctx, current, findings, against), findings, rounds


def calibrated_gate(ctx: AuditContext, evals: list[Evaluation], nc: NullCalibration | None) -> None:
    """Hold back a candidate judged on the scalar calibration whose held-out gain beside
    the null model does not reach the gate the null model's bootstrap sets for the whole
    selection (``nc``, :attr:`pipeline.audit.stage.Auditor.null_calibration`): its
    threshold, and the least gain worth a term unless evidence outside the calibration
    confirmed the gain; a candidate its own evidence outside the calibration decides is not
    judged there."""
    if nc is None:
        return
    for e in evals:
        if (
            e.decided_outside
            or e.held_back
            or not e.passes(ctx.s)
            or nc.passes(e.key, e.confirmed_gain)
        ):
            continue
        e.held_back = True
        e.reason = (
            f"its held-out gain beside the null model, {100 * nc.observed_gain[e.key]:.1f} %,"
            f" is below the {100 * nc.gate(e.confirmed_gain):.1f} % the null model's bootstrap"
            f" sets for the whole selection at a flight-level rate of {nc.alpha:g}"
        )


def admit_nuisances(ctx: AuditContext, spec: ModelSpec, finding: str) -> ModelSpec:
    """Add to ``spec`` each nuisance group it lacks that, with the findings so far in the
    model, lowers held-out data as :func:`prune_nuisances` requires one to stay: the
    field of an effect not yet modelled (a gradient's, along the manoeuvres) can hide a
    nuisance from the selection on the baseline, and the next candidates are judged
    against the null model the data support."""
    trials = []
    if spec.eddy_tau_s == 0:
        tau = eddy_decay_tau(ctx, spec)
        trials.append(("eddy_decay", spec.with_(eddy_tau_s=tau), {"tau_s": tau}))
    if not spec.second_order:
        trials.append(("second_order", spec.with_(second_order=True), {}))
    for name, trial, est in trials:
        try:
            h = ctx.heldout(fold_lag(ctx, spec), fold_lag(ctx, trial))
        except (ValueError, np.linalg.LinAlgError):
            continue
        if nuisance_matters(ctx, h):
            spec = trial
            ctx.nuisances.nuisances.append(Nuisance(name, float(h.reduction), est))
            ctx.notes.append(
                f"the nuisance {name} lowers held-out data by {100 * h.reduction:.1f} % "
                f"(p {h.p_value:.2g}) with the {finding.replace('_', ' ')} in the model: "
                "taken into the null model"
            )
    return spec


def nuisance_matters(ctx: AuditContext, h: HeldOut) -> bool:
    """Whether a nuisance's held-out comparison ``h`` holds it in the model: p below
    ``alpha``, at least ``min_gain`` of the RMS and ``min_nuisance_nT`` of interference."""
    removed_nT = float(np.sqrt(max(h.rms_before_nT**2 - h.rms_after_nT**2, 0.0)))
    return (
        h.p_value < ctx.s.alpha
        and h.reduction >= ctx.s.min_gain
        and removed_nT >= ctx.s.min_nuisance_nT
    )


def prune_nuisances(ctx: AuditContext, spec: ModelSpec) -> ModelSpec:
    """Drop from ``spec`` each nuisance that no longer lowers held-out data with the
    findings in the model (p < ``alpha``, by ``min_gain`` and ``min_nuisance_nT`` of
    interference; each model with its own lag): taken before the catalogue
    effects, a nuisance can have followed part of one (a gradient's field moves with the
    manoeuvres' small displacements). One the survey's crossovers need
    (:func:`pipeline.audit.survey_guard.survey_needs`) stays. Kept nuisances stay in
    ``ctx.nuisances``; the dropped ones are noted."""
    kept = []
    for n in ctx.nuisances.nuisances:
        dropped = spec.with_(**NUISANCE_OFF[n.name])
        if dropped == spec:
            continue
        try:
            h = ctx.heldout(fold_lag(ctx, dropped), fold_lag(ctx, spec))
        except (ValueError, np.linalg.LinAlgError):
            kept.append(n)
            continue
        if nuisance_matters(ctx, h) or survey_needs(ctx, n, spec, dropped):
            kept.append(n)
            continue
        removed_nT = float(np.sqrt(max(h.rms_before_nT**2 - h.rms_after_nT**2, 0.0)))
        spec = dropped
        ctx.notes.append(
            f"the nuisance {n.name} taken before the catalogue effects lowers held-out data "
            f"by {100 * h.reduction:.1f} % (p {h.p_value:.2g}; {removed_nT:.3f} nT of "
            f"interference, {ctx.s.min_nuisance_nT:g} nT matters) with the findings in the "
            "model: dropped"
        )
    ctx.nuisances.nuisances = kept
    return spec


def fold_lag(ctx: AuditContext, spec: ModelSpec):
    """A held-out builder of ``spec`` whose lag, when it has one, is estimated on each
    fold's training rows with the spec's own other terms: a lag fitted beside a nuisance
    is not the lag of the model without it (a decay takes part of a delay), so a model
    judged with another model's lag would be judged unfairly."""

    def build(train, k):
        if spec.lag_s == 0:
            return spec
        return spec.with_(lag_s=lag_estimate(ctx, spec.with_(lag_s=0.0), train, f"fold{k}"))

    return build


def still_shown_outside(ctx: AuditContext, accepted: Evaluation, again: Evaluation) -> bool:
    """Whether a finding that evidence outside the calibration decided (``accepted``) keeps
    that acceptance when re-evaluated with the other findings in the model (``again``):
    that evidence still shows it (its test's p < ``alpha``, predicting its own data, an
    estimate of the same sign that still matters to the survey: ``Evaluation.outside``).
    The acceptance statistics are the accepting round's; its level (Bonferroni over the
    channels) is not asked twice, and the calibration's rival, which that evidence set
    aside, does not drop it (a switch's step is no function of the attitude)."""
    if not accepted.decided_outside or accepted.outside is None or again.outside is None:
        return False
    p, k = again.outside
    return bool(p < ctx.s.alpha and np.sign(k) == np.sign(accepted.outside[1]))


def refine(
    ctx: AuditContext,
    spec: ModelSpec,
    findings: list[Evaluation],
    against: dict[int, ModelSpec] | None = None,
) -> ModelSpec:
    """Re-estimate every accepted effect with all the others in the model.

    An effect accepted early was estimated while later ones were still unmodelled (a
    lag estimated before a current coupling is biased by it); the estimates reported
    are these, with the others present, and so are their intervals. The acceptance
    statistics stay those of the round that accepted the effect. An effect that, with the
    others present, a competing explanation or its own direct evidence now rejects
    (``held_back``, unless :func:`still_shown_outside`) is dropped from ``findings`` (in
    place) and from the model (a current's steps inside the calibration legs ramp like a
    gradient until the current is in the model).

    ``against``: the model each finding (by ``id``) was accepted against. A finding whose
    model without it is that model keeps its own evaluation: evaluating it again is
    deterministic and would give the same record.
    """
    against = against or {}
    order = sorted(findings, key=lambda f: f.effect != "sensor_lag")  # lag first
    for f in order:
        rest = without(spec, f)
        e = f if against.get(id(f)) == rest else evaluate(ctx, rest, f.effect, f.key)
        if e.held_back and still_shown_outside(ctx, f, e):
            ctx.notes.append(
                f"{f.key} kept with the other findings in the model: the evidence outside "
                f"the calibration that decided it still shows it (p {e.outside[0]:.2g}); "
                f"set aside: {e.reason}"
            )
        elif e.held_back:
            spec = without(spec, f)
            findings.remove(f)
            f.accepted = False
            f.reason = f"dropped with the other findings in the model: {e.reason}"
            continue
        if not e.estimate:
            continue
        f.estimate = {**e.estimate, "at_acceptance": f.estimate}
        # the intervals reported are the re-estimate's: an interval read at acceptance
        # need not hold the estimate reported
        if e.ci95:
            f.ci95 = e.ci95
        # estimated values in the spec (a lag, a vector calibration, a measured
        # gradient) take the re-estimate; switched-on columns are refitted anyway
        if e.spec is not None and (
            f.effect in ("sensor_lag", "vector_calibration")
            or e.spec.known_gradient_nT_per_m is not None
        ):
            spec = e.spec
    return spec
