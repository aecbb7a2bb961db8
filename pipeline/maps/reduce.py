"""Reduction of the compensated field to the crustal anomaly."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import UTC, datetime

import numpy as np

from pipeline.geo.igrf import igrf_ned_nT, spaced_epochs

# the main field's gradient changes over hundreds of km: evaluated every 10 s of flight
# (a few hundred metres) and interpolated, it is exact to far below 1e-6 nT/m
GRADIENT_SPACING_S = 10.0


@dataclass
class Reduction:
    """The reduced field (:func:`reduce_to_anomaly`), per sample.

    Attributes
    ----------
    anomaly_nT : ndarray
        Compensated field - IGRF - diurnal, nT.
    igrf_nT : ndarray
        IGRF total field, nT.
    diurnal_nT : ndarray or None
        Smoothed base-station reading minus its mean, nT (None without a base station).
    lag_s : float
        Sensor lag the compensated stream was shifted by, s.
    """

    anomaly_nT: np.ndarray
    igrf_nT: np.ndarray
    diurnal_nT: np.ndarray | None
    lag_s: float


def igrf_total_nT(
    time_ns: np.ndarray,
    lat_deg: np.ndarray,
    lon_deg: np.ndarray,
    alt_m: np.ndarray,
    spacing_s: float = 1.0,
) -> np.ndarray:
    """IGRF total field at each sample (position, ellipsoidal height, date).

    ppigrf is evaluated every ``spacing_s`` of time (:func:`pipeline.geo.igrf.spaced_epochs`)
    and interpolated in time: the main field is linear to far below 0.01 nT over the ground a
    second of flight covers (it changes by a few nT per km). The last
    few results are kept by the inputs' content: the audit, the map, the quality and the
    navigation stages all reduce the same flight (~0.3 s a call at 5 h); a copy is returned.
    """
    import hashlib

    h = hashlib.blake2b(str(spacing_s).encode(), digest_size=16)
    for a in (time_ns, lat_deg, lon_deg, alt_m):
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.view(np.uint8) if a.size else b"")
    key = h.digest()
    hit = _IGRF_KEPT.get(key)
    if hit is None:
        hit = _igrf_total_nT(time_ns, lat_deg, lon_deg, alt_m, spacing_s)
        _IGRF_KEPT[key] = hit
        while len(_IGRF_KEPT) > 2:
            _IGRF_KEPT.pop(next(iter(_IGRF_KEPT)))
    return hit.copy()


_IGRF_KEPT: dict[bytes, np.ndarray] = {}


def igrf_total_gradient_nT_per_m(
    time_ns: np.ndarray,
    lat_deg: np.ndarray,
    lon_deg: np.ndarray,
    alt_m: np.ndarray,
    step_m: float = 1000.0,
) -> np.ndarray:
    """Gradient of the IGRF total field at each sample, (n, 3): d/d north, east, up, nT/m.

    Central differences over ``step_m`` either side (the main field's curvature changes the
    gradient over hundreds of km, so 1 km steps are exact to far below 1e-3 nT/km), each side
    evaluated as :func:`igrf_total_nT` (every ``GRADIENT_SPACING_S``, interpolated in time). The
    navigation filters' core-field Jacobian (MagNav's ``igrf_grad``).
    """
    lat = np.asarray(lat_deg, float)
    lon = np.asarray(lon_deg, float)
    alt = np.asarray(alt_m, float)
    r = 6_371_000.0 + alt
    dlat = np.degrees(step_m / r)
    dlon = np.degrees(step_m / (r * np.cos(np.radians(lat))))

    def diff(lat_a, lon_a, alt_a, lat_b, lon_b, alt_b):
        hi = _igrf_total_nT(time_ns, lat_a, lon_a, alt_a, GRADIENT_SPACING_S)
        lo = _igrf_total_nT(time_ns, lat_b, lon_b, alt_b, GRADIENT_SPACING_S)
        return (hi - lo) / (2.0 * step_m)

    return np.column_stack(
        [
            diff(lat + dlat, lon, alt, lat - dlat, lon, alt),
            diff(lat, lon + dlon, alt, lat, lon - dlon, alt),
            diff(lat, lon, alt + step_m, lat, lon, alt - step_m),
        ]
    )


def _igrf_total_nT(time_ns, lat_deg, lon_deg, alt_m, spacing_s: float) -> np.ndarray:
    """:func:`igrf_total_nT`, computed (nT)."""
    ok = np.flatnonzero(np.isfinite(lat_deg) & np.isfinite(lon_deg) & np.isfinite(alt_m))
    out = np.full(time_ns.size, np.nan)
    if ok.size == 0:
        return out
    t = (time_ns - time_ns[0]) / 1e9
    pick = spaced_epochs(t, ok, spacing_s)
    when = datetime.fromtimestamp(int(np.median(time_ns[ok])) / 1e9, tz=UTC)
    b = igrf_ned_nT(lat_deg[pick], lon_deg[pick], alt_m[pick], when)
    tot = np.linalg.norm(b, axis=1)
    out[ok] = np.interp(t[ok], t[pick], tot)
    return out


def time_window_mean(time_s: np.ndarray, x: np.ndarray, window_s: float) -> np.ndarray:
    """Centred running mean over ``window_s`` of time (irregular sampling and NaNs allowed)."""
    x = np.asarray(x, float)
    ok = np.isfinite(x)
    if window_s <= 0 or ok.sum() < 2:
        return x.copy()
    tk, xk = time_s[ok], x[ok]
    csum = np.r_[0.0, np.cumsum(xk)]
    lo = np.searchsorted(tk, time_s - window_s / 2, side="left")
    hi = np.searchsorted(tk, time_s + window_s / 2, side="right")
    out = np.full(x.size, np.nan)
    has = hi > lo
    out[has] = (csum[hi[has]] - csum[lo[has]]) / (hi[has] - lo[has])
    out[~ok] = np.nan
    return out


# Base-station readings are smoothed over this window before they are subtracted: the diurnal
# varies over minutes to hours, the base magnetometer's noise does not, and unsmoothed it adds
# its whole noise to every reduced sample (0.05 nT at 1 Hz doubles a 0.05 nT CPT's noise in
# crossover and overlap differences).
BASE_SMOOTHING_S = 60.0


def reduce_to_anomaly(
    time_ns: np.ndarray,
    compensated_nT: np.ndarray,
    lat_deg: np.ndarray,
    lon_deg: np.ndarray,
    alt_m: np.ndarray,
    base_nT: np.ndarray | None = None,
    lag_s: float = 0.0,
    base_smoothing_s: float = BASE_SMOOTHING_S,
) -> Reduction:
    """anomaly = compensated - IGRF - diurnal.

    The diurnal is the base-station reading, smoothed over ``base_smoothing_s``, minus its
    own mean (the base sits still, so its IGRF is constant). A positive ``lag_s`` means the
    magnetometer reports late: its stream is shifted earlier by ``lag_s`` before reduction.
    """
    comp = np.asarray(compensated_nT, float)
    t = (time_ns - time_ns[0]) / 1e9
    if lag_s:
        ok = np.isfinite(comp)
        comp = np.interp(t + lag_s, t[ok], comp[ok], left=np.nan, right=np.nan)
    igrf = igrf_total_nT(time_ns, lat_deg, lon_deg, alt_m)
    anomaly = comp - igrf
    diurnal = None
    if base_nT is not None and np.isfinite(base_nT).any():
        smooth = time_window_mean(t, np.asarray(base_nT, float), base_smoothing_s)
        diurnal = smooth - np.nanmean(smooth)
        anomaly = anomaly - diurnal
    return Reduction(anomaly, igrf, diurnal, lag_s)
