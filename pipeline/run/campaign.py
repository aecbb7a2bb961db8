"""A campaign's steps, without Prefect: several processed sorties over one area checked,
read, their crossovers found within and between flights, levelled jointly, gridded once and
written (:mod:`pipeline.campaign`). ``flows/campaign.py`` runs the per-flight work as tasks.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.config import Config


def read(index: int, info, frame_args: tuple):
    """One sortie's line data in the campaign's grid frame (``GridFrame(*frame_args)``)."""
    from pipeline.campaign.sorties import read_sortie
    from pipeline.geo.projected import GridFrame

    return read_sortie(index, info, GridFrame(*frame_args))


def crossovers(a, b, min_angle_deg: float):
    """The crossovers within sortie ``a`` (``b`` None) or between ``a`` and ``b``."""
    from pipeline.campaign.joint import sortie_crossovers

    return sortie_crossovers(a, b, min_angle_deg)


WORK: dict[str, Callable[..., Any]] = {"read": read, "crossovers": crossovers}


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


def run_plain(folder: str | Path, out_dir: str | Path, config_path: str | None = None):
    """The campaign's steps without Prefect (tests, benchmarks).

    Returns
    -------
    dict
        The campaign summary.
    """
    cfg = Config.load(config_path)
    cfg.validate()
    return campaign_steps(
        str(folder), str(out_dir), cfg, lambda kind, args: [WORK[kind](*a) for a in args]
    )
