"""Despiking figures (docs/science.md): detection and false-alarm rates against injected spikes,
and the compensation FOM with spikes, with and without despiking.

    python -m benchmarks.bench_despike [--seeds 4]
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np

from pipeline.compensate import FitSettings
from pipeline.compensate.stage import run_compensation
from pipeline.despike import despike, despike_flight
from pipeline.simulate.records import RECORD_NOISE_NT as NOISE_NT
from pipeline.simulate.records import record

AMPLITUDES_SIGMA = (5, 10, 20, 100, 2000)  # spike amplitude in units of the noise


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=4)
    seeds = ap.parse_args().seeds
    hits = {a: [] for a in AMPLITUDES_SIGMA}
    false = samples = clean_spikes = 0
    for seed in range(seeds):
        t, x = record(seed)
        clean_spikes += despike(x, t).spikes
        rng = np.random.default_rng(100 + seed)
        n = len(AMPLITUDES_SIGMA) * 40
        pos = np.sort(rng.choice(np.arange(10, x.size - 10, 12), size=n, replace=False))
        amp = np.repeat(AMPLITUDES_SIGMA, 40) * NOISE_NT * rng.choice([-1, 1], n)
        rng.shuffle(amp)
        y = x.copy()
        y[pos] += amp
        r = despike(y, t)
        found = np.isin(pos, r.spike_index)
        for a in AMPLITUDES_SIGMA:
            hits[a].append(found[np.isclose(np.abs(amp), a * NOISE_NT)].mean())
        false += np.setdiff1d(r.spike_index, pos).size
        samples += x.size
    print(f"records: {seeds} x 1 h at 10 Hz, noise {NOISE_NT} nT; 40 spikes per amplitude each")
    for a in AMPLITUDES_SIGMA:
        print(f"  {a:5d} sigma ({a * NOISE_NT:6.2f} nT): detected {np.mean(hits[a]):.3f}")
    print(f"  false alarms: {false} in {samples} samples; clean records: {clean_spikes} spikes")
    missed = false = total = steps = 0
    for seed in range(seeds):
        t, x = record(seed)
        rng = np.random.default_rng(50 + seed)
        starts = np.sort(rng.choice(np.arange(20, x.size - 20, 30), size=300, replace=False))
        y, pos = x.copy(), []
        for j, s0 in enumerate(starts):
            for w in range(1 + j % 3):
                k = s0 + w * (1 + (j // 3) % 3)
                y[k] += rng.choice([-1, 1]) * 10 ** rng.uniform(0, 2)
                pos.append(k)
        pos = np.array(pos)
        r = despike(y, t)
        missed += int((~np.isin(pos, r.spike_index)).sum())
        false += np.setdiff1d(r.spike_index, pos).size
        total += pos.size
        steps += r.steps
    print(
        f"  bursts of 1-3 spikes 1-3 samples apart (1-100 nT): {missed} of {total} missed, "
        f"{false} false, {steps} clusters taken for steps"
    )

    import tempfile

    from pipeline.io.reader import read_flight
    from pipeline.segment import segment_flight
    from pipeline.simulate import Scenario, simulate, write_simulation

    with tempfile.TemporaryDirectory() as tmp:
        flight = read_flight(
            write_simulation(simulate(Scenario.load("uav-small"), 3), f"{tmp}/s.mcap")
        )
    seg = segment_flight(flight)
    s = FitSettings(model="tl18")
    clean = run_compensation(flight, seg, s).fom.total["compensated"]
    x0 = flight.data["scalar_nT"].to_numpy(float)
    print(f"uav-small seed 3, tl18 FOM spike-free {clean:.3f} nT")
    for seed in range(seeds):
        rng = np.random.default_rng(seed)
        pos = rng.choice(np.arange(5, x0.size - 5), size=x0.size // 500, replace=False)
        amp = rng.choice([-1, 1], pos.size) * 10 ** rng.uniform(0, 2.5, pos.size)
        x = x0.copy()
        x[pos] += amp
        spiky = dataclasses.replace(flight, data=flight.data.assign(scalar_nT=x))
        f_sp = run_compensation(spiky, seg, s).fom.total["compensated"]
        fixed, r = despike_flight(spiky)
        f_de = run_compensation(fixed, seg, s).fom.total["compensated"]
        print(
            f"  seed {seed}: {pos.size} spikes 1-316 nT: FOM with spikes {f_sp:.3f}, "
            f"despiked {f_de:.3f} nT ({r.spikes} found)"
        )


if __name__ == "__main__":
    main()
