"""White noise, estimated from the record itself: the one home of the estimator.

A magnetometer's own noise is white; everything else in a flight record is not: the anomaly
field and the carrier's interference are concentrated at low frequencies, steps (a current
switching) are rare events, vibration shows as narrow spectral lines. The estimator exploits
each difference:

1. the 4th difference removes the smooth part (geology, manoeuvre-driven interference) and
   its exact gain ``|2 sin(pi f / fs)|**8`` is divided out again, so the estimate is a power
   spectral density of the record *as if* it had not been differenced (no window leakage from
   the strong low-frequency content);
2. Welch's periodograms are combined by their **median** over segments, so segments holding a
   step or a manoeuvre-residual burst do not count;
3. the white level is the **median** over the upper half of the band, so a spectral line
   (vibration aliased into the band) does not count either.

``sigma = sqrt(P_white * fs / 2)`` for a one-sided density ``P_white`` in nT^2/Hz.

Interference that is broadband at the sample rate (attitude jitter faster than it resolves)
passes all three. It rises with frequency, though, so the quietest 0.5 Hz band of a
compensated record (:func:`quietest_band_noise_nT`) is a second, often tighter upper bound.

Every stage that needs a white-noise level (despike, map, quality, navigation, the audit) calls
:func:`white_noise_nT`; why this estimator and not the median absolute 4th difference is in
its notes. Hand-written because no library offers a line- and step-robust white-noise level;
:func:`scipy.signal.welch` does the spectral work.
"""

from __future__ import annotations

import numpy as np
from scipy.signal import welch

from pipeline.compensate.filters import contiguous_blocks

SEGMENT_SAMPLES = 128  # Welch segment: 12.8 s at 10 Hz, 64 frequency bins
MIN_SEGMENT_SAMPLES = 16  # on records too short for 128: 9 bins, 4 of them in the upper band
UPPER_BAND = (0.5, 0.95)  # fractions of the Nyquist frequency holding the white level


def sample_blocks(x_nT: np.ndarray, time_s: np.ndarray | None = None) -> list[np.ndarray]:
    """Index arrays of the runs of finite samples, also split at sampling gaps when the times
    are given (a difference is never taken across a missing sample or a gap)."""
    finite = np.isfinite(np.asarray(x_nT, float))
    if time_s is not None:
        return contiguous_blocks(finite, np.asarray(time_s, float))
    idx = np.flatnonzero(finite)
    return np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1) if idx.size else []


def _differenced_spectrum(
    x_nT: np.ndarray, blocks: list[np.ndarray], rate_hz: float, order: int, segment: int
) -> tuple[np.ndarray, np.ndarray] | None:
    """(f Hz, one-sided density nT^2/Hz) of the ``order``-th difference: Welch's median over
    ``segment``-sample segments in each block, the blocks weighted by length; None when no
    block holds two segments."""
    x = np.asarray(x_nT, float)
    spectra, weights = [], []
    for b in blocks:
        if b.size < 2 * segment:
            continue
        f, p = welch(np.diff(x[b], order), fs=rate_hz, nperseg=segment, average="median")
        spectra.append(p)
        weights.append(b.size)
    if not spectra:
        return None
    return f, np.average(spectra, axis=0, weights=weights)


def white_noise_nT(x_nT: np.ndarray, time_s: np.ndarray | None = None) -> float:
    """White-noise standard deviation per sample of a record: the one estimator of it.

    Despiking, the map (sensor and grid noise), quality (per line), navigation (the map's
    and the sensor's noise) and the audit (the noise floor) all call this one.

    Parameters
    ----------
    x_nT : ndarray
        Samples (nT) in order along time or along a grid lane, raw or compensated; NaN marks
        missing samples.
    time_s : ndarray, optional
        Their times (s); sampling gaps split the record into blocks analysed separately.
        Without, only NaN samples split it (grid lanes, a line's samples).

    Returns
    -------
    float
        Per-sample standard deviation (nT) of the white component, or NaN when no block is
        long enough (``2 * MIN_SEGMENT_SAMPLES`` samples). The sample rate does not enter:
        the level is per sample, the band a fraction of the Nyquist frequency.

    Notes
    -----
    Why this estimator: on white noise plus a smooth signal (geology at 30 m/s and
    manoeuvre interference at 0.08-0.5 Hz, ``benchmarks/bench_white_noise.py``) its bias is
    within 1 % at 5-50 Hz and +13 % at 2 Hz, against +32 % at 5 Hz and x24 at 2 Hz for the
    median absolute 4th difference the other stages used, whose d4 still holds the signal
    where the rate is low; both read within 1 % at 10 Hz and above. Sparse spikes it counts
    as noise (+12 % with one 20-sigma spike per 500 samples, the median difference +1 %):
    a spike is as broadband as noise, so despiking reports the level of its repaired record.

    Structure that is itself broadband at high frequency (interference from attitude jitter
    faster than the sample rate resolves) is indistinguishable from sensor noise by its
    spectrum and raises the estimate (see :func:`quietest_band_noise_nT`).

    The segment is the longest power of two up to ``SEGMENT_SAMPLES`` that the longest
    block holds twice; blocks shorter than two segments are left out.
    """
    blocks = sample_blocks(x_nT, time_s)
    longest = max((b.size for b in blocks), default=0)
    segment = SEGMENT_SAMPLES
    while segment > MIN_SEGMENT_SAMPLES and 2 * segment > longest:
        segment //= 2
    got = _differenced_spectrum(x_nT, blocks, 1.0, 4, segment)  # per sample: fs = 1
    if got is None:
        return float("nan")
    f, p = got
    gain = (2.0 * np.sin(np.pi * f)) ** 8
    sel = (f >= UPPER_BAND[0] * 0.5) & (f <= UPPER_BAND[1] * 0.5)
    return float(np.sqrt(np.median(p[sel] / gain[sel]) * 0.5))


QUIET_SEGMENT_SAMPLES = 256  # finer bins for the quietest band: 25.6 s at 10 Hz
QUIET_BAND_HZ = 0.5  # width of the band the level is averaged over
QUIET_LOWEST_HZ = 0.1  # below: geology along the lines and the flight's slow drifts


def quietest_band_noise_nT(x_nT: np.ndarray, time_s: np.ndarray, rate_hz: float) -> float:
    """White-noise level of the quietest 0.5 Hz band of a (compensated) record.

    Interference from attitude jitter faster than the sample rate resolves is broadband
    after aliasing but not flat: eddy currents follow the rate of turn, so it rises with
    frequency, and in a compensated record its resolvable part is gone below ~1.5 Hz. The
    quietest band is then the tightest upper bound on the sensor's own white noise the
    record offers.

    Parameters
    ----------
    x_nT : ndarray
        Total-field samples (nT), best compensated; NaN marks missing samples.
    time_s : ndarray
        Their times (s); gaps split the record into blocks analysed separately.
    rate_hz : float
        Nominal sample rate (Hz).

    Returns
    -------
    float
        Per-sample standard deviation (nT): the band's mean density of the 2nd difference,
        gain divided out (Welch median over 25.6 s segments); NaN when no block is long
        enough. On white noise it reads 3-4 % low (the least of ~40 band means).
    """
    blocks = sample_blocks(x_nT, time_s)
    got = _differenced_spectrum(x_nT, blocks, rate_hz, 2, QUIET_SEGMENT_SAMPLES)
    if got is None:
        return float("nan")
    f, p = got
    inside = (f >= QUIET_LOWEST_HZ) & (f <= UPPER_BAND[1] * rate_hz / 2.0)
    density = p[inside] / (2.0 * np.sin(np.pi * f[inside] / rate_hz)) ** 4
    k = max(1, int(round(QUIET_BAND_HZ / (f[1] - f[0]))))
    if density.size < k:
        return float("nan")
    means = np.convolve(density, np.ones(k) / k, mode="valid")  # every band of width k
    return float(np.sqrt(means.min() * rate_hz / 2.0))
