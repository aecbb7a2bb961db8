"""Magnetic anomaly navigation (issue 18): INS error model, map model, EKF, PF, CRLB, command.

Every figure is checked against the truth (the simulated INS errors and the true track), never
against the filters' own residuals. Maps are synthetic (smooth random fields and harmonica
dipoles), tracks synthetic racetracks and straight lines, except the demo-flight check (slow).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline.maps.grid import Grid
from pipeline.navigation.crlb import crlb
from pipeline.navigation.ekf import ekf
from pipeline.navigation.ins import (
    GRADES,
    InsErrorModel,
    Trajectory,
    simulate_ins_errors,
)
from pipeline.navigation.map_model import MapModel, upward_continue
from pipeline.navigation.pf import particle_filter
from pipeline.simulate.navigation import dipole_map, racetrack, random_field_map
from tests.navmaps import box_frame, in_process_cli, one_line_error, utm_map  # noqa: F401

NMI_M = 1852.0


def _setup(duration_s, grade="navigation", rate_hz=10.0, track=None, mag_bias_nT=1.0):
    t, e, n = track if track is not None else racetrack(duration_s, rate_hz)
    up = np.zeros_like(t)
    lat = 45.0 + n / 111_000.0
    traj = Trajectory.from_track(t, n, e, up, lat)
    model = InsErrorModel(GRADES[grade], mag_bias_nT=mag_bias_nT)
    phi = model.transitions(traj)
    qd = model.process_noise(np.diff(t, prepend=t[0]))
    return t, e, n, traj, model, phi, qd


def _drms(err_ne):
    return float(np.sqrt(np.mean(np.sum(err_ne**2, axis=1))))


# ------------------------------------------------------------------------------- map model
def test_map_model_is_the_cubic_spline_and_its_gradient():
    from scipy.ndimage import map_coordinates

    g = random_field_map(2, size_m=3000.0, cell_m=50.0, correlation_m=200.0)
    mm = MapModel(g)
    rng = np.random.default_rng(0)
    e = rng.uniform(-9990.0, -7010.0, 300)
    n = rng.uniform(-9990.0, -7010.0, 300)
    v, gx, gy = mm.value_and_gradient(e, n)
    ref = map_coordinates(
        g.values, [(n - g.north0_m) / g.cell_m, (e - g.east0_m) / g.cell_m], order=3, mode="mirror"
    )
    assert np.allclose(v, ref, atol=1e-9)
    h = 1e-3
    assert np.allclose(gx, (mm.value(e + h, n) - mm.value(e - h, n)) / (2 * h), atol=1e-6)
    assert np.allclose(gy, (mm.value(e, n + h) - mm.value(e, n - h)) / (2 * h), atol=1e-6)
    for k in range(5):  # the filters' scalar path agrees with the vectorised one
        assert np.allclose(mm.at(e[k], n[k]), (v[k], gx[k], gy[k]), atol=1e-9)
    assert np.isnan(mm.at(1e6, 0.0)[0]) and not mm.inside([1e6], [0.0])[0]


def test_masked_cells_are_off_the_map():
    g = random_field_map(3, size_m=1000.0, cell_m=50.0, origin_m=(0.0, 0.0))
    vals = g.values.copy()
    vals[:, :5] = np.nan
    mm = MapModel(g.with_values(vals))
    assert not mm.inside([100.0], [500.0])[0]
    assert mm.inside([600.0], [500.0])[0]
    assert np.isnan(mm.value([100.0], [500.0])[0])


def test_upward_continuation_damps_each_wavenumber_by_exp_minus_k_h():
    # a single Fourier mode continued upward by h is multiplied by exp(-|k| h), exactly
    cell, size = 50.0, 128
    x = cell * np.arange(size)
    kx, ky = 2 * np.pi * 4 / (cell * size), 2 * np.pi * 3 / (cell * size)
    vals = 100.0 * np.cos(kx * x)[None, :] * np.cos(ky * x)[:, None]
    up = upward_continue(Grid(vals, 0.0, 0.0, cell), 300.0)
    expected = vals * np.exp(-np.hypot(kx, ky) * 300.0)
    c = slice(32, -32)  # the reflection padding is exact for this even mode; edges aside
    assert np.allclose(up.values[c, c], expected[c, c], atol=0.02 * np.abs(expected).max())
    low = Grid(vals, 0.0, 0.0, cell)
    mm, note = MapModel(low, altitude_m=300.0).continued_to(500.0)
    assert "upward by 200.0 m" in note and mm.altitude_m == 500.0
    same, note = MapModel(low, altitude_m=300.0).continued_to(250.0)
    assert same.altitude_m == 300.0 and "below the map" in note


@pytest.mark.slow
def test_upward_continuation_matches_the_dipoles_computed_higher():
    low = dipole_map(4, size_m=8000.0, cell_m=40.0, count=40, height_m=0.0)
    high = dipole_map(4, size_m=8000.0, cell_m=40.0, count=40, height_m=200.0)
    up = upward_continue(low, 200.0)
    c = slice(50, -50)  # away from the edges (the FFT's padding is an approximation there)
    diff = up.values[c, c] - high.values[c, c]
    assert np.sqrt(np.mean(diff**2)) < 0.05 * np.std(high.values[c, c])


# ------------------------------------------------------------------------------- INS model
def test_navigation_grade_drifts_about_one_nautical_mile_per_hour():
    # a straight 1 h flight at 60 m/s, 1 Hz, 24 seeds: the median horizontal error at one hour
    t = np.arange(0.0, 3600.0, 1.0)
    d = 60.0 * t
    _, _, _, traj, model, phi, _ = _setup(0, track=(t, d * np.sqrt(0.5), d * np.sqrt(0.5)))
    final = [np.hypot(*simulate_ins_errors(model, traj, s, phi)[-1, :2]) for s in range(24)]
    median_nmi = float(np.median(final)) / NMI_M
    assert 0.4 < median_nmi < 2.5, median_nmi
    tactical = InsErrorModel(GRADES["tactical"])
    phi_t = tactical.transitions(traj)
    worse = [np.hypot(*simulate_ins_errors(tactical, traj, s, phi_t)[-1, :2]) for s in range(6)]
    assert np.median(worse) > 10 * np.median(final)


def test_simulation_is_seeded():
    _, _, _, traj, model, phi, _ = _setup(60.0)
    a = simulate_ins_errors(model, traj, 7, phi)
    assert np.array_equal(a, simulate_ins_errors(model, traj, 7, phi))
    assert not np.array_equal(a, simulate_ins_errors(model, traj, 8, phi))


# ------------------------------------------------------------------------------- filters
@pytest.fixture(scope="module")
def field_map():
    return MapModel(random_field_map(1, size_m=16_000.0, cell_m=50.0, correlation_m=300.0))


def test_noiseless_map_and_sensor_reach_the_crlb(field_map):
    # noiseless map, near-noiseless sensor (0.05 nT, a CPT's noise); five seeds
    t, e, n, traj, model, phi, qd = _setup(600.0, mag_bias_nT=0.1)
    sigma = 0.05
    ratios = []
    for seed in range(5):
        x = simulate_ins_errors(model, traj, seed, phi)
        z = field_map.value(e, n) + np.random.default_rng(100 + seed).normal(0, sigma, t.size)
        p0 = model.initial_covariance()
        res = ekf(phi, qd, p0, z, e + x[:, 1], n + x[:, 0], field_map, sigma**2)
        bound = crlb(phi, qd, p0, e, n, field_map, sigma**2)
        late = slice(t.size // 4, None)  # after the first convergence
        err = x[late, :2] - res.state[late, :2]
        ratios.append(_drms(err) / np.sqrt(np.mean(bound[late, 0, 0] + bound[late, 1, 1])))
        assert _drms(err) < _drms(x[late, :2]) / 5
    assert 0.5 < np.sqrt(np.mean(np.square(ratios))) < 2.0, ratios


def test_shifted_map_shifts_the_track(field_map):
    smooth = MapModel(random_field_map(5, size_m=16_000.0, cell_m=50.0, correlation_m=800.0))
    t, e, n, traj, model, phi, qd = _setup(600.0)
    x = simulate_ins_errors(model, traj, 3, phi)
    sigma = 0.1
    z = smooth.value(e, n) + np.random.default_rng(9).normal(0, sigma, t.size)
    offset_e, offset_n = 40.0, -25.0
    g = smooth.grid
    shifted = MapModel(Grid(g.values, g.east0_m + offset_e, g.north0_m + offset_n, g.cell_m))
    p0 = model.initial_covariance(init_pos_m=60.0)
    res = ekf(phi, qd, p0, z, e + x[:, 1], n + x[:, 0], shifted, sigma**2)
    # estimated position minus truth = estimated error minus ... : est = ins - x_hat
    est_e = e + x[:, 1] - res.state[:, 1]
    est_n = n + x[:, 0] - res.state[:, 0]
    late = slice(t.size // 2, None)
    assert abs(np.mean(est_e[late] - e[late]) - offset_e) < 2.0
    assert abs(np.mean(est_n[late] - n[late]) - offset_n) < 2.0


@pytest.mark.parametrize("grade", ["navigation", "tactical"])
def test_covariance_stays_symmetric_positive_definite(field_map, grade):
    t, e, n, traj, model, phi, qd = _setup(300.0, grade)
    x = simulate_ins_errors(model, traj, 1, phi)
    z = field_map.value(e, n) + np.random.default_rng(2).normal(0, 0.5, t.size)
    res = ekf(
        phi,
        qd,
        model.initial_covariance(),
        z,
        e + x[:, 1],
        n + x[:, 0],
        field_map,
        0.25,
        check_every=10,
    )
    assert res.min_eigenvalue > 0.0
    assert res.max_asymmetry < 1e-6 * np.abs(res.pos_cov_m2).max()
    assert np.all(np.linalg.eigvalsh(res.pos_cov_m2) > 0)


def test_particle_filter_recovers_a_large_initial_error(field_map):
    t, e, n, traj, model, phi, qd = _setup(300.0)
    x = simulate_ins_errors(model, traj, 0, phi, init_pos_m=500.0)
    assert np.hypot(*x[0, :2]) > 300.0  # a large start error, many map correlation lengths
    sigma = 1.0
    z = field_map.value(e, n) + np.random.default_rng(5).normal(0, sigma, t.size)
    p0 = model.initial_covariance(init_pos_m=500.0)
    ins_e, ins_n = e + x[:, 1], n + x[:, 0]
    pf = particle_filter(phi, qd, p0, z, ins_e, ins_n, field_map, sigma**2, seed=1, times_s=t)
    late = slice(t.size // 2, None)
    pf_err = _drms(x[late, :2] - pf.state[late, :2])
    assert pf_err < 10.0, pf_err
    ekf_res = ekf(phi, qd, p0, z, ins_e, ins_n, field_map, sigma**2)
    ekf_err = _drms(x[late, :2] - ekf_res.state[late, :2])
    assert pf_err < ekf_err  # the EKF's linearisation fails this far from the truth
    # the particle filter handing over to the EKF once settled recovers as well
    both = particle_filter(
        phi, qd, p0, z, ins_e, ins_n, field_map, sigma**2, seed=1, times_s=t, handover_m=5.0
    )
    assert both.handover_epoch is not None and both.handover_epoch < t.size // 2
    assert _drms(x[late, :2] - both.state[late, :2]) < 10.0


# ------------------------------------------------------------------------------- command
@pytest.mark.parametrize("filter_", ["ekf", "pf"])
def test_command_runs_on_a_raw_recording_and_writes_valid_channels(
    box_path, tmp_path, filter_, cli
):
    from tests.recordings import validate_every_message

    tif = utm_map(box_path, tmp_path)
    out, nav = tmp_path / "nav.mcap", tmp_path / "nav.json"
    code, text = cli(
        "navigate",
        box_path,
        "--map",
        tif,
        "--json",
        nav,
        "--out",
        out,
        "--segments",
        "all",
        "--filter",
        filter_,
        "--seed",
        3,
    )
    assert code == 0, text
    doc = json.loads(nav.read_text())["navigation"]
    assert set(doc["drms_m"]) == {"ins_only", "map_aided", "crlb"}
    assert doc["settings"]["filter"] == filter_ and doc["settings"]["seed"] == 3
    assert doc["map"]["crs"].startswith("EPSG:")
    assert doc["cep50_m"]["ins_only"] > 0 and doc["segments"]
    topics = {"/nav/ins", "/nav/map_aided", "/nav/error", "/nav/innovation"}
    assert validate_every_message(out, topics) > 100


def test_map_that_does_not_cover_the_track_is_one_line(box_path, tmp_path, cli):
    tif = utm_map(box_path, tmp_path, shift_m=50_000.0)
    code, text = cli(
        "navigate", box_path, "--map", tif, "--json", tmp_path / "n.json", "--segments", "all"
    )
    line = one_line_error(code, text)
    assert "does not cover the track: 100%" in line


def test_map_without_a_crs_is_one_line(box_path, tmp_path, cli):
    tif = utm_map(box_path, tmp_path, crs=False)
    code, text = cli("navigate", box_path, "--map", tif, "--json", tmp_path / "n.json")
    line = one_line_error(code, text)
    assert "cannot be placed" in line


def test_recording_without_the_map_channel_is_one_line(box_path, tmp_path, cli):
    code, text = cli("navigate", box_path, "--map", box_path, "--json", tmp_path / "n.json")
    line = one_line_error(code, text)
    assert "/map/anomaly_filtered" in line and "no such channel" in line


def test_magnav_hdf5_map_is_read_in_radians_and_degrees(tmp_path):
    import h5py

    from pipeline.navigation.map_io import read_map

    g = random_field_map(7, size_m=2000.0, cell_m=50.0)
    ny, nx = g.shape
    lon = np.linspace(108.90, 108.92, nx)
    lat = np.linspace(34.25, 34.27, ny)
    for units, conv in (("rad", np.radians), ("deg", lambda v: v)):
        path = tmp_path / f"map_{units}.h5"
        with h5py.File(path, "w") as h5:
            h5["map"] = g.values.T  # as Julia writes it (column-major): h5py sees (nx, ny)
            h5["xx"], h5["yy"], h5["alt"] = conv(lon), conv(lat), 800.0
        m = read_map(path)
        assert m.altitude_m == 800.0 and m.grid.shape[1] >= nx - 1
        e, n = m.to_local(np.array([34.26]), np.array([108.91]))
        assert abs(e[0]) < 1.0 and abs(n[0]) < 1.0  # the centre
        lat_back, lon_back = m.to_geodetic(e, n)
        assert abs(lat_back[0] - 34.26) < 1e-9


@pytest.mark.slow
def test_demo_flight_meets_the_issue_targets(tmp_path, cli):
    code, text = cli("demo", "--out", tmp_path)
    assert code == 0, text
    demo = tmp_path / "demo_flight.processed.mcap"
    nav = tmp_path / "nav.json"
    code, text = cli("navigate", demo, "--map", demo, "--json", nav)
    assert code == 0, text
    d = json.loads(nav.read_text())["navigation"]["drms_m"]
    assert d["map_aided"] <= d["ins_only"] / 5
    assert d["map_aided"] <= 2 * d["crlb"]


def test_recording_map_is_placed_by_its_map_frame(box_path, tmp_path):
    from types import SimpleNamespace

    from pipeline.errors import AeromagError
    from pipeline.geo.local import LocalFrame
    from pipeline.geo.projected import survey_frame
    from pipeline.io.writer import OutputChannel, write_with_new_channels
    from pipeline.navigation.map_io import read_map
    from pipeline.products.channels import grid_channel, map_frame_channel

    lat0, lon0 = box_frame(box_path)
    frame = survey_frame([lat0], [lon0], [420.0])  # UTM, origin on a round km near the box
    g = random_field_map(8, size_m=1000.0, cell_m=25.0, origin_m=(-500.0, -500.0))
    t0 = 1_781_485_200_000_000_000
    ch = grid_channel("/map/anomaly_filtered", t0, g)
    fr = map_frame_channel(SimpleNamespace(frame=frame, main_field=(50_000.0, 50.0, -3.0)), t0)
    placed = tmp_path / "placed.mcap"
    write_with_new_channels(box_path, placed, [ch, fr])
    m = read_map(placed)
    assert m.altitude_m == 420.0 and "/map/frame" in m.notes[0] and m.crs == frame.crs
    e, n = m.to_local(np.array([lat0]), np.array([lon0]))
    want_e, want_n, _ = frame.to_enu(lat0, lon0)
    assert e[0] == pytest.approx(want_e, abs=1e-6) and n[0] == pytest.approx(want_n, abs=1e-6)
    assert 0 < np.hypot(e[0], n[0]) < 710  # the origin: the box's position rounded to 1 km
    assert np.allclose(m.grid.values, g.values.astype("float32"))
    assert m.grid.east0_m == pytest.approx(-500.0) and m.grid.north0_m == pytest.approx(-500.0)
    # a recording processed before the change: the azimuthal equidistant frame about its origin
    old = LocalFrame(lat0, lon0, 420.0)
    legacy = OutputChannel("/map/frame", "aeromag.MapFrame")
    legacy.add(
        t0,
        {
            "frame_id": "local_enu",
            "crs": old.crs,
            "latitude": lat0,
            "longitude": lon0,
            "altitude_m": 420.0,
            "utm_epsg": 32649,
            "igrf_inclination_deg": 50.0,
            "igrf_declination_deg": -3.0,
        },
    )
    before = tmp_path / "before.processed.mcap"
    write_with_new_channels(box_path, before, [ch, legacy])
    m = read_map(before)
    e, n = m.to_local(np.array([lat0]), np.array([lon0]))
    assert abs(e[0]) < 1e-6 and abs(n[0]) < 1e-6 and m.crs == old.crs
    lat, lon = m.to_geodetic(np.array([300.0]), np.array([-200.0]))
    assert np.allclose(old.to_enu(lat, lon)[:2], [[300.0], [-200.0]], atol=1e-6)
    bare = tmp_path / "old.processed.mcap"
    write_with_new_channels(box_path, bare, [ch])
    with pytest.raises(AeromagError, match="no map georeference"):
        read_map(bare)


def test_netcdf_lon_lat_grid_is_placed_without_a_crs(tmp_path):
    import xarray as xr

    from pipeline.navigation.map_io import read_map

    g = random_field_map(9, size_m=2000.0, cell_m=50.0)
    ny, nx = g.shape
    lon = np.linspace(108.90, 108.92, nx)
    lat = np.linspace(34.27, 34.25, ny)  # north-up rows, as many grids store them
    da = xr.DataArray(g.values, coords={"lat": lat, "lon": lon}, dims=("lat", "lon"))
    da.attrs["altitude_m"] = 650.0
    path = tmp_path / "map.nc"
    da.to_dataset(name="anomaly").to_netcdf(path)
    m = read_map(path)
    assert m.altitude_m == 650.0
    mm = MapModel(m.grid)
    # stored cells (row 0 is the north edge) at their coordinates, inside the span of the
    # resampled nodes (which may stop short of the edges by less than a cell); the unequal steps
    # were resampled onto square cells, so agreement is to the field's smoothness
    for r, c in ((1, 2), (3, 5), (ny - 3, nx - 3)):
        e, n = m.to_local(np.array([lat[r]]), np.array([lon[c]]))
        assert mm.value(e, n)[0] == pytest.approx(g.values[r, c], abs=1.0)
