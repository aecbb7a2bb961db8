"""The vector calibration candidate: the fluxgate's offsets, scale and non-orthogonality, judged
on the fluxgate itself (rules V1, V2 of docs/audit.md)."""

from __future__ import annotations

import numpy as np

from pipeline.audit.context import AuditContext
from pipeline.audit.crossval import jackknife_ci95
from pipeline.audit.evidence import heldout_gain, nested_test
from pipeline.audit.extended import ModelSpec
from pipeline.audit.result import Evaluation
from pipeline.audit.vector_cal import fit_vector_calibration
from pipeline.compensate.terms import direction_cosines
from pipeline.maps.reduce import time_window_mean

EFFECT = "vector_calibration"


def keys(ctx: AuditContext, current: ModelSpec) -> list[str]:
    """The candidate when ``current`` has no vector calibration."""
    return [EFFECT] if current.vector_cal is None else []


def without(spec: ModelSpec, key: str) -> ModelSpec:
    """``spec`` with the fluxgate taken as calibrated."""
    return spec.with_(vector_cal=None)


def evaluate(ctx: AuditContext, current: ModelSpec, key: str) -> Evaluation:
    """The fluxgate's errors, judged on the fluxgate itself.

    Its magnitude |m| should equal the scalar field (compensated, smoothed over 2 s): the
    in-sample test asks whether the mismatch depends on attitude (offsets through u,
    scale and non-orthogonality through u u); the held-out test fits the calibration on
    each fold's training blocks and compares the held-out mismatch before (less the
    training mean: a constant is no sensor error) and after. The scalar compensation's
    own held-out gain is reported beside it (``compensation_*``): T-L absorbs most of a
    fluxgate's errors, so that gain is small even for large errors and would hide them.
    """
    comp = ctx.compensated(current)
    ref = time_window_mean(ctx.data.time_s, comp, 2.0)  # the Earth field, noise smoothed
    m = ctx.data.vector_nT
    sel = ctx.mask & np.isfinite(ref) & np.all(np.isfinite(m), axis=1)
    mismatch = np.linalg.norm(m, axis=1) - ref
    u = direction_cosines(m)
    quad = np.column_stack([u[:, i] * u[:, j] for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2))])
    ones = np.ones((m.shape[0], 1))
    # attitude dependence of |m| - B: offsets (u) and scale/non-orthogonality (u u)
    test = nested_test(
        mismatch[sel], ones[sel], np.column_stack([ones, u, quad])[sel], max(ctx.step, 5)
    )

    fold_vc = {}

    def ext_for(train, k):
        # the reference level from the all-calibration fit (a fold's cross-validated
        # lambda leaves the compensated field's level free, see AuditContext.fit)
        ok = train & sel
        fold_vc[k] = fit_vector_calibration(m[ok], ref[ok])
        return current.with_(vector_cal=fold_vc[k])

    compensation = ctx.heldout(current, ext_for)
    before, after, when = [], [], []
    for k, (train, test_epochs) in enumerate(ctx.folds):
        t = test_epochs & sel
        before.append(mismatch[t] - np.mean(mismatch[train & sel]))
        after.append(np.linalg.norm(fold_vc[k].apply(m[t]), axis=1) - ref[t])
        when.append(ctx.data.time_s[t])
    held = heldout_gain(
        np.concatenate(before), np.concatenate(after), np.concatenate(when), ctx.s.block_s
    )
    vc = fit_vector_calibration(m[sel], ref[sel])
    est = {
        **vc.sensor_errors(),
        "mismatch_rms_before_nT": vc.residual_before_nT,
        "mismatch_rms_after_nT": vc.residual_after_nT,
        "compensation_rms_before_nT": compensation.rms_before_nT,
        "compensation_rms_after_nT": compensation.rms_after_nT,
    }
    ci = jackknife_ci95(vc.sensor_errors(), [fold_vc[k].sensor_errors() for k in sorted(fold_vc)])
    ev = Evaluation(
        "vector_calibration",
        key,
        est,
        test,
        held,
        current.with_(vector_cal=vc),
        metric="heldout_fluxgate_mismatch_rms",
        ci95={**ci, **{k: None for k in est if k not in ci}},
    )
    tolerance_nT = ctx.s.fluxgate_tolerance * float(np.nanmedian(ref[sel]))
    if held.rms_before_nT < tolerance_nT:
        ev.reason = (
            f"the fluxgate agrees with the scalar field to {held.rms_before_nT:.1f} nT "
            f"held out (tolerance {tolerance_nT:.0f} nT): its errors and the carrier's "
            "field at it are too small to name"
        )
        ev.held_back = True
    return ev
