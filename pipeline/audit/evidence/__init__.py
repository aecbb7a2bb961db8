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


# A direction of a design (columns scaled to unit RMS) whose singular value is below this
# fraction of the largest is taken as no direction. Band-passed columns carry rounding of
# about 1e-13 of themselves; a rank decided there flips with the order of operations, and
# with it the F-test's degrees of freedom and BIC's penalty (nearly collinear nuisance
# columns, a decay of 0.02 s beside T-L's instantaneous eddy terms, come that close).
RANK_RTOL = 1e-8


def least_squares_rss(a: np.ndarray, y: np.ndarray) -> tuple[float, int, np.ndarray]:
    """Ordinary least squares of ``y`` on the columns of ``a``: (residual sum of squares,
    rank of ``a``, coefficients of the minimum-norm solution); no columns: (y . y, 0,
    empty). Columns are scaled to unit RMS and the rank counts singular values above
    :data:`RANK_RTOL` of the largest, so rounding cannot change it."""
    y = np.asarray(y, float)
    if a.shape[1] == 0:
        return float(y @ y), 0, np.zeros(0)
    scale = np.sqrt(np.mean(np.asarray(a, float) ** 2, axis=0))
    scale = np.where(scale > 0, scale, 1.0)
    u, sv, vt = np.linalg.svd(a / scale, full_matrices=False)
    rank = int(np.sum(sv > RANK_RTOL * sv[0])) if sv.size and sv[0] > 0 else 0
    ur = u[:, :rank]
    proj = ur.T @ y
    r = y - ur @ proj
    coef = (vt[:rank].T @ (proj / sv[:rank])) / scale
    return float(r @ r), rank, coef


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
    """F-test and BIC of ``x_ext`` (which contains ``x_base``'s columns) against ``x_base``,
    on every ``step``-th row; degrees of freedom from the designs' ranks
    (:func:`least_squares_rss`)."""
    yb = np.asarray(y, float)[::step]
    rss0, k0, _ = least_squares_rss(np.asarray(x_base, float)[::step], yb)
    rss1, k1, _ = least_squares_rss(np.asarray(x_ext, float)[::step], yb)
    n, df = yb.size, k1 - k0
    if df <= 0 or n - k1 <= 0 or not rss1 > 0:
        return NestedTest(0.0, 1.0, max(df, 0), 0.0, int(n))
    f = max(rss0 - rss1, 0.0) / df / (rss1 / (n - k1))
    bic = n * np.log(rss1 / rss0) + df * np.log(n)
    return NestedTest(float(f), float(stats.f.sf(f, df, n - k1)), int(df), float(bic), int(n))


def profile_f_test(
    y0: np.ndarray, y1: np.ndarray, x: np.ndarray, step: int, x1: np.ndarray | None = None
) -> NestedTest:
    """F-test and BIC of one estimated non-linear parameter (a lag) by its profile
    likelihood: ``y0`` and ``y1`` are the record without and with the parameter at its
    estimate, fitted by the columns ``x`` (``x1`` with the parameter, when it moves the
    columns too: a sensor filter's rows)."""
    xb = np.asarray(x, float)[::step]
    xb1 = xb if x1 is None else np.asarray(x1, float)[::step]
    rss0, _, _ = least_squares_rss(xb, np.asarray(y0, float)[::step])
    rss1, k, _ = least_squares_rss(xb1, np.asarray(y1, float)[::step])
    n = xb.shape[0]
    dof = n - k - 1
    if dof <= 0 or not rss1 > 0:
        return NestedTest(0.0, 1.0, 1, 0.0, int(n))
    f = max(rss0 - rss1, 0.0) / (rss1 / dof)
    bic = n * np.log(rss1 / rss0) + np.log(n)
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


def weighted_rms(errors_nT: np.ndarray, precision: np.ndarray) -> float:
    """The RMS (nT) of ``errors_nT`` weighted by each one's ``precision`` (1 / nT^2; any
    common factor cancels): sqrt(sum p e^2 / sum p), the plain RMS when every p is the same.
    Held-out errors of unequal precision (sets read to different accuracy, predictions of
    different leverage) are summed so, as a Gaussian held-out likelihood sums them."""
    return float(np.sqrt(np.sum(precision * errors_nT**2) / np.sum(precision)))


def band_noise_gain(rate_hz: float, band_hz: tuple[float, float], poles: int) -> float:
    """RMS of unit white noise after the zero-phase band-pass (deterministic, seeded)."""
    x = np.random.default_rng(0).normal(size=200_000)
    return float(np.std(sosfiltfilt(bandpass_sos(band_hz, rate_hz, poles), x)))


def significant(h: HeldOut | None, alpha: float, min_gain: float) -> bool:
    """Whether a held-out comparison shows a gain: one-sided p below ``alpha`` and at least
    ``min_gain`` of the held-out RMS removed."""
    return h is not None and h.p_value < alpha and h.reduction >= min_gain


def holm(p_values: list[float]) -> list[float]:
    """Holm-adjusted p-values, for several candidates tested at once: the step-down
    adjustment of statsmodels' ``multipletests(method="holm")``, the same arithmetic written
    out because that function collects garbage on every call (a tenth of a second each, and
    an audit makes several)."""
    p = np.asarray(p_values, float)
    if p.size == 0:
        return []
    order = np.argsort(p)
    adjusted = np.empty(p.size)
    adjusted[order] = np.minimum(np.maximum.accumulate(p[order] * np.arange(p.size, 0, -1)), 1.0)
    return [float(v) for v in adjusted]
