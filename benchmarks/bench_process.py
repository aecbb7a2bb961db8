"""`aeromag process` against the official mcap reader, on two survey shapes and two sizes each.

    .venv/bin/python benchmarks/bench_process.py [--hours 1,5] [--block-lines 12,45] [--keep DIR]

Flights (10 Hz, simulated and written once; ``--keep`` keeps them between runs):

- **demo**: the demo survey (15 lines, 700 m wide, ties every 500 m, the X lines, two
  calibration boxes) with its lines stretched to about the given hours: the line count stays,
  the lines grow;
- **block**: the ``uav-block`` scenario (45 lines x 2 km at 50 m, 3 ties 1 km apart, the X
  lines, one calibration box; about 5 h) and the same block with fewer lines (``--block-lines``):
  the lines stay 2 km, their count grows, so crossings grow with the square of the line count.

Per flight, in one run:

- the official reader's bare iteration over the file (``mcap.reader.make_reader(f)
  .iter_messages()``, log-time order, the default; nothing decoded);
- ``aeromag process FILE --out DIR`` as a child process (the command a user types: the
  Prefect flow with its temporary local server, started once beforehand on the same
  database so that every flight pays the same warm start): wall seconds and the child's peak
  resident memory (``wait4``; the largest of the CLI process and the server it started);
- the per-stage seconds and the flow process's own peak memory from the summary JSON
  (``timings_s``, ``peak_memory_mb``);
- ``aeromag audit FILE --json ... --report ...`` alone as a child process (issue 35's scale
  item: the audit of the file, reading it included): wall seconds and peak memory.

Prints a table with the ratios process / bare iteration and, per shape, the fitted exponent k
of ``seconds ~ epochs^k`` of the whole run, of the bare iteration and of every stage (linear
cost: k close to 1 or below; fixed costs pull k below 1). Targets (issues 35 and 37): process
and the audit command each <= 3x the bare iteration and peak memory <= 1 GB on every flight,
no stage's k above 1. Exits
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


def block_file(lines: int, folder: Path) -> Path:
    """The ``uav-block`` scenario with ``lines`` lines of 2 km at its 50 m spacing (45: the
    scenario itself, about 5 h at 10 Hz), written once per folder."""
    from pipeline.simulate import Scenario, simulate, write_simulation

    path = folder / f"block-{lines}lines.mcap"
    if not path.exists():
        sc = Scenario.load("uav-block")
        width = (lines - 1) * float(sc["survey"]["line_spacing_m"])
        sc = Scenario.load("uav-block", [f"survey.width_m={width:g}"])
        write_simulation(simulate(sc, 1), path)
    return path


def _written_apart(jobs: list, folder: Path) -> None:
    """Simulate and write the flights in a child process. A parent that simulated 5 h
    flights holds ~0.9 GB, and Linux carries a process's memory at exec into the peak
    (``ru_maxrss``) of what it runs: every command's peak would read as this process's."""
    import multiprocessing

    with multiprocessing.get_context("spawn").Pool(1) as pool:
        for func, arg in jobs:
            pool.apply(func, (arg, folder))


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
    return run_command(["process", str(path), "--out", str(out)], out, env)


def run_audit(path: Path, out: Path, env: dict[str, str]) -> tuple[float, float, str]:
    """``aeromag audit`` in a child process (the command alone: read, despike, segment,
    audit, report): wall seconds, peak RSS (MB), stderr tail."""
    args = ["audit", str(path), "--json", str(out / "audit.json"), "--report", str(out)]
    return run_command(args, out, env)


def run_command(args: list[str], out: Path, env: dict[str, str]) -> tuple[float, float, str]:
    """``aeromag ARGS`` in a child process: wall seconds, peak RSS (MB), stderr tail."""
    out.mkdir(parents=True, exist_ok=True)
    log = out / "stderr.txt"
    with log.open("wb") as f:
        t = time.perf_counter()
        proc = subprocess.Popen(
            [sys.executable, "-m", "flows.cli", *args],
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
        raise RuntimeError(f"aeromag {' '.join(args[:2])} failed: {err[-1500:]}")
    return wall, usage.ru_maxrss / 1024, err


def exponent(epochs: np.ndarray, seconds: np.ndarray) -> float:
    """k in ``seconds ~ epochs^k`` (least squares on logs; NaN with fewer than two sizes or a
    non-positive time)."""
    ok = np.isfinite(seconds) & (seconds > 0)
    if ok.sum() < 2 or np.ptp(np.log(epochs[ok])) == 0:
        return float("nan")
    return float(np.polyfit(np.log(epochs[ok]), np.log(seconds[ok]), 1)[0])


def exponent_rows(shape: str, res: list[dict]) -> list[tuple[str, str]]:
    """The fitted exponents of one shape's flights: the whole run, the bare iteration and
    every stage."""
    if len(res) < 2:
        return []
    e = np.array([r["epochs"] for r in res], float)
    whole = ", ".join(
        f"{name} {exponent(e, np.array([r[key] for r in res], float)):.2f}"
        for name, key in (
            ("process", "wall"),
            ("bare iteration", "bare"),
            ("stages' sum", "sum"),
            ("audit command", "audit command"),
        )
    )
    names = list(dict.fromkeys(k for r in res for k in r["stages"]))
    stages = ", ".join(
        f"{k} {exponent(e, np.array([r['stages'].get(k, np.nan) for r in res], float)):.2f}"
        for k in names
    )
    return [
        (f"{shape}: fitted exponent k in seconds ~ epochs^k (linear: k <= ~1)", whole),
        (f"{shape}: k per stage", stages),
    ]


def measure(path: Path, label: str, out: Path, env: dict[str, str], errors: list[str]):
    """Bare iteration and ``aeromag process`` of one flight: the table's rows and a record for
    the exponents (None when the run failed)."""
    n, bare = bare_iteration(path)
    try:
        wall, rss, _ = run_process(path, out, env)
        audit_wall, audit_rss, _ = run_audit(path, out / "audit", env)
    except RuntimeError as exc:
        errors.append(str(exc))
        return [], None
    summary = json.loads((out / f"{path.stem}.summary.json").read_text())
    stages = summary.get("timings_s", {})
    own_mb = summary.get("peak_memory_mb", float("nan"))
    epochs = summary["input"]["epochs"]
    dur_h = summary["input"]["duration_s"] / 3600
    if "quality" not in summary or "map" not in summary:
        errors.append(f"{path.name}: the summary has no map or quality section")
    tag = f"{label}, {dur_h:.2f} h"
    rows = [
        (
            f"{tag}: file",
            f"{n} messages, {path.stat().st_size / 1e6:.1f} MB, {epochs} epochs",
        ),
        (f"{tag}: official reader, bare iteration", f"{bare:.2f} s"),
        (
            f"{tag}: aeromag process (wall; ratio to bare, target <= 3x)",
            f"{wall:.1f} s ({wall / bare:.1f}x)",
        ),
        (
            f"{tag}: stages (summary timings_s, sum)",
            ", ".join(f"{k} {v:.1f}" for k, v in stages.items())
            + f"; sum {sum(stages.values()):.1f} s",
        ),
        (
            f"{tag}: peak memory (target <= 1 GB)",
            f"{rss:.0f} MB child process; flow process {own_mb:.0f} MB (summary)",
        ),
        (
            f"{tag}: aeromag audit alone (wall; ratio to bare, target <= 3x; peak, <= 1 GB)",
            f"{audit_wall:.1f} s ({audit_wall / bare:.1f}x); {audit_rss:.0f} MB",
        ),
    ]
    rec = {
        "epochs": epochs,
        "bare": bare,
        "wall": wall,
        "sum": sum(stages.values()) or np.nan,
        "audit command": audit_wall,
        "stages": stages,
    }
    return rows, rec


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--hours", default="1,5", help="demo survey stretched to these hours")
    ap.add_argument("--block-lines", default="12,45", help="line counts of the block survey")
    ap.add_argument("--keep", type=Path, help="folder to keep the simulated flights in")
    args = ap.parse_args()
    rows: list[tuple[str, str]] = []
    errors: list[str] = []
    hours = [float(x) for x in args.hours.split(",") if x]
    lines = [int(x) for x in args.block_lines.split(",") if x]
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.keep or Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        t = time.perf_counter()
        _written_apart([(flight_file, h) for h in hours] + [(block_file, k) for k in lines], folder)
        flights = [("demo", f"{h:g} h", flight_file(h, folder)) for h in hours]
        flights += [("block", f"{k} lines", block_file(k, folder)) for k in lines]
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
        res: dict[str, list[dict]] = {}
        for shape, size, path in flights:
            got, rec = measure(path, f"{shape} {size}", Path(tmp) / f"out-{path.stem}", env, errors)
            rows += got
            if rec is not None:
                res.setdefault(shape, []).append(rec)
        for shape, recs in res.items():
            rows += exponent_rows(shape, recs)
    return finish(rows, errors)


if __name__ == "__main__":
    sys.exit(main())
