"""Paper 004's experiment: does the ARIMA + Kalman map filter improve map-aided navigation?

    PYTHONPATH=. .venv/bin/python benchmarks/bench_nav_map_filter.py [--quick]
        [--noise 0.05,0.5,1,2] [--surveys 3] [--ins-seeds 20] [--scenario uav-small]

Paper 004 (Table/§4.3) reports the position error of map matching on the raw map against the
filtered one: 2092.6 m -> 946.2 m (-54.7 %) in simulation, 225.47 -> 199.83 m (-11.4 %) in
flight. Here, per sensor noise level (scenario override ``sensors.scalar_noise_nT``) and
survey seed, one simulated flight (``--scenario``, default ``uav-small``: 50 m lines, tie
lines and the "X" validation lines) is compensated (AGG-TL) and mapped by the map stage with
the shipped settings (:func:`pipeline.maps.stage.build_map`), giving three maps on the same
cells:

* ``raw``: the gridded, levelled anomaly (``/map/anomaly``);
* ``filtered``: the ARIMA + Kalman-filtered grid (``/map/anomaly_filtered``);
* ``truth``: the simulator's true anomaly on those cells, with the map's datum (offset,
  regional plane and gain fitted to the raw grid: the map keeps the regional plane and the
  unobservable induced scale, see ``tests/test_flow.py``).

The three share one mask: the raw grid's cells inside the simulator's truth grid (the survey
block; the map reaches a line spacing beyond it, the truth does not), so the ends of the
"X" beyond the block are dead reckoning for every map alike.

The validation lines (never used for the map) are then flown with a navigation-grade INS
(``--ins-seeds`` seeds, the same for every map) and the EKF aided by each map
(:func:`pipeline.navigation.stage.run_navigation`, the ``aeromag navigate`` defaults). Printed
per noise level: mean DRMS (INS-only, each map, CRLB on the filtered map) with 95 % intervals
(cluster bootstrap: survey seeds, then INS seeds within), and the relative change of mean DRMS,
filtered against raw (paper 004's -54.7 %) and truth against raw (the most any map filter
could gain), with their 95 % intervals.

Exits non-zero when the filtered map makes navigation worse than the raw one by more than
the interval allows at any noise level (the filter must not harm).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from tempfile import TemporaryDirectory

import numpy as np
from report import finish

from pipeline.compensate import FitSettings
from pipeline.compensate.stage import run_compensation
from pipeline.geo.local import LocalFrame
from pipeline.io.reader import read_flight
from pipeline.maps.grid import Grid
from pipeline.maps.stage import build_map
from pipeline.navigation.map_io import frame_map
from pipeline.navigation.stage import NavigationSettings, run_navigation
from pipeline.segment import segment_flight
from pipeline.simulate import write_simulation
from pipeline.simulate.scenario import Scenario
from pipeline.simulate.simulator import simulate

PAPER_SIMULATION = -54.7  # %, 2092.6 m -> 946.2 m
PAPER_FLIGHT = -11.4  # %, 225.47 m -> 199.83 m
MAPS = ("raw", "filtered", "truth")


def truth_grid(sim, grid: Grid, frame: LocalFrame) -> tuple[Grid, dict[str, float]]:
    """The simulator's true anomaly on ``grid``'s cells with the map's datum: offset,
    east/north plane and gain least-squares fitted to ``grid`` (masked as ``grid``)."""
    from scipy.interpolate import RegularGridInterpolator

    tg = sim.truth["anomaly"]["grid"]
    site = sim.truth["site"]
    tv = np.array(tg["values_nT"], float)
    gx, gy = np.meshgrid(*grid.coordinates())
    lat, lon, _ = frame.to_geodetic(gx, gy)
    e, n, _ = LocalFrame(site["latitude_deg"], site["longitude_deg"]).to_enu(lat, lon)
    ri = RegularGridInterpolator(
        (
            tg["north0_m"] + tg["cell_m"] * np.arange(tv.shape[0]),
            tg["east0_m"] + tg["cell_m"] * np.arange(tv.shape[1]),
        ),
        tv,
        bounds_error=False,
    )
    t = ri(np.stack([n, e], -1))
    ok = np.isfinite(t) & np.isfinite(grid.values)
    a = np.column_stack([np.ones(ok.sum()), gx[ok], gy[ok], t[ok]])
    coef, *_ = np.linalg.lstsq(a, grid.values[ok], rcond=None)
    out = coef[0] + coef[1] * gx + coef[2] * gy + coef[3] * t
    out[~np.isfinite(grid.values)] = np.nan
    rms = float(np.sqrt(np.mean((grid.values[ok] - a @ coef) ** 2)))
    return Grid(out, grid.east0_m, grid.north0_m, grid.cell_m), {
        "gain": float(coef[3]),
        "raw_minus_truth_rms_nT": rms,
    }


def survey_maps(scenario: str, noise_nT: float, seed: int, folder: Path):
    """Simulate, compensate and map one survey: (flight, segmentation, compensated field,
    {map name: GeoMap}, truth-fit info)."""
    sim = simulate(Scenario.load(scenario, [f"sensors.scalar_noise_nT={noise_nT}"]), seed)
    path = write_simulation(sim, folder / f"s{seed}_{noise_nT:g}.mcap")
    flight = read_flight(path)
    seg = segment_flight(flight)
    comp = run_compensation(flight, seg, FitSettings(model="agg-tl")).compensated_nT
    mr = build_map(flight, seg, comp)
    truth, info = truth_grid(sim, mr.grid, mr.frame)
    # the same cells for the three maps: the raw grid's and the truth's (the simulator's
    # truth grid covers the survey block only, the map reaches a line spacing beyond it)
    off = ~np.isfinite(truth.values)
    g0 = (mr.grid.east0_m, mr.grid.north0_m, mr.grid.cell_m)
    grids = {
        "raw": Grid(np.where(off, np.nan, mr.grid.values), *g0),
        "filtered": Grid(np.where(off, np.nan, mr.filtered.values), *g0),
        "truth": truth,
    }
    f_err = {
        k: float(np.sqrt(np.nanmean((g.values - truth.values) ** 2)))
        for k, g in grids.items()
        if k != "truth"
    }
    info.update({f"{k}_minus_truth_rms_nT": v for k, v in f_err.items()})
    maps = {k: frame_map(g, mr.frame, f"{scenario} seed {seed}", k) for k, g in grids.items()}
    return flight, seg, comp, maps, info


def cluster_bootstrap(
    values: np.ndarray, stat, n_boot: int = 2000, seed: int = 0
) -> tuple[float, float, float]:
    """``stat`` of ``values`` (surveys, INS seeds, ...) and its 95 % interval by resampling
    survey seeds, then INS seeds within each."""
    rng = np.random.default_rng(seed)
    s, k = values.shape[:2]
    est = stat(values.reshape(s * k, *values.shape[2:]))
    boots = np.empty(n_boot)
    for b in range(n_boot):
        si = rng.integers(0, s, s)
        ki = rng.integers(0, k, (s, k))
        v = values[si[:, None], ki]
        boots[b] = stat(v.reshape(s * k, *values.shape[2:]))
    lo, hi = np.percentile(boots, [2.5, 97.5])
    return float(est), float(lo), float(hi)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--noise", default="0.05,0.5,1,2", help="sensor noise levels, nT")
    ap.add_argument("--surveys", type=int, default=3, help="survey seeds per noise level")
    ap.add_argument("--ins-seeds", type=int, default=20)
    ap.add_argument("--scenario", default="uav-small")
    ap.add_argument("--quick", action="store_true", help="0.05 and 2 nT, 1 survey, 5 INS seeds")
    a = ap.parse_args()
    levels = [float(x) for x in a.noise.split(",")]
    surveys, ins_seeds = a.surveys, a.ins_seeds
    if a.quick:
        levels, surveys, ins_seeds = [0.05, 2.0], 1, 5
    clock = time.perf_counter()
    rows: list[tuple[str, str]] = []
    errors: list[str] = []
    table = [
        "| sensor nT | DRMS m: INS-only | raw map | filtered map | truth map | CRLB (filtered) "
        "| filtered vs raw | truth vs raw | map error nT: raw, filtered |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    with TemporaryDirectory() as tmp:
        for noise in levels:
            # drms[survey, ins seed, map]; ins-only and crlb apart
            drms = np.empty((surveys, ins_seeds, len(MAPS)))
            ins_only = np.empty((surveys, ins_seeds))
            bound = np.empty((surveys, ins_seeds))
            map_err = []
            for si in range(surveys):
                flight, seg, comp, maps, info = survey_maps(a.scenario, noise, si, Path(tmp))
                map_err.append(
                    (info["raw_minus_truth_rms_nT"], info["filtered_minus_truth_rms_nT"])
                )
                for ki in range(ins_seeds):
                    for mi, name in enumerate(MAPS):
                        run = run_navigation(
                            flight, seg, comp, maps[name], NavigationSettings(seed=ki)
                        )
                        d = run.summary()["drms_m"]
                        drms[si, ki, mi] = d["map_aided"]
                        if name == "filtered":
                            ins_only[si, ki], bound[si, ki] = d["ins_only"], d["crlb"]
            mean = lambda v: float(np.mean(v))  # noqa: E731

            def change(i: int):
                return lambda v: 100.0 * (np.mean(v[:, i]) / np.mean(v[:, 0]) - 1.0)

            cells = [cluster_bootstrap(drms[..., i], mean) for i in range(len(MAPS))]
            f_vs_r = cluster_bootstrap(drms, change(1))
            t_vs_r = cluster_bootstrap(drms, change(2))
            ins = cluster_bootstrap(ins_only, mean)
            crl = cluster_bootstrap(bound, mean)
            me = np.mean(map_err, axis=0)

            def ci(x, fmt=".2f"):
                return f"{x[0]:{fmt}} [{x[1]:{fmt}}, {x[2]:{fmt}}]"

            table.append(
                f"| {noise:g} | {ci(ins, '.0f')} | {ci(cells[0])} | {ci(cells[1])} | "
                f"{ci(cells[2])} | {ci(crl)} | {ci(f_vs_r, '+.1f')} % | {ci(t_vs_r, '+.1f')} % | "
                f"{me[0]:.3f}, {me[1]:.3f} |"
            )
            rows.append(
                (
                    f"sensor {noise:g} nT: DRMS change, filtered vs raw map",
                    f"{ci(f_vs_r, '+.1f')} % (paper 004: {PAPER_SIMULATION:+.1f} % simulation, "
                    f"{PAPER_FLIGHT:+.1f} % flight)",
                )
            )
            if f_vs_r[1] > 0.0:
                errors.append(f"sensor {noise:g} nT: the filtered map is worse ({ci(f_vs_r)} %)")
            print(table[-1], flush=True)
    rows.append(("runs", f"{surveys} surveys x {ins_seeds} INS seeds x {len(MAPS)} maps per level"))
    rows.append(("wall time", f"{time.perf_counter() - clock:.0f} s"))
    print()
    print("\n".join(table))
    print()
    return finish(rows, errors)


if __name__ == "__main__":
    sys.exit(main())
