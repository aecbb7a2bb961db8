"""Compensation on the demo flight, with and without its 0.45 nT/m gradient.

    .venv/bin/python benchmarks/bench_compensation.py [--seed 1]

For each model: FOM (raw -> compensated), and the heading error measured against the
simulator's truth: the mean of (compensated - true field) over survey and tie lines grouped by
cardinal heading, as a spread (max - min) in nT. Exits non-zero if AGG-TL does not beat T-L by
at least 3x over the gradient, or if the gradient estimate is off by more than 10 %.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

from pipeline.compensate import FitSettings
from pipeline.compensate.stage import run_compensation
from pipeline.io.reader import read_flight
from pipeline.segment import segment_flight
from pipeline.simulate import Scenario, simulate, write_simulation

MODELS = (("tl16", "tl16"), ("tl18", "tl18"), ("agg-tl", "tl18"), ("agg-tl", "tl16"))


def heading_spread(seg, err) -> float:
    card = np.array(list("NESW"))[np.round(np.nan_to_num(seg.heading_deg) / 90).astype(int) % 4]
    means = [
        np.nanmean(err[seg.mask(lab) & (card == c)])
        for lab in ("survey", "tie")
        for c in "NESW"
        if (seg.mask(lab) & (card == c)).any()
    ]
    return float(max(means) - min(means))


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    rows, results = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        for grad in (True, False):
            switch = f"effects.geomagnetic_gradient.enabled={str(grad).lower()}"
            sc = Scenario.load("demo", [switch])
            sim = simulate(sc, args.seed)
            flight = read_flight(write_simulation(sim, Path(tmp) / f"g{grad}.mcap"))
            seg = segment_flight(flight)
            earth = sim.series["earth_total_nT"][
                np.searchsorted(sim.series["time_ns"], flight.time_ns)
            ]
            for model, base in MODELS:
                run = run_compensation(flight, seg, FitSettings(model=model, base=base))
                name = model if model != "agg-tl" else f"agg-tl ({base} terms)"
                spread = heading_spread(seg, run.compensated_nT - earth)
                g = run.model.gradient_nT_per_m()
                results[(grad, name)] = (spread, g)
                fom = run.fom.total
                rows.append(
                    (
                        f"{'0.45 nT/m' if grad else 'none'}",
                        name,
                        f"{fom['uncompensated']:.1f} -> {fom['compensated']:.2f}",
                        f"{spread:.3f}",
                        "-" if not g else f"{g['east']:.3f} / {g['north']:.3f}",
                    )
                )
            if grad:
                true_g = sim.truth["effective"]["gradient_nT_per_m"]
    print("| gradient | model | FOM nT | heading-error spread nT | gradient E / N nT/m |")
    print("|---|---|---|---|---|")
    for r in rows:
        print("| " + " | ".join(r) + " |")
    print(f"\ntrue gradient: {true_g[0]:.3f} E / {true_g[1]:.3f} N nT/m")
    errors = []
    tl = results[(True, "tl16")][0]
    agg, g = results[(True, "agg-tl (tl18 terms)")]
    if not agg * 3 <= tl:
        errors.append(f"AGG-TL heading error {agg:.3f} nT is not 3x below T-L's {tl:.3f} nT")
    for k, i in (("east", 0), ("north", 1)):
        if abs(g[k] - true_g[i]) > 0.1 * abs(true_g[i]):
            errors.append(f"gradient {k} {g[k]:.3f} vs true {true_g[i]:.3f} nT/m")
    for e in errors:
        print(f"WRONG: {e}", file=sys.stderr)
    return 1 if errors else 0


if __name__ == "__main__":
    sys.exit(main())
