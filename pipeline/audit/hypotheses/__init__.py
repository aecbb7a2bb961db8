"""The candidate effects of the catalogue, one module each: what each adds to a model, its
tests on the calibration and its evidence outside it.

Each module's ``evaluate(ctx, current, key)`` tests its candidate against the model
``current`` (:class:`pipeline.audit.extended.ModelSpec`) on the audit's context
(:class:`pipeline.audit.context.AuditContext`) and returns its
:class:`pipeline.audit.result.Evaluation`; :mod:`pipeline.audit.decide` selects among them.
"""

from __future__ import annotations

import numpy as np

from pipeline.audit.context import AuditContext
from pipeline.audit.extended import ModelSpec
from pipeline.audit.hypotheses import (
    diurnal,
    electrical_current,
    geomagnetic_gradient,
    sensor_lag,
    vector_calibration,
)
from pipeline.audit.result import Evaluation

EVALUATORS = {
    "geomagnetic_gradient": geomagnetic_gradient.evaluate,
    "sensor_lag": sensor_lag.evaluate,
    "electrical_current": electrical_current.evaluate,
    "vector_calibration": vector_calibration.evaluate,
    "diurnal": diurnal.evaluate,
}


def evaluate(ctx: AuditContext, current: ModelSpec, effect: str, key: str) -> Evaluation:
    """Test candidate ``key`` of ``effect`` against ``current`` (its module's ``evaluate``).

    A candidate whose fit fails (``ValueError``, ``LinAlgError``) comes back untested, with the
    reason.
    """
    try:
        return EVALUATORS[effect](ctx, current, key)
    except (ValueError, np.linalg.LinAlgError) as exc:
        return Evaluation(effect, key, {}, None, None, None, reason=f"could not be tested: {exc}")
