"""Map-aided navigation on maps with errors: never worse than the INS alone, and consistent
(issue 38, item 4). Monte Carlo over seeded trials (:mod:`pipeline.simulate.navigation_trials`).

    .venv/bin/python benchmarks/bench_nav_consistency.py [--runs 60] [--duration 1200]
        [--first-seed 1]

Seeds ``--first-seed`` onwards. Seeds 1-60 are the development block (looked at while the
model was built); 1001-1060 are held out (``--first-seed 1001``): a change to the filter or
its noise model is judged on them, once, after it is made.

Each run draws (log-uniform) a sensor noise of 0.05-2 nT and a map error of 0.1-5 nT (half a
smooth field correlated over 100-400 m, 30 % white noise per cell, 20 % a constant offset),
and a true anomaly field (random, correlated over 200-800 m, 20-100 nT RMS): maps of several
roughnesses. The truth is the clean field; the filter navigates on the field plus the error,
20 min of a racetrack at 60 m/s and 2 Hz with a navigation-grade INS from a GNSS-aided
covariance and a magnetometer whose slowly drifting bias is the filters' catch-all state,
innovation gate at 0.9999. Three configurations, on the same draws:

* ``told``: the filter is told the map's 1 sigma (as ``/map/uncertainty`` tells it) and the
  default correlation length (``[navigate] map_error_length_m``, whatever the true one);
* ``default``: the map's sigma is not known: ``[navigate] map_sigma_nT``;
* ``white``: told the sigma but taking the map error as white (no inflation): why the
  inflation is there.

Printed per configuration: runs where map-aided DRMS exceeds INS-only's, the median and worst
ratio, the average NEES (position, 2 dof) and NIS (1 dof) against the 95 % chi-square band of
an average over the runs at one epoch, and the fraction of epochs within it. Exits non-zero
when ``told`` or ``default`` is worse than the INS alone on any run or ``told``'s average NEES
is outside the band.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace

import numpy as np
from report import finish
from scipy.stats import chi2

from pipeline.defaults import default_value
from pipeline.simulate.navigation_trials import Trial, run_trial


def draw(seed: int, duration_s: float) -> Trial:
    """The seed's trial: sensor, map error, its correlation, the field's roughness."""
    rng = np.random.default_rng(seed)

    def logu(lo, hi):
        return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))

    return Trial(
        seed,
        sensor_nT=logu(0.05, 2.0),
        map_error_nT=logu(0.1, 5.0),
        correlation_m=float(rng.uniform(100.0, 400.0)),
        field_correlation_m=float(rng.uniform(200.0, 800.0)),
        field_rms_nT=float(rng.uniform(20.0, 100.0)),
        duration_s=duration_s,
        told_length_m=float(default_value("navigate", "map_error_length_m")),
        gate_probability=float(default_value("navigate", "gate_probability")),
    )


def band(dof: int, runs: int) -> tuple[float, float]:
    """95 % band of the average of ``runs`` chi-square(dof) values."""
    return tuple(float(chi2.ppf(q, dof * runs) / runs) for q in (0.025, 0.975))


def summarise(name: str, results: list[dict]) -> tuple[list[tuple[str, str]], dict]:
    ins = np.array([r["ins_only_m"] for r in results])
    aid = np.array([r["map_aided_m"] for r in results])
    ratio = aid / ins
    m = len(results)
    nees = np.nanmean(np.stack([r["nees"] for r in results]), axis=0)  # per epoch, over runs
    nis_runs = np.stack([r["nis"] for r in results])
    nis = np.nanmean(nis_runs, axis=0)
    lo, hi = band(2, m)
    nlo, nhi = band(1, m)
    stats = {
        "worse": int((ratio > 1.0).sum()),
        "anees": float(np.mean(nees)),
        "anis": float(np.nanmean(nis)),
        "band": (lo, hi),
    }
    rows = [
        (f"{name}: runs map-aided worse than INS-only", f"{stats['worse']} of {m}"),
        (
            f"{name}: DRMS map-aided / INS-only",
            f"median {np.median(ratio):.3f}, worst {ratio.max():.3f} "
            f"(map-aided median {np.median(aid):.2f} m, INS-only {np.median(ins):.1f} m)",
        ),
        (
            f"{name}: average NEES (2 dof)",
            f"{stats['anees']:.2f}, band [{lo:.2f}, {hi:.2f}]; epochs within "
            f"{np.mean((nees >= lo) & (nees <= hi)):.0%}",
        ),
        (
            f"{name}: average NIS (1 dof)",
            f"{stats['anis']:.2f}, band [{nlo:.2f}, {nhi:.2f}]; gate refused "
            f"{sum(r['rejected'] for r in results)} of {sum(r['updates'] for r in results)}",
        ),
    ]
    return rows, stats


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=60)
    ap.add_argument("--duration", type=float, default=1200.0)
    ap.add_argument("--first-seed", type=int, default=1)
    a = ap.parse_args()
    seeds = range(a.first_seed, a.first_seed + a.runs)
    trials = [draw(seed, a.duration) for seed in seeds]
    default_sigma = float(default_value("navigate", "map_sigma_nT"))
    configs = {
        "told": trials,
        "default": [replace(t, told_map_sigma_nT=default_sigma) for t in trials],
        "white": [replace(t, told_length_m=0.0) for t in trials],
    }
    rows: list[tuple[str, str]] = [
        ("runs", f"{a.runs} x {a.duration:g} s at 2 Hz, seeds {seeds[0]}-{seeds[-1]}"),
    ]
    errors: list[str] = []
    for name, ts in configs.items():
        clock = time.perf_counter()
        results = [run_trial(t) for t in ts]
        r, st = summarise(name, results)
        rows += r
        rows.append((f"{name}: time", f"{time.perf_counter() - clock:.0f} s"))
        if name in ("told", "default") and st["worse"]:
            errors.append(f"{name}: map-aided worse than INS-only on {st['worse']} runs")
        lo, hi = st["band"]
        if name == "told" and not lo <= st["anees"] <= hi:
            errors.append(f"told: average NEES {st['anees']:.2f} outside [{lo:.2f}, {hi:.2f}]")
    return finish(rows, errors)


if __name__ == "__main__":
    sys.exit(main())
