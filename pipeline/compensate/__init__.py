"""Tolles-Lawson (tl16, tl18), anti-geomagnetic-gradient (AGG-TL) compensation and the
extensions of tl18 chosen on held-out calibration (tl-plus, tl-nn)."""

from pipeline.compensate.fit import fit_compensation
from pipeline.compensate.model import (
    EXTENSIONS,
    MODELS,
    CompensationModel,
    FigureOfMerit,
    FitSettings,
    Measurements,
    bandpassed,
    figure_of_merit,
)
from pipeline.compensate.ridge import LCurve, RidgeSVD
from pipeline.compensate.terms import (
    MAGNAV_TERMS,
    tl16_terms,
    tl18_rate_terms,
    tl18_terms,
    tl18_truth_coefficients,
)

__all__ = [
    "EXTENSIONS",
    "MAGNAV_TERMS",
    "MODELS",
    "CompensationModel",
    "FigureOfMerit",
    "FitSettings",
    "LCurve",
    "Measurements",
    "RidgeSVD",
    "bandpassed",
    "figure_of_merit",
    "fit_compensation",
    "tl16_terms",
    "tl18_rate_terms",
    "tl18_terms",
    "tl18_truth_coefficients",
]
