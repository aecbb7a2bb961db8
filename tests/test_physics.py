"""Physics of the shared module and of simulated recordings, checked against independent paths."""

from __future__ import annotations

from datetime import datetime

import numpy as np
import ppigrf
import pytest

from pipeline.geo.frames import body_to_ned, ned_to_body
from pipeline.io.reader import read_flight
from pipeline.physics import (
    CarrierInterference,
    DipoleSource,
    FluxgateErrors,
    dipole_field_ned_nT,
    scalar_reading_nT,
)
from pipeline.simulate import write_simulation
from tests.conftest import QUIET, run_sim


def test_frames_follow_zyx_convention():
    # Facing east, north is on the left (-y); nose up 90 deg, "down" is behind (-x).
    np.testing.assert_allclose(ned_to_body([1.0, 0.0, 0.0], 0, 0, 90), [0, -1, 0], atol=1e-12)
    np.testing.assert_allclose(ned_to_body([0.0, 0.0, 1.0], 0, 90, 0), [-1, 0, 0], atol=1e-12)
    # Right wing down 90 deg: "down" is along +y (right).
    np.testing.assert_allclose(ned_to_body([0.0, 0.0, 1.0], 90, 0, 0), [0, 1, 0], atol=1e-12)
    rng = np.random.default_rng(0)
    v = rng.normal(size=(50, 3))
    ang = rng.uniform(-80, 80, size=(3, 50))
    np.testing.assert_allclose(body_to_ned(ned_to_body(v, *ang), *ang), v, atol=1e-12)


def test_dipole_field_matches_axial_and_equatorial_formulas():
    m = 1.0e6  # A m^2, pointing down
    src = [DipoleSource(0.0, 0.0, -100.0, (0.0, 0.0, m))]
    r = 150.0
    below = dipole_field_ned_nT(src, 0.0, 0.0, -100.0 - r)[0]  # on the axis
    side = dipole_field_ned_nT(src, r, 0.0, -100.0)[0]  # in the equatorial plane
    np.testing.assert_allclose(below, [0, 0, 2 * 100.0 * m / r**3], rtol=1e-12)
    np.testing.assert_allclose(side, [0, 0, -100.0 * m / r**3], rtol=1e-12, atol=1e-12)


def test_interference_vector_and_first_order_projection():
    ci = CarrierInterference(
        [10.0, -20.0, 30.0], np.diag([0.001, 0.002, 0.003]), np.full((3, 3), 0.01)
    )
    b = np.array([[20000.0, 0.0, 45000.0]])
    db = np.array([[100.0, -50.0, 0.0]])
    expected = np.array([10 + 20.0 + 0.5, -20 + 0.0 + 0.5, 30 + 135.0 + 0.5])
    np.testing.assert_allclose(ci.vector_nT(b, db)[0], expected)
    # |b + d| - |b| - u.d = sqrt((|b| + u.d)^2 + |d_perp|^2) - (|b| + u.d): the second-order
    # term, between 0 and |d_perp|^2 / (2 (|b| + u.d)).
    rng = np.random.default_rng(1)
    bb = rng.normal(size=(1000, 3)) * 30000
    d = rng.normal(size=(1000, 3)) * 300
    u = bb / np.linalg.norm(bb, axis=1, keepdims=True)
    along = np.einsum("ij,ij->i", u, d)
    err = scalar_reading_nT(bb, d) - np.linalg.norm(bb, axis=1) - along
    d_perp2 = np.sum(d**2, axis=1) - along**2
    assert np.all(err >= -1e-9)
    assert np.all(err <= d_perp2 / (2 * (np.linalg.norm(bb, axis=1) + along)) + 1e-9)


def test_fluxgate_errors_identity_and_model():
    b = np.array([[1000.0, -2000.0, 3000.0]])
    np.testing.assert_allclose(FluxgateErrors().apply(b), b)
    fe = FluxgateErrors([0.01, 0.0, 0.0], [0.0, 0.0, 0.0], [5.0, 0.0, 0.0])
    np.testing.assert_allclose(fe.apply(b), [[1015.0, -2000.0, 3000.0]])


@pytest.fixture(scope="module")
def quiet_off(tmp_path_factory):
    """Noise-free calibration box with the carrier's interference switched off."""
    sim = run_sim(
        "calibration-only", 5, ["calibration.passes=1", "interference_enabled=false", *QUIET]
    )
    path = write_simulation(sim, tmp_path_factory.mktemp("q") / "off.mcap")
    return sim, read_flight(path)


def test_interference_off_scalar_equals_field_magnitude(quiet_off):
    _sim, fl = quiet_off
    d = fl.data
    mag = np.sqrt(d.vector_x_nT**2 + d.vector_y_nT**2 + d.vector_z_nT**2)
    assert np.isfinite(mag).all() and len(mag) > 5000
    np.testing.assert_allclose(d.scalar_nT, mag, atol=1e-6, rtol=0)


def test_scalar_matches_independent_igrf_and_dipoles(quiet_off):
    """The recorded total field equals IGRF (ppigrf called here) plus the truth dipoles.

    The simulator evaluates IGRF once a second along the track and interpolates; the main
    field changes by < 0.03 nT per second of flight at 7 m/s, so the residual bound is 1e-3 nT.
    """
    sim, fl = quiet_off
    d = fl.data.iloc[::50]
    when = datetime(2026, 6, 15, 1, 0, 0)
    be, bn, bu = ppigrf.igrf(d.lon_deg.values, d.lat_deg.values, d.alt_m.values / 1000, when)
    main = np.stack([np.ravel(bn), np.ravel(be), -np.ravel(bu)], -1)
    from pipeline.geo.local import LocalFrame

    site = sim.truth["site"]
    frame = LocalFrame(site["latitude_deg"], site["longitude_deg"], site["ground_altitude_m"])
    e, n, u = frame.to_enu(d.lat_deg.values, d.lon_deg.values, d.alt_m.values)
    crust = np.zeros_like(main)
    for dp in sim.truth["anomaly"]["dipoles"]:  # the dipole formula, written out again
        r = np.stack([n - dp["north_m"], e - dp["east_m"], -(u - dp["up_m"])], -1)
        dist = np.linalg.norm(r, axis=1, keepdims=True)
        m = np.asarray(dp["moment_ned_A_m2"])
        crust += 100.0 * (3 * (r @ m)[:, None] * r / dist**2 - m) / dist**3
    expected = np.linalg.norm(main + crust, axis=1)
    assert np.max(np.abs(d.scalar_nT.values - expected)) < 1e-3


def test_scalar_interference_is_projection_on_field_to_first_order(tmp_path):
    """Scalar - |b| equals u.(p + A b + E db/dt) of the truth coefficients to second order.

    The fluxgate (no interference, no noise) at 50 Hz on the scalar's clock gives b and db/dt;
    the bound per sample is the second-order term |d_perp|^2/(2(|b| + u.d)) plus the 50 Hz
    central-difference error (< 0.005 nT here).
    """
    sim = run_sim(
        "calibration-only",
        6,
        [
            "calibration.passes=1",
            *QUIET,
            "sensors.vector_rate_hz=50.0",
            "vector_interference={permanent_nT=[0.0,0.0,0.0], induced=[[0.0,0.0,0.0],[0.0,0.0,0.0],"
            "[0.0,0.0,0.0]], eddy_s=[[0.0,0.0,0.0],[0.0,0.0,0.0],[0.0,0.0,0.0]]}",
        ],
    )
    sv, ss = sim.streams["/mag/vector"], sim.streams["/mag/scalar"]
    bv = np.stack([sv["cols"][k] for k in ("x_nT", "y_nT", "z_nT")], -1)
    dbv = np.gradient(bv, 1 / 50.0, axis=0)
    idx = np.rint((ss["t"] - sv["t"][0]) * 50.0).astype(int)  # same clock: nearest sample
    ok = (idx > 0) & (idx < len(sv["t"]) - 1)
    idx = idx[ok]
    assert np.allclose(sv["t"][idx], ss["t"][ok], atol=1e-9)
    b, db = bv[idx], dbv[idx]
    ci = CarrierInterference(**sim.truth["interference"]["scalar"])
    d = ci.vector_nT(b, db)
    bn = np.linalg.norm(b, axis=1)
    u = b / bn[:, None]
    measured = ss["cols"]["total_nT"][ok] - bn
    first = np.einsum("ij,ij->i", u, d)
    d_perp2 = np.sum(d**2, axis=1) - first**2
    assert np.all(np.abs(measured - first) <= d_perp2 / (2 * (bn + first)) + 0.005)
    # and the interference is far from negligible, so the check has teeth
    assert np.ptp(measured) > 30.0
