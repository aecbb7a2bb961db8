"""A candidate against a competing explanation: what its extension still gains on held-out data
with the rival already in the model."""

from __future__ import annotations

from pipeline.audit.context import AuditContext
from pipeline.audit.extended import ModelSpec
from pipeline.audit.result import Evaluation


def beyond(
    ctx: AuditContext, ev: Evaluation, alt: ModelSpec, both: ModelSpec, alt_name: str, what: str
) -> None:
    """Hold ``ev`` back unless its extension still lowers held-out data (p < alpha, by
    ``min_gain``) in a model that already has the competing explanation ``alt``."""
    beyond = ctx.heldout(alt, lambda train, k: both)
    ev.estimate["beyond_alternative"] = {"alternative": alt_name, **beyond.to_dict()}
    ev.ci95["beyond_alternative"] = None
    # the survey's own confirmation already tells the two apart (its lines are flown
    # steadily, where the alternative is a level per heading): the calibration then only
    # has to agree in direction
    if ev.decided_outside:  # a switch's step is no function of the attitude
        return
    holds = (
        beyond.reduction > 0
        if ev.confirmed_gain
        else beyond.p_value < ctx.s.alpha and beyond.reduction >= ctx.s.min_gain
    )
    if not holds:
        ev.reason = (
            f"{alt_name} explain the residual about as well: with them in the "
            f"model it lowers held-out data by {100 * beyond.reduction:.1f} % "
            f"(p {beyond.p_value:.2g}); not {what}"
        )
        ev.held_back = True
