"""The fold-level held-out test (:func:`pipeline.compensate.heldout.fold_test`) is at its
level under the null and reaches 1/2^K when the gain is positive in every one of K folds.

The null is simulated with physics the test does not assume: per-fold residuals of two
exchangeable models (Gaussian, and heavy-tailed, with fold lengths and scales that differ),
so each fold's log ratio is symmetric about 0 but neither normal nor identically
distributed.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from pipeline.audit.evidence import holm
from pipeline.compensate.heldout import N_BLOCKS, fold_test, sign_flip_p

N_NULL = 2000


def _null_folds(rng: np.random.Generator, heavy: bool):
    """Two exchangeable models' residuals over N_BLOCKS folds of uneven length and scale."""
    sizes = rng.integers(40, 400, N_BLOCKS)
    fold = np.repeat(np.arange(N_BLOCKS), sizes)
    scale = np.repeat(rng.uniform(0.05, 0.5, N_BLOCKS), sizes)
    draw = (lambda n: rng.standard_t(2, n)) if heavy else rng.standard_normal
    common = scale * draw(fold.size)  # what both models leave (correlated residuals)
    a = common + 0.3 * scale * draw(fold.size)
    b = common + 0.3 * scale * draw(fold.size)
    return a, b, fold


@pytest.mark.parametrize("heavy", [False, True])
def test_fold_test_is_at_its_level_under_the_null(heavy):
    rng = np.random.default_rng(36)
    p = np.array([fold_test(*_null_folds(rng, heavy)) for _ in range(N_NULL)])
    for alpha in (0.05, 0.2):
        # attainable level of the exact test: a multiple of 1/2^K at or below alpha
        level = np.floor(alpha * 2**N_BLOCKS) / 2**N_BLOCKS
        lo, hi = stats.binom.interval(0.999, N_NULL, level)
        assert lo <= np.sum(p <= alpha) <= hi, (alpha, np.mean(p <= alpha), level)
    # roughly uniform over the whole range, not only in the tail
    assert stats.kstest(p, "uniform").pvalue > 1e-3


def test_fold_test_reaches_one_over_two_to_the_k_when_every_fold_gains():
    rng = np.random.default_rng(1)
    a, _, fold = _null_folds(rng, False)
    gain = np.repeat(rng.uniform(0.5, 0.99, N_BLOCKS), np.bincount(fold))  # uneven gains
    p = fold_test(a, gain * a, fold)
    assert abs(p - 1.0 / 2**N_BLOCKS) < 1e-12
    # and passes alpha 0.01 after Holm over a round of six candidate groups
    assert max(holm([p] * 6)) < 0.01
    # one fold that loses a little still leaves p small; the reverse comparison gives 1
    gain[fold == 3] = 1.05
    assert fold_test(a, gain * a, fold) < 0.01
    assert fold_test(gain * a, a, fold) > 0.9


def test_sign_flip_p_is_exact_on_small_cases_and_sampled_beyond():
    # three values: the 8 sign patterns' sums are +-1 +-2 +-4; observed 7 is the largest
    assert sign_flip_p(np.array([1.0, 2.0, 4.0])) == pytest.approx(1 / 8)
    # observed 1 + 2 - 4 = -1: the sums >= -1 are 7, 5, 3, 1, -1, 5 of 8
    assert sign_flip_p(np.array([1.0, 2.0, -4.0])) == pytest.approx(5 / 8)
    x = np.abs(np.random.default_rng(2).standard_normal(20))
    p = sign_flip_p(x)  # sampled patterns: never below 1 / (draws + 1)
    assert 0 < p <= 2.0 / 2**16
    assert sign_flip_p(-x) > 0.99


def test_holm_matches_statsmodels_multipletests(monkeypatch):
    """:func:`holm` is statsmodels' Holm step-down adjustment, ties and p near 1 included."""
    import gc

    from statsmodels.stats.multitest import multipletests

    # the reference runs a full garbage collection on every call: ~0.3 s each in a test
    # process holding many simulated flights, a minute for these 200 calls; it changes no
    # number
    monkeypatch.setattr(gc, "collect", lambda *args: 0)
    rng = np.random.default_rng(3)
    for n in (1, 2, 5, 12):
        for _ in range(50):
            p = rng.uniform(0, 1, n) ** rng.uniform(0.5, 4)
            if n > 2:
                p[1] = p[0]  # a tie
            want = multipletests(p, method="holm")[1]
            assert np.allclose(holm(list(p)), want, rtol=0, atol=1e-15)
    assert holm([]) == []
