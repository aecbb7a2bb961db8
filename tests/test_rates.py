"""Nothing counted in samples: the settings that stand for a time are in seconds, and the
same physical record sampled at 5, 10, 25 and 50 Hz is treated the same (issue 35, item 5).

At 10 Hz every setting keeps the sample count it had when it was one: the despike window 101
samples, the band-pass trim 20 samples, the smallest lag named 0.2 of a sample, the fuzzy-R
window 30 steps.
"""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.audit import AuditSettings
from pipeline.audit.extended import BandSettings
from pipeline.compensate import FitSettings
from pipeline.compensate.estimator import bandpassed_design
from pipeline.compensate.fit import fit_compensation
from pipeline.compensate.model import Measurements
from pipeline.config import Config
from pipeline.despike import DespikeSettings, despike
from pipeline.errors import AeromagError

RATES_HZ = (5.0, 10.0, 25.0, 50.0)
NOISE_NT = 0.05
# spike times on every rate's sample grid (multiples of 0.2 s) and their sizes (nT)
SPIKES = [(31.0, 2.0), (77.4, -1.5), (122.2, 3.0), (180.0, -2.5), (240.6, 1.2), (281.8, 2.2)]
SPIKES += [(321.0, -1.8), (355.2, 1.6), (410.4, -3.0), (466.0, 2.7), (521.8, -1.3)]


def physical_record(rate_hz: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Ten minutes of the same field at ``rate_hz``: geology flown at 30 m/s (anomalies
    150-600 m wide, up to 60 nT), manoeuvre interference at 0.08-0.3 Hz (up to 8 nT), a 2 nT
    current step at 300 s, white sensor noise of NOISE_NT and the spikes of SPIKES (nT). Its
    fastest signal is resolved at 5 Hz too: what differs between the rates is the sampling."""
    t = np.arange(int(round(600.0 * rate_hz))) / rate_hz
    s = 30.0 * t
    geo = np.zeros(t.size)
    for c, w, a in ((1500.0, 150.0, 60.0), (5200.0, 600.0, -40.0), (12000.0, 250.0, 25.0)):
        geo += a / (1 + ((s - c) / w) ** 2) ** 1.5
    man = sum(
        a * np.sin(2 * np.pi * f * t + ph)
        for f, a, ph in ((0.08, 8.0, 0.3), (0.2, 5.0, 1.1), (0.3, 2.0, 2.0))
    )
    x = 50_000 + geo + man + np.where(t >= 300.1, 2.0, 0.0)
    x += np.random.default_rng(seed).normal(0.0, NOISE_NT, t.size)
    for at, a in SPIKES:
        x[int(round(at * rate_hz))] += a
    return t, x


@pytest.mark.parametrize("rate_hz", RATES_HZ)
def test_despike_finds_the_same_spikes_over_the_same_window_at_every_rate(rate_hz):
    t, x = physical_record(rate_hz)
    r = despike(x, t)
    np.testing.assert_allclose(t[r.spike_index], [at for at, _ in SPIKES], atol=1e-9)
    np.testing.assert_allclose(r.amplitude_nT, [a for _, a in SPIKES], atol=6 * NOISE_NT)
    assert r.steps >= 1  # the current step is signal: left alone
    # the running window spans window_s (odd samples: within one sample interval)
    span_s = r.window_samples / rate_hz
    assert abs(span_s - DespikeSettings().window_s) <= 1.0 / rate_hz
    assert r.summary()["window_s"] == DespikeSettings().window_s
    if rate_hz == 10.0:
        assert r.window_samples == 101  # the former default, unchanged at 10 Hz


def _calibration(rate_hz: float, seconds: float = 300.0) -> Measurements:
    """A carrier swinging in attitude in a 50 000 nT field: a tl16 interference of a few nT."""
    t = np.arange(int(round(seconds * rate_hz))) / rate_hz
    yaw = 2 * np.pi * t / 120.0
    roll = np.deg2rad(10.0) * np.sin(2 * np.pi * t / 6.0)
    pitch = np.deg2rad(5.0) * np.sin(2 * np.pi * t / 5.0)
    u = np.column_stack(
        [np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(roll), 0.8 + 0.2 * np.sin(pitch)]
    )
    u /= np.linalg.norm(u, axis=1)[:, None]
    b = 50_000.0 * u
    y = 50_000.0 + 3.0 * u[:, 0] - 2.0 * u[:, 1] + 1.5 * u[:, 2]
    y += np.random.default_rng(1).normal(0.0, NOISE_NT, t.size)
    return Measurements(t, y, b)


@pytest.mark.parametrize("rate_hz", RATES_HZ)
def test_compensation_trims_the_same_seconds_at_every_rate(rate_hz):
    meas = _calibration(rate_hz)
    s = FitSettings(model="tl16")
    assert s.trim_s == 2.0
    n = meas.time_s.size
    k = np.column_stack([meas.vector_nT, np.ones(n)])
    _, _, where = bandpassed_design(
        k, meas.scalar_nT, meas.time_s, rate_hz, np.ones(n, bool), s.band_hz, s.poles, s.trim_s
    )
    # the first and last kept rows are 2 s inside the block, at every rate
    assert meas.time_s[where[0]] == pytest.approx(2.0, abs=0.5 / rate_hz)
    assert meas.time_s[-1] - meas.time_s[where[-1]] == pytest.approx(2.0, abs=0.5 / rate_hz)
    model = fit_compensation(meas, np.ones(n, bool), s).to_dict()
    trim = int(round(2.0 * rate_hz))
    assert (model["trim"], model["trim_s"], model["samples"]) == (trim, 2.0, n - 2 * trim)
    if rate_hz == 10.0:
        assert trim == 20  # the former default, unchanged at 10 Hz
    # the audit's band trims the same seconds
    assert BandSettings().trim_at(rate_hz) == trim


def test_the_audit_lag_resolution_is_in_seconds():
    """0.02 s: 0.2 of a sample at 10 Hz (the former setting), one sample at 50 Hz."""
    a = Config.load().audit_settings()
    assert a.min_lag_s == AuditSettings().min_lag_s == 0.02
    assert not hasattr(a, "min_lag_samples")
    assert a.band.trim_s == Config.load()["compensation"]["trim_s"]


@pytest.mark.parametrize(
    ("key", "new"),
    [
        ("compensation.trim", "compensation.trim_s"),
        ("despike.window_samples", "despike.window_s"),
        ("vector.fuzzy_window", "vector.fuzzy_window_s"),
    ],
)
def test_an_old_sample_count_is_a_one_line_error_naming_its_replacement(tmp_path, key, new):
    section, name = key.split(".")
    f = tmp_path / "old.toml"
    f.write_text(f"[{section}]\n{name} = 20\n")
    with pytest.raises(AeromagError) as exc:
        Config.load(f)
    text = str(exc.value)
    assert "\n" not in text and str(f) in text
    assert f"{key} (samples) was replaced by {new} (seconds" in text


@pytest.mark.slow
@pytest.mark.parametrize("rate_hz", [5.0, 25.0, 50.0])
def test_the_audit_names_a_sensor_lag_at_other_rates(rate_hz, tmp_path):
    """A short simulated flight (two calibration boxes over quiet ground, nothing hidden but
    a late scalar sensor) sampled at 5, 25 and 50 Hz: the lag is named alone, at its size."""
    from pipeline.audit import run_audit
    from pipeline.io.reader import read_flight
    from pipeline.segment import segment_flight
    from pipeline.simulate import write_simulation
    from tests.conftest import run_sim

    fast = max(20.0, rate_hz)
    sim = run_sim(
        "uav-small",
        3,
        [
            "calibration.passes=2",
            "anomaly.quiet_calibration_m=400.0",
            "effects.sensor_lag.enabled=true",
            f"sensors.scalar_rate_hz={rate_hz:g}",
            f"sensors.vector_rate_hz={fast:g}",
            f"sensors.attitude_rate_hz={fast:g}",
            f"flight.master_rate_hz={max(50.0, rate_hz):g}",
        ],
    )
    flight = read_flight(write_simulation(sim, tmp_path / "f.mcap"))
    res = run_audit(flight, segment_flight(flight))
    named = {f.effect: f.estimate for f in res.findings}
    assert set(named) == {"sensor_lag"}, res.to_json()["rounds"]
    truth = sim.truth["effective"]["sensor_lag_s"]
    assert named["sensor_lag"]["lag_s"] == pytest.approx(truth, abs=0.01)


@pytest.mark.parametrize("rate_hz", RATES_HZ)
def test_the_fuzzy_r_window_is_the_same_seconds_at_every_rate(rate_hz):
    from pipeline.vector.component import ComponentKF

    kf = ComponentKF.paper(scaled=True, fuzzy=True).configure(Config.load()["vector"])
    kf.sample_s = 1.0 / rate_hz
    assert kf.window_steps() == round(3.0 * rate_hz)  # 30 steps at 10 Hz, as before
    with pytest.raises(ValueError, match="sample interval"):
        ComponentKF.paper(fuzzy=True).window_steps()
