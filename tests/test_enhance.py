"""Map enhancements against analytic dipole fields (harmonica's forward model), and the
``aeromag enhance`` command."""

from __future__ import annotations

import numpy as np
import pytest

import tests.cli
from pipeline.errors import AeromagError
from pipeline.maps.enhance import enhance, fill_gaps, parse_products
from pipeline.maps.grid import Grid

INC, DEC = 50.0, 10.0  # main field (and induced magnetisation) direction, deg
CELL = 20.0
SOURCE = (100.0, -60.0, -150.0)  # east, north, up (m): 150 m below the observation plane
AXIS = np.arange(-1500.0, 1500.0 + 1, CELL)


def total_field_anomaly(height_m: float) -> np.ndarray:
    """Total-field anomaly (nT) of an induced dipole on the grid at ``height_m``: the
    anomalous vector projected on the main-field direction."""
    import harmonica as hm

    ee, nn = np.meshgrid(AXIS, AXIS)
    coords = (ee.ravel(), nn.ravel(), np.full(ee.size, height_m))
    moment = np.array(hm.magnetic_angles_to_vec(1e9, INC, DEC))  # A m^2, (e, n, u)
    b = hm.dipole_magnetic(coords, SOURCE, moment, field="b", parallel=False)
    f = hm.magnetic_angles_to_vec(1.0, INC, DEC)
    return sum(np.asarray(c).reshape(ee.shape) * u for c, u in zip(b, f, strict=True))


@pytest.fixture(scope="module")
def dipole():
    return Grid(total_field_anomaly(0.0), AXIS[0], AXIS[0], CELL)


def _peak(values: np.ndarray) -> tuple[float, float]:
    r, c = np.unravel_index(np.nanargmax(values), values.shape)
    return AXIS[c], AXIS[r]


def test_rtp_of_an_inclined_dipole_peaks_over_the_source(dipole):
    out = enhance(dipole, parse_products(["rtp"]), INC, DEC)
    e, n = _peak(out["/map/rtp"].values)
    assert abs(e - SOURCE[0]) <= CELL and abs(n - SOURCE[1]) <= CELL
    # the total-field anomaly itself peaks off the source (to the south, inclination 50 deg)
    e0, n0 = _peak(dipole.values)
    assert np.hypot(e0 - SOURCE[0], n0 - SOURCE[1]) > 2 * CELL


def test_no_rtp_where_the_inclination_would_amplify_the_errors(dipole):
    """Near the magnetic equator the reduction to the pole multiplies the map's errors by up
    to 1 / sin^2(I) (2e6 at 0.04 deg): it is left out and the reason said; the other
    products are computed; at 20 deg (8.5x) it is made."""
    from pipeline.maps.enhance import rtp_refusal

    assert rtp_refusal(20.0) is None and rtp_refusal(-20.0) is None
    assert "skipped" in rtp_refusal(0.04) and "skipped" in rtp_refusal(-12.0)
    out = enhance(dipole, parse_products(["rtp", "dz"]), 0.04, DEC)
    assert set(out) == {"/map/vertical_derivative"}
    assert "/map/rtp" in enhance(dipole, parse_products(["rtp"]), 20.0, DEC)


def test_upward_continuation_matches_the_field_at_the_new_height(dipole):
    truth = total_field_anomaly(100.0)
    # on the dipole alone, and under a regional gradient (900 nT across the grid), which is
    # harmonic and continues unchanged
    ee, nn = np.meshgrid(AXIS, AXIS)
    regional = 300.0 + 0.3 * ee - 0.2 * nn
    for extra in (0.0, regional):
        out = enhance(dipole.with_values(dipole.values + extra), parse_products(["up:100"]), 0, 0)
        up = out["/map/upward_100m"].values - extra
        rel = np.sqrt(np.mean((up - truth) ** 2)) / np.sqrt(np.mean(truth**2))
        assert rel < 0.005


def test_derivatives_tilt_and_analytic_signal(dipole):
    out = enhance(dipole, parse_products(["dz", "thd", "tilt", "as"]), INC, DEC)
    fd = (total_field_anomaly(1.0) - total_field_anomaly(-1.0)) / 2.0  # upward, nT/m
    dz = out["/map/vertical_derivative"].values
    assert np.sqrt(np.mean((dz - fd) ** 2)) < 0.005 * np.sqrt(np.mean(fd**2))
    # edges included: no artefact from the periodic transform
    assert np.max(np.abs(dz - fd)) < 0.005 * np.max(np.abs(fd))
    thd = out["/map/horizontal_derivative"].values
    asig = out["/map/analytic_signal"].values
    np.testing.assert_allclose(asig, np.sqrt(thd**2 + dz**2), rtol=1e-9)
    tilt = out["/map/tilt"].values
    assert np.nanmax(np.abs(tilt)) <= 90.0
    # tilt positive (near 90 deg) at the anomaly's peak; the analytic signal peaks near the
    # source whatever the inclination
    r, c = np.unravel_index(np.argmax(dipole.values), dipole.shape)
    assert tilt[r, c] > 80.0
    e, n = _peak(asig)
    assert np.hypot(e - SOURCE[0], n - SOURCE[1]) < 4 * CELL


def test_gaps_are_filled_for_the_transform_and_masked_again(dipole):
    v = dipole.values.copy()
    v[:20, :30] = np.nan  # an uncovered corner
    v[100:104, 40:60] = np.nan  # a hole between lines
    out = enhance(dipole.with_values(v), parse_products(["rtp", "up:50", "tilt"]), INC, DEC)
    for g in out.values():
        assert np.array_equal(np.isnan(g.values), np.isnan(v))
    full = enhance(dipole, parse_products(["up:50"]), INC, DEC)["/map/upward_50m"].values
    gap = out["/map/upward_50m"].values
    far = np.zeros(v.shape, bool)
    far[60:, 60:] = True  # away from both gaps
    assert np.nanmax(np.abs(gap - full)[far]) < 0.02 * np.nanmax(np.abs(full))
    filled = fill_gaps(v)
    assert np.isfinite(filled).all() and np.array_equal(filled[~np.isnan(v)], v[~np.isnan(v)])


def test_products_parse():
    ps = parse_products(["rtp", " DZ", "up:100", "up:12.5", "rtp"])
    assert [p.topic for p in ps] == [
        "/map/rtp",
        "/map/vertical_derivative",
        "/map/upward_100m",
        "/map/upward_12.5m",
    ]
    assert ps[2].field_name == "upward_100m_nT"
    for bad in ("up", "up:-5", "up:x", "fft"):
        with pytest.raises(ValueError):
            parse_products([bad])


def test_cli_enhance_then_export(tmp_path):
    from tests.mapfile import write_processed
    from tests.recordings import validate_every_message

    src, _ = write_processed(tmp_path / "f.processed.mcap")
    out = tmp_path / "f.enhanced.mcap"
    res = tests.cli.run("enhance", str(src), "--out", str(out), "--products", "rtp,tilt,up:100")
    assert res.returncode == 0, res.stderr
    new = {"/map/rtp", "/map/tilt", "/map/upward_100m"}
    assert validate_every_message(out, new) == 3
    from pipeline.export import export_recording

    export_recording(out, tmp_path / "x", ["geotiff", "netcdf"])  # the CLI: test_export.py
    names = {p.name for p in (tmp_path / "x").iterdir()}
    assert {"f.enhanced.rtp.tif", "f.enhanced.tilt.tif", "f.enhanced.upward_100m.tif"} <= names
    import xarray as xr

    with xr.open_dataset(tmp_path / "x" / "f.enhanced.maps.nc") as ds:
        assert ds["tilt"].attrs["units"] == "degree" and ds["rtp"].attrs["units"] == "nT"
    # the Foxglove layout shows each enhancement grid in a tab, coloured by its own field
    from pipeline.products.layout import layout_panels, recording_layout

    doc = recording_layout(out)
    cfg = doc["configById"]
    tabs = cfg["Tab!aeromag-enhancements"]["tabs"]
    assert [t["title"] for t in tabs] == ["rtp", "tilt", "upward 100m"]
    for t, field in zip(tabs, ("rtp_nT", "tilt_deg", "upward_100m_nT"), strict=True):
        (topic,) = cfg[t["layout"]]["topics"]
        assert cfg[t["layout"]]["topics"][topic]["colorField"] == field
    panels = layout_panels(doc["layout"], cfg)
    assert sorted(panels) == sorted(cfg)  # every panel placed once, the tabs' included
    # enhancing twice refuses (the channels exist), in one line; so does a bad product
    again = tests.cli.run(
        "enhance", str(out), "--out", str(tmp_path / "g.mcap"), "--products", "rtp"
    )
    assert again.returncode == 2 and len(again.stderr.strip().splitlines()) == 1
    assert "/map/rtp" in again.stderr and not (tmp_path / "g.mcap").exists()
    from typer.testing import CliRunner

    from flows.cli import app

    bad = CliRunner().invoke(
        app, ["enhance", str(src), "--out", str(tmp_path / "h.mcap"), "--products", "fft"]
    )
    assert bad.exit_code == 2 and "unknown enhancement 'fft'" in bad.output
    assert not (tmp_path / "h.mcap").exists()


def test_post_flight_enhancements_channels_figures_and_report(dipole, tmp_path):
    """What the write stage adds with ``[enhance] enabled = true`` (without running a flow)."""
    from types import SimpleNamespace

    from pipeline.config import Config
    from pipeline.products.channels import enhancement_channels
    from pipeline.products.figures import enhancement_figures
    from pipeline.products.html import render_html
    from pipeline.run.steps import enhancement_grids

    cfg = Config.load().with_values({"enhance.enabled": True, "enhance.products": ["rtp", "up:50"]})
    cfg.validate()
    run = SimpleNamespace(
        grid=dipole, filtered=dipole, main_field=(5e4, INC, DEC), grid_declination_deg=DEC, lines=[]
    )
    grids = enhancement_grids(run, cfg)
    assert list(grids) == ["/map/rtp", "/map/upward_50m"]
    chans = enhancement_channels(grids, cfg.enhance_settings(), 10**18)
    assert [c.messages[0][1]["fields"][0]["name"] for c in chans] == ["rtp_nT", "upward_50m_nT"]
    figs = enhancement_figures(grids, cfg.enhance_settings(), [])
    assert set(figs) == {"enhance_rtp", "enhance_upward_50m"}
    images = {}
    for name, fig in figs.items():
        images[name] = tmp_path / f"{name}.png"
        fig.savefig(images[name])
    summary = {
        "map": {
            "grid_shape": [1, 1],
            "cell_m": 1.0,
            "arima_order": [1, 1, 1],
            "enhancements": list(grids),
            "main_field": {"inclination_deg": INC, "declination_deg": DEC},
        }
    }
    page = render_html("x", summary, images)
    assert "<h3>Enhancements</h3>" in page and 'id="fig-enhance_rtp"' in page
    for bad in ({"export.formats": ["kml"]}, {"enhance.products": ["up:0"]}):
        with pytest.raises(AeromagError):
            Config.load().with_values(bad).validate()


def test_enhancing_a_recording_without_maps_is_one_line(tmp_path):
    from pipeline.config import Config
    from pipeline.run.commands import enhance_recording
    from tests.mapfile import write_processed

    raw, _ = write_processed(tmp_path / "raw.mcap", frame=False, lines=False, grids=False)
    with pytest.raises(AeromagError) as exc:
        enhance_recording(raw, tmp_path / "out.mcap", Config.load())
    assert "/map/anomaly" in str(exc.value) and "aeromag process" in str(exc.value)
    assert not (tmp_path / "out.mcap").exists()


@pytest.mark.parametrize("legacy", [False, True])
def test_a_recordings_rtp_takes_the_declination_from_grid_north(tmp_path, legacy):
    """The grids' axes are the CRS's: the reduction to the pole turns by the declination
    less the meridian convergence (-1.18 deg at the synthetic survey, 2.1 deg west of its
    UTM zone's central meridian); an older recording's azimuthal equidistant frame has none
    at its origin, so its RTP is unchanged."""
    from pipeline.config import Config
    from pipeline.export.source import read_map_products
    from pipeline.run.commands import enhance_recording
    from tests.mapfile import write_processed

    src, _ = write_processed(tmp_path / "f.processed.mcap", legacy=legacy)
    cfg = Config.load().with_values({"enhance.products": ["rtp"], "enhance.source": "anomaly"})
    enhance_recording(src, tmp_path / "e.mcap", cfg)
    mp = read_map_products(tmp_path / "e.mcap")
    f = mp.frame
    gamma = f.grid_frame().convergence_deg()
    if legacy:
        assert abs(gamma) < 1e-6 and f.grid_declination_deg == pytest.approx(-4.2)
    else:
        assert -1.3 < gamma < -1.1
        assert f.grid_declination_deg == pytest.approx(-4.2 - gamma)
    rtp = mp.grid("rtp").grid.values
    anomaly = mp.grid("anomaly").grid
    want = enhance(anomaly, parse_products(["rtp"]), 53.3, f.grid_declination_deg)["/map/rtp"]
    ok = np.isfinite(rtp)
    np.testing.assert_allclose(rtp[ok], want.values[ok], atol=1e-3)  # float32 in the channel
    if not legacy:  # the true declination would give another map
        true = enhance(anomaly, parse_products(["rtp"]), 53.3, -4.2)["/map/rtp"].values
        assert np.max(np.abs(true[ok] - rtp[ok])) > 0.05
