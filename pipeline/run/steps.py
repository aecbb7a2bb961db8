"""The post-flight stages, each one function of the flight, its segmentation and the
configuration (called in order by :func:`pipeline.run.postflight.postflight_steps`, as
Prefect tasks by ``flows/postflight.py`` or plainly), and :class:`FlightResults`, what they
made of one flight.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pipeline.compensate.stage import CompensationRun, run_compensation
from pipeline.config import Config
from pipeline.despike import DespikeResult, despike_flight, despike_scalar
from pipeline.errors import AeromagError
from pipeline.flight import Flight
from pipeline.io.reader import read_flight
from pipeline.maps.grid import Grid
from pipeline.maps.stage import build_map
from pipeline.quality.stage import QualityRun
from pipeline.run.fields import assess_quality, final_field, quality_fields
from pipeline.segment import Segmentation


def ingest_stage(recording: str) -> Flight:
    """Ingest: read, check and align the recording (:func:`pipeline.io.reader.read_flight`).

    Returns
    -------
    Flight
    """
    return read_flight(recording)


def despike_stage(flight: Flight, cfg) -> tuple[Flight, DespikeResult]:
    """Despike the primary scalar magnetometer (Hampel test on its 4th difference) with the
    configuration's ``[despike]`` settings.

    Returns
    -------
    Flight
        The flight with the spike samples replaced (the same object when none was found).
    DespikeResult
    """
    return despike_flight(flight, cfg.despike_settings())


def despike_step(flight: Flight, cfg) -> DespikeResult:
    """:func:`despike_stage`'s result alone (the post-flight step: a resumable run persists
    the result, not a second copy of the flight;
    :func:`pipeline.despike.repaired_flight` rebuilds it).

    Returns
    -------
    DespikeResult
    """
    return despike_scalar(flight, cfg.despike_settings())


def compensate_stage(
    flight: Flight, seg: Segmentation, model: str, cfg, audit: dict | None = None
) -> CompensationRun:
    """Compensate: fit ``model`` (``tl16``, ``tl18``, ``agg-tl``, ``tl-plus`` or ``tl-nn``)
    with the configuration's settings; ``audit``: the audit's summary, whose
    ``unexplained.nuisances`` tl-plus tries first.

    Returns
    -------
    CompensationRun
    """
    return run_compensation(flight, seg, cfg.fit_settings(model), audit=audit)


def audit_stage(flight: Flight, seg: Segmentation, cfg):
    """Audit: :func:`pipeline.audit.run_audit` with the configuration's settings.

    Returns
    -------
    AuditResult
    """
    from pipeline.audit import run_audit

    return run_audit(flight, seg, cfg.audit_settings())


def vector_run(flight: Flight, seg: Segmentation | None, cfg: Config):
    """The vector magnetometer stage with ``[vector]``: its method and the fuzzy-R settings
    of ``component-kf``.

    Returns
    -------
    VectorRun

    Raises
    ------
    AeromagError, ValueError
        See :func:`pipeline.vector.stage.run_vector`.
    """
    from pipeline.vector.stage import run_vector

    return run_vector(flight, seg, cfg["vector"]["method"], settings=cfg["vector"])


def vector_stage(flight: Flight, seg: Segmentation | None, cfg):
    """Vector magnetometer stage with the configured method (:func:`vector_run`).

    Returns
    -------
    VectorRun or str
        The run, or the one-line reason it could not run (logged; the other stages go on).
    """
    try:
        return vector_run(flight, seg, cfg)
    except (AeromagError, ValueError) as exc:
        return str(exc)  # reported in the log; the other stages go on


def enhancement_grids(map_run, cfg) -> dict[str, Grid]:
    """The configured enhancements of a map run's grid (``enhance.source``), RTP with the
    main field at the map origin (topic -> grid)."""
    from pipeline.maps.enhance import enhance

    st = cfg.enhance_settings()
    grid = map_run.filtered if st.source == "anomaly_filtered" else map_run.grid
    incl = map_run.main_field[1]
    try:
        return enhance(grid, st.products, incl, map_run.grid_declination_deg, st.pad_fraction)
    except ValueError as exc:
        raise AeromagError(f"enhance: {exc}", channel=f"/map/{st.source}") from None


def enhancement_skipped(map_run, cfg) -> list[str]:
    """Why configured enhancements of the map run are not computed
    (:func:`pipeline.maps.enhance.refused`)."""
    from pipeline.maps.enhance import refused

    return refused(cfg.enhance_settings().products, map_run.main_field[1])


def map_stage(flight: Flight, seg: Segmentation, comp: np.ndarray, cfg, field: str = "compensated"):
    """Map: reduce, level, grid and filter ``comp`` (compensated field, nT, one per epoch;
    ``field``: which, :attr:`pipeline.maps.stage.MapRun.field`).

    Returns
    -------
    MapRun
    """
    return build_map(flight, seg, comp, cfg.map_settings(), field)


def navigate_stage(flight: Flight, seg: Segmentation | None, comp: np.ndarray, map_run, cfg):
    """Navigation on the flight's own map (``[navigate]``): the validation lines flown with a
    simulated INS aided by the map (``navigate.map``), as ``aeromag navigate`` does.

    Returns
    -------
    NavigationRun or str
        The run, or why navigation was skipped (no validation lines, no map, the map not
        covering them): one log line, never an error.
    """
    from pipeline.navigation.map_io import frame_map
    from pipeline.navigation.stage import run_navigation

    if map_run is None:
        return "no map"
    if seg is None or seg.mask("validation").sum() < 10:
        return "no validation lines"
    which = cfg["navigate"]["map"]
    grid = map_run.filtered if which == "anomaly_filtered" else map_run.grid
    geomap = frame_map(grid, map_run.frame, f"/map/{which}", f"this flight's /map/{which}")
    geomap.sigma, geomap.error_length_m = map_run.uncertainty, map_run.error_length_m
    try:
        return run_navigation(flight, seg, comp, geomap, cfg.navigation_settings())
    except AeromagError as exc:
        return exc.problem
    except (ValueError, np.linalg.LinAlgError) as exc:  # reported; the other outputs go on
        return f"{type(exc).__name__}: {exc}"


def navigability_stage(flight: Flight, comp: np.ndarray, map_run, cfg):
    """Navigability of the flight's own map (``[navigate] navigability``): the position CRLB
    a vehicle reaches flying into each cell
    (:func:`pipeline.navigation.navigability.navigability_map`, as ``aeromag navigability``,
    all four headings) at the survey's median ground speed, with the map's
    ``/map/uncertainty`` and the compensated field's white noise.

    Returns
    -------
    tuple of (Grid, dict) or str
        The grid (m) and its summary, or why it was skipped (one log line, never an error).
    """
    from pipeline.navigation.map_io import frame_map
    from pipeline.navigation.navigability import navigability_map, track_speed_mps
    from pipeline.noise import white_noise_nT

    if map_run is None:
        return "no map"
    which = cfg["navigate"]["map"]
    grid = map_run.filtered if which == "anomaly_filtered" else map_run.grid
    geomap = frame_map(grid, map_run.frame, f"/map/{which}", f"this flight's /map/{which}")
    geomap.sigma, geomap.error_length_m = map_run.uncertainty, map_run.error_length_m
    speed = track_speed_mps(flight, geomap)
    if not np.isfinite(speed):
        return "the track does not move"
    t = flight.data["time_s"].to_numpy(float)
    sensor = white_noise_nT(np.asarray(comp, float), t)
    try:
        return navigability_map(flight, geomap, sensor, cfg.navigation_settings(), speed)
    except (ValueError, np.linalg.LinAlgError) as exc:  # reported; the other outputs go on
        return f"{type(exc).__name__}: {exc}"


def quality_stage(flight: Flight, seg: Segmentation, runs: dict, audit, cfg) -> QualityRun:
    """Quality: every processing state (raw, each model, the extended model) compared at
    the validation lines, with the 12-box FOM table when the calibration boxes were found.

    Returns
    -------
    QualityRun
    """
    fields, _, _ = quality_fields(flight, seg, runs, cfg)
    final = final_field(runs, audit)
    if final is not None and final[0] == "extended":
        fields["extended"] = final[1]
    return assess_quality(flight, seg, fields, cfg)


@dataclass
class FlightResults:
    """What the post-flight steps made of one flight, handed to
    :func:`pipeline.run.outputs.write_outputs`.

    ``runs``: each configured model's compensation (model name -> run); ``audit``, ``vector``,
    ``map_run``, ``quality``: the stages' results (None: not run); ``despiked``: the despike
    step's result; ``nav``: :func:`navigate_stage`'s result (a run, a skip reason, or None:
    not enabled); ``navigability``: :func:`navigability_stage`'s (likewise); ``why``: why
    segmentation failed ("" when it did not); ``map_skipped``: why there is no map.
    """

    flight: Flight
    seg: Any = None  # pipeline.segment.Segmentation
    why: str = ""
    runs: dict[str, CompensationRun] = field(default_factory=dict)
    audit: Any = None  # pipeline.audit.AuditResult
    vector: Any = None  # pipeline.vector.stage.VectorRun
    map_run: Any = None  # pipeline.maps.stage.MapRun
    quality: Any = None  # pipeline.quality.QualityRun
    despiked: DespikeResult | None = None
    nav: Any = None  # pipeline.navigation.stage.NavigationRun | str
    navigability: Any = None  # (Grid, summary dict) | str
    map_skipped: str = ""  # why there is no map (pipeline.maps.stage.map_refusal)
