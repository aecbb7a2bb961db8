"""The audit's calibration designs built on the calibration's neighbourhood equal the whole
flight's, and its nested test does not let rounding choose a design's rank."""

from __future__ import annotations

import numpy as np

from pipeline.audit.evidence import nested_test
from pipeline.audit.extended import (
    AuditData,
    BandSettings,
    ModelSpec,
    bandpassed_rows,
    calibration_rows,
    design,
    lag_cost,
)
from pipeline.compensate.heldout import calibration_window
from tests.manoeuvres import manoeuvres


def _flight(seed: int = 3):
    """Three passes of the manoeuvres with a long straight stretch between them (the survey):
    only the first and the last pass are calibration."""
    rng = np.random.default_rng(seed)
    t1, b1 = manoeuvres()
    n = t1.size
    straight = np.tile(b1[-1], (6 * n, 1)) + rng.normal(0.0, 5.0, (6 * n, 3)).cumsum(axis=0) * 0.01
    b = np.vstack([b1, straight, b1[::-1], straight[::-1], b1])
    t = np.arange(b.shape[0]) / 10.0
    lag_field = np.linalg.norm(b, axis=1)
    scalar = np.interp(t - 0.15, t, lag_field) + rng.normal(0.0, 0.05, t.size)
    mask = np.zeros(t.size, bool)
    mask[:n] = True
    mask[-n:] = True
    enu = np.column_stack([np.cos(t / 100.0) * 500.0, t * 3.0, 100.0 + np.sin(t / 30.0)])
    aux = {"cur": np.sign(np.sin(t / 7.0))}
    return AuditData(t, scalar, b, enu, aux, {"cur": "A"}), mask


SPEC = ModelSpec(
    eddy_tau_s=0.8, second_order=True, lag_s=0.2, gradient=True, aux=("cur",), eddy_rate=True
)


def test_the_window_holds_the_calibration_and_its_neighbourhood_only():
    data, mask = _flight()
    idx = calibration_window(data.time_s, mask, 30.0)
    assert np.all(np.isin(np.flatnonzero(mask), idx))
    near = np.min(np.abs(data.time_s[idx][:, None] - data.time_s[mask][None, ::50]), axis=1)
    assert near.max() <= 30.0 + 5.0  # every kept epoch is near the calibration (s)
    assert idx.size < 0.5 * data.time_s.size  # the survey between the passes is left out


def test_calibration_rows_equal_the_whole_flights():
    data, mask = _flight()
    bs = BandSettings()
    got = calibration_rows(data, SPEC, mask, bs)
    des = design(data, SPEC)  # every epoch of the flight, as before the window
    kf, yf, where = bandpassed_rows(data, des, mask, bs)
    assert np.array_equal(got.where, where)
    # rounding only: the sample rate read from fewer intervals differs in the last digits
    scale = np.sqrt(np.mean(kf**2, axis=0))
    assert np.max(np.abs(got.kf - kf) / scale) < 1e-7
    assert np.max(np.abs(got.yf - yf)) < 1e-7 * np.std(yf)
    # a window shorter than the decay's memory would not do: the comparison can tell
    sub, sub_mask, idx = data.calibration_part(mask, pad_s=1.0)
    short = design(sub, SPEC)
    k_short, _, w_short = bandpassed_rows(sub, short, sub_mask, bs)
    assert np.array_equal(idx[w_short], where)
    assert np.max(np.abs(k_short - kf) / scale) > 1e-6


def test_the_lag_costs_equal_the_whole_flights():
    data, mask = _flight()
    bs = BandSettings()
    taus = np.array([-0.3, 0.0, 0.15, 0.4])
    spec = SPEC.with_(lag_s=0.0)
    got = lag_cost(data, spec, mask, bs, 1e-3, 1.0)(taus)
    # the same costs when the window is the whole flight (a pad longer than the flight)
    far = AuditData.calibration_part
    try:
        AuditData.calibration_part = lambda self, m, pad_s=0.0: (self, m, np.arange(m.size))
        want = lag_cost(data, spec, mask, bs, 1e-3, 1.0)(taus)
    finally:
        AuditData.calibration_part = far
    assert np.allclose(got, want, rtol=1e-9)
    assert np.all(np.isfinite(got))


def test_a_lag_twins_rows_reuse_its_columns_and_equal_a_fresh_build():
    """The rows of a model at another lag, built from its twin's band-passed columns, are
    the rows built afresh; so are the lag costs from them; and a twin whose record is finite
    on other epochs (the flight's start cut) is not reused."""
    data, mask = _flight()
    # the calibration 5 s from the flight's ends: a lag cannot empty its epochs
    mask &= (data.time_s > 5.0) & (data.time_s < data.time_s[-1] - 5.0)
    bs = BandSettings()
    twin = calibration_rows(data, SPEC.with_(lag_s=0.0), mask, bs)
    for lag in (0.2, -0.35):
        spec = SPEC.with_(lag_s=lag)
        fresh = calibration_rows(data, spec, mask, bs)
        reused = calibration_rows(data, spec, mask, bs, like=twin)
        assert reused.kf is twin.kf  # not rebuilt
        assert np.array_equal(reused.where, fresh.where)
        assert np.array_equal(reused.kf, fresh.kf)
        assert np.allclose(reused.yf, fresh.yf, rtol=0, atol=1e-12 * np.std(fresh.yf))
        assert not np.allclose(reused.yf, twin.yf)  # the record moved with the lag
    taus = np.array([-0.3, 0.0, 0.15, 0.4])
    want = lag_cost(data, SPEC.with_(lag_s=0.0), mask, bs, 1e-3, 1.0)(taus)
    got = lag_cost(data, SPEC.with_(lag_s=0.0), mask, bs, 1e-3, 1.0, like=twin)(taus)
    assert np.allclose(got, want, rtol=1e-12)
    # the calibration's first epochs with no scalar: the twin's blocks are not these
    cut = AuditData(
        data.time_s,
        np.where(data.time_s < 7.0, np.nan, data.scalar_nT),
        data.vector_nT,
        data.enu_m,
        data.aux,
        data.aux_units,
    )
    fresh = calibration_rows(cut, SPEC, mask, bs)
    reused = calibration_rows(cut, SPEC, mask, bs, like=twin)
    assert reused.kf is not twin.kf and np.array_equal(reused.where, fresh.where)


def test_the_nested_test_does_not_let_rounding_set_the_rank():
    rng = np.random.default_rng(7)
    n = 2000
    x = rng.normal(size=(n, 4))
    # a column within 1e-12 of another: what a 0.02 s decay is beside T-L's eddy columns
    near = x[:, :1] + 1e-12 * rng.normal(size=(n, 1))
    base = np.column_stack([x, near])
    extra = rng.normal(size=(n, 1))
    y = x @ np.array([1.0, -2.0, 0.5, 3.0]) + 0.1 * extra[:, 0] + rng.normal(size=n)
    results = []
    for _ in range(5):
        jitter = 1.0 + 1e-13 * rng.normal(size=base.shape)  # rounding-sized changes
        b = base * jitter
        results.append(nested_test(y, b, np.column_stack([b, extra]), 1))
    assert {r.df for r in results} == {1}
    f = np.array([r.f for r in results])
    assert np.ptp(f) < 1e-6 * f.mean()
    assert all(r.p_value < 0.01 for r in results)  # the extra column is there to be found
