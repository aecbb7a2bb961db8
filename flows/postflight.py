"""The post-flight flow.

ingest -> despike (the scalar magnetometer) -> segment -> compensate (each configured T-L
model and AGG-TL) -> audit -> extended model -> vector stage (when a fluxgate exists) ->
anomaly reduction, leveling, gridding, ARIMA-Kalman filter -> quality -> navigation on the
flight's own map (validation lines, ``[navigate]``) -> write (output MCAP, summary JSON,
report, figures).

The order lives in :func:`postflight_steps`, a plain function that calls each stage through a
``call`` hook: the Prefect flow passes tasks (results persisted in Prefect's local result
storage, keyed by the recording's hash, the configuration's hash and the stage, so a failed run
resumes after the last finished task; the results are deleted once the run has written its
outputs), archive workers pass plain calls. Tasks wrap
``flows.stages`` functions, which wrap ``pipeline``.
"""

from __future__ import annotations

import hashlib
import shutil
import time
from collections.abc import Callable
from functools import cache
from pathlib import Path
from typing import Any

from prefect import flow, task

from flows import stages
from flows.errors import install_one_line_errors
from pipeline.config import Config
from pipeline.report import sha256_file


def postflight_steps(
    recording: str, out_dir: str, cfg: Config, call: Callable[..., Any]
) -> dict[str, Any]:
    """Every stage in order; ``call(stage, *args)`` runs one (see the module docstring).

    The seconds of each stage (summed over calls: ``compensate`` covers every model) go to
    the write stage, which puts them in the summary (``timings_s``)."""
    timings: dict[str, float] = {}
    plain_call = call

    def call(stage: str, *args):
        t0 = time.perf_counter()
        try:
            return plain_call(stage, *args)
        finally:
            timings[stage] = timings.get(stage, 0.0) + time.perf_counter() - t0

    flight = call("ingest", recording)
    timings["ingest"] += stages.validated_read_s()  # read before the flow started
    despiked = None
    if cfg["despike"]["enabled"]:  # every later stage sees the despiked scalar
        flight, despiked = call("despike", flight, cfg)
    seg, why = call("segment", flight)
    runs: dict[str, Any] = {}
    audit = vector = map_run = quality = None
    if seg is not None and flight.has("vector_x_nT") and seg.passes():
        for m in stages.configured_models(flight, cfg):
            runs[m] = call("compensate", flight, seg, m, cfg)
        if cfg["audit"]["enabled"]:
            audit = call("audit", flight, seg, cfg)
    if cfg["vector"]["enabled"] and flight.has("vector_x_nT", "roll_deg"):
        vector = call("vector", flight, seg, cfg)
    final = stages.final_field(runs, audit)
    if (
        final is not None
        and seg is not None
        and seg.mask("survey").sum() > 100
        and flight.has("lat_deg", "alt_m")
    ):
        map_run = call("map", flight, seg, final[1], cfg)
        quality = call("quality", flight, seg, runs, audit, cfg)
    nav = None
    if cfg["navigate"]["enabled"]:  # skipped (one log line) without validation lines or map
        nav = (
            call("navigate", flight, seg, final[1], map_run, cfg)
            if map_run is not None
            else "no map"
        )
    return call(
        "write",
        recording,
        out_dir,
        cfg,
        flight,
        seg,
        why,
        runs,
        audit,
        vector,
        map_run,
        quality,
        timings,
        despiked,
        nav,
    )


# --------------------------------------------------------------------------------------------
install_one_line_errors()

STAGE_FUNCTIONS: dict[str, Callable[..., Any]] = {
    "ingest": stages.ingest_stage,
    "despike": stages.despike_stage,
    "segment": stages.try_segment,
    "compensate": stages.compensate_stage,
    "audit": stages.audit_stage,
    "vector": stages.vector_stage,
    "map": stages.map_stage,
    "quality": stages.quality_stage,
    "navigate": stages.navigate_stage,
    "write": stages.write_stage,
}


def _cache_key(context, parameters) -> str:
    # a folder per (recording, configuration) under Prefect's local result storage
    return f"aeromag/{parameters['key']}/{parameters['stage']}-{parameters['variant']}"


@cache
def code_fingerprint() -> str:
    """Hash of the installed pipeline and flow code: resumable results of one version are
    never unpickled into another (a stage's objects change shape between versions)."""
    import pipeline

    h = hashlib.sha256()
    for root in (Path(pipeline.__file__).parent, Path(__file__).parent):
        for p in sorted(root.rglob("*.py")):
            h.update(p.read_bytes())
    return h.hexdigest()[:12]


def run_key(recording: str, cfg: Config) -> str:
    """Cache folder name of one recording, configuration and code version."""
    return f"{sha256_file(recording)[:16]}-{cfg.hash[:16]}-{code_fingerprint()}"


def cache_folder(key: str) -> Path:
    """Where the persisted stage results of run ``key`` live (under Prefect's local storage)."""
    from prefect.settings import PREFECT_LOCAL_STORAGE_PATH

    return Path(PREFECT_LOCAL_STORAGE_PATH.value()) / "aeromag" / key


@task(name="stage", cache_key_fn=_cache_key, persist_result=True)
def _stage(stage: str, key: str, variant: str, args: tuple) -> Any:
    return STAGE_FUNCTIONS[stage](*args)


@task(name="write-outputs")
def _write(args: tuple) -> Any:
    return stages.write_stage(*args)


@flow(name="postflight", log_prints=False)
def postflight(recording: str, out_dir: str, config_path: str | None = None) -> dict[str, Any]:
    """Process one flight recording into an output MCAP, summary JSON and report."""
    recording, out_dir = str(recording), str(out_dir)
    cfg = Config.load(config_path)
    cfg.validate()
    key = run_key(recording, cfg)

    def call(stage: str, *args):
        if stage == "write":
            return _write(args)
        variant = args[2] if stage == "compensate" else ""
        t = _stage.with_options(
            name=stage, task_run_name=f"{stage}{'-' + variant if variant else ''}"
        )
        return t(stage, key, variant, args)

    result = postflight_steps(recording, out_dir, cfg, call)
    shutil.rmtree(cache_folder(key), ignore_errors=True)  # finished: nothing to resume
    return result


def run_plain(recording: str, out_dir: str, config_path: str | None = None) -> dict[str, Any]:
    """The same steps without Prefect tasks (archive workers, benchmarks)."""
    cfg = Config.load(config_path)
    cfg.validate()
    return postflight_steps(
        str(recording), str(out_dir), cfg, lambda stage, *args: STAGE_FUNCTIONS[stage](*args)
    )
