"""The fold test over several candidates: the maximum statistic of the sign-flip test.

One candidate: the plain sign-flip p. Several candidates sharing the folds (correlated
gains, symmetric about 0 under the null): the chance that any candidate passes at 0.05 is
at most 5 % (within its exact interval over 2000 draws). A gain in nine folds of ten with
one small loss passes at 0.01 among six candidates, where Holm over the plain tests
cannot.
"""

from __future__ import annotations

import numpy as np
from scipy.stats import binomtest

from pipeline.audit.evidence import holm
from pipeline.compensate.heldout import fold_test_max, sign_flip_p


def test_one_candidate_is_the_sign_flip_test():
    x = np.array([0.3, 0.1, -0.05, 0.2, 0.4, 0.15, 0.05, 0.22, -0.1, 0.3])
    assert abs(fold_test_max({"a": x})["a"] - sign_flip_p(x)) < 1e-12


def test_the_family_error_rate_is_the_level_under_the_null():
    rng = np.random.default_rng(7)
    cov = 0.5 * np.eye(6) + 0.5  # candidates share the folds: correlated gains
    draws, hits = 2000, 0
    for _ in range(draws):
        x = rng.multivariate_normal(np.zeros(6), cov, size=10)
        p = fold_test_max({f"g{j}": x[:, j] for j in range(6)}, seed=0)
        hits += min(p.values()) < 0.05
    ci = binomtest(hits, draws).proportion_ci(0.99)
    assert ci.low <= 0.05, (hits, draws)
    assert hits / draws > 0.02  # not a test that never passes


def test_one_small_loss_in_ten_folds_passes_among_six_candidates():
    rng = np.random.default_rng(3)
    gains = {f"g{j}": rng.normal(0.0, 0.05, 10) for j in range(5)}
    gains["eddy"] = np.array([0.9, 0.7, 1.1, 0.8, -0.02, 0.6, 1.0, 0.9, 0.7, 0.8])
    p = fold_test_max(gains)
    assert p["eddy"] < 0.01, p
    plain = holm([sign_flip_p(v) for v in gains.values()])
    assert plain[-1] >= 0.01  # Holm over the plain tests: only a gain in every fold passes


def test_a_candidate_that_makes_held_out_data_much_worse_hides_no_gain():
    # the same gain in nine folds of ten beside a candidate that loses a lot in every fold:
    # flipped, its large losses are large gains, which as raw means took the maximum in
    # most patterns
    gains = {
        "eddy": np.array([0.30, 0.25, 0.35, 0.28, -0.02, 0.22, 0.33, 0.30, 0.26, 0.29]),
        "second_order": np.log(1.0 / np.array([2.4, 2.2, 2.6, 2.3, 2.5, 2.4, 2.1, 2.7, 2.4, 2.3])),
    }
    p = fold_test_max(gains)
    assert p["eddy"] < 0.01, p
    assert p["second_order"] > 0.5, p
