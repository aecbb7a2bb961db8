"""The field's steps where a channel switches (pipeline.audit.switching): analytic cases."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.audit.switching import (
    SwitchSteps,
    placebo_inflation,
    switch_body_coupling,
    switch_coupling,
    switch_instants,
    switch_steps,
)


def _flight(rng, coupling_nT_per_A, settle_s=2.0, rate_hz=10.0, duration_s=1800.0):
    """A load switched between two levels at random dwells, settling exponentially; the
    field: a slow random walk (geology along track) plus a bend, the coupling, white noise."""
    t = np.arange(0.0, duration_s, 1.0 / rate_hz)
    level = np.zeros(t.size)
    s, hi = 20.0, False
    while s < duration_s:
        level[t >= s] = 1.9 if not hi else 0.6
        hi = not hi
        s += rng.uniform(40.0, 160.0)
    level[t < 20.0] = 0.6
    alpha = 1.0 - np.exp(-1.0 / (rate_hz * settle_s))
    current = np.empty_like(level)
    current[0] = level[0]
    for i in range(1, t.size):  # the load's settling: a first-order response
        current[i] = current[i - 1] + alpha * (level[i] - current[i - 1])
    current += rng.normal(0.0, 0.01, t.size)
    geology = np.cumsum(rng.normal(0.0, 0.02, t.size)) + 3.0 * np.sin(2 * np.pi * t / 600.0)
    field = 50_000.0 + geology + coupling_nT_per_A * current + rng.normal(0.0, 0.1, t.size)
    return t, field, current


def test_switch_instants_counts_each_switch_once():
    t = np.arange(0.0, 100.0, 0.1)
    x = np.where((t > 30) & (t < 60), 2.0, 0.5) + 0.001 * np.sin(t)
    assert switch_instants(t, x).size == 2
    assert switch_instants(t, x) == pytest.approx([30.0, 60.0], abs=0.6)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_coupling_is_measured_at_the_switches(seed):
    rng = np.random.default_rng(seed)
    t, field, current = _flight(rng, 3.0)
    steps = switch_steps(t, field, current)
    assert steps is not None and steps.step_nT.size >= 8
    got = switch_coupling(steps)
    assert got.p_value < 1e-4
    assert got.total_field_nT_per_unit == pytest.approx(3.0, abs=0.3)
    assert got.heldout.reduction > 0.5


def test_no_coupling_is_rarely_significant():
    # over many flights the p-value of a channel that couples into nothing is uniform:
    # false alarms at alpha = 0.01 stay rare (binomial: <= 3 of 40 has p > 0.99 if 1 %)
    hits = 0
    for seed in range(40):
        rng = np.random.default_rng(100 + seed)
        t, field, current = _flight(rng, 0.0, duration_s=900.0)
        steps = switch_steps(t, field, current)
        got = None if steps is None else switch_coupling(steps)
        hits += got is not None and got.p_value < 0.01
    assert hits <= 3


def _wobbly(rng, t):
    """Interference the windows' line misreads: noise correlated over ~2.5 s (a Hann window
    of 25 samples at 10 Hz), about 2.5 nT RMS."""
    return 0.8 * np.convolve(rng.normal(0.0, 1.0, t.size), np.hanning(25), "same")


def test_placebo_switches_widen_the_errors_the_windows_understate():
    # with no coupling, the field's wobble makes the windows' own errors too small: the
    # channel moved in time (placebo switches) spreads as the true alignment does, and the
    # test at the widened errors keeps its level (binomial: 4 of 20 at 5 % has p 0.016)
    plain, wobbly, false_before, false_after = [], [], 0, 0
    for seed in range(20):
        rng = np.random.default_rng(500 + seed)
        t, field, current = _flight(rng, 0.0, duration_s=1800.0)
        plain.append(placebo_inflation(t, field, current))
        field = field + _wobbly(rng, t)
        wobbly.append(placebo_inflation(t, field, current))
        steps = switch_steps(t, field, current)
        false_before += switch_coupling(steps).p_value < 0.05
        false_after += switch_coupling(steps, inflation=wobbly[-1]).p_value < 0.05
    assert np.median(plain) < 1.2 < 1.4 < np.median(wobbly)
    assert false_after <= 3 and false_after < false_before


def test_placebo_switches_leave_a_true_coupling_measured():
    rng = np.random.default_rng(8)
    t, field, current = _flight(rng, 3.0)
    wider = placebo_inflation(t, field, current)
    got = switch_coupling(switch_steps(t, field, current), inflation=wider)
    assert wider < 1.3
    assert got.p_value < 1e-4 and got.total_field_nT_per_unit == pytest.approx(3.0, abs=0.3)


def test_turns_are_left_out():
    rng = np.random.default_rng(7)
    t, field, current = _flight(rng, 3.0)
    usable = np.ones(t.size, bool)
    all_steps = switch_steps(t, field, current, usable=usable)
    usable[: t.size // 2] = False
    half = switch_steps(t, field, current, usable=usable)
    assert half is not None and half.time_s.min() > t[t.size // 2]
    assert half.time_s.size < all_steps.time_s.size


def test_only_turns_at_a_steady_bank_take_switches():
    from types import SimpleNamespace

    import pandas as pd

    from pipeline.audit.evidence.survey_side import steady_turns

    t = np.arange(0.0, 120.0, 0.1)
    roll = np.where(t < 40.0, 0.0, 25.0) + np.where((t > 80.0) & (t < 90.0), 5.0 * (t - 80.0), 0.0)
    turn = t >= 30.0

    class _Flight:
        data = pd.DataFrame({"roll_deg": roll, "pitch_deg": np.zeros(t.size)})

        def has(self, *cols):
            return all(c in self.data for c in cols)

    ctx = SimpleNamespace(
        flight=_Flight(),
        seg=SimpleNamespace(mask=lambda *labels: turn),
        s=SimpleNamespace(switch_steady_attitude_deg=2.0),
        data=SimpleNamespace(rate_hz=10.0),
    )
    steady = steady_turns(ctx)
    assert not steady[t < 30.0].any()  # not a turn
    assert not steady[(t > 38.0) & (t < 42.0)].any()  # the roll-in within the window
    assert steady[(t > 45.0) & (t < 75.0)].all()  # the bank held
    assert not steady[(t > 81.0) & (t < 89.0)].any()  # the bank changing
    ctx.flight.data = ctx.flight.data.drop(columns="roll_deg")
    assert steady_turns(ctx) is None


def test_a_switch_over_rough_ground_does_not_spoil_the_coupling():
    # a fast carrier crossing an anomaly's flank right at three switches: within their
    # windows the geology is no line; those steps carry large errors and weigh little
    rng = np.random.default_rng(11)
    t, field, current = _flight(rng, 2.5)
    inst = switch_instants(t, current)
    for ts in inst[:3]:
        field = field + 40.0 * np.exp(-0.5 * ((t - ts - 0.7) / 1.2) ** 2)
    got = switch_coupling(switch_steps(t, field, current))
    assert got.total_field_nT_per_unit == pytest.approx(2.5, abs=0.3)
    assert got.p_value < 1e-4
    assert got.heldout.reduction > 0.5 and got.heldout.p_value < 0.01
    # the interval (2 standard errors) holds the truth
    assert abs(got.total_field_nT_per_unit - 2.5) < 2.5 * got.se_nT_per_unit + 0.05


def _steps_at_headings(rng, c, headings_deg, inclination_deg=60.0, se_nT=0.2):
    """Switch steps dI (u . c) + noise, u the field's direction in the body frame of a level
    carrier flying each heading (NED field of the given inclination, no declination)."""
    inc = np.radians(inclination_deg)
    h = np.radians(np.asarray(headings_deg, float))
    u = np.column_stack(
        [np.cos(inc) * np.cos(h), -np.cos(inc) * np.sin(h), np.full(h.size, np.sin(inc))]
    )
    change = np.where(np.arange(h.size) % 2 == 0, 1.3, -1.3)
    step = change * (u @ c) + rng.normal(0.0, se_nT, h.size)
    return SwitchSteps(np.arange(h.size) * 100.0, change, step, np.full(h.size, se_nT), u)


def test_switches_at_many_headings_resolve_the_body_vector():
    c = np.array([0.6, -0.9, 2.8])
    hits = 0
    for seed in range(40):
        rng = np.random.default_rng(seed)
        steps = _steps_at_headings(rng, c, rng.choice([0.0, 90.0, 180.0, 270.0], 14))
        got = switch_body_coupling(steps)
        hits += got.ci95[0] <= np.linalg.norm(c) <= got.ci95[1]
    assert got.vector_nT_per_unit == pytest.approx(c, abs=0.5)
    assert hits >= 36  # a 95 % interval: 38 expected of 40, binomial 5 % tail at 35


def test_switches_at_one_heading_leave_the_body_vector_open():
    rng = np.random.default_rng(3)
    c = np.array([0.6, -0.9, 2.8])
    steps = _steps_at_headings(rng, c, np.zeros(12) + rng.normal(0, 0.5, 12))
    got = switch_body_coupling(steps)
    # one heading sees u . c only: the norm is bounded below (about), not above
    assert got is None or got.ci95[1] - got.ci95[0] > 5.0
