"""The field's steps where a channel switches (pipeline.audit.switching): analytic cases."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.audit.switching import switch_coupling, switch_instants, switch_steps


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


def test_turns_are_left_out():
    rng = np.random.default_rng(7)
    t, field, current = _flight(rng, 3.0)
    usable = np.ones(t.size, bool)
    all_steps = switch_steps(t, field, current, usable=usable)
    usable[: t.size // 2] = False
    half = switch_steps(t, field, current, usable=usable)
    assert half is not None and half.time_s.min() > t[t.size // 2]
    assert half.time_s.size < all_steps.time_s.size
