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

from dataclasses import dataclass

import numpy as np
from scipy import stats
from scipy.signal import sosfiltfilt

from pipeline.compensate.filters import bandpass_sos


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

    yb = np.asarray(y, float)[::step]
    xb = np.asarray(x_base, float)[::step]
    xe = np.asarray(x_ext, float)[::step]
    # columns scaled to unit RMS: the same fit, better conditioned pseudo-inverse
    sb = np.sqrt(np.mean(xb**2, axis=0)) + 1e-300
    se = np.sqrt(np.mean(xe**2, axis=0)) + 1e-300
    r0 = sm.OLS(yb, xb / sb).fit()
    r1 = sm.OLS(yb, xe / se).fit()
    f, p, df = r1.compare_f_test(r0)
    return NestedTest(float(f), float(p), int(round(df)), float(r1.bic - r0.bic), int(yb.size))


@dataclass
class HeldOut:
    """Held-out comparison of two models' residuals on the same samples.

    Attributes
    ----------
    rms_before_nT, rms_after_nT : float
        Held-out residual RMS of the base and the extended model, nT.
    p_value : float
        One-sided p that the extended model's residual is smaller (Wilcoxon signed-rank over
        the paired blocks or points); 1 when too few.
    blocks : int
        Blocks (or points) in the paired test.
    """

    rms_before_nT: float
    rms_after_nT: float
    p_value: float
    blocks: int

    @property
    def reduction(self) -> float:
        """Fractional held-out RMS reduction, 1 - after / before (0 when before is 0)."""
        return 1.0 - self.rms_after_nT / self.rms_before_nT if self.rms_before_nT > 0 else 0.0

    def to_dict(self) -> dict:
        """JSON-ready fields, with the reduction in percent (``reduction_pct``)."""
        return {
            "rms_before_nT": self.rms_before_nT,
            "rms_after_nT": self.rms_after_nT,
            "p_value": self.p_value,
            "blocks": self.blocks,
            "reduction_pct": 100.0 * self.reduction,
        }


def heldout_gain(
    r_before: np.ndarray, r_after: np.ndarray, time_s: np.ndarray, block_s: float = 10.0
) -> HeldOut:
    """Is ``r_after`` smaller than ``r_before`` (same samples) beyond what noise explains?"""
    a, b, t = (np.asarray(v, float) for v in (r_before, r_after, time_s))
    ok = np.isfinite(a) & np.isfinite(b)
    a, b, t = a[ok], b[ok], t[ok]
    if a.size < 10:
        return HeldOut(float("nan"), float("nan"), 1.0, 0)
    key = np.floor((t - t.min()) / block_s).astype(int)
    _, inv = np.unique(key, return_inverse=True)
    n = np.bincount(inv)
    d = (np.bincount(inv, a**2) - np.bincount(inv, b**2)) / n
    d = d[n >= 5]
    p = (
        float(stats.wilcoxon(d, alternative="greater").pvalue)
        if d.size > 5 and np.any(d != 0)
        else 1.0
    )
    return HeldOut(float(np.sqrt(np.mean(a**2))), float(np.sqrt(np.mean(b**2))), p, int(d.size))


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
