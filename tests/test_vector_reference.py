"""Steps in the carrier's permanent field against the fluxgate (issue 16, item 3): found
where they are at their size, not invented from geology, interference or autocorrelated
residual."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import lfilter

from pipeline.audit.vector_reference import (
    difference_design,
    persists_against_fluxgate,
    scan_vector_reference,
    vector_reference_step,
)

RATE_HZ = 10.0
DURATION_S = 2400.0


def flight(seed: int, dp_nT=(0.0, 0.0, 0.0), step_s: float = 1300.0, off_s: float = np.inf):
    """A flight of straight legs on headings turning by 70 deg every 100 s (every heading
    flown before and after any time), with 3 deg roll and pitch oscillations, in a 50 000 nT
    field inclined 60 deg with a geology of tens of nT along track. The scalar sensor reads
    ``|b + p + A b|`` with white noise and a 3 s AR(1) residual, plus ``u . dp`` from
    ``step_s`` (to ``off_s``); the fluxgate ``b + p_v`` with 0.5 nT of noise.

    Returns time (s), scalar (nT), fluxgate (n, 3; body frame x forward, y right, z down, nT).
    """
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, DURATION_S, 1 / RATE_HZ)
    # heading: 100 s legs, each turned 70 deg from the last in a 10 s turn
    legs = np.floor(t / 100.0)
    within = np.clip((t - 100.0 * legs) / 10.0, 0.0, 1.0)
    yaw = np.radians(70.0 * (legs - 1 + within))
    roll = np.radians(3.0) * np.sin(2 * np.pi * t / 7.0)
    pitch = np.radians(3.0) * np.sin(2 * np.pi * t / 11.0 + 1.0)
    inc = np.radians(60.0)
    geology = np.convolve(rng.normal(0, 8.0, t.size), np.ones(50) / np.sqrt(50), "same")
    f = 50_000.0 + geology
    ned = f[:, None] * np.array([np.cos(inc), 0.0, np.sin(inc)])
    # NED -> body: R_x(roll)^T R_y(pitch)^T R_z(yaw)^T
    cy, sy, cp, sp, cr, sr = (np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch),
                              np.cos(roll), np.sin(roll))  # fmt: skip
    x1 = cy * ned[:, 0] + sy * ned[:, 1]
    y1 = -sy * ned[:, 0] + cy * ned[:, 1]
    z1 = ned[:, 2]
    x2 = cp * x1 - sp * z1
    z2 = sp * x1 + cp * z1
    y3 = cr * y1 + sr * z2
    z3 = -sr * y1 + cr * z2
    b = np.column_stack([x2, y3, z3])
    u = b / np.linalg.norm(b, axis=1, keepdims=True)
    perm = np.array([30.0, -20.0, 45.0])
    induced = np.array([[1.2, 0.4, -0.7], [0.4, 0.9, 0.3], [-0.7, 0.3, 2.1]]) * 1e-3
    scalar = np.linalg.norm(b + perm + b @ induced.T, axis=1)
    a = np.exp(-1 / (3.0 * RATE_HZ))
    scalar += lfilter([np.sqrt(1 - a**2)], [1, -a], rng.normal(0, 0.2, t.size))
    scalar += rng.normal(0, 0.05, t.size)
    scalar += ((t > step_s) & (t < off_s)) * (u @ np.asarray(dp_nT, float))
    vector = b + np.array([10.0, -8.0, 15.0]) + rng.normal(0, 0.5, b.shape)
    return t, scalar, vector


def test_a_step_is_found_where_it_is_at_its_size():
    dp = np.array([2.0, -3.0, 1.5])
    t, s, v = flight(1, dp, step_s=1313.0)
    step = vector_reference_step(t, s, v, alpha=0.01, min_size_nT=1.0)
    assert step is not None
    assert step.start_s - 10.0 <= 1313.0 <= step.end_s + 10.0
    assert step.size_nT == pytest.approx(np.linalg.norm(dp), rel=0.15)
    assert np.allclose(step.dp_nT, dp, atol=0.5)
    ev = step.to_dict(10**18)
    assert ev["kind"] == "step" and ev["start_ns"] < 10**18 + 1313.5e9 < ev["end_ns"] + 10e9


def test_no_step_without_one():
    """Geology, the carrier's permanent and induced fields and the fluxgate's own offset
    all lie in the model: no event, and the scan's p is not small."""
    for seed in (2, 3, 4):
        t, s, v = flight(seed)
        assert vector_reference_step(t, s, v, alpha=0.01, min_size_nT=0.0) is None
        assert scan_vector_reference(t, s, v).p_value > 0.01


def test_a_recorded_switched_current_is_no_step():
    """A current recorded on an auxiliary channel, switched on for good at 1300 s and
    coupling into the scalar sensor, is in the model; unrecorded, it is a step."""
    t, s, v = flight(5)
    current = (t > 1300.0) * 2.0
    u = v / np.linalg.norm(v, axis=1, keepdims=True)
    s = s + current * (u @ np.array([1.5, 1.0, -2.0]))
    assert vector_reference_step(t, s, v) is not None
    assert vector_reference_step(t, s, v, aux={"current": current}) is None


def test_a_recorded_current_with_gaps_and_a_scalar_dropout_still_joins_the_model():
    """A channel recorded on most epochs joins the model with its gaps left out (before, a
    single missing sample dropped the channel, so its switch read as a step), and a scalar
    dropout beside a recorded channel is left out too (it used to stop the audit)."""
    t, s, v = flight(5)
    current = (t > 1300.0) * 2.0
    u = v / np.linalg.norm(v, axis=1, keepdims=True)
    s = s + current * (u @ np.array([1.5, 1.0, -2.0]))
    gappy = current.copy()
    gappy[[0, 1, 5000, 5001]] = np.nan  # a channel's first and a few later samples missing
    s[8000:8050] = np.nan  # a 5 s scalar dropout
    assert vector_reference_step(t, s, v, aux={"current": gappy}) is None
    assert vector_reference_step(t, s, v) is not None


def test_too_short_a_record_gives_nothing():
    t, s, v = flight(6, (3.0, 0.0, 0.0), step_s=100.0)
    keep = t < 300.0
    assert scan_vector_reference(t[keep], s[keep], v[keep]) is None


def test_a_step_that_dominates_the_residual_is_found():
    """A trial flight (:mod:`pipeline.simulate.audit_trials`: a multicopter, one calibration
    pass far from a 400 m survey) with a 6.4 nT step in the carrier's permanent field two
    thirds into the survey. The model's residual without the step is mostly the step: a
    scan whitened and weighted from it puts its likeliest change point elsewhere, at F under
    its null's 95 % point. The least-squares first scan finds it, and the whitened scans
    then confirm it far beyond the margin."""
    from pathlib import Path
    from tempfile import TemporaryDirectory

    from pipeline.audit.context import AuditData
    from pipeline.segment import segment_flight
    from pipeline.simulate import audit_trials as at

    rng = np.random.default_rng(3838603)
    overrides = at.random_flight_overrides(rng) + at.hidden_overrides("step", rng)
    overrides += at.TIED_SURVEY[at.override_value(overrides, "profile")]
    sim = at.simulate(at.Scenario.load("uav-small", overrides), int(rng.integers(2**31)))
    truth = at.add_permanent_step(sim, rng)
    with TemporaryDirectory() as tmp:
        f = at.read_flight(at.write_simulation(sim, Path(tmp) / "step.mcap"))
    d = AuditData.from_flight(f, segment_flight(f).mask("calibration"))
    step = vector_reference_step(d.time_s, d.scalar_nT, d.vector_nT, d.aux, alpha=0.01)
    assert step is not None
    assert abs(step.time_s - truth["time_s"]) < 10.0
    assert np.allclose(step.dp_nT, truth["dp_nT"], atol=0.6)


@pytest.mark.parametrize("seed", [1, 2])
def test_a_change_that_persists_is_told_from_a_load_switched_off_again(seed):
    """A load on from 1313 s and off at 1391 s, inside the turn after its leg (1390-1400 s),
    fits the difference as a pulse; a change left on fits as a step to the end; a load
    switched off after the window (a later leg) is read as persisting there."""
    dp = np.array([1.0, -1.2, 0.5])
    window = (1390.0, 1400.0)
    t, s, v = flight(seed, dp, step_s=1313.0, off_s=1391.0)
    assert persists_against_fluxgate(t, s, v, 1313.0, window) is False
    t, s, v = flight(seed, dp, step_s=1313.0)
    assert persists_against_fluxgate(t, s, v, 1313.0, window) is True
    t, s, v = flight(seed, dp, step_s=1313.0, off_s=1900.0)
    assert persists_against_fluxgate(t, s, v, 1313.0, window) is True
    # a record ending in the window holds nothing after it
    keep = t < 1401.0
    assert persists_against_fluxgate(t[keep], s[keep], v[keep], 1313.0, window) is None


def test_a_step_design_the_base_spans_adds_no_direction():
    # a recorded current switched on once and left on is a step u . dp the base's current
    # columns already hold: its part outside the base is rounding noise, not three new
    # directions; a design outside the base keeps an orthonormal basis
    from pipeline.audit.vector_reference import _span_basis, _step_bases

    rng = np.random.default_rng(5)
    n = 400
    u = rng.normal(size=(n, 3))
    on = (np.arange(n) > 150).astype(float)
    spanned = u * on[:, None]
    base = np.column_stack([np.ones(n), u, spanned @ rng.normal(size=(3, 3))])
    q0 = _span_basis(base)
    free = u * (np.arange(n) > 260)[:, None]
    b = _step_bases(q0, [spanned * 1e3, free])
    assert np.all(b[:, :3] == 0.0)
    assert np.allclose(b[:, 3:].T @ b[:, 3:], np.eye(3), atol=1e-9)
    assert np.allclose(q0.T @ b[:, 3:], 0.0, atol=1e-9)


def test_a_design_built_once_gives_what_each_test_builds_itself():
    # the audit builds the difference's design once for the step scan and the persistence
    # check: given it, each gives the same answer as from the readings
    t, s, v = flight(6, np.array([2.0, -3.0, 1.5]), step_s=1313.0, off_s=1500.0)
    design = difference_design(t, s, v)
    own, given = scan_vector_reference(t, s, v), scan_vector_reference(t, s, v, design=design)
    assert (given.time_s, given.p_value) == (own.time_s, own.p_value)
    assert np.array_equal(given.dp_nT, own.dp_nT)
    for window in ((1310.0, 1320.0), (1450.0, 1600.0)):
        assert persists_against_fluxgate(t, s, v, 1313.0, window) is persists_against_fluxgate(
            t, s, v, 1313.0, window, design=design
        )
