"""Map grids as GeoTIFF and CF-1.8 netCDF: the computed cells, unchanged.

The grids are computed in the projected CRS of ``/map/frame`` (the survey's UTM zone, or
``map.crs``), their poses in metres about the frame's origin: a file's cell centres are the
origin plus those metres, its values the channel's float32 cells (same count, NaN = no data).
Nothing is resampled. A recording processed before the grids were computed in a projected CRS
is written the same way, in the azimuthal equidistant CRS it was computed in.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline import __version__
from pipeline.export.source import MapFrame, MapGrid
from pipeline.io.writer import atomic_path
from pipeline.maps.grid import Grid


def grid_in_crs(grid: Grid, frame: MapFrame) -> Grid:
    """The grid with its cell centres as eastings and northings in the frame's CRS (m):
    the same values, the origin added (``crs`` then names the CRS itself)."""
    return Grid(
        grid.values,
        frame.origin_easting_m + grid.east0_m,
        frame.origin_northing_m + grid.north0_m,
        grid.cell_m,
        frame.crs,
    )


def write_geotiff(path: str | Path, mg: MapGrid, frame: MapFrame) -> Path:
    """One grid channel as a single-band float32 GeoTIFF in the frame's CRS, its cells as
    computed (north-up rows; deflate, nodata NaN; band description and ``units`` tag from
    the channel), written atomically. The geotransform puts the first cell's centre at the
    frame's origin plus the channel's first cell centre."""
    import rasterio
    from affine import Affine
    from pyproj import CRS

    g = grid_in_crs(mg.grid, frame)
    ny, nx = g.shape
    c = g.cell_m
    # north-up: the top row is the grid's last (northernmost); corners half a cell out
    transform = Affine(c, 0.0, g.east0_m - c / 2, 0.0, -c, g.north0_m + (ny - 0.5) * c)
    crs = rasterio.crs.CRS.from_wkt(CRS.from_user_input(g.crs).to_wkt())
    profile = {
        "driver": "GTiff",
        "height": ny,
        "width": nx,
        "count": 1,
        "dtype": "float32",
        "crs": crs,
        "transform": transform,
        "nodata": np.nan,
        "compress": "DEFLATE",
    }
    with atomic_path(path) as tmp, rasterio.open(tmp, "w", **profile) as ds:
        ds.write(np.ascontiguousarray(g.values[::-1], dtype=np.float32), 1)
        ds.set_band_description(1, mg.field_name)
        ds.update_tags(1, units=mg.units)
        ds.update_tags(
            long_name=mg.field_name, units=mg.units, source=f"aeromag {__version__}: {mg.topic}"
        )
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


def _error_length(mg: MapGrid, frame: MapFrame) -> dict[str, float]:
    """The map error's correlation length (m) as an attribute of the uncertainty variable,
    where ``/map/frame`` records it: what ``aeromag navigate`` reads back with the σ."""
    from pipeline.navigation.map_io import ERROR_LENGTH_ATTR, UNCERTAINTY_CHANNEL

    if mg.topic != UNCERTAINTY_CHANNEL or frame.error_length_m is None:
        return {}
    return {ERROR_LENGTH_ATTR: float(frame.error_length_m)}


def write_netcdf(path: str | Path, grids: list[MapGrid], frame: MapFrame) -> Path:
    """Every grid channel as a variable (:func:`cf_name` of its name) of one CF-1.8
    netCDF-4 file, its cells as computed.

    Coordinates ``x``, ``y`` (m, the cell centres' easting/northing in the frame's CRS),
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
    east, north = grid_in_crs(first, frame).coordinates()
    crs = CRS.from_user_input(frame.crs)
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
                    **_error_length(mg, frame),
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
            "frame_origin_easting_m": frame.origin_easting_m,
            "frame_origin_northing_m": frame.origin_northing_m,
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
