"""Runs more than one benchmark makes (not a benchmark itself): a long flight simulated and taken
through the post-flight steps, timed per stage."""

from __future__ import annotations

import resource
import time
from pathlib import Path

from pipeline.simulate import Scenario, simulate, write_simulation


def long_flight(
    hours: float, tmp: Path, rows: list, errors: list, label: str = "long flight"
) -> tuple[int, float]:
    """Simulate a flight of about ``hours`` and run the post-flight steps; returns (epochs,
    wall seconds)."""
    from flows import postflight as pf
    from pipeline.config import Config

    # flight time grows with the line length: 2.02 h at 2000 m (the demo), 4.29 h at 4958 m
    length = (hours - 0.486) / 7.67e-4
    sc = Scenario.load("demo", [f"survey.length_m={length:.0f}"])
    t0 = time.perf_counter()
    sim = simulate(sc, 1)
    tmp.mkdir(parents=True, exist_ok=True)
    path = write_simulation(sim, tmp / "long.mcap")
    t_sim = time.perf_counter() - t0
    stage_s: dict[str, float] = {}

    def call(step, *args):
        t = time.perf_counter()
        out = step.function(*args)
        stage_s[step.name] = stage_s.get(step.name, 0.0) + time.perf_counter() - t
        return out

    cfg = Config.load()
    t0 = time.perf_counter()
    summary = pf.postflight_steps(str(path), str(tmp / "long-out"), cfg, call)
    total = time.perf_counter() - t0
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    if "quality" not in summary:
        errors.append("the long flight has no quality section")
    epochs = summary["input"]["epochs"]
    rows += [
        (
            f"{label}: {sim.trajectory.duration_s / 3600:.2f} h, {epochs} epochs",
            f"simulated and written in {t_sim:.1f} s",
        ),
        (f"{label}: post-flight steps (target <= 60 s for 5 h)", f"{total:.1f} s"),
        (f"{label}: per stage", ", ".join(f"{k} {v:.1f} s" for k, v in stage_s.items())),
        (f"{label}: peak memory (process so far)", f"{peak_mb:.0f} MB"),
    ]
    return epochs, total
