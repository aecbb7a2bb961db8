"""Micro-levelling figures (docs/science.md), all against the true field.

    python -m benchmarks.bench_microlevel [--seeds 20]

1. synthetic corrugated surveys (pipeline/simulate/corrugated.py): grid error and its stripes before
   and after, and the change on the same surveys without corrugation;
2. a ridge parallel to the lines: peak lost;
3. simulated uav-small flights (tie-levelled, uncorrugated) through build_map, with and
   without micro-levelling: grid error against the simulator's truth grid.
"""

from __future__ import annotations

import argparse
import tempfile

import numpy as np

from pipeline.simulate.corrugated import (
    error_nT,
    microlevelled,
    stripes_nT,
    survey,
    truth_field,
)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=20)
    n = ap.parse_args().seeds
    rows = []
    for seed in range(n):
        f = truth_field(seed)
        g, gm, m = microlevelled(survey(f, seed))
        c, cm, _ = microlevelled(survey(f, seed, 0.0, 0.0))
        ch = (cm.values - c.values)[np.isfinite(c.values)]
        rows.append(
            (
                error_nT(g, f),
                error_nT(gm, f),
                stripes_nT(g, f),
                stripes_nT(gm, f),
                m.rms_nT,
                error_nT(c, f),
                error_nT(cm, f),
                float(np.sqrt(np.mean(ch**2))),
            )
        )
    r = np.array(rows)
    fac = r[:, 0] / r[:, 1]
    print(f"synthetic, {n} seeds (21 lines 50 m apart, 1.5 nT offsets + 1 nT drifts):")
    print(
        f"  grid error {r[:, 0].mean():.3f} -> {r[:, 1].mean():.3f} nT (mean); factor median "
        f"{np.median(fac):.2f}, range {fac.min():.2f}-{fac.max():.2f}"
    )
    print(f"  stripes (< 4 spacings across) {r[:, 2].mean():.3f} -> {r[:, 3].mean():.3f} nT")
    print(f"  correction RMS {r[:, 4].mean():.3f} nT")
    print(
        f"  uncorrugated: error {r[:, 5].mean():.3f} -> {r[:, 6].mean():.3f} nT, grid change "
        f"{r[:, 7].mean():.3f} nT RMS (max {r[:, 7].max():.3f})"
    )
    for sigma in (25.0, 50.0, 100.0):

        def ridge(e, nn, s=sigma):
            return 10.0 * np.exp(-((e - 500.0) ** 2) / (2 * s**2)) + 0.0 * nn

        g, gm, _ = microlevelled(survey(ridge, 0, 0.0, 0.0))
        e, nn = g.coordinates()
        i, j = np.argmin(np.abs(nn - 500.0)), np.argmin(np.abs(e - 500.0))
        print(
            f"  10 nT ridge along the lines, sigma {sigma:g} m: peak "
            f"{g.values[i, j]:.2f} -> {gm.values[i, j]:.2f} nT"
        )

    from pipeline.compensate import FitSettings
    from pipeline.compensate.stage import run_compensation
    from pipeline.io.reader import read_flight
    from pipeline.maps.stage import MapSettings, build_map
    from pipeline.segment import segment_flight
    from pipeline.simulate import Scenario, simulate, write_simulation
    from pipeline.simulate.truth import truth_on

    deep = [
        "anomaly.depth_m=[300.0, 500.0]",
        "anomaly.dipoles=2",
        "anomaly.moment_A_m2=[2.0e7, 5.0e7]",
        "anomaly.margin_m=-100.0",
        "anomaly.remanent_fraction=0.0",
    ]
    print("simulated uav-small (tie-levelled, no corrugation), agg-tl, grid error vs truth:")
    for label, seed, over in (("2 deep dipoles", 7, deep), ("default", 3, []), ("default", 5, [])):
        sim = simulate(Scenario.load("uav-small", over), seed)
        with tempfile.TemporaryDirectory() as tmp:
            flight = read_flight(write_simulation(sim, f"{tmp}/s.mcap"))
        seg = segment_flight(flight)
        comp = run_compensation(flight, seg, FitSettings(model="agg-tl")).compensated_nT
        out = []
        for on in (False, True):
            mr = build_map(flight, seg, comp, MapSettings(arima=(1, 1, 1), microlevel=on))
            truth = truth_on(sim, mr.grid, mr.frame)
            d = (mr.grid.values - truth)[np.isfinite(truth) & np.isfinite(mr.grid.values)]
            out.append(float(np.sqrt(np.mean((d - d.mean()) ** 2))))
        print(
            f"  seed {seed} ({label}, truth RMS {np.nanstd(truth):.1f} nT): "
            f"{out[0]:.3f} -> {out[1]:.3f} nT"
        )


if __name__ == "__main__":
    main()
