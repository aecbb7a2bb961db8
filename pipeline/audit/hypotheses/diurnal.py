"""The diurnal candidate: whether the compensated field follows the base station at the survey's
crossovers and along the calibration legs (:mod:`pipeline.audit.diurnal`)."""

from __future__ import annotations

import numpy as np
from scipy.optimize import curve_fit

from pipeline.audit.context import (
    CROSSOVER_SMOOTHING_S,
    AuditContext,
    base_difference,
    crossover_set,
)
from pipeline.audit.diurnal import DiurnalSet, diurnal_evidence
from pipeline.audit.evidence import paired_point_gain
from pipeline.audit.evidence.survey_side import survey_spread
from pipeline.audit.extended import ModelSpec
from pipeline.audit.legs import leg_block_means
from pipeline.audit.result import Evaluation
from pipeline.audit.survey import heading_levels
from pipeline.audit.vector_reference import bin_means

EFFECT = "diurnal"


def keys(ctx: AuditContext, current: ModelSpec) -> list[str]:
    """The candidate when ``current`` has no diurnal correction and the flight a base
    station."""
    return [EFFECT] if not current.diurnal and ctx.flight.has("base_nT") else []


def without(spec: ModelSpec, key: str) -> ModelSpec:
    """``spec`` without the diurnal correction."""
    return spec.with_(diurnal=False)


def evaluate(ctx: AuditContext, current: ModelSpec, key: str) -> Evaluation:
    """The diurnal: does ``current``'s compensated field follow the base station where the
    survey's lines cross and along the calibration legs
    (:func:`pipeline.audit.diurnal.diurnal_evidence`)? With enough validation overlaps
    (8) those are the held-out points instead."""
    sets = [s for s in (_diurnal_crossovers(ctx, current), _diurnal_legs(ctx, current)) if s]
    ev_d = diurnal_evidence(sets)
    if ev_d is None:
        return Evaluation(
            "diurnal",
            key,
            {},
            None,
            None,
            None,
            reason="no survey crossovers or calibration legs with base-station variation",
        )
    held, metric = ev_d.heldout, "heldout_crossover_and_leg_rms"
    if ctx.flight.has("lat_deg", "lon_deg", "alt_m") and ctx.seg.mask("validation").any():
        _, _, ov, red, base, _, _ = ctx._crossover_data(current, smooth_s=CROSSOVER_SMOOTHING_S)
        if ov.count >= 8:
            held = paired_point_gain(ov.differences(red), ov.differences(red - base))
            metric = "heldout_validation_overlap_rms"
    est = {
        "base_coefficient": ev_d.coefficient,
        # the evidence's size: crossovers and calibration-leg blocks used, and left out
        # as gross errors
        "crossovers": ev_d.used.get("crossovers", 0),
        "leg_blocks": ev_d.used.get("legs", 0),
        "screened_out": sum(ev_d.screened_out.values()),
        **_diurnal_shape(ctx.data.time_s, ctx.base_smoothed_nT),
    }
    ev = Evaluation(
        "diurnal",
        key,
        est,
        ev_d.test,
        held,
        current.with_(diurnal=True),
        ci95={"base_coefficient": list(ev_d.ci95)},
    )
    ev.metric = metric
    _matters(ctx, ev)
    return ev


def _matters(ctx: AuditContext, ev: Evaluation) -> None:
    """Hold the diurnal back when the correction it names would do less than
    ``min_survey_effect_nT`` to the survey: the base station's variation about its mean over
    the survey's epochs (nT RMS; a constant is a level the levelling takes), recorded as
    ``survey_effect_nT``. Many crossovers and leg blocks make a negligible variation
    significant too, and the held-out gain is relative to a residual that can be as small."""
    size = survey_spread(ctx, ctx.base_smoothed_nT)
    ev.estimate["survey_effect_nT"] = size
    ev.ci95["survey_effect_nT"] = None
    if size < ctx.s.min_survey_effect_nT:
        ev.held_back = True
        ev.reason = (
            f"the base station varies by {size:.3f} nT RMS over the survey, under "
            f"{ctx.s.min_survey_effect_nT:g} nT (min_survey_effect_nT): a correction that "
            "does not matter to the survey"
        )


def _diurnal_crossovers(ctx: AuditContext, spec: ModelSpec) -> DiurnalSet | None:
    """The survey's crossovers as a diurnal data set: ``spec``'s crossover differences
    (smoothed along track over :data:`CROSSOVER_SMOOTHING_S`), a level per heading, the base
    station's difference between the two readings, averaged over the same seconds;
    grouped by survey line and by tie line."""
    if not (ctx.flight.has("lat_deg", "lon_deg", "alt_m") and ctx.seg.mask("tie").any()):
        return None
    dx, _, _, _, _, xs, heading = ctx._crossover_data(spec, smooth_s=CROSSOVER_SMOOTHING_S)
    if dx.size == 0:
        return None
    # the regressor averaged as the observation is, not the reduction's minute-smoothed
    # base: the variation's short part (a random walk) is in the airborne reading, and a
    # regressor without it biases the coefficient
    db = base_difference(xs, ctx.data.time_s, ctx.base_over(CROSSOVER_SMOOTHING_S))
    ok = np.isfinite(dx) & np.isfinite(db)  # none beside a gap in the recording
    if not ok.any():
        return None
    dx, db, xs = dx[ok], db[ok], [c for c, k in zip(xs, ok, strict=True) if k]
    x = crossover_set(dx, xs, heading)
    # a crossover shares its survey line's error with the line's other crossovers, and
    # its tie line's with the tie's
    return DiurnalSet("crossovers", dx, heading_levels(x), db, x.line_a, x.line_b)


def _diurnal_legs(ctx: AuditContext, spec: ModelSpec) -> DiurnalSet | None:
    """The calibration legs as a diurnal data set: 10 s block means of ``spec``'s
    compensated field along each leg (the manoeuvres' cycles average out), a level per
    leg and the east/north/up position (the ground's gradient), the base station's block
    mean over the same blocks (:func:`pipeline.audit.legs.leg_block_means`; the base
    record as read, not the reduction's minute-smoothed one: the regressor is averaged as
    the observation is)."""
    if ctx.data.enu_m is None:
        return None
    base = ctx.base_over(0.0)
    a, leg_of = leg_block_means(
        ctx.data.time_s,
        np.column_stack([ctx.compensated(spec), base, ctx.data.enu_m]),
        ctx.legs,
        ctx.s.block_s,
    )
    if leg_of.size == 0:
        return None
    levels = (leg_of[:, None] == np.unique(leg_of)[None, :]).astype(float)
    return DiurnalSet(
        "legs",
        a[:, 0],
        np.column_stack([levels, a[:, 2:5]]),
        a[:, 1],
        group=leg_of,
    )


# the base station's record is smoothed over a minute (``BASE_SMOOTHING_S``) and the
# variation's periods are hours: means over this many seconds lose nothing of the sinusoid
# and spare the fit a flight's worth of samples
SHAPE_BIN_S = 10.0


def _diurnal_shape(time_s: np.ndarray, base: np.ndarray) -> dict[str, float | None]:
    """Amplitude and period of the base-station variation (a sinusoid fitted to its means
    over :data:`SHAPE_BIN_S`)."""
    ok = np.isfinite(base)
    t, b = time_s[ok], base[ok] - np.nanmean(base)
    if t.size:
        t, b = bin_means(t, np.column_stack([t, b]), SHAPE_BIN_S)[0].T
    span = float(t[-1] - t[0]) if t.size else 0.0
    if t.size < 20 or span <= 0:
        return {"amplitude_nT": None, "period_s": None}
    best = None
    for p0 in (span / 2, span, 2 * span):
        try:
            par, _ = curve_fit(
                lambda x, a, p, ph, c: a * np.sin(2 * np.pi * x / p + ph) + c,
                t,
                b,
                p0=[np.std(b) * 1.4, p0, 0.0, 0.0],
                maxfev=20_000,
            )
        except (RuntimeError, ValueError):
            continue
        r = np.mean((b - (par[0] * np.sin(2 * np.pi * t / par[1] + par[2]) + par[3])) ** 2)
        if best is None or r < best[0]:
            best = (r, par)
    if best is None:
        return {"amplitude_nT": float(np.ptp(b) / 2), "period_s": None}
    a, p = abs(float(best[1][0])), abs(float(best[1][1]))
    # a period much longer than the record is not determined: report the range instead
    return {
        "amplitude_nT": a if p < 4 * span else float(np.ptp(b) / 2),
        "period_s": p if p < 4 * span else None,
    }
