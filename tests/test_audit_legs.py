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
        est = leg_gradient(t, y, enu, legs)  # a field of g alone: no crust
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


def test_a_soft_iron_scale_is_inside_the_interval_when_declared():
    """A carrier whose isotropic soft iron scales the whole reading by 1.005 reads a
    gradient 0.5 % too large; no fit can tell, so only the declared scale uncertainty
    keeps the truth inside the interval."""
    g = np.array([0.3, -0.3, 0.0])
    t, y, enu, cls = box_flight(g, 7, noise_nT=0.02)
    legs = leg_ids(np.ones(t.size, bool), cls, np.ones(t.size, int), t)
    scaled = 1.005 * y
    plain = leg_gradient(t, scaled, enu, legs).ci95()
    declared = leg_gradient(t, scaled, enu, legs, scale_uncertainty=0.005).ci95()
    inside = lambda ci: (ci[:2, 0] <= g[:2]) & (g[:2] <= ci[:2, 1])  # noqa: E731
    assert not inside(plain).any()
    assert inside(declared).all()
    # half-width ~1.96 x 0.005 x 0.3 nT/m
    assert np.allclose(np.diff(declared[:2], axis=1).ravel() / 2, 1.96 * 0.005 * 0.3, rtol=0.1)


def test_no_gradient_gives_uniform_p_and_a_small_ramp():
    ps = []
    for seed in range(40):
        t, y, enu, cls = box_flight([0.0, 0.0, 0.0], 100 + seed)
        est = leg_gradient(t, y, enu, leg_ids(np.ones(t.size, bool), cls, np.ones(t.size, int), t))
        ps.append(est.p_value)
        assert est.ramp_rms_nT < 0.5
    assert 0.0 <= np.mean(np.array(ps) < 0.05) <= 0.2


def switching_current(t, cls, seed):
    """A payload current switched between 0.6 and 1.9 A once on each leg, at a random time
    in the leg's middle half (A)."""
    rng = np.random.default_rng(seed)
    out, level = np.empty(t.size), 0
    for c in "NESW":
        sel = np.flatnonzero(cls == c)
        cut = sel[int(sel.size * rng.uniform(0.25, 0.75))]
        out[sel] = np.where(t[sel] < t[cut], level, 1 - level)
        level = 1 - level
    return 0.6 + 1.3 * out


def test_a_current_compensated_with_a_wrong_coupling_is_no_gradient():
    """No gradient; a current switching within the legs, its coupling fitted wrong by dc
    (nT/A, body frame): the compensated field keeps dc . u I, whose steps differ by heading.
    Read without the current they look like ramps; with u_x I, u_y I, u_z I as nuisance
    columns the p-values are uniform again and a true gradient stays inside its interval."""
    g = np.array([0.05, -0.03, 0.0])
    dc = np.array([12.0, -4.0, 2.0])
    # the field's direction in the body on each heading (x forward, y right, z down; 60 deg
    # inclination): north is forward heading north, to the left heading east
    u_leg = {"N": (0.5, 0.0, 0.87), "E": (0.0, -0.5, 0.87), "S": (-0.5, 0.0, 0.87)}
    u_leg["W"] = (0.0, 0.5, 0.87)
    wrong, ok, cover = 0, 0, 0
    for seed in range(30):
        t, y, enu, cls = box_flight(np.zeros(3), 300 + seed, noise_nT=0.1)
        legs = leg_ids(np.ones(t.size, bool), cls, np.ones(t.size, int), t)
        current = switching_current(t, cls, seed)
        u = np.array([u_leg[c] for c in cls])
        y_left = y + (u @ dc) * current
        columns = u * current[:, None]
        wrong += int(leg_gradient(t, y_left, enu, legs).p_value < 0.01)
        ok += int(leg_gradient(t, y_left, enu, legs, nuisance=columns).p_value >= 0.01)
        real = leg_gradient(t, y_left + enu @ g, enu, legs, nuisance=columns)
        ci = real.ci95()
        cover += int(np.all((ci[:2, 0] <= g[:2]) & (g[:2] <= ci[:2, 1])))
    assert wrong >= 25
    assert ok >= 27
    assert cover >= 27


def test_the_main_fields_gradient_is_no_excess():
    """Legs measure the main field's own gradient (~5 nT/km) at p ~ 0; the excess test
    against it is uniform under the null and rejects a gradient 10 nT/km beyond it."""
    main = np.array([-0.0015, 0.0045])
    p_zero, p_null, p_beyond = [], [], []
    for seed in range(40):
        t, y, enu, cls = box_flight([*main, 0.0], 500 + seed, noise_nT=0.02, leg_s=120.0)
        legs = leg_ids(np.ones(t.size, bool), cls, np.ones(t.size, int), t)
        est = leg_gradient(t, y, enu, legs)
        p_zero.append(est.p_value)
        p_null.append(est.excess_p_value(main))
        beyond = leg_gradient(t, y + enu[:, 0] * 0.01, enu, legs)
        p_beyond.append(beyond.excess_p_value(main))
    assert np.mean(np.array(p_zero) < 0.01) > 0.9
    assert np.mean(np.array(p_null) < 0.05) <= 0.2
    assert np.mean(np.array(p_beyond) < 0.01) > 0.9


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


def crust_field(seed, quiet_box=True):
    """A crust of 40 Gaussian bodies (1-60 nT, 80-400 m wide) over 3 x 3 km holding the
    box (0-630 m each way) and a survey north of it (y 1 000-2 000 m); crews fly the box
    over quieter ground, so the bodies there are weaker. Not the ratio's model: the test
    asks whether the survey's roughness transfers to the box's gradient."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-1000.0, 2000.0, (40, 2))
    width = rng.uniform(80.0, 400.0, 40)
    amp = rng.normal(0.0, 30.0, 40)
    if quiet_box:
        near = np.hypot(xy[:, 0] - 315.0, xy[:, 1] - 315.0) < 700.0
        amp[near] *= 0.1

    def field(e, n):
        d2 = (e[:, None] - xy[None, :, 0]) ** 2 + (n[:, None] - xy[None, :, 1]) ** 2
        return np.exp(-d2 / (2.0 * width**2)) @ amp

    return field


def survey_tracks(field, g, speed_m_s=7.0, rate_hz=10.0, flip=False):
    """Ten north-south lines of 1 km (50 m apart, alternate directions; ``flip``: each
    the other way) and three ties, their times, and ``field`` plus the gradient ``g``
    along them (local metres)."""
    from pipeline.quality.overlap import Track

    along = np.arange(0.0, 1000.0, speed_m_s / rate_hz)
    tracks, ys, ts, t0, start = [], [], [], 0.0, 0
    for k in range(13):
        if k < 10:  # lines
            e = np.full(along.size, -200.0 + 50.0 * k)
            n = 1000.0 + (along if (k + flip) % 2 == 0 else along[::-1])
            kind, heading = "survey", 0.0 if (k + flip) % 2 == 0 else 180.0
        else:  # ties
            e = -200.0 + (along if (k + flip) % 2 == 0 else along[::-1])
            n = np.full(along.size, 1100.0 + 400.0 * (k - 10))
            kind, heading = "tie", 90.0 if (k + flip) % 2 == 0 else 270.0
        idx = np.arange(start, start + along.size)
        tracks.append(Track(f"L{k}", kind, idx, e, n, heading))
        ys.append(field(e, n) + g[0] * e + g[1] * n)
        ts.append(t0 + along / speed_m_s)
        t0 += 1000.0 / speed_m_s + 30.0
        start += along.size
    return np.concatenate(ts), np.concatenate(ys), tracks


def test_the_crust_own_gradient_at_the_site_is_inside_the_interval():
    """A gradient effect over a box whose crust adds its own gradient: the legs read the
    sum, as they should, and with the crust's spread measured on the survey (the ratio of
    its gradients' spread to its departure from a plane, times the legs' residual) the
    interval holds the effect alone on 90 % of crusts; without it, far fewer."""
    from pipeline.audit.legs import crust_roughness_ratio, leg_length_m

    g = np.array([0.03, -0.04, 0.0])
    covered = {"measured": 0, "none": 0}
    for seed in range(30):
        field = crust_field(seed)
        t, y, enu, cls = box_flight(g, seed, noise_nT=0.02)
        y = y + field(enu[:, 0], enu[:, 1])
        legs = leg_ids(np.ones(t.size, bool), cls, np.ones(t.size, int), t)
        ts, ys, tracks = survey_tracks(field, g)
        ratio = crust_roughness_ratio(ts, ys, tracks, leg_length_m(enu, legs))
        assert ratio is not None and ratio[1] >= 13
        for name, r in (("measured", ratio[0]), ("none", None)):
            ci = leg_gradient(t, y, enu, legs, crust_ratio_per_m=r).ci95()
            covered[name] += int(np.all((ci[:2, 0] <= g[:2]) & (g[:2] <= ci[:2, 1])))
    assert covered["measured"] >= 26, covered
    assert covered["none"] <= 20, covered


def test_the_crust_ratio_ignores_a_regional_gradient_and_the_flying_direction():
    """The ratio measures the crust's variation from place to place: a gradient the same
    everywhere (the main field's, a regional one) and the direction each line is flown in
    do not change it; a stronger crust of the same shape leaves it unchanged too."""
    from pipeline.audit.legs import crust_roughness_ratio

    field = crust_field(5)
    # 50 m blocks: a 500 m window holds ten, from either end
    t, y0, tracks = survey_tracks(field, np.zeros(3), speed_m_s=5.0)
    base = crust_roughness_ratio(t, y0, tracks, 500.0)
    _, y1, _ = survey_tracks(field, np.array([0.4, -0.2, 0.0]), speed_m_s=5.0)
    assert np.isclose(crust_roughness_ratio(t, y1, tracks, 500.0)[0], base[0], rtol=1e-6)
    assert np.isclose(crust_roughness_ratio(t, 3.0 * y0, tracks, 500.0)[0], base[0], rtol=1e-9)
    # every line flown the other way round: the same ground, the same ratio
    _, y2, flipped = survey_tracks(field, np.zeros(3), speed_m_s=5.0, flip=True)
    assert np.isclose(crust_roughness_ratio(t, y2, flipped, 500.0)[0], base[0], rtol=0.05)


def test_a_box_over_rough_ground_shows_no_gradient_effect():
    """No gradient effect, the box over a crust with gradients of its own: the legs read
    the ground's gradient at p ~ 0, and the excess test that counts the crust's spread
    measured on the survey as a random effect rejects at about its level, not on most
    boxes."""
    from pipeline.audit.legs import crust_roughness_ratio, leg_length_m

    zero = np.zeros(2)
    rejected = {"measured": 0, "none": 0}
    for seed in range(30):
        field = crust_field(seed)
        t, y, enu, cls = box_flight(np.zeros(3), seed, noise_nT=0.02)
        y = y + field(enu[:, 0], enu[:, 1])
        legs = leg_ids(np.ones(t.size, bool), cls, np.ones(t.size, int), t)
        ts, ys, tracks = survey_tracks(field, np.zeros(3))
        ratio = crust_roughness_ratio(ts, ys, tracks, leg_length_m(enu, legs))
        for name, r in (("measured", ratio[0]), ("none", None)):
            est = leg_gradient(t, y, enu, legs, crust_ratio_per_m=r)
            rejected[name] += int(est.excess_p_value(zero) < 0.05)
    assert rejected["measured"] <= 5, rejected
    assert rejected["none"] >= 20, rejected
