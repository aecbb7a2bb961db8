"""Physics shared by the simulator and the processing models (one copy, no drift)."""

from pipeline.physics.dipoles import DipoleSource, dipole_field_ned_nT, total_field_anomaly_nT
from pipeline.physics.interference import CarrierInterference, scalar_reading_nT
from pipeline.physics.vector_sensor import FluxgateErrors

__all__ = [
    "CarrierInterference",
    "DipoleSource",
    "FluxgateErrors",
    "dipole_field_ned_nT",
    "scalar_reading_nT",
    "total_field_anomaly_nT",
]
