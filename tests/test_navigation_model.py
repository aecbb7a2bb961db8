"""The navigation measurement model (map altitude term, core field) and the window's start
state (a GNSS-aided INS's covariance): issue 38, items 2 and 5."""

from __future__ import annotations

import numpy as np

from pipeline.navigation.alignment import gnss_aided_covariance
from pipeline.navigation.crlb import crlb
from pipeline.navigation.ekf import MeasurementModel, ekf
from pipeline.navigation.ins import GRADES, InsErrorModel, Trajectory, simulate_ins_errors
from pipeline.navigation.map_model import MapModel, upward_continue, vertical_derivative
from pipeline.simulate.navigation import racetrack, random_field_map
from tests.navmaps import navigate_box


def _setup(duration_s, grade="navigation", rate_hz=10.0):
    t, e, n = racetrack(duration_s, rate_hz)
    traj = Trajectory.from_track(t, n, e, np.zeros_like(t), 45.0 + n / 111_000.0)
    model = InsErrorModel(GRADES[grade])
    return t, e, n, traj, model


def _drms(err_ne):
    return float(np.sqrt(np.mean(np.sum(err_ne**2, axis=1))))


def test_h_jacobian_is_the_derivative_of_h():
    """H (map gradient, altitude term, core gradient, bias) is dh/dx by central differences."""
    g = random_field_map(3, size_m=4000.0, cell_m=50.0, correlation_m=400.0)
    mm = MapModel(g, altitude_m=300.0)
    meas = MeasurementModel(
        mm,
        vertical=MapModel(vertical_derivative(g)),
        alt_above_map_m=np.array([40.0]),
        core_grad=np.array([[0.004, -0.002, -0.027]]),
        core_nT=np.array([52_000.0]),
    )
    rng = np.random.default_rng(0)
    e0, n0 = g.east0_m + 2000.0, g.north0_m + 1900.0
    for _ in range(5):
        x = np.zeros(18)
        x[:3] = rng.normal(0, [30.0, 30.0, 5.0])
        x[-1] = 0.7
        h, H = meas.evaluate(0, x, e0, n0)
        num = np.zeros(18)
        for i in (0, 1, 2, 5, 17):
            d = np.zeros(18)
            d[i] = 1e-3
            num[i] = (
                meas.evaluate(0, x + d, e0, n0)[0] - meas.evaluate(0, x - d, e0, n0)[0]
            ) / 2e-3
        assert abs(H[2] - num[2]) < 1e-6 and abs(H[17] - 1.0) < 1e-12 and num[5] == 0.0
        assert np.allclose(H[:2], num[:2], rtol=1e-4, atol=1e-7)
    # the CRLB's vectorised rows are the same Jacobian at zero error
    rows = meas.jacobians_at(np.array([e0]), np.array([n0]), 18)
    assert np.allclose(rows[0], meas.evaluate(0, np.zeros(18), e0, n0)[1], rtol=1e-12)


def test_altitude_term_follows_a_flight_above_the_map():
    """A flight 60 m above the map, read with the map's vertical derivative, sees the field
    continued upward to first order: the residual against the true higher field shrinks."""
    g = random_field_map(4, size_m=8000.0, cell_m=50.0, correlation_m=600.0)
    high = upward_continue(g, 60.0)
    mm = MapModel(g, altitude_m=0.0)
    v = MapModel(vertical_derivative(g))
    rng = np.random.default_rng(1)
    e = g.east0_m + rng.uniform(2000, 6000, 200)
    n = g.north0_m + rng.uniform(2000, 6000, 200)
    truth = MapModel(high).value(e, n)
    plain = mm.value(e, n)
    with_term = plain + v.value(e, n) * 60.0
    assert np.std(truth - with_term) < 0.3 * np.std(truth - plain)


def test_core_gradient_keeps_the_filter_on_track_across_a_core_gradient():
    """The measurement is the total field reduced with the IGRF at the INS-indicated
    position, so it carries -grad(core) . x; with the core gradient in h and H (MagNav's
    core=true) the filter models it, without it the error reads as map signal. A tactical INS
    (errors of hundreds of m) over a steep core gradient (20 nT/km, exaggerated so the effect
    is well above the map's) on three seeds."""
    g = random_field_map(1, size_m=16_000.0, cell_m=50.0, correlation_m=300.0)
    mm = MapModel(g)
    t, e, n, traj, model = _setup(600.0, "tactical")
    phi = model.transitions(traj)
    qd = model.process_noise(np.diff(t, prepend=t[0]))
    p0 = model.initial_covariance()
    grad = np.tile([0.02, 0.012, -0.027], (t.size, 1))
    sigma = 0.1
    better = []
    for seed in range(3):
        x = simulate_ins_errors(model, traj, seed, phi)
        noise = np.random.default_rng(50 + seed).normal(0, sigma, t.size)
        z = mm.value(e, n) - (grad * x[:, :3]).sum(axis=1) + noise
        ins_e, ins_n = e + x[:, 1], n + x[:, 0]
        with_core = ekf(phi, qd, p0, z, ins_e, ins_n, MeasurementModel(mm, core_grad=grad), 0.01)
        without = ekf(phi, qd, p0, z, ins_e, ins_n, mm, sigma**2)
        late = slice(t.size // 2, None)
        a = _drms(x[late, :2] - with_core.state[late, :2])
        b = _drms(x[late, :2] - without.state[late, :2])
        assert a < _drms(x[late, :2]) / 5
        better.append(a < b)
    assert all(better)


def test_gnss_aided_start_has_one_fixs_position_error_and_small_velocity_errors():
    """A GNSS-aided run (3 m fixes at 1 Hz over a 10 min racetrack) leaves position errors
    of about one fix (correlated GNSS errors do not average out), velocity errors of cm/s, a
    symmetric positive definite covariance, and the magnetic bias untouched."""
    t, e, n, traj, model = _setup(600.0, rate_hz=1.0)
    p = gnss_aided_covariance(model, traj, 3.0)
    assert np.allclose(p, p.T) and np.linalg.eigvalsh(p)[0] > 0
    sd = np.sqrt(np.diag(p))
    assert 3.0 <= sd[0] < 3.5 and 3.0 <= sd[1] < 3.5
    assert np.all(sd[3:5] < 0.1)
    assert sd[17] == np.sqrt(model.initial_covariance()[17, 17])
    # the INS-only bound starts from one fix's error and grows
    phi = model.transitions(traj)
    qd = model.process_noise(np.diff(t, prepend=t[0]))
    mm = MapModel(random_field_map(1, size_m=16_000.0, cell_m=50.0, correlation_m=300.0))
    free = crlb(phi, qd, p, e, n, mm, 0.01, np.zeros(t.size, bool))
    assert 4.0 < np.sqrt(free[0, 0, 0] + free[0, 1, 1]) < 5.0
    assert np.sqrt(free[-1, 0, 0] + free[-1, 1, 1]) > np.sqrt(free[0, 0, 0] + free[0, 1, 1])


def test_stage_starts_both_runs_from_the_aided_covariance(monkeypatch, box_path):
    """run_navigation hands the same aided covariance to the filter, the CRLB, the INS-only
    bound and the INS simulation."""
    import pipeline.navigation.stage as stage

    seen = {}
    real_ekf, real_crlb, real_sim = stage.ekf, stage.crlb, stage.simulate_ins_errors

    def spy_ekf(phi, qd, p0, *a, **k):
        seen["ekf"] = p0
        return real_ekf(phi, qd, p0, *a, **k)

    def spy_crlb(phi, qd, p0, *a, **k):
        seen.setdefault("crlb", []).append(p0)
        return real_crlb(phi, qd, p0, *a, **k)

    def spy_sim(*a, p0=None, **k):
        seen["sim"] = p0
        return real_sim(*a, p0=p0, **k)

    monkeypatch.setattr(stage, "ekf", spy_ekf)
    monkeypatch.setattr(stage, "crlb", spy_crlb)
    monkeypatch.setattr(stage, "simulate_ins_errors", spy_sim)
    run = navigate_box(box_path)
    ref = seen["ekf"]
    # the same covariance everywhere, but for the bias state's prior in the filter and its
    # bound, which also holds the map's error (it may be an offset)
    bias = ref[-1, -1] - seen["sim"][-1, -1]
    assert run.map_sigma_source == "default"  # a map without an error grid
    assert np.isclose(bias, run.settings.default_map_sigma_nT**2, rtol=1e-9)
    for p in [seen["sim"], *seen["crlb"]]:
        q = p.copy()
        q[-1, -1] = ref[-1, -1]
        assert np.array_equal(ref, q)
    assert np.array_equal(ref, seen["crlb"][0])
    assert len(seen["crlb"]) == 2
    assert any(note.startswith("initial covariance: GNSS-aided INS") for note in run.notes)
    # not the alignment's diagonal P0: the fixes correlated the states
    assert np.count_nonzero(ref[:17, :17] - np.diag(np.diag(ref[:17, :17]))) > 0


def test_transition_matrices_are_the_exact_exponential():
    """expm_taylor against scipy's expm at 10 Hz and 1 Hz steps (the metre states' scale)."""
    from scipy.linalg import expm

    from pipeline.navigation.ins import expm_taylor

    t, e, n, traj, model = _setup(300.0)
    f = model.dynamics(traj)[::100]
    for dt in (0.1, 1.0):
        want = expm(f * dt)
        assert np.abs(expm_taylor(f * dt) - want).max() < 1e-12 * np.abs(want).max()


def test_each_line_starts_with_its_level_unknown():
    """``stage._line_offsets`` adds the bias state's prior variance at the first epoch of every
    selected line after the window's first, nowhere else; with it, a step in the measured
    level between two lines (a heading-dependent compensation residual) goes to the bias
    state instead of the position: the second line's map-aided DRMS is several times smaller
    than when the bias is carried across."""
    from pipeline.navigation.stage import _line_offsets

    qd = np.zeros((8, 3))
    ids = np.array(["a", "a", "turn", "b", "b", "b", "c", "c"])
    sel = ids != "turn"
    out = _line_offsets(qd, sel, ids, 5.0)
    assert np.flatnonzero(out[:, -1]).tolist() == [3, 6]
    assert np.all(out[:, :-1] == 0) and np.all(qd == 0)

    t, e, n, traj, model = _setup(400.0, rate_hz=5.0)
    phi = model.transitions(traj)
    qd = model.process_noise(np.diff(t, prepend=t[0]))
    mm = MapModel(random_field_map(5, size_m=16_000.0, correlation_m=400.0, rms_nT=30.0))
    ids = np.where(np.isclose(e, 1000.0), "L1", np.where(np.isclose(e, -1000.0), "L2", "turn"))
    sel = ids != "turn"
    p0 = model.initial_covariance()
    p0[-1, -1] += 2.0**2
    meas = MeasurementModel(mm, map_sigma_nT=2.0)
    second = ids == "L2"
    for seed in range(3):
        x = simulate_ins_errors(model, traj, seed, phi, p0=p0)
        noise = np.random.default_rng(seed).normal(0.0, 0.5, t.size)
        z = mm.value(e, n) + np.where(second, 2.0, -2.0) + noise
        drms = [
            _drms(
                (
                    x[:, :2]
                    - ekf(phi, q, p0, z, e + x[:, 1], n + x[:, 0], meas, 0.25, sel).state[:, :2]
                )[second]
            )
            for q in (qd, _line_offsets(qd, sel, ids, p0[-1, -1]))
        ]
        assert drms[1] < drms[0] / 2, drms
