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
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

from prefect import flow, task

from flows import stages
from flows.errors import install_one_line_errors
from pipeline.config import Config
from pipeline.products.summary import sha256_file


@dataclass(frozen=True)
class Step:
    """One stage of the post-flight flow: its name (the Prefect task's name and cache key)
    and the ``flows.stages`` function that runs it."""

    name: str
    function: Callable[..., Any]


INGEST = Step("ingest", stages.ingest_stage)
DESPIKE = Step("despike", stages.despike_stage)
SEGMENT = Step("segment", stages.try_segment)
COMPENSATE = Step("compensate", stages.compensate_stage)
AUDIT = Step("audit", stages.audit_stage)
VECTOR = Step("vector", stages.vector_stage)
MAP = Step("map", stages.map_stage)
QUALITY = Step("quality", stages.quality_stage)
NAVIGATE = Step("navigate", stages.navigate_stage)
WRITE = Step("write", stages.write_stage)
STEPS = (INGEST, DESPIKE, SEGMENT, COMPENSATE, AUDIT, VECTOR, MAP, QUALITY, NAVIGATE, WRITE)
STEP_BY_NAME = {s.name: s for s in STEPS}


def postflight_steps(
    recording: str, out_dir: str, cfg: Config, call: Callable[..., Any]
) -> dict[str, Any]:
    """Every stage in order; ``call(step, *args)`` runs one :class:`Step` (see the module
    docstring): ``step.function(*args)``, or a Prefect task around it.

    The seconds of each stage (summed over calls: ``compensate`` covers every model) go to
    the write stage, which puts them in the summary (``timings_s``)."""
    timings: dict[str, float] = {}
    plain_call = call

    def call(step: Step, *args):
        t0 = time.perf_counter()
        try:
            return plain_call(step, *args)
        finally:
            timings[step.name] = timings.get(step.name, 0.0) + time.perf_counter() - t0

    flight = call(INGEST, recording)
    timings["ingest"] += stages.validated_read_s()  # read before the flow started
    despiked = None
    if cfg["despike"]["enabled"]:  # every later stage sees the despiked scalar
        flight, despiked = call(DESPIKE, flight, cfg)
    seg, why = call(SEGMENT, flight)
    res = stages.FlightResults(flight, seg, why, despiked=despiked)
    if seg is not None and flight.has("vector_x_nT") and seg.passes():
        for m in stages.configured_models(flight, cfg):
            res.runs[m] = call(COMPENSATE, flight, seg, m, cfg)
        if cfg["audit"]["enabled"]:
            res.audit = call(AUDIT, flight, seg, cfg)
    if cfg["vector"]["enabled"] and flight.has("vector_x_nT", "roll_deg"):
        res.vector = call(VECTOR, flight, seg, cfg)
    final = stages.final_field(res.runs, res.audit)
    if (
        final is not None
        and seg is not None
        and seg.mask("survey").sum() > 100
        and flight.has("lat_deg", "alt_m")
    ):
        res.map_run = call(MAP, flight, seg, final[1], cfg)
        res.quality = call(QUALITY, flight, seg, res.runs, res.audit, cfg)
    if cfg["navigate"]["enabled"]:  # skipped (one log line) without validation lines or map
        res.nav = (
            call(NAVIGATE, flight, seg, final[1], res.map_run, cfg)
            if res.map_run is not None
            else "no map"
        )
    return call(WRITE, recording, out_dir, cfg, res, timings)


# --------------------------------------------------------------------------------------------
install_one_line_errors()


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
    return STEP_BY_NAME[stage].function(*args)


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

    def call(step: Step, *args):
        if step is WRITE:
            return _write(args)
        variant = args[2] if step is COMPENSATE else ""
        t = _stage.with_options(
            name=step.name, task_run_name=f"{step.name}{'-' + variant if variant else ''}"
        )
        return t(step.name, key, variant, args)

    result = postflight_steps(recording, out_dir, cfg, call)
    shutil.rmtree(cache_folder(key), ignore_errors=True)  # finished: nothing to resume
    return result


def run_plain(recording: str, out_dir: str, config_path: str | None = None) -> dict[str, Any]:
    """The same steps without Prefect tasks (archive workers, benchmarks)."""
    cfg = Config.load(config_path)
    cfg.validate()
    return postflight_steps(
        str(recording), str(out_dir), cfg, lambda step, *args: step.function(*args)
    )
