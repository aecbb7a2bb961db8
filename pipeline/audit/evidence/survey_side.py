"""Evidence outside the calibration: the survey's crossovers and a channel's switches."""

from __future__ import annotations

import numpy as np
from scipy.ndimage import maximum_filter1d, minimum_filter1d

from pipeline.audit.context import AuditContext
from pipeline.audit.evidence import HeldOut
from pipeline.audit.extended import ModelSpec
from pipeline.audit.survey import (
    CrossoverSet,
    SurveyCoupling,
    SurveyHeading,
    SurveyLag,
    survey_coupling,
    survey_coupling_gain,
    survey_heading,
    survey_lag,
)
from pipeline.audit.switching import (
    WINDOW_S,
    SwitchSteps,
    placebo_inflation,
    switch_instants,
    switch_steps,
)
from pipeline.compensate.filters import contiguous_blocks
from pipeline.compensate.terms import direction_cosines
from pipeline.maps.reduce import time_window_mean


def lines_difference_nT(ctx: AuditContext, a: ModelSpec, b: ModelSpec) -> float | None:
    """How much the survey depends on which of two explanations holds: the RMS (nT) of the
    difference of their compensated fields (:meth:`AuditContext.compensated`) along the
    survey, tie and validation lines, each straight run's mean removed (a level that
    tie-line levelling takes out). A tie whose explanations differ by less than the
    survey's noise does not matter to the map; one that differs by more is the user's to
    resolve. None without lines."""
    d = ctx.compensated(a) - ctx.compensated(b)
    ok = ctx.seg.mask("survey", "tie", "validation") & np.isfinite(d)
    parts = [d[i] - d[i].mean() for i in contiguous_blocks(ok, ctx.data.time_s) if i.size > 1]
    if not parts:
        return None
    return float(np.sqrt(np.mean(np.concatenate(parts) ** 2)))


def crossover_lag(ctx: AuditContext, spec: ModelSpec) -> SurveyLag | None:
    """The lag seen at the survey's crossovers (:func:`pipeline.audit.survey.survey_lag`)."""
    got = ctx._survey_crossovers(spec)
    if got is None:
        return None
    cs, red = got
    t = ctx.data.time_s
    ok = np.isfinite(red)
    rate = np.full(t.size, np.nan)
    rate[ok] = np.gradient(red[ok], t[ok])
    return survey_lag(cs, np.interp(cs.time_a_s, t, rate), np.interp(cs.time_b_s, t, rate))


def crossover_heading(ctx: AuditContext, spec: ModelSpec) -> SurveyHeading | None:
    """``spec``'s heading error seen at the survey's crossovers, and whether it changes
    across the survey (:func:`pipeline.audit.survey.survey_heading`)."""
    got = ctx._survey_crossovers(spec)
    if got is None:
        return None
    cs = got[0]
    return survey_heading(cs, cs.east_m / 1000.0, cs.north_m / 1000.0)


def crossover_channel(
    ctx: AuditContext, spec: ModelSpec, name: str
) -> tuple[CrossoverSet, np.ndarray, np.ndarray] | None:
    """``spec``'s survey crossovers with channel ``name`` at their two readings (smoothed
    over 1 s, as the crossovers are)."""
    got = ctx._survey_crossovers(spec)
    if got is None:
        return None
    cs = got[0]
    t = ctx.data.time_s
    aux = time_window_mean(t, ctx.data.aux[name], 1.0)
    return cs, np.interp(cs.time_a_s, t, aux), np.interp(cs.time_b_s, t, aux)


def crossover_coupling(ctx: AuditContext, spec: ModelSpec, name: str) -> SurveyCoupling | None:
    """Channel ``name``'s coupling seen at the survey's crossovers
    (:func:`pipeline.audit.survey.survey_coupling`)."""
    got = crossover_channel(ctx, spec, name)
    return None if got is None else survey_coupling(*got, step_s=located_step_s(ctx))


def channel_switch_steps(
    ctx: AuditContext, spec: ModelSpec, name: str
) -> tuple[SwitchSteps | None, float]:
    """The steps of ``spec``'s compensated field where channel ``name`` switches, with the
    field's direction at each (:func:`pipeline.audit.switching.switch_steps`), and how much
    their t statistic spreads beyond Student's with the channel moved in time
    (:func:`pipeline.audit.switching.placebo_inflation`; 1 without steps), both on the same
    epochs."""
    usable = _switch_usable(ctx)
    t, field, channel = ctx.data.time_s, ctx.compensated(spec), ctx.data.aux[name]
    instants = switch_instants(t, channel)
    steps = switch_steps(
        t,
        field,
        channel,
        usable=usable,
        direction=direction_cosines(ctx.data.vector_nT),
        instants_s=instants,
    )
    if steps is None:
        return None, 1.0
    return steps, placebo_inflation(t, field, channel, usable=usable, instants_s=instants)


def _switch_usable(ctx: AuditContext) -> np.ndarray:
    """Where a switch's window may lie: not in the calibration, whose manoeuvres a load can
    follow (a motor's current, the bus voltage: a residual there would pass for a
    coupling), and in a turn only at a steady bank (:func:`steady_turns`), where what the
    compensation leaves changes with the heading only, slowly: the window's line and the
    steps' scatter take it."""
    usable = ~ctx.seg.mask("turn", "calibration")
    steady = steady_turns(ctx)
    return usable if steady is None else usable | steady


def steady_turns(ctx: AuditContext) -> np.ndarray | None:
    """The turns' epochs whose roll and pitch change by at most
    ``switch_steady_attitude_deg`` over a switch's window about them (bool per epoch; None
    without attitude): a bank held steady. A roll-in or roll-out changes the interference
    the model leaves within a second or two, as a switch changes the field."""
    d = ctx.flight.data
    if not ctx.flight.has("roll_deg", "pitch_deg"):
        return None
    width = max(3, int(round(2.0 * WINDOW_S * ctx.data.rate_hz)) + 1)
    steady = ctx.seg.mask("turn")
    for col in ("roll_deg", "pitch_deg"):
        a = d[col].to_numpy(float)
        ok = np.isfinite(a)
        a = np.where(ok, a, 0.0)
        spread = maximum_filter1d(a, width) - minimum_filter1d(a, width)
        # a missing sample anywhere in the window leaves the bank unknown there
        seen = minimum_filter1d(ok.astype(np.uint8), width).astype(bool)
        steady = steady & seen & (spread <= ctx.s.switch_steady_attitude_deg)
    return steady


def crossover_coupling_gain(ctx: AuditContext, spec: ModelSpec, name: str) -> HeldOut | None:
    """Leave-one-out gain of channel ``name``'s coupling at the survey's crossovers
    (:func:`pipeline.audit.survey.survey_coupling_gain`)."""
    got = crossover_channel(ctx, spec, name)
    return None if got is None else survey_coupling_gain(*got, step_s=located_step_s(ctx))


def located_step_s(ctx: AuditContext) -> float | None:
    """The likeliest time (s) of the carrier's permanent-field step the fluxgate locates
    (:attr:`AuditContext.fluxgate_step`), or None."""
    step = ctx.fluxgate_step
    return None if step is None else float(step.time_s)


def survey_spread(ctx: AuditContext, x: np.ndarray) -> float:
    """Standard deviation of a per-epoch series ``x`` over the survey's epochs (survey, tie
    and validation lines; non-finite values left out; a constant is a level the levelling
    takes), in ``x``'s unit; 0 with fewer than two values. What a term proportional to ``x``
    does to the lines."""
    v = np.asarray(x, float)[ctx.seg.mask("survey", "tie", "validation")]
    v = v[np.isfinite(v)]
    return float(np.std(v)) if v.size > 1 else 0.0
