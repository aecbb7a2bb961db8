"""The projected CRS the maps are gridded in: the survey's UTM zone or a user-given EPSG code.

A :class:`GridFrame` is a projected CRS (easting/northing in metres, pyproj) and an origin in
it; map positions are metres east/north of that origin along the CRS's grid axes, so a grid
made in it is a grid of the CRS, translated. The translation keeps the numbers small (a
viewer's 3D scene, line and crossover positions) and costs nothing: a cell centre's
easting is ``origin_east_m + east_m``. Grid north differs from true north by the meridian
convergence (:meth:`GridFrame.convergence_deg`), which directions (line headings, the
declination of a reduction to the pole) take into account.

The UTM zone follows the standard's exceptions (hand-written: pyproj's zone queries go by
the EPSG areas of use, which do not hold them): zone 32 is widened to 3-12 deg E between 56
and 64 deg N (south-west Norway, band V) and between 72 and 84 deg N (band X) zones 31, 33, 35
and 37 replace 31-37 (Svalbard); beyond 84 deg N and 80 deg S the polar stereographic UPS
grids take over.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from pyproj import CRS, Proj, Transformer

from pipeline.errors import AeromagError

ORIGIN_ROUNDING_M = 1000.0  # the origin on a round kilometre: cell centres on round eastings
UPS_NORTH, UPS_SOUTH = 32661, 32761  # WGS 84 / UPS North (N,E), UPS South (N,E)


def utm_zone(lat_deg, lon_deg):
    """UTM zone number (1-60) of points, with the Norway (32V) and Svalbard (31X, 33X, 35X,
    37X) exceptions (an int for a point, an array for arrays)."""
    lat = np.asarray(lat_deg, float)
    lon = (np.asarray(lon_deg, float) + 180.0) % 360.0 - 180.0
    zone = np.floor((lon + 180.0) / 6.0).astype(int) % 60 + 1
    zone = np.where((lat >= 56.0) & (lat < 64.0) & (lon >= 3.0) & (lon < 12.0), 32, zone)
    svalbard = (lat >= 72.0) & (lat <= 84.0) & (lon >= 0.0) & (lon < 42.0)
    zone = np.where(
        svalbard, np.select([lon < 9.0, lon < 21.0, lon < 33.0], [31, 33, 35], 37), zone
    )
    return int(zone) if zone.ndim == 0 else zone


def utm_epsg(lat_deg, lon_deg):
    """EPSG code of the WGS-84 UTM grid holding points: 326zz north of the equator, 327zz
    south (zones with the Norway and Svalbard exceptions, :func:`utm_zone`); UPS North
    (32661) beyond 84 deg N and UPS South (32761) beyond 80 deg S (an int for a point, an
    array for arrays)."""
    lat = np.asarray(lat_deg, float)
    code = np.where(lat >= 0, 32600, 32700) + utm_zone(lat, lon_deg)
    code = np.where(lat > 84.0, UPS_NORTH, np.where(lat < -80.0, UPS_SOUTH, code))
    return int(code) if code.ndim == 0 else code


def parse_crs_setting(value, source=None) -> int | None:
    """``map.crs``: ``"auto"`` (None: the survey's UTM zone) or an EPSG code (``32632``,
    ``"32632"`` or ``"EPSG:32632"``) of a projected CRS in metres.

    Raises
    ------
    AeromagError
        Not ``auto``, not an EPSG code, or a CRS that is not projected in metres (naming
        ``source``, the configuration file).
    """
    text = str(value).strip()
    if text.lower() in ("auto", ""):
        return None
    code = text.upper().removeprefix("EPSG:")
    try:
        epsg = int(code)
        crs = CRS.from_epsg(epsg)
    except Exception:  # noqa: BLE001 - pyproj raises several types for an unknown code
        raise AeromagError(
            f"map.crs {value!r}: use auto or the EPSG code of a projected CRS (e.g. 32632)",
            file=source,
        ) from None
    if not crs.is_projected or crs.axis_info[0].unit_name not in ("metre", "meter"):
        raise AeromagError(
            f"map.crs EPSG:{epsg} ({crs.name}) is not a projected CRS in metres", file=source
        )
    return epsg


@dataclass(frozen=True)
class GridFrame:
    """Metres east/north of an origin along a projected CRS's grid axes.

    Parameters
    ----------
    crs : str
        The CRS, as pyproj reads it (``EPSG:32632``; recordings made before the maps were
        gridded in a projected CRS give the PROJ string of their azimuthal equidistant frame).
    origin_east_m, origin_north_m : float
        The origin's easting and northing in ``crs``, m.
    alt0_m : float
        Height of the frame's "up" zero above the WGS-84 ellipsoid (the mean survey altitude).
    note : str
        How the CRS was chosen (for the summary and the log).
    zones : tuple of int
        EPSG codes of the UTM grids the survey's positions fall in (several: a survey across
        a zone boundary, gridded in one of them).
    """

    crs: str
    origin_east_m: float = 0.0
    origin_north_m: float = 0.0
    alt0_m: float = 0.0
    note: str = field(default="", compare=False)
    zones: tuple[int, ...] = field(default=(), compare=False)

    @cached_property
    def _fwd(self) -> Transformer:
        return Transformer.from_crs("EPSG:4326", self.crs, always_xy=True)

    @cached_property
    def _inv(self) -> Transformer:
        return Transformer.from_crs(self.crs, "EPSG:4326", always_xy=True)

    def __getstate__(self) -> dict:  # the transformers are rebuilt, not pickled
        return {k: v for k, v in self.__dict__.items() if k not in ("_fwd", "_inv")}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)

    @property
    def epsg(self) -> int | None:
        """The CRS's EPSG code (None for a CRS without one: an older recording's frame)."""
        return epsg_of(self.crs)

    @property
    def lat0_deg(self) -> float:
        """Latitude of the origin, deg (WGS-84)."""
        return float(self.to_geodetic(0.0, 0.0)[0])

    @property
    def lon0_deg(self) -> float:
        """Longitude of the origin, deg (WGS-84)."""
        return float(self.to_geodetic(0.0, 0.0)[1])

    @property
    def grid_crs(self) -> str:
        """What a grid's coordinates in this frame are (``Grid.crs``): the CRS itself when the
        origin is the CRS's, else the CRS and the origin (not a pyproj string on purpose:
        a grid's coordinates about the origin are not the CRS's; exports add the origin)."""
        if self.origin_east_m == 0.0 and self.origin_north_m == 0.0:
            return self.crs
        return f"{self.crs} about E {self.origin_east_m:.3f} m, N {self.origin_north_m:.3f} m"

    def to_enu(self, lat_deg, lon_deg, alt_m=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """East/north/up metres of geodetic positions.

        Parameters
        ----------
        lat_deg, lon_deg : array_like
            Latitude and longitude, deg (WGS84).
        alt_m : array_like, optional
            Ellipsoidal height, m; up is 0 when omitted.

        Returns
        -------
        east_m, north_m, up_m : ndarray
            Easting and northing in the CRS less the origin's (m); up relative to ``alt0_m``.
        """
        e, n = self._fwd.transform(np.asarray(lon_deg, float), np.asarray(lat_deg, float))
        e = np.asarray(e) - self.origin_east_m
        n = np.asarray(n) - self.origin_north_m
        u = (np.asarray(alt_m, float) - self.alt0_m) if alt_m is not None else np.zeros_like(e)
        return e, n, np.asarray(u)

    def to_geodetic(self, east_m, north_m, up_m=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Geodetic positions of frame metres (the inverse of :meth:`to_enu`).

        Returns
        -------
        lat_deg, lon_deg, alt_m : ndarray
            Latitude and longitude (deg, WGS84) and ellipsoidal height (m: ``alt0_m`` +
            ``up_m``; 0 when ``up_m`` is omitted).
        """
        lon, lat = self._inv.transform(
            np.asarray(east_m, float) + self.origin_east_m,
            np.asarray(north_m, float) + self.origin_north_m,
        )
        lat = np.asarray(lat)
        alt = (np.asarray(up_m, float) + self.alt0_m) if up_m is not None else np.zeros_like(lat)
        return lat, np.asarray(lon), alt

    def convergence_deg(self, east_m: float = 0.0, north_m: float = 0.0) -> float:
        """Meridian convergence at a frame position, deg: a direction's azimuth from grid
        north is its azimuth from true north minus this (pyproj's sign)."""
        lat, lon, _ = self.to_geodetic(east_m, north_m)
        return float(Proj(self.crs).get_factors(float(lon), float(lat)).meridian_convergence)

    def args(self) -> tuple[str, float, float, float]:
        """``(crs, origin_east_m, origin_north_m, alt0_m)``: the frame again as
        ``GridFrame(*args)`` (to pass it between processes)."""
        return (self.crs, self.origin_east_m, self.origin_north_m, self.alt0_m)


def epsg_of(crs: str) -> int | None:
    """The EPSG code of an ``EPSG:n`` string (None for any other CRS text)."""
    text = str(crs).strip().upper()
    if text.startswith("EPSG:") and text[5:].isdigit():
        return int(text[5:])
    return None


def survey_frame(lat_deg, lon_deg, alt_m, epsg: int | None = None) -> GridFrame:
    """The frame a survey's maps are gridded in.

    The CRS is ``epsg`` when given, else the UTM zone (:func:`utm_epsg`) of the survey's
    centroid (the mean of the projected positions' geodetic centre: one zone even when the
    survey crosses a zone boundary, which the frame's ``note`` says). The origin is the
    centroid's easting and northing rounded to :data:`ORIGIN_ROUNDING_M`, "up" zero the mean
    altitude.

    Parameters
    ----------
    lat_deg, lon_deg, alt_m : array_like
        The positions to be mapped (deg, WGS-84; m above the ellipsoid); NaN skipped.
    epsg : int, optional
        A projected CRS in metres (:func:`parse_crs_setting`).

    Raises
    ------
    ValueError
        No finite position, or positions the CRS cannot project.
    """
    lat, lon = np.asarray(lat_deg, float), np.asarray(lon_deg, float)
    alt = np.broadcast_to(np.asarray(alt_m, float), lat.shape)
    ok = np.isfinite(lat) & np.isfinite(lon)
    if not ok.any():
        raise ValueError("no valid position")
    lat, lon, alt = lat[ok], lon[ok], alt[ok]
    # the centroid on the sphere (a survey across the antimeridian averages right)
    rl, ro = np.radians(lat), np.radians(lon)
    xyz = np.array([np.cos(rl) * np.cos(ro), np.cos(rl) * np.sin(ro), np.sin(rl)]).mean(axis=1)
    lat_c = float(np.degrees(np.arctan2(xyz[2], np.hypot(xyz[0], xyz[1]))))
    lon_c = float(np.degrees(np.arctan2(xyz[1], xyz[0])))
    zones = tuple(int(z) for z in np.unique(utm_epsg(lat, lon)))
    if epsg is None:
        code = utm_epsg(lat_c, lon_c)
        note = _zone_note(zones, code)
    else:
        code = int(epsg)
        note = f"EPSG:{code} ({CRS.from_epsg(code).name}): map.crs"
    alt0 = float(np.nanmean(alt)) if np.isfinite(alt).any() else 0.0
    frame = GridFrame(f"EPSG:{code}", 0.0, 0.0, alt0, note)
    e, n, _ = frame.to_enu(lat_c, lon_c)
    if not (np.isfinite(e) and np.isfinite(n)):
        raise ValueError(
            f"EPSG:{code} cannot project the survey's centre ({lat_c:.4f}, {lon_c:.4f})"
        )
    r = ORIGIN_ROUNDING_M
    return GridFrame(
        frame.crs, float(np.round(e / r) * r), float(np.round(n / r) * r), alt0, note, zones
    )


def survey_positions(
    lat_deg: np.ndarray,
    lon_deg: np.ndarray,
    alt_m: np.ndarray,
    survey: np.ndarray,
    epsg: int | None,
    source,
    no_survey: str,
) -> tuple[GridFrame, np.ndarray, np.ndarray, np.ndarray]:
    """A flight's :func:`survey_frame` (over its survey epochs with a position) and every
    epoch's east, north and up (m) in it: the frame the map and its quality figures share.

    Raises a one-line AeromagError (``source``'s /gnss/fix) with fewer than 100 such epochs
    (the message ``no_survey``) or when ``epsg`` (map.crs) cannot project the survey.
    """
    surv = survey & np.isfinite(lat_deg)
    if surv.sum() < 100:
        raise AeromagError(no_survey, file=source, channel="/gnss/fix")
    try:
        frame = survey_frame(lat_deg[surv], lon_deg[surv], alt_m[surv], epsg)
    except ValueError as exc:
        raise AeromagError(f"map.crs: {exc}", file=source, channel="/gnss/fix") from None
    return (frame, *frame.to_enu(lat_deg, lon_deg, alt_m))


def _zone_note(zones: tuple[int, ...], code: int) -> str:
    """Which UTM grid was chosen, and whether the survey spans others (then the centroid's
    zone holds it all: one grid, no seam)."""
    name = CRS.from_epsg(code).name
    if zones == (code,):
        return f"EPSG:{code} ({name}): the survey's UTM zone"
    others = ", ".join(f"EPSG:{z}" for z in zones if z != code)
    return (
        f"EPSG:{code} ({name}): the survey spans UTM zones beyond its centroid's ({others}); "
        "it is gridded in the centroid's zone"
    )
