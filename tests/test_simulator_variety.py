"""Flight variety in the simulator (issue 16 item 6): every option does what it says, checked
against physics or an independent computation, and changes nothing while it is off."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import CubicSpline
from scipy.signal import StateSpace, lsim

from pipeline.compensate.terms import tl18_terms
from pipeline.errors import AeromagError
from pipeline.noise import white_noise_nT
from pipeline.simulate import Scenario
from pipeline.simulate.simulator import VIBRATION_MODES
from pipeline.simulate.trajectory import build_trajectory, manoeuvre_truth, plan_legs
from pipeline.simulate.variety import OUTSIDE_TERMS, random_flight_overrides
from tests.conftest import QUIET, run_sim

BOX = ["calibration.passes=1", *QUIET]
RANGES = [
    "calibration.block_duration_s=[15.0, 60.0]",
    "calibration.period_range_s=[3.0, 10.0]",
    "calibration.amplitude_range_deg=[3.0, 15.0]",
]


def _scalar(sim) -> tuple[np.ndarray, np.ndarray]:
    s = sim.streams["/mag/scalar"]
    return np.asarray(s["t"]), np.asarray(s["cols"]["total_nT"])


def _mask(sim, t: np.ndarray, label: str = "calibration", manoeuvre: str | None = None):
    m = np.zeros(t.size, bool)
    for sg in sim.truth["segments"]:
        if sg["label"] == label and (manoeuvre is None or sg["manoeuvre"] == manoeuvre):
            m |= (t >= sg["start_s"]) & (t < sg["end_s"])
    return m


def _tl18_residual_rms(sim) -> float:
    """RMS left on the calibration legs by a least-squares tl18 fit (the compensation stage's
    columns from the *recorded* fluxgate, plus a constant) of scalar minus Earth field."""
    t, total = _scalar(sim)
    v = sim.streams["/mag/vector"]
    assert np.allclose(v["t"], t)  # QUIET: one clock for every stream
    k, _ = tl18_terms(np.stack([v["cols"][c] for c in ("x_nT", "y_nT", "z_nT")], -1), t)
    k = np.column_stack([k, np.ones(t.size)])
    y = total - sim.series["earth_total_nT"]
    cal = _mask(sim, t)
    scale = np.linalg.norm(k[cal], axis=0)
    coef, *_ = np.linalg.lstsq(k[cal] / scale, y[cal], rcond=None)
    return float(np.sqrt(np.mean((y[cal] - k[cal] / scale @ coef) ** 2)))


# ------------------------------------------------------------------------- defaults unchanged
def test_options_at_their_default_change_nothing():
    plain = run_sim("calibration-only", 3, ["calibration.passes=1"])
    explicit = run_sim(
        "calibration-only",
        3,
        [
            "calibration.passes=1",
            'calibration.heading_order=""',
            "calibration.block_duration_s=[]",
            "interference.outside_basis.vibration_nT=0.0",
            "effects.sensor_lag.response=delay",
            "effects.electrical_current.temperature_coefficient_per_K=0.0",
        ],
    )
    for topic, st in plain.streams.items():
        for col, values in st.get("cols", {}).items():
            np.testing.assert_array_equal(values, explicit.streams[topic]["cols"][col])
    assert plain.truth == explicit.truth
    assert "calibration_manoeuvres" not in plain.truth
    assert "outside_basis_interference" not in plain.truth
    assert "heading_order" not in plain.truth["scenario"]["calibration"]
    assert "outside_basis" not in plain.truth["scenario"]["interference"]
    assert "response" not in plain.truth["effects"]["sensor_lag"]
    # a used option is recorded (a new section whole, with its time constants)
    sc = Scenario.load(
        "calibration-only",
        ["interference.outside_basis.vibration_nT=0.3", "calibration.heading_order=random"],
    )
    rec = sc.recorded_config()
    assert rec["interference"]["outside_basis"]["vibration_nT"] == 0.3
    assert rec["interference"]["outside_basis"]["eddy_tau_s"] == 0.5
    assert rec["calibration"]["heading_order"] == "random"
    assert "block_duration_s" not in rec["calibration"]


# ------------------------------------------------------------------------- calibration variety
def test_heading_order_is_honoured_letters_and_random():
    def order(sc, seed):
        legs = [g for g in plan_legs(sc, seed) if g.label == "calibration"]
        return ["".join(g.cardinal for g in legs if g.block == b) for b in ("cal1", "cal2")]

    assert order(Scenario.load("calibration-only", ["calibration.heading_order=WNES"]), 0) == [
        "WNES",
        "WNES",
    ]
    sc = Scenario.load("calibration-only", ["calibration.heading_order=random"])
    seen = [order(sc, seed) for seed in range(8)]
    assert all(sorted(p) == list("ENSW") for pair in seen for p in pair)
    assert len({p for pair in seen for p in pair}) >= 5  # many of the 24 orders
    assert any(a != b for a, b in seen)  # each pass draws its own order
    assert order(sc, 3) == order(sc, 3)  # seeded
    # the flown legs really point that way
    legs = [g for g in plan_legs(sc, 3) if g.label == "calibration"]
    for g in legs:
        assert (
            abs(
                (g.heading_deg - {"N": 0, "E": 90, "S": 180, "W": 270}[g.cardinal] + 180) % 360
                - 180
            )
            < 1e-6
        )
    with pytest.raises(AeromagError, match="heading_order"):
        plan_legs(Scenario.load("calibration-only", ["calibration.heading_order=NXE"]))


@pytest.mark.parametrize("profile", ["uav", "fixed-wing"])
def test_manoeuvre_blocks_are_drawn_from_their_ranges_and_flown(profile):
    """Each block's length, period and amplitude lie in their ranges; the attitude reaches
    the drawn amplitude and oscillates at the drawn period (zero crossings every period/2)."""
    sc = Scenario.load(
        "calibration-only",
        [
            f"profile={profile}",
            "calibration.passes=1",
            *RANGES,
            "calibration.manoeuvre_order=random",
        ],
    )
    traj = build_trajectory(sc, 5)
    blocks = manoeuvre_truth(traj)
    assert len(blocks) == 12
    by_leg: dict[str, list[str]] = {}
    for b in blocks:
        by_leg.setdefault(b["line_id"], []).append(b["kind"])
        assert 15.0 - 1e-9 <= b["end_s"] - b["start_s"] <= 60.0 + 1e-9
        assert 3.0 <= b["period_s"] <= 10.0 and 3.0 <= b["amplitude_deg"] <= 15.0
    assert all(sorted(k) == ["pitch", "roll", "yaw"] for k in by_leg.values())
    assert len({tuple(k) for k in by_leg.values()}) > 1  # the order changes between legs
    assert len({round(b["period_s"], 6) for b in blocks}) == 12  # drawn per block
    cruise = float(sc["flight"]["cruise_pitch_deg"])
    for b in blocks:
        if b["kind"] == "yaw":
            continue
        t = np.arange(b["start_s"], b["end_s"], 0.005)
        st = traj.state(t)
        x = st["roll_deg"] if b["kind"] == "roll" else st["pitch_deg"] - cruise
        assert abs(np.max(np.abs(x)) - b["amplitude_deg"]) < 0.02 * b["amplitude_deg"]
        inner = (t > t[0] + 0.05) & (t < t[-1] - 0.05)
        s = np.sign(x[inner])
        zc = t[inner][1:][s[1:] != s[:-1]]
        assert abs(np.mean(np.diff(zc)) - b["period_s"] / 2) < 0.02 * b["period_s"]
    # the segment truth (what segmentation is scored against) follows the drawn blocks
    sim = run_sim(
        "calibration-only",
        5,
        [
            f"profile={profile}",
            "calibration.passes=1",
            *RANGES,
            "calibration.manoeuvre_order=random",
        ],
    )
    seg = [
        (s["start_s"], s["end_s"])
        for s in sim.truth["segments"]
        if s["manoeuvre"] in ("roll", "pitch", "yaw")
    ]
    np.testing.assert_allclose(
        seg, [(b["start_s"], b["end_s"]) for b in sim.truth["calibration_manoeuvres"]]
    )
    np.testing.assert_allclose(seg, [(b["start_s"], b["end_s"]) for b in blocks])


# ------------------------------------------------------------------------- sensor response
def test_first_order_sensor_lag_is_a_filter_with_group_delay_tau():
    tau = 0.3
    ref = run_sim("calibration-only", 4, BOX)
    lag = run_sim(
        "calibration-only",
        4,
        [
            *BOX,
            "effects.sensor_lag.enabled=true",
            f"effects.sensor_lag.lag_s={tau}",
            "effects.sensor_lag.response=first_order",
        ],
    )
    t_ref, v_ref = _scalar(ref)
    t_lag, v_lag = _scalar(lag)
    # cross-correlation lag: the shift of the unfiltered truth that best matches the recording
    spline = CubicSpline(t_ref, v_ref)
    cal = _mask(lag, t_lag) & (t_lag > t_ref[0] + 2)
    delays = np.arange(0.0, 0.8, 0.005)
    cost = [np.mean((v_lag[cal] - spline(t_lag[cal] - d)) ** 2) for d in delays]
    best = delays[int(np.argmin(cost))]
    assert abs(best - tau) < 0.15 * tau
    # ... but not a pure delay: the recording is the first-order response of the unfiltered
    # signal (scipy's continuous-time simulation, linear between samples)
    k = np.rint((t_lag - t_ref[0]) * 10).astype(int)
    ok = (k >= 0) & (k < t_ref.size)
    x = v_ref[k[ok]]
    sys = StateSpace([[-1 / tau]], [[1 / tau]], [[1.0]], [[0.0]])
    _, y, _ = lsim(sys, x, t_lag[ok] - t_lag[ok][0], X0=[x[0]], interp=True)
    np.testing.assert_allclose(v_lag[ok], y, atol=1e-6)
    assert min(cost) > 1e-4  # a shifted copy does not reproduce the filtered signal
    # the effect's delay mode is still a pure delay (shift 0.3 s reproduces it exactly)
    dly = run_sim(
        "calibration-only",
        4,
        [*BOX, "effects.sensor_lag.enabled=true", f"effects.sensor_lag.lag_s={tau}"],
    )
    t_d, v_d = _scalar(dly)
    np.testing.assert_allclose(v_d[cal], spline(t_d[cal] - tau), atol=1e-3)


# ------------------------------------------------------------------------- current coupling
def test_current_coupling_drifts_with_the_recorded_temperature():
    base = [*BOX, "aux.temperature_rise_K=20.0", "aux.temperature_time_s=300.0"]
    cur = [
        "effects.electrical_current.enabled=true",
        "effects.electrical_current.coupling_nT_per_A=4.0",
    ]
    k = 0.01
    off = run_sim("calibration-only", 6, base)
    flat = run_sim("calibration-only", 6, [*base, *cur])
    drift = run_sim(
        "calibration-only",
        6,
        [*base, *cur, f"effects.electrical_current.temperature_coefficient_per_K={k}"],
    )
    d_flat = _scalar(flat)[1] - _scalar(off)[1]
    d_drift = _scalar(drift)[1] - _scalar(off)[1]
    temp = drift.streams["/aux/temperature"]["cols"]["value"]  # same clock, 0.05 K noise
    big = np.abs(d_flat) > 0.5
    ratio = d_drift[big] / d_flat[big]
    expected = 1 + k * (temp[big] - 24.0)
    assert np.ptp(expected) > 0.15  # the coupling changes by more than 15 % in flight
    assert np.max(np.abs(ratio - expected)) < 0.003  # 0.05 K noise x 0.01/K, plus rounding


# ------------------------------------------------------------------------- outside the basis
@pytest.mark.parametrize("term", OUTSIDE_TERMS)
def test_outside_basis_terms_have_the_requested_share(term):
    """The reported share matches the request, and an independent tl18 least-squares fit on
    the recorded fluxgate (the compensation stage's own columns) cannot remove it."""
    want = 0.8
    sim = run_sim("calibration-only", 5, [*BOX, f"interference.outside_basis.{term}_nT={want}"])
    rep = sim.truth["outside_basis_interference"]
    assert set(rep["terms"]) == {term}
    assert abs(rep["calibration_outside_tl18_rms_nT"] - want) < 0.2 * want
    assert rep["calibration_rms_nT"] >= 0.99 * rep["calibration_outside_tl18_rms_nT"]
    resid = _tl18_residual_rms(sim)
    assert 0.8 * want <= resid < 1.2 * want
    if term == "unrecorded_current":
        plain = run_sim("calibration-only", 5, BOX)
        # nothing outside the basis: the same fit leaves almost nothing
        assert _tl18_residual_rms(plain) < 0.05 * want
        # no new channel: the current is unrecorded
        assert set(sim.streams) == set(plain.streams)


def test_lagging_eddy_currents_follow_the_manoeuvres_and_vibration_aliases():
    sim = run_sim(
        "calibration-only",
        2,
        [
            *BOX,
            "calibration.steady_s=10.0",
            "interference.outside_basis.eddy_lag_nT=0.5",
            "interference.outside_basis.vibration_nT=0.5",
            "interference.outside_basis.vibration_hz=23.3",
        ],
    )
    t, _ = _scalar(sim)
    eddy = sim.series["outside_basis_eddy_lag_nT"]
    # lagging eddy fields need a changing field: none in steady straight flight (3 s after a
    # block, the 0.5 s decay is over; 3 s before a turn, whose roll-in has not begun), strong
    # while manoeuvring
    steady = np.zeros(t.size, bool)
    for sg in sim.truth["segments"]:
        if sg["label"] == "calibration" and sg["manoeuvre"] == "steady":
            steady |= (t >= sg["start_s"] + 3.0) & (t < sg["end_s"] - 3.0)
    moving = _mask(sim, t, "calibration", "roll") | _mask(sim, t, "calibration", "yaw")
    assert np.sqrt(np.mean(eddy[moving] ** 2)) > 30 * np.sqrt(np.mean(eddy[steady] ** 2))
    # vibration at 23.3 Hz (modes x1.13, x0.87) sampled at 10 Hz: in steady flight (rotors at
    # hover speed) the power sits at the aliased frequencies
    vib = sim.series["outside_basis_vibration_nT"]
    seg = max(
        (s for s in sim.truth["segments"] if s["label"] == "transit"),
        key=lambda s: s["end_s"] - s["start_s"],
    )
    w = (t >= seg["start_s"]) & (t < seg["end_s"])
    x = vib[w] * np.hanning(w.sum())
    f = np.fft.rfftfreq(x.size, 0.1)
    p = np.abs(np.fft.rfft(x)) ** 2
    alias = [abs(23.3 * r - 10 * round(23.3 * r / 10)) for r in VIBRATION_MODES]
    near = np.any([np.abs(f - a) < 0.1 for a in alias], axis=0)
    assert p[near].sum() > 0.9 * p.sum()
    assert np.max(alias) < 5.0 and p[f > 3.0].sum() > 0.3 * p.sum()  # not only near DC


# ------------------------------------------------------------------------- random flights
def test_random_flight_overrides_stay_in_their_ranges():
    a = random_flight_overrides(np.random.default_rng(9))
    assert a == random_flight_overrides(np.random.default_rng(9))
    rng = np.random.default_rng(0)
    profiles, passes = set(), set()
    for _ in range(40):
        ov = random_flight_overrides(rng, outside_basis_nT=(0.2, 1.0))
        sc = Scenario.load("uav-small", ov)  # every key is a scenario key
        cal, ob = sc["calibration"], sc["interference"]["outside_basis"]
        profiles.add(sc["profile"])
        passes.add(cal["passes"])
        assert sorted(cal["heading_order"]) == list("ENSW")
        assert cal["period_range_s"] == [3.0, 10.0] and cal["amplitude_range_deg"] == [3.0, 15.0]
        assert 15.0 <= cal["block_duration_s"][0] <= cal["block_duration_s"][1] <= 60.0
        assert 0.02 <= sc["sensors"]["scalar_noise_nT"] <= 0.5
        total = np.sqrt(sum(ob[f"{k}_nT"] ** 2 for k in OUTSIDE_TERMS))
        assert 0.2 - 1e-9 <= total <= 1.0 + 1e-9
        assert sc["survey"]["enabled"] and not sc["survey"]["validation"]
    assert profiles == {"uav", "fixed-wing"} and passes == {1, 2}


def test_random_flights_report_their_share_and_noise():
    """Simulated random flights: the total share outside the basis is the requested root-sum-
    square on calibration and is reported for the survey too; on quiet flights (nothing
    outside the basis) the 4th-difference noise estimate recovers the requested sigma."""
    rng = np.random.default_rng(16)
    for seed in range(2):
        ov = random_flight_overrides(
            rng, profiles=("uav",), passes=(1, 1), outside_basis_nT=(0.3, 1.0)
        )
        sim = run_sim("uav-small", seed, ov)
        sc = sim.scenario
        want = np.sqrt(
            sum(sc["interference"]["outside_basis"][f"{k}_nT"] ** 2 for k in OUTSIDE_TERMS)
        )
        rep = sim.truth["outside_basis_interference"]
        assert abs(rep["calibration_outside_tl18_rms_nT"] - want) < 0.2 * want
        assert rep["survey_rms_nT"] > 0 and rep["survey_outside_tl18_rms_nT"] > 0
        assert sim.truth["duration_s"] < 30 * 60
    for profile, sigma in (("uav", 0.02), ("fixed-wing", 0.02), ("uav", 0.5)):
        ov = random_flight_overrides(
            rng,
            profiles=(profile,),
            passes=(1, 1),
            noise_nT=(sigma, sigma),
            outside_basis_nT=(0.0, 0.0),
        )
        sim = run_sim("uav-small", 1, ov)
        _t, v = _scalar(sim)
        # the pipeline's one white-noise estimator (the 4th difference's spectral level, its
        # gain divided out): a 60 m/s aircraft's manoeuvres and turns do not count at 0.02 nT
        est = white_noise_nT(v)
        assert abs(est - sigma) < 0.15 * sigma, (profile, sigma, est)
