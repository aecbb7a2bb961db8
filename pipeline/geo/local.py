"""Local metric coordinates around a reference point.

East/north metres come from an azimuthal equidistant projection centred on the reference
(pyproj); "up" is the ellipsoidal height difference. Over survey areas of tens of km this is
a flat-earth frame with sub-metre distortion, for track geometry (segmentation, compensation,
the audit). The maps are gridded in a projected CRS instead (:mod:`pipeline.geo.projected`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from pyproj import Transformer


@dataclass
class LocalFrame:
    """East-north-up metres about (lat0_deg, lon0_deg, alt0_m)."""

    lat0_deg: float
    lon0_deg: float
    alt0_m: float = 0.0
    _fwd: Transformer = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self._fwd = Transformer.from_crs(
            "EPSG:4326",
            f"+proj=aeqd +lat_0={self.lat0_deg} +lon_0={self.lon0_deg} +datum=WGS84 +units=m",
            always_xy=True,
        )

    @property
    def crs(self) -> str:
        """PROJ string of the frame's azimuthal equidistant projection (WGS84, metres)."""
        return f"+proj=aeqd +lat_0={self.lat0_deg} +lon_0={self.lon0_deg} +datum=WGS84 +units=m"

    def to_enu(self, lat_deg, lon_deg, alt_m=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Local east/north/up metres of geodetic positions.

        Parameters
        ----------
        lat_deg, lon_deg : array_like
            Latitude and longitude, deg (WGS84).
        alt_m : array_like, optional
            Ellipsoidal height, m; up is 0 when omitted.

        Returns
        -------
        east_m, north_m, up_m : ndarray
            Metres about the reference point (up relative to ``alt0_m``).
        """
        e, n = self._fwd.transform(np.asarray(lon_deg, float), np.asarray(lat_deg, float))
        u = (np.asarray(alt_m, float) - self.alt0_m) if alt_m is not None else np.zeros_like(e)
        return np.asarray(e), np.asarray(n), np.asarray(u)

    def to_geodetic(self, east_m, north_m, up_m=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Geodetic positions of local east/north/up metres (the inverse of :meth:`to_enu`).

        Parameters
        ----------
        east_m, north_m : array_like
            Metres about the reference point.
        up_m : array_like, optional
            Metres above ``alt0_m``; the altitude is 0 when omitted.

        Returns
        -------
        lat_deg, lon_deg, alt_m : ndarray
            Latitude and longitude (deg, WGS84) and ellipsoidal height (m).
        """
        lon, lat = self._fwd.transform(
            np.asarray(east_m, float), np.asarray(north_m, float), direction="INVERSE"
        )
        alt = (np.asarray(up_m, float) + self.alt0_m) if up_m is not None else np.zeros_like(lat)
        return np.asarray(lat), np.asarray(lon), np.asarray(alt)


def local_east_north(lat_deg, lon_deg) -> tuple[np.ndarray, np.ndarray]:
    """East/north metres of a track about the median of its finite positions (NaN stays NaN).

    Raises
    ------
    ValueError
        No finite position.
    """
    lat, lon = np.asarray(lat_deg, float), np.asarray(lon_deg, float)
    ok = np.isfinite(lat) & np.isfinite(lon)
    if not ok.any():
        raise ValueError("no valid position")
    e, n, _ = LocalFrame(float(np.median(lat[ok])), float(np.median(lon[ok]))).to_enu(lat, lon)
    return np.asarray(e), np.asarray(n)
