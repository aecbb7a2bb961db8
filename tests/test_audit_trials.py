"""The audit trials' measure of a hidden effect's size: what it does to the survey left
uncompensated (``pipeline.simulate.audit_trials.survey_error_nT``), against analytic cases."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from pipeline.simulate.audit_trials import hidden_overrides, survey_error_nT


def _sim(effects: dict, t: np.ndarray, earth: np.ndarray, streams: dict | None = None):
    start_ns = 1_700_000_000_000_000_000
    return SimpleNamespace(
        start_ns=start_ns,
        series={"time_ns": start_ns + np.round(t * 1e9).astype(np.int64), "earth_total_nT": earth},
        truth={
            "segments": [
                {"label": "calibration", "start_s": 0.0, "end_s": 100.0},
                {"label": "survey", "start_s": 100.0, "end_s": 400.0},
            ]
        },
        scenario=SimpleNamespace(effect=lambda name: effects.get(name)),
        streams=streams or {},
    )


def test_a_lag_reads_the_field_late_by_tau_times_its_rate():
    """B = A sin(w t) along the lines: a lag tau errs by tau A w cos(w t), RMS
    tau A w / sqrt(2); the calibration's stretch does not count."""
    t = np.arange(0.0, 400.0, 0.1)
    a, w, tau = 5.0, 2 * np.pi / 20.0, 0.1
    # manoeuvre-fast changes on the calibration, fading to nothing where the survey starts
    fade = np.clip((100.0 - t) / 100.0, 0.0, None) ** 2
    earth = 50_000 + a * np.sin(w * t) + 30 * np.sin(3 * t) * fade
    sim = _sim({"sensor_lag": {"lag_s": tau}}, t, earth)
    got = survey_error_nT("sensor_lag", sim)
    np.testing.assert_allclose(got, tau * a * w / np.sqrt(2), rtol=0.01)
    assert survey_error_nT("diurnal", sim) is None


def test_a_current_adds_its_coupling_along_the_field_less_its_mean():
    """Field along body z (u = z), coupling 2 nT/A along z, a current switching 0/1 A
    with a duty cycle of one half: the survey error is 2 x 0.5 = 1 nT RMS."""
    t = np.arange(0.0, 400.0, 0.1)
    current = (np.floor(t / 10.0) % 2).astype(float)
    streams = {
        "/aux/payload_current": {"t": t, "cols": {"value": current}},
        "/mag/vector": {
            "t": t,
            "cols": {"x_nT": 0 * t, "y_nT": 0 * t, "z_nT": 50_000 + 0 * t},
        },
    }
    cur = {"channel": "payload_current", "coupling_nT_per_A": 2.0, "direction_body": [0, 0, 3]}
    sim = _sim({"electrical_current": cur}, t, 50_000 + 0 * t, streams)
    np.testing.assert_allclose(survey_error_nT("electrical_current", sim), 1.0, rtol=0.01)


def test_sizes_are_drawn_after_the_forms_so_fixed_size_flights_do_not_change():
    a = hidden_overrides("sensor_lag", np.random.default_rng(3))
    b = hidden_overrides("sensor_lag", np.random.default_rng(3), sizes=True)
    assert b[: len(a)] == a and b[-1].startswith("effects.sensor_lag.lag_s=")
    lag = float(b[-1].split("=")[1])
    assert 0.02 <= lag <= 0.3
