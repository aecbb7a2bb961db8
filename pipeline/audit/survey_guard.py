"""The survey's word on the null model's nuisances.

A nuisance group (decaying eddy currents, second-order induced terms) enters the null model
because it lowers the held-out calibration residual; the calibration is a few minutes of
manoeuvres in one box, the survey hours of straight lines. Fitted inside the band of the
manoeuvres, its terms can extrapolate badly to the lines' attitudes and slow changes, where
no calibration row checks them. The survey's own check is where its lines cross: the same
ground read twice. A group is kept in the model applied to the survey (and in the model the
findings are re-estimated in) unless the survey's crossover differences are larger with it
than without it, by a calibrated test and by a size that matters — the guard ``tl-plus``
applies to the same groups (:func:`pipeline.compensate.stage.crossover_guard`), with the test
of :func:`pipeline.compensate.heading_levels.crossover_improvement_p`. The same check, the
other way round, keeps a group the findings made unnecessary on the calibration
(:func:`pipeline.audit.decide.prune_nuisances`) when the survey's crossovers are smaller with
it: without it the other terms take its part in the calibration fit and carry it to the lines.

Sizes in nT.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.audit.context import CROSSOVER_SMOOTHING_S, AuditContext, crossover_set
from pipeline.audit.extended import ModelSpec
from pipeline.audit.nuisances import Nuisance
from pipeline.audit.survey import heading_levels
from pipeline.compensate.heading_levels import crossover_improvement_p

# each nuisance group's columns switched off in a model spec
NUISANCE_OFF = {"eddy_decay": {"eddy_tau_s": 0.0}, "second_order": {"second_order": False}}


@dataclass(frozen=True)
class CrossoverCheck:
    """The survey's crossovers with a nuisance group and without it.

    Attributes
    ----------
    rms_with_nT, rms_without_nT : float
        RMS of the crossover differences (less the base station's difference and a level
        per heading class, each model its own) with and without the group, nT.
    p_value : float
        One-sided p that the differences are smaller without the group (the sign-flip test
        on each survey line's sum of ``with^2 - without^2``).
    p_value_with : float
        One-sided p that they are smaller with it (the same test, the other way round).
    lines, crossovers : int
        Survey lines and crossovers the test read.
    """

    rms_with_nT: float
    rms_without_nT: float
    p_value: float
    p_value_with: float
    lines: int
    crossovers: int

    def worse(self, alpha: float, min_gain: float) -> bool:
        """Whether the group raises the survey's crossover differences: p < ``alpha`` and an
        RMS more than ``min_gain`` (fraction) above the one without it."""
        return self.p_value < alpha and self.rms_with_nT > self.rms_without_nT * (1 + min_gain)

    def better(self, alpha: float, min_gain: float) -> bool:
        """Whether the group lowers them: :meth:`worse` the other way round."""
        return self.p_value_with < alpha and self.rms_without_nT > self.rms_with_nT * (1 + min_gain)

    def to_dict(self) -> dict[str, float | int]:
        """The record kept with the nuisance (``unexplained.nuisances[].survey_guard``)."""
        return {
            "crossover_rms_with_nT": self.rms_with_nT,
            "crossover_rms_without_nT": self.rms_without_nT,
            "p_value": self.p_value,
            "p_value_with": self.p_value_with,
            "lines": self.lines,
            "crossovers": self.crossovers,
        }


def compare_crossovers(
    line: np.ndarray, levels: np.ndarray, with_nT: np.ndarray, without_nT: np.ndarray
) -> CrossoverCheck | None:
    """The check of :class:`CrossoverCheck` on crossover differences ``with_nT`` and
    ``without_nT`` (nT, the same crossings; ``line``: each one's survey line; ``levels``:
    the heading-level columns fitted out of each). None with fewer than 3 survey lines or
    no more crossovers than level columns."""
    n = with_nT.size
    if np.unique(line).size < 3 or n <= levels.shape[1] + 1:
        return None

    def residual(d: np.ndarray) -> np.ndarray:
        if levels.shape[1] == 0:
            return d - d.mean()
        a = np.column_stack([np.ones(n), levels])
        return d - a @ np.linalg.lstsq(a, d, rcond=None)[0]

    r1, r0 = residual(with_nT), residual(without_nT)
    p, k = crossover_improvement_p(list(line), r1, r0)
    p_with, _ = crossover_improvement_p(list(line), r0, r1)
    return CrossoverCheck(
        float(np.sqrt(np.mean(r1**2))), float(np.sqrt(np.mean(r0**2))), p, p_with, k, int(n)
    )


def survey_check(ctx: AuditContext, spec: ModelSpec, dropped: ModelSpec) -> CrossoverCheck | None:
    """:func:`compare_crossovers` of ``spec`` (with the group) and ``dropped`` (without it)
    on the survey's survey-tie crossovers; None without them."""
    if not (ctx.flight.has("lat_deg", "lon_deg", "alt_m") and ctx.seg.mask("tie").any()):
        return None
    dx1, db, _, _, _, xs, heading = ctx._crossover_data(spec, smooth_s=CROSSOVER_SMOOTHING_S)
    dx0 = ctx._crossover_data(dropped, smooth_s=CROSSOVER_SMOOTHING_S)[0]
    if dx1.size == 0:
        return None
    ok = np.isfinite(dx1) & np.isfinite(dx0)
    if np.all(np.isfinite(db)):  # the day's variation is in both alike: out of the comparison
        dx1, dx0 = dx1 - db, dx0 - db
    x = crossover_set(dx1, xs, heading)
    return compare_crossovers(x.line_a[ok], heading_levels(x)[ok], dx1[ok], dx0[ok])


def _checked(ctx: AuditContext, spec: ModelSpec, dropped: ModelSpec) -> CrossoverCheck | None:
    """:func:`survey_check`, None where the crossovers cannot be fitted."""
    try:
        return survey_check(ctx, spec, dropped)
    except (ValueError, np.linalg.LinAlgError):
        return None


def survey_needs(ctx: AuditContext, n: Nuisance, spec: ModelSpec, dropped: ModelSpec) -> bool:
    """Whether the survey's crossovers are smaller with nuisance ``n`` (in ``spec``) than
    without it (``dropped``; :meth:`CrossoverCheck.better` at ``alpha`` and ``min_gain``):
    recorded with the nuisance, and noted when it needs it."""
    check = _checked(ctx, spec, dropped)
    if check is None or not check.better(ctx.s.survey_guard_alpha, ctx.s.min_gain):
        return False
    n.survey_guard = {**check.to_dict(), "applied_to_survey": True}
    ctx.notes.append(
        f"the nuisance {n.name} no longer lowers held-out calibration data enough with the "
        f"findings in the model, but without it the survey's crossover differences rise "
        f"from {check.rms_with_nT:.3f} to {check.rms_without_nT:.3f} nT RMS over "
        f"{check.crossovers} crossovers on {check.lines} lines (p {check.p_value_with:.2g}): "
        "kept"
    )
    return True


def guard_nuisances(ctx: AuditContext, spec: ModelSpec) -> ModelSpec:
    """Drop from ``spec`` each nuisance group whose terms raise the survey's crossover
    differences (:meth:`CrossoverCheck.worse` at ``survey_guard_alpha`` and ``min_gain``);
    the check is recorded with the nuisance (``survey_guard``), and a dropped one noted and
    marked ``applied_to_survey`` false (it still lowers the held-out calibration)."""
    for n in ctx.nuisances.nuisances:
        dropped = spec.with_(**NUISANCE_OFF[n.name])
        if dropped == spec:
            continue
        check = _checked(ctx, spec, dropped)
        if check is None:
            continue
        n.survey_guard = check.to_dict()
        if check.worse(ctx.s.survey_guard_alpha, ctx.s.min_gain):
            spec = dropped
            n.survey_guard["applied_to_survey"] = False
            ctx.notes.append(
                f"the nuisance {n.name} lowers the held-out calibration but raises the "
                f"survey's crossover differences from {check.rms_without_nT:.3f} to "
                f"{check.rms_with_nT:.3f} nT RMS over {check.crossovers} crossovers on "
                f"{check.lines} lines (p {check.p_value:.2g}): not applied to the survey"
            )
        else:
            n.survey_guard["applied_to_survey"] = True
    return spec
