"""Does the scalar sensor keep time with the vector magnetometer? Seen along straight lines.

A late scalar sensor delays its whole reading, the Earth's field included. Along a straight
line the field changes with the ground below (geology) by nT per second, and the vector
magnetometer's magnitude |m| sees the same changes (the carrier's interference at either
sensor is nearly constant while heading and attitude are). The delay that best aligns the
two low-passed records is the scalar's lag against the fluxgate. On the calibration
manoeuvres a lag is hard to tell from eddy currents with a time constant (both are a
derivative of the interference); along lines there are no manoeuvres, so this measures the
lag that eddy currents cannot imitate.

Hand-written: a sub-sample delay with a per-line scale, offset and drift between two
records; scipy.signal.correlation_lags gives whole samples only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats
from scipy.signal import butter, sosfiltfilt

from pipeline.compensate.filters import contiguous_blocks

GEOLOGY_CUT_HZ = 0.5  # the ground's field along track lies below; above, the fluxgate's noise
LINE_END_S = 5.0  # left out at either end of a line: a turn's tail, filter transients
MIN_LINE_S = 30.0  # shorter straight runs carry too little geology
MIN_EXPLAINED = 0.8  # share of the scalar's variation about a trend the fluxgate must explain
COARSE_STEP_S = 0.04
FINE_STEP_S = 0.002


@dataclass(frozen=True)
class TimingLag:
    """The scalar reading's delay against the fluxgate's magnitude (:func:`timing_lag`).

    Attributes
    ----------
    lag_s : float
        Delay of the scalar reading, s (> 0: the scalar reports late).
    ci95_s : tuple of float
        95 % interval, s (Student t over the lines' own delays).
    p_value : float
        Two-sided p against no delay.
    lines : int
        Straight runs used.
    """

    lag_s: float
    ci95_s: tuple[float, float]
    p_value: float
    lines: int


def _line_rss(
    t: np.ndarray, s_lp: np.ndarray, f_lp: np.ndarray, lags_s: np.ndarray, trim: int
) -> np.ndarray:
    """Residual sum of squares of s ~ a f(t - L) + b + c t (a, b, c free: the sensors'
    scales, offsets and slow drifts differ) for every lag L, nT^2, over the line less
    ``trim`` samples at either end.

    The offset and the centred trend are orthogonal, so both come out of s and of every
    shifted f by one projection; the scale is then one ratio per lag (all lags at once).
    """
    sl = slice(trim, t.size - trim)
    tc = t[sl] - t[sl].mean()
    tt = float(tc @ tc)

    def detrend(x: np.ndarray) -> np.ndarray:  # rows: series; their offset and trend out
        x = x - x.mean(axis=-1, keepdims=True)
        return x - np.outer(x @ tc / tt, tc) if tt > 0 else x

    y = detrend(s_lp[sl][None, :])[0]
    shifted = np.stack([np.interp(t - lag, t, f_lp)[sl] for lag in lags_s])
    f = detrend(shifted)
    ff = np.einsum("ij,ij->i", f, f)
    fy = f @ y
    gain = np.divide(fy**2, ff, out=np.zeros_like(ff), where=ff > 1e-12 * max(ff.max(), 1e-300))
    return np.maximum(float(y @ y) - gain, 0.0)


def _trend_rss(t: np.ndarray, s_lp: np.ndarray, trim: int) -> float:
    """Residual sum of squares of s ~ b + c t over the trimmed line, nT^2."""
    sl = slice(trim, t.size - trim)
    a = np.column_stack([np.ones(t[sl].size), t[sl] - t[sl].mean()])
    coef, *_ = np.linalg.lstsq(a, s_lp[sl], rcond=None)
    return float(np.sum((s_lp[sl] - a @ coef) ** 2))


def _argmin_parabola(lags_s: np.ndarray, rss: np.ndarray) -> float:
    """Minimum of ``rss`` over ``lags_s``, refined by a parabola through its neighbours."""
    i = int(np.argmin(rss))
    if 0 < i < lags_s.size - 1:
        y0, y1, y2 = rss[i - 1], rss[i], rss[i + 1]
        den = y0 - 2 * y1 + y2
        if den > 0:
            return float(lags_s[i] + 0.5 * (y0 - y2) / den * (lags_s[1] - lags_s[0]))
    return float(lags_s[i])


def _line_records(
    t: np.ndarray, s: np.ndarray, f: np.ndarray, ok: np.ndarray, sos: np.ndarray, trim: int
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The straight runs of ``ok`` at least ``MIN_LINE_S`` long: each run's times (s) and
    its scalar ``s`` and fluxgate magnitude ``f`` (nT) less their means, low-passed by
    ``sos``."""
    lines = []
    for idx in contiguous_blocks(ok, t):
        if t[idx[-1]] - t[idx[0]] < MIN_LINE_S or idx.size <= 2 * trim + 10:
            continue
        s_lp = sosfiltfilt(sos, s[idx] - s[idx].mean())
        f_lp = sosfiltfilt(sos, f[idx] - f[idx].mean())
        lines.append((t[idx], s_lp, f_lp))
    return lines


def _each_line_lag(
    lines: list, coarse: np.ndarray, coarse_rss: list, edge: float, trim: int
) -> list[float]:
    """Each line's own delay (s), refined around its minimum over the coarse grid
    ``coarse`` (its residuals ``coarse_rss``); a line whose own minimum lies at the search's
    edge (``edge``) fixes no delay and is left out. Each line times the sensors on its own,
    over the whole search: a window around the pooled minimum would clip a line's delay to
    its edge and make the lines agree falsely."""
    each = []
    for ln, c in zip(lines, coarse_rss, strict=True):
        own = _argmin_parabola(coarse, c)
        if abs(own) >= edge:
            continue
        fine = own + np.arange(-COARSE_STEP_S, COARSE_STEP_S + 1e-9, FINE_STEP_S)
        each.append(_argmin_parabola(fine, _line_rss(*ln, fine, trim)))
    return each


def timing_lag(
    time_s: np.ndarray,
    scalar_nT: np.ndarray,
    vector_nT: np.ndarray,
    straight: np.ndarray,
    rate_hz: float,
    max_lag_s: float = 1.0,
) -> TimingLag | None:
    """The scalar's delay against the fluxgate's magnitude along straight lines.

    Parameters
    ----------
    time_s : ndarray, shape (n,)
        Epoch times, s.
    scalar_nT : ndarray, shape (n,)
        Scalar magnetometer reading, compensated (the raw reading's interference changes
        as a line begins), nT.
    vector_nT : ndarray, shape (n, 3)
        Vector magnetometer reading at the same epochs, nT (body frame; only its
        magnitude is used).
    straight : ndarray of bool, shape (n,)
        Epochs on straight lines (survey, tie, validation lines).
    rate_hz : float
        Sample rate, Hz.
    max_lag_s : float
        Largest delay searched, either sign, s.

    Returns
    -------
    TimingLag or None
        None with fewer than 4 straight runs of ``MIN_LINE_S`` whose own best delay lies
        inside the search, when the lines' pooled best delay lies at the search's edge, or
        when the fluxgate explains less than ``MIN_EXPLAINED`` of the scalar's variation
        about a trend along the lines.
    """
    t = np.asarray(time_s, float)
    s = np.asarray(scalar_nT, float)
    f = np.linalg.norm(np.asarray(vector_nT, float), axis=1)
    ok = np.asarray(straight, bool) & np.isfinite(s) & np.isfinite(f)
    # low-passed: the geology's changes stay, the fluxgate's noise above the cut does not
    # (differences or a high-pass would amplify that noise or need long edge margins)
    sos = butter(4, min(GEOLOGY_CUT_HZ, 0.4 * rate_hz), fs=rate_hz, output="sos")
    trim = int(round(LINE_END_S * rate_hz))  # a turn's tail, the filter's edge transient
    lines = _line_records(t, s, f, ok, sos, trim)
    if len(lines) < 4:
        return None
    coarse = np.arange(-max_lag_s, max_lag_s + 1e-9, COARSE_STEP_S)
    edge = max_lag_s - COARSE_STEP_S
    coarse_rss = [_line_rss(*ln, coarse, trim) for ln in lines]  # each line's, once
    lag0 = _argmin_parabola(coarse, sum(coarse_rss))
    if abs(lag0) >= edge:
        return None  # no minimum inside the search: the records do not fix a delay
    # the fluxgate must explain most of the scalar's variation along the lines, else there
    # is too little geology (or too much interference) to time one against the other
    fine0 = lag0 + np.arange(-5 * COARSE_STEP_S, 5 * COARSE_STEP_S + 1e-9, FINE_STEP_S)
    total = sum(_line_rss(*ln, fine0, trim) for ln in lines)
    trend_only = sum(_trend_rss(tt, s_lp, trim) for tt, s_lp, _ in lines)
    if 1.0 - total.min() / trend_only < MIN_EXPLAINED:
        return None
    each = _each_line_lag(lines, coarse, coarse_rss, edge, trim)
    k = len(each)
    if k < 4:
        return None
    # lines are independent replicates, so the interval is Student's over the lines'
    # delays (a jackknife of the pooled minimum is too narrow: the minimum of a sum is not
    # a smooth statistic)
    each = np.asarray(each)
    se = float(np.std(each, ddof=1) / np.sqrt(k))
    lag = float(np.mean(each))
    tq = float(stats.t.ppf(0.975, k - 1))
    p = float(2 * stats.t.sf(abs(lag) / se, k - 1)) if se > 0 else 0.0
    return TimingLag(lag, (lag - tq * se, lag + tq * se), p, k)


def combined_interval(estimates: list) -> tuple[float, float, float] | None:
    """Inverse-variance combination of independent lag estimates.

    Parameters
    ----------
    estimates : list
        Objects with ``lag_s`` and a 95 % interval ``ci95_s`` (s), e.g. :class:`TimingLag`
        and the crossovers' :class:`pipeline.audit.survey.SurveyLag`.

    Returns
    -------
    tuple of float or None
        (lag, low, high), s: the weighted mean and its 95 % interval, each estimate's
        standard error read from its interval's width (normal approximation); None without a
        finite, non-degenerate estimate.
    """
    w, x = [], []
    for e in estimates:
        se = (e.ci95_s[1] - e.ci95_s[0]) / (2 * 1.959964)
        if np.isfinite(e.lag_s) and np.isfinite(se) and se > 0:
            w.append(1.0 / se**2)
            x.append(e.lag_s)
    if not w:
        return None
    lag = float(np.average(x, weights=w))
    half = 1.959964 / float(np.sqrt(np.sum(w)))
    return lag, lag - half, lag + half
