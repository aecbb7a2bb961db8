"""The post-flight flow: the steps of :func:`pipeline.run.postflight.postflight_steps`, each
a Prefect task.

Task results are persisted in Prefect's local result storage, keyed by the recording's hash,
the configuration's hash and the stage, so a failed run resumes after the last finished task;
the results are deleted once the run has written its outputs. Archive workers run the same
steps without tasks (:func:`pipeline.run.postflight.run_plain`).
"""

from __future__ import annotations

import hashlib
import re
import shutil
import time
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from functools import cache
from pathlib import Path
from typing import Any

from prefect import flow, task

from flows.errors import install_one_line_errors
from pipeline.config import Config
from pipeline.errors import AeromagError
from pipeline.flight import Flight
from pipeline.io.reader import read_flight
from pipeline.products.summary import sha256_file
from pipeline.run.postflight import (
    COMPENSATE,
    INGEST,
    STEPS,
    WRITE,
    Step,
    postflight_steps,
    run_plain,
)

__all__ = ["INGEST", "STEP_BY_NAME", "STEPS", "Step", "checked", "postflight", "run_plain"]
STEP_BY_NAME = {s.name: s for s in STEPS}  # the tasks run the step of their name

# The flight the CLI read to check a recording before the flow (the recording's stat key,
# the flight, seconds to read it): set only inside :func:`checked`, so the flow it starts
# does not read the recording twice.
_CHECKED: ContextVar[tuple[tuple, Flight, float] | None] = ContextVar(
    "aeromag_checked_flight", default=None
)


def _stat_key(recording: str | Path) -> tuple:
    st = Path(recording).stat()
    return str(Path(recording).resolve()), st.st_size, st.st_mtime_ns


@contextmanager
def checked(recording: str | Path) -> Iterator[Flight]:
    """Read and check a recording (scan, channel contract, units) before any flow starts,
    so that bad input fails with one line and no Prefect run at all; a :func:`postflight`
    run on the same, unchanged file inside the block takes this flight over.

    Raises
    ------
    AeromagError
        Missing, empty or unreadable file, no scalar magnetometer, wrong units.
    """
    if not Path(recording).is_file():
        raise AeromagError("file not found", file=recording)
    t0 = time.perf_counter()
    flight = read_flight(recording)
    token = _CHECKED.set((_stat_key(recording), flight, time.perf_counter() - t0))
    try:
        yield flight
    finally:
        _CHECKED.reset(token)


def _take_checked(recording: str) -> tuple[Flight | None, float]:
    found = _CHECKED.get()
    if found is None:
        return None, 0.0
    try:
        same = found[0] == _stat_key(recording)
    except OSError:
        return None, 0.0
    return (found[1], found[2]) if same else (None, 0.0)


def publish_artifact(stem: str, markdown: str) -> None:
    """The report as a Prefect markdown artifact, when running inside a flow or task."""
    try:
        from prefect.artifacts import create_markdown_artifact
        from prefect.context import get_run_context

        get_run_context()
    except Exception:  # noqa: BLE001 - outside a run: no artifact
        return
    key = re.sub(r"[^a-z0-9-]", "-", f"aeromag-{stem}".lower())[:100]
    create_markdown_artifact(markdown=markdown, key=key, description="post-flight summary")


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
    summary = WRITE.function(*args)
    report = Path(summary["outputs"]["report"])
    publish_artifact(Path(args[0]).stem, report.read_text())
    return summary


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

    flight, read_s = _take_checked(recording)
    result = postflight_steps(recording, out_dir, cfg, call, flight, read_s)
    shutil.rmtree(cache_folder(key), ignore_errors=True)  # finished: nothing to resume
    return result
