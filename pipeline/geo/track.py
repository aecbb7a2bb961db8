"""The flight's track with the GNSS receiver's sample-to-sample noise smoothed out.

A magnetic gradient turns position noise into field noise: 0.5 m of receiver noise under a
0.45 nT/m gradient is 0.2 nT per sample, in the compensation band, larger than a good
carrier's residual. The track itself is smooth at those frequencies (an aircraft's position
has two integrations of bounded accelerations behind it), so a penalised spline separates the
two. Its smoothing is chosen by cross-validation, so a receiver that is
already quiet is left as it is, and no noise level has to be known or assumed.

The spline is the natural cubic smoothing spline (the minimiser of the squared misfit plus
``lam`` times the integrated squared second derivative), the same minimiser as scipy's
:func:`~scipy.interpolate.make_smoothing_spline`, solved in Reinsch's form (Green & Silverman,
*Nonparametric Regression and Generalized Linear Models*, 1994, sec. 2.3): one banded
symmetric system in the knots' second derivatives. It is written out here because scipy's
builds its banded system in a Python loop over the samples, some 70 times slower on a
flight's track (0.36 s against 5 ms for 22 000 samples), and the choice of the smoothing fits
hundreds of windows. scipy's own GCV choice costs about forty fits of the whole record; here
the smoothing is chosen by two-fold cross-validation on a few windows spread over the record
(the choice depends on the noise level and the track's roughness, which the windows sample),
and the whole record is then fitted once with it.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import solveh_banded
from scipy.optimize import minimize_scalar

# samples per window on which the smoothing is chosen: at 5-10 Hz, 60-120 s of track
CV_WINDOW = 600
# log10 of the smoothing searched (values normalised to unit spread; s^3): from
# interpolating every sample to a straight line through the window
LOG_LAMBDA_RANGE = (-8.0, 10.0)
# windows on which the smoothing is chosen: those where the track bends most, and the least
# smoothing of theirs is used, so turns and manoeuvres are followed (a straight, steady leg
# would ask for a straight line)
CV_WINDOWS = 2
# span of the means whose second differences rate a window's bending, s: longer than the
# receiver's sample interval, so its noise does not rate a window
BEND_SPAN_S = 1.0
# a gap longer than this many median sample intervals splits the track: the spline does not
# bridge an outage
GAP_FACTOR = 5.0


def smoothing_lambda(time_s: np.ndarray, values: np.ndarray) -> float:
    """The spline's smoothing for one coordinate, by two-fold cross-validation on windows of
    the record.

    The record is cut into windows; those where the track bends most (the largest
    accelerations of its one-second means) are used. Each one's even samples predict its odd
    ones and the reverse; the smoothing with the least prediction error is taken (a coarse
    logarithmic scan, then Brent's method about its best point), and the least of the
    windows' choices is used.

    Parameters
    ----------
    time_s : ndarray
        Strictly increasing sample times, s.
    values : ndarray
        One coordinate at those times (any unit: the choice does not depend on it).

    Returns
    -------
    float
        The smoothing parameter of :func:`smoothing_spline` for the
        record's own sample rate (its penalty weighs a sum over samples, so a window's choice
        holds for the whole record at the same rate).
    """
    n = time_s.size
    width = min(n, CV_WINDOW)
    starts = np.arange(0, n - width + 1, width)
    bend = [_bending(time_s[a : a + width], values[a : a + width]) for a in starts]
    chosen = starts[np.argsort(bend)[::-1][:CV_WINDOWS]]
    logs = [_window_log_lambda(time_s[a : a + width], values[a : a + width]) for a in chosen]
    # half the samples carry half the misfit against the same penalty: double for the record
    return 2.0 * 10.0 ** float(np.min(logs))


def _bending(time_s: np.ndarray, values: np.ndarray) -> float:
    """How much a window's track bends: the 90th percentile of the absolute second
    differences of its ``BEND_SPAN_S`` means, per s^2."""
    step = float(np.median(np.diff(time_s)))
    m = max(1, int(round(BEND_SPAN_S / step)))
    k = values.size // m
    if k < 3:
        return 0.0
    means = values[: k * m].reshape(k, m).mean(axis=1)
    return float(np.percentile(np.abs(np.diff(means, 2)), 90)) / (m * step) ** 2


def _window_log_lambda(time_s: np.ndarray, values: np.ndarray) -> float:
    """log10 of the smoothing that best predicts each half of a window from the other."""
    halves = ((slice(0, None, 2), slice(1, None, 2)), (slice(1, None, 2), slice(0, None, 2)))
    scale = float(np.std(values)) or 1.0
    y = (values - values.mean()) / scale

    def cv(log_lam: float) -> float:
        err = 0.0
        for fit, test in halves:
            spline = smoothing_spline(time_s[fit], y[fit], 10.0**log_lam)
            err += float(np.sum((y[test] - spline(time_s[test])) ** 2))
        return err

    grid = np.arange(LOG_LAMBDA_RANGE[0], LOG_LAMBDA_RANGE[1] + 1.0, 2.0)
    best = grid[int(np.argmin([cv(g) for g in grid]))]
    got = minimize_scalar(
        cv, bounds=(best - 2.0, best + 2.0), method="bounded", options={"xatol": 0.05}
    )
    # the smoothing does not depend on the values' scale: misfit and penalty scale alike
    return float(got.x)


def smooth_track(
    time_s: np.ndarray, coords: np.ndarray, at_s: np.ndarray, *, gap_factor: float = GAP_FACTOR
) -> np.ndarray:
    """Smoothed positions at chosen times.

    Parameters
    ----------
    time_s : ndarray, shape (n,)
        The receiver's sample times, s, strictly increasing.
    coords : ndarray, shape (n, k)
        Its positions, one column per coordinate (latitude and longitude in degrees and
        altitude in metres, or local east/north/up metres; each column is smoothed on its
        own, which over a survey's extent is the same as smoothing in a metric frame).
    at_s : ndarray, shape (m,)
        Times to evaluate at, s.
    gap_factor : float
        A gap longer than this many median sample intervals splits the track.

    Returns
    -------
    ndarray, shape (m, k)
        Smoothed positions; NaN outside the track's pieces (before, after, in a gap).
    """
    time_s = np.asarray(time_s, float)
    coords = np.asarray(coords, float).reshape(time_s.size, -1)
    out = np.full((np.size(at_s), coords.shape[1]), np.nan)
    if time_s.size < 8:
        return out
    step = float(np.median(np.diff(time_s)))
    cuts = np.flatnonzero(np.diff(time_s) > gap_factor * step) + 1
    pieces = [p for p in np.split(np.arange(time_s.size), cuts) if p.size >= 8]
    longest = max(pieces, key=len)
    for k in range(coords.shape[1]):
        lam = smoothing_lambda(time_s[longest], coords[longest, k])
        for p in pieces:
            spline = smoothing_spline(time_s[p], coords[p, k], lam)
            inside = (at_s >= time_s[p[0]]) & (at_s <= time_s[p[-1]])
            out[inside, k] = spline(at_s[inside])
    return out


def smoothing_spline(x: np.ndarray, y: np.ndarray, lam: float):
    """The natural cubic smoothing spline of ``y`` at ``x``: the curve g minimising
    sum (y_i - g(x_i))^2 + ``lam`` * integral g''(u)^2 du (Reinsch's form, see the module
    docstring), as a function evaluating g (inside [x[0], x[-1]]; the end pieces' cubics
    continued outside).

    Parameters
    ----------
    x : ndarray, shape (n,)
        Strictly increasing abscissae (here times, s), n >= 5.
    y : ndarray, shape (n,)
        Values at ``x`` (any unit).
    lam : float
        Smoothing, >= 0 (units of y^2 x^3 / y^2: the penalty's weight against the misfit).

    Raises
    ------
    ValueError
        Fewer than 5 abscissae, or not strictly increasing.
    """
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    n = x.size
    h = np.diff(x)
    if n < 5 or not np.all(h > 0):
        raise ValueError("a smoothing spline needs 5 or more strictly increasing abscissae")
    ih = 1.0 / h
    # Q (n x n-2), the second divided differences: column j holds q0, q1, q2 in rows j..j+2
    q0, q1, q2 = ih[:-1], -(ih[:-1] + ih[1:]), ih[1:]
    # R + lam Q'Q in the upper banded storage of solveh_banded (R: the penalty's tridiagonal
    # Gram matrix of the interior knots' second derivatives)
    ab = np.zeros((3, n - 2))
    ab[2] = (h[:-1] + h[1:]) / 3.0 + lam * (q0**2 + q1**2 + q2**2)
    ab[1, 1:] = h[1:-1] / 6.0 + lam * (q1[:-1] * q0[1:] + q2[:-1] * q1[1:])
    ab[0, 2:] = lam * q2[:-2] * q0[2:]
    gamma = solveh_banded(ab, q0 * y[:-2] + q1 * y[1:-1] + q2 * y[2:])
    q_gamma = np.zeros(n)
    q_gamma[:-2] += q0 * gamma
    q_gamma[1:-1] += q1 * gamma
    q_gamma[2:] += q2 * gamma
    f = y - lam * q_gamma  # the spline at the knots
    m = np.r_[0.0, gamma, 0.0]  # its second derivative there (natural ends)

    def spline(at: np.ndarray) -> np.ndarray:
        t = np.asarray(at, float)
        i = np.clip(np.searchsorted(x, t, side="right") - 1, 0, n - 2)
        hi, a, b = h[i], x[i + 1] - t, t - x[i]
        return (m[i] * a**3 + m[i + 1] * b**3) / (6.0 * hi) + (
            (f[i] / hi - m[i] * hi / 6.0) * a + (f[i + 1] / hi - m[i + 1] * hi / 6.0) * b
        )

    return spline
