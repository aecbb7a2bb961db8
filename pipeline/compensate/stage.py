"""The compensation stage: choose calibration data, fit, apply, measure (FOM and residuals)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.compensate.guards import CalibrationCheck, check_calibration
from pipeline.compensate.model import (
    CompensationModel,
    FigureOfMerit,
    FitSettings,
    Measurements,
    bandpassed,
    figure_of_merit,
    fit_compensation,
    fom_band,
)
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

    def summary(self) -> dict[str, Any]:
        """The keys of the compensate summary JSON (issue 3 contract) plus details."""
        m = self.model.to_dict()
        fom = self.fom.to_dict() if self.fom else {"uncompensated": None, "compensated": None}
        return {
            "model": m["model"],
            "lambda": m["lambda"],
            "terms": m["terms"],
            "coefficients": m["coefficients"],
            "fom_nT": fom,
            "residual_std_nT": self.residual_std_nT,
            "calibration_guards": self.check.to_dict() if self.check else None,
            **{k: v for k, v in m.items() if k not in ("model", "lambda", "terms", "coefficients")},
        }


def run_compensation(
    flight: Flight,
    segmentation: Segmentation | None,
    settings: FitSettings,
    calibration: str = "auto",
) -> CompensationRun:
    """Fit ``settings.model`` on the chosen calibration epochs and compensate the flight.

    Residual figures are standard deviations of the band-passed compensated field over the
    calibration passes and over the survey lines (where present).
    """
    meas = Measurements.from_flight(flight)
    mask = calibration_mask(flight, segmentation, calibration)
    try:
        model = fit_compensation(meas, mask, settings)
    except ValueError as exc:
        raise AeromagError(
            str(exc), file=flight.source, channel=flight.topic_of.get("vector", "/mag/vector")
        ) from None
    comp, interference = model.compensate(meas)
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
    return CompensationRun(model, comp, interference, fom, resid, check)
