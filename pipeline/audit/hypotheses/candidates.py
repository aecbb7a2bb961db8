"""The candidate effects not yet in a model."""

from __future__ import annotations

import numpy as np

from pipeline.audit.context import AuditContext
from pipeline.audit.extended import ModelSpec


def candidates(ctx: AuditContext, current: ModelSpec) -> list[tuple[str, str]]:
    """Candidate effects not yet in ``current``, as (effect, key) pairs.

    The geomagnetic gradient (with positions), sensor lag, the diurnal (with a base station),
    each auxiliary channel with an electrical unit that varies over the
    calibration (key ``electrical_current:<name>``) and the vector calibration.
    """
    out = []
    if (
        not current.gradient
        and current.known_gradient_nT_per_m is None
        and ctx.data.enu_m is not None
    ):
        out.append(("geomagnetic_gradient", "geomagnetic_gradient"))
    if not current.lag_s:
        out.append(("sensor_lag", "sensor_lag"))
    if not current.diurnal and ctx.flight.has("base_nT"):
        out.append(("diurnal", "diurnal"))
    for name, x in ctx.data.aux.items():
        if (
            name in current.aux
            or name in dict(current.known_aux)
            or not _electrical(ctx.data.aux_units.get(name, ""))
        ):
            continue
        xc = x[ctx.mask]
        if np.isfinite(xc).sum() > 100 and np.nanstd(xc) > 1e-9:
            out.append(("electrical_current", f"electrical_current:{name}"))
    if current.vector_cal is None:
        out.append(("vector_calibration", "vector_calibration"))
    return out


def _electrical(unit: str) -> bool:
    """A channel that can carry a current coupling: a current or a voltage (a load's
    proxy), or one whose unit the recording does not say. A temperature, a pressure ...
    changes the carrier's field too, but that is not an electrical current."""
    u = unit.strip()
    return u == "" or u in {"A", "mA", "uA", "kA", "V", "mV"}
