"""The gradient along the calibration legs (pipeline.audit.legs) against analytic truth."""

from __future__ import annotations

import numpy as np

from pipeline.audit.legs import fisher_combined, leg_gradient, leg_ids


def box_flight(g, seed, noise_nT=0.2, speed_m_s=7.0, leg_s=90.0, rate_hz=10.0):
    """Four straight legs N, E, S, W of a box with a level per leg (heading error), 5 s
    manoeuvre residual cycles, white noise and a few metres of height wobble."""
    rng = np.random.default_rng(seed)
    t_leg = np.arange(0.0, leg_s, 1.0 / rate_hz)
    dirs = {"N": (0, 1), "E": (1, 0), "S": (0, -1), "W": (-1, 0)}
    start = {"N": (0, 0), "E": (0, 630), "S": (630, 630), "W": (630, 0)}
    t, enu, cls, lev = [], [], [], []
    for k, c in enumerate("NESW"):
        e = start[c][0] + dirs[c][0] * speed_m_s * t_leg
        n = start[c][1] + dirs[c][1] * speed_m_s * t_leg
        u = 3.0 * np.sin(2 * np.pi * t_leg / 40.0 + k)
        t.append(k * (leg_s + 10.0) + t_leg)
        enu.append(np.column_stack([e, n, u]))
        cls += [c] * t_leg.size
        lev.append(np.full(t_leg.size, rng.normal(0, 20.0)))
    t, enu, lev = np.concatenate(t), np.vstack(enu), np.concatenate(lev)
    field = enu @ np.asarray(g) + lev + 0.5 * np.sin(2 * np.pi * t / 5.0)
    field += rng.normal(0, noise_nT, t.size)
    return t, field, enu, np.array(cls)


def test_gradient_recovered_within_its_interval_over_seeds():
    g = np.array([0.3, -0.12, 0.05])
    inside, z = 0, []
    for seed in range(40):
        t, y, enu, cls = box_flight(g, seed)
        legs = leg_ids(np.ones(t.size, bool), cls, np.ones(t.size, int), t)
        assert legs.max() == 3
        est = leg_gradient(t, y, enu, legs)
        assert est is not None and est.legs == 4 and est.p_value < 1e-10
        ci = est.ci95()
        inside += int(np.all((ci[:, 0] <= g) & (g <= ci[:, 1])))
        z.append((est.gradient_nT_per_m - g) / est.se_nT_per_m)
        # the ramp along a 630 m leg of a 0.3 nT/m gradient is ~55 nT RMS
        assert 30.0 < est.ramp_rms_nT < 80.0
    # three components, each within its 95 % interval: at least ~0.86 of flights all three
    # (more: the intervals carry a scale uncertainty these flights do not have)
    assert inside >= 28
    # unbiased; the spread of the z-scores at most that of a standard normal
    assert abs(float(np.mean(z))) < 0.5 and 0.2 < float(np.std(z)) < 1.3


def test_no_gradient_gives_uniform_p_and_a_small_ramp():
    ps = []
    for seed in range(40):
        t, y, enu, cls = box_flight([0.0, 0.0, 0.0], 100 + seed)
        est = leg_gradient(t, y, enu, leg_ids(np.ones(t.size, bool), cls, np.ones(t.size, int), t))
        ps.append(est.p_value)
        assert est.ramp_rms_nT < 0.5
    assert 0.0 <= np.mean(np.array(ps) < 0.05) <= 0.2


def test_too_few_legs_gives_none():
    t, y, enu, cls = box_flight([0.1, 0.1, 0.0], 1)
    one = cls == "N"
    assert (
        leg_gradient(
            t[one],
            y[one],
            enu[one],
            leg_ids(np.ones(one.sum(), bool), cls[one], np.ones(one.sum(), int), t[one]),
        )
        is None
    )


def test_fisher_combination():
    assert fisher_combined(0.5, 0.5) > 0.5
    assert fisher_combined(0.04, 1e-10) < 1e-9
