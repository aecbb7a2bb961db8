"""T-L / AGG-TL compensation: closed form, recovered interference, gradient bias, L-curve."""

from __future__ import annotations

import json
import subprocess

import numpy as np
import pytest
from scipy.signal import butter, sosfiltfilt

import tests.cli
from pipeline.compensate import FitSettings, Measurements, RidgeSVD, fit_compensation
from pipeline.compensate.filters import bandpass_blocks, bandpass_sos, contiguous_blocks
from pipeline.compensate.model import tl_terms
from pipeline.compensate.stage import calibration_mask, run_compensation
from pipeline.io.reader import read_flight
from pipeline.segment import segment_flight
from pipeline.simulate import write_simulation
from tests.conftest import FIXTURES, run_sim
from tests.recordings import validate_every_message


def cli(*args: str) -> subprocess.CompletedProcess:
    """The command in-process (tests/cli.py): no interpreter start-up per call."""
    return tests.cli.run(*args)


# ------------------------------------------------------------------------------------------
def _fdm(x):
    """MagNav.jl's ``fdm`` (src/analysis_util.jl), written out: per-sample central differences
    (x[k+1] - x[k-1]) / 2, one-sided at the ends, not divided by the sample interval."""
    out = np.empty_like(x, dtype=float)
    out[1:-1] = (x[2:] - x[:-2]) / 2.0
    out[0] = x[1] - x[0]
    out[-1] = x[-1] - x[-2]
    return out


def _magnav_create_tl_a(bx, by, bz, bt_scale=50000.0):
    """MagNav.jl's ``create_TL_A`` with its default terms (:permanent, :induced, :eddy),
    written out term by term from its formulas, in its column order."""
    bt = np.sqrt(bx**2 + by**2 + bz**2)
    xh, yh, zh = bx / bt, by / bt, bz / bt
    dx, dy, dz = _fdm(bx), _fdm(by), _fdm(bz)
    return np.column_stack(
        [
            xh,
            yh,
            zh,
            xh * bx / bt_scale,
            xh * by / bt_scale,
            xh * bz / bt_scale,
            yh * by / bt_scale,
            yh * bz / bt_scale,
            zh * bz / bt_scale,
            xh * dx / bt_scale,
            xh * dy / bt_scale,
            xh * dz / bt_scale,
            yh * dx / bt_scale,
            yh * dy / bt_scale,
            yh * dz / bt_scale,
            zh * dx / bt_scale,
            zh * dy / bt_scale,
            zh * dz / bt_scale,
        ]
    )


def _small_vector_input(n=9, seed=5):
    rng = np.random.default_rng(seed)
    return np.array([18000.0, -4000.0, 48000.0]) + np.cumsum(rng.normal(0, 300, (n, 3)), 0)


def test_tl18_equals_magnavs_design_matrix_at_any_sample_rate():
    """tl18 = MagNav's create_TL_A column for column; the eddy columns are per-sample
    differences, so they do not change with an even sampling's rate (10 Hz, 1 Hz)."""
    from pipeline.compensate import tl18_terms

    b = _small_vector_input()
    want = _magnav_create_tl_a(b[:, 0], b[:, 1], b[:, 2])
    for t in (np.arange(9) * 0.1, np.arange(9) * 1.0, None):
        k, names = tl18_terms(b, t)
        assert k.shape == (9, 18) and len(names) == 18
        np.testing.assert_allclose(k, want, rtol=1e-12, atol=1e-15)
    assert names[:3] == ["perm_ux", "perm_uy", "perm_uz"]
    assert names[3:9] == ["ind_uxBx", "ind_uxBy", "ind_uxBz", "ind_uyBy", "ind_uyBz", "ind_uzBz"]
    assert names[9:12] == ["eddy_uxdBx", "eddy_uxdBy", "eddy_uxdBz"]
    # the fitting path (model "tl18") uses the same columns
    meas = Measurements(np.arange(9) * 0.1, np.zeros(9), b)
    np.testing.assert_allclose(tl_terms("tl18", meas)[0], want, rtol=1e-13, atol=1e-16)


def test_uneven_sampling_does_not_scale_the_eddy_columns():
    """A recorder's uneven timing (samples 30 % of an interval early or late): MagNav's
    per-sample difference scales each derivative by its own intervals; taken per median
    interval the derivative follows the signal's to the stencil's error."""
    from pipeline.compensate.terms import per_nominal_sample_difference, per_sample_difference

    rng = np.random.default_rng(3)
    t = np.arange(600) * 0.1 + rng.uniform(-0.03, 0.03, 600)
    t.sort()
    w = 2 * np.pi * 0.25  # a 4 s manoeuvre
    x = 100.0 * np.sin(w * t)
    want = 100.0 * w * np.cos(w * t) * 0.1
    inner = slice(1, -1)
    err_nominal = per_nominal_sample_difference(x, t)[inner] - want[inner]
    err_sample = per_sample_difference(x)[inner] - want[inner]
    rms = np.sqrt(np.mean(want**2))
    assert np.sqrt(np.mean(err_nominal**2)) < 0.01 * rms
    assert np.sqrt(np.mean(err_sample**2)) > 0.1 * rms
    # repeated times (no derivative in time): MagNav's difference
    repeated = per_nominal_sample_difference(x, np.r_[t[:10], t[9], t[11:]])
    np.testing.assert_allclose(repeated, per_sample_difference(x), rtol=1e-12)
    # on even sampling the two are the same columns
    even = np.arange(600) * 0.1
    np.testing.assert_allclose(
        per_nominal_sample_difference(np.sin(w * even), even),
        per_sample_difference(np.sin(w * even)),
        rtol=1e-9,
        atol=1e-12,
    )


def test_magnav_term_options_map_to_ours():
    """MagNav's documented term groups (:permanent, :induced, :eddy, :bias and their short
    forms) select the same columns, in MagNav's fixed order whatever the order asked."""
    from pipeline.compensate import MAGNAV_TERMS, tl18_terms

    b = _small_vector_input()
    full = _magnav_create_tl_a(b[:, 0], b[:, 1], b[:, 2])
    groups = {"permanent": slice(0, 3), "induced": slice(3, 9), "eddy": slice(9, 18)}
    assert set(MAGNAV_TERMS) == {"permanent", "induced", "eddy", "bias"}
    for group, cols in groups.items():
        for spelling in (group, f":{group}", group[0]):
            k, names = tl18_terms(b, None, terms=(spelling,))
            np.testing.assert_allclose(k, full[:, cols], rtol=1e-13, atol=1e-16)
            assert all(n.startswith(MAGNAV_TERMS[group]) for n in names)
    k, names = tl18_terms(b, None, terms=(":bias", ":eddy", ":permanent", ":induced"))
    np.testing.assert_allclose(k[:, :18], full, rtol=1e-13, atol=1e-16)
    assert names[-1] == MAGNAV_TERMS["bias"] and np.all(k[:, -1] == 1.0)
    with pytest.raises(ValueError, match="unknown T-L term group"):
        tl18_terms(b, None, terms=("eddy", "gradient"))


def test_tl18_eddy_coefficients_scale_with_the_sample_interval():
    """A carrier (p, A, E) gives tl18 eddy coefficients E Bt_scale / dt: the same
    interference at 10 Hz and 20 Hz; the rate-independent set (per-second eddy columns,
    coefficients E Bt_scale) agrees; both match the linearised physics u . (p + A b + E db/dt)
    to the accuracy of the central difference."""
    from pipeline.compensate import tl18_rate_terms, tl18_terms, tl18_truth_coefficients

    rng = np.random.default_rng(11)
    p = rng.normal(0, 50, 3)
    a = rng.normal(0, 1e-3, (3, 3))
    e = rng.normal(0, 2e-3, (3, 3))
    for rate in (10.0, 20.0):
        t = np.arange(0, 30, 1 / rate)
        ang = 0.3 * np.sin(2 * np.pi * 0.2 * t)[:, None] * np.array([1.0, 0.7, 0.4])
        b = 50000 * np.column_stack(
            [np.cos(ang[:, 0]), np.sin(ang[:, 0]) * np.cos(ang[:, 1]), np.sin(ang[:, 1]) + 0.5]
        )
        db = np.gradient(b, t, axis=0)
        u = b / np.linalg.norm(b, axis=1, keepdims=True)
        physics = np.einsum("ni,ni->n", u, p + b @ a.T + db @ e.T)
        k, _ = tl18_terms(b, t)
        theta = tl18_truth_coefficients(p, a, e, 1 / rate)
        kr, names = tl18_rate_terms(b, t)
        theta_r = tl18_truth_coefficients(p, a, e, 1.0)
        assert names[9] == "eddy_uxdBxdt"
        np.testing.assert_allclose(theta[9:], theta_r[9:] * rate, rtol=1e-12)
        np.testing.assert_allclose(k @ theta, kr @ theta_r, rtol=1e-10, atol=1e-9)
        inner = slice(1, -1)
        assert np.max(np.abs((k @ theta - physics)[inner])) < 1e-6 * np.std(physics)


def test_tl18_coefficients_equal_the_closed_form(tmp_path):
    """`--model tl18 --band 0.1 0.9 --poles 4 --ridge 0.001` and `trim_s = 2.0` (20 samples
    at the fixture's 10 Hz) on a recording with only the two magnetometers equals
    theta = (K'K + lambda I)^-1 K'y written out here."""
    src = FIXTURES / "box_scalar_vector_only.mcap"
    cfg = tmp_path / "trim.toml"
    cfg.write_text("[compensation]\ntrim_s = 2.0\n")
    res = cli(
        "compensate",
        str(src),
        "--out",
        str(tmp_path / "o.mcap"),
        "--json",
        str(tmp_path / "s.json"),
        "--model",
        "tl18",
        "--band",
        "0.1",
        "0.9",
        "--poles",
        "4",
        "--ridge",
        "0.001",
        "--calibration",
        "all",
        "--config",
        str(cfg),
    )
    assert res.returncode == 0, res.stderr
    summary = json.loads((tmp_path / "s.json").read_text())

    d = read_flight(src).data  # aligned inputs (the reader is tested on its own)
    b = d[["vector_x_nT", "vector_y_nT", "vector_z_nT"]].to_numpy()
    y = d["scalar_nT"].to_numpy()

    bt = np.sqrt((b**2).sum(axis=1))
    u = b / bt[:, None]
    db = _fdm(b)
    cols = [u[:, 0], u[:, 1], u[:, 2]]
    cols += [
        u[:, i] * b[:, j] / 50000.0 for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
    ]
    cols += [u[:, i] * db[:, j] / 50000.0 for i in range(3) for j in range(3)]
    k = np.column_stack(cols)
    ok = np.isfinite(k).all(axis=1) & np.isfinite(y)
    first, last = np.flatnonzero(ok)[[0, -1]]
    assert ok[first : last + 1].all()  # one contiguous block
    sos = butter(4, [0.1 / 5.0, 0.9 / 5.0], btype="bandpass", output="sos")
    kf = sosfiltfilt(sos, k[first : last + 1], axis=0)[20:-20]
    yf = sosfiltfilt(sos, y[first : last + 1])[20:-20]
    theta = np.linalg.solve(kf.T @ kf + 0.001 * np.eye(18), kf.T @ yf)
    assert summary["model"] == "tl18" and summary["lambda"] == 0.001
    assert len(summary["terms"]) == 18 and summary["samples"] == len(yf)
    np.testing.assert_allclose(summary["coefficients"], theta, rtol=1e-6, atol=1e-9)
    assert summary["fom_nT"] == {"uncompensated": None, "compensated": None}  # no boxes here
    assert set(summary["residual_std_nT"]) == {"calibration", "survey"}
    assert validate_every_message(tmp_path / "o.mcap") > 10000


# ------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def clean_survey(tmp_path_factory):
    """A short UAV survey without gradient, compensated with tl18 (calibration: auto)."""
    sim = run_sim("uav-small", 3)
    flight = read_flight(write_simulation(sim, tmp_path_factory.mktemp("c") / "s.mcap"))
    seg = segment_flight(flight)
    run = run_compensation(flight, seg, FitSettings(model="tl18"))
    idx = np.searchsorted(sim.series["time_ns"], flight.time_ns)
    return sim, flight, seg, run, idx


def test_known_interference_is_recovered(clean_survey):
    """The band-passed interference the model predicts on the calibration passes matches the
    simulator's true interference better than the scalar sensor's noise (0.05 nT)."""
    sim, flight, seg, run, idx = clean_survey
    meas = Measurements.from_flight(flight)
    cal = calibration_mask(flight, seg, "auto")
    k, _ = tl_terms("tl18", meas)
    sos = bandpass_sos((0.1, 0.9), meas.rate_hz, 4)
    blocks = contiguous_blocks(cal & np.isfinite(k).all(axis=1), meas.time_s)
    kb, _ = bandpass_blocks(k, blocks, sos, 20)
    tb, _ = bandpass_blocks(sim.series["interference_nT"][idx], blocks, sos, 20)
    err = np.sqrt(np.mean((kb @ run.model.coefficients - tb) ** 2))
    noise = sim.truth["noise"]["scalar_nT"]
    assert err < noise
    assert np.std(tb) > 50 * err  # the interference itself is far larger


def test_survey_residual_within_noise_and_fom_drop(clean_survey):
    """Compensated survey = true field to within 1.5 x sensor noise, once the offset and the
    scale that no calibration can observe are removed.

    The isotropic part of the induced matrix, (tr A / 3) |B|, is constant during a
    calibration (|B| hardly changes), so band-pass fitting cannot see it; on the survey it
    scales the anomaly by tr A / 3 (0.14 % here). The fitted scale must be exactly that.
    """
    sim, flight, seg, run, idx = clean_survey
    earth = sim.series["earth_total_nT"][idx]
    s = seg.mask("survey") & np.isfinite(run.compensated_nT)
    x = np.column_stack([np.ones(s.sum()), earth[s]])
    coef, *_ = np.linalg.lstsq(x, run.compensated_nT[s], rcond=None)
    resid = run.compensated_nT[s] - x @ coef
    noise = sim.truth["noise"]["scalar_nT"]
    assert np.std(resid) <= 1.5 * noise
    trace_third = np.trace(np.array(sim.truth["interference"]["scalar"]["induced"])) / 3
    # standard error of the scale from the residual over ~1000 independent 0.1 Hz samples
    se = np.std(resid) / (np.std(earth[s]) * np.sqrt(s.sum() * 0.1 / 10.0))
    assert abs((coef[1] - 1.0) - trace_third) < 3 * se + 0.05 * trace_third
    fom = run.fom.total
    assert fom["uncompensated"] >= 5 * fom["compensated"]
    assert len(run.fom.boxes) == 12


# ------------------------------------------------------------------------------------------
def _box_pair(seed, extra=()):
    """The same calibration box (same seed, same noise) without and with a 0.45 nT/m
    gradient."""
    out = []
    for grad in (False, True):
        switch = f"effects.geomagnetic_gradient.enabled={str(grad).lower()}"
        sim = run_sim("calibration-only", seed, ["calibration.passes=1", *extra, switch])
        import tempfile
        from pathlib import Path

        fl = read_flight(write_simulation(sim, Path(tempfile.mkdtemp()) / "b.mcap"))
        seg = segment_flight(fl)
        out.append((sim, fl, Measurements.from_flight(fl), calibration_mask(fl, seg, "auto")))
    return out


def _recovery_error(sim, fl, meas, cal, model):
    """RMS of (predicted - true) band-passed interference on the fitted samples, and the
    error noise alone would give a correct model: sigma_res sqrt(p / n_eff), with n_eff the
    number of independent samples in the 0.1-0.9 Hz band."""
    k, _ = tl_terms(model.model, meas, model.settings.base)
    sos = bandpass_sos((0.1, 0.9), meas.rate_hz, 4)
    blocks = contiguous_blocks(cal & np.isfinite(k).all(axis=1), meas.time_s)
    kb, _ = bandpass_blocks(k, blocks, sos, 20)
    idx = np.searchsorted(sim.series["time_ns"], fl.time_ns)
    tb, _ = bandpass_blocks(sim.series["interference_nT"][idx], blocks, sos, 20)
    err = float(np.sqrt(np.mean((kb @ model.coefficients[: k.shape[1]] - tb) ** 2)))
    n_eff = model.n_fit * 2 * (0.9 - 0.1) / meas.rate_hz
    return err, model.fit_residual_nT * np.sqrt(len(model.terms) / n_eff)


@pytest.mark.parametrize("seed", [3, 4])
def test_gradient_biases_tl_and_agg_tl_recovers(seed):
    (s0, f0, m0, c0), (s1, f1, m1, c1) = _box_pair(seed)
    base_err, base_noise = _recovery_error(
        s0, f0, m0, c0, fit_compensation(m0, c0, FitSettings("tl18"))
    )
    tl_err, _ = _recovery_error(s1, f1, m1, c1, fit_compensation(m1, c1, FitSettings("tl18")))
    agg = fit_compensation(m1, c1, FitSettings("agg-tl"))
    agg_err, agg_noise = _recovery_error(s1, f1, m1, c1, agg)
    # T-L over a gradient: biased far beyond anything the (identical) noise explains
    assert tl_err > 5 * base_err and tl_err > base_err + 10 * base_noise
    # AGG-TL: back to the gradient-free error, within 3x what noise alone would add
    assert agg_err <= base_err + 3 * agg_noise


def test_agg_tl_estimates_the_gradient():
    """Over magnetically quiet ground the position terms give the regional gradient.

    The coefficient standard errors assume white residuals; the band-passed residual is
    correlated over ~1/(2 x 0.8 Hz), which inflates them by sqrt(fs / (2 B)) = 2.5.
    """
    (_s0, _f0, _m0, _c0), (sim, _fl, meas, cal) = _box_pair(4, ["anomaly.dipoles=0"])
    agg = fit_compensation(meas, cal, FitSettings("agg-tl"))
    g = agg.gradient_nT_per_m()
    sd = dict(zip(agg.terms, agg.coefficient_std * np.sqrt(10.0 / 1.6), strict=True))
    true = sim.truth["effective"]["gradient_nT_per_m"]
    assert abs(g["east"] - true[0]) <= 3 * sd["pos_e"]
    assert abs(g["north"] - true[1]) <= 3 * sd["pos_n"]


# ------------------------------------------------------------------------------------------
def test_lcurve_finds_a_known_corner():
    """Ten well-determined components (s = 1) and ten noise-only ones (s = 1e-3, |u'y| = eps):
    the L-curve's branches meet at residual eps sqrt(10) and solution norm sqrt(10)."""
    rng = np.random.default_rng(0)
    u, _ = np.linalg.qr(rng.normal(size=(400, 20)))
    v, _ = np.linalg.qr(rng.normal(size=(20, 20)))
    s = np.r_[np.ones(10), np.full(10, 1e-3)]
    eps = 1e-2
    y = u @ np.r_[np.ones(10), eps * rng.choice([-1.0, 1.0], 10)]
    lc = RidgeSVD(u @ np.diag(s) @ v.T, y).lcurve()
    c = lc.corner
    assert abs(np.log10(lc.residual_norm[c] / (eps * np.sqrt(10)))) < 0.05
    assert abs(np.log10(lc.solution_norm[c] / np.sqrt(10))) < 0.05
    assert 1e-6 < lc.lambda_corner < 1e-2  # between the two singular-value clusters


def test_compensate_cli_errors_and_window(tmp_path):
    src = FIXTURES / "box_scalar_vector_only.mcap"
    res = cli(
        "compensate",
        str(src),
        "--out",
        str(tmp_path / "a.mcap"),
        "--json",
        str(tmp_path / "a.json"),
    )
    assert res.returncode == 2 and "--calibration auto needs the segmentation" in res.stderr
    assert not (tmp_path / "a.mcap").exists()
    res = cli(
        "compensate",
        str(src),
        "--out",
        str(tmp_path / "b.mcap"),
        "--json",
        str(tmp_path / "b.json"),
        "--calibration",
        "100:400",
        "--model",
        "tl16",
    )
    assert res.returncode == 0, res.stderr
    s = json.loads((tmp_path / "b.json").read_text())
    w = s["calibration_windows_s"]
    assert len(w) == 1 and 99.9 <= w[0][0] and w[0][1] <= 400.1
    assert s["lcurve_png"].endswith(".lcurve.png")
    res = cli(
        "compensate",
        str(src),
        "--out",
        str(tmp_path / "c.mcap"),
        "--json",
        str(tmp_path / "c.json"),
        "--calibration",
        "all",
        "--model",
        "agg-tl",
    )
    assert res.returncode == 2 and "agg-tl needs positions" in res.stderr
    res = cli(
        "compensate",
        str(src),
        "--out",
        str(tmp_path / "d.mcap"),
        "--json",
        str(tmp_path / "d.json"),
        "--calibration",
        "all",
        "--band",
        "0.1",
        "6.0",
    )
    assert res.returncode == 2 and "Nyquist" in res.stderr


def test_compensate_with_segmentation_writes_every_channel(tmp_path, box_path):
    res = cli(
        "compensate",
        str(box_path),
        "--out",
        str(tmp_path / "o.mcap"),
        "--json",
        str(tmp_path / "s.json"),
        "--model",
        "agg-tl",
    )
    assert res.returncode == 0, res.stderr
    s = json.loads((tmp_path / "s.json").read_text())
    assert s["fom_nT"]["uncompensated"] > 5 * s["fom_nT"]["compensated"]
    assert s["residual_std_nT"]["calibration"] is not None
    assert s["gradient_nT_per_m"] is not None and s["base_terms"] == "tl18"
    from mcap.reader import make_reader

    with (tmp_path / "o.mcap").open("rb") as f:
        topics = {c.topic for c in make_reader(f).get_summary().channels.values()}
    assert {"/flight/segment", "/mag/compensated", "/compensation/model", "/aeromag/log"} <= topics
    validate_every_message(tmp_path / "o.mcap")


def test_calibration_guards_pass_a_full_box_and_flag_a_poor_one(box_path):
    """The full box passes all three guards for every model; one heading only, or boxes cut
    to 4.5 s, are flagged (and recorded in the summary) rather than silently fitted."""
    from pipeline.compensate import FitSettings
    from pipeline.compensate.fit import fit_compensation
    from pipeline.compensate.guards import CONDITION_LIMITS, check_calibration
    from pipeline.compensate.model import Measurements
    from pipeline.compensate.stage import run_compensation
    from pipeline.io.reader import read_flight
    from pipeline.segment import segment_flight

    fl = read_flight(box_path)
    seg = segment_flight(fl)
    full = {}  # condition number of the complete box, per model
    for model in ("tl16", "tl18", "agg-tl"):
        run = run_compensation(fl, seg, FitSettings(model=model), "auto")
        g = run.summary()["calibration_guards"]
        assert g["ok"] and g["warnings"] == [], g["warnings"]
        full[model] = g["condition_number"]
        assert g["condition_number"] < CONDITION_LIMITS[model] / 3  # a margin below the limit
        assert all(v > 60 for v in g["headings_s"].values())
        assert len(g["boxes"]) == 12 and min(b["seconds"] for b in g["boxes"]) > 10
    # one leg of the box: a single heading, the fit ill-conditioned
    west = seg.boxes()[-1].index
    t = fl.data["time_s"].to_numpy()
    run = run_compensation(fl, seg, FitSettings(model="tl18"), f"{t[west[0]]}:{t[west[-1]]}")
    text = " | ".join(run.check.warnings)
    assert "ill-conditioned" in text and "misses heading(s)" in text
    assert run.check.condition_number > max(100 * full["tl18"], CONDITION_LIMITS["tl18"])
    # every manoeuvre flown, but for 4.5 s only
    meas = Measurements.from_flight(fl)
    mask = np.zeros(t.size, bool)
    for b in seg.boxes():
        mask[b.index[:45]] = True
    model = fit_compensation(meas, mask, FitSettings(model="tl16"))
    check = check_calibration(
        "tl16",
        model.condition_number,
        model.weakest_terms,
        t,
        fl.data["yaw_deg"].to_numpy(),
        mask,
        seg.boxes(),
        min_heading_s=5.0,
    )
    text = " | ".join(check.warnings)
    assert "12 manoeuvre(s) shorter than 5 s" in text
    assert "ill-conditioned" in text
    assert check.condition_number > max(10 * full["tl16"], CONDITION_LIMITS["tl16"])


def test_audit_baseline_and_postflight_tl18_are_one_estimator(clean_survey):
    """The audit's baseline model is a term set of the post-flight estimator: on the same
    calibration epochs, the same band and the same lambda, ``fit_model`` (audit) and
    ``fit_compensation`` (process) give the same coefficients when the eddy columns take the
    same derivative (``ModelSpec.eddy_difference``). The audit's own (a five-point stencil)
    moves the eddy coefficients by about the central difference's shortfall, and the others
    hardly."""
    import pipeline.audit.extended as ext

    _sim, flight, seg, run, _idx = clean_survey
    cal = calibration_mask(flight, seg, "auto")
    lam = run.model.lambda_
    post = fit_compensation(
        Measurements.from_flight(flight), cal, FitSettings(model="tl18", ridge=lam)
    )
    data = ext.AuditData.from_flight(flight, cal)
    own = ext.fit_model(data, ext.ModelSpec("tl18"), cal, ridge=lam)
    audit = ext.fit_model(data, ext.ModelSpec("tl18", eddy_difference="per_sample"), cal, ridge=lam)
    assert audit.names[: len(post.terms)] == post.terms
    scale = np.max(np.abs(post.coefficients))
    np.testing.assert_allclose(
        audit.theta[: post.coefficients.size], post.coefficients, rtol=0, atol=1e-8 * scale
    )
    moved = np.abs(own.theta[: post.coefficients.size] - post.coefficients)
    assert 0 < np.max(moved) < 0.05 * scale


@pytest.mark.parametrize(
    ("rate_hz", "band_hz", "poles", "shape"),
    [
        (10.0, (0.1, 0.9), 4, (500,)),
        (20.0, (0.1, 0.9), 4, (300, 7)),
        (5.0, (0.05, 1.0), 2, (90, 1)),
    ],
)
def test_the_zero_phase_filter_is_scipys(rate_hz, band_hz, poles, shape):
    """The block filter's zero-phase pass (its steady state computed once per filter) gives
    scipy's sosfiltfilt to the last bit, and the cached design is a copy each call."""
    from pipeline.compensate.filters import filtfilt_sos

    x = np.random.default_rng(5).standard_normal(shape).cumsum(axis=0)
    sos = bandpass_sos(band_hz, rate_hz, poles)
    np.testing.assert_array_equal(filtfilt_sos(sos, x), sosfiltfilt(sos, x, axis=0))
    sos[0, 0] = 99.0  # a caller's change does not reach the next caller
    assert bandpass_sos(band_hz, rate_hz, poles)[0, 0] != 99.0
    with pytest.raises(ValueError):
        filtfilt_sos(sos, x[:10])


def test_fom_compares_the_boxes_both_fields_cover():
    """A fluxgate that starts late leaves the first legs uncompensated: the pass's FOM sums
    the boxes where both fields exist (like with like), says how many, and is not called
    complete; a box without data reads None, not NaN."""
    from pipeline.compensate.model import figure_of_merit
    from pipeline.segment.segmenter import Box

    rng = np.random.default_rng(4)
    t = np.arange(12 * 300) / 10.0
    raw = 5.0 * np.sin(2 * np.pi * 0.2 * t) + rng.normal(0, 0.05, t.size)
    comp = raw / 10.0
    comp[: 4 * 300] = np.nan  # the first four boxes without a compensated field
    boxes = [
        Box(1, "NESW"[k // 3], ("roll", "pitch", "yaw")[k % 3], np.arange(k * 300, (k + 1) * 300))
        for k in range(12)
    ]
    fom = figure_of_merit(t, raw, comp, boxes)
    (p,) = fom.passes
    assert (p["boxes"], p["boxes_compared"], p["complete"]) == (12, 8, False)
    assert fom.boxes[0]["compensated_nT"] is None
    assert p["compensated_nT"] == pytest.approx(p["uncompensated_nT"] / 10.0, rel=0.05)
    full = figure_of_merit(t, raw, raw / 10.0, boxes).passes[0]
    assert full["complete"] and full["boxes_compared"] == 12
