"""Zero-phase Butterworth band-pass of contiguous blocks."""

from __future__ import annotations

import numpy as np
from scipy.signal import butter, sosfiltfilt


def bandpass_sos(band_hz: tuple[float, float], fs_hz: float, poles: int) -> np.ndarray:
    """Second-order sections of a Butterworth band-pass.

    ``poles`` is the order of the low-pass prototype (as in MagNav.jl's ``pole``): the
    band-pass has 2 x poles poles. The edges are normalised by the actual sample rate, so a
    recording at 20 Hz gets the same 0.1-0.9 Hz band as one at 10 Hz; an upper edge at or
    above Nyquist is an error.
    """
    lo, hi = band_hz
    nyq = fs_hz / 2.0
    if not 0 < lo < hi < nyq:
        raise ValueError(
            f"band {lo}-{hi} Hz does not fit below the Nyquist frequency "
            f"{nyq:.3g} Hz of a {fs_hz:.3g} Hz recording"
        )
    return butter(poles, [lo / nyq, hi / nyq], btype="bandpass", output="sos")


def contiguous_blocks(
    mask: np.ndarray, time_s: np.ndarray, gap_factor: float = 3.0
) -> list[np.ndarray]:
    """Index arrays of the runs of ``mask``, also split where sampling has a gap."""
    idx = np.flatnonzero(mask)
    if idx.size == 0:
        return []
    dt = np.median(np.diff(time_s))
    breaks = (np.diff(idx) > 1) | (np.diff(time_s[idx]) > gap_factor * dt)
    return np.split(idx, np.flatnonzero(breaks) + 1)


def trim_samples(trim_s: float, rate_hz: float) -> int:
    """Samples in ``trim_s`` seconds at ``rate_hz`` (nearest): the edge a filtered block loses."""
    return int(round(trim_s * rate_hz))


def bandpass_blocks(
    x: np.ndarray, blocks: list[np.ndarray], sos: np.ndarray, trim: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Band-pass ``x`` (n,) or (n, k) within each block; drop ``trim`` samples at both ends.

    Returns the filtered rows and their epoch indices. Blocks too short to filter after
    trimming are skipped.
    """
    out, where = [], []
    pad = 3 * (2 * sos.shape[0] + 1)  # sosfiltfilt's default padding
    for ix in blocks:
        if ix.size <= max(2 * trim, pad) + 1:
            continue
        y = sosfiltfilt(sos, x[ix], axis=0)
        keep = slice(trim, ix.size - trim) if trim else slice(None)
        out.append(y[keep])
        where.append(ix[keep])
    if not out:
        shape = (0,) + np.shape(x)[1:]
        return np.zeros(shape), np.zeros(0, int)
    return np.concatenate(out), np.concatenate(where)
