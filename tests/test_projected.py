"""The projected CRS the maps are gridded in: UTM zones (with their exceptions), the frame."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
from pyproj import Transformer

from pipeline.errors import AeromagError
from pipeline.geo.projected import GridFrame, parse_crs_setting, survey_frame, utm_epsg


def test_standard_utm_zones():
    assert utm_epsg(34.26, 108.9) == 32649  # Xi'an
    assert utm_epsg(-33.9, 151.2) == 32756  # southern hemisphere: 327zz
    assert utm_epsg(45.0, -75.7) == 32618
    assert utm_epsg(0.0, 179.99) == 32660 and utm_epsg(0.0, -180.0) == 32601
    assert utm_epsg(0.0, 180.0) == 32601  # the antimeridian is zone 1's western edge
    assert utm_epsg(-80.0, 0.0) == 32731 and utm_epsg(84.0, 0.0) == 32631


def test_norway_32v_widens_zone_32_west_to_3_degrees_east():
    assert utm_epsg(60.0, 5.3) == 32632  # Bergen: zone 31 by longitude, 32V by the exception
    assert utm_epsg(60.0, 2.99) == 32631  # west of 3 E: zone 31 still
    assert utm_epsg(63.99, 3.0) == 32632
    assert utm_epsg(64.0, 5.0) == 32631  # north of band V: the standard zone
    assert utm_epsg(55.99, 5.0) == 32631  # south of band V
    assert utm_epsg(60.0, 11.99) == 32632 and utm_epsg(60.0, 12.0) == 32633


@pytest.mark.parametrize(
    ("lon", "epsg"),
    [
        (0.5, 32631),
        (8.99, 32631),  # would be 32 by longitude: 32X does not exist
        (9.0, 32633),
        (15.6, 32633),  # Longyearbyen
        (20.99, 32633),  # would be 34
        (21.0, 32635),
        (32.99, 32635),  # would be 36
        (33.0, 32637),
        (41.99, 32637),
        (42.0, 32638),  # east of the exceptions: the standard zone again
        (-0.5, 32630),
    ],
)
def test_svalbard_31x_33x_35x_37x(lon, epsg):
    assert utm_epsg(78.2, lon) == epsg
    assert utm_epsg(72.0, lon) == epsg


def test_polar_areas_take_ups():
    assert utm_epsg(84.5, 10.0) == 32661 and utm_epsg(-80.5, 10.0) == 32761


def test_vectorised_zones_match_the_scalar_ones():
    rng = np.random.default_rng(3)
    lat, lon = rng.uniform(-89, 89, 500), rng.uniform(-180, 180, 500)
    lat[:40], lon[:40] = rng.uniform(55, 85, 40), rng.uniform(-1, 43, 40)
    codes = utm_epsg(lat, lon)
    assert [int(c) for c in codes] == [utm_epsg(a, b) for a, b in zip(lat, lon, strict=True)]


def test_a_survey_across_a_zone_boundary_is_gridded_in_its_centroids_zone_and_says_so():
    # a line from 113.0 to 114.3 E astride 114 E (zones 49 | 50), its centroid west of it
    lon = np.linspace(113.0, 114.3, 200)
    lat = np.full(200, 30.0)
    f = survey_frame(lat, lon, 100.0)
    assert f.crs == "EPSG:32649" and f.zones == (32649, 32650)
    assert "EPSG:32650" in f.note and "centroid" in f.note
    g = survey_frame(lat, lon + 0.5, 100.0)  # now the centroid is east of it
    assert g.crs == "EPSG:32650"
    inside = survey_frame(lat, lon - 1.5, 100.0)
    assert inside.zones == (32649,) and "beyond" not in inside.note


def test_a_survey_in_norway_32v_and_in_svalbard_takes_the_exceptional_zone():
    f = survey_frame(np.full(10, 60.4), np.linspace(5.2, 5.4, 10), 0.0)  # Bergen
    assert f.crs == "EPSG:32632" and f.zones == (32632,)
    s = survey_frame(np.full(10, 78.2), np.linspace(15.4, 15.8, 10), 0.0)  # Longyearbyen
    assert s.crs == "EPSG:32633" and s.zones == (32633,)


def test_the_frame_origin_and_round_trip():
    lat = np.array([34.20, 34.30, 34.25])
    lon = np.array([108.85, 108.95, 108.90])
    f = survey_frame(lat, lon, np.array([500.0, 520.0, 510.0]))
    assert f.crs == "EPSG:32649" and f.epsg == 32649 and f.alt0_m == pytest.approx(510.0)
    assert f.origin_east_m % 1000 == 0 and f.origin_north_m % 1000 == 0
    # frame metres are the CRS's easting/northing less the origin's
    x, y = Transformer.from_crs("EPSG:4326", "EPSG:32649", always_xy=True).transform(lon, lat)
    e, n, u = f.to_enu(lat, lon, np.array([500.0, 520.0, 510.0]))
    np.testing.assert_allclose(e, np.asarray(x) - f.origin_east_m, atol=1e-6)
    np.testing.assert_allclose(n, np.asarray(y) - f.origin_north_m, atol=1e-6)
    np.testing.assert_allclose(u, [-10.0, 10.0, 0.0])
    assert np.max(np.hypot(e, n)) < 8000  # the origin near the survey
    la, lo, al = f.to_geodetic(e, n, u)
    np.testing.assert_allclose(la, lat, atol=1e-9)
    np.testing.assert_allclose(lo, lon, atol=1e-9)
    np.testing.assert_allclose(al, [500.0, 520.0, 510.0])
    # the same frame again from its arguments and through pickle (process pools)
    assert GridFrame(*f.args()) == f
    assert pickle.loads(pickle.dumps(f)).to_enu(34.25, 108.9)[0] == pytest.approx(
        f.to_enu(34.25, 108.9)[0]
    )
    assert "EPSG:32649 about E" in f.grid_crs


def test_convergence_is_the_angle_from_grid_north_to_true_north():
    """A line flown true north is seen in the grid at minus the convergence: west of the
    central meridian (Xi'an is 2.1 deg west of 111 E) grid north lies east of true north."""
    f = survey_frame([34.25], [108.9], [0.0])
    gamma = f.convergence_deg()
    assert -1.3 < gamma < -1.1
    e0, n0, _ = f.to_enu(34.25, 108.9)
    e1, n1, _ = f.to_enu(34.35, 108.9)  # 11 km true north
    azimuth_grid = np.degrees(np.arctan2(e1 - e0, n1 - n0))
    assert azimuth_grid == pytest.approx(0.0 - gamma, abs=0.01)


def test_a_given_epsg_is_used_and_checked():
    assert parse_crs_setting("auto") is None
    assert parse_crs_setting("EPSG:32650") == 32650 == parse_crs_setting(" 32650 ")
    assert parse_crs_setting("epsg:3006") == 3006  # SWEREF99 TM: northing first, metres
    f = survey_frame([59.33], [18.07], [30.0], epsg=3006)
    assert f.crs == "EPSG:3006" and "map.crs" in f.note
    x, y = Transformer.from_crs("EPSG:4326", "EPSG:3006", always_xy=True).transform(18.07, 59.33)
    e, n, _ = f.to_enu(59.33, 18.07)
    assert float(e) + f.origin_east_m == pytest.approx(x) and x < 1e6 < y  # easting first
    for bad in ("EPSG:4326", "utm", "EPSG:999999", "2263"):  # lon/lat, text, unknown, feet
        with pytest.raises(AeromagError, match="map.crs"):
            parse_crs_setting(bad, "c.toml")


def test_a_survey_across_zones_is_a_warning_in_the_log_and_map_crs_is_checked():
    from types import SimpleNamespace

    from pipeline.config import Config
    from pipeline.products.log import LOG_INFO, LOG_WARNING, map_lines

    def lines_for(frame):
        s = {
            "grid_shape": [3, 4],
            "cell_m": 25.0,
            "line_spacing_m": 100.0,
            "crossover_rms_nT": {"before": 1.0, "after": 0.5},
            "leveling": {"crossovers": 10},
            "arima_order": [1, 1, 0],
            "arima_coefficients": {"ar": [0.5], "ma": []},
            "kalman": {"measurement_noise_nT": 0.1},
            "microlevel": {"enabled": False},
            "origin": {"crs_choice": frame.note, "utm_zones_spanned": list(frame.zones)},
        }
        return map_lines(SimpleNamespace(summary=lambda: s))

    lat, lon = np.full(50, 30.0), np.linspace(113.0, 114.3, 50)
    level, text = lines_for(survey_frame(lat, lon, 0.0))[0]
    assert level == LOG_WARNING and "EPSG:32649" in text and "EPSG:32650" in text
    level, text = lines_for(survey_frame(lat, lon - 1.5, 0.0))[0]
    assert level == LOG_INFO and "UTM zone 49N" in text
    level, _ = lines_for(survey_frame(lat, lon, 0.0, epsg=32650))[0]  # the user's choice
    assert level == LOG_INFO
    assert Config.load().with_values({"map.crs": "EPSG:32650"}).map_settings().crs_epsg == 32650
    assert Config.load().map_settings().crs_epsg is None
    with pytest.raises(AeromagError, match="map.crs"):
        Config.load().with_values({"map.crs": "EPSG:4326"}).validate()


def test_a_map_placed_in_a_frame_pickles_with_its_transforms():
    """A map's transforms are module functions bound to the frame, not closures: the
    navigation results that hold the map pickle with the standard library (a process pool,
    a child process) and place points as before."""
    from pipeline.maps.grid import Grid
    from pipeline.navigation.map_io import frame_map

    f = survey_frame([34.25, 34.26], [108.9, 108.91], [500.0, 520.0])
    grid = Grid(np.arange(12.0).reshape(3, 4), -100.0, -50.0, 25.0)
    m = frame_map(grid, f, "test", "in-memory map")
    back = pickle.loads(pickle.dumps(m))
    e, n = back.to_local(34.255, 108.905)
    e0, n0 = m.to_local(34.255, 108.905)
    assert float(e) == pytest.approx(float(e0)) and float(n) == pytest.approx(float(n0))
    la, lo = back.to_geodetic(e, n)
    assert float(la) == pytest.approx(34.255, abs=1e-9)
    assert float(lo) == pytest.approx(108.905, abs=1e-9)
