"""A simulated campaign: uav-small sorties over one geology on several days (tests and
benchmarks/bench_campaign.py).

Every sortie flies over the same crustal sources (``anomaly.seed``) with its own seed, its
own day, its own diurnal level (``effects.diurnal.offset_nT``: the level a base station's mean
does not remove) and its lines shifted across track (``survey.line_offset_m``); it is
processed cheaply (one model, no audit, no vector stage, no exports).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from scipy.interpolate import RegularGridInterpolator

from pipeline.geo.local import LocalFrame
from pipeline.simulate import Scenario, simulate

# name, seed, start, diurnal level (nT), line shift (m)
SORTIES = (
    ("day1", 1, "2026-06-15T01:00:00Z", 6.0, 0.0),
    ("day2", 2, "2026-06-17T03:00:00Z", -4.0, 25.0),
    ("day3", 3, "2026-06-20T02:00:00Z", 1.5, 12.5),
)


def campaign_plan(n: int) -> list[tuple]:
    """``SORTIES``, then more up to ``n``: day 2k + 1 of July, a diurnal level drawn from
    N(0, 5) nT (seeded), lines shifted by 12.5 k m modulo the 50 m spacing."""
    rng = np.random.default_rng(19)
    out = list(SORTIES[:n])
    for k in range(len(out), n):
        start = f"2026-07-{1 + 2 * k:02d}T02:00:00Z"
        out.append((f"day{k + 1}", k + 1, start, round(float(rng.normal(0, 5)), 2), 12.5 * k % 50))
    return out


CONFIG = """config_version = 1
[compensation]
models = ["agg-tl"]
[audit]
enabled = false
[vector]
enabled = false
[map]
arima = "1,1,1"
[export]
formats = []
"""


def simulate_campaign(folder: Path, sorties=SORTIES, extra: list[str] | None = None) -> Path:
    """Simulate and process the sorties into ``folder/proc`` (truth beside the recordings).

    ``sorties``: (name, seed, start time, diurnal level nT, line shift m) per flight."""
    from flows.postflight import run_plain
    from pipeline.simulate import write_simulation

    cfg = folder / "process.toml"
    cfg.write_text(CONFIG)
    for name, seed, start, level, shift in sorties:
        sim = simulate(
            Scenario.load(
                "uav-small",
                [
                    "anomaly.seed=7",
                    f"start_time='{start}'",
                    "effects.diurnal.enabled=true",
                    "effects.diurnal.amplitude_nT=0.0",
                    "effects.diurnal.random_walk_nT_per_sqrt_s=0.0",
                    f"effects.diurnal.offset_nT={level}",
                    f"survey.line_offset_m={shift}",
                    "survey.validation=false",
                    *(extra or []),
                ],
            ),
            seed,
        )
        src = write_simulation(sim, folder / f"{name}.mcap", folder / f"{name}.truth.json")
        run_plain(str(src), str(folder / "proc"), str(cfg))
    return folder / "proc"


class Truth:
    """The simulator's true anomaly at any WGS-84 position."""

    def __init__(self, path: Path):
        truth = json.loads(path.read_text())
        tg, site = truth["anomaly"]["grid"], truth["site"]
        v = np.array(tg["values_nT"])
        self.site = LocalFrame(site["latitude_deg"], site["longitude_deg"])
        self.interp = RegularGridInterpolator(
            (
                tg["north0_m"] + tg["cell_m"] * np.arange(v.shape[0]),
                tg["east0_m"] + tg["cell_m"] * np.arange(v.shape[1]),
            ),
            v,
            bounds_error=False,
        )
        self.survey = truth["scenario"]["survey"]

    def at(self, frame: LocalFrame, east_m, north_m, inside_m: float = 25.0) -> np.ndarray:
        """Truth at campaign-frame points; NaN outside the block shrunk by ``inside_m``."""
        lat, lon, _ = frame.to_geodetic(east_m, north_m)
        e, n, _ = self.site.to_enu(lat, lon)
        out = self.interp(np.stack([n, e], -1))
        s = self.survey
        inside = (
            (e > s["east_m"] + inside_m)
            & (e < s["east_m"] + s["width_m"] - inside_m)
            & (n > s["north_m"] + inside_m)
            & (n < s["north_m"] + s["length_m"] - inside_m)
        )
        return np.where(inside, out, np.nan)


def sorties_and_frame(proc: Path):
    """The campaign frame and every sortie of ``proc`` read into it."""
    from pipeline.campaign.sorties import campaign_frame, read_sortie, validate_campaign

    infos = validate_campaign(proc)
    frame = campaign_frame(infos)
    return frame, [read_sortie(k, info, frame) for k, info in enumerate(infos)]


def grid_rmse_nT(grid, truth: Truth, frame: LocalFrame) -> float:
    """RMS of grid - truth over the scored block, after one common offset (the datum)."""
    ge, gn = np.meshgrid(*grid.coordinates())
    t = truth.at(frame, ge, gn)
    ok = np.isfinite(t) & np.isfinite(grid.values)
    d = grid.values[ok] - t[ok]
    return float(np.sqrt(np.mean((d - d.mean()) ** 2)))


def true_levels_nT(sorties, truth: Truth, frame: LocalFrame) -> np.ndarray:
    """The level each flight's line data really has (mean of data - truth over its samples,
    minus the mean over the flights): its diurnal level plus the constant its own
    compensation left."""
    level = []
    for s in sorties:
        e = np.concatenate([ln.east_m for ln in s.lines])
        n = np.concatenate([ln.north_m for ln in s.lines])
        v = np.concatenate([ln.value_nT for ln in s.lines])
        t = truth.at(frame, e, n, inside_m=-25.0)
        level.append(float(np.nanmean(v - t)))
    return np.array(level) - np.mean(level)


def all_crossovers(sorties, min_angle_deg: float = 30.0):
    """Every crossover within and between the sorties, and which are between flights."""
    from pipeline.campaign.joint import sortie_crossovers

    xs, between = [], []
    for i, a in enumerate(sorties):
        for b in [None, *sorties[i + 1 :]]:
            part = sortie_crossovers(a, b, min_angle_deg)
            xs += part
            between += [b is not None] * len(part)
    return xs, np.array(between, bool)
