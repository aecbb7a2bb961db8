"""Scaling of the post-flight steps with flight length: 1, 2 and 4 h flights at 10 Hz.

    .venv/bin/python benchmarks/bench_scaling.py [--hours 1,2,4]

Fits time = c * epochs^k on the runs (least squares in log-log) and prints k (target <= 1.1:
nothing in the flow may grow faster than the data). Exits non-zero if a run fails or gives a
wrong result (never because it is slow). About 3 minutes on 2 cores.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
from report import finish
from runs import long_flight


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--hours", default="1,2,4")
    args = ap.parse_args()
    rows: list[tuple[str, str]] = []
    errors: list[str] = []
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        for h in (float(x) for x in args.hours.split(",")):
            runs.append(long_flight(h, Path(tmp) / f"{h:g}h", rows, errors, f"{h:g} h flight"))
    epochs, secs = np.array(runs, float).T
    k, _ = np.polyfit(np.log(epochs), np.log(secs), 1)
    rows.append(("fitted exponent k in time ~ epochs^k (target <= 1.1)", f"{k:.2f}"))
    rows.append(("time per hour of flight", ", ".join(f"{s / (e / 36000):.1f} s" for e, s in runs)))
    return finish(rows, errors)


if __name__ == "__main__":
    sys.exit(main())
