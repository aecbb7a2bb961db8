"""The scalar sensor's white noise, estimated from the recording itself.

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

Hand-written because no library offers a line- and step-robust white-noise level;
:func:`scipy.signal.welch` does the spectral work.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import welch

from pipeline.compensate.filters import contiguous_blocks

SEGMENT_SAMPLES = 128  # Welch segment: 12.8 s at 10 Hz, 64 frequency bins
UPPER_BAND = (0.5, 0.95)  # fractions of the Nyquist frequency holding the white level


def _differenced_spectrum(
    x_nT: np.ndarray, time_s: np.ndarray, rate_hz: float, order: int, segment: int
) -> tuple[np.ndarray, np.ndarray] | None:
    """(f Hz, one-sided density nT^2/Hz) of the ``order``-th difference: Welch's median over
    ``segment``-sample segments in each gap-free block, the blocks weighted by length; None
    when no block holds two segments."""
    x = np.asarray(x_nT, float)
    spectra, weights = [], []
    for b in contiguous_blocks(np.isfinite(x), np.asarray(time_s, float)):
        if b.size < 2 * segment:
            continue
        f, p = welch(np.diff(x[b], order), fs=rate_hz, nperseg=segment, average="median")
        spectra.append(p)
        weights.append(b.size)
    if not spectra:
        return None
    return f, np.average(spectra, axis=0, weights=weights)


def white_noise_nT(x_nT: np.ndarray, time_s: np.ndarray, rate_hz: float) -> float:
    """White-noise standard deviation of a scalar magnetometer record.

    Parameters
    ----------
    x_nT : ndarray
        Total-field samples (nT), raw or compensated; NaN marks missing samples.
    time_s : ndarray
        Their times (s); gaps split the record into blocks analysed separately.
    rate_hz : float
        Nominal sample rate (Hz).

    Returns
    -------
    float
        Per-sample standard deviation (nT) of the white component, or NaN when no block is
        long enough (``2 * SEGMENT_SAMPLES`` samples).

    Notes
    -----
    Structure that is itself broadband at high frequency (interference from attitude jitter
    faster than the sample rate resolves) is indistinguishable from sensor noise by its
    spectrum and raises the estimate; see ``docs`` of the audit.
    """
    got = _differenced_spectrum(x_nT, time_s, rate_hz, 4, SEGMENT_SAMPLES)
    if got is None:
        return float("nan")
    f, p = got
    gain = (2.0 * np.sin(np.pi * f / rate_hz)) ** 8
    nyq = rate_hz / 2.0
    sel = (f >= UPPER_BAND[0] * nyq) & (f <= UPPER_BAND[1] * nyq)
    return float(np.sqrt(np.median(p[sel] / gain[sel]) * nyq))


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
    got = _differenced_spectrum(x_nT, time_s, rate_hz, 2, QUIET_SEGMENT_SAMPLES)
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


@dataclass(frozen=True)
class NoiseFloorBounds:
    """Three upper bounds on the scalar sensor's white noise per sample (nT).

    Attributes
    ----------
    raw_upper_band_nT : float
        The raw record's upper band (:func:`white_noise_nT`).
    upper_band_nT : float
        The upper band of the sensor's own samples less the model's interference.
    quietest_band_nT : float
        The quietest 0.5 Hz band of the same (:func:`quietest_band_noise_nT`).
    """

    raw_upper_band_nT: float
    upper_band_nT: float
    quietest_band_nT: float

    @property
    def sensor_nT(self) -> float:
        """The tightest bound: the scalar sensor's white noise per sample as the audit
        reports it, ``noise_floor_nT`` (NaN when no record is long enough)."""
        b = [self.raw_upper_band_nT, self.upper_band_nT, self.quietest_band_nT]
        return float(np.nanmin(b)) if np.isfinite(b).any() else float("nan")

    @property
    def rise(self) -> float:
        """Upper band over quietest band of the compensated record: ~1 on white noise
        (1.04: the quietest of ~40 band means reads 3-4 % low); well above, the record
        holds broadband interference that rises with frequency, and the floor is then an
        upper bound on the sensor's own noise rather than a measure of it."""
        return self.upper_band_nT / self.quietest_band_nT

    def to_dict(self) -> dict[str, float]:
        return {
            "raw_upper_band_nT": self.raw_upper_band_nT,
            "upper_band_nT": self.upper_band_nT,
            "quietest_band_nT": self.quietest_band_nT,
        }


def noise_floor_bounds(
    raw_nT: np.ndarray,
    compensated_nT: np.ndarray,
    interference_nT: np.ndarray | None,
    time_s: np.ndarray,
    rate_hz: float,
    delay_s: float = 0.0,
) -> NoiseFloorBounds:
    """The three upper bounds on the scalar sensor's white noise.

    The raw record's upper band (:func:`white_noise_nT`), and the upper band and the
    quietest band (:func:`quietest_band_noise_nT`) of the sensor's own samples less the
    model's interference. Compensation removes the jitter interference the vector sensor
    sees but adds that sensor's noise through the regressors, and aliased jitter
    interference rises with frequency, so each bound can be the tightest.

    Parameters
    ----------
    raw_nT : ndarray
        The scalar sensor's samples (nT) at ``time_s``.
    compensated_nT : ndarray
        The model's compensated field (nT) at ``time_s``; with a delay, the stream re-timed
        by ``delay_s`` less the interference.
    interference_nT : ndarray or None
        The model's interference (nT) at ``time_s``; read only with a delay (None without).
    time_s : ndarray
        Epochs (s).
    rate_hz : float
        Nominal sample rate (Hz).
    delay_s : float
        The model's pure delay of the scalar stream (s; 0: none). Re-timing by a fraction
        of a sample interpolates between samples and averages their noise down, so the
        interference is moved back to the sensor's own epochs instead. A deconvolved stream
        (a first-order response) amplifies the noise: an upper bound still, used as it is.

    Returns
    -------
    NoiseFloorBounds
        Each bound a per-sample standard deviation (nT; NaN when no record is long enough).
    """
    own = np.asarray(compensated_nT, float)
    if delay_s:
        if interference_nT is None:
            raise ValueError("a delay model's noise floor needs its interference")
        t = np.asarray(time_s, float)
        i = np.asarray(interference_nT, float)
        ok = np.isfinite(i)
        own = np.asarray(raw_nT, float) - np.interp(
            t - delay_s, t[ok], i[ok], left=np.nan, right=np.nan
        )
    return NoiseFloorBounds(
        white_noise_nT(raw_nT, time_s, rate_hz),
        white_noise_nT(own, time_s, rate_hz),
        quietest_band_noise_nT(own, time_s, rate_hz),
    )
