"""Operations: archive reprocessing on 1 vs 2 Dask workers, and one long flight end to end.

    .venv/bin/python benchmarks/bench_ops.py [--flights 8] [--hours 5] [--skip-archive]

Archive: ``--flights`` simulated uav-small flights (different seeds) reprocessed by the
``reprocess-archive`` flow on a local Dask cluster of 1, then 2 worker processes (fresh
output folders; a local Prefect server is started when none is configured). Long flight: the
demo survey stretched to about ``--hours`` h at 10 Hz, processed by the post-flight steps
without Prefect, with the time of each stage and the peak memory. Targets (issue 8):
speed-up >= 1.7x, long flight <= 60 s on 2 cores. Exits non-zero if a recording fails or an
output is missing (never because something is slow).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

from report import finish
from runs import long_flight

from pipeline.simulate import Scenario, simulate, write_simulation


def archive(n: int, tmp: Path, rows: list, errors: list) -> None:
    from flows.archive import dask_runner, prefect_api, reprocess_archive

    arch = tmp / "archive"
    arch.mkdir()
    for k in range(n):
        write_simulation(simulate(Scenario.load("uav-small"), 100 + k), arch / f"f{k:02d}.mcap")
    times = {}
    with prefect_api():
        for workers in (1, 2):
            t0 = time.perf_counter()
            res = reprocess_archive.with_options(task_runner=dask_runner(workers, None))(
                str(arch), str(tmp / f"out{workers}")
            )
            times[workers] = time.perf_counter() - t0
            if res["processed"] != n:
                errors.append(f"{workers} workers: {res}")
    rows += [
        (f"archive of {n} flights, 1 worker", f"{times[1]:.1f} s"),
        (f"archive of {n} flights, 2 workers", f"{times[2]:.1f} s"),
        ("speed-up (target >= 1.7x)", f"{times[1] / times[2]:.2f}x"),
    ]


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--flights", type=int, default=8)
    ap.add_argument("--hours", type=float, default=5.0)
    ap.add_argument("--skip-archive", action="store_true")
    args = ap.parse_args()
    rows: list[tuple[str, str]] = []
    errors: list[str] = []
    with tempfile.TemporaryDirectory() as tmp:
        if not args.skip_archive:
            archive(args.flights, Path(tmp), rows, errors)
        long_flight(args.hours, Path(tmp), rows, errors)
    return finish(rows, errors)


if __name__ == "__main__":
    sys.exit(main())
