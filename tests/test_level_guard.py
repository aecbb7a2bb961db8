"""The calibration legs' heading-level check of an extension (issue 36, item 3).

On a synthetic box (a crust and noise common to both models, per-heading level errors the
band-passed fit cannot see): a heading-dependent level the extension adds is caught, equal
or better levels pass, and with both models' heading errors drawn from one distribution
the test rejects at its level over many seeds. In the stage: a used extension that passes
records the check, one whose levels are worse is reverted to tl18's field, saying why.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import binomtest

from pipeline.compensate import FitSettings
from pipeline.compensate import stage as stage_mod
from pipeline.compensate.level_guard import LevelCheck, compare_levels
from pipeline.io.reader import read_flight
from pipeline.segment import segment_flight
from pipeline.simulate import write_simulation
from tests.conftest import run_sim

RATE_HZ = 10.0
LEG_S = 60.0


def _box(passes: int = 2):
    """(leg, heading class) per epoch of a box of four headings flown ``passes`` times,
    60 s legs at 10 Hz."""
    n = int(LEG_S * RATE_HZ)
    legs = np.repeat(np.arange(4 * passes), n)
    return legs, legs % 4


def _crust(legs, rng):
    """What the crust under each leg and the day's variation leave in the reduced field,
    the same for every model (nT), and white noise."""
    return rng.normal(0.0, 0.5, legs.max() + 1)[legs] + rng.normal(0.0, 0.05, legs.size)


def test_a_heading_level_the_extension_adds_is_caught():
    rng = np.random.default_rng(1)
    legs, head = _box()
    common = _crust(legs, rng)
    tl18 = common + np.array([0.05, -0.03, 0.02, -0.04])[head]
    worse = tl18 + np.array([1.2, -0.5, -1.4, 0.7])[head]
    every = np.ones(legs.size, bool)
    check = compare_levels(worse, tl18, head, every)
    assert isinstance(check, LevelCheck) and check.headings == 4
    assert check.p_value < 0.05, check
    assert check.spread_nT > 2 * check.tl18_spread_nT
    # the other way round: the extension removes tl18's heading error
    assert compare_levels(tl18, worse, head, every).p_value > 0.9


def test_equal_levels_pass_and_two_headings_give_no_test():
    rng = np.random.default_rng(2)
    legs, head = _box()
    f = _crust(legs, rng)
    every = np.ones(legs.size, bool)
    assert compare_levels(f, f.copy(), head, every).p_value == 1.0
    assert compare_levels(f + 1.0 * head, f, head, head < 2) is None


def test_the_level_test_rejects_at_its_level_under_the_null():
    """Both models' heading errors drawn from one distribution (0.3 nT per heading, shared
    by its legs) beside a crust common to both, over 400 seeds: the share with p < 0.05
    is 5 % within its exact binomial interval."""
    legs, head = _box()
    every = np.ones(legs.size, bool)
    hits, draws = 0, 400
    for seed in range(draws):
        rng = np.random.default_rng([36, seed])
        common = _crust(legs, rng)
        a, b = (common + rng.normal(0.0, 0.3, 4)[head] for _ in range(2))
        hits += compare_levels(a, b, head, every).p_value < 0.05
    ci = binomtest(hits, draws).proportion_ci(0.99)
    assert ci.low <= 0.05 <= ci.high, (hits, draws)


@pytest.fixture(scope="module")
def eddy_flight():
    """A two-box calibration with a lagging eddy current outside tl18's basis (tl-plus
    takes its eddy-decay group there)."""
    sim = run_sim("calibration-only", 1, ["interference.outside_basis.eddy_lag_nT=0.5"])
    fl = read_flight(write_simulation(sim, Path(tempfile.mkdtemp()) / "eddy.mcap"))
    return fl, segment_flight(fl)


def test_the_stage_reverts_an_extension_whose_legs_are_worse(eddy_flight, monkeypatch):
    fl, seg = eddy_flight
    kept = stage_mod.run_compensation(fl, seg, FitSettings(model="tl-plus"))
    ext = kept.model.extension
    assert kept.model.used, ext["reason"]
    assert ext["level_guard"] == "passed" and ext["level_guard_headings"] >= 3
    assert 0.05 <= ext["level_guard_p"] <= 1.0
    tl18 = stage_mod.run_compensation(fl, seg, FitSettings(model="tl18"))

    def worse(*args, **kwargs):
        return LevelCheck(p_value=0.001, spread_nT=0.9, tl18_spread_nT=0.3, headings=4)

    monkeypatch.setattr(stage_mod, "compare_levels", worse)
    reverted = stage_mod.run_compensation(fl, seg, FitSettings(model="tl-plus"))
    ext = reverted.model.extension
    assert not reverted.model.used and ext["guard"] == "level"
    assert "calibration legs' levels by heading" in ext["reason"], ext["reason"]
    ok = np.isfinite(tl18.compensated_nT)
    assert np.allclose(reverted.compensated_nT[ok], tl18.compensated_nT[ok], atol=1e-9)
