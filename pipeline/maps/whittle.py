"""Whittle's approximate likelihood of an ARIMA signal plus white noise, for ranking orders.

The map stage chooses the ARIMA order of its identification stretch by BIC over a dozen
candidates, and each candidate's exact likelihood (statsmodels' state-space Kalman filter)
costs ~100 evaluations of a filter over every cell. Whittle's likelihood (Whittle 1953)
replaces the exact Gaussian likelihood by its frequency-domain form,

    -2 ln L ~ sum_j [ ln(2 pi f(w_j)) + 2 pi I(w_j) / (2 pi f(w_j)) ] ,

over the Fourier frequencies w_j of the sequence (both halves of the spectrum; I the
periodogram), which is asymptotically equivalent and costs one FFT and then O(n) per
evaluation. The d-th differences of an ARIMA(p, d, q) signal plus white noise of variance R
have the spectral density

    f(w) = [ s2 |theta(e^-iw)|^2 / |phi(e^-iw)|^2 + R |1 - e^-iw|^(2 d) ] / (2 pi) .

It ranks the candidates only (:func:`pipeline.maps.arima.fit_arima` fits the shortlist by
the exact likelihood and BIC chooses among those). Hand-written because statsmodels offers
Whittle estimation for none of its ARIMA models, let alone one with a known measurement
noise. A sequence with missing cells is split at them: each gap-free run (at least
:data:`MIN_RUN` samples) contributes its own periodogram, as independent stretches would.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

# gap-free runs shorter than this carry too few frequencies to rank a model on
MIN_RUN = 64


@dataclass(frozen=True)
class WhittleFit:
    """A candidate's Whittle fit.

    Attributes
    ----------
    ar, ma : ndarray
        phi_1..phi_p and theta_1..theta_q of (1 - sum phi B^i) and (1 + sum theta B^j).
    sigma2 : float
        Innovation variance of the signal (the sequence's units squared).
    bic : float
        k ln(n) - 2 ln L_Whittle, k = p + q + 1, n the samples scored.
    """

    ar: np.ndarray
    ma: np.ndarray
    sigma2: float
    bic: float


@dataclass(frozen=True)
class Periodograms:
    """The periodogram ordinates of a differenced sequence's gap-free runs, pooled: the
    frequencies w (rad per sample, 0 < w < pi) and 2 pi I(w), each counted twice (its
    mirror), and the samples they hold."""

    w: np.ndarray
    two_pi_i: np.ndarray
    samples: int

    @classmethod
    def of(cls, x: np.ndarray, d: int) -> Periodograms:
        """The d-th differences of ``x`` (NaN: missing; a difference across one is missing),
        split at missing samples into runs of at least :data:`MIN_RUN`."""
        y = np.diff(np.asarray(x, float), n=d) if d else np.asarray(x, float)
        ok = np.isfinite(y)
        edges = np.flatnonzero(np.diff(np.r_[0, ok.astype(np.int8), 0]))
        w, pi2, n = [], [], 0
        for a, b in zip(edges[::2], edges[1::2], strict=True):
            m = b - a
            if m < MIN_RUN:
                continue
            seg = y[a:b] - y[a:b].mean()  # the zero frequency, a run's level, is left out
            j = np.arange(1, (m - 1) // 2 + 1)
            w.append(2 * np.pi * j / m)
            pi2.append(np.abs(np.fft.rfft(seg)[j]) ** 2 / m)
            n += m
        if not w:
            raise ValueError(f"no gap-free run of {MIN_RUN} samples to score")
        return cls(np.concatenate(w), np.concatenate(pi2), n)


def _polynomial_power(coefs: np.ndarray, z: np.ndarray, sign: float) -> np.ndarray:
    """|1 + sign * sum c_i z^i|^2 at ``z`` (complex, on the unit circle)."""
    acc = np.ones_like(z)
    zk = np.ones_like(z)
    for c in coefs:
        zk = zk * z
        acc = acc + sign * c * zk
    return np.abs(acc) ** 2


def whittle_fit(
    pg: Periodograms, p: int, d: int, q: int, measurement_var: float | None
) -> WhittleFit:
    """The Whittle estimates of ARIMA(p, d, q) (plus white noise of ``measurement_var``,
    known; None: no noise term) on the periodograms ``pg`` of the d-th differences: AR
    stationary and MA invertible through statsmodels' constraining transforms, the
    innovation variance on a log scale, by L-BFGS from white noise."""
    from statsmodels.tsa.statespace.tools import constrain_stationary_univariate

    z = np.exp(-1j * pg.w)
    noise = (
        0.0
        if not measurement_var
        else float(measurement_var) * np.abs(1.0 - z) ** (2 * d)  # white noise differenced
    )
    var_y = float(np.mean(pg.two_pi_i))
    floor = 1e-12 * max(var_y, 1e-300)

    def unpack(v: np.ndarray):
        ar = constrain_stationary_univariate(v[:p]) if p else np.zeros(0)
        ma = -constrain_stationary_univariate(v[p : p + q]) if q else np.zeros(0)
        return ar, ma, float(np.exp(v[-1]))

    def cost(v: np.ndarray) -> float:
        ar, ma, s2 = unpack(v)
        two_pi_f = s2 * _polynomial_power(ma, z, 1.0) / _polynomial_power(ar, z, -1.0) + noise
        two_pi_f = np.maximum(two_pi_f, floor)
        return float(np.sum(np.log(two_pi_f) + pg.two_pi_i / two_pi_f))

    start_var = max(var_y - float(np.mean(noise)), 0.01 * var_y)
    v0 = np.r_[np.zeros(p + q), np.log(max(start_var, floor))]
    res = minimize(cost, v0, method="L-BFGS-B")
    ar, ma, s2 = unpack(res.x)
    # each ordinate stands for itself and its mirror: -2 ln L is twice the half-sum
    bic = (p + q + 1) * np.log(pg.samples) + 2.0 * float(res.fun)
    return WhittleFit(ar, ma, s2, float(bic))
