"""The audit's null model: the carrier's physics outside the T-L basis taken in first
(:mod:`pipeline.audit.nuisances`), a late sensor weighed against eddy currents that decay
(:mod:`pipeline.audit.hypotheses.lag_decay`), and the whole selection's false-finding rate
measured by a parametric bootstrap of the null model (:mod:`pipeline.audit.null_calibration`).

The synthetic calibrations are made here with their own physics (an exact first-order
discretisation of the decay, a random-telegraph current, AR(1) sensor noise), not with the
audit's design builders. The slow checks run the whole audit on the independent recordings
in ``../shared/recordings`` (made by a generator that is not aeromag's), skipped when absent.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.signal import lfilter

from pipeline.audit.extended import BandSettings
from pipeline.audit.hypotheses.lag_decay import LagVersusDecay, _unresolved, timing_p_late
from pipeline.audit.nuisances import select_from
from pipeline.audit.null_calibration import calibrate_null, monte_carlo_threshold, surrogates
from pipeline.audit.result import Evaluation
from pipeline.audit.timing import TimingLag
from pipeline.compensate.heldout import HeldOut
from pipeline.compensate.model import Measurements
from tests.manoeuvres import manoeuvres
from tests.recordings import INDEPENDENT

RECORDINGS = INDEPENDENT
ALPHA, MIN_GAIN = 0.01, 0.05


def calibration(rate_hz: float = 10.0, seed: int = 1):
    """Four 90-s legs of roll, pitch and yaw oscillations (4-7 s periods, 5-10 deg): time (s),
    body-frame field (nT; x forward, y right, z down), direction cosines, and the carrier's
    permanent and induced field's total-field part (nT)."""
    rng = np.random.default_rng(seed)
    t, b = manoeuvres(rate_hz)
    u = b / np.linalg.norm(b, axis=1, keepdims=True)
    carrier = u @ rng.normal(0.0, 30.0, 3) + np.sum(u * (b @ rng.normal(0, 2e-4, (3, 3))), axis=1)
    return t, b, u, carrier


def decayed(x: np.ndarray, dt: float, tau_s: float) -> np.ndarray:
    """Exact first-order response (step-invariant) of ``x`` (n, k) to a decay ``tau_s``."""
    a = np.exp(-dt / tau_s)
    return lfilter([1.0 - a], [1.0, -a], x, axis=0)


def ar1_noise(n: int, sigma_nT: float, rho: float, rng) -> np.ndarray:
    """Coloured sensor noise: AR(1) with lag-one correlation ``rho``, RMS ``sigma_nT``."""
    return lfilter([1.0], [1.0, -rho], rng.normal(0.0, sigma_nT * np.sqrt(1 - rho**2), n))


def eddy_flight(tau_s: float, seed: int = 3):
    """A 10 Hz calibration whose eddy currents decay over ``tau_s`` (the physics run at
    1 kHz, where the discretisation of the decay does not matter, then sampled)."""
    rng = np.random.default_rng(seed)
    t, b, u, carrier = calibration(rate_hz=1000.0, seed=seed)
    e_matrix = rng.normal(0.0, 3e-5, (3, 3))  # s: eddy field per rate of change of the field
    eddy = decayed(np.gradient(b, t, axis=0), t[1] - t[0], tau_s) @ e_matrix.T
    scalar = np.linalg.norm(b, axis=1) + carrier + np.sum(u * eddy, axis=1)
    t, b, scalar = t[::100], b[::100], scalar[::100]
    return Measurements(t, scalar + ar1_noise(t.size, 0.01, 0.3, rng), b)


@pytest.mark.parametrize("tau_s", [0.1, 0.2, 0.5])
def test_eddy_decay_enters_the_null_with_its_time_constant(tau_s):
    meas = eddy_flight(tau_s)
    sel = select_from(meas, np.ones(meas.time_s.size, bool), BandSettings(), ALPHA, MIN_GAIN)
    got = {n.name: n for n in sel.nuisances}
    assert "eddy_decay" in got, sel.to_list()
    assert got["eddy_decay"].heldout_gain >= MIN_GAIN
    assert abs(np.log(sel.eddy_tau_s / tau_s)) < np.log(1.3), sel.eddy_tau_s
    assert set(got["eddy_decay"].to_dict()) == {"name", "heldout_gain", "estimate"}


def test_a_calibration_with_nothing_outside_tl_takes_no_nuisance():
    rng = np.random.default_rng(5)
    t, b, _, carrier = calibration(seed=5)
    scalar = np.linalg.norm(b, axis=1) + carrier + ar1_noise(t.size, 0.02, 0.3, rng)
    sel = select_from(Measurements(t, scalar, b), np.ones(t.size, bool), BandSettings(), 0.01, 0.05)
    assert sel.nuisances == []


def telegraph(t: np.ndarray, dwell_s: float, rng) -> np.ndarray:
    """A current switched on and off at random dwell times (mean ``dwell_s``), 0/1 A."""
    edges = np.cumsum(rng.exponential(dwell_s, int(2 * t[-1] / dwell_s) + 10))
    return (np.searchsorted(edges, t) % 2).astype(float)


@pytest.mark.parametrize("coupling_nT_per_A", [0.0, 0.3])
def test_the_null_bootstrap_measures_the_selections_false_finding_rate(coupling_nT_per_A):
    rng = np.random.default_rng(11)
    t, b, u, carrier = calibration(seed=11)
    current = telegraph(t, 8.0, rng)
    direction = np.array([0.3, -0.5, 0.8])
    scalar = np.linalg.norm(b, axis=1) + carrier + ar1_noise(t.size, 0.02, 0.5, rng)
    scalar += coupling_nT_per_A * current * (u @ direction)
    meas = Measurements(t, scalar, b)
    sel = select_from(meas, np.ones(t.size, bool), BandSettings(), ALPHA, MIN_GAIN)
    cands = {
        "electrical_current:load": current[:, None] * u,
        "electrical_current:other": telegraph(t, 5.0, rng)[:, None] * u,
    }
    nc = calibrate_null(sel.setup, sel.columns, cands, 0.05, MIN_GAIN, draws=400, seed=0)
    out = nc.to_dict()
    assert out["method"] == "parametric_bootstrap" and out["draws"] >= 200
    # the rate is counted on half the draws: 3 binomial standard errors of slack
    assert out["flight_alpha"] <= 0.05 + 3 * np.sqrt(0.05 * 0.95 / (out["draws"] // 2))
    assert not nc.passes("electrical_current:other")
    if coupling_nT_per_A:
        assert nc.passes("electrical_current:load") and nc.p_value < 0.01
    else:
        assert not nc.passes("electrical_current:load")


@pytest.mark.parametrize("coupling_nT_per_A", [0.0, 0.015])
def test_a_gain_confirmed_outside_the_calibration_need_only_reach_the_threshold(
    coupling_nT_per_A,
):
    """A weak coupling's held-out gain lies above the bootstrap's threshold but below the
    least gain worth a term: held back on the calibration alone, named once evidence outside
    it (the survey's crossovers, the switches) confirmed it; no coupling stays below the
    threshold, confirmed or not."""
    rng = np.random.default_rng(11)
    t, b, u, carrier = calibration(seed=11)
    current = telegraph(t, 8.0, rng)
    scalar = np.linalg.norm(b, axis=1) + carrier + ar1_noise(t.size, 0.02, 0.5, rng)
    scalar += coupling_nT_per_A * current * (u @ np.array([0.3, -0.5, 0.8]))
    sel = select_from(
        Measurements(t, scalar, b), np.ones(t.size, bool), BandSettings(), ALPHA, MIN_GAIN
    )
    key = "electrical_current:load"
    nc = calibrate_null(sel.setup, sel.columns, {key: current[:, None] * u}, 0.05, MIN_GAIN, 400, 0)
    assert not nc.passes(key), nc.to_dict()
    assert nc.passes(key, confirmed=True) == (coupling_nT_per_A > 0), nc.to_dict()


def cubic_interference(u: np.ndarray) -> np.ndarray:
    """Four unit-RMS columns cubic in the direction cosines: interference outside T-L's
    basis (its induced terms are quadratic), the stand-in for second-order physics."""
    c = (u - u.mean(0)) / u.std(0)
    out = np.column_stack([c[:, 0] ** 3, c[:, 0] * c[:, 1] * c[:, 2], c[:, 2] ** 2 * c[:, 1]])
    out = np.column_stack([out, c[:, 1] ** 3])
    return out / out.std(0)


@pytest.mark.parametrize("coupled", [False, True])
def test_a_candidate_is_judged_beside_the_rival_it_must_beat(coupled):
    """A channel that follows the manoeuvres (a motor's current) stands in for cubic
    interference the null model lacks: beside the null model alone it reaches the gate,
    beside its rival it gains nothing; a coupling of its own still reaches the gate."""
    rng = np.random.default_rng(21)
    t, b, u, carrier = calibration(seed=21)
    rival = cubic_interference(u)
    motor = rival[:, :3] + 0.05 * rng.normal(size=(t.size, 3))
    scalar = np.linalg.norm(b, axis=1) + carrier + rival @ np.array([0.3, 0.2, -0.2, 0.1])
    scalar += ar1_noise(t.size, 0.02, 0.3, rng)
    if coupled:
        scalar += 0.3 * (motor - rival[:, :3]) @ np.array([1.0, -0.5, 0.8])
    sel = select_from(
        Measurements(t, scalar, b), np.ones(t.size, bool), BandSettings(), ALPHA, MIN_GAIN
    )
    key = "electrical_current:motor"
    alone = calibrate_null(sel.setup, sel.columns, {key: motor}, 0.05, MIN_GAIN, 400, 0)
    beside = calibrate_null(
        sel.setup,
        sel.columns,
        {key: motor},
        0.05,
        MIN_GAIN,
        400,
        0,
        {key: "cubic"},
        {"cubic": rival},
    )
    assert alone.passes(key)
    assert beside.passes(key) == coupled, beside.to_dict()
    if not coupled:
        assert beside.observed_gain[key] < MIN_GAIN


def test_surrogates_keep_the_residuals_spectrum_and_lose_its_phase():
    rng = np.random.default_rng(2)
    r = ar1_noise(2000, 1.0, 0.8, rng)
    s = surrogates(r, [np.arange(2000)], 50, rng)
    x = np.arange(2000)
    trend = np.polyval(np.polyfit(x, r, 1), x)
    amp, got = np.abs(np.fft.rfft(r - trend)), np.abs(np.fft.rfft(s[:, 7] - trend))
    np.testing.assert_allclose(got[1:-1], amp[1:-1], rtol=1e-6, atol=1e-9)
    assert abs(np.corrcoef(r, s[:, 7])[0, 1]) < 0.2


def held(reduction: float, p: float) -> HeldOut:
    return HeldOut(1.0, 1.0 - reduction, p, 40)


def test_a_tie_between_a_lag_and_a_decay_names_nothing_unless_the_lines_time_it():
    tie = LagVersusDecay(held(0.01, 0.3), held(0.2, 1e-6), held(0.19, 1e-6), held(0.005, 0.4))
    assert tie.verdict(ALPHA, MIN_GAIN, "silent") == "ambiguous"
    assert tie.verdict(ALPHA, MIN_GAIN, "holds") == "lag"
    assert tie.verdict(ALPHA, MIN_GAIN, "excludes") == "none"
    amb = tie.ambiguity()
    assert amb["candidates"] == ["sensor_lag", "eddy_decay"]
    assert set(amb["heldout_gain"]) == {"sensor_lag", "eddy_decay"}
    # a lag that lowers held-out data beside the decay is a lag whatever the lines say
    beyond = LagVersusDecay(held(0.3, 1e-8), None, held(0.2, 1e-6), held(0.0, 0.6))
    assert beyond.verdict(ALPHA, MIN_GAIN, "silent") == "lag"
    # the decay adds to the lag: the decay is the cause, no lag
    decay = LagVersusDecay(held(0.01, 0.3), held(0.1, 1e-4), held(0.3, 1e-9), held(0.2, 1e-6))
    assert decay.verdict(ALPHA, MIN_GAIN, "holds") == "none"


def test_a_tie_goes_to_the_rival_that_predicts_held_out_data_better():
    """The lag model (the whole reading delayed) against the decay model (the decayed eddy
    columns beside T-L's): the winner by the held-out test is the explanation,
    whatever the timing along the lines; neither winning leaves the timing to decide."""
    args = (held(0.01, 0.3), held(0.2, 1e-6), held(0.19, 1e-6), held(0.005, 0.4))
    lag = LagVersusDecay(*args, lag_over_decay=held(0.3, 1e-8), decay_over_lag=held(-0.4, 1.0))
    assert lag.verdict(ALPHA, MIN_GAIN, "silent") == "lag"
    assert lag.verdict(ALPHA, MIN_GAIN, "excludes") == "lag"
    decay = LagVersusDecay(*args, lag_over_decay=held(-0.4, 1.0), decay_over_lag=held(0.3, 1e-8))
    assert decay.verdict(ALPHA, MIN_GAIN, "holds") == "none"
    even = LagVersusDecay(*args, lag_over_decay=held(0.01, 0.3), decay_over_lag=held(-0.01, 0.7))
    assert even.verdict(ALPHA, MIN_GAIN, "silent") == "ambiguous"
    assert even.verdict(ALPHA, MIN_GAIN, "holds") == "lag"
    assert set(even.to_dict()) >= {"lag_over_decay", "decay_over_lag"}


def test_the_calibration_and_the_lines_timing_join_to_break_a_tie():
    """Neither the calibration's comparison (p 0.03) nor the lines' timing alone is
    significant at 0.01; together (Fisher) they are. A calibration that leans to the
    decay (the lag model a little worse held out, p 0.6) is outweighed only by timing
    far beyond chance: a sensor filter and a decay of about its time constant are one
    response on the calibration, the lines are delayed by one of them only."""
    args = (held(0.01, 0.3), held(0.2, 1e-6), held(0.19, 1e-6), held(0.005, 0.4))
    vs = LagVersusDecay(*args, lag_over_decay=held(0.08, 0.03), decay_over_lag=held(-0.1, 0.9))
    late = TimingLag(0.2, (0.05, 0.35), 0.01, 5)  # 2.6 standard errors late
    assert vs.verdict(ALPHA, MIN_GAIN, "silent", timing_p_late(late, None)) == "lag"
    early = TimingLag(-0.2, (-0.35, -0.05), 0.01, 5)
    assert vs.verdict(ALPHA, MIN_GAIN, "silent", timing_p_late(early, None)) == "ambiguous"
    worse = LagVersusDecay(*args, lag_over_decay=held(-0.02, 0.6), decay_over_lag=held(0.02, 0.4))
    assert worse.verdict(ALPHA, MIN_GAIN, "silent", timing_p_late(late, None)) == "ambiguous"
    sure = TimingLag(0.024, (0.0205, 0.0275), 1e-5, 20)  # 13 standard errors late
    assert worse.verdict(ALPHA, MIN_GAIN, "silent", timing_p_late(sure, None)) == "lag"
    against = LagVersusDecay(
        *args, lag_over_decay=held(-0.02, 0.999), decay_over_lag=held(0.02, 0.4)
    )
    assert against.verdict(ALPHA, MIN_GAIN, "silent", timing_p_late(late, None)) == "ambiguous"


def test_joining_the_evidence_names_a_decay_a_lag_at_most_at_alpha():
    """The decay true, no lag: the calibration's comparison p uniform (its gain always
    large enough, the worst case) and the two timing estimates unbiased with their own
    errors; the share of ties named a lag stays within alpha (3 binomial errors)."""
    rng = np.random.default_rng(11)
    draws, named = 4000, 0
    args = (held(0.01, 0.3), held(0.2, 1e-6), held(0.19, 1e-6), held(0.005, 0.4))
    for _ in range(draws):
        se_a, se_b = rng.uniform(0.02, 0.2, 2)
        a, b = rng.normal(0, se_a), rng.normal(0, se_b)
        sl = TimingLag(a, (a - 1.96 * se_a, a + 1.96 * se_a), 1.0, 5)
        tl = TimingLag(b, (b - 1.96 * se_b, b + 1.96 * se_b), 1.0, 5)
        vs = LagVersusDecay(
            *args, lag_over_decay=held(0.1, rng.uniform()), decay_over_lag=held(-0.1, 0.9)
        )
        named += vs.verdict(ALPHA, MIN_GAIN, "silent", timing_p_late(sl, tl)) == "lag"
    assert named / draws <= ALPHA + 3 * np.sqrt(ALPHA * (1 - ALPHA) / draws)


def test_a_small_lag_beside_a_needed_decay_is_named_on_the_lines_timing():
    """Both physics there: the lag lowers held-out data beside the decay (p 1e-6, but by
    under min_gain), or the decay took all of it and the lag alone explains the residual,
    and the decay adds beside the lag. The calibration's share does not decide; the lines'
    timing does, and with no lag it names one at most at alpha."""
    args = (held(0.03, 1e-6), held(0.7, 1e-9), held(0.75, 1e-9), held(0.12, 1e-6))
    both = LagVersusDecay(*args)
    late = TimingLag(0.085, (0.05, 0.12), 0.001, 5)
    assert both.verdict(ALPHA, MIN_GAIN, "holds", timing_p_late(late, None)) == "lag_beside_decay"
    unsure = TimingLag(0.03, (-0.03, 0.09), 0.3, 5)
    assert both.verdict(ALPHA, MIN_GAIN, "silent", timing_p_late(unsure, None)) == "none"
    assert both.verdict(ALPHA, MIN_GAIN, "silent", None) == "none"
    # the decay took the whole of the lag's residual (the lag beside it p above alpha) but
    # the lag alone explains it: the lines decide
    absorbed = LagVersusDecay(held(0.03, 0.2), *args[1:])
    assert absorbed.verdict(ALPHA, MIN_GAIN, "holds", timing_p_late(late, None)) == (
        "lag_beside_decay"
    )
    assert absorbed.verdict(ALPHA, MIN_GAIN, "silent", timing_p_late(unsure, None)) == "none"
    # no lag-like residual in the calibration at all: however late the lines, no lag
    flat = LagVersusDecay(held(0.03, 0.2), held(0.01, 0.4), *args[2:])
    assert flat.verdict(ALPHA, MIN_GAIN, "holds", timing_p_late(late, None)) == "none"
    rng = np.random.default_rng(12)
    draws, named = 4000, {"both": 0, "absorbed": 0}
    for _ in range(draws):
        se_a, se_b = rng.uniform(0.02, 0.2, 2)
        a, b = rng.normal(0, se_a), rng.normal(0, se_b)
        sl = TimingLag(a, (a - 1.96 * se_a, a + 1.96 * se_a), 1.0, 5)
        tl = TimingLag(b, (b - 1.96 * se_b, b + 1.96 * se_b), 1.0, 5)
        for name, vs in (("both", both), ("absorbed", absorbed)):
            named[name] += vs.verdict(ALPHA, MIN_GAIN, "silent", timing_p_late(sl, tl)) != "none"
    for n in named.values():
        assert n / draws <= ALPHA + 3 * np.sqrt(ALPHA * (1 - ALPHA) / draws)


def test_a_lag_named_beside_a_slower_decay_must_be_resolvable():
    """Beside a slower decay the lag named is the one beside it, not the whole reading's
    delay without the decay; a few milliseconds there is the resampling's error (L9),
    whatever the delay without the decay read."""
    for lag_s, held_back in ((0.0033, True), (-0.004, True), (0.05, False)):
        ev = Evaluation("sensor_lag", "sensor_lag", {"lag_s": lag_s}, None, None, None)
        _unresolved(ev, 0.02)
        assert ev.held_back is held_back
        assert ("min_lag_s" in ev.reason) is held_back


@pytest.fixture(scope="session")
def audited(tmp_path_factory):
    """``aeromag audit`` on a shared recording, once per session: name -> (AUDIT.json,
    truth)."""
    from tests.cli import run

    done: dict[str, tuple[dict, dict]] = {}

    def get(name: str) -> tuple[dict, dict]:
        if name not in done:
            src = RECORDINGS / f"{name}.mcap"
            if not src.exists():
                pytest.skip(f"{src} not present")
            tmp = tmp_path_factory.mktemp(name)
            out = tmp / "a.json"
            ran = run("audit", str(src), "--json", str(out), "--report", str(tmp / "rep"))
            assert ran.returncode == 0, ran.stderr
            truth = json.loads((RECORDINGS / f"{name}.truth.json").read_text())
            done[name] = (json.loads(out.read_text()), truth)
        return done[name]

    return get


def decay_tau_error(res: dict, truth: dict) -> float | None:
    """|log(estimated / true)| of the null model's eddy-decay time constant (None: no decay)."""
    tau = truth["sensors"]["scalar"]["realism"]["eddy_time_constant_s"]
    nz = {n["name"]: n for n in res["unexplained"]["nuisances"]}
    if "eddy_decay" not in nz:
        return None
    return float(abs(np.log(nz["eddy_decay"]["estimate"]["tau_s"] / tau)))


@pytest.mark.slow
@pytest.mark.parametrize("name", ["realism_none", "realism_geomagnetic_gradient"])
def test_eddy_decay_is_no_late_sensor_on_independent_flights(name, audited):
    res, truth = audited(name)
    named = {f["effect"] for f in res["findings"]}
    assert "sensor_lag" not in named
    # alone the decay must stay; beside a finding it may be dropped (it lowers nothing more)
    if name == "realism_none":
        assert decay_tau_error(res, truth) is not None
    for a in res["unexplained"]["ambiguities"]:
        assert {"candidates", "heldout_gain"} <= set(a)
    assert res["null_calibration"]["draws"] >= 200


NEAR_TIE = pytest.mark.xfail(
    strict=True,
    reason="the held-out grid's time constants near-tie beside a gradient (docs/audit.md, Limits)",
)


@pytest.mark.slow
@pytest.mark.parametrize(
    "name", ["realism_none", pytest.param("realism_geomagnetic_gradient", marks=NEAR_TIE)]
)
def test_the_null_models_decay_time_constant_within_30_percent(name, audited):
    err = decay_tau_error(*audited(name))
    assert err is None or err < np.log(1.3)


@pytest.mark.slow
def test_a_late_sensor_beside_decaying_eddy_currents_is_named(audited):
    res, truth = audited("realism_sensor_lag")
    lags = [f for f in res["findings"] if f["effect"] == "sensor_lag"]
    assert lags, res["unexplained"]
    lo, hi = lags[0]["estimate_ci95"]["lag_s"]
    # the named lag carries its own sampling error: it never sits on the interval's end
    assert lo < lags[0]["estimate"]["lag_s"] < hi


@pytest.mark.slow
@pytest.mark.xfail(
    strict=True,
    reason="a lag read beside eddy decay runs long, a bias every manoeuvre shares "
    "(docs/audit.md, Limits)",
)
def test_a_late_sensor_beside_decaying_eddy_currents_has_an_interval_that_holds_it(audited):
    res, truth = audited("realism_sensor_lag")
    lag = [f for f in res["findings"] if f["effect"] == "sensor_lag"][0]
    lo, hi = lag["estimate_ci95"]["lag_s"]
    assert lo <= truth["effect_params"]["lag_s"] <= hi


@pytest.mark.slow
@pytest.mark.xfail(
    strict=True, reason="a lag read beside eddy decay runs long (docs/audit.md, Results)"
)
def test_a_late_sensor_beside_decaying_eddy_currents_is_read_within_60_ms(audited):
    res, truth = audited("realism_sensor_lag")
    lag = [f for f in res["findings"] if f["effect"] == "sensor_lag"][0]["estimate"]["lag_s"]
    assert abs(lag - truth["effect_params"]["lag_s"]) < 0.06


@pytest.mark.parametrize("step_nT", [0.0, 3.0])
def test_a_change_between_passes_must_reach_the_selections_gate(step_nT):
    """A change of the permanent field between the calibration's halves (the pass-step
    candidate: direction cosines after the gap) is judged by the same null maximum as the
    findings: over interference the null model lacks (cubic in the direction cosines), no
    change reaches the gate; a 3 nT change does."""
    rng = np.random.default_rng(31)
    t, b, u, carrier = calibration(seed=31)
    scalar = np.linalg.norm(b, axis=1) + carrier
    scalar += cubic_interference(u) @ np.array([0.3, 0.2, -0.2, 0.1])
    scalar += ar1_noise(t.size, 0.02, 0.3, rng)
    after = (t > np.median(t)).astype(float)[:, None]
    scalar += step_nT * (u * after) @ np.array([0.6, -0.48, 0.64])
    sel = select_from(
        Measurements(t, scalar, b), np.ones(t.size, bool), BandSettings(), ALPHA, MIN_GAIN
    )
    key = "pass_step:0"
    nc = calibrate_null(sel.setup, sel.columns, {key: u * after}, 0.05, MIN_GAIN, 400, 0)
    assert nc.passes(key) == (step_nT > 0), nc.to_dict()


def test_the_monte_carlo_threshold_holds_its_level_for_few_draws():
    """A new null draw reaches the threshold set on 39 draws at most alpha of the time
    (exactly (n + 1 - k) / (n + 1) for continuous draws); the plain quantile's rate is
    above alpha at that size."""
    rng = np.random.default_rng(3)
    sets, new = rng.uniform(size=(40_000, 39)), rng.uniform(size=40_000)
    alpha = 0.05
    ours = np.array([monte_carlo_threshold(s, alpha) for s in sets])
    plain = np.quantile(sets, 1.0 - alpha, axis=1)
    se = np.sqrt(alpha * (1 - alpha) / new.size)
    assert np.mean(new >= ours) <= alpha + 2 * se
    assert np.mean(new >= plain) > alpha + 3 * se


def _every_other_sample(src, dst) -> None:
    """``src`` at half its rate: every other message of each channel but the base station's
    (the recording's sensors sampled at 5 Hz; schemas, channels and payloads as they were)."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    with open(src, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        messages = list(reader.iter_messages(log_time_order=True))
    with open(dst, "wb") as f:
        w = Writer(f)
        w.start()
        sid = {k: w.register_schema(s.name, s.encoding, s.data) for k, s in summary.schemas.items()}
        cid = {
            k: w.register_channel(c.topic, c.message_encoding, sid[c.schema_id], c.metadata)
            for k, c in summary.channels.items()
        }
        seen: dict[int, int] = {}
        for _s, c, m in messages:
            k = seen[c.id] = seen.get(c.id, -1) + 1
            if c.topic == "/base/scalar" or k % 2 == 0:
                w.add_message(cid[c.id], log_time=m.log_time, data=m.data, publish_time=m.log_time)
        w.finish()


@pytest.mark.slow
def test_no_late_sensor_is_named_for_decaying_eddy_currents_at_5_hz(tmp_path):
    # at 5 Hz the null model does not take the decay, and a lag ties with it on the
    # calibration while the lines' timing does not hold the lag: an ambiguity (L10)
    from tests.cli import run

    src = RECORDINGS / "realism_none.mcap"
    if not src.exists():
        pytest.skip(f"{src} not present")
    half = tmp_path / "realism_none_5hz.mcap"
    _every_other_sample(src, half)
    out = tmp_path / "a.json"
    ran = run("audit", str(half), "--json", str(out), "--report", str(tmp_path / "rep"))
    assert ran.returncode == 0, ran.stderr
    res = json.loads(out.read_text())
    assert not res["findings"]
    assert any("sensor_lag" in a["candidates"] for a in res["unexplained"]["ambiguities"])
