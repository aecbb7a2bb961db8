"""The fluxgate step test's margin, set by simulating the null: flights with no step.

    .venv/bin/python benchmarks/bench_fluxgate_step_margin.py [--flights 200] [--seed 6262]
        [--step-flights 40] [--workers 2] [--json OUT.json]

The scalar-minus-fluxgate scan (:mod:`pipeline.audit.vector_reference`) compares its
maximum F with a Gaussian null through the same whitened designs; interference outside the
difference's model (eddy fields that lag, unrecorded switched currents, second-order terms)
lifts a step-free flight's F above that null. How far is measured here: flights drawn as
:mod:`pipeline.simulate.audit_trials` draws them (both airframes, one or two calibration
passes, 0-1 nT outside the T-L basis at random share, every catalogue effect or none
hidden, no step), their ratio ``F / F_null_95``; the margin the audit uses
(``AuditSettings.fluxgate_step_margin``) is the ratio's quantile at the event test's level
(``event_alpha``), with a bootstrap interval. On flights with a 3-8 nT step the share whose
ratio reaches that margin at a change point within 120 s of the step is the test's power.
Seeds: ``seed * 1000 + i`` (null) and ``seed * 1000 + 500 + i`` (step); the frozen
benchmark blocks of ``bench_audit_variety.py`` use other seeds.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from pipeline.audit.context import AuditContext
from pipeline.audit.settings import AuditSettings
from pipeline.audit.vector_reference import scan_vector_reference
from pipeline.io.reader import read_flight
from pipeline.segment import segment_flight
from pipeline.simulate import audit_trials as at

NULL_KINDS = ("none", *at.CLASSES[1:-1])  # every catalogue effect, or none: no step


def one(job: tuple[str, int]) -> dict:
    """Simulate one flight (``kind``: a null class or "step"), scan it, return the ratio."""
    kind, seed = job
    rng = np.random.default_rng(seed)
    overrides = at.random_flight_overrides(rng) + at.hidden_overrides(kind, rng)
    overrides += at.TIED_SURVEY[at.override_value(overrides, "profile")]
    sim = at.simulate(at.Scenario.load("uav-small", overrides), int(rng.integers(2**31)))
    step = at.add_permanent_step(sim, rng) if kind == "step" else None
    with tempfile.TemporaryDirectory() as tmp:
        flight = read_flight(at.write_simulation(sim, Path(tmp) / "f.mcap"))
    d = AuditContext(flight, segment_flight(flight), AuditSettings()).data
    s = scan_vector_reference(d.time_s, d.scalar_nT, d.vector_nT, d.aux)
    row = {"kind": kind, "seed": seed, "ratio": None, "near": None, "size_nT": None}
    if s is not None:
        row.update(ratio=s.f_stat / s.f_null_95, p_value=s.p_value, size_nT=s.size_nT)
        if step is not None:
            row["near"] = bool(abs(s.time_s - step["time_s"]) <= at.EVENT_WINDOW_S)
    return row


def margin(ratios: np.ndarray, level: float, draws: int = 2000, seed: int = 0):
    """The ``1 - level`` quantile of the null ratios, and its bootstrap 95 % interval."""
    q = float(np.quantile(ratios, 1.0 - level))
    rng = np.random.default_rng(seed)
    boot = np.quantile(rng.choice(ratios, (draws, ratios.size)), 1.0 - level, axis=1)
    return q, (float(np.quantile(boot, 0.025)), float(np.quantile(boot, 0.975)))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--flights", type=int, default=200)
    ap.add_argument("--step-flights", type=int, default=40)
    ap.add_argument("--seed", type=int, default=6262)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    jobs = [(NULL_KINDS[i % len(NULL_KINDS)], a.seed * 1000 + i) for i in range(a.flights)]
    jobs += [("step", a.seed * 1000 + 500 + i) for i in range(a.step_flights)]
    rows = []
    with ProcessPoolExecutor(max(1, a.workers)) as pool:
        for i, row in enumerate(pool.map(one, jobs)):
            rows.append(row)
            print(f"{i + 1}/{len(jobs)} {row['kind']} ratio {row['ratio']}", flush=True)
    level = AuditSettings().event_alpha
    null = np.array([r["ratio"] for r in rows if r["kind"] != "step" and r["ratio"] is not None])
    q, ci = margin(null, level)
    steps = [r for r in rows if r["kind"] == "step" and r["ratio"] is not None]
    hit = sum(r["ratio"] >= q and r["near"] for r in steps)
    shipped = AuditSettings().fluxgate_step_margin
    print(
        f"null flights {null.size}: ratio median {np.median(null):.2f}, max {null.max():.2f}; "
        f"quantile at the event level {level:g}: {q:.2f} (95 % {ci[0]:.2f}-{ci[1]:.2f}); "
        f"shipped margin {shipped:g} reached on {int(np.sum(null >= shipped))}/{null.size}"
    )
    print(f"step flights: ratio >= {q:.2f} within 120 s on {hit}/{len(steps)}")
    if a.json:
        a.json.write_text(json.dumps({"rows": rows, "margin": q, "margin_ci95": ci}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
