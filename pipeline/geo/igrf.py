"""Main (core) field from IGRF via ppigrf, in NED and nT."""

from __future__ import annotations

from datetime import UTC, datetime

import numpy as np
import ppigrf


def igrf_ned_nT(lat_deg, lon_deg, alt_m, when: datetime) -> np.ndarray:
    """IGRF main field at geodetic positions, as (n, 3) NED components in nT.

    ``alt_m`` is the height above the WGS-84 ellipsoid. ppigrf costs about 40 us per point;
    callers with dense tracks evaluate it at :func:`spaced_epochs` and interpolate (the main
    field changes by a few nT per km).
    """
    lat = np.atleast_1d(np.asarray(lat_deg, float))
    lon = np.atleast_1d(np.asarray(lon_deg, float))
    h_km = np.atleast_1d(np.asarray(alt_m, float)) / 1000.0
    lat, lon, h_km = np.broadcast_arrays(lat, lon, h_km)
    if when.tzinfo is not None:  # ppigrf compares against naive UTC dates
        when = when.astimezone(UTC).replace(tzinfo=None)
    be, bn, bu = ppigrf.igrf(lon.ravel(), lat.ravel(), h_km.ravel(), when)
    return np.stack([np.ravel(bn), np.ravel(be), -np.ravel(bu)], axis=-1)


def spaced_epochs(time_s: np.ndarray, ok: np.ndarray, spacing_s: float) -> np.ndarray:
    """The epochs among ``ok`` (sorted epoch indices) at which to evaluate the main field
    along a track: the first of every ``spacing_s``-long interval of time from the first,
    and the last (s; in time, whatever the sample rate)."""
    t = np.asarray(time_s, float)[ok]
    interval = np.floor((t - t[0]) / spacing_s)
    pick = ok[np.r_[True, interval[1:] != interval[:-1]]]
    return pick if pick[-1] == ok[-1] else np.r_[pick, ok[-1]]


def main_field_direction(
    lat_deg: float, lon_deg: float, alt_m: float, when: datetime
) -> tuple[np.ndarray, float, float, float]:
    """Unit vector (NED) of the main field, with total (nT), inclination and declination (deg)."""
    b = igrf_ned_nT(lat_deg, lon_deg, alt_m, when)[0]
    total = float(np.linalg.norm(b))
    incl = float(np.degrees(np.arctan2(b[2], np.hypot(b[0], b[1]))))
    decl = float(np.degrees(np.arctan2(b[1], b[0])))
    return b / total, total, incl, decl


def main_field_gradient_nT_per_m(
    lat_deg: float, lon_deg: float, alt_m: float, when: datetime, step_m: float = 100.0
) -> np.ndarray:
    """Gradient of the IGRF total field, (east, north, up) in nT/m, by central differences
    over +-``step_m``.

    A magnetometer moving over a survey area sees it on top of the crust's gradient (a few
    nT per km: about 0.005 nT/m north at mid-latitudes), so a fitted gradient (AGG-TL's
    position terms, the audit's gradient finding) includes it.
    """
    dlat = step_m / 111_320.0
    dlon = dlat / np.cos(np.radians(lat_deg))
    lat = np.array([lat_deg, lat_deg, lat_deg + dlat, lat_deg - dlat, lat_deg, lat_deg])
    lon = np.array([lon_deg + dlon, lon_deg - dlon, lon_deg, lon_deg, lon_deg, lon_deg])
    alt = np.array([alt_m] * 4 + [alt_m + step_m, alt_m - step_m])
    f = np.linalg.norm(igrf_ned_nT(lat, lon, alt, when), axis=1)
    return (f[0::2] - f[1::2]) / (2.0 * step_m)
