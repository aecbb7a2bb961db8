"""Is ``/map/uncertainty`` the map's error? Its sigma against the true error, survey by survey.

    PYTHONPATH=. .venv/bin/python benchmarks/bench_map_uncertainty.py [--seeds 8]
        [--first-seed 500] [--noise 0.05,0.5,2] [--scenarios uav-small,fixed-wing]
        [--workers 2] [--json OUT.json]

Per scenario, sensor noise (scenario override ``sensors.scalar_noise_nT``) and seed, one
simulated flight is compensated (AGG-TL) and gridded by the map stage with the shipped
settings (:func:`pipeline.maps.stage.anomaly_grid`); its error model is fitted twice on the
same levelled lines:

* ``shipped``: :func:`pipeline.maps.stage.map_uncertainty` as the stage runs it (tie lines
  held out, raised where held-out survey lines miss by more than the ties);
* ``survey-lines``: the same without the tie lines, i.e. the along-line shape scaled by
  held-out survey lines (the method of surveys without ties; the shipped one before tie
  lines were used).

The truth is the simulator's dipole field on every cell
(:func:`pipeline.simulate.truth.true_anomaly_grid`, the map's datum fitted inside the
block). Per map: ``z`` = RMS over the block's cells of (map - truth) / sigma (1: sigma is the
error; above 1 sigma is too small, which makes a navigation filter read map error as
position), and the true error and sigma per band of distance to the nearest line sample (0-1/8,
1/8-1/4, 1/4-1/2 of a spacing). Printed per scenario and noise: median and largest ``z`` per
model, and how many maps have ``z`` > 1.5; and the error's correlation length the shipped
model measured (``MapUncertainty.error_length_m``) against the true error's along the grid's
two axes (:func:`true_length_m`), in line spacings.

Exits non-zero when a map stage fails; ``z`` has no pass mark here (the results table in
docs/navigation.md states what was measured).
"""

from __future__ import annotations

import argparse
import json
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from tempfile import TemporaryDirectory

import numpy as np
from report import finish
from rich.progress import Progress
from scipy.spatial import cKDTree

from pipeline.compensate import FitSettings
from pipeline.compensate.stage import run_compensation
from pipeline.io.reader import read_flight
from pipeline.maps.stage import MapSettings, anomaly_grid, lines_noise_nT, map_uncertainty
from pipeline.segment import segment_flight
from pipeline.simulate import write_simulation
from pipeline.simulate.scenario import Scenario
from pipeline.simulate.simulator import simulate
from pipeline.simulate.truth import true_anomaly_grid

BANDS = (0.0, 0.125, 0.25, 0.5)  # distance to the nearest line sample, line spacings
MODELS = ("shipped", "survey-lines")


def true_length_m(err: np.ndarray, cell_m: float, axis: int) -> float:
    """Two-sided integral (m) of the autocorrelation of the map's true error ``err`` (cells,
    NaN outside the block) along the grid's ``axis`` (1: along rows, east; 0: along columns,
    north), each row's (column's) mean removed as a navigation filter's per-line level takes
    it, summed to the first lag where it is no longer positive: what
    :func:`pipeline.maps.uncertainty.error_correlation_length` estimates for the filter."""
    rows = err if axis == 1 else err.T
    n = rows.shape[1]
    num, cnt, var = np.zeros(n), np.zeros(n), []
    for r in rows:
        ok = np.isfinite(r)
        if ok.sum() < 3:
            continue
        x = np.where(ok, r - np.nanmean(r), 0.0)
        var.append(x[ok] ** 2)
        for k in range(1, n):
            both = ok[:-k] & ok[k:]
            num[k] += float(np.sum((x[:-k] * x[k:])[both]))
            cnt[k] += float(both.sum())
    if not var:
        return float("nan")
    with np.errstate(invalid="ignore", divide="ignore"):
        rho = (num[1:] / cnt[1:]) / float(np.mean(np.concatenate(var)))
    stop = np.flatnonzero(~(rho > 0))
    rho = rho[: stop[0] if stop.size else rho.size]
    return float(cell_m * (1.0 + 2.0 * np.sum(rho)))


def one(scenario: str, noise_nT: float, seed: int) -> dict:
    """Simulate, map and score one survey (see the module docstring)."""
    sim = simulate(Scenario.load(scenario, [f"sensors.scalar_noise_nT={noise_nT}"]), seed)
    with TemporaryDirectory() as td:
        flight = read_flight(write_simulation(sim, Path(td) / "s.mcap"))
    seg = segment_flight(flight)
    comp = run_compensation(flight, seg, FitSettings(model="agg-tl")).compensated_nT
    gm = anomaly_grid(flight, seg, comp, MapSettings())
    truth, info = true_anomaly_grid(sim, gm.grid, gm.frame)
    block = info["block"]
    sensor = lines_noise_nT(gm.lines)
    survey_only = gm.data.subset(gm.data.kind == "survey")
    sigmas = {
        "shipped": map_uncertainty(gm.data, gm.grid, gm.spacing_m, sensor, gm.leveling),
        "survey-lines": map_uncertainty(survey_only, gm.grid, gm.spacing_m, sensor, gm.leveling),
    }
    gx, gy = np.meshgrid(*gm.grid.coordinates())
    tree = cKDTree(np.column_stack([gm.data.east_m, gm.data.north_m]))
    d, _ = tree.query(np.column_stack([gx[block], gy[block]]))
    err = (gm.grid.values - truth.values)[block]
    edges = np.asarray(BANDS) * gm.spacing_m
    ok = np.isfinite(err)
    bands = [ok & (d >= a) & (d < b) for a, b in zip(edges[:-1], edges[1:], strict=True)]
    row = {
        "scenario": scenario,
        "noise_nT": noise_nT,
        "seed": seed,
        "true_nT": [float(np.sqrt(np.mean(err[m] ** 2))) for m in bands],
        "spacing_m": float(gm.spacing_m),
    }
    err2d = np.where(block, gm.grid.values - truth.values, np.nan)
    row["true_length_m"] = {
        "east": true_length_m(err2d, gm.grid.cell_m, 1),
        "north": true_length_m(err2d, gm.grid.cell_m, 0),
    }
    for name, (grid, model, _) in sigmas.items():
        s = grid.values[block]
        ok = np.isfinite(err) & np.isfinite(s) & (s > 0)
        row[name] = {
            "z": float(np.sqrt(np.mean((err[ok] / s[ok]) ** 2))),
            "sigma_nT": [float(np.sqrt(np.mean(s[m & ok] ** 2))) for m in bands],
            "method": model.method,
            "length_m": model.error_length_m,
        }
    return row


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--first-seed", type=int, default=500)
    ap.add_argument("--noise", default="0.05,0.5,2", help="sensor noise levels, nT")
    ap.add_argument("--scenarios", default="uav-small,fixed-wing")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", help="write every map's row here")
    args = ap.parse_args()
    jobs = [
        (sc, float(nz), args.first_seed + k)
        for sc in args.scenarios.split(",")
        for nz in args.noise.split(",")
        for k in range(args.seeds)
    ]
    rows, errors = [], []
    with Progress() as progress, ProcessPoolExecutor(args.workers) as pool:
        task = progress.add_task("maps", total=len(jobs))
        futures = {pool.submit(one, *j): j for j in jobs}
        for fut, job in futures.items():
            try:
                rows.append(fut.result())
            except Exception as exc:  # a failing stage is the benchmark's finding
                errors.append(f"{job}: {exc}")
            progress.advance(task)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    table = []
    for sc in args.scenarios.split(","):
        for nz in args.noise.split(","):
            sel = [r for r in rows if r["scenario"] == sc and r["noise_nT"] == float(nz)]
            if not sel:
                continue
            cells = []
            for name in MODELS:
                z = np.array([r[name]["z"] for r in sel])
                cells.append(
                    f"{name}: z median {np.median(z):.2f}, max {z.max():.2f}, "
                    f"> 1.5 on {int(np.sum(z > 1.5))}/{z.size}"
                )
            table.append((f"{sc}, {nz} nT, {len(sel)} maps", "; ".join(cells)))
            # the error's correlation length: shipped estimate over the true one along the
            # grid's axes (the shorter and the longer of the two), in line spacings
            est = np.array([r["shipped"]["length_m"] / r["spacing_m"] for r in sel])
            lo, hi = (
                np.array([f(r["true_length_m"].values()) / r["spacing_m"] for r in sel])
                for f in (min, max)
            )
            table.append(
                (
                    f"{sc}, {nz} nT: correlation length, spacings",
                    f"shipped median {np.median(est):.2f} ({est.min():.2f}-{est.max():.2f}); "
                    f"true along the grid axes: shorter {np.median(lo):.2f}, "
                    f"longer {np.median(hi):.2f}; shipped >= shorter on "
                    f"{int(np.sum(est >= lo))}/{est.size}, >= longer on "
                    f"{int(np.sum(est >= hi))}/{est.size}",
                )
            )
    return finish(table, errors)


if __name__ == "__main__":
    sys.exit(main())
