"""The model audit on hidden effects: what it finds, how well it estimates, what it gains.

    .venv/bin/python benchmarks/bench_audit.py [--seeds 1 2]

Each case simulates the uav-small survey (two calibration boxes over quiet ground) with the
named effects switched on, audits it, and prints the findings against the simulator's truth
and the gain of the extended model. Exits non-zero when a case finds a different set of
effects than it hid (a clean flight must give none).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

from report import finish

from pipeline.audit import run_audit
from pipeline.io.reader import read_flight
from pipeline.segment import segment_flight
from pipeline.simulate import Scenario, simulate, write_simulation

BASE = ["calibration.passes=2", "anomaly.quiet_calibration_m=400.0"]
CASES = [
    (),
    ("geomagnetic_gradient",),
    ("sensor_lag",),
    ("diurnal",),
    ("electrical_current",),
    ("vector_calibration",),
    ("geomagnetic_gradient", "sensor_lag", "electrical_current", "diurnal"),
]


def short(effect: str, est: dict) -> str:
    if effect == "geomagnetic_gradient":
        return f"{est['east_nT_per_m']:.3f} E / {est['north_nT_per_m']:.3f} N nT/m"
    if effect == "sensor_lag":
        return f"{est['lag_s'] * 1000:.1f} ms"
    if effect == "diurnal":
        p = est["period_s"]
        return f"x{est['base_coefficient']:.2f} of base, {est['amplitude_nT']:.1f} nT, " + (
            "-" if p is None else f"{p:.0f} s"
        )
    if effect == "electrical_current":
        return f"{est['channel']} {est['nT_per_unit']:.2f} nT/{est['unit']}"
    s = est["scale_error"]
    return f"scale {s[0]:+.4f} {s[1]:+.4f} {s[2]:+.4f}"


def truth_of(effect: str, truth: dict) -> str:
    e = truth["effects"].get(effect, {})
    if effect == "geomagnetic_gradient":
        return f"{e['east_nT_per_m']:.3f} E / {e['north_nT_per_m']:.3f} N nT/m"
    if effect == "sensor_lag":
        return f"{e['lag_s'] * 1000:.1f} ms"
    if effect == "diurnal":
        return f"{e['amplitude_nT']:.1f} nT, {e['period_s']:.0f} s"
    if effect == "electrical_current":
        return f"/aux/{e['channel']} {e['coupling_nT_per_A']:.2f} nT/A"
    s = truth["fluxgate_errors"]["scale_error"]
    return f"scale {s[0]:+.4f} {s[1]:+.4f} {s[2]:+.4f}"


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2])
    args = ap.parse_args()
    errors: list[str] = []
    print(
        "| seed | hidden | found | estimate (truth) | held-out residual nT | "
        "heading error nT | audit s |"
    )
    print("|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seeds:
            for case in CASES:
                sc = Scenario.load(
                    "uav-small", [*BASE, *[f"effects.{e}.enabled=true" for e in case]]
                )
                sim = simulate(sc, seed)
                flight = read_flight(write_simulation(sim, Path(tmp) / "f.mcap"))
                seg = segment_flight(flight)
                t0 = time.perf_counter()
                res = run_audit(flight, seg)
                dt = time.perf_counter() - t0
                got = [f.effect for f in res.findings]
                est = "; ".join(
                    f"{f.effect}: {short(f.effect, f.estimate)} ({truth_of(f.effect, sim.truth)})"
                    for f in res.findings
                )
                g = res.gain
                he = g["heading_error_rms_nT"]
                print(
                    f"| {seed} | {', '.join(case) or 'none'} | {', '.join(got) or 'none'} | "
                    f"{est or '-'} | {g['heldout_calibration_residual_rms_nT']['before']:.4f}"
                    f" -> {g['heldout_calibration_residual_rms_nT']['after']:.4f} | "
                    f"{he['before']:.3f} -> {he['after']:.3f} | {dt:.1f} |"
                )
                if set(got) != set(case):
                    errors.append(f"seed {seed}: hid {sorted(case)}, found {sorted(got)}")
                if res.unexplained:
                    print(f"|  |  | unexplained | {res.unexplained['note']} |  |  |  |")
    print()
    return finish([("seeds", " ".join(map(str, args.seeds))), ("cases", str(len(CASES)))], errors)


if __name__ == "__main__":
    sys.exit(main())
