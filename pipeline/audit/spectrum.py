"""The shape of a held-out residual's spectrum inside the fit band."""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.signal import welch

# a line stands this many times above the band's median power: far beyond the scatter of a
# Welch estimate's bins (chi-square with about 2 x segments degrees of freedom)
LINE_RATIO = 8.0
# Welch segment (samples): 51 s at 10 Hz resolves a 0.1 Hz line from the band's lower edge
WELCH_SEGMENT = 512


def residual_spectrum(residual: np.ndarray, rate_hz: float, band) -> dict[str, Any]:
    """Name the shape of the held-out residual's spectrum inside the fit band.

    White noise through the band-pass has the filter's flat pass band; a line (an
    oscillation the model lacks) stands far above the band's median level; coloured noise
    has a slope in log power vs log frequency. Returns kind (white | line | coloured), the
    dominant frequency (Hz), the peak-to-median power ratio, the log-log slope and a
    sentence.
    """
    r = np.asarray(residual, float)
    r = r[np.isfinite(r)]
    if r.size < 64:
        return {
            "kind": "unknown",
            "dominant_frequency_hz": None,
            "peak_ratio": None,
            "slope": None,
            "description": "too few samples",
        }
    f, pxx = welch(r, fs=rate_hz, nperseg=min(WELCH_SEGMENT, r.size))
    lo, hi = band.band_hz
    inside = (f >= lo * 1.5) & (f <= hi / 1.1)  # the flat part of the pass band
    if inside.sum() < 4:
        inside = (f >= lo) & (f <= hi)
    fi, pi = f[inside], pxx[inside]
    k = int(np.argmax(pi))
    ratio = float(pi[k] / np.median(pi))
    slope = float(np.polyfit(np.log(fi), np.log(pi), 1)[0])
    if ratio > LINE_RATIO:
        kind, text = "line", f"a line at {fi[k]:.3f} Hz ({ratio:.0f}x the band's median power)"
    elif abs(slope) > 1.0:
        kind, text = (
            "coloured",
            (f"coloured noise (power ~ f^{slope:.1f} in the band; white noise would be flat)"),
        )
    else:
        kind, text = "white", "flat in the band, like white noise"
    return {
        "kind": kind,
        "dominant_frequency_hz": float(fi[k]),
        "peak_ratio": ratio,
        "slope": slope,
        "description": text,
    }


def manoeuvre_line(vector_nT: np.ndarray, rate_hz: float, frequency_hz: float, band) -> bool:
    """Whether the manoeuvres drive the field at ``frequency_hz``: some body-frame vector
    component (x forward, y right, z down; nT, the calibration's samples) has a line
    (:data:`LINE_RATIO` above its band median) within one Welch bin of it. A residual line
    there is the carrier's response to the attitude that the model lacks, not an event.
    """
    v = np.asarray(vector_nT, float)
    v = v[np.all(np.isfinite(v), axis=1)]
    if v.shape[0] < 64:
        return False
    f, pxx = welch(v, fs=rate_hz, nperseg=min(WELCH_SEGMENT, v.shape[0]), axis=0)
    lo, hi = band.band_hz
    inside = (f >= lo) & (f <= hi)
    near = inside & (np.abs(f - frequency_hz) <= (f[1] - f[0]) * 1.01)
    if not near.any():
        return False
    med = np.median(pxx[inside], axis=0)
    return bool(np.any(pxx[near].max(axis=0) > LINE_RATIO * med))
