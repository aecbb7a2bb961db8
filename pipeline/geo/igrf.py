"""Main (core) field from IGRF via ppigrf, in NED and nT."""

from __future__ import annotations

from datetime import UTC, datetime

import numpy as np
import ppigrf


def igrf_ned_nT(lat_deg, lon_deg, alt_m, when: datetime) -> np.ndarray:
    """IGRF main field at geodetic positions, as (n, 3) NED components in nT.

    ``alt_m`` is the height above the WGS-84 ellipsoid. ppigrf costs about 40 us per point;
    callers with dense tracks evaluate a decimated track and interpolate (the main field
    changes by a few nT per km).
    """
    lat = np.atleast_1d(np.asarray(lat_deg, float))
    lon = np.atleast_1d(np.asarray(lon_deg, float))
    h_km = np.atleast_1d(np.asarray(alt_m, float)) / 1000.0
    lat, lon, h_km = np.broadcast_arrays(lat, lon, h_km)
    if when.tzinfo is not None:  # ppigrf compares against naive UTC dates
        when = when.astimezone(UTC).replace(tzinfo=None)
    be, bn, bu = ppigrf.igrf(lon.ravel(), lat.ravel(), h_km.ravel(), when)
    return np.stack([np.ravel(bn), np.ravel(be), -np.ravel(bu)], axis=-1)


def main_field_direction(
    lat_deg: float, lon_deg: float, alt_m: float, when: datetime
) -> tuple[np.ndarray, float, float, float]:
    """Unit vector (NED) of the main field, with total (nT), inclination and declination (deg)."""
    b = igrf_ned_nT(lat_deg, lon_deg, alt_m, when)[0]
    total = float(np.linalg.norm(b))
    incl = float(np.degrees(np.arctan2(b[2], np.hypot(b[0], b[1]))))
    decl = float(np.degrees(np.arctan2(b[1], b[0])))
    return b / total, total, incl, decl
