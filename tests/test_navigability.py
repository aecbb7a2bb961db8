"""Navigability map (issue 38, item 6, library part): the per-cell position CRLB against the
CRLB of flights along chosen tracks over a map with a rich half and a quiet half."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.navigation.crlb import crlb
from pipeline.navigation.ekf import MeasurementModel, correlated_error_scale
from pipeline.navigation.ins import GRADES, InsErrorModel, Trajectory
from pipeline.navigation.map_model import MapModel
from pipeline.navigation.navigability import NavigabilitySettings, navigability
from pipeline.simulate.navigation import random_field_map

SPEED, SIGMA, SENSOR = 60.0, 0.5, 0.1


@pytest.fixture(scope="module")
def half_quiet():
    """An 8 km map whose west half is 30 times quieter, and its navigability (stride 8)."""
    g = random_field_map(3, size_m=8000.0, cell_m=50.0, origin_m=(-4000.0, -4000.0))
    ce, _ = g.coordinates()
    v = g.values.copy()
    v[:, ce < 0] *= 1.0 / 30.0
    g = g.with_values(v)
    s = NavigabilitySettings(speed_mps=SPEED, stride_cells=8)
    return g, navigability(g, SENSOR, SIGMA, s), s


def _flight_crlb(g, east_m, heading_deg, s):
    """CRLB DRMS (m) of a flight along a chosen track: a straight line through the map at
    ``east_m`` on ``heading_deg`` (0: north, 180: south), 2 Hz, 110 s, from the navigability's
    start sigma; its positions and the bound over the last half."""
    t = np.arange(0.0, 110.0, 0.5)
    sign = 1.0 if heading_deg == 0.0 else -1.0
    n = sign * (-3300.0 + SPEED * t)
    e = np.full_like(t, east_m)
    traj = Trajectory.from_track(t, n, e, np.zeros_like(t), np.full(t.size, s.lat_deg))
    model = InsErrorModel(GRADES["navigation"])
    phi = model.transitions(traj)
    qd = model.process_noise(np.diff(t, prepend=t[0]))
    scale = correlated_error_scale(s.map_error_length_m, SPEED * 0.5)
    meas = MeasurementModel(MapModel(g), map_sigma_nT=SIGMA, map_var_scale=scale)
    b = crlb(phi, qd, model.initial_covariance(s.start_sigma_m), e, n, meas, SENSOR**2)
    k = t > 55.0
    return e[k], n[k], np.sqrt(b[k, 0, 0] + b[k, 1, 1])


def test_navigability_follows_the_crlb_of_flights_along_chosen_tracks(half_quiet):
    g, nav, s = half_quiet
    assert nav.shape == g.shape and np.array_equal(np.isfinite(nav.values), np.isfinite(g.values))
    ce, _ = g.coordinates()
    quiet = np.nanmedian(nav.values[:, (ce < -1000) & (ce > -3000)])
    rich = np.nanmedian(nav.values[:, (ce > 1000) & (ce < 3000)])
    assert quiet > 5 * rich
    for east in (-2000.0, -1200.0, 1200.0, 2000.0):
        for heading in (0.0, 180.0):
            e, n, flown = _flight_crlb(g, east, heading, s)
            mapped = nav.interpolate(e, n)
            ratio = np.median(flown) / np.median(mapped)
            # a different sampling and a single heading against four: the same order
            assert 1 / 3 < ratio < 3, (east, heading, np.median(flown), np.median(mapped))


def test_a_larger_map_error_makes_every_cell_less_navigable(half_quiet):
    g, nav, s = half_quiet
    worse = navigability(g, SENSOR, 5.0, s)
    ok = np.isfinite(nav.values)
    assert np.all(worse.values[ok] >= nav.values[ok] * (1 - 1e-9))
    assert np.nanmedian(worse.values / nav.values) > 1.5


def test_the_line_is_sized_to_the_maps_covered_area():
    """Item 6.2: the line into a cell on a heading reaches from the centre of the map's
    covered cells (NaN margins do not count) to their edge, so a line into the map's centre
    lies on the map; half the shorter side across, more along an elongated block; bounded
    to [20, 120] s."""
    from pipeline.navigation.navigability import MAX_WINDOW_S, MIN_WINDOW_S, line_window_s

    g = random_field_map(5, size_m=4000.0, cell_m=25.0, origin_m=(-2000.0, -2000.0))
    ce, cn = g.coordinates()
    v = g.values.copy()
    v[:, np.abs(ce) > 1500.0] = np.nan  # covered: 3000 m east-west
    v[np.abs(cn) > 500.0, :] = np.nan  # and 1000 m north-south
    g = g.with_values(v)
    speed = 20.0
    window = line_window_s(g, speed)
    assert window == pytest.approx(1000.0 / 2 / speed)  # 41 cell centres 25 m apart, halved
    assert line_window_s(g, speed, 90.0) == pytest.approx(1500.0 / speed)  # the long axis
    assert line_window_s(g, speed, 0.0) == pytest.approx(window)
    for heading_deg in np.arange(0.0, 360.0, 22.5):
        reach = speed * line_window_s(g, speed, heading_deg)
        assert speed * window - 1e-6 <= reach <= 1500.0 + 1e-6
        along = np.linspace(-reach, 0.0, 50) * (1 - 1e-9)  # the last centre: inside
        h = np.radians(heading_deg)
        assert np.isfinite(g.interpolate(along * np.sin(h), along * np.cos(h))).all(), heading_deg
    assert line_window_s(g, 0.5) == MAX_WINDOW_S and line_window_s(g, 500.0) == MIN_WINDOW_S
    s = NavigabilitySettings(speed_mps=speed, headings_deg=(0.0,), stride_cells=8)
    sized = navigability(g, SENSOR, SIGMA, s)
    fixed = navigability(g, SENSOR, SIGMA, NavigabilitySettings(**{**vars(s), "window_s": 120.0}))
    # the default is the sized line, not the fixed one (which starts off this map)
    assert np.nanmax(np.abs(np.log(sized.values / fixed.values))) > 1e-3


def test_the_batched_bound_is_the_bound_of_each_track(half_quiet):
    """The navigability's batched recursion (every cell's line at once) gives the last
    epoch of :func:`crlb` on each track, on and off the map and with a sigma grid."""
    from pipeline.navigation.crlb import crlb_final
    from pipeline.navigation.navigability import _line

    g, _, s = half_quiet
    sigma = g.with_values(0.2 + 0.01 * np.abs(g.values))
    meas = MeasurementModel(MapModel(g), sigma=MapModel(sigma, method="linear"))
    north, east, phi, qd, p0 = _line(s, 30.0, 40.0)
    ends = np.array([[0.0, 0.0], [-2500.0, 1500.0], [3900.0, 3900.0], [9000.0, 0.0]])
    e, n = ends[:, :1] + east[None, :], ends[:, 1:] + north[None, :]
    batched = crlb_final(phi, qd, p0, e, n, meas, SENSOR**2)
    for k in range(len(ends)):
        one = crlb(phi, qd, p0, e[k], n[k], meas, SENSOR**2)[-1]
        np.testing.assert_allclose(batched[k], one, rtol=1e-9, atol=1e-9)
