"""Campaign: joint levelling of simulated sorties against the simulator's truth.

N uav-small sorties over one geology on different days, each with its own diurnal level
(nT, drawn from N(0, 5)) and its lines shifted across track by multiples of 12.5 m
(pipeline/simulate/campaign.py), processed, then merged by ``aeromag campaign``'s steps. Reports the
crossover RMS within and between flights before and after, the ratio against the target
(between <= 1.2 x within, after), the flight offsets against the flights' true levels, the
merged grid's RMS error against the true anomaly (after a common offset) with joint levelling
and with each flight levelled alone, and the time of the campaign steps.

    .venv/bin/python benchmarks/bench_campaign.py [--flights 3] [--cli]

``--cli`` also runs ``aeromag campaign`` itself (its own Prefect server, 2 Dask workers).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402
from report import finish  # noqa: E402

from pipeline.simulate.campaign import (  # noqa: E402
    Truth,
    all_crossovers,
    campaign_plan,
    grid_rmse_nT,
    simulate_campaign,
    sorties_and_frame,
    true_levels_nT,
)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--flights", type=int, default=3)
    ap.add_argument("--cli", action="store_true", help="also run `aeromag campaign` on Dask")
    args = ap.parse_args()
    from flows.campaign import run_plain
    from pipeline.campaign.stage import run_campaign

    rows: list[tuple[str, str]] = []
    errors: list[str] = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        plan = campaign_plan(args.flights)
        t0 = time.perf_counter()
        proc = simulate_campaign(folder, plan)
        rows.append(
            (f"{len(plan)} sorties simulated and processed", f"{time.perf_counter() - t0:.1f} s")
        )
        cfg = folder / "c.toml"
        cfg.write_text('config_version = 1\n[export]\nformats = ["geotiff", "netcdf"]\n')
        t0 = time.perf_counter()
        doc = run_plain(proc, folder / "out", str(cfg))
        rows.append(("campaign steps (plain, no Prefect)", f"{time.perf_counter() - t0:.1f} s"))
        r = doc["crossover_rms_nT"]
        for key in ("within_flight", "between_flights"):
            rows.append(
                (
                    f"crossover RMS {key.replace('_', ' ')} ({doc['crossovers'][key]})",
                    f"{r[key]['before']:.3f} -> {r[key]['after']:.3f} nT",
                )
            )
        ratio = doc["between_over_within_after"]
        rows.append(("between / within after (target <= 1.2)", f"{ratio:.2f}"))
        if ratio > 1.2:
            errors.append(f"between/within {ratio:.2f} > 1.2")
        frame, ss = sorties_and_frame(proc)
        truth = Truth(folder / "day1.truth.json")
        level = true_levels_nT(ss, truth, frame)
        offs = np.array([doc["flight_offsets_nT"][s.name] for s in ss])
        inj = np.array([p[3] for p in plan])
        rows.append(
            (
                "flight offsets (nT)",
                ", ".join(f"{s.name} {o:+.3f}" for s, o in zip(ss, offs, strict=True)),
            )
        )
        rows.append(("injected diurnal levels - their mean (nT)", _list(inj - inj.mean())))
        rows.append(("true flight levels - their mean (nT)", _list(level)))
        err = float(np.max(np.abs(offs - level)))
        rows.append(("largest offset error against the true level", f"{err:.3f} nT"))
        if err > 0.15:
            errors.append(f"flight offsets off by {err:.3f} nT")
        xs, between = all_crossovers(ss)
        run = run_campaign(ss, frame, xs, between, per_flight_grid=True)
        joint = grid_rmse_nT(run.grid, truth, frame)
        alone = grid_rmse_nT(run.per_flight_grid, truth, frame)
        rows.append(("grid RMS error vs truth, each flight levelled alone", f"{alone:.3f} nT"))
        rows.append(("grid RMS error vs truth, joint levelling", f"{joint:.3f} nT"))
        if joint >= alone:
            errors.append("joint levelling does not improve the grid")
        if args.cli:
            t0 = time.perf_counter()
            res = subprocess.run(
                [sys.executable, "-m", "flows.cli", "campaign", str(proc), "--out"]
                + [str(folder / "cli"), "--workers", "2"],
                capture_output=True,
                text=True,
                cwd=REPO,
            )
            rows.append(("`aeromag campaign` (Prefect server + 2 Dask workers)", _secs(t0)))
            if res.returncode:
                errors.append(res.stderr.strip()[-500:])
            else:
                cli = json.loads((folder / "cli" / "campaign.summary.json").read_text())
                if cli["flight_offsets_nT"] != doc["flight_offsets_nT"]:
                    errors.append("the CLI's flight offsets differ from the plain steps'")
    return finish(rows, errors)


def _list(values) -> str:
    return ", ".join(f"{v:+.3f}" for v in values)


def _secs(t0: float) -> str:
    return f"{time.perf_counter() - t0:.1f} s"


if __name__ == "__main__":
    sys.exit(main())
