"""Whittle's likelihood (:mod:`pipeline.maps.whittle`), the map's ARIMA order screening, on
simulated ARMA signals under white noise whose parameters are known, and against the exact
likelihood's own choice of order."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.signal import lfilter

from pipeline.maps.arima import SHORTLIST, fit_arima
from pipeline.maps.whittle import MIN_RUN, Periodograms, whittle_fit


def arma(rng, n, ar, ma, sigma=1.0):
    """An ARMA signal (1 - sum ar B^i) x = (1 + sum ma B^j) e, with a burn-in dropped."""
    e = rng.normal(0, sigma, n + 500)
    return lfilter(np.r_[1.0, ma], np.r_[1.0, -np.asarray(ar)], e)[500:]


@pytest.mark.parametrize("seed", range(3))
def test_the_estimates_of_a_signal_under_known_noise(seed):
    """AR(2) signal, innovation sd 1, under white noise of variance 4: the Whittle estimates
    land on the truth within a few standard errors (n = 20 000)."""
    rng = np.random.default_rng(seed)
    x = arma(rng, 20_000, [1.2, -0.5], []) + rng.normal(0, 2.0, 20_000)
    fit = whittle_fit(Periodograms.of(x, 0), 2, 0, 0, measurement_var=4.0)
    assert np.allclose(fit.ar, [1.2, -0.5], atol=0.06)
    assert fit.sigma2 == pytest.approx(1.0, rel=0.2)


def test_differenced_noise_is_modelled_as_such():
    """A random walk (innovation sd 0.3) under white noise of sd 1, once differenced: white
    signal plus an MA(1) of the noise; ARIMA(0, 1, 0) under the known noise scores better
    than ARIMA(0, 1, 1) without a noise term would need, and reads the walk's variance."""
    rng = np.random.default_rng(9)
    x = np.cumsum(rng.normal(0, 0.3, 30_000)) + rng.normal(0, 1.0, 30_000)
    fit = whittle_fit(Periodograms.of(x, 1), 0, 1, 0, measurement_var=1.0)
    assert fit.sigma2 == pytest.approx(0.09, rel=0.25)


def test_runs_between_missing_cells_are_scored_apart():
    x = np.random.default_rng(1).normal(size=1_000)
    x[100:110] = np.nan
    x[150] = np.nan  # a run of 39 samples between: too short to score
    pg = Periodograms.of(x, 0)
    assert pg.samples == 100 + (1_000 - 151)
    with pytest.raises(ValueError):
        Periodograms.of(np.r_[x[: MIN_RUN - 1], np.nan, x[: MIN_RUN - 1]], 0)


@pytest.mark.parametrize(
    "seed", [0, *(pytest.param(s, marks=pytest.mark.slow) for s in (1, 2))]
)  # each: eleven exact fits on 12 000 samples
def test_the_shortlist_holds_the_exact_searchs_choice(seed, monkeypatch):
    """On lanes with a signal of known order under noise, the exact likelihood's search over
    every candidate picks an order the Whittle screening puts on its shortlist, and the
    screened search, which keeps Whittle's estimates, chooses the same order with an exact
    likelihood within a unit per parameter of that order's maximum (BIC within two)."""
    import pipeline.maps.arima as arima

    rng = np.random.default_rng(seed)
    ar, ma = [[0.9], [1.5, -0.6], [0.6]][seed], [[], [], [0.4]][seed]
    x = arma(rng, 12_000, ar, ma) + rng.normal(0, 0.5, 12_000)
    screened = fit_arima(x, measurement_var=0.25)
    shortlist = screened.tests["screened"][str(screened.d)]
    assert len(shortlist) == SHORTLIST
    monkeypatch.setattr(arima, "SCREEN_ABOVE", 10**9)
    full = fit_arima(x, measurement_var=0.25)
    assert [full.p, full.q] in shortlist
    assert screened.tests["estimated_by"] == "whittle"
    assert (screened.p, screened.d, screened.q) == (full.p, full.d, full.q)
    assert full.bic <= screened.bic < full.bic + 2 * (full.p + full.q + 1)


def test_a_serpentine_random_walk_falls_back_to_exact_fits_then_differences():
    """A random walk read back and forth (a serpentine map's lanes: its segment means do not
    trend, so the stationarity test keeps d = 0) under noise: every shortlisted Whittle
    estimate at d = 0 has an AR root on the unit circle, so the shortlist is fitted exactly;
    those fits are degenerate too, and one more difference gives a model from Whittle's
    estimates."""
    rng = np.random.default_rng(0)
    walk = np.cumsum(rng.normal(size=1_500))
    x = np.concatenate([walk, walk[::-1]] * 4) + rng.normal(0, 0.5, 12_000)
    model = fit_arima(x, measurement_var=0.25)
    assert model.tests["d_from_test"] == 0 and set(model.tests["screened"]) == {"0", "1"}
    assert model.d == 1 and model.tests["estimated_by"] == "whittle"
    failed = model.tests["failed_candidates"]
    assert any(",0," in f and "unit circle" in f for f in failed)
    # the shortlist's Whittle estimates at d = 0 are listed as passed over, then their exact
    # fits as rejected
    passed_over = [f for f in failed if ",0," in f and "Whittle's estimates" in f]
    assert len(passed_over) == len(model.tests["screened"]["0"])
    assert any(",0," in f and "Whittle" not in f for f in failed)


def test_the_order_search_prints_no_statsmodels_warnings_on_first_import():
    """statsmodels' import puts "always" filters for its warnings in front of any set
    before it, so the search's own filter must be set after the import: in a fresh
    interpreter (where the search imports statsmodels) no convergence or start-parameter
    warning reaches the user's console."""
    code = (
        "import numpy as np\n"
        "from pipeline.maps.arima import fit_arima\n"
        "rng = np.random.default_rng(0)\n"
        "walk = np.cumsum(rng.normal(size=1_500))\n"
        "x = np.concatenate([walk, walk[::-1]] * 2) + rng.normal(0, 0.5, 6_000)\n"
        "fit_arima(x[:3_000], measurement_var=0.25)\n"
    )
    root = Path(__file__).resolve().parents[1]
    run = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        cwd=root,
        env={**os.environ, "PYTHONPATH": str(root)},
        timeout=300,
    )
    assert run.returncode == 0, run.stderr[-2000:]
    assert "Warning" not in run.stderr, run.stderr[-2000:]
