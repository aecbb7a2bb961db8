"""The compensation stage: choose calibration data, fit, apply, measure (FOM and residuals)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from pipeline.compensate.extension import ExtendedModel
from pipeline.compensate.fit import fit_compensation
from pipeline.compensate.guards import CalibrationCheck, check_calibration
from pipeline.compensate.level_guard import compare_levels
from pipeline.compensate.model import (
    CompensationModel,
    FigureOfMerit,
    FitSettings,
    Measurements,
    bandpassed,
    design_of,
    figure_of_merit,
    fom_band,
)
from pipeline.compensate.plus import HeldOutSetup, audit_nuisances
from pipeline.errors import AeromagError
from pipeline.flight import Flight
from pipeline.segment import Segmentation

CALIBRATION_HELP = (
    "auto (the segmentation's calibration passes, turns between headings "
    "included), all (every epoch), or T0:T1 (seconds from the first epoch, or "
    "Unix seconds)"
)


def calibration_mask(flight: Flight, segmentation: Segmentation | None, spec: str) -> np.ndarray:
    """Epochs to fit on, from ``auto`` | ``all`` | ``T0:T1``."""
    t = flight.data["time_s"].to_numpy()
    if spec == "all":
        return np.ones(t.size, bool)
    if spec == "auto":
        if segmentation is None:
            raise AeromagError(
                "--calibration auto needs the segmentation (attitude and GNSS, "
                "or /plan/line); give --calibration all or T0:T1",
                file=flight.source,
                channel="/gnss/fix",
            )
        mask = np.zeros(t.size, bool)
        for span in segmentation.passes():
            mask[span] = True
        if not mask.any():
            raise AeromagError(
                "no calibration manoeuvres found; give --calibration all or T0:T1",
                file=flight.source,
                channel="/ins/attitude",
            )
        return mask
    try:
        a, b = (float(x) for x in spec.split(":"))
    except ValueError:
        raise AeromagError(f"--calibration {spec!r}: use {CALIBRATION_HELP}") from None
    if a > 1e9 and b > 1e9:  # absolute Unix seconds
        a, b = a - flight.time_ns[0] / 1e9, b - flight.time_ns[0] / 1e9
    mask = (t >= a) & (t <= b)
    if not mask.any():
        raise AeromagError(
            f"calibration window {spec} holds no epoch (flight spans 0-{t[-1]:.1f} s)",
            file=flight.source,
            channel=flight.topic_of["scalar"],
        )
    return mask


@dataclass
class CompensationRun:
    """A fitted model applied to a flight, with its figures."""

    model: CompensationModel
    compensated_nT: np.ndarray
    interference_nT: np.ndarray
    fom: FigureOfMerit | None
    residual_std_nT: dict[str, float | None]
    check: CalibrationCheck | None = None

    heldout_residual_nT: float | None = None
    # RMS of the survey-tie crossover differences of the compensated field (nT), and their count
    crossover_rms_nT: float | None = None
    crossovers: int = 0

    def summary(self) -> dict[str, Any]:
        """The keys of the compensate summary JSON (issue 3 contract) plus details: the
        held-out calibration residual (nT, :mod:`pipeline.compensate.heldout`; None when the
        calibration is too short for held-out blocks) and, for tl-plus / tl-nn, the
        extension's record with its ``term_groups`` / ``feature_importance`` lifted to the
        top (issue 36 contract)."""
        m = self.model.to_dict()
        fom = self.fom.to_dict() if self.fom else {"uncompensated": None, "compensated": None}
        out = {
            "model": m["model"],
            "lambda": m["lambda"],
            "terms": m["terms"],
            "coefficients": m["coefficients"],
            "fom_nT": fom,
            "residual_std_nT": self.residual_std_nT,
            "heldout_residual_nT": self.heldout_residual_nT,
            "crossover_rms_nT": self.crossover_rms_nT,
            "crossovers": self.crossovers,
            "calibration_guards": self.check.to_dict() if self.check else None,
            **{k: v for k, v in m.items() if k not in ("model", "lambda", "terms", "coefficients")},
        }
        ext = m.get("extension")
        if ext:
            for key in ("term_groups", "feature_importance"):
                if key in ext:
                    out[key] = ext[key]
        return out


def run_compensation(
    flight: Flight,
    segmentation: Segmentation | None,
    settings: FitSettings,
    calibration: str = "auto",
    audit: dict | None = None,
) -> CompensationRun:
    """Fit ``settings.model`` on the chosen calibration epochs and compensate the flight.

    ``audit``: the model audit's summary; tl-plus tries the term groups it names under
    ``unexplained.nuisances`` first (:func:`pipeline.compensate.plus.audit_nuisances`; the
    key may be absent).

    Residual figures are standard deviations of the band-passed compensated field over the
    calibration passes and over the survey lines (where present).
    """
    meas = Measurements.from_flight(flight)
    mask = calibration_mask(flight, segmentation, calibration)
    legs, base = calibration_legs(flight, segmentation, mask, settings)
    try:
        seeded = audit_nuisances(audit) if settings.model == "tl-plus" else None
        model = fit_compensation(meas, mask, settings, legs, base, seeded)
    except ValueError as exc:
        channel = flight.topic_of.get("vector", "/mag/vector")
        if "/ins/attitude" in str(exc):
            channel = "/ins/attitude"
        raise AeromagError(str(exc), file=flight.source, channel=channel) from None
    if isinstance(model, ExtendedModel) and model.used:
        model = level_guard(flight, segmentation, meas, mask, model)
    if isinstance(model, ExtendedModel) and model.used:
        model = crossover_guard(flight, segmentation, meas, mask, model)
    if isinstance(model, ExtendedModel) and settings.model == "tl-plus":
        model = heading_level_step(flight, segmentation, meas, mask, model)
    comp, interference = model.compensate(meas)
    heldout = heldout_residual(meas, mask, model)
    band, _ = fom_band(settings.band_hz)  # unfiltered fit: the FOM in the shipped band
    fom = None
    resid: dict[str, float | None] = {"calibration": None, "survey": None}
    comp_bp = bandpassed(meas.time_s, comp, band, settings.poles)
    cal_bp = comp_bp[mask & np.isfinite(comp_bp)]
    resid["calibration"] = float(np.std(cal_bp)) if cal_bp.size else None
    if segmentation is not None:
        boxes = segmentation.boxes()
        if boxes:
            fom = figure_of_merit(meas.time_s, meas.scalar_nT, comp, boxes, band, settings.poles)
        sv = comp_bp[segmentation.mask("survey") & np.isfinite(comp_bp)]
        resid["survey"] = float(np.std(sv)) if sv.size else None
    yaw = flight.data["yaw_deg"].to_numpy(float) if flight.has("yaw_deg") else None
    check = check_calibration(
        settings.model,
        model.condition_number,
        model.weakest_terms,
        meas.time_s,
        yaw,
        mask,
        segmentation.boxes() if segmentation is not None else None,
    )
    xrms, nx = crossover_rms_nT(flight, segmentation, comp) if segmentation else (np.nan, 0)
    return CompensationRun(
        model,
        comp,
        interference,
        fom,
        resid,
        check,
        heldout,
        float(xrms) if nx else None,
        nx,
    )


def calibration_legs(
    flight: Flight, segmentation: Segmentation | None, mask: np.ndarray, settings: FitSettings
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """AGG-TL's evidence beside the band-passed fit: (calibration leg per epoch, the base
    station's field in nT), each None when absent or not needed."""
    if settings.model != "agg-tl" or segmentation is None:
        return None, None
    from pipeline.audit.legs import leg_ids

    t = flight.data["time_s"].to_numpy(float)
    legs = leg_ids(mask, segmentation.cardinal, segmentation.calibration_pass, t)
    base = flight.data["base_nT"].to_numpy(float) if flight.has("base_nT") else None
    return (legs if (legs >= 0).any() else None), base


def heldout_residual(meas: Measurements, mask: np.ndarray, model) -> float | None:
    """The held-out calibration residual (nT) of the applied model: the extension's own
    when it is used, else that of its linear design refitted per fold; None when the
    calibration is too short for held-out blocks or the fit is unfiltered."""
    if isinstance(model, ExtendedModel):
        ext = model.extension
        return ext["candidate_heldout_residual_nT" if model.used else "tl18_heldout_residual_nT"]
    try:
        setup = HeldOutSetup.of(meas, mask, model.settings)
    except ValueError:
        return None
    k, _, _, _ = design_of(model.settings, meas, mask)
    held = setup.linear(k)
    return held.rms_nT if held.residual_nT.size else None


def crossover_rms_nT(flight: Flight, seg: Segmentation, field_nT: np.ndarray) -> tuple[float, int]:
    """RMS of the survey-tie crossover differences of ``field_nT`` (nT) and their count
    (NaN, 0 without positions or crossings)."""
    xs = survey_tie_crossovers(flight, seg, field_nT)
    if not xs:
        return float("nan"), 0
    dx = np.array([c.difference_nT for c in xs])
    return float(np.sqrt(np.mean(dx**2))), int(dx.size)


def survey_tie_crossovers(flight: Flight, seg: Segmentation, field_nT: np.ndarray) -> list:
    """The survey lines' crossings with the tie lines (:class:`pipeline.maps.level.Crossover`,
    survey line first), ``field_nT`` read at each; empty without positions or crossings."""
    from pipeline.geo.local import LocalFrame
    from pipeline.maps.level import Line, crossovers
    from pipeline.quality.stage import flight_tracks

    if not flight.has("lat_deg", "lon_deg"):
        return []
    d = flight.data
    lat, lon = d["lat_deg"].to_numpy(float), d["lon_deg"].to_numpy(float)
    sel = seg.mask("survey") & np.isfinite(lat)
    if not sel.any():
        return []
    e, n, _ = LocalFrame(float(np.mean(lat[sel])), float(np.mean(lon[sel]))).to_enu(lat, lon)
    t = d["time_s"].to_numpy(float)
    lines = {"survey": [], "tie": []}
    for tr in flight_tracks(seg, e, n, kinds=("survey", "tie")):
        lines[tr.kind].append(Line.from_track(tr, t, field_nT))
    return crossovers(lines["survey"], lines["tie"])


def leg_reduction(
    flight: Flight, seg: Segmentation | None, meas: Measurements, mask: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The calibration legs' epochs (indices), the main field and the day's variation
    there (IGRF plus the base station's reading smoothed over ``BASE_SMOOTHING_S``, nT) and
    each epoch's heading class (the box's headings numbered); None without legs on a
    heading or positions."""
    from pipeline.geo.heading import CARDINALS
    from pipeline.maps.reduce import BASE_SMOOTHING_S, igrf_total_nT, time_window_mean

    card = np.asarray(seg.cardinal).astype(str) if seg is not None else None
    legs = mask & np.isin(card, CARDINALS) if card is not None else None
    if legs is None or not meas.has_position or not legs.any():
        return None
    idx = np.flatnonzero(legs)
    reduction = igrf_total_nT(
        flight.time_ns[idx], meas.lat_deg[idx], meas.lon_deg[idx], meas.alt_m[idx]
    )
    if flight.has("base_nT"):
        base = flight.data["base_nT"].to_numpy(float)
        reduction = reduction + time_window_mean(meas.time_s, base, BASE_SMOOTHING_S)[idx]
    return idx, reduction, np.array([CARDINALS.index(c) for c in card[idx]])


def heading_level_step(
    flight: Flight,
    seg: Segmentation | None,
    meas: Measurements,
    mask: np.ndarray,
    model: ExtendedModel,
) -> ExtendedModel:
    """tl-plus's heading-level correction (:mod:`pipeline.compensate.heading_levels`):
    fitted to the calibration legs' levels of ``model``'s field and kept when the survey's
    crossovers with the ties confirm it at ``heading_levels_alpha``; recorded in
    ``extension["heading_levels"]`` either way."""
    from pipeline.audit.legs import leg_ids
    from pipeline.compensate.heading_levels import crossover_improvement_p, fit_heading_correction
    from pipeline.compensate.terms import direction_cosines
    from pipeline.geo.local import LocalFrame

    rec: dict = {"used": False}
    model.extension["heading_levels"] = rec
    alpha = model.settings.heading_levels_alpha
    if alpha <= 0:
        rec["reason"] = "heading_levels_alpha is 0"
        return model
    legs = leg_reduction(flight, seg, meas, mask)
    if legs is None:
        rec["reason"] = "no calibration legs with positions"
        return model
    idx, reduction, heading = legs
    comp = model.compensate(meas)[0]
    n = meas.time_s.size
    reduced, head = np.full(n, np.nan), np.full(n, -1)
    reduced[idx], head[idx] = comp[idx] - reduction, heading
    leg = leg_ids(mask, seg.cardinal, seg.calibration_pass, meas.time_s)
    unit = direction_cosines(meas.vector_nT)
    # a gap in the positions leaves NaN there: the frame is centred on the fixes there are
    lat, lon = meas.lat_deg[idx], meas.lon_deg[idx]
    fixed = np.isfinite(lat) & np.isfinite(lon)
    if not fixed.any():
        rec["reason"] = "no positions on the calibration legs"
        return model
    frame = LocalFrame(float(np.mean(lat[fixed])), float(np.mean(lon[fixed])))
    east, north, _ = frame.to_enu(meas.lat_deg, meas.lon_deg)
    try:
        corr = fit_heading_correction(
            reduced, unit, np.where(head >= 0, leg, -1), head, meas.time_s, east, north
        )
    except ValueError as exc:
        rec["reason"] = str(exc)
        return model
    rec.update(
        p_nT=[float(x) for x in corr.p_nT],
        legs=corr.legs,
        headings=corr.headings,
        level_spread_nT=corr.level_spread_nT,
        residual_spread_nT=corr.residual_spread_nT,
        gradient_nT_per_m=corr.gradient_nT_per_m,
    )
    after = comp - corr.interference_nT(unit)
    xs0, xs1 = (survey_tie_crossovers(flight, seg, f) for f in (comp, after))
    if not xs0:
        rec["reason"] = "no survey-tie crossovers to confirm it"
        return model
    if len(xs0) != len(xs1):  # the crossings are the tracks' own: the same for both fields
        rec["reason"] = "the survey-tie crossovers differ between the two fields"
        return model
    d0 = np.array([c.difference_nT for c in xs0])
    d1 = np.array([c.difference_nT for c in xs1])
    p, lines = crossover_improvement_p([c.line_a for c in xs0], d0, d1)
    rec.update(
        crossover_rms_before_nT=float(np.sqrt(np.mean(d0**2))),
        crossover_rms_after_nT=float(np.sqrt(np.mean(d1**2))),
        crossover_p=p,
        crossover_lines=lines,
    )
    if p >= alpha:
        rec["reason"] = f"the survey's crossovers do not confirm it (p {p:.2g} over {lines} lines)"
        return model
    rec["used"] = True
    return replace(model, heading=corr)


def level_guard(
    flight: Flight,
    seg: Segmentation | None,
    meas: Measurements,
    mask: np.ndarray,
    model: ExtendedModel,
) -> ExtendedModel:
    """Keep an extension only if its heading levels on the calibration legs (the field less
    IGRF and the base station's smoothed reading), which the band-passed fit never saw, do
    not spread wider than tl18's at p < ``level_guard_alpha``
    (:mod:`pipeline.compensate.level_guard`); otherwise revert to tl18, saying so. Without
    headings or positions the guard is recorded as not applied."""
    if model.settings.level_guard_alpha <= 0:
        model.extension["level_guard"] = "not applied: level_guard_alpha is 0"
        return model
    legs = leg_reduction(flight, seg, meas, mask)
    if legs is None:
        model.extension["level_guard"] = "not applied: no calibration legs with positions"
        return model
    idx, reduction, heading = legs
    tl18 = model.revert("", "level")
    check = compare_levels(
        model.compensate(meas)[0][idx] - reduction,
        tl18.compensate(meas)[0][idx] - reduction,
        heading,
        np.ones(idx.size, bool),
    )
    if check is None:
        model.extension["level_guard"] = "not applied: calibration legs on fewer than 3 headings"
        return model
    model.extension["level_guard_p"] = check.p_value
    model.extension["heading_level_spread_nT"] = check.spread_nT
    model.extension["tl18_heading_level_spread_nT"] = check.tl18_spread_nT
    model.extension["level_guard_headings"] = check.headings
    if check.p_value < model.settings.level_guard_alpha:
        why = (
            f"spreads the calibration legs' levels by heading from {check.tl18_spread_nT:.3f} "
            f"nT (tl18) to {check.spread_nT:.3f} nT over {check.headings} headings (p "
            f"{check.p_value:.2g}): its terms extrapolate below the fit band; tl18 kept"
        )
        return model.revert(why, "level")
    model.extension["level_guard"] = "passed"
    return model


def crossover_guard(
    flight: Flight,
    seg: Segmentation | None,
    meas: Measurements,
    mask: np.ndarray,
    model: ExtendedModel,
) -> ExtendedModel:
    """Keep an extension only if the survey's crossover RMS with it is not above tl18's by
    more than ``extension_min_gain`` (the fraction an extension must gain on held-out
    calibration): otherwise revert to tl18, saying so. Without crossovers the guard is
    recorded as not applied."""
    if seg is None:
        model.extension["crossover_guard"] = "not applied: no segmentation"
        return model
    tl18 = model.revert("", "crossover")
    rms18, n = crossover_rms_nT(flight, seg, tl18.compensate(meas)[0])
    rms, _ = crossover_rms_nT(flight, seg, model.compensate(meas)[0])
    if n == 0 or not np.isfinite(rms18):
        model.extension["crossover_guard"] = "not applied: no survey-tie crossovers"
        return model
    model.extension["crossover_rms_nT"] = rms
    model.extension["tl18_crossover_rms_nT"] = rms18
    model.extension["crossovers"] = n
    limit = rms18 * (1.0 + model.settings.extension_min_gain)
    if rms > limit:
        why = (
            f"raises the survey's crossover RMS from {rms18:.3f} nT (tl18) to {rms:.3f} nT "
            f"over {n} crossovers; tl18 kept"
        )
        return model.revert(why, "crossover")
    model.extension["crossover_guard"] = "passed"
    return model
