"""A step inside a calibration leg: a change of the carrier's permanent field persists through
the rest of the calibration (an event); a load switched on and off again does not (a
switched-current nuisance). Whole simulated flights through ``run_audit``: slow."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline.audit.stage import run_audit
from pipeline.io.reader import read_flight
from pipeline.segment import segment_flight
from pipeline.simulate import Scenario, simulate, write_simulation


def _audit_with_step(
    tmp_path: Path, seed: int, transient: bool, leg: int = 1, mid_block: bool = False
) -> dict:
    """A 2 nT change u . dp from the middle of calibration leg ``leg`` (in time order; with
    ``mid_block``, of the manoeuvre block nearest it, clear of the scan's guard at the
    blocks' edges): to the end of the flight, or (``transient``) only to the end of the
    turn after that leg."""
    sim = simulate(Scenario.load("uav-small", ["calibration.passes=1"]), seed)
    legs: dict = {}
    for g in sim.truth["segments"]:
        if g["label"] == "calibration":
            legs.setdefault(g["line_id"], []).append((g["start_s"], g["end_s"]))
    ordered = sorted(legs.values())
    i = leg % len(ordered)
    a, b = ordered[i][0][0], ordered[i][-1][1]
    c = ordered[i + 1][0][0] if i + 1 < len(ordered) else b + 12.0  # the transit after the last
    on = 0.5 * (a + b)
    if mid_block:
        block = min(ordered[i], key=lambda blk: abs(0.5 * (blk[0] + blk[1]) - on))
        on = 0.5 * (block[0] + block[1])
    on, off = on + 0.37, (c - 2.0) if transient else np.inf
    s, v = sim.streams["/mag/scalar"], sim.streams["/mag/vector"]
    vec = np.stack([np.interp(s["t"], v["t"], v["cols"][f"{k}_nT"]) for k in "xyz"], -1)
    u = vec / np.linalg.norm(vec, axis=1, keepdims=True)
    dp = np.random.default_rng(seed).normal(size=3)
    dp *= 2.0 / np.linalg.norm(dp)
    s["cols"]["total_nT"] = s["cols"]["total_nT"] + ((s["t"] > on) & (s["t"] < off)) * (u @ dp)
    flight = read_flight(write_simulation(sim, tmp_path / f"f{seed}{transient}{leg}.mcap"))
    res = run_audit(flight, segment_flight(flight)).to_json()
    return res


# the step lies 4.1 s before a manoeuvre block's end: inside the 5 s where the leg scan
# looks for none (interference even in the attitude settles there; docs/audit.md)
IN_GUARD = pytest.mark.xfail(
    strict=True, reason="step within guard_s of a manoeuvre's edge: not scanned"
)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [pytest.param(3, marks=IN_GUARD), 4])
def test_a_load_switched_off_again_is_a_nuisance_not_an_event(tmp_path, seed):
    res = _audit_with_step(tmp_path, seed, transient=True)
    events = res["unexplained"]["events"]
    leg_events = [e for e in events if e["evidence"] == "calibration residual"]
    assert leg_events == []
    forms = [n["estimate"].get("form") for n in res["unexplained"]["nuisances"]]
    assert "switching" in forms


@pytest.mark.slow
@pytest.mark.parametrize("seed", [3, 4])
def test_a_load_switched_off_in_the_turn_is_no_event_where_the_scan_sees_it(tmp_path, seed):
    """Switched on mid-block, where the legs' scan finds it, and off in the turn after the
    leg: the scalar-minus-fluxgate record shows it off again, so no change of the
    permanent field is reported from the calibration."""
    res = _audit_with_step(tmp_path, seed, transient=True, mid_block=True)
    events = res["unexplained"]["events"]
    assert [e for e in events if e["evidence"] == "calibration residual"] == []


@pytest.mark.slow
@pytest.mark.parametrize("seed", [3, 4])
def test_a_permanent_change_in_the_calibration_stays_an_event(tmp_path, seed):
    res = _audit_with_step(tmp_path, seed, transient=False)
    steps = [e for e in res["unexplained"]["events"] if e["kind"] == "step"]
    assert steps


@pytest.mark.slow
@pytest.mark.parametrize("seed", [pytest.param(3, marks=IN_GUARD), pytest.param(4, marks=IN_GUARD)])
def test_a_permanent_change_in_the_last_leg_is_judged_on_the_legs_before(tmp_path, seed):
    """No calibration follows the last leg: the legs before it, whose permanent terms the
    change does not touch, still tell it (they fit better with the terms free after it)."""
    res = _audit_with_step(tmp_path, seed, transient=False, leg=-1)
    events = res["unexplained"]["events"]
    assert [e for e in events if e["evidence"] == "calibration residual"]
