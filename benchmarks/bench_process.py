"""`aeromag process` against the official mcap reader, for flights of about 1, 2.5 and 5 h.

    .venv/bin/python benchmarks/bench_process.py [--hours 1,2.5,5] [--keep DIR]

For each flight (the demo survey stretched to about the given duration, 10 Hz, simulated and
written once; ``--keep`` keeps them between runs), in one run:

- the official reader's bare iteration over the file (``mcap.reader.make_reader(f)
  .iter_messages()``, log-time order, the default; nothing decoded);
- ``aeromag process FILE --out DIR`` as a child process (the command a user types: the
  Prefect flow with its temporary local server, started once beforehand on the same
  database so that every flight pays the same warm start): wall seconds and the child's peak
  resident memory (``wait4``; the largest of the CLI process and the server it started);
- the per-stage seconds and the flow process's own peak memory from the summary JSON
  (``timings_s``, ``peak_memory_mb``).

Prints a table with the ratios process / bare iteration and the fitted exponent k of
``process seconds ~ epochs^k`` (linear cost: k close to 1; the fixed cost of starting Prefect
pulls k below 1, so the stages' sum is fitted as well). Targets (issue 20): process <= 5x
the bare iteration, peak memory <= 1 GB for a 5 h flight, cost linear in duration. Exits
non-zero when a run fails or its outputs are wrong (never because something is slow).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from mcap.reader import make_reader
from report import finish

REPO = Path(__file__).resolve().parent.parent


def flight_file(hours: float, folder: Path) -> Path:
    """The demo survey stretched to about ``hours`` at 10 Hz (line length from the flight
    time: 2.02 h at 2000 m, 4.29 h at 4958 m), written once per folder."""
    from pipeline.simulate import Scenario, simulate, write_simulation

    path = folder / f"flight-{hours:g}h.mcap"
    if not path.exists():
        length = (hours - 0.486) / 7.67e-4
        sc = Scenario.load("demo", [f"survey.length_m={length:.0f}"])
        write_simulation(simulate(sc, 1), path)
    return path


def bare_iteration(path: Path) -> tuple[int, float]:
    """Messages and seconds of the official reader's bare iteration (log-time order)."""
    t = time.perf_counter()
    n = 0
    with path.open("rb") as f:
        for _ in make_reader(f).iter_messages():
            n += 1
    return n, time.perf_counter() - t


def run_process(path: Path, out: Path, env: dict[str, str]) -> tuple[float, float, str]:
    """``aeromag process`` in a child process: wall seconds, peak RSS (MB), stderr tail."""
    out.mkdir(parents=True, exist_ok=True)
    log = out / "stderr.txt"
    with log.open("wb") as f:
        t = time.perf_counter()
        proc = subprocess.Popen(
            [sys.executable, "-m", "flows.cli", "process", str(path), "--out", str(out)],
            env=env,
            cwd=REPO,
            stdout=subprocess.DEVNULL,
            stderr=f,
        )
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t
    proc.returncode = os.waitstatus_to_exitcode(status)
    err = log.read_text(errors="replace")
    if proc.returncode:
        raise RuntimeError(f"aeromag process {path.name} failed: {err[-1500:]}")
    return wall, usage.ru_maxrss / 1024, err


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--hours", default="1,2.5,5")
    ap.add_argument("--keep", type=Path, help="folder to keep the simulated flights in")
    args = ap.parse_args()
    rows: list[tuple[str, str]] = []
    errors: list[str] = []
    hours = [float(x) for x in args.hours.split(",")]
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.keep or Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        t = time.perf_counter()
        files = [flight_file(h, folder) for h in hours]
        rows.append(
            ("flights simulated and written (or reused)", f"{time.perf_counter() - t:.1f} s")
        )
        env = {
            **os.environ,
            "PREFECT_HOME": str(Path(tmp) / "prefect"),
            "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
            "DO_NOT_TRACK": "1",
            "PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS": "90",
            "PREFECT_LOGGING_LEVEL": "WARNING",
            "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]),
        }
        env.pop("PREFECT_API_URL", None)
        # warm-up: the first run creates the Prefect database (slower than any later start)
        warm, _, _ = run_process(REPO / "fixtures" / "box_uav.mcap", Path(tmp) / "warm", env)
        rows.append(("warm-up (box fixture; creates the Prefect database)", f"{warm:.1f} s"))
        res = []
        for h, path in zip(hours, files, strict=True):
            n, bare = bare_iteration(path)
            try:
                wall, rss, _ = run_process(path, Path(tmp) / f"out-{h:g}", env)
            except RuntimeError as exc:
                errors.append(str(exc))
                continue
            summary = json.loads(
                (Path(tmp) / f"out-{h:g}" / f"{path.stem}.summary.json").read_text()
            )
            stages = summary.get("timings_s", {})
            own_mb = summary.get("peak_memory_mb", float("nan"))
            epochs = summary["input"]["epochs"]
            dur_h = summary["input"]["duration_s"] / 3600
            if "quality" not in summary or "map" not in summary:
                errors.append(f"{path.name}: the summary has no map or quality section")
            res.append((epochs, bare, wall, sum(stages.values()) or np.nan, rss))
            rows += [
                (
                    f"{dur_h:.2f} h flight: file",
                    f"{n} messages, {path.stat().st_size / 1e6:.1f} MB, {epochs} epochs",
                ),
                (f"{dur_h:.2f} h: official reader, bare iteration", f"{bare:.2f} s"),
                (
                    f"{dur_h:.2f} h: aeromag process (wall; ratio to bare, target <= 5x)",
                    f"{wall:.1f} s ({wall / bare:.1f}x)",
                ),
                (
                    f"{dur_h:.2f} h: stages (summary timings_s, sum)",
                    ", ".join(f"{k} {v:.1f}" for k, v in stages.items())
                    + f"; sum {sum(stages.values()):.1f} s",
                ),
                (
                    f"{dur_h:.2f} h: peak memory (target <= 1 GB at 5 h)",
                    f"{rss:.0f} MB child process; flow process {own_mb:.0f} MB (summary)",
                ),
            ]
    if len(res) >= 2:
        e, bare, wall, stage_sum, _ = np.array(res, float).T
        k_wall = np.polyfit(np.log(e), np.log(wall), 1)[0]
        k_bare = np.polyfit(np.log(e), np.log(bare), 1)[0]
        line = f"process wall {k_wall:.2f}, bare iteration {k_bare:.2f}"
        if np.isfinite(stage_sum).all():
            line += f", stages' sum {np.polyfit(np.log(e), np.log(stage_sum), 1)[0]:.2f}"
        rows.append(("fitted exponent k in seconds ~ epochs^k (linear: k ~ 1)", line))
        rows.append(
            (
                "process seconds per hour of flight",
                ", ".join(f"{w / (n_ / 36000):.1f}" for n_, w in zip(e, wall, strict=True)),
            )
        )
    return finish(rows, errors)


if __name__ == "__main__":
    sys.exit(main())
