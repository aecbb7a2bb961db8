"""The post-flight flow: the steps of :func:`pipeline.run.postflight.postflight_steps`, each
a Prefect task.

Task results are persisted in Prefect's local result storage, keyed by the recording's hash,
the configuration's hash and the stage, so a failed run resumes after the last finished task;
the results are deleted once the run has written its outputs. Archive workers run the same
steps without tasks (:func:`pipeline.run.postflight.run_plain`).
"""

from __future__ import annotations

import re
import shutil
from pathlib import Path
from typing import Any

from prefect import flow, task

from flows.errors import install_one_line_errors
from pipeline.config import Config
from pipeline.run.postflight import (
    COMPENSATE,
    INGEST,
    STEPS,
    WRITE,
    Step,
    checked,
    postflight_steps,
    run_key,
    run_plain,
    take_checked,
)

__all__ = ["INGEST", "STEP_BY_NAME", "STEPS", "Step", "checked", "postflight", "run_plain"]
STEP_BY_NAME = {s.name: s for s in STEPS}  # the tasks run the step of their name


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

    flight, read_s = take_checked(recording)
    result = postflight_steps(recording, out_dir, cfg, call, flight, read_s)
    shutil.rmtree(cache_folder(key), ignore_errors=True)  # finished: nothing to resume
    return result
