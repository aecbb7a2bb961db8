"""I/O benchmark on the demo flight: simulate, write, ingest, copy, inspect.

    .venv/bin/python benchmarks/bench_io.py [--scenario demo] [--seed 1]

Prints a table (Markdown, for the README) and exits non-zero if an output value is wrong
(not if something is slow). Compare ratios within one run: absolute times vary run to run.
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from mcap.reader import make_reader
from report import finish

from pipeline.io.inspect import inspect_recording
from pipeline.io.reader import read_flight
from pipeline.io.writer import write_with_new_channels
from pipeline.products.log import ingest_lines, log_channel
from pipeline.simulate import Scenario, simulate, write_simulation


def timed(fn):
    t = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenario", default="demo")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    rows: list[tuple[str, str]] = []
    errors: list[str] = []
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "flight.mcap"
        sc = Scenario.load(args.scenario)
        sim, t_sim = timed(lambda: simulate(sc, args.seed))
        _, t_write = timed(lambda: write_simulation(sim, path))
        n_msgs = sum(len(s["t"]) for s in sim.streams.values())
        minutes = sim.trajectory.duration_s / 60
        rows += [
            (
                "flight",
                f"{args.scenario}: {minutes:.1f} min, {n_msgs} messages, "
                f"{path.stat().st_size / 1e6:.1f} MB",
            ),
            ("simulate (physics)", f"{t_sim:.2f} s"),
            ("write recording", f"{t_write:.2f} s ({n_msgs / t_write / 1e3:.0f} k msg/s)"),
        ]

        def bare(order: bool):
            n = 0
            with path.open("rb") as f:
                for _ in make_reader(f).iter_messages(log_time_order=order):
                    n += 1
            return n

        n_bare, t_bare = timed(lambda: bare(True))
        _, t_bare_u = timed(lambda: bare(False))
        flight, t_read = timed(lambda: read_flight(path))
        peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux
        rows += [
            (
                "official reader, bare iteration (log-time order, the default)",
                f"{t_bare:.2f} s ({n_bare / t_bare / 1e3:.0f} k msg/s)",
            ),
            (
                "official reader, bare iteration (file order)",
                f"{t_bare_u:.2f} s ({n_bare / t_bare_u / 1e3:.0f} k msg/s)",
            ),
            (
                "ours: decoded and aligned columns",
                f"{t_read:.2f} s ({n_bare / t_read / 1e3:.0f} k msg/s; process peak "
                f"{peak_mb:.0f} MB)",
            ),
            (
                "ratio (target >= 3x, then 5x)",
                f"{t_bare / t_read:.1f}x the default iteration, {t_bare_u / t_read:.1f}x the "
                "file-order iteration",
            ),
        ]
        if n_bare != n_msgs:
            errors.append(f"bare iteration read {n_bare} messages, wrote {n_msgs}")
        if len(flight.data) != len(sim.streams["/mag/scalar"]["t"]):
            errors.append("ingest epochs differ from scalar samples")
        # identical values: every contract stream decoded by the official reader + json
        ref: dict[str, list] = {}
        with path.open("rb") as f:
            for _, ch, msg in make_reader(f).iter_messages(log_time_order=False):
                ref.setdefault(ch.topic, []).append((msg.log_time, json.loads(msg.data)))
        for topic, series in flight.series.items():
            got = sorted(ref[topic], key=lambda r: r[0])
            t_ref = np.array([r[0] for r in got], np.int64)
            same = np.array_equal(series.time_ns, t_ref)
            for fld, vals in series.values.items():
                same &= np.array_equal(vals, np.array([r[1][fld] for r in got], float))
            if not same:
                errors.append(f"{topic}: decoded values differ from the official reader's")
        rows.append(
            (
                "identical values",
                f"{len(flight.series)} streams, every field, equal to "
                "the official reader + json.loads",
            )
        )
        ch = log_channel(flight, ingest_lines(flight), "ingest")
        _, t_copy = timed(lambda: write_with_new_channels(path, Path(tmp) / "out.mcap", [ch]))
        rows.append(("copy input + new channel", f"{t_copy:.2f} s"))
        rep, t_insp = timed(lambda: inspect_recording(path))
        rows.append(("inspect (every message validated)", f"{t_insp:.2f} s"))
        if rep.violations:
            errors.append(f"inspect found violations: {rep.violations[:2]}")
    return finish(rows, errors)


if __name__ == "__main__":
    sys.exit(main())
