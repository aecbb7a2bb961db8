"""Evidence below the fit band: the calibration legs' gradient, and the main field's."""

from __future__ import annotations

from datetime import UTC, datetime

import numpy as np

from pipeline.audit.context import AuditContext
from pipeline.audit.extended import ModelSpec
from pipeline.audit.legs import LegGradient, crust_roughness_ratio, leg_gradient, leg_length_m
from pipeline.compensate.terms import BT_SCALE_NT, direction_cosines


def legs_gradient(ctx: AuditContext, spec: ModelSpec) -> LegGradient | None:
    """The total field's gradient along the calibration legs, from ``spec``'s compensated
    field (the base station's smoothed reading taken out when the recording has one;
    :func:`pipeline.audit.legs.leg_gradient`)."""
    if ctx.data.enu_m is None:
        return None
    comp = ctx.compensated(spec)
    if ctx.flight.has("base_nT"):
        comp = comp - ctx.base_smoothed_nT
    # the carrier's isotropic soft iron scales the reading and no fit can see it (it is
    # the induced columns' missing sum); its anisotropic part, which the fit does see, is
    # of the same order on real carriers, so the largest fitted induced coefficient
    # stands for the scale's uncertainty
    fm = ctx.fit(spec, None, "all")
    induced = [abs(v) for n, v in zip(fm.names, fm.theta, strict=True) if n.startswith("ind_")]
    scale = max(induced, default=0.0) / BT_SCALE_NT
    # the channels whose coupling the model fitted or took as measured: a coupling wrong
    # by dc leaves dc . u times the channel, which a switch within a leg makes a ramp
    channels = dict.fromkeys([*spec.aux, *(name for name, _ in spec.known_aux)])
    u = direction_cosines(ctx.data.vector_nT)
    nuisance = (
        np.column_stack([u * ctx.data.aux[c][:, None] for c in channels]) if channels else None
    )
    return leg_gradient(
        ctx.data.time_s,
        comp,
        ctx.data.enu_m,
        ctx.legs,
        scale_uncertainty=scale,
        nuisance=nuisance,
        crust_ratio_per_m=crust_ratio(ctx, comp),
    )


def crust_ratio(ctx: AuditContext, comp: np.ndarray) -> float | None:
    """The crust's gradient spread per nT of departure from a plane over the legs' length
    (1/m), measured along the survey's lines in ``comp`` (compensated, day's variation
    removed) less the main field (:func:`pipeline.audit.legs.crust_roughness_ratio`); None
    without survey lines."""
    f = ctx.flight
    if not (f.has("lat_deg", "lon_deg", "alt_m") and ctx.seg.mask("survey").any()):
        return None
    window = leg_length_m(ctx.data.enu_m, ctx.legs)
    if window is None:
        return None
    igrf, _, tracks = ctx._survey_geometry()
    got = crust_roughness_ratio(ctx.data.time_s, comp - igrf, tracks, window)
    return None if got is None else got[0]


def main_field_gradient(ctx: AuditContext) -> np.ndarray | None:
    """IGRF's total-field gradient (east, north, up; nT/m) at the calibration site."""
    from pipeline.geo.igrf import main_field_gradient_nT_per_m

    f = ctx.flight
    if not f.has("lat_deg", "lon_deg", "alt_m"):
        return None
    d = f.data
    sel = ctx.mask & np.isfinite(d["lat_deg"].to_numpy(float))
    if not sel.any():
        return None
    lat, lon, alt = (
        float(np.mean(d[c].to_numpy(float)[sel])) for c in ("lat_deg", "lon_deg", "alt_m")
    )
    when = datetime.fromtimestamp(float(f.time_ns[np.flatnonzero(sel)[0]]) / 1e9, UTC)
    return main_field_gradient_nT_per_m(lat, lon, alt, when)
