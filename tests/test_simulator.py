"""The flight simulator: plan geometry, manoeuvre kinematics, effects, determinism."""

from __future__ import annotations

import numpy as np
import orjson
import pytest
from mcap.reader import make_reader

from pipeline.errors import AeromagError
from pipeline.simulate import Scenario, write_simulation
from pipeline.simulate.trajectory import _Dubins, build_trajectory, plan_legs
from tests.conftest import QUIET, run_sim


def test_same_seed_same_file_different_seed_different_file(tmp_path):
    paths = []
    for name, seed in (("a", 3), ("b", 3), ("c", 4)):
        sim = run_sim("calibration-only", seed, ["calibration.passes=1"])
        paths.append(write_simulation(sim, tmp_path / f"{name}.mcap", tmp_path / f"{name}.json"))
    a, b, c = (p.read_bytes() for p in paths)
    assert a == b
    assert a != c
    assert (tmp_path / "a.json").read_bytes() == (tmp_path / "b.json").read_bytes()


def test_recording_holds_only_what_a_recorder_has(box_sim_file):
    _sim, path = box_sim_file
    with path.open("rb") as f:
        reader = make_reader(f)
        topics = {c.topic for c in reader.get_summary().channels.values()}
        assert not list(reader.iter_metadata()) and not list(reader.iter_attachments())
    assert topics == {
        "/mag/scalar",
        "/mag/vector",
        "/ins/attitude",
        "/gnss/fix",
        "/base/scalar",
        "/aux/motor_current",
        "/aux/payload_current",
        "/aux/bus_voltage",
        "/aux/temperature",
    }  # no /plan/line unless asked, no truth


def test_demo_plan_is_the_002_survey():
    legs = plan_legs(Scenario.load("demo"))
    survey = [g for g in legs if g.label == "survey"]
    ties = [g for g in legs if g.label == "tie"]
    val = [g for g in legs if g.label == "validation"]
    cal = [g for g in legs if g.label == "calibration"]
    assert len(survey) == 15 and all(abs(g.length_m - 2000) < 1e-6 for g in survey)
    easts = sorted(g.start_en[0] for g in survey)
    np.testing.assert_allclose(np.diff(easts), 50.0)
    assert {round(g.heading_deg) for g in survey} == {0, 180}
    assert len(ties) == 5 and {round(g.heading_deg) for g in ties} <= {90, 270}
    assert len(val) == 2 and all(abs(g.length_m - np.hypot(700, 2000)) < 1e-6 for g in val)
    assert len(cal) == 8 and sorted({g.cardinal for g in cal}) == ["E", "N", "S", "W"]
    assert all(g.alt_agl_m == 100.0 for g in survey + ties + val + cal)


def test_segments_cover_the_flight_and_calibration_has_12_boxes_per_pass():
    sim = run_sim("calibration-only", 2)
    seg = sim.truth["segments"]
    starts = np.array([s["start_s"] for s in seg])
    ends = np.array([s["end_s"] for s in seg])
    np.testing.assert_allclose(starts[1:], ends[:-1])
    assert starts[0] == 0.0 and abs(ends[-1] - sim.truth["duration_s"]) < 1e-9
    boxes = {
        (s["line_id"][:2], s["cardinal"], s["manoeuvre"])
        for s in seg
        if s["label"] == "calibration" and s["manoeuvre"] in ("roll", "pitch", "yaw")
    }
    assert len(boxes) == 24  # 2 passes x 4 headings x 3 manoeuvres


def test_manoeuvres_reach_their_amplitude_and_move_the_multicopter():
    """Roll +-10 deg at 6 s makes a multicopter sway sideways by g tan(10 deg)/w^2 ~ 1.58 m."""
    sc = Scenario.load("calibration-only", ["calibration.passes=1"])
    traj = build_trajectory(sc)
    seg = next(
        s
        for s in run_sim("calibration-only", 1, ["calibration.passes=1"]).truth["segments"]
        if s["manoeuvre"] == "roll" and s["cardinal"] == "N"
    )
    t = np.arange(seg["start_s"], seg["end_s"], 0.01)
    st = traj.state(t)
    assert abs(np.max(np.abs(st["roll_deg"])) - 10.0) < 0.05
    # north-bound leg: sideways is east; remove the straight-line position
    sway = st["east_m"] - np.median(st["east_m"])
    omega = 2 * np.pi / 6.0
    expected = 9.80665 * np.tan(np.radians(10.0)) / omega**2
    mid = (t > seg["start_s"] + 3.0) & (t < seg["end_s"] - 3.0)  # full-amplitude cycle
    assert abs(np.max(np.abs(sway[mid])) - expected) / expected < 0.05
    assert np.max(np.abs(st["pitch_deg"] + 3.0)) < 1e-6  # no pitch during the roll box


def test_dubins_turns_end_on_the_next_leg():
    rng = np.random.default_rng(0)
    for _ in range(200):
        p0, p1 = rng.normal(size=2) * 100, rng.normal(size=2) * 100
        a0, a1 = rng.uniform(0, 2 * np.pi, 2)
        d = _Dubins(
            p0, np.array([np.cos(a0), np.sin(a0)]), p1, np.array([np.cos(a1), np.sin(a1)]), 20.0
        )
        pos, ang, _k = d.evaluate(np.array([0.0, d.length]))
        np.testing.assert_allclose(pos[0], p0, atol=1e-6)
        np.testing.assert_allclose(pos[1], p1, atol=1e-6)
        assert abs(np.angle(np.exp(1j * (ang[1] - a1)))) < 1e-9


def test_fixed_wing_profile_flies_fast_and_calibrates_high():
    sim = run_sim("fixed-wing", 1)
    g = sim.streams["/gnss/fix"]
    traj = sim.trajectory
    t = np.asarray(g["t"])
    st = traj.state(t)
    speed = np.hypot(np.gradient(st["east_m"], t), np.gradient(st["north_m"], t))
    assert abs(np.median(speed) - 60.0) < 1.0
    cal = [s for s in sim.truth["segments"] if s["label"] == "calibration"]
    tc = np.concatenate([np.arange(s["start_s"], s["end_s"], 1.0) for s in cal])
    assert traj.state(tc)["up_m"].min() >= 1500.0
    assert np.max(np.abs(traj.state(traj.master_t)["roll_deg"])) <= 35.0 + 1e-6


def test_gradient_effect_adds_the_planar_field(tmp_path):
    """With noise off, gradient-on minus gradient-off equals g . (position - reference).

    Interference is off: the induced term A b would otherwise scale the added field by
    (1 + u'Au), about 0.2 % here.
    """
    base = ["calibration.passes=1", *QUIET, "interference_enabled=false"]
    off = run_sim("calibration-only", 9, base)
    on = run_sim("calibration-only", 9, [*base, "effects.geomagnetic_gradient.enabled=true"])
    diff = (
        on.streams["/mag/scalar"]["cols"]["total_nT"]
        - off.streams["/mag/scalar"]["cols"]["total_nT"]
    )
    st = on.trajectory.state(on.streams["/mag/scalar"]["t"])
    gvec = np.array(on.truth["effective"]["gradient_nT_per_m"])
    ref = np.array([0.0, 0.0, 100.0])  # survey corner at survey height
    pos = np.stack([st["east_m"], st["north_m"], st["up_m"]], -1)
    expected = (pos - ref) @ gvec
    assert np.ptp(expected) > 100  # the box sits hundreds of metres from the reference
    # added along the main field: the scalar sees it scaled by cos(field, main) ~ 1 - 1e-6
    np.testing.assert_allclose(diff, expected, atol=0.01 + 1e-4 * np.abs(expected).max())


def test_sensor_lag_delays_the_scalar_stream():
    base = ["calibration.passes=1", *QUIET]
    ref = run_sim("calibration-only", 4, base)
    lag = run_sim(
        "calibration-only",
        4,
        [*base, "effects.sensor_lag.enabled=true", "effects.sensor_lag.lag_s=0.2"],
    )
    assert lag.truth["effective"]["sensor_lag_s"] == 0.2
    t_ref, v_ref = ref.streams["/mag/scalar"]["t"], ref.streams["/mag/scalar"]["cols"]["total_nT"]
    t_lag, v_lag = lag.streams["/mag/scalar"]["t"], lag.streams["/mag/scalar"]["cols"]["total_nT"]
    # the lagged sensor stamps at t what the reference sensor stamped at t - 0.2 s
    k = np.rint((t_lag - 0.2 - t_ref[0]) * 10).astype(int)
    ok = (k >= 0) & (k < t_ref.size)
    assert np.allclose(t_ref[k[ok]], t_lag[ok] - 0.2, atol=1e-9)
    np.testing.assert_allclose(v_lag[ok], v_ref[k[ok]], atol=1e-6)


def test_diurnal_is_seen_by_the_base_station():
    sim = run_sim(
        "calibration-only",
        2,
        [
            "calibration.passes=1",
            *QUIET,
            "effects.diurnal.enabled=true",
            "effects.diurnal.amplitude_nT=20.0",
            "effects.diurnal.period_s=600.0",
            "effects.diurnal.random_walk_nT_per_sqrt_s=0.0",
        ],
    )
    base = sim.streams["/base/scalar"]["cols"]["total_nT"]
    assert 30.0 < np.ptp(base) <= 40.0 + 1e-6  # a 20 nT sinusoid over most of a period


def test_electrical_current_couples_into_the_scalar():
    base = ["calibration.passes=1", *QUIET]
    off = run_sim("calibration-only", 5, base)
    on = run_sim(
        "calibration-only",
        5,
        [
            *base,
            "effects.electrical_current.enabled=true",
            "effects.electrical_current.coupling_nT_per_A=4.0",
        ],
    )
    diff = (
        on.streams["/mag/scalar"]["cols"]["total_nT"]
        - off.streams["/mag/scalar"]["cols"]["total_nT"]
    )
    current = on.streams["/aux/payload_current"]["cols"]["value"]  # same clock, no noise
    # |diff| = 4 nT/A x I x |u . d| with |u . d| <= 1
    assert np.corrcoef(diff, current)[0, 1] > 0.9
    assert np.max(np.abs(diff)) <= 4.0 * np.max(current) + 1e-6


def test_vector_calibration_errors_apply_the_sensor_model():
    base = ["calibration.passes=1", *QUIET, "interference_enabled=false"]
    off = run_sim("calibration-only", 5, base)
    on = run_sim("calibration-only", 5, [*base, "effects.vector_calibration.enabled=true"])
    from pipeline.physics import FluxgateErrors

    fe = FluxgateErrors(**on.truth["fluxgate_errors"])
    b = np.stack([off.streams["/mag/vector"]["cols"][k] for k in ("x_nT", "y_nT", "z_nT")], -1)
    m = np.stack([on.streams["/mag/vector"]["cols"][k] for k in ("x_nT", "y_nT", "z_nT")], -1)
    np.testing.assert_allclose(m, fe.apply(b), atol=1e-6)
    assert np.max(np.abs(m - b)) > 50.0


def test_plan_markers_and_dropouts(tmp_path):
    sim = run_sim(
        "calibration-only",
        1,
        [
            "calibration.passes=1",
            "sensors.plan_markers=true",
            'sensors.dropouts=[{topic="/ins/attitude", start_s=200.0, duration_s=3.0}]',
        ],
    )
    plan = sim.streams["/plan/line"]
    assert plan["labels"]["kind"][:3] == ["transit", "calibration", "turn"]
    assert "C1N" in plan["labels"]["line_id"]
    t = sim.streams["/ins/attitude"]["t"]
    assert not np.any((t >= 200.0) & (t < 203.0))
    assert np.max(np.diff(t)) > 2.9


def test_scenario_errors_are_one_line():
    with pytest.raises(AeromagError, match="unknown scenario key 'survey.lenght_m'"):
        Scenario.load("demo", ["survey.lenght_m=10"])
    with pytest.raises(AeromagError, match="unknown scenario 'nope'.*demo"):
        Scenario.load("nope")
    with pytest.raises(AeromagError, match="unknown profile"):
        Scenario.from_dict({"profile": "zeppelin"})


def test_truth_document_carries_what_stages_must_find(box_sim_file):
    sim, path = box_sim_file
    truth = orjson.loads(path.with_suffix("").with_suffix(".truth.json").read_bytes())
    assert truth["seed"] == 11
    assert set(truth["interference"]["scalar"]) == {"permanent_nT", "induced", "eddy_s"}
    assert truth["enabled_effects"] == []
    g = truth["anomaly"]["grid"]
    assert np.array(g["values_nT"]).shape == tuple(g["shape"])
    assert truth["noise"]["scalar_nT"] == sim.scenario["sensors"]["scalar_noise_nT"]
