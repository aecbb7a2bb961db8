"""Helpers of the navigation command's tests: the in-process CLI, one-line errors, and
GeoTIFF maps placed around the committed box flight."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline.maps.grid import Grid
from pipeline.simulate.navigation import random_field_map


@pytest.fixture(name="cli")
def in_process_cli(capsys, monkeypatch):
    """The real entry point (``flows.cli.main``: one-line errors, exit codes) run in-process
    (a subprocess per call would re-import the stack for seconds)."""
    from flows.cli import main

    def run(*args):
        monkeypatch.setattr("sys.argv", ["aeromag", *[str(a) for a in args]])
        try:
            main()
            code = 0
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 1
        cap = capsys.readouterr()
        return code, (cap.out + cap.err).strip()

    return run


def one_line_error(code, text):
    assert code == 2, text
    assert "Traceback" not in text
    lines = [ln for ln in text.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("aeromag: error:"), text
    return lines[0]


def geotiff(path: Path, grid: Grid, crs: str | None) -> Path:
    import rioxarray  # noqa: F401
    import xarray as xr

    e, n = grid.coordinates()
    da = xr.DataArray(
        grid.values[::-1].astype("float32"),
        coords={"y": n[::-1], "x": e},
        dims=("y", "x"),
        attrs={"altitude_m": 500.0},
    )
    if crs:
        da = da.rio.write_crs(crs)
    da.rio.to_raster(path)
    return path


def navigate_box(path, **settings):
    """The flight at ``path`` (the committed box or a copy of it) through ``run_navigation``
    over a random map placed around it; ``settings``: NavigationSettings fields (segments
    all unless given)."""
    from pipeline.geo.projected import survey_frame
    from pipeline.io.reader import read_flight
    from pipeline.navigation import stage
    from pipeline.navigation.map_io import frame_map

    f = read_flight(path)
    d = f.data
    frame = survey_frame(d["lat_deg"], d["lon_deg"], d["alt_m"])
    g = random_field_map(6, size_m=8000.0, cell_m=25.0, origin_m=(-4000.0, -4000.0))
    geomap = frame_map(g, frame, "test", "random map")
    s = stage.NavigationSettings(**{"segments": "all", **settings})
    return stage.run_navigation(f, None, d["scalar_nT"].to_numpy(float), geomap, s)


def box_frame(box_path):
    from pipeline.io.reader import read_flight

    f = read_flight(box_path)
    lat, lon = f.data["lat_deg"].to_numpy(float), f.data["lon_deg"].to_numpy(float)
    return float(np.nanmean(lat)), float(np.nanmean(lon))


def utm_map(box_path, tmp_path, shift_m=0.0, crs=True) -> Path:
    from pyproj import Transformer

    lat, lon = box_frame(box_path)
    zone = int((lon + 180) // 6) + 1
    epsg = f"EPSG:{32600 + zone if lat >= 0 else 32700 + zone}"
    x0, y0 = Transformer.from_crs("EPSG:4326", epsg, always_xy=True).transform(lon, lat)
    g = random_field_map(6, size_m=6000.0, cell_m=25.0, origin_m=(0.0, 0.0))
    g = Grid(g.values, x0 - 3000.0 + shift_m, y0 - 3000.0, 25.0)
    return geotiff(tmp_path / "map.tif", g, epsg if crs else None)
