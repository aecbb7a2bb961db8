"""The post-flight flow under Prefect (test harness) and through the command line."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

import tests.cli
from pipeline.io.scan import scan_mcap
from tests.conftest import sha256


def _messages(path):
    """(topic, log_time, payload) of every message, by our salvaging scanner (fast)."""
    sc = scan_mcap(path)
    return sorted(
        (ch.topic, t, d)
        for ch in sc.channels.values()
        for t, d in zip(ch.log_time_ns, ch.data, strict=True)
    )


def _log_lines(path) -> list[str]:
    """The messages of a recording's /aeromag/log, in time order."""
    return [json.loads(d)["message"] for topic, _, d in _messages(path) if topic == "/aeromag/log"]


def test_postflight_flow_writes_input_plus_new_channels(demo_output):
    """The demo (the README's first command) through the Prefect flow: the input untouched,
    copied record for record, plus every new channel."""
    out_dir, summary = demo_output
    src = out_dir / "demo_flight.mcap"
    out = out_dir / "demo_flight.processed.mcap"
    assert summary["outputs"]["mcap"] == str(out)
    assert summary["input"]["sha256"] == sha256(src)  # read-only: the hash did not change
    new = {
        "/aeromag/log",
        "/flight/segment",
        "/mag/compensated",
        "/mag/compensated/tl16",
        "/mag/compensated/tl18",
        "/mag/compensated/agg-tl",
        "/compensation/model",
        "/audit/finding",
        "/mag/vector/compensated",
        "/map/frame",
        "/map/anomaly",
        "/map/anomaly_filtered",
        "/map/uncertainty",
        "/map/navigability",
        "/map/lines",
        "/map/tracks",
        "/quality/heading_error",
        "/quality/crossovers",
        "/nav/ins",
        "/nav/map_aided",
        "/nav/error",
        "/nav/innovation",
    }
    assert set(summary["channels_written"]) == new
    # exports on by default, read back from the processed MCAP: GeoTIFF + netCDF
    assert set(summary["exports"]) == {"geotiff", "netcdf"}
    for f in ("demo_flight.anomaly.tif", "demo_flight.anomaly_filtered.tif", "demo_flight.maps.nc"):
        assert (out_dir / f).stat().st_size > 10000
    comp = summary["compensation"]
    assert {"tl16", "tl18", "agg-tl"} <= set(comp)
    assert comp["final"] == "tl18+geomagnetic_gradient"  # the audit's extended model
    for m in ("tl16", "tl18", "agg-tl"):
        assert comp[m]["fom_nT"]["uncompensated"] > 5 * comp[m]["fom_nT"]["compensated"]
    assert summary["segments"]["boxes"] == 24 and summary["segments"]["calibration_passes"] == 2
    assert summary["config"]["version"] == 1 and len(summary["config"]["hash"]) == 64
    assert "audit" in summary and summary["vector"]["method"] == "component-kf"
    assert (out_dir / "demo_flight.report.md").read_text().startswith("# Post-flight")
    for png in ("lcurve", "compensation", "audit_residual_time", "flight_map", "anomaly"):
        assert (out_dir / f"demo_flight.{png}.png").stat().st_size > 10000
    m_in, m_out = _messages(src), _messages(out)
    assert [m for m in m_out if m[0] not in new] == m_in
    assert {m[0] for m in m_out} == {m[0] for m in m_in} | new


def test_the_exported_geotiff_lands_on_the_simulated_anomaly(demo_output):
    """End to end: the post-flight GeoTIFF (UTM: the computed cells), its cell centres
    taken back into the simulator's own frame, is the true anomaly there (up to the regional
    plane the map keeps), and no shift of the truth fits better."""
    import numpy as np
    import rasterio
    from pyproj import Transformer

    from pipeline.maps.grid import Grid

    out_dir, _ = demo_output
    t = json.loads((out_dir / "demo_truth.json").read_text())
    g = t["anomaly"]["grid"]
    truth = Grid(
        np.array(g["values_nT"], float),
        g["east0_m"],
        g["north0_m"],
        g["cell_m"],
        t["site"]["local_frame"],
    )
    with rasterio.open(out_dir / "demo_flight.anomaly_filtered.tif") as ds:
        v = ds.read(1).ravel()
        rows, cols = np.indices(ds.shape)
        x, y = rasterio.transform.xy(ds.transform, rows.ravel(), cols.ravel())
        epsg = ds.crs.to_epsg()
    assert epsg == 32649
    e, n = Transformer.from_crs(f"EPSG:{epsg}", truth.crs, always_xy=True).transform(x, y)

    def fit(de, dn):  # map = plane + gain * truth shifted by (de, dn) m
        tv = truth.interpolate(e + de, n + dn)
        ok = np.isfinite(tv) & np.isfinite(v)
        a = np.column_stack([np.ones(ok.sum()), e[ok], n[ok], tv[ok]])
        coef, *_ = np.linalg.lstsq(a, v[ok], rcond=None)
        return float(np.sqrt(np.mean((v[ok] - a @ coef) ** 2))), float(coef[3]), int(ok.sum())

    rms, gain, cells = fit(0.0, 0.0)
    assert cells > 5000 and abs(gain - 1.0) < 0.02 and rms < 0.5
    assert all(fit(de, dn)[0] > rms for de, dn in ((10, 0), (-10, 0), (0, 10), (0, -10)))


def _decode_grid_channel(path, topic):
    """The cells of a ``foxglove.Grid`` channel and their centres' easting/northing, decoded
    here from the MCAP and ``/map/frame`` alone (schemas/README.md), not by our reader."""
    import base64

    import numpy as np

    msgs = {t: json.loads(d) for t, _, d in _messages(path) if t in (topic, "/map/frame")}
    g, f = msgs[topic], msgs["/map/frame"]
    nx, cell = g["column_count"], g["cell_size"]["x"]
    values = np.frombuffer(base64.b64decode(g["data"]), "<f4").reshape(-1, nx)
    ny = values.shape[0]
    x = f["origin_easting_m"] + g["pose"]["position"]["x"] + (np.arange(nx) + 0.5) * cell
    y = f["origin_northing_m"] + g["pose"]["position"]["y"] + (np.arange(ny) + 0.5) * cell
    return values, x, y, f


def test_the_exports_hold_the_channels_cells_exactly(demo_output):
    """GeoTIFF and netCDF are /map/anomaly_filtered and /map/anomaly as computed: same count
    of valid cells, same float32 values, centres at the same easting/northing in the survey's
    UTM zone (the demo's: 49N); a known point of a flight line lands in its cell."""
    import numpy as np
    import rasterio
    import xarray as xr
    from pyproj import Transformer

    out_dir, summary = demo_output
    out = out_dir / "demo_flight.processed.mcap"
    o = summary["map"]["origin"]
    assert o["crs"] == "EPSG:32649" and o["utm_zones_spanned"] == [32649]
    for name in ("anomaly", "anomaly_filtered", "uncertainty", "navigability"):
        cells, x, y, frame = _decode_grid_channel(out, f"/map/{name}")
        assert frame["crs"] == "EPSG:32649" and frame["epsg"] == 32649
        with rasterio.open(out_dir / f"demo_flight.{name}.tif") as ds:
            assert ds.crs.to_epsg() == 32649 and ds.shape == cells.shape
            tif = ds.read(1)[::-1]  # north-up rows in the file
            cx, _ = rasterio.transform.xy(ds.transform, [0] * cells.shape[1], range(cells.shape[1]))
            _, cy = rasterio.transform.xy(ds.transform, range(cells.shape[0]), [0] * cells.shape[0])
        assert np.isfinite(tif).sum() == np.isfinite(cells).sum() > 5000
        np.testing.assert_array_equal(tif, cells)
        np.testing.assert_allclose(cx, x, atol=1e-6)
        np.testing.assert_allclose(np.asarray(cy)[::-1], y, atol=1e-6)
        with xr.open_dataset(out_dir / "demo_flight.maps.nc") as nc:
            np.testing.assert_array_equal(nc[name].to_numpy(), cells)
            np.testing.assert_allclose(nc["x"].to_numpy(), x, atol=1e-6)
            np.testing.assert_allclose(nc["y"].to_numpy(), y, atol=1e-6)
    # a known point: a line sample's position falls in the cell whose centre is within half
    # a cell of it, in the file as in the channel
    sample = next(json.loads(d) for t, _, d in _messages(out) if t == "/map/lines")
    px, py = Transformer.from_crs("EPSG:4326", "EPSG:32649", always_xy=True).transform(
        sample["longitude"], sample["latitude"]
    )
    assert px - frame["origin_easting_m"] == pytest.approx(sample["east_m"], abs=0.01)
    cells, x, y, _ = _decode_grid_channel(out, "/map/anomaly")
    col, row = int(np.argmin(np.abs(x - px))), int(np.argmin(np.abs(y - py)))
    cell = x[1] - x[0]
    assert abs(x[col] - px) <= cell / 2 + 1e-6 and abs(y[row] - py) <= cell / 2 + 1e-6
    with rasterio.open(out_dir / "demo_flight.anomaly.tif") as ds:
        r, c = ds.index(px, py)
        assert (ds.height - 1 - r, c) == (row, col)
        assert ds.read(1)[r, c] == cells[row, col]


def test_summary_records_stage_timings_and_peak_memory(demo_output):
    """`timings_s`: seconds of every stage that ran (compensate summed over the models), the
    write up to the summary itself; `peak_memory_mb`: the process's peak resident memory."""
    _, summary = demo_output
    t = summary["timings_s"]
    assert list(t) == [
        "ingest",
        "despike",
        "segment",
        "compensate",
        "audit",
        "vector",
        "map",
        "quality",
        "navigate",
        "navigability",
        "write",
    ]
    assert all(isinstance(v, float) and 0 <= v < 600 for v in t.values())
    assert t["ingest"] > 0.05 and t["audit"] > t["segment"]  # the flight was really read
    assert 100 < summary["peak_memory_mb"] < 4000


def test_process_command_runs_the_flow_without_a_server(box_path, tmp_path):
    """`aeromag process` with no Prefect server configured: a temporary one is started."""
    env = {**os.environ, "PREFECT_HOME": str(tmp_path / "prefect")}
    env.pop("PREFECT_API_URL", None)
    res = subprocess.run(
        [
            sys.executable,
            "-m",
            "flows.cli",
            "process",
            str(box_path),
            "--out",
            str(tmp_path / "out"),
        ],
        capture_output=True,
        text=True,
        env=env,
        timeout=600,
    )
    assert res.returncode == 0, res.stderr[-2000:]
    out = tmp_path / "out" / "box_uav.processed.mcap"
    assert f"output recording: {out}" in res.stdout
    insp = tests.cli.run("inspect", str(out))  # in-process: the process above was the script
    assert insp.returncode == 0 and "/mag/compensated" in insp.stdout
    # a calibration box alone: no map, so navigation is skipped in one log line, no error,
    # and the reason there is no map is said
    summary = json.loads((tmp_path / "out" / "box_uav.summary.json").read_text())
    assert summary["navigation"]["skipped"].startswith("no map (0 survey epochs: no block")
    assert summary["navigability"] == summary["navigation"]
    assert not any(t.startswith("/nav/") for t in summary["channels_written"])


def test_postflight_navigates_the_validation_lines_on_its_own_map(demo_output):
    """Issue 18, item 6: the flow flies the demo's two validation lines with a simulated
    navigation-grade INS aided by the flight's filtered map. The errors are against the
    simulator's own track (/gnss/fix is the truth plus GNSS noise), the map-aided DRMS well
    below the INS alone's and within a few CRLBs; channels valid (every channel is checked in
    tests/test_viewing.py), figures, report sections and the Map panel's three tracks."""
    out_dir, summary = demo_output
    nav = summary["navigation"]
    d = nav["drms_m"]
    assert set(d) == {"ins_only", "map_aided", "crlb"} and set(nav["cep50_m"]) == {
        "ins_only",
        "map_aided",
    }
    assert set(nav["segments"]) == {"V0010", "V0020"}
    assert nav["settings"]["segments"] == "validation" and nav["settings"]["seed"] == 0
    assert nav["map"]["file"] == "/map/anomaly_filtered"
    assert d["map_aided"] < d["ins_only"] / 5 and d["map_aided"] < 3 * d["crlb"]
    assert summary["timings_s"]["navigate"] < 60
    for png in ("navigation_track", "navigation_error"):
        assert (out_dir / f"demo_flight.{png}.png").stat().st_size > 10000
    report = (out_dir / "demo_flight.report.md").read_text()
    assert "## Navigation on the map" in report and "demo_flight.navigation_track.png" in report
    page = (out_dir / "demo_flight.report.html").read_text()
    assert "Navigation on the map" in page and 'id="fig-navigation_error"' in page
    layout = json.loads((out_dir / "demo_flight.layout.json").read_text())["configById"]
    colours = layout["map!aeromag-track"]["topicColors"]
    assert {"/gnss/fix", "/nav/ins", "/nav/map_aided"} <= set(colours)
    assert len({colours[t] for t in ("/gnss/fix", "/nav/ins", "/nav/map_aided")}) == 3
    assert layout["map!aeromag-track"]["followTopic"] == "/gnss/fix"
    plot = [p["value"] for p in layout["Plot!aeromag-navigation"]["paths"]]
    assert "/nav/error.map_aided_horizontal_m" in plot and "/nav/error.crlb_drms_m" in plot
    log = _log_lines(out_dir / "demo_flight.processed.mcap")
    assert any(ln.startswith("navigate: ekf on validation with a navigation-grade") for ln in log)


def test_postflight_maps_the_navigability_of_its_own_map(demo_output):
    """Issue 38, item 6: the flow turns its filtered map into /map/navigability (m) on the
    map's cells with its /map/uncertainty, at the survey's speed on lines sized to the map;
    the summary holds the command's block, the report one line and the figure."""

    import numpy as np

    out_dir, summary = demo_output
    nb = summary["navigability"]
    assert set(nb) == {
        "channel",
        "speed_mps",
        "headings_deg",
        "line_s",
        "start_sigma_m",
        "sensor_sigma_nT",
        "map_sigma",
        "drms_m",
    }
    assert nb["channel"] == "/map/navigability" and nb["map_sigma"] == "grid"
    assert nb["headings_deg"] == [0.0, 45.0, 90.0, 135.0]
    assert 3.0 < nb["speed_mps"] < 30.0  # the UAV's ground speed, not a default
    assert len(nb["line_s"]) == 4 and all(20.0 <= t <= 120.0 for t in nb["line_s"])
    assert min(nb["line_s"]) < 120.0  # shorter than the fixed line across this small map
    cells, *_ = _decode_grid_channel(out_dir / "demo_flight.processed.mcap", "/map/navigability")
    anomaly, *_ = _decode_grid_channel(out_dir / "demo_flight.processed.mcap", "/map/anomaly")
    assert np.array_equal(np.isfinite(cells), np.isfinite(anomaly))
    v = cells[np.isfinite(cells)]
    assert (v > 0).all()
    d = nb["drms_m"]
    assert d["p10"] < d["median"] < d["p90"]
    assert d["median"] == pytest.approx(float(np.median(v)), rel=1e-3)
    assert "navigability" in summary["timings_s"]
    assert (out_dir / "demo_flight.navigability.png").stat().st_size > 10000
    report = (out_dir / "demo_flight.report.md").read_text()
    assert "## Navigability of the map" in report and f"{d['median']:.1f} m at the median" in report
    page = (out_dir / "demo_flight.report.html").read_text()
    assert "Navigability of the map" in page and 'id="fig-navigability"' in page
    log = _log_lines(out_dir / "demo_flight.processed.mcap")
    assert any(ln.startswith("navigability: /map/navigability, CRLB DRMS") for ln in log)


def test_navigation_is_skipped_without_validation_lines_or_a_map():
    """One log line, never an error: no map, no validation lines."""
    import numpy as np

    from pipeline.config import Config
    from pipeline.products.log import navigation_lines
    from pipeline.run.steps import navigability_stage, navigate_stage

    class NoValidation:  # a segmentation whose flight has no validation epochs
        def mask(self, *labels):
            return np.zeros(100, bool)

    cfg = Config.load()
    assert navigate_stage(None, None, None, None, cfg) == "no map"
    assert navigability_stage(None, None, None, cfg) == "no map"
    assert navigate_stage(None, NoValidation(), None, object(), cfg) == "no validation lines"
    assert navigation_lines("no validation lines") == [
        (navigation_lines("x")[0][0], "navigate: skipped: no validation lines")
    ]
