"""Reduction of the compensated field to the crustal anomaly."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import UTC, datetime

import numpy as np

from pipeline.geo.igrf import igrf_ned_nT


@dataclass
class Reduction:
    anomaly_nT: np.ndarray
    igrf_nT: np.ndarray
    diurnal_nT: np.ndarray | None
    lag_s: float


def igrf_total_nT(time_ns: np.ndarray, lat_deg: np.ndarray, lon_deg: np.ndarray,
                  alt_m: np.ndarray, every: int = 10) -> np.ndarray:
    """IGRF total field at each sample (position, ellipsoidal height, date).

    ppigrf is evaluated on every ``every``-th finite sample and interpolated in time: the main
    field changes by well under 0.01 nT between them (a few nT per km of flight).
    """
    ok = np.flatnonzero(np.isfinite(lat_deg) & np.isfinite(lon_deg) & np.isfinite(alt_m))
    out = np.full(time_ns.size, np.nan)
    if ok.size == 0:
        return out
    pick = ok[::every]
    if pick[-1] != ok[-1]:
        pick = np.r_[pick, ok[-1]]
    when = datetime.fromtimestamp(int(np.median(time_ns[ok])) / 1e9, tz=UTC)
    b = igrf_ned_nT(lat_deg[pick], lon_deg[pick], alt_m[pick], when)
    tot = np.linalg.norm(b, axis=1)
    t = (time_ns - time_ns[0]) / 1e9
    out[ok] = np.interp(t[ok], t[pick], tot)
    return out


def reduce_to_anomaly(time_ns: np.ndarray, compensated_nT: np.ndarray, lat_deg: np.ndarray,
                      lon_deg: np.ndarray, alt_m: np.ndarray, base_nT: np.ndarray | None = None,
                      lag_s: float = 0.0) -> Reduction:
    """anomaly = compensated - IGRF - diurnal.

    The diurnal is the base-station reading minus its own mean (the base sits still, so its
    IGRF is constant). A positive ``lag_s`` means the magnetometer reports late: its stream
    is shifted earlier by ``lag_s`` before reduction.
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
        diurnal = np.asarray(base_nT, float) - np.nanmean(base_nT)
        anomaly = anomaly - diurnal
    return Reduction(anomaly, igrf, diurnal, lag_s)
