"""``aeromag campaign``: several processed sorties over one area, levelled jointly and
gridded once (:mod:`pipeline.campaign`).

The steps live in :func:`campaign_steps`, which runs the per-flight work through a ``run_all``
hook: the Prefect flow submits it as tasks to its task runner (a Dask cluster from the CLI,
as ``reprocess``: reading each flight's line data, and finding the crossovers within each
flight and between each pair of flights), the plain variant calls it in turn. The joint
solve, the grid and the outputs follow in the flow itself.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from prefect import flow, task

from flows.errors import install_one_line_errors
from pipeline.config import Config

install_one_line_errors()


def _read(index: int, info, frame_args: tuple):
    from pipeline.campaign.sorties import read_sortie
    from pipeline.geo.projected import GridFrame

    return read_sortie(index, info, GridFrame(*frame_args))


def _crossovers(a, b, min_angle_deg: float):
    from pipeline.campaign.joint import sortie_crossovers

    return sortie_crossovers(a, b, min_angle_deg)


WORK: dict[str, Callable[..., Any]] = {"read": _read, "crossovers": _crossovers}


def campaign_steps(
    folder: str, out_dir: str, cfg: Config, run_all: Callable[[str, list[tuple]], list]
) -> dict[str, Any]:
    """Check, read, find crossovers, level jointly, grid, write (see the module docstring).

    ``run_all(kind, args)`` runs ``WORK[kind]`` on each argument tuple and returns the
    results in order.
    """
    from pipeline.campaign.outputs import write_campaign
    from pipeline.campaign.sorties import campaign_frame, validate_campaign
    from pipeline.campaign.stage import run_campaign

    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    infos = validate_campaign(folder)
    frame = campaign_frame(infos, cfg.campaign_settings().crs_epsg)
    origin = frame.args()
    timings["check"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    sorties = run_all("read", [(k, info, origin) for k, info in enumerate(infos)])
    timings["read"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    settings = cfg.campaign_settings()
    angle = settings.min_crossing_angle_deg
    pairs = [(a, None) for a in sorties] + [
        (a, b) for i, a in enumerate(sorties) for b in sorties[i + 1 :]
    ]
    found = run_all("crossovers", [(a, b, angle) for a, b in pairs])
    xs, between = [], []
    for (_, b), part in zip(pairs, found, strict=True):
        xs += part
        between += [b is not None] * len(part)
    timings["crossovers"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    run = run_campaign(sorties, frame, xs, np.array(between, bool), settings)
    timings["level_and_grid"] = time.perf_counter() - t0
    return write_campaign(run, out_dir, cfg.hash, cfg["export"]["formats"], timings)


@task(name="campaign-read-sortie")
def _read_task(index: int, info, origin):
    return _read(index, info, origin)


@task(name="campaign-crossovers")
def _crossovers_task(a, b, min_angle_deg: float):
    return _crossovers(a, b, min_angle_deg)


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


def run_plain(folder: str | Path, out_dir: str | Path, config_path: str | None = None):
    """The same steps without Prefect (tests, benchmarks)."""
    cfg = Config.load(config_path)
    cfg.validate()
    return campaign_steps(
        str(folder), str(out_dir), cfg, lambda kind, args: [WORK[kind](*a) for a in args]
    )
