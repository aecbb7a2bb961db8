"""The shape of a held-out residual's spectrum inside the fit band."""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.signal import coherence, welch

# a line stands this many times above the band's median power: far beyond the scatter of a
# Welch estimate's bins (chi-square with about 2 x segments degrees of freedom)
LINE_RATIO = 8.0
# Welch segment: 51 s resolves a 0.1 Hz line from the band's lower edge
WELCH_SEGMENT_S = 51.2


def _segment(rate_hz: float, n: int) -> int:
    return int(min(n, max(64, round(WELCH_SEGMENT_S * rate_hz))))


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
    f, pxx = welch(r, fs=rate_hz, nperseg=_segment(rate_hz, r.size))
    lo, hi = band.band_hz
    inside = (f >= lo * 1.5) & (f <= hi / 1.1)  # the flat part of the pass band
    if inside.sum() < 4:
        inside = (f >= lo) & (f <= hi)
    fi, pi = f[inside], pxx[inside]
    k = int(np.argmax(pi))
    ratio = float(pi[k] / np.median(pi))
    slope = float(np.polyfit(np.log(fi), np.log(pi), 1)[0])
    # the line's own power: its bins (the peak and the window's two neighbours) above the
    # band's median level, integrated over frequency
    df = float(f[1] - f[0])
    near = np.abs(fi - fi[k]) <= 1.5 * df
    line_var = float(np.sum(np.clip(pi[near] - np.median(pi), 0.0, None)) * df)
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
        "line_rms_nT": float(np.sqrt(line_var)) if kind == "line" else None,
    }


def periodic_nuisance(spectrum: dict[str, Any], heldout_rms_nT: float) -> dict[str, Any]:
    """A residual line not coherent with the attitude as a nuisance of the null model.

    A periodic interference that no channel records (a switching current, a pump, a gimbal)
    lasts through the flight: it is the carrier's physics outside the model's forms, not an
    event localised in time. Its held-out gain is the fraction of the held-out residual
    RMS (nT) that taking the line out would remove.

    Parameters
    ----------
    spectrum : dict
        :func:`residual_spectrum` of the held-out residual, of kind ``line``.
    heldout_rms_nT : float
        The held-out residual's RMS (nT).

    Returns
    -------
    dict
        ``{"name": "unrecorded_current", "heldout_gain", "estimate": {"frequency_hz",
        "rms_nT"}}`` (``unexplained.nuisances``'s record).
    """
    line = float(spectrum.get("line_rms_nT") or 0.0)
    share = min(1.0, (line / heldout_rms_nT) ** 2) if heldout_rms_nT > 0 else 0.0
    return {
        "name": "unrecorded_current",
        "heldout_gain": float(1.0 - np.sqrt(1.0 - share)),
        "estimate": {"frequency_hz": spectrum["dominant_frequency_hz"], "rms_nT": line},
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
    seg = _segment(rate_hz, r.size)
    k = r.size // seg
    if k < 3:
        return False
    level = 1.0 - alpha ** (1.0 / (k - 1))
    for i in range(3):
        f, coh = coherence(r, v[:, i], fs=rate_hz, nperseg=seg)
        if coh[int(np.argmin(np.abs(f - frequency_hz)))] > level:
            return True
    return False
