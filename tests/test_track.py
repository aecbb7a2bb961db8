"""The GNSS track smoother (pipeline.geo.track) against analytic tracks with known noise."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.geo.track import smooth_track


def _track(t: np.ndarray) -> np.ndarray:
    """East/north/up (m) of a flight that turns and climbs: smooth at the receiver's rate."""
    return np.column_stack(
        [60.0 * t + 400.0 * np.sin(t / 20.0), 300.0 * np.cos(t / 45.0), 1500 + 20 * np.sin(t / 7)]
    )


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_white_receiver_noise_is_removed(seed):
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 1200.0, 0.2)
    sigma = np.array([0.5, 0.5, 1.0])
    y = _track(t) + rng.normal(0.0, 1.0, (t.size, 3)) * sigma
    at = np.arange(1.0, 1199.0, 0.1) + 0.03  # another sensor's epochs, not the receiver's
    err = smooth_track(t, y, at) - _track(at)
    rms = np.sqrt(np.mean(err**2, axis=0))
    # a spline through noise of this size on this track leaves a fifth of it or less
    assert np.all(rms < 0.3 * sigma), rms
    # and does not bend the turns: no bias along the track
    assert np.all(np.abs(err.mean(axis=0)) < 0.05 * sigma)


def test_quiet_receiver_is_left_as_it_is():
    rng = np.random.default_rng(4)
    t = np.arange(0.0, 600.0, 0.1)
    y = _track(t) + rng.normal(0.0, 0.01, (t.size, 3))
    at = t[10:-10:3] + 0.05
    err = smooth_track(t, y, at) - _track(at)
    # centimetre noise: the smoothing follows the track to within the noise itself
    assert np.sqrt(np.mean(err**2)) < 0.01


def test_outage_is_not_bridged():
    t = np.concatenate([np.arange(0.0, 100.0, 0.2), np.arange(130.0, 250.0, 0.2)])
    y = _track(t)
    at = np.array([50.0, 115.0, 200.0, 260.0])
    out = smooth_track(t, y, at)
    assert np.all(np.isfinite(out[[0, 2]]))
    assert np.all(np.isnan(out[[1, 3]]))
    assert np.allclose(out[[0, 2]], _track(at[[0, 2]]), atol=0.01)


def _box_track(t: np.ndarray) -> np.ndarray:
    """A calibration box: 90 s straight legs at 7 m/s joined by 35 m radius turns, with a
    pitch block's 0.5 m, 5 s altitude wiggle on each leg (east/north/up, m)."""
    dt = 0.01
    tf = np.arange(0.0, t[-1] + 1.0, dt)
    phase = np.mod(tf, 98.0)
    rate = np.where(phase >= 90.0, np.deg2rad(90.0) / 8.0, 0.0)  # 7 m/s / 35 m ≈ 0.2 rad/s
    heading = np.cumsum(rate) * dt
    east = np.cumsum(7.0 * np.sin(heading)) * dt
    north = np.cumsum(7.0 * np.cos(heading)) * dt
    wiggle = 0.5 * np.sin(2 * np.pi * (phase - 30.0) / 5.0)  # six whole periods
    up = 100.0 + np.where((phase > 30) & (phase < 60), wiggle, 0.0)
    return np.column_stack([np.interp(t, tf, c) for c in (east, north, up)])


def test_turns_and_manoeuvres_are_followed():
    # straight legs alone would ask for a straight line: the turns and the altitude wiggle
    # must survive the smoothing the legs would choose
    rng = np.random.default_rng(5)
    t = np.arange(0.0, 400.0, 0.1)
    truth = _box_track(t)
    y = truth + rng.normal(0.0, 0.02, truth.shape)
    at = t[20:-20] + 0.05
    err = smooth_track(t, y, at) - _box_track(at)
    assert np.max(np.sqrt(np.mean(err**2, axis=0))) < 0.02
    assert np.max(np.abs(err)) < 0.1


@pytest.mark.parametrize("lam", [1e-4, 1e-1, 10.0, 1e3])
def test_smoothing_spline_is_scipys_minimiser(lam):
    """The Reinsch-form spline equals scipy's make_smoothing_spline (same objective) at
    knots and between them, on uneven sampling."""
    from scipy.interpolate import make_smoothing_spline

    from pipeline.geo.track import smoothing_spline

    rng = np.random.default_rng(7)
    x = np.cumsum(rng.uniform(0.05, 0.15, 400))
    y = 30.0 * np.sin(x / 3.0) + rng.normal(0.0, 0.5, x.size)
    at = np.sort(np.r_[x[::7], rng.uniform(x[0], x[-1], 500)])
    want = make_smoothing_spline(x, y, lam=lam)(at)
    got = smoothing_spline(x, y, lam)(at)
    assert np.max(np.abs(got - want)) < 1e-6 * np.ptp(y)


def test_smoothing_spline_refuses_repeated_abscissae():
    from pipeline.geo.track import smoothing_spline

    with pytest.raises(ValueError, match="strictly increasing"):
        smoothing_spline(np.array([0.0, 1.0, 1.0, 2.0, 3.0, 4.0]), np.zeros(6), 1.0)
