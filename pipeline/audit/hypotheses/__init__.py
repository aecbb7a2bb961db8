"""The candidate effects of the catalogue, one module each: what each adds to a model, its
tests on the calibration and its evidence outside it.

Each module names its ``EFFECT`` and has ``keys(ctx, current)``, its candidates not yet in the
model ``current`` (:class:`pipeline.audit.extended.ModelSpec`); ``evaluate(ctx, current, key)``,
which tests one on the audit's context (:class:`pipeline.audit.context.AuditContext`) and
returns its :class:`pipeline.audit.result.Evaluation`; and ``without(spec, key)``, the model
with the extension taken out. :mod:`pipeline.audit.decide` selects among them.
"""

from __future__ import annotations

import numpy as np

from pipeline.audit.context import AuditContext
from pipeline.audit.extended import ModelSpec
from pipeline.audit.hypotheses import (
    diurnal,
    electrical_current,
    geomagnetic_gradient,
    lag_decay,
    sensor_lag,
    vector_calibration,
)
from pipeline.audit.result import Evaluation

# the order in which each round tests them
HYPOTHESES = (geomagnetic_gradient, sensor_lag, diurnal, electrical_current, vector_calibration)
BY_EFFECT = {h.EFFECT: h for h in HYPOTHESES}


def candidates(ctx: AuditContext, current: ModelSpec) -> list[tuple[str, str]]:
    """Candidate effects not yet in ``current``, as (effect, key) pairs.

    The geomagnetic gradient (with positions), sensor lag, the diurnal (with a base station),
    each auxiliary channel with an electrical unit that varies over the
    calibration (key ``electrical_current:<name>``) and the vector calibration.
    """
    return [(h.EFFECT, key) for h in HYPOTHESES for key in h.keys(ctx, current)]


def evaluate(ctx: AuditContext, current: ModelSpec, effect: str, key: str) -> Evaluation:
    """Test candidate ``key`` of ``effect`` against ``current`` (its module's ``evaluate``).

    A candidate whose fit fails (``ValueError``, ``LinAlgError``) comes back untested, with the
    reason.
    """
    try:
        return BY_EFFECT[effect].evaluate(ctx, current, key)
    except (ValueError, np.linalg.LinAlgError) as exc:
        return Evaluation(effect, key, {}, None, None, None, reason=f"could not be tested: {exc}")


def without(spec: ModelSpec, f: Evaluation) -> ModelSpec:
    """``spec`` with finding ``f``'s extension taken out, and the nuisance it took the place
    of given back (a lag named in place of the null model's eddy decay,
    :func:`pipeline.audit.hypotheses.lag_decay.took_the_place_of`)."""
    out = BY_EFFECT[f.effect].without(spec, f.key)
    tau = f.estimate.get(lag_decay.IN_PLACE_OF_DECAY)
    return out if tau is None else out.with_(eddy_tau_s=float(tau))
