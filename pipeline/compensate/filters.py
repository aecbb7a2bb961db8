"""Zero-phase Butterworth band-pass of contiguous blocks."""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy.signal import butter, sosfilt, sosfilt_zi


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
    return _butter_bandpass(float(lo) / nyq, float(hi) / nyq, int(poles)).copy()


# a flight's fits design the same filter hundreds of times (each fold, model and scan): the
# design and its initial state are computed once per band
@lru_cache(maxsize=32)
def _butter_bandpass(lo: float, hi: float, poles: int) -> np.ndarray:
    return butter(poles, [lo, hi], btype="bandpass", output="sos")  # callers get copies


@lru_cache(maxsize=32)
def _steady_state(key: bytes, n_sections: int) -> np.ndarray:
    zi = sosfilt_zi(np.frombuffer(key).reshape(n_sections, 6))
    zi.flags.writeable = False
    return zi


def filtfilt_sos(sos: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Zero-phase filtering of ``x`` (n,) or (n, k) along its first axis: the steps of
    :func:`scipy.signal.sosfiltfilt` with its defaults (odd extension of three times the
    filter's taps, each pass started in the steady state of its first sample), with the
    steady state computed once per filter instead of per call (it is most of the cost of
    filtering a short block). Raises ValueError when ``x`` is not longer than the padding."""
    sos = np.asarray(sos, float)
    ns = sos.shape[0]
    ntaps = 2 * ns + 1 - min(int(np.sum(sos[:, 2] == 0)), int(np.sum(sos[:, 5] == 0)))
    edge = 3 * ntaps
    x = np.asarray(x, float)
    if x.shape[0] <= edge:
        raise ValueError(f"the input must be longer than {edge} samples")
    # each column a row of a C-ordered array, filtered along its last axis: sosfilt's
    # working copy is then a plain copy, not a transpose (the same numbers either way)
    xt = x.reshape(x.shape[0], -1).T
    ext = np.concatenate(
        (2 * xt[:, :1] - xt[:, edge:0:-1], xt, 2 * xt[:, -1:] - xt[:, -2 : -(edge + 2) : -1]),
        axis=1,
    )
    zi = _steady_state(np.ascontiguousarray(sos).tobytes(), ns)[:, None, :]
    y, _ = sosfilt(sos, ext, axis=-1, zi=zi * ext[None, :, :1])
    y, _ = sosfilt(sos, y[:, ::-1], axis=-1, zi=zi * y[None, :, -1:])
    return np.ascontiguousarray(y[:, ::-1][:, edge:-edge].T).reshape(x.shape)


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
        y = filtfilt_sos(sos, x[ix])
        keep = slice(trim, ix.size - trim) if trim else slice(None)
        out.append(y[keep])
        where.append(ix[keep])
    if not out:
        shape = (0,) + np.shape(x)[1:]
        return np.zeros(shape), np.zeros(0, int)
    return np.concatenate(out), np.concatenate(where)
