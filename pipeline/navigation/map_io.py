"""Reading a navigation map and placing it on the Earth.

Three sources:

* a processed aeromag recording: the ``foxglove.Grid`` on ``/map/anomaly_filtered`` (or
  another channel), in the ``local_enu`` frame whose CRS and origin the recording's
  ``/map/frame`` channel gives (older recordings: an azimuthal equidistant frame)
  (:func:`pipeline.export.source.read_map_products`, the one reader of the map channels; any
  other reader can georeference the grid the same way).
* a GeoTIFF or netCDF grid (rioxarray / xarray) with a CRS, or longitude/latitude coordinates.
* a MagNav.jl HDF5 map (``get_map`` fields ``map`` (ny x nx), ``xx`` (longitudes), ``yy``
  (latitudes), ``alt``, optional ``mask``). MagNav writes ``xx``/``yy`` in degrees by default and
  uses radians internally (``get_map``'s ``file_units``); both are accepted (radians when every
  value is within +-2 pi). Arrays written by Julia read transposed in h5py: a ``map`` of shape
  (nx, ny) is transposed.

Every map becomes a :class:`~pipeline.maps.grid.Grid` on square cells in a local metric frame
with the functions that take a track into that frame and back.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np

from pipeline.errors import AeromagError
from pipeline.geo.projected import GridFrame
from pipeline.maps.grid import Grid

DEFAULT_CHANNEL = "/map/anomaly_filtered"
UNCERTAINTY_CHANNEL = "/map/uncertainty"
UNCERTAINTY_VARIABLE = "uncertainty"  # its netCDF variable (aeromag export)
# the uncertainty variable's attribute holding the error's correlation length along a track, m
ERROR_LENGTH_ATTR = "correlation_length_m"


@dataclass
class GeoMap:
    """A map in a local metric frame and how to get there from geodetic coordinates."""

    grid: Grid
    to_local: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]
    to_geodetic: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]
    altitude_m: float | None
    source: str
    kind: str
    crs: str
    notes: list[str] = field(default_factory=list)
    # the map's 1-sigma error per cell, nT, on the same cells (a recording's /map/uncertainty,
    # a netCDF's ``uncertainty`` variable); None: the map does not say
    sigma: Grid | None = None
    # the distance the map's error stays correlated over, m (the map stage's measurement
    # along its held-out lines, when known; None: [navigate] map_error_length_m)
    error_length_m: float | None = None

    def ned_to_map(self, lat_deg, lon_deg, step_m: float = 10.0) -> np.ndarray:
        """(N, 2, 2): map-frame (east, north) metres per metre moved (north, east) at each
        point, by finite differences of :attr:`to_local` (the projection's meridian
        convergence and scale; the identity for a local tangent frame)."""
        lat = np.atleast_1d(np.asarray(lat_deg, float))
        lon = np.atleast_1d(np.asarray(lon_deg, float))
        a, f = 6_378_137.0, 1 / 298.257223563
        e2 = f * (2 - f)
        sl = np.sin(np.radians(lat))
        m_rad = a * (1 - e2) / (1 - e2 * sl * sl) ** 1.5
        n_rad = a / np.sqrt(1 - e2 * sl * sl)
        dlat = np.degrees(step_m / m_rad)
        dlon = np.degrees(step_m / (n_rad * np.cos(np.radians(lat))))
        e0, n0 = (np.asarray(v, float) for v in self.to_local(lat, lon))
        en, nn = (np.asarray(v, float) for v in self.to_local(lat + dlat, lon))
        ee, ne = (np.asarray(v, float) for v in self.to_local(lat, lon + dlon))
        j = np.empty((lat.size, 2, 2))
        j[:, 0, 0], j[:, 1, 0] = (en - e0) / step_m, (nn - n0) / step_m
        j[:, 0, 1], j[:, 1, 1] = (ee - e0) / step_m, (ne - n0) / step_m
        return j

    def describe(self) -> dict:
        """The map as NAV.json reports it: file, kind, CRS, shape, cell (m), altitude (m)."""
        ny, nx = self.grid.shape
        return {
            "file": self.source,
            "kind": self.kind,
            "crs": self.crs,
            "grid_shape": [ny, nx],
            "cell_m": self.grid.cell_m,
            "altitude_m": self.altitude_m,
            "uncertainty": self.sigma is not None,
            "notes": self.notes,
        }


def _to_local(frame: GridFrame, lat, lon):
    e, n, _ = frame.to_enu(lat, lon)
    return e, n


def _to_geodetic(frame: GridFrame, e, n):
    lat, lon, _ = frame.to_geodetic(e, n)
    return lat, lon


def _local(frame: GridFrame):
    # partials of module functions, not closures: a map's transforms pickle with it (the
    # flow hands results between processes and persists them)
    return partial(_to_local, frame), partial(_to_geodetic, frame)


def read_map(path: str | Path, channel: str = DEFAULT_CHANNEL) -> GeoMap:
    """Read a map file by its kind (``.mcap``, ``.tif``/``.tiff``, ``.nc``, ``.h5``/``.hdf5``)."""
    path = Path(path)
    if not path.is_file():
        raise AeromagError("map file not found", file=path)
    suffix = path.suffix.lower()
    if suffix == ".mcap":
        return read_recording_map(path, channel)
    if suffix in (".tif", ".tiff", ".nc", ".nc4", ".grd"):
        return read_raster_map(path)
    if suffix in (".h5", ".hdf5"):
        return read_magnav_map(path)
    raise AeromagError(
        f"unknown map format {suffix!r} (use a processed .mcap, GeoTIFF, netCDF or MagNav .h5)",
        file=path,
    )


# ------------------------------------------------------------------------------- recording
def read_recording_map(path: Path, channel: str = DEFAULT_CHANNEL) -> GeoMap:
    """The grid on ``channel`` of a processed recording, placed by its ``/map/frame``."""
    from pipeline.export.source import map_topics, read_map_products

    topics = map_topics(path)
    products = None if topics is not None and channel not in topics else read_map_products(path)
    found = (
        None if products is None else next((g for g in products.grids if g.topic == channel), None)
    )
    if found is None:
        raise AeromagError(
            "the map recording has no such channel (run `aeromag map` or `process` on "
            "it first, or pick another with --map-channel)",
            file=path,
            channel=channel,
        )
    fr = products.frame
    frame = fr.grid_frame()
    grid = found.grid
    grid.crs = frame.grid_crs
    to_local, to_geo = _local(frame)
    sigma = next((g.grid for g in products.grids if g.topic == UNCERTAINTY_CHANNEL), None)
    notes = ["CRS and origin from the recording's /map/frame"]
    if sigma is not None and (sigma.shape != grid.shape or channel == UNCERTAINTY_CHANNEL):
        sigma = None  # not the map's cells (an enhancement of another size, or itself)
    if sigma is not None:
        notes.append(f"map error per cell from {UNCERTAINTY_CHANNEL}")
    return GeoMap(
        grid,
        to_local,
        to_geo,
        fr.altitude_m,
        str(path),
        f"recording {channel}",
        frame.crs,
        notes,
        sigma,
        fr.error_length_m if sigma is not None else None,
    )


def frame_map(grid: Grid, frame: GridFrame, source: str, kind: str) -> GeoMap:
    """A grid in the frame ``frame`` (an in-memory map, e.g. a
    :class:`pipeline.maps.stage.MapRun`'s), placed as a recording's ``/map/frame`` places it.

    Parameters
    ----------
    grid : Grid
        Values on cells in east/north metres of ``frame``, nT (copied; ``crs`` set).
    frame : GridFrame
        CRS, origin and altitude (m; the map's altitude).
    source, kind : str
        What the map is, for the summary (``map.file``, ``map.kind``).
    """
    g = Grid(grid.values, grid.east0_m, grid.north0_m, grid.cell_m, frame.grid_crs)
    to_local, to_geo = _local(frame)
    return GeoMap(g, to_local, to_geo, frame.alt0_m, source, kind, frame.crs, [])


# ------------------------------------------------------------------------------- rasters
def _square_grid(values: np.ndarray, x_m: np.ndarray, y_m: np.ndarray) -> Grid:
    """A grid on square cells from values on ascending regular axes x (columns), y (rows),
    resampled (bilinear, NaN-aware) when the axes' steps differ."""
    dx = float(np.median(np.diff(x_m)))
    dy = float(np.median(np.diff(y_m)))
    if abs(dx - dy) <= 1e-6 * max(dx, dy):
        return Grid(values, float(x_m[0]), float(y_m[0]), dx)
    from scipy.interpolate import RegularGridInterpolator

    cell = min(dx, dy)
    # nodes inside the data's span only (one beyond it would interpolate to NaN)
    xs = x_m[0] + cell * np.arange(int(np.floor((x_m[-1] - x_m[0]) / cell + 1e-9)) + 1)
    ys = y_m[0] + cell * np.arange(int(np.floor((y_m[-1] - y_m[0]) / cell + 1e-9)) + 1)
    itp = RegularGridInterpolator((y_m, x_m), values, bounds_error=False, fill_value=np.nan)
    yy, xx = np.meshgrid(ys, xs, indexing="ij")
    return Grid(itp((yy, xx)), float(xs[0]), float(ys[0]), cell)


def _geographic(values, lon_deg, lat_deg, source, kind, alt, notes) -> GeoMap:
    """A longitude/latitude grid placed in a local metric frame about its centre: on survey
    scales the regular lon/lat axes map linearly to east/north metres (local radii of
    curvature), so the grid stays regular there."""
    lat0 = float(np.mean(lat_deg))
    lon0 = float(np.mean(lon_deg))
    a, f = 6_378_137.0, 1 / 298.257223563
    e2 = f * (2 - f)
    s = np.sin(np.radians(lat0))
    m_rad = a * (1 - e2) / (1 - e2 * s * s) ** 1.5  # meridian radius
    n_rad = a / np.sqrt(1 - e2 * s * s)  # prime vertical radius
    kx = np.radians(1.0) * n_rad * np.cos(np.radians(lat0))
    ky = np.radians(1.0) * m_rad
    grid = _square_grid(values, (lon_deg - lon0) * kx, (lat_deg - lat0) * ky)
    grid.crs = f"lon/lat about {lat0:.6f}, {lon0:.6f} (local linear metres)"

    def to_local(lat, lon):
        return (np.asarray(lon, float) - lon0) * kx, (np.asarray(lat, float) - lat0) * ky

    def to_geodetic(e, n):
        return np.asarray(n, float) / ky + lat0, np.asarray(e, float) / kx + lon0

    return GeoMap(grid, to_local, to_geodetic, alt, source, kind, "EPSG:4326", notes)


def read_raster_map(path: Path) -> GeoMap:
    """A GeoTIFF / netCDF anomaly grid (first 2-D variable), nT."""
    import rioxarray  # noqa: F401  (registers the .rio accessor)
    import xarray as xr

    sigma_da = None
    try:
        if path.suffix.lower() in (".tif", ".tiff"):
            da = xr.open_dataarray(path, engine="rasterio").squeeze(drop=True)
        else:
            # "all": the CF grid-mapping variable (the CRS) stays attached to the grids
            ds = xr.open_dataset(path, decode_coords="all")
            names = [v for v in ds.data_vars if ds[v].ndim == 2]
            if not names:
                raise AeromagError("no 2-D variable in the netCDF map", file=path)
            da = ds[names[0]]
            if UNCERTAINTY_VARIABLE in names and names[0] != UNCERTAINTY_VARIABLE:
                sigma_da = ds[UNCERTAINTY_VARIABLE]
    except AeromagError:
        raise
    except Exception as exc:
        raise AeromagError(f"cannot read the map: {exc}", file=path) from None
    if da.ndim != 2:
        raise AeromagError(f"the map is not a 2-D grid (dims {da.dims})", file=path)
    ydim, xdim = da.dims
    x = np.asarray(da[xdim].values, float)
    y = np.asarray(da[ydim].values, float)
    vals = np.asarray(da.values, float)
    nodata = da.attrs.get("_FillValue", da.rio.nodata if hasattr(da, "rio") else None)
    if nodata is not None and np.isfinite(nodata):
        vals = np.where(vals == nodata, np.nan, vals)
    sig = None
    if sigma_da is not None and sigma_da.dims == da.dims:
        sig = np.asarray(sigma_da.values, float)
    if x[0] > x[-1]:
        x, vals = x[::-1], vals[:, ::-1]
        sig = None if sig is None else sig[:, ::-1]
    if y[0] > y[-1]:
        y, vals = y[::-1], vals[::-1]
        sig = None if sig is None else sig[::-1]
    gm = _raster_geomap(path, da, vals, x, y, xdim, ydim)
    if sig is not None:
        # placed exactly as the map (same axes, same resampling)
        gm.sigma = _raster_geomap(path, da, sig, x, y, xdim, ydim).grid
        gm.notes.append(f"map error per cell from the {UNCERTAINTY_VARIABLE!r} variable")
        from pipeline.export.source import positive_or_none

        try:
            gm.error_length_m = positive_or_none(
                sigma_da.attrs.get(ERROR_LENGTH_ATTR), ERROR_LENGTH_ATTR
            )
        except ValueError:
            raise AeromagError(
                f"the {UNCERTAINTY_VARIABLE!r} variable's {ERROR_LENGTH_ATTR} attribute is not "
                "a positive number of metres",
                file=path,
            ) from None
    return gm


def _raster_geomap(path: Path, da, vals, x, y, xdim: str, ydim: str) -> GeoMap:
    """The raster's values on ascending axes ``x``, ``y`` placed by its CRS (or its
    longitude/latitude coordinates)."""
    alt = next(
        (float(da.attrs[k]) for k in ("altitude_m", "alt", "height_m") if k in da.attrs), None
    )
    notes = [] if alt is not None else ["map altitude not in the file's attributes"]
    crs = None
    try:
        crs = da.rio.crs
    except Exception:
        crs = None
    geographic_names = {"lon", "longitude", "x"} >= {xdim.lower()} and ydim.lower() in (
        "lat",
        "latitude",
    )
    if crs is None:
        if geographic_names:
            return _geographic(vals, x, y, str(path), "raster lon/lat", alt, notes)
        raise AeromagError(
            "the map has no CRS and no longitude/latitude coordinates: it cannot be placed",
            file=path,
        )
    from pyproj import CRS, Transformer

    try:
        crs = CRS.from_user_input(crs)
        if crs.is_geographic:
            return _geographic(vals, x, y, str(path), f"raster {crs.name}", alt, notes)
        if not crs.is_projected or crs.axis_info[0].unit_name not in ("metre", "meter"):
            raise ValueError(f"{crs.name} is not a projected CRS in metres")
        fwd = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
        inv = Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
        fwd.transform(0.0, 0.0, errcheck=True)
    except Exception as exc:
        raise AeromagError(f"the map's CRS cannot be placed: {exc}", file=path) from None
    grid = _square_grid(vals, x, y)
    grid.crs = crs.to_string()

    def to_local(lat, lon):
        e, n = fwd.transform(np.asarray(lon, float), np.asarray(lat, float))
        return np.asarray(e), np.asarray(n)

    def to_geodetic(e, n):
        lon, lat = inv.transform(np.asarray(e, float), np.asarray(n, float))
        return np.asarray(lat), np.asarray(lon)

    return GeoMap(grid, to_local, to_geodetic, alt, str(path), "raster", crs.to_string(), notes)


# ------------------------------------------------------------------------------- MagNav
def read_magnav_map(path: Path) -> GeoMap:
    """A MagNav.jl scalar map (HDF5 fields of ``get_map``)."""
    import h5py

    try:
        with h5py.File(path, "r") as h5:
            if "map" not in h5:
                raise AeromagError(
                    "no scalar 'map' field (MagNav get_map layout: map, xx, yy, alt)", file=path
                )
            vals = np.asarray(h5["map"][()], float)
            xx = np.ravel(np.asarray(h5["xx"][()], float))
            yy = np.ravel(np.asarray(h5["yy"][()], float))
            alt = np.asarray(h5["alt"][()], float) if "alt" in h5 else None
            mask = np.asarray(h5["mask"][()]) if "mask" in h5 else None
    except AeromagError:
        raise
    except Exception as exc:
        raise AeromagError(f"cannot read the MagNav map: {exc}", file=path) from None
    notes = []
    if vals.ndim != 2:
        raise AeromagError(f"only 2-D scalar maps are supported (shape {vals.shape})", file=path)
    ny, nx = yy.size, xx.size
    if vals.shape == (nx, ny):  # written by Julia (column-major): h5py sees it transposed
        vals = vals.T
        mask = mask.T if mask is not None and mask.shape == (nx, ny) else mask
    if vals.shape != (ny, nx):
        raise AeromagError(
            f"map shape {vals.shape} does not match yy ({ny}) x xx ({nx})", file=path
        )
    if mask is not None and mask.shape == vals.shape and mask.any():
        vals = np.where(mask.astype(bool), vals, np.nan)
    if max(np.abs(xx).max(), np.abs(yy).max()) <= 2 * np.pi:
        xx, yy = np.degrees(xx), np.degrees(yy)
        notes.append("xx/yy read as radians")
    else:
        notes.append("xx/yy read as degrees")
    if np.abs(yy).max() > 90 or np.abs(xx).max() > 360:
        raise AeromagError(
            "xx/yy are not longitudes/latitudes (a map in metres has no CRS here): "
            "it cannot be placed",
            file=path,
        )
    alt_m = None
    if alt is not None and alt.size:
        alt_m = float(np.nanmean(alt))
        if alt.size > 1:
            notes.append(f"drape or 3-D map: altitude taken as its mean {alt_m:.1f} m")
    if xx[0] > xx[-1]:
        xx, vals = xx[::-1], vals[:, ::-1]
    if yy[0] > yy[-1]:
        yy, vals = yy[::-1], vals[::-1]
    return _geographic(vals, xx, yy, str(path), "MagNav HDF5", alt_m, notes)
