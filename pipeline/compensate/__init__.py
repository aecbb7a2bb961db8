"""Tolles-Lawson (tl16, tl18) and anti-geomagnetic-gradient (AGG-TL) compensation."""

from pipeline.compensate.model import (
    MODELS,
    CompensationModel,
    FigureOfMerit,
    FitSettings,
    Measurements,
    bandpassed,
    figure_of_merit,
    fit_compensation,
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
