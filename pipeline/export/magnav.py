"""A map grid as an HDF5 file MagNav.jl's ``get_map`` loads (a scalar ``MapS`` map).

``get_map`` (MagNav.jl ``src/get_map.jl``) reads the datasets ``map`` (``ny`` x ``nx``), ``xx``
(``nx`` longitudes) and ``yy`` (``ny`` latitudes), in degrees by default (``file_units =
:deg``), ``alt`` (one altitude: a level map, m) and, when present, ``info`` (a string) and
``mask`` (``ny`` x ``nx``, 1 where the map holds data). MagNav counts a zero cell as no data, so
cells outside the coverage are 0 with mask 0.

Julia stores arrays column-major and HDF5.jl reverses the dimensions of a dataset written in
row-major order (h5py): the ``ny`` x ``nx`` Julia matrix is written as its (``nx``, ``ny``)
transpose. MagNav's maps are on longitude/latitude axes, so this is the one export that
resamples: the grid goes (bilinear, :func:`to_lonlat`) from the frame's projected CRS onto a
regular longitude/latitude grid of about the same cell size, ``yy`` ascending.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.export.source import MapFrame, MapGrid
from pipeline.io.writer import atomic_path

M_PER_DEG_LAT = 111_320.0  # a degree of latitude, m (to choose the cell size in degrees)


def to_lonlat(mg: MapGrid, frame: MapFrame):
    """The grid resampled (bilinear) from the frame's CRS onto a regular WGS-84
    longitude/latitude grid covering its cell centres, about the same cell size.

    Each longitude/latitude node is taken into the frame (pyproj) and interpolated there
    (:meth:`pipeline.maps.grid.Grid.interpolate`): NaN outside the cell centres' span or next
    to a masked cell, never extrapolated.

    Returns
    -------
    lon_deg : ndarray
        ``nx`` cell-centre longitudes, ascending.
    lat_deg : ndarray
        ``ny`` cell-centre latitudes, ascending.
    values : ndarray
        ``(ny, nx)``; NaN outside the data.
    """
    g = mg.grid
    gf = frame.grid_frame()
    east, north = g.coordinates()
    # the span of the cell centres, its border sampled (a projected rectangle is curved)
    edge_e = np.concatenate(
        [east, east, np.full(north.size, east[0]), np.full(north.size, east[-1])]
    )
    edge_n = np.concatenate(
        [np.full(east.size, north[0]), np.full(east.size, north[-1]), north, north]
    )
    lat_b, lon_b, _ = gf.to_geodetic(edge_e, edge_n)
    # about the frame's longitude: a survey across the antimeridian spans a few cells, not
    # the globe (longitudes past 180 deg then run on, as MagNav's interpolation needs)
    lon_b = frame.longitude_deg + np.mod(lon_b - frame.longitude_deg + 180.0, 360.0) - 180.0
    dlat = g.cell_m / M_PER_DEG_LAT
    dlon = dlat / max(np.cos(np.radians(frame.latitude_deg)), 1e-6)
    lon = lon_b.min() + dlon * np.arange(int(np.floor(np.ptp(lon_b) / dlon)) + 1)
    lat = lat_b.min() + dlat * np.arange(int(np.floor(np.ptp(lat_b) / dlat)) + 1)
    lo, la = np.meshgrid(lon, lat)
    e, n, _ = gf.to_enu(la, lo)
    return lon, lat, g.interpolate(e, n)


def write_magnav_h5(path: str | Path, mg: MapGrid, frame: MapFrame, info: str = "") -> Path:
    """One grid channel as a MagNav.jl map file (see the module docstring), written
    atomically. ``alt`` is the frame's altitude: the mean survey height above the WGS-84
    ellipsoid, m."""
    import h5py

    lon, lat, values = to_lonlat(mg, frame)
    valid = np.isfinite(values)
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            f.create_dataset("info", data=info or f"aeromag {mg.topic} ({mg.field_name})")
            f.create_dataset("map", data=np.where(valid, values, 0.0).T)
            f.create_dataset("xx", data=lon.astype(np.float64))
            f.create_dataset("yy", data=lat.astype(np.float64))
            f.create_dataset("alt", data=np.float64(frame.altitude_m))
            f.create_dataset("mask", data=valid.astype(np.int8).T)
    return Path(path)
