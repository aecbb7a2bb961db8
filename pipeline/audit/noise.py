"""The audit's noise floor: three upper bounds on the scalar sensor's white noise per sample,
from the estimator's one home :mod:`pipeline.noise` (the upper band of the raw and of the
compensated record, and the quietest band of the compensated one)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.noise import quietest_band_noise_nT, white_noise_nT


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
        white_noise_nT(raw_nT, time_s),
        white_noise_nT(own, time_s),
        quietest_band_noise_nT(own, time_s, rate_hz),
    )
