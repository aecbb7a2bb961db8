"""The scalar's delay against the fluxgate along lines (pipeline.audit.timing): analytic cases."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter1d

from pipeline.audit.timing import timing_lag

RATE_HZ = 10.0


def _lines(
    rng,
    lag_s,
    n_lines=8,
    line_s=120.0,
    turn_s=20.0,
    vector_noise_nT=1.0,
    feature_s=5.0,
    geology_nT=400.0,
):
    """Straight lines over smooth random geology (tens of nT, features of ~2 ``feature_s``),
    turns between them; the scalar reads the field ``lag_s`` late, the fluxgate on time (its
    magnitude: the field, an offset and a 1 % scale error, noisy)."""
    period = line_s + turn_s
    t = np.arange(0.0, n_lines * period, 1.0 / RATE_HZ)
    fine_t = np.arange(-5.0, t[-1] + 5.0, 0.01)
    geology = gaussian_filter1d(rng.normal(0.0, 1.0, fine_t.size), 100 * feature_s) * geology_nT
    field = 50_000.0 + 0.05 * fine_t + geology
    scalar = np.interp(t - lag_s, fine_t, field) + rng.normal(0.0, 0.05, t.size)
    flux = 1.01 * np.interp(t, fine_t, field) + 120.0 + rng.normal(0.0, vector_noise_nT, t.size)
    vector = np.column_stack([0.3 * flux, 0.2 * flux, np.sqrt(1 - 0.13) * flux])
    straight = (t % period) < line_s
    return t, scalar, vector, straight


@pytest.mark.parametrize("lag_s", [0.0, 0.16])
def test_the_delay_is_measured_with_an_interval(lag_s):
    covered = 0
    for seed in range(6):
        t, s, v, straight = _lines(np.random.default_rng(seed), lag_s)
        got = timing_lag(t, s, v, straight, RATE_HZ)
        assert got is not None and got.lines == 8
        assert got.lag_s == pytest.approx(lag_s, abs=0.03)
        covered += got.ci95_s[0] <= lag_s <= got.ci95_s[1]
        if lag_s >= 0.1:
            assert got.p_value < 0.01
    assert covered >= 5  # 95 % intervals: at least 5 of 6 (P = 0.97)


def test_lines_that_do_not_fix_a_delay_widen_the_interval_not_narrow_it():
    # slow interference in the scalar alone (features of ~4 s, ~2 nT, beside broad geology)
    # moves each short line's best delay by up to seconds. Each line's delay clipped to a
    # window round the pooled minimum made the lines agree falsely: 10 of 30 intervals
    # covered the truth. Lines whose own minimum lies at the search's edge fix no delay
    rng = np.random.default_rng(2026)
    covered = returned = 0
    for _ in range(30):
        t, s, v, straight = _lines(
            rng, 0.1, n_lines=6, line_s=50.0, turn_s=20.0, feature_s=15.0, geology_nT=600.0
        )
        s = s + gaussian_filter1d(rng.normal(0.0, 1.0, t.size), 40.0) * 2.0
        got = timing_lag(t, s, v, straight, RATE_HZ)
        if got is not None:
            returned += 1
            covered += got.ci95_s[0] <= 0.1 <= got.ci95_s[1]
    assert returned >= 15
    assert covered >= 0.85 * returned


def test_no_geology_no_timing():
    # flat ground: the fluxgate's record holds nothing to time the scalar against
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 8 * 140.0, 0.1)
    s = 50_000.0 + 0.05 * t + rng.normal(0, 0.05, t.size)
    f = s + rng.normal(0, 1.0, t.size)
    v = np.column_stack([0.3 * f, 0.2 * f, np.sqrt(1 - 0.13) * f])
    assert timing_lag(t, s, v, (t % 140.0) < 120.0, RATE_HZ) is None


def test_too_few_lines():
    t, s, v, straight = _lines(np.random.default_rng(1), 0.1, n_lines=3)
    assert timing_lag(t, s, v, straight, RATE_HZ) is None


def test_independent_estimates_combine_by_inverse_variance():
    from types import SimpleNamespace

    from pipeline.audit.timing import combined_interval

    z = 1.959964
    a = SimpleNamespace(lag_s=0.1, ci95_s=(0.1 - z * 0.1, 0.1 + z * 0.1))  # se 0.1
    b = SimpleNamespace(lag_s=0.4, ci95_s=(0.4 - z * 0.2, 0.4 + z * 0.2))  # se 0.2
    lag, lo, hi = combined_interval([a, b])
    # weights 100 and 25: (10 + 10) / 125; se 1 / sqrt(125)
    assert lag == pytest.approx(0.16)
    assert hi - lag == pytest.approx(lag - lo) == pytest.approx(z / np.sqrt(125.0))
    # a degenerate or missing estimate adds nothing
    flat = SimpleNamespace(lag_s=5.0, ci95_s=(5.0, 5.0))
    assert combined_interval([a, flat]) == pytest.approx((0.1, 0.1 - z * 0.1, 0.1 + z * 0.1))
    assert combined_interval([]) is None
