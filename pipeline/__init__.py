"""aeromag: post-flight processing of airborne and UAV magnetic surveys.

The library is pure: functions and small estimator objects on numpy/pandas data.
File access lives in :mod:`pipeline.io`; Prefect lives in ``flows/`` only.

The names below are the curated public API. They are imported lazily, on first use
(``pipeline.read_flight``, ``from pipeline import run_audit``), so ``import pipeline`` stays
cheap; the subpackages keep their own, longer ``__all__``.

Conventions: fields in nT, time in ns since the Unix epoch (UTC) or s since the first epoch,
body frame x forward / y right / z down, navigation frame NED, Z-Y-X attitude in degrees with
yaw = true heading.
"""

TYPE_CHECKING = False  # typing.TYPE_CHECKING without importing typing (about 10 ms)

__version__ = "0.1.0"

# public name -> module that provides it
_LAZY: dict[str, str] = {
    # errors and configuration
    "AeromagError": "pipeline.errors",
    "Config": "pipeline.config",
    # reading and writing recordings
    "Flight": "pipeline.flight",
    "read_flight": "pipeline.io",
    "inspect_recording": "pipeline.io.inspect",
    "OutputChannel": "pipeline.io",
    "write_with_new_channels": "pipeline.io",
    # segmentation
    "Segmentation": "pipeline.segment",
    "SegmentParams": "pipeline.segment",
    "segment_flight": "pipeline.segment",
    # Tolles-Lawson compensation
    "FitSettings": "pipeline.compensate",
    "CompensationModel": "pipeline.compensate",
    "fit_compensation": "pipeline.compensate",
    "figure_of_merit": "pipeline.compensate",
    "CompensationRun": "pipeline.compensate.stage",
    "run_compensation": "pipeline.compensate.stage",
    # anomaly maps
    "MapSettings": "pipeline.maps.stage",
    "MapRun": "pipeline.maps.stage",
    "build_map": "pipeline.maps.stage",
    "Grid": "pipeline.maps.grid",
    "minimum_curvature": "pipeline.maps.grid",
    # quality
    "QualitySettings": "pipeline.quality",
    "QualityRun": "pipeline.quality",
    "run_quality": "pipeline.quality",
    # model audit
    "AuditSettings": "pipeline.audit",
    "AuditResult": "pipeline.audit",
    "run_audit": "pipeline.audit",
    # vector magnetometer
    "VectorRun": "pipeline.vector.stage",
    "run_vector": "pipeline.vector.stage",
}

__all__ = [  # the same names as _LAZY (tests/test_api.py checks)
    "__version__",
    "AeromagError",
    "Config",
    "Flight",
    "read_flight",
    "inspect_recording",
    "OutputChannel",
    "write_with_new_channels",
    "Segmentation",
    "SegmentParams",
    "segment_flight",
    "FitSettings",
    "CompensationModel",
    "fit_compensation",
    "figure_of_merit",
    "CompensationRun",
    "run_compensation",
    "MapSettings",
    "MapRun",
    "build_map",
    "Grid",
    "minimum_curvature",
    "QualitySettings",
    "QualityRun",
    "run_quality",
    "AuditSettings",
    "AuditResult",
    "run_audit",
    "VectorRun",
    "run_vector",
]

if TYPE_CHECKING:  # what the names are, for type checkers and editors
    from pipeline.audit import AuditResult, AuditSettings, run_audit
    from pipeline.compensate import (
        CompensationModel,
        FitSettings,
        figure_of_merit,
        fit_compensation,
    )
    from pipeline.compensate.stage import CompensationRun, run_compensation
    from pipeline.config import Config
    from pipeline.errors import AeromagError
    from pipeline.flight import Flight
    from pipeline.io import OutputChannel, read_flight, write_with_new_channels
    from pipeline.io.inspect import inspect_recording
    from pipeline.maps.grid import Grid, minimum_curvature
    from pipeline.maps.stage import MapRun, MapSettings, build_map
    from pipeline.quality import QualityRun, QualitySettings, run_quality
    from pipeline.segment import Segmentation, SegmentParams, segment_flight
    from pipeline.vector.stage import VectorRun, run_vector


def __getattr__(name: str) -> object:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'pipeline' has no attribute {name!r}")
    from importlib import import_module

    value = getattr(import_module(module), name)
    globals()[name] = value  # later look-ups skip this hook
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
