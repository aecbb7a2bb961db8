"""Number for number against MagNav.jl on its own test data (issue 38, item 1).

The data are MagNav.jl's ``test/test_data`` (real Caravan calibration flight, MagNav's expected
outputs), in ``../shared/peer/magnav/`` beside the repository (its README says what each
file holds and what MagNav's tests assert). Our own code runs here: the Pinson model
(:class:`InsErrorModel`), the EKF, the CRLB, harmonica's upward continuation and our T-L
estimator; nothing of MagNav's is re-implemented in this file.

Conversions at the test's boundary (nowhere else):

* states: MagNav's latitude/longitude errors are radians, ours north/east metres
  (``R dlat``, ``R cos(lat) dlon``, :meth:`InsErrorModel.metre_scale` at each epoch's
  latitude); MagNav's errors are true minus indicated (``get_h`` reads the map at
  ``lat + x``), ours indicated minus true, so every INS state changes sign (the Pinson
  dynamics are unchanged by it) and the magnetic bias state keeps its sign. ``S_k`` below is
  that diagonal map, ``x_ours = S_k x_magnav``, ``P_ours = S_k P_magnav S_k``.
* map: MagNav's map is on a longitude/latitude grid; ours is given the same grid with its
  coordinates in radians, interpolated bilinearly (MagNav's ``:linear``), and the filter is
  told the map-frame units per metre of position error (``1/R``, ``1/(R cos lat)``).
* Cnb: MATLAB's 3 x 3 x N to our N x 3 x 3.

Tolerances: MagNav's own (absolute, in its units) and, since an absolute 1e-6 on a radian
latitude error (~5e-7 rad per 3 m) would test nothing, the same numbers as relative ones in
every state's own scale: a state's difference over its standard deviation, a covariance
element's over ``sqrt(P_ii P_jj)``.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np
import pytest
from scipy.io import loadmat

from pipeline.maps.grid import Grid
from pipeline.navigation.crlb import crlb
from pipeline.navigation.ekf import MeasurementModel, ekf
from pipeline.navigation.ins import GRADES, R_EARTH_M, InsErrorModel, Trajectory
from pipeline.navigation.map_model import MapModel, upward_continue_values

# the shared folder beside the repository (CI: a fresh clone with shared/ next to it);
# AEROMAG_SHARED overrides it for checkouts laid out otherwise (git worktrees)
PEER = (
    Path(os.environ.get("AEROMAG_SHARED") or Path(__file__).resolve().parents[1].parent / "shared")
    / "peer"
    / "magnav"
)
pytestmark = pytest.mark.skipif(
    not (PEER / "test_data_ekf.mat").is_file(),
    reason=f"MagNav.jl's test data not found in {PEER} (the shared folder beside the repo)",
)


def _load(name: str, struct: str):
    return loadmat(PEER / name, squeeze_me=True)[struct]


def _f(s, key: str) -> np.ndarray:
    """A field of a MATLAB struct as float (scalars come back 0-d)."""
    v = s[key]
    return np.asarray(v.item() if v.shape == () else v, float)


def _trajectory(s, dt: float) -> Trajectory:
    n = _f(s, "lat").size
    return Trajectory(
        np.arange(n) * dt,
        np.radians(_f(s, "lat")),
        np.stack([_f(s, "vn"), _f(s, "ve"), _f(s, "vd")], axis=1),
        np.stack([_f(s, "fn"), _f(s, "fe"), _f(s, "fd")], axis=1),
        np.moveaxis(_f(s, "Cnb"), 2, 0),
    )


@pytest.fixture(scope="module")
def peer():
    params = _load("test_data_params.mat", "params")
    ekf_data = _load("test_data_ekf.mat", "ekf_data")
    map_data = _load("test_data_map.mat", "map_data")
    grade = dataclasses.replace(
        GRADES["navigation"],
        baro_tau_s=float(_f(params, "baro_tau")),
        acc_tau_s=float(_f(params, "acc_tau")),
        gyro_tau_s=float(_f(params, "gyro_tau")),
    )
    model = InsErrorModel(grade, mag_bias_tau_s=float(_f(params, "meas_tau")))
    lon, lat = np.radians(_f(map_data, "xx")), np.radians(_f(map_data, "yy"))
    cell = float(np.diff(lon).mean())
    # MagNav's map is (latitude rows, longitude columns) on a uniform 0.01 deg grid
    assert np.allclose(np.diff(lon), cell, rtol=1e-9) and np.allclose(np.diff(lat), cell, rtol=1e-9)
    grid = Grid(_f(map_data, "map"), float(lon[0]), float(lat[0]), cell)
    return {
        "dt": float(_f(params, "dt")),
        "model": model,
        "map": MapModel(grid, method="linear"),
        "P0": _f(ekf_data, "P0"),
        "Qd": _f(ekf_data, "Qd"),
        "R": float(_f(ekf_data, "R")),
        "ekf": ekf_data,
        "ins": _load("test_data_ins.mat", "ins_data"),
        "traj": _load("test_data_traj.mat", "traj"),
    }


def _ours(peer, track):
    """Transition matrices, P0 and Qd in our states, the sign/unit map S (N, 18) and the
    measurement model, along ``track`` (the INS for the EKF, the truth for the CRLB)."""
    model = peer["model"]
    traj = _trajectory(track, peer["dt"])
    s = model.metre_scale(traj.lat_rad)
    s[:, :17] *= -1.0  # true-minus-indicated -> indicated-minus-true
    p0 = s[0][:, None] * peer["P0"] * s[0][None, :]
    assert np.count_nonzero(peer["Qd"] - np.diag(np.diag(peer["Qd"]))) == 0
    qd = np.diag(peer["Qd"])[None, :] * s**2
    scale = np.stack(
        [np.full(len(traj), 1.0 / R_EARTH_M), 1.0 / (R_EARTH_M * np.cos(traj.lat_rad))], axis=1
    )
    meas = MeasurementModel(peer["map"], map_scale=scale)
    return model.transitions(traj), p0, qd, s, meas


def _close_cov(ours_m, s, want, atol):
    """Our covariance (metre states) against MagNav's: absolute in MagNav's units and
    relative to ``sqrt(P_ii P_jj)``."""
    got = ours_m / s[:, None] / s[None, :]
    scale = np.sqrt(np.outer(np.diag(want), np.diag(want)))
    assert np.abs(got - want).max() <= atol
    rel = np.abs(got - want) / scale
    assert rel.max() <= atol, f"largest relative difference {rel.max():.2e}"


def test_ekf_reproduces_magnavs_first_and_last_step(peer):
    phi, p0, qd, s, meas = _ours(peer, peer["ins"])
    ins = peer["ins"]
    z = _f(peer["traj"], "mag_1_c")
    res = ekf(
        phi,
        qd,
        p0,
        z,
        np.radians(_f(ins, "lon")),
        np.radians(_f(ins, "lat")),
        meas,
        peer["R"],
        full_cov=True,
    )
    x_want, p_want = _f(peer["ekf"], "x_out"), _f(peer["ekf"], "P_out")
    assert res.updated.all()
    for col, k, tol in ((0, 0, 1e-6), (1, z.size - 1, 1e-3)):
        x = res.state[k] / s[k]
        assert np.abs(x - x_want[:, col]).max() <= tol
        sd = np.sqrt(np.diag(p_want[:, :, col]))
        rel = np.abs(x - x_want[:, col]) / sd
        assert rel.max() <= tol, f"epoch {k}: state off by {rel.max():.2e} of its sigma"
        _close_cov(res.cov[k], s[k], p_want[:, :, col], tol)
    # the filter moved: the comparison is not of two zero states
    assert np.abs(x_want[:, 1] / np.sqrt(np.diag(p_want[:, :, 1]))).max() > 0.1


def test_crlb_reproduces_magnavs_along_the_true_track(peer):
    phi, p0, qd, s, meas = _ours(peer, peer["traj"])
    tr = peer["traj"]
    bound = crlb(
        phi,
        qd,
        p0,
        np.radians(_f(tr, "lon")),
        np.radians(_f(tr, "lat")),
        meas,
        peer["R"],
        full_cov=True,
    )
    want = _f(peer["ekf"], "crlb_P")
    for col, k in ((0, 0), (1, bound.shape[0] - 1)):
        _close_cov(bound[k], s[k], want[:, :, col], 1e-6)
    # the map informed the bound: below the INS alone at the end
    lon, lat = np.radians(_f(tr, "lon")), np.radians(_f(tr, "lat"))
    free = crlb(phi, qd, p0, lon, lat, meas, peer["R"], np.zeros(lat.size, bool))
    assert np.trace(bound[-1][:2, :2]) < 0.9 * np.trace(free[-1])


def test_upward_continuation_reproduces_magnavs_upward_fft():
    """harmonica's operator without padding = MagNav's ``upward_fft(map, dx, dy, dz;
    expand=false)``; dx is along the columns (longitude), dy along the rows."""
    m = _load("test_data_map.mat", "map_data")
    got = upward_continue_values(_f(m, "map"), _f(m, "dx"), _f(m, "dy"), _f(m, "dz"), pad=False)
    want = _f(m, "map_out")
    rel = np.sqrt(np.mean((got - want) ** 2)) / np.sqrt(np.mean(want**2))
    assert rel < 1e-6
    # padded (our default) is a different, deliberate edge treatment: not MagNav's numbers
    padded = upward_continue_values(_f(m, "map"), _f(m, "dx"), _f(m, "dy"), _f(m, "dz"))
    assert np.sqrt(np.mean((padded - want) ** 2)) / np.sqrt(np.mean(want**2)) > 1e-3


def test_tolles_lawson_within_magnavs_tenth_of_a_nanotesla():
    """Our estimator (tl18 terms, band-passed ridge) with MagNav's fit settings compensates
    like MagNav: std of the difference of the compensated outputs < 0.1 nT, raw and with the
    correction detrended (MagNav's two assertions)."""
    from scipy.signal import detrend

    from pipeline.compensate import FitSettings, fit_compensation
    from pipeline.compensate.model import Measurements
    from pipeline.compensate.terms import tl18_terms

    tl = _load("test_data_TL.mat", "TL_data")
    settings = _load("test_data_params.mat", "params")["TL"].item()
    p = {k: float(np.asarray(settings[k]).ravel()[0]) for k in settings.dtype.names}
    fs = float(_f(tl, "fs"))
    b = np.stack([_f(tl, "flux_a_x"), _f(tl, "flux_a_y"), _f(tl, "flux_a_z")], axis=1)
    uc = _f(tl, "mag_1_uc")
    # the design matrix is MagNav's create_TL_A
    a, _ = tl18_terms(b, bt_scale_nT=p["Bt_scale"])
    np.testing.assert_allclose(a, _f(tl, "A_a"), rtol=1e-10, atol=1e-12)
    fit = FitSettings(
        model="tl18",
        band_hz=(p["pass1"], p["pass2"]),
        trim_s=round(p["trim"]) / fs,  # MagNav counts samples
        ridge=p["lambda"],
        bt_scale_nT=p["Bt_scale"],
    )
    model = fit_compensation(
        Measurements(np.arange(uc.size) / fs, uc, b), np.ones(uc.size, bool), fit
    )
    comp, interference = model.compensate(Measurements(np.arange(uc.size) / fs, uc, b))
    assert np.std(comp - _f(tl, "mag_1_c"), ddof=1) < 0.1
    assert np.std(uc - detrend(interference) - _f(tl, "mag_1_c_d"), ddof=1) < 0.1
