"""The shape of a held-out residual's spectrum inside the fit band."""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.signal import coherence, welch

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


def manoeuvre_line(
    residual: np.ndarray, vector_nT: np.ndarray, rate_hz: float, frequency_hz: float, alpha: float
) -> bool:
    """Whether a residual line at ``frequency_hz`` is the carrier's response to the attitude:
    the residual (nT) is coherent there with some body-frame vector component (x forward,
    y right, z down; nT, the same rows) beyond the coherence a pair of independent series
    reaches with probability ``alpha`` over the Welch segments (1 - alpha^(1/(K-1)), K
    non-overlapping segments). Such a line is interference outside the model's forms, not an
    event; an oscillation of its own (a gimbal, a pump) is not coherent with the attitude.
    """
    r = np.asarray(residual, float)
    v = np.asarray(vector_nT, float)
    ok = np.isfinite(r) & np.all(np.isfinite(v), axis=1)
    r, v = r[ok], v[ok]
    seg = min(WELCH_SEGMENT, r.size)
    k = r.size // seg
    if k < 3:
        return False
    level = 1.0 - alpha ** (1.0 / (k - 1))
    for i in range(3):
        f, coh = coherence(r, v[:, i], fs=rate_hz, nperseg=seg)
        if coh[int(np.argmin(np.abs(f - frequency_hz)))] > level:
            return True
    return False
