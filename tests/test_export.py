"""Exports: GeoTIFF and CF netCDF (the channel's cells in its CRS), line CSV/XYZ and MagNav
HDF5 from a processed MCAP."""

from __future__ import annotations

import csv

import numpy as np
import pytest
from pyproj import Transformer

import tests.cli
from pipeline.errors import AeromagError
from pipeline.export import export_recording
from pipeline.geo.local import LocalFrame
from pipeline.geo.projected import utm_epsg
from tests.mapfile import ALT0, LAT0, LON0, field_nT, map_frame, write_processed
from tests.recordings import validate_every_message

EPSG = utm_epsg(LAT0, LON0)
ALL = ("geotiff", "netcdf", "csv", "xyz", "magnav")


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    d = tmp_path_factory.mktemp("export")
    src, grid = write_processed(d / "flight.processed.mcap", uncertainty=True)
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
        "flight.uncertainty.tif",
    ]
    assert set(written) == set(ALL)


def test_the_uncertainty_grid_is_exported_cell_for_cell(exported):
    """/map/uncertainty is written with the other grids: the GeoTIFF and the netCDF hold
    the channel's cells exactly, on the anomaly's cells (not as a MagNav map: MagNav's map
    file has no error field, and an error grid read as a map would be navigated on)."""
    import xarray as xr

    out, _, _, src = exported
    sigma, _ = _channel(src, "uncertainty")
    grid, _ = _channel(src)
    v, x, y, _, _, _, units = _geotiff(out / "flight.uncertainty.tif")
    np.testing.assert_array_equal(v, sigma.values.astype(np.float32))
    assert units == "nT" and sigma.shape == grid.shape
    _, xa, ya, *_ = _geotiff(out / "flight.anomaly.tif")
    np.testing.assert_array_equal(x, xa)
    np.testing.assert_array_equal(y, ya)
    assert np.array_equal(np.isfinite(v), np.isfinite(grid.values))
    with xr.open_dataset(out / "flight.maps.nc") as ds:
        np.testing.assert_array_equal(ds["uncertainty"].to_numpy(), sigma.values.astype(np.float32))
        assert ds["uncertainty"].attrs["units"] == "nT"


def _channel(src, name="anomaly"):
    """The grid channel and frame read back from the processed MCAP."""
    from pipeline.export.source import read_map_products

    mp = read_map_products(src)
    return mp.grid(name).grid, mp.frame


def test_netcdf_holds_the_channel_cells_exactly(exported):
    import xarray as xr

    out, _, _, src = exported
    grid, frame = _channel(src)
    with xr.open_dataset(out / "flight.maps.nc") as ds:
        assert ds.attrs["Conventions"] == "CF-1.8"
        a = ds["anomaly"]
        assert a.attrs["units"] == "nT" and a.attrs["grid_mapping"] == "crs"
        # the same cells: count, values (float32, as the channel stores them), places
        np.testing.assert_array_equal(a.to_numpy(), grid.values.astype(np.float32))
        assert np.isfinite(a.to_numpy()).sum() == np.isfinite(grid.values).sum()
        east, north = grid.coordinates()
        np.testing.assert_allclose(ds["x"].to_numpy(), frame.origin_easting_m + east, atol=1e-6)
        np.testing.assert_allclose(ds["y"].to_numpy(), frame.origin_northing_m + north, atol=1e-6)
        assert ds["x"].attrs["standard_name"] == "projection_x_coordinate"
        assert ds["crs"].attrs["grid_mapping_name"] == "transverse_mercator"
        assert ds.attrs["utm_epsg"] == EPSG
        # a known point: the cell whose centre is nearest in lat/lon is the point's cell
        lat, lon, _ = map_frame().to_geodetic(east[17], north[11])
        d2 = (ds["lat"].to_numpy() - lat) ** 2 + (ds["lon"].to_numpy() - lon) ** 2
        assert np.unravel_index(np.argmin(d2), d2.shape) == (11, 17)
    # and the CRS round-trips through rioxarray (GDAL reads the grid mapping)
    import rioxarray  # noqa: F401

    with xr.open_dataset(out / "flight.maps.nc", decode_coords="all") as ds:
        assert ds["anomaly"].rio.crs.to_epsg() == EPSG
    # GDAL's netCDF driver places it: north-up, corner half a cell beyond the first centres
    import rasterio

    with rasterio.open(f"netcdf:{out / 'flight.maps.nc'}:anomaly") as gd:
        assert gd.shape == grid.shape
        t = gd.transform
        assert (t.a, t.e) == pytest.approx((grid.cell_m, -grid.cell_m))
        assert t.c == pytest.approx(frame.origin_easting_m + east[0] - grid.cell_m / 2)
        assert t.f == pytest.approx(frame.origin_northing_m + north[-1] + grid.cell_m / 2)
        np.testing.assert_array_equal(gd.read(1), grid.values[::-1].astype(np.float32))


def _geotiff(path):
    """Values (rows south to north, as the channel's), cell-centre eastings/northings and
    the EPSG code of a single-band GeoTIFF."""
    import rasterio

    with rasterio.open(path) as ds:
        v = ds.read(1)[::-1]
        rows, cols = np.indices(ds.shape)
        x, y = rasterio.transform.xy(ds.transform, rows.ravel(), cols.ravel())
        epsg, crs, nodata, units = ds.crs.to_epsg(), ds.crs, ds.nodata, ds.tags(1)["units"]
    shape = v.shape
    x, y = (np.asarray(a).reshape(shape)[::-1] for a in (x, y))
    return v, x, y, epsg, crs, nodata, units


def test_geotiff_holds_the_channel_cells_exactly(exported):
    """No resampling: the GeoTIFF is /map/anomaly cell for cell in the frame's CRS."""
    out, _, _, src = exported
    grid, frame = _channel(src)
    v, x, y, epsg, _, nodata, units = _geotiff(out / "flight.anomaly.tif")
    assert epsg == EPSG == 32649 and frame.epsg == EPSG
    assert np.isnan(nodata) and units == "nT"
    assert v.shape == grid.shape
    assert np.isfinite(v).sum() == np.isfinite(grid.values).sum()
    np.testing.assert_array_equal(v, grid.values.astype(np.float32))
    east, north = grid.coordinates()
    np.testing.assert_allclose(
        x, np.broadcast_to(frame.origin_easting_m + east, v.shape), atol=1e-6
    )
    np.testing.assert_allclose(
        y, np.broadcast_to((frame.origin_northing_m + north)[:, None], v.shape), atol=1e-6
    )
    # the cells are the analytic field at their centres (placed by the CRS alone)
    e, n = x - frame.origin_easting_m, y - frame.origin_northing_m
    ok = np.isfinite(v)
    np.testing.assert_allclose(v[ok], field_nT(e, n)[ok], atol=1e-3)


def test_a_known_survey_point_lands_in_the_right_geotiff_cell(exported):
    import rasterio

    out, grid, _, _ = exported
    east, north = grid.coordinates()
    e0, n0 = east[20] + 3.0, north[9] - 4.0  # a point inside cell (9, 20)
    lat, lon, _ = map_frame().to_geodetic(e0, n0)
    x, y = Transformer.from_crs("EPSG:4326", f"EPSG:{EPSG}", always_xy=True).transform(lon, lat)
    with rasterio.open(out / "flight.anomaly.tif") as ds:
        r, c = ds.index(x, y)
        cx, cy = rasterio.transform.xy(ds.transform, r, c)
        value = ds.read(1)[r, c]
        ny = ds.height
    assert (ny - 1 - r, c) == (9, 20)  # rows north-up in the file
    assert abs(cx - x) <= grid.cell_m / 2 + 1e-6 and abs(cy - y) <= grid.cell_m / 2 + 1e-6
    assert value == np.float32(grid.values[9, 20])


def test_a_legacy_recording_still_exports_its_cells_in_its_own_crs(tmp_path):
    """A recording processed before the change (local azimuthal equidistant /map/frame
    without an EPSG code or origin): every export works, the grids cell for cell in that
    frame's CRS, the lines' x/y in it."""
    from pyproj import CRS

    from pipeline.export.source import read_map_products

    src, grid = write_processed(tmp_path / "old.processed.mcap", legacy=True)
    mp = read_map_products(src)
    assert mp.frame.legacy and mp.frame.epsg is None
    assert (mp.frame.origin_easting_m, mp.frame.origin_northing_m) == (0.0, 0.0)
    written = export_recording(src, tmp_path / "out", ALL)
    assert set(written) == set(ALL)
    v, x, y, epsg, crs, _, _ = _geotiff(tmp_path / "out" / "old.anomaly.tif")
    assert epsg is None and "Azimuthal" in CRS.from_wkt(crs.to_wkt()).to_wkt()
    np.testing.assert_array_equal(v, grid.values.astype(np.float32))
    east, north = grid.coordinates()
    np.testing.assert_allclose(x[0], east, atol=1e-6)
    np.testing.assert_allclose(y[:, 0], north, atol=1e-6)
    with open(tmp_path / "out" / "old.lines.csv") as f:
        row = next(csv.DictReader(f))
    e, n, _ = LocalFrame(LAT0, LON0, ALT0).to_enu(float(row["lat"]), float(row["lon"]))
    assert float(row["x"]) == pytest.approx(float(e), abs=0.01)
    assert float(row["y"]) == pytest.approx(float(n), abs=0.01)


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
    frame = map_frame()
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
    e, n, _ = map_frame().to_enu(lat, lon)
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


@pytest.mark.parametrize("kind", ["rows", "columns"])
def test_the_channels_just_written_export_as_the_file_reads_back(tmp_path, kind):
    """The post-flight write hands its new channels to the export instead of reading the
    output again: decoded from the bytes the writer wrote, the map products equal those read
    back from the file (grids cell for cell, frame, line samples in log-time order)."""
    from pipeline.export.source import read_map_products, written_map_topics
    from pipeline.io.writer import OutputChannel, write_with_new_channels
    from tests.corpus import BOX
    from tests.mapfile import (
        T0,
        frame_payload,
        grid_channel,
        line_payloads,
        synthetic_grid,
        uncertainty_of,
    )

    grid = synthetic_grid()
    frame = OutputChannel("/map/frame", "aeromag.MapFrame")
    frame.add(T0, frame_payload())
    samples = line_payloads(grid)[::-1]  # out of time order: the writer sorts them
    times = np.array([t for t, _ in samples], np.int64)
    channels = [
        frame,
        grid_channel("/map/anomaly", T0, grid, "anomaly_nT"),
        grid_channel("/map/uncertainty", T0, uncertainty_of(grid), "uncertainty_nT"),
    ]
    if kind == "rows":
        channels.append(
            OutputChannel.rows(
                "/map/lines", "aeromag.LineSample", times, lambda k: dict(samples[k][1])
            )
        )
    else:
        columns = {
            k: np.array([p[k] for _, p in samples], None if k != "line_id" else object)
            for k in samples[0][1]
        }
        channels.append(OutputChannel.columns("/map/lines", "aeromag.LineSample", times, columns))
    out = write_with_new_channels(BOX, tmp_path / "f.processed.mcap", channels)
    read = read_map_products(out, lines=True)
    handed = read_map_products(out, lines=True, written=written_map_topics(channels))
    assert handed.frame == read.frame
    assert [g.topic for g in handed.grids] == [g.topic for g in read.grids]
    for a, b in zip(handed.grids, read.grids, strict=True):
        assert (a.field_name, a.time_ns, a.grid.crs) == (b.field_name, b.time_ns, b.grid.crs)
        assert (a.grid.east0_m, a.grid.north0_m, a.grid.cell_m) == (
            b.grid.east0_m,
            b.grid.north0_m,
            b.grid.cell_m,
        )
        np.testing.assert_array_equal(a.grid.values, b.grid.values)
    assert handed.lines == read.lines and len(read.lines) == len(samples)


def test_a_magnav_map_across_the_antimeridian_spans_the_survey(tmp_path, monkeypatch):
    """A survey straddling 180 deg longitude: the MagNav map's longitudes run on past 180
    over the survey's few cells (not round the globe, 2.6 million columns), and the grid
    reads back there."""
    import h5py

    import tests.mapfile as mf

    monkeypatch.setattr(mf, "LAT0", -17.0)
    monkeypatch.setattr(mf, "LON0", 179.999)
    src, _ = write_processed(tmp_path / "flight.processed.mcap")
    export_recording(src, tmp_path / "out", ("magnav",))
    with h5py.File(tmp_path / "out" / "flight.anomaly.magnav.h5") as f:
        lon = np.asarray(f["xx"])  # deg, as MagNav's map files hold them
        mask = np.asarray(f["mask"])
    assert lon.size < 200 and np.all(np.diff(lon) > 0)
    assert lon[0] < 180.0 < lon[-1] < 180.1
    assert mask.mean() > 0.5
    from pipeline.navigation.map_io import read_map

    m = read_map(tmp_path / "out" / "flight.anomaly.magnav.h5")
    gx, gy = np.meshgrid(*m.grid.coordinates())
    lat, lon = m.to_geodetic(gx, gy)
    e, n, _ = mf.map_frame().to_enu(lat, lon)
    ok = np.isfinite(m.grid.values) & (m.grid.values != 0)
    assert ok.sum() > 100
    np.testing.assert_allclose(m.grid.values[ok], field_nT(e[ok], n[ok]), atol=0.3)
