"""Exports: GeoTIFF (UTM), CF netCDF, line CSV/XYZ and MagNav HDF5 from a processed MCAP."""

from __future__ import annotations

import csv

import numpy as np
import pytest
from pyproj import Transformer

import tests.cli
from pipeline.errors import AeromagError
from pipeline.export import export_recording
from pipeline.geo.local import LocalFrame, utm_epsg
from tests.mapfile import ALT0, LAT0, LON0, field_nT, write_processed
from tests.recordings import validate_every_message

EPSG = utm_epsg(LAT0, LON0)
ALL = ("geotiff", "netcdf", "csv", "xyz", "magnav")


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    d = tmp_path_factory.mktemp("export")
    src, grid = write_processed(d / "flight.processed.mcap")
    written = export_recording(src, d / "out", ALL)
    return d / "out", grid, written, src


def test_the_synthetic_recording_validates(exported):
    _, _, _, src = exported
    assert validate_every_message(src, {"/map/frame", "/map/anomaly", "/map/lines"}) > 50


def test_every_format_and_grid_is_written(exported):
    out, _, written, _ = exported
    names = sorted(p.name for p in out.iterdir())
    assert names == [
        "flight.anomaly.magnav.h5",
        "flight.anomaly.tif",
        "flight.anomaly_filtered.magnav.h5",
        "flight.anomaly_filtered.tif",
        "flight.lines.csv",
        "flight.lines.xyz",
        "flight.maps.nc",
    ]
    assert set(written) == set(ALL)


def test_netcdf_is_the_native_grid_cell_for_cell(exported):
    import xarray as xr

    out, grid, _, _ = exported
    with xr.open_dataset(out / "flight.maps.nc") as ds:
        assert ds.attrs["Conventions"] == "CF-1.8"
        a = ds["anomaly"]
        assert a.attrs["units"] == "nT" and a.attrs["grid_mapping"] == "crs"
        np.testing.assert_array_equal(a.to_numpy(), grid.values.astype(np.float32))
        east, north = grid.coordinates()
        np.testing.assert_allclose(ds["x"].to_numpy(), east)
        np.testing.assert_allclose(ds["y"].to_numpy(), north)
        assert ds["x"].attrs["standard_name"] == "projection_x_coordinate"
        assert ds["crs"].attrs["grid_mapping_name"] == "azimuthal_equidistant"
        assert ds["crs"].attrs["latitude_of_projection_origin"] == pytest.approx(LAT0)
        # a known point: the cell whose centre is nearest in lat/lon is the point's cell
        lat, lon, _ = LocalFrame(LAT0, LON0, ALT0).to_geodetic(east[17], north[11])
        d2 = (ds["lat"].to_numpy() - lat) ** 2 + (ds["lon"].to_numpy() - lon) ** 2
        assert np.unravel_index(np.argmin(d2), d2.shape) == (11, 17)
    # and the CRS round-trips through rioxarray (GDAL reads the grid mapping)
    import rioxarray  # noqa: F401

    with xr.open_dataset(out / "flight.maps.nc", decode_coords="all") as ds:
        assert ds["anomaly"].rio.crs is not None
        assert "Azimuthal" in ds["anomaly"].rio.crs.to_wkt()
    # GDAL's netCDF driver places it: north-up, corner half a cell beyond the first centres
    import rasterio

    with rasterio.open(f"netcdf:{out / 'flight.maps.nc'}:anomaly") as gd:
        assert gd.shape == grid.shape
        t = gd.transform
        assert (t.a, t.e) == pytest.approx((grid.cell_m, -grid.cell_m))
        assert t.c == pytest.approx(east[0] - grid.cell_m / 2)
        assert t.f == pytest.approx(north[-1] + grid.cell_m / 2)
        np.testing.assert_array_equal(gd.read(1), grid.values[::-1].astype(np.float32))


def test_geotiff_is_utm_and_matches_the_grid_at_cell_centres(exported):
    import rasterio

    out, grid, _, _ = exported
    with rasterio.open(out / "flight.anomaly.tif") as ds:
        assert ds.crs.to_epsg() == EPSG == 32649
        assert ds.res == pytest.approx((grid.cell_m, grid.cell_m))
        assert np.isnan(ds.nodata) and ds.tags(1)["units"] == "nT"
        v = ds.read(1)
        rows, cols = np.indices(v.shape)
        x, y = rasterio.transform.xy(ds.transform, rows.ravel(), cols.ravel())
    to_local = Transformer.from_crs(f"EPSG:{EPSG}", grid.crs, always_xy=True)
    e, n = to_local.transform(np.asarray(x), np.asarray(y))
    native = grid.interpolate(e, n)  # NaN outside or next to a masked cell
    tif = v.ravel()
    both = np.isfinite(native) & np.isfinite(tif)
    assert both.sum() > 0.8 * np.isfinite(grid.values).sum()
    # GDAL's bilinear resampling is the grid's own bilinear interpolation (measured: 1e-4 nT,
    # float32); both are within 0.06 nT of the analytic field on a +-60 nT anomaly
    assert np.max(np.abs(tif[both] - native[both])) < 0.01
    assert np.max(np.abs(tif[both] - field_nT(e, n)[both])) < 0.1
    # nodata outside: the uncovered corner and the rotated raster's margins are NaN
    assert np.isnan(tif).sum() > 0
    assert not np.isfinite(tif[np.isnan(native) & (np.abs(e) > 1e4)]).any()


def test_a_known_survey_point_lands_in_the_right_geotiff_cell(exported):
    import rasterio

    out, grid, _, _ = exported
    east, north = grid.coordinates()
    e0, n0 = east[20] + 3.0, north[9] - 4.0  # a point inside cell (9, 20)
    lat, lon, _ = LocalFrame(LAT0, LON0, ALT0).to_geodetic(e0, n0)
    x, y = Transformer.from_crs("EPSG:4326", f"EPSG:{EPSG}", always_xy=True).transform(lon, lat)
    with rasterio.open(out / "flight.anomaly.tif") as ds:
        r, c = ds.index(x, y)
        cx, cy = rasterio.transform.xy(ds.transform, r, c)
        value = ds.read(1)[r, c]
    assert abs(cx - x) <= grid.cell_m / 2 + 1e-6 and abs(cy - y) <= grid.cell_m / 2 + 1e-6
    ce, cn = Transformer.from_crs(f"EPSG:{EPSG}", grid.crs, always_xy=True).transform(cx, cy)
    assert value == pytest.approx(field_nT(ce, cn), abs=0.2)


def test_line_csv_and_xyz(exported):
    out, _, _, _ = exported
    with open(out / "flight.lines.csv") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == [
        "line",
        "fiducial",
        "time",
        "lon",
        "lat",
        "x",
        "y",
        "altitude",
        "raw",
        "compensated",
        "levelled",
        "anomaly",
    ]
    assert len(rows) == 80
    assert [r["line"] for r in rows[:1]] == ["L0010"] and rows[-1]["line"] == "T0010"
    assert rows[3]["raw"] == ""  # the missing raw sample
    to_utm = Transformer.from_crs("EPSG:4326", f"EPSG:{EPSG}", always_xy=True)
    for r in rows[::17]:
        x, y = to_utm.transform(float(r["lon"]), float(r["lat"]))
        assert float(r["x"]) == pytest.approx(x, abs=0.01)
        assert float(r["y"]) == pytest.approx(y, abs=0.01)
        assert float(r["levelled"]) - float(r["anomaly"]) == pytest.approx(52990.0, abs=0.002)
    text = (out / "flight.lines.xyz").read_text().splitlines()
    assert text[0].startswith("/ ") and f"EPSG:{EPSG}" in text[1]
    assert text[2].split()[1:] == [
        "fiducial",
        "time",
        "lon",
        "lat",
        "x",
        "y",
        "altitude",
        "raw",
        "compensated",
        "levelled",
        "anomaly",
    ]
    assert [t for t in text if t[:4] in ("Line", "Tie ")] == [
        "Line L0010",
        "Line L0020",
        "Tie T0010",
    ]
    data = [t.split() for t in text if t.startswith("  ")]
    assert len(data) == 80 and all(len(d) == 11 for d in data)
    assert data[3][7] == "*"


def test_magnav_file_has_the_fields_get_map_reads(exported):
    import h5py

    out, grid, _, _ = exported
    with h5py.File(out / "flight.anomaly.magnav.h5") as f:
        assert {"map", "xx", "yy", "alt", "info", "mask"} <= set(f)
        xx, yy, m, mask = f["xx"][()], f["yy"][()], f["map"][()], f["mask"][()]
        assert f["alt"][()] == pytest.approx(ALT0)
    # Julia reads the row-major (nx, ny) dataset as its ny x nx transpose
    assert m.shape == (xx.size, yy.size) == mask.shape
    assert np.all(np.diff(xx) > 0) and np.all(np.diff(yy) > 0)
    assert LON0 - 0.01 < xx.mean() < LON0 + 0.01 and LAT0 - 0.01 < yy.mean() < LAT0 + 0.01
    assert np.array_equal(mask.astype(bool), m != 0)
    frame = LocalFrame(LAT0, LON0, ALT0)
    j, i = np.nonzero(mask)  # j: column (xx), i: row (yy)
    e, n, _ = frame.to_enu(yy[i], xx[j])
    np.testing.assert_allclose(m[j, i], field_nT(e, n), atol=0.2)


def test_magnav_file_reads_back_through_the_navigation_map_reader(exported):
    """The exported MagNav map, read by ``aeromag navigate``'s MagNav reader (written
    separately from get_map.jl), gives the field at the right places."""
    from pipeline.navigation.map_io import read_map

    out, _, _, _ = exported
    m = read_map(out / "flight.anomaly.magnav.h5")
    assert m.altitude_m == pytest.approx(ALT0)
    gx, gy = np.meshgrid(*m.grid.coordinates())
    lat, lon = m.to_geodetic(gx, gy)
    e, n, _ = LocalFrame(LAT0, LON0, ALT0).to_enu(lat, lon)
    ok = np.isfinite(m.grid.values) & (m.grid.values != 0)
    assert ok.sum() > 100
    np.testing.assert_allclose(m.grid.values[ok], field_nT(e[ok], n[ok]), atol=0.3)


def test_a_recording_without_maps_is_one_line_naming_what_is_missing(tmp_path):
    src, _ = write_processed(tmp_path / "raw.mcap", frame=False, lines=False, grids=False)
    with pytest.raises(AeromagError) as exc:
        export_recording(src, tmp_path / "out")
    msg = str(exc.value)
    assert "/map/anomaly" in msg and "aeromag process" in msg and "\n" not in msg
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())
    src, _ = write_processed(tmp_path / "old.mcap", frame=False)
    with pytest.raises(AeromagError, match="/map/frame"):
        export_recording(src, tmp_path / "out")
    src, _ = write_processed(tmp_path / "nolines.mcap", lines=False)
    with pytest.raises(AeromagError, match="/map/lines"):
        export_recording(src, tmp_path / "out", ["csv"])
    with pytest.raises(AeromagError, match="unknown export format 'kml'"):
        export_recording(src, tmp_path / "out", ["geotiff", "kml"])


def test_cli_export_and_its_one_line_error(tmp_path):
    src, _ = write_processed(tmp_path / "f.processed.mcap")
    raw, _ = write_processed(tmp_path / "raw.mcap", frame=False, lines=False, grids=False)
    res = tests.cli.run("export", str(src), "--out", str(tmp_path / "o"), "--format", "geotiff,csv")
    assert res.returncode == 0, res.stderr
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == [
        "f.anomaly.tif",
        "f.anomaly_filtered.tif",
        "f.lines.csv",
    ]
    bad = tests.cli.run("export", str(raw), "--out", str(tmp_path / "o2"))
    assert bad.returncode == 2
    lines = bad.stderr.strip().splitlines()
    assert len(lines) == 1 and "aeromag process" in lines[0] and "Traceback" not in bad.stderr


def test_utm_zone_of_a_point():
    assert utm_epsg(34.26, 108.9) == 32649  # the demo survey (Xi'an)
    assert utm_epsg(-33.9, 151.2) == 32756  # southern hemisphere: 327zz
    assert utm_epsg(45.0, -75.7) == 32618
    assert utm_epsg(0.0, 179.99) == 32660 and utm_epsg(0.0, -180.0) == 32601
