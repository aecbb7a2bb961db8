"""Model audit: find what the baseline model of a measured flight gets wrong and why."""

from pipeline.audit.extended import AuditData, ModelSpec, fit_model, simulate_measurement
from pipeline.audit.stage import AuditResult, AuditSettings, run_audit
from pipeline.audit.vector_cal import VectorCalibration, fit_vector_calibration
from pipeline.effects import EFFECTS  # the candidate causes: the catalogue's ids

__all__ = [
    "EFFECTS",
    "AuditData",
    "AuditResult",
    "AuditSettings",
    "ModelSpec",
    "VectorCalibration",
    "fit_model",
    "fit_vector_calibration",
    "run_audit",
    "simulate_measurement",
]
