"""Steps inside calibration legs (issue 16, item 3): located, and not invented from the
autocorrelated residual that manoeuvres leave."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import lfilter

from pipeline.audit.calibration_events import (
    calibration_steps,
    is_switching,
    manoeuvre_blocks,
    switching_nuisance,
)

RATE_HZ = 10.0


def legs_with_residual(seed: int, step_nT: float = 0.0, step_s: float = 0.0):
    """Four 80 s legs separated by 10 s turns: each leg a different level and along-track
    trend (the Earth field), plus white noise and an AR(1) residual with a 3 s correlation
    time (what manoeuvres leave after compensation)."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 4 * 90.0, 1 / RATE_HZ)
    leg = np.full(t.size, -1)
    y = np.full(t.size, np.nan)
    a = np.exp(-1 / (3.0 * RATE_HZ))
    ar = lfilter([np.sqrt(1 - a**2)], [1, -a], rng.normal(0, 0.15, t.size))
    for k in range(4):
        m = (t >= 90 * k) & (t < 90 * k + 80)
        leg[m] = k
        y[m] = (
            50_000
            + rng.normal(0, 20)
            + rng.normal(0, 0.01) * (t[m] - 90 * k)
            + ar[m]
            + rng.normal(0, 0.05, m.sum())
        )
    y = y + step_nT * (t > step_s)
    return t, y, leg


def test_a_step_inside_a_leg_is_found_where_it_is():
    t, y, leg = legs_with_residual(3, step_nT=1.0, step_s=137.3)
    ev = calibration_steps(t, y, leg, alpha=0.01, min_size_nT=0.3)
    assert len(ev) == 1
    assert ev[0].start_s - 2.0 <= 137.3 <= ev[0].end_s + 2.0
    assert ev[0].size_nT == pytest.approx(1.0, abs=0.3)


def test_a_step_between_legs_is_not_one():
    """Between legs the level changes anyway (heading): no event."""
    t, y, leg = legs_with_residual(4, step_nT=3.0, step_s=85.0)
    assert calibration_steps(t, y, leg, alpha=0.01, min_size_nT=0.3) == []


def test_no_events_from_autocorrelated_residual():
    false = sum(
        bool(calibration_steps(*legs_with_residual(100 + s), alpha=0.01, min_size_nT=0.0))
        for s in range(40)
    )
    # alpha 0.01 after the scan correction: 0.4 expected; 3 or more would mean the
    # autocorrelation is not accounted for (p < 0.01 under a binomial(40, 0.01))
    assert false <= 2


def test_an_oscillation_is_not_a_step():
    """A 0.4 nT, 0.25 Hz oscillation over the calibration (a gimbal motor) is structure, but
    not a step: the oscillation event comes from the residual spectrum instead."""
    t, y, leg = legs_with_residual(5)
    y = y + 0.4 * np.sin(2 * np.pi * 0.25 * t)
    assert calibration_steps(t, y, leg, alpha=0.01, min_size_nT=0.3) == []


def telegraph(t: np.ndarray, seed: int, size_nT: float, dwell_s=(5.0, 40.0)) -> np.ndarray:
    """A load switched on and off at random dwell times: 0 or ``size_nT`` (nT)."""
    rng = np.random.default_rng(seed)
    edges = np.cumsum(rng.uniform(*dwell_s, 200))
    return size_nT * (np.searchsorted(edges, t) % 2)


def test_a_switched_load_is_a_nuisance_not_a_step():
    """Repeated steps back and forth (an unrecorded switched current, dwelling 20-60 s) are
    not the one change of the permanent field an event reports: two or more steps make a
    switching nuisance. (Switched faster, its steps raise each leg's residual above three
    times a step and few are found: see docs/audit.md, limits.)"""
    hits = 0
    for s in range(6):
        t, y, leg = legs_with_residual(200 + s)
        tel = telegraph(t, s, 1.0, (20.0, 60.0))
        hits += is_switching(calibration_steps(t, y + tel, leg, 0.01, 0.3, max_steps=6))
    assert hits >= 5
    t, y, leg = legs_with_residual(210)
    y = y + telegraph(t, 10, 1.0, (20.0, 60.0))
    steps = calibration_steps(t, y, leg, 0.01, 0.3, max_steps=6)
    rec = switching_nuisance(t, y, leg, steps)
    assert rec["name"] == "unrecorded_current"
    assert rec["estimate"]["form"] == "switching"
    assert rec["estimate"]["step_nT"] == pytest.approx(1.0, abs=0.3)
    assert 0.0 < rec["heldout_gain"] < 1.0


def test_one_step_stays_one_when_more_are_looked_for():
    """A single change of the permanent field is not taken for a switched load: the scan for
    further steps finds none beyond the scan's level (at most 2 of 20 seeds)."""
    several = 0
    for s in range(20):
        t, y, leg = legs_with_residual(300 + s, step_nT=1.0, step_s=137.3)
        steps = calibration_steps(t, y, leg, 0.01, 0.3, max_steps=6)
        assert steps, s
        several += is_switching(steps)
    assert several <= 2


def test_manoeuvre_blocks_number_each_run_of_one_manoeuvre():
    lab = np.array(["", "roll", "roll", "steady", "pitch", "pitch", "roll", "steady", ""])
    assert manoeuvre_blocks(lab).tolist() == [-1, 0, 0, -1, 1, 1, 2, -1, -1]


def test_a_level_change_where_a_manoeuvre_stops_is_no_step():
    """Interference even in the attitude (a second-order term, roll squared) raises the
    compensated field's mean while the carrier rolls: a 1 nT level change where each roll
    block stops (and starts). With the manoeuvre blocks known no step is looked for at
    their edges; read blind, the same record gives one. A step inside a block is still
    found where it is."""
    t, y, leg = legs_with_residual(7)
    label = np.full(t.size, "steady", dtype=object)
    rolling = np.zeros(t.size, bool)
    for k in range(4):  # a 30 s roll block in the middle of each leg
        rolling |= (t >= 90 * k + 25) & (t < 90 * k + 55)
    label[rolling] = "roll"
    label[leg < 0] = ""
    block = manoeuvre_blocks(label)
    offset = y + 1.0 * rolling
    assert calibration_steps(t, offset, leg, alpha=0.01, min_size_nT=0.3, block=block) == []
    assert calibration_steps(t, offset, leg, alpha=0.01, min_size_nT=0.3) != []
    stepped = y + 1.0 * (t > 130.3)  # inside the second leg's roll block (115-145 s)
    ev = calibration_steps(t, stepped, leg, alpha=0.01, min_size_nT=0.3, block=block)
    assert len(ev) == 1
    assert ev[0].start_s - 2.0 <= 130.3 <= ev[0].end_s + 2.0


def test_a_level_that_builds_up_as_a_manoeuvre_starts_is_no_step():
    """The attitude's amplitude builds up over a manoeuvre's first seconds (a fixed-wing's
    roll-in), and the mean of interference in the attitude with it: a 1 nT level reached
    2 s after each roll block starts, within guard_s of the edge. Read with only the edge
    bins left out, the ramp's steep part is a "step" one bin inside the block; with the
    manoeuvre's edges guarded as a leg's ends are, none is found. A step in the middle of
    a block is still found."""
    t, y, leg = legs_with_residual(8)
    label = np.full(t.size, "steady", dtype=object)
    ramp = np.zeros(t.size)
    for k in range(4):  # a 40 s roll block in the middle of each leg, 2 s roll-in
        start = 90 * k + 20
        inside = (t >= start) & (t < start + 40)
        label[inside] = "roll"
        ramp[inside] = np.clip((t[inside] - start - 1.0) / 1.0, 0.0, 1.0)
    label[leg < 0] = ""
    block = manoeuvre_blocks(label)
    ramped = y + 1.0 * ramp
    assert calibration_steps(t, ramped, leg, alpha=0.01, min_size_nT=0.3, block=block) == []
    stepped = y + 1.0 * (t > 130.3)  # inside the second leg's roll block (110-150 s)
    ev = calibration_steps(t, stepped, leg, alpha=0.01, min_size_nT=0.3, block=block)
    assert len(ev) == 1
    assert ev[0].start_s - 2.0 <= 130.3 <= ev[0].end_s + 2.0
