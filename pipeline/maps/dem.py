"""Terrain heights from a digital elevation model (GeoTIFF, any CRS rasterio reads)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.errors import AeromagError


def dem_heights_m(path: str | Path, lat_deg: np.ndarray, lon_deg: np.ndarray) -> np.ndarray:
    """Terrain height (m, the DEM's vertical datum: give heights above the WGS-84 ellipsoid,
    as GNSS altitudes are) at geodetic points, bilinear in the DEM's own grid.

    Raises
    ------
    AeromagError
        The file cannot be read, has no CRS, or covers less than 95 % of the points (the
        message gives the covered fraction).
    """
    import rioxarray
    from pyproj import Transformer

    path = Path(path)
    try:
        dem = rioxarray.open_rasterio(path, masked=True).squeeze("band", drop=True)
    except Exception as exc:  # rasterio's errors have no common base class worth naming
        raise AeromagError(f"cannot read the DEM: {exc}", file=str(path)) from None
    if dem.rio.crs is None:
        raise AeromagError("the DEM has no coordinate reference system", file=str(path))
    to_dem = Transformer.from_crs("EPSG:4326", dem.rio.crs, always_xy=True)
    lat, lon = np.asarray(lat_deg, float), np.asarray(lon_deg, float)
    x, y = to_dem.transform(lon.ravel(), lat.ravel())
    import xarray as xr

    h = dem.interp(
        x=xr.DataArray(np.asarray(x), dims="p"), y=xr.DataArray(np.asarray(y), dims="p")
    ).to_numpy()
    covered = float(np.mean(np.isfinite(h))) if h.size else 0.0
    if covered < 0.95:
        raise AeromagError(
            f"the DEM covers {100 * covered:.0f} % of the map (needs 95 %)", file=str(path)
        )
    return h.reshape(lat.shape)
