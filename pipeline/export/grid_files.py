"""Map grids as GeoTIFF (the survey's UTM zone) and CF-1.8 netCDF (the native grid).

The grids are made in the ``local_enu`` frame of ``/map/frame``: an azimuthal equidistant
projection about the survey centre (``Grid.crs``). The netCDF keeps that grid cell for cell,
with its projection as a CF grid mapping and 2-D latitude/longitude; the GeoTIFF is the grid
resampled (bilinear, rasterio/GDAL through rioxarray) onto the UTM zone at the same cell size,
NaN (the nodata value) outside the covered cells.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline import __version__
from pipeline.export.source import MapFrame, MapGrid
from pipeline.io.writer import atomic_path
from pipeline.maps.grid import Grid


def grid_dataarray(grid: Grid, name: str = "values"):
    """A grid as an :class:`xarray.DataArray` on cell-centre coordinates ``y`` (north, m,
    ascending) and ``x`` (east, m) in its local frame, with the CRS attached (rioxarray)."""
    import rioxarray  # noqa: F401 - registers the .rio accessor
    import xarray as xr

    east, north = grid.coordinates()
    da = xr.DataArray(
        grid.values.astype(np.float32), coords={"y": north, "x": east}, dims=("y", "x"), name=name
    )
    return da.rio.write_crs(grid.crs).rio.write_nodata(np.nan, encoded=False)


def to_utm(grid: Grid, utm_epsg: int, cell_m: float | None = None):
    """The grid resampled (bilinear) onto its UTM zone, north-up, NaN outside the data.

    Parameters
    ----------
    grid
        Values on the local azimuthal equidistant frame (``grid.crs``).
    utm_epsg
        EPSG code of the UTM zone (326zz / 327zz).
    cell_m
        Output cell size, m (default: the grid's).

    Returns
    -------
    xarray.DataArray
        Dims ``y`` (northing, descending), ``x`` (easting), CRS ``EPSG:<utm_epsg>``.
    """
    from rasterio.enums import Resampling

    return reproject(grid, f"EPSG:{utm_epsg}", float(cell_m or grid.cell_m), Resampling.bilinear)


def reproject(grid: Grid, dst_crs: str, resolution, resampling):
    """The grid resampled onto ``dst_crs`` (rioxarray/GDAL), north-up, NaN outside the data;
    ``resolution`` in the target's units (one value or (x, y))."""
    import warnings

    da = grid_dataarray(grid).isel(y=slice(None, None, -1))  # north-up for GDAL
    with warnings.catch_warnings():  # affine's `*` deprecation inside rioxarray
        warnings.simplefilter("ignore", PendingDeprecationWarning)
        return da.rio.reproject(
            dst_crs, resolution=resolution, resampling=resampling, nodata=np.nan
        )


def write_geotiff(path: str | Path, mg: MapGrid, frame: MapFrame) -> Path:
    """One grid channel as a single-band float32 GeoTIFF in the survey's UTM zone (deflate,
    nodata NaN; band description and ``units`` tag from the channel), written atomically."""
    utm = to_utm(mg.grid, frame.utm_epsg)
    utm.attrs.update(
        {
            "long_name": mg.field_name,
            "units": mg.units,
            "source": f"aeromag {__version__}: {mg.topic}",
        }
    )
    import warnings

    import rasterio

    with atomic_path(path) as tmp:
        with warnings.catch_warnings():  # affine's `*` deprecation inside rioxarray
            warnings.simplefilter("ignore", PendingDeprecationWarning)
            utm.rio.to_raster(tmp, driver="GTiff", compress="DEFLATE", dtype="float32")

        with rasterio.open(tmp, "r+") as ds:
            ds.set_band_description(1, mg.field_name)
            ds.update_tags(1, units=mg.units)
    return Path(path)


def _long_name(mg: MapGrid) -> str:
    """The channel's description in the contract (``levelled total-field anomaly grid``)."""
    from pipeline.io.contract import rule_for_topic

    rule = rule_for_topic(mg.topic)
    return rule.description if rule is not None and rule.description else mg.field_name


def cf_name(name: str) -> str:
    """A netCDF variable name as CF recommends (letters, digits, underscores): the channel
    name with any other character as ``_`` (``upward_12.5m`` -> ``upward_12_5m``)."""
    import re

    return re.sub(r"[^A-Za-z0-9_]", "_", name)


def write_netcdf(path: str | Path, grids: list[MapGrid], frame: MapFrame) -> Path:
    """Every grid channel as a variable (:func:`cf_name` of its name) of one CF-1.8
    netCDF-4 file, on the native grid.

    Coordinates ``x``, ``y`` (m, the projection's easting/northing of the cell centres),
    auxiliary 2-D ``lat``/``lon`` (degrees), a ``crs`` grid-mapping variable (CF attributes
    from pyproj, with ``crs_wkt`` and GDAL's ``spatial_ref``); each variable has ``units``,
    ``long_name``, ``grid_mapping`` and NaN as ``_FillValue``. Written atomically.

    Raises
    ------
    ValueError
        The grids do not share one geometry (shape, origin, cell size).
    """
    import xarray as xr
    from pyproj import CRS, Transformer

    first = grids[0].grid
    for mg in grids[1:]:
        g = mg.grid
        if g.shape != first.shape or not np.allclose(
            (g.east0_m, g.north0_m, g.cell_m), (first.east0_m, first.north0_m, first.cell_m)
        ):
            raise ValueError(f"{mg.topic} is not on the grid of {grids[0].topic}")
    east, north = first.coordinates()
    crs = CRS.from_user_input(first.crs)
    ee, nn = np.meshgrid(east, north)
    lon, lat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(ee, nn)
    cf = crs.to_cf()
    cf["spatial_ref"] = cf.get("crs_wkt", crs.to_wkt())
    ds = xr.Dataset(
        {
            cf_name(mg.name): (
                ("y", "x"),
                mg.grid.values.astype(np.float32),
                {
                    "long_name": _long_name(mg),
                    "units": mg.units,
                    "grid_mapping": "crs",
                    "coordinates": "lat lon",
                    "source_channel": mg.topic,
                },
            )
            for mg in grids
        },
        coords={
            "x": (
                "x",
                east,
                {
                    "standard_name": "projection_x_coordinate",
                    "long_name": "easting of the cell centre",
                    "units": "m",
                    "axis": "X",
                },
            ),
            "y": (
                "y",
                north,
                {
                    "standard_name": "projection_y_coordinate",
                    "long_name": "northing of the cell centre",
                    "units": "m",
                    "axis": "Y",
                },
            ),
            "lat": (("y", "x"), lat, {"standard_name": "latitude", "units": "degrees_north"}),
            "lon": (("y", "x"), lon, {"standard_name": "longitude", "units": "degrees_east"}),
        },
        attrs={
            "Conventions": "CF-1.8",
            "title": "aeromag magnetic anomaly maps",
            "source": f"aeromag {__version__}",
            "references": "schemas/README.md (/map/* channels)",
            "frame_origin_latitude_deg": frame.latitude_deg,
            "frame_origin_longitude_deg": frame.longitude_deg,
            "observation_height_m": frame.altitude_m,
            "observation_height_reference": "WGS-84 ellipsoid",
            "utm_epsg": frame.utm_epsg,
            "igrf_inclination_deg": frame.igrf_inclination_deg,
            "igrf_declination_deg": frame.igrf_declination_deg,
        },
    )
    ds["crs"] = xr.DataArray(np.int32(0), attrs=cf)
    enc = {cf_name(mg.name): {"_FillValue": np.float32(np.nan), "zlib": True} for mg in grids}
    enc.update({c: {"_FillValue": None} for c in ("x", "y", "lat", "lon")})
    with atomic_path(path) as tmp:
        ds.to_netcdf(tmp, engine="h5netcdf", encoding=enc)
    return Path(path)
