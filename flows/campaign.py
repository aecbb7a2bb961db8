"""``aeromag campaign``: the steps of :func:`pipeline.run.campaign.campaign_steps`, whose
per-flight work (reading each flight's line data, the crossovers within each flight and
between each pair of flights) the Prefect flow submits as tasks to its task runner (a Dask
cluster from the CLI, as ``reprocess``); ``run_plain`` calls it in turn, without Prefect.
"""

from __future__ import annotations

from typing import Any

from prefect import flow, task

from flows.errors import install_one_line_errors
from pipeline.config import Config
from pipeline.run.campaign import campaign_steps, crossovers, read, run_plain

__all__ = ["campaign", "run_plain"]

install_one_line_errors()


# each task installs the filter where it runs: on a Dask worker the import-time install
# above has not run, and the worker logs a failing task with its traceback
@task(name="campaign-read-sortie")
def _read_task(index: int, info, origin):
    install_one_line_errors()
    return read(index, info, origin)


@task(name="campaign-crossovers")
def _crossovers_task(a, b, min_angle_deg: float):
    install_one_line_errors()
    return crossovers(a, b, min_angle_deg)


TASKS = {"read": _read_task, "crossovers": _crossovers_task}


@flow(name="campaign", log_prints=False)
def campaign(folder: str, out_dir: str, config_path: str | None = None) -> dict[str, Any]:
    """Merge the processed recordings of ``folder`` into one jointly levelled campaign in
    ``out_dir``; the per-flight work runs on the flow's task runner."""
    cfg = Config.load(config_path)
    cfg.validate()

    def run_all(kind: str, args: list[tuple]) -> list:
        futures = [TASKS[kind].submit(*a) for a in args]
        return [f.result() for f in futures]

    return campaign_steps(str(folder), str(out_dir), cfg, run_all)
