"""Statistics for accepting a model extension: nested tests, held-out gain, noise floor.

Band-passed residuals are correlated over about 1/(2 B) seconds (B the bandwidth), so the
regressions behind the F-test and BIC use every k-th sample with k = rate / (2 B): the
nominal p-values then hold approximately instead of being wildly optimistic. The held-out
comparison averages squared residuals over blocks of ``block_s`` seconds, which are close
to independent, and tests the paired block differences with the one-sided Wilcoxon
signed-rank test: block differences are heavy-tailed (a sensor lag shows mostly in the
fastest manoeuvres), and a t-test then misses even a large reduction.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from scipy import stats
from scipy.signal import sosfiltfilt

from pipeline.compensate.filters import bandpass_sos
from pipeline.compensate.heldout import HeldOut, heldout_gain  # noqa: F401 (re-exported)


def thinning_step(rate_hz: float, band_hz: tuple[float, float]) -> int:
    """Sample step leaving about one sample per correlation time 1 / (2 B) of a band-passed series.

    Parameters
    ----------
    rate_hz : float
        Sample rate, Hz.
    band_hz : tuple of float
        Pass band (low, high), Hz; the bandwidth B is high - low.

    Returns
    -------
    int
        k = round(rate / (2 B)), at least 1: use every k-th sample.
    """
    return max(1, int(round(rate_hz / (2.0 * (band_hz[1] - band_hz[0])))))


def least_squares_rss(a: np.ndarray, y: np.ndarray) -> tuple[float, int, np.ndarray]:
    """Ordinary least squares of ``y`` on the columns of ``a``: (residual sum of squares,
    rank of ``a``, coefficients); no columns: (y . y, 0, empty)."""
    if a.shape[1] == 0:
        return float(y @ y), 0, np.zeros(0)
    coef, *_ = np.linalg.lstsq(a, y, rcond=None)
    r = y - a @ coef
    return float(r @ r), int(np.linalg.matrix_rank(a)), coef


def f_test_p(rss0: float, k0: int, rss1: float, k1: int, n: int) -> float:
    """p of the F-test of a nested least-squares model (``k1`` columns, residual sum of
    squares ``rss1``) against its base (``k0``, ``rss0``) on ``n`` rows; 1 when the test has
    no degrees of freedom."""
    df1, df2 = k1 - k0, n - k1
    if df1 <= 0 or df2 <= 0 or rss1 <= 0:
        return 1.0
    f = ((rss0 - rss1) / df1) / (rss1 / df2)
    return float(stats.f.sf(f, df1, df2))


@dataclass
class NestedTest:
    """Nested-model comparison of an extended design against its base (:func:`nested_test`).

    Attributes
    ----------
    f : float
        F statistic of the extension.
    p_value : float
        p of the F-test (on the thinned samples).
    df : int
        Numerator degrees of freedom (the number of added columns).
    delta_bic : float
        BIC(extended) - BIC(base); negative favours the extension.
    samples : int
        Rows used after thinning.
    """

    f: float
    p_value: float
    df: int
    delta_bic: float  # BIC(extended) - BIC(base): negative favours the extension
    samples: int

    def to_dict(self) -> dict:
        """JSON-ready fields."""
        return {
            "f": self.f,
            "p_value": self.p_value,
            "df": self.df,
            "delta_bic": self.delta_bic,
            "samples": self.samples,
        }


def nested_test(y: np.ndarray, x_base: np.ndarray, x_ext: np.ndarray, step: int) -> NestedTest:
    """F-test and BIC of ``x_ext`` (which contains ``x_base``'s columns) against ``x_base``."""
    import statsmodels.api as sm
    from statsmodels.tools.sm_exceptions import SingularMatrixWarning

    yb = np.asarray(y, float)[::step]
    xb = np.asarray(x_base, float)[::step]
    xe = np.asarray(x_ext, float)[::step]
    # columns scaled to unit RMS: the same fit, better conditioned pseudo-inverse
    sb = np.sqrt(np.mean(xb**2, axis=0)) + 1e-300
    se = np.sqrt(np.mean(xe**2, axis=0)) + 1e-300
    with warnings.catch_warnings():
        # columns a flight does not excite (a track without height changes, a straight
        # smoothed leg): the pseudo-inverse fits, and the F-test counts the design's rank
        warnings.simplefilter("ignore", SingularMatrixWarning)
        r0 = sm.OLS(yb, xb / sb).fit()
        r1 = sm.OLS(yb, xe / se).fit()
    f, p, df = r1.compare_f_test(r0)
    return NestedTest(float(f), float(p), int(round(df)), float(r1.bic - r0.bic), int(yb.size))


def profile_f_test(y0: np.ndarray, y1: np.ndarray, x: np.ndarray, step: int) -> NestedTest:
    """F-test and BIC of one estimated non-linear parameter (a lag) by its profile
    likelihood: ``y0`` and ``y1`` are the record without and with the parameter at its
    estimate, both fitted by the same columns ``x``."""
    import statsmodels.api as sm
    from statsmodels.tools.sm_exceptions import SingularMatrixWarning

    xb = np.asarray(x, float)[::step]
    xb = xb / (np.sqrt(np.mean(xb**2, axis=0)) + 1e-300)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SingularMatrixWarning)  # as in nested_test
        r0 = sm.OLS(np.asarray(y0, float)[::step], xb).fit()
        r1 = sm.OLS(np.asarray(y1, float)[::step], xb).fit()
    n, dof = r1.nobs, r1.df_resid - 1
    if dof <= 0 or not r1.ssr > 0:
        return NestedTest(0.0, 1.0, 1, 0.0, int(n))
    f = max(r0.ssr - r1.ssr, 0.0) / (r1.ssr / dof)
    bic = n * np.log(r1.ssr / r0.ssr) + np.log(n)
    return NestedTest(float(f), float(stats.f.sf(f, 1, dof)), 1, float(bic), int(n))


def paired_point_gain(d_before: np.ndarray, d_after: np.ndarray, rank: bool = False) -> HeldOut:
    """The same comparison for independent points (crossovers, overlap points); ``rank``:
    a one-sided Wilcoxon signed-rank test of the squares' differences instead of the t-test
    (for heavy-tailed points)."""
    a, b = np.asarray(d_before, float), np.asarray(d_after, float)
    ok = np.isfinite(a) & np.isfinite(b)
    a, b = a[ok], b[ok]
    if a.size < 3:
        return HeldOut(float("nan"), float("nan"), 1.0, int(a.size))
    d = a**2 - b**2
    if not np.std(d) > 0:
        p = 1.0
    elif rank:
        p = float(stats.wilcoxon(d, alternative="greater").pvalue)
    else:
        p = float(stats.ttest_1samp(d, 0.0, alternative="greater").pvalue)
    return HeldOut(float(np.sqrt(np.mean(a**2))), float(np.sqrt(np.mean(b**2))), p, int(a.size))


def band_noise_gain(rate_hz: float, band_hz: tuple[float, float], poles: int) -> float:
    """RMS of unit white noise after the zero-phase band-pass (deterministic, seeded)."""
    x = np.random.default_rng(0).normal(size=200_000)
    return float(np.std(sosfiltfilt(bandpass_sos(band_hz, rate_hz, poles), x)))


def holm(p_values: list[float]) -> list[float]:
    """Holm-adjusted p-values (statsmodels), for several candidates tested at once."""
    from statsmodels.stats.multitest import multipletests

    if not p_values:
        return []
    return [float(v) for v in multipletests(p_values, method="holm")[1]]
