"""Anomaly maps: ARIMA identification and state space, Kalman filter, leveling, gridding."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

import tests.cli
from pipeline.compensate import FitSettings
from pipeline.compensate.stage import run_compensation
from pipeline.io.reader import read_flight
from pipeline.maps.arima import (
    ArimaModel,
    _level_state,
    fit_arima,
    kalman_filter,
    reverse_arrangements,
)
from pipeline.maps.grid import Grid, minimum_curvature
from pipeline.maps.level import Line, crossovers, level_lines, track_crossings
from pipeline.maps.stage import anomaly_grid, build_map, filter_sequence, serialize
from pipeline.segment import segment_flight
from pipeline.simulate import write_simulation
from pipeline.simulate.truth import truth_on
from tests.conftest import MAPPED_SURVEY, run_sim
from tests.recordings import validate_every_message

PAPER_AR = np.array([-0.4178, -0.3517])


def simulate_arima(ar, ma, d, n, rng):
    e = rng.normal(size=n + 100)
    w = np.zeros_like(e)
    for k in range(e.size):
        w[k] = (
            e[k]
            + sum(ar[i] * w[k - 1 - i] for i in range(len(ar)) if k - 1 - i >= 0)
            + sum(ma[j] * e[k - 1 - j] for j in range(len(ma)) if k - 1 - j >= 0)
        )
    x = w[100:]
    for _ in range(d):
        x = np.cumsum(x)
    return x


def test_paper_arima_211_is_identified():
    x = simulate_arima(PAPER_AR, [0.3], 1, 6000, np.random.default_rng(4))
    m = fit_arima(x)
    assert m.order == (2, 1, 1)
    np.testing.assert_allclose(m.ar, PAPER_AR, atol=0.05)
    np.testing.assert_allclose(m.ma, [0.3], atol=0.05)
    assert any(s["d"] == 0 and not s["stationary"] for s in m.tests["stationarity"])


def test_companion_form_reproduces_the_recursion_exactly():
    """(1 - phi1 B - phi2 B^2)(1 - B) = 1 - 0.5822 B - 0.0661 B^2 - 0.3517 B^3: the last
    coefficient of x_(k-3) is +0.3517 (the paper prints -0.3517)."""
    m = ArimaModel(2, 1, 1, PAPER_AR, np.array([0.002]), 1.0)
    np.testing.assert_allclose(m.integrated_ar(), [0.5822, 0.0661, 0.3517], atol=1e-12)
    rng = np.random.default_rng(0)
    e = rng.normal(size=500)
    # ARIMA recursion written directly from the paper's definitions
    w = np.zeros(500)
    x = np.zeros(500)
    for k in range(500):
        w[k] = (
            e[k]
            + 0.002 * (e[k - 1] if k else 0.0)
            + sum(PAPER_AR[i] * w[k - 1 - i] for i in range(2) if k - 1 - i >= 0)
        )
        x[k] = (x[k - 1] if k else 0.0) + w[k]
    # the lagged-state companion matrix (paper's form), driven by the MA-filtered noise w
    f = m.companion()
    s = np.zeros(3)
    dw = np.zeros(500)
    for k in range(500):
        u = e[k] + 0.002 * (e[k - 1] if k else 0.0)
        s = f @ s + np.r_[u, 0, 0]
        dw[k] = s[0]
    np.testing.assert_allclose(dw, x, atol=1e-9)
    # and Harvey's form (used by the filter) on the raw innovations
    t, r, z = m.harvey()
    a = np.zeros(3)
    hx = np.zeros(500)
    for k in range(500):
        a = t @ a + r * e[k]
        hx[k] = z @ a
    np.testing.assert_allclose(hx, x, atol=1e-9)


def test_kalman_filter_equals_statsmodels():
    from statsmodels.tsa.statespace.kalman_filter import KalmanFilter

    rng = np.random.default_rng(2)
    m = ArimaModel(2, 1, 1, PAPER_AR, np.array([0.3]), 0.8)
    y = simulate_arima(PAPER_AR, [0.3], 1, 8000, rng) + rng.normal(0, 0.5, 8000)
    y[700:730] = np.nan
    y[5000:5900] = np.nan
    ours = kalman_filter(y, m, 0.25)
    t, r, z = m.harvey()
    kf = KalmanFilter(k_endog=1, k_states=3, k_posdef=1)
    kf.bind(y.reshape(-1, 1))
    kf["design"], kf["transition"] = z.reshape(1, -1), t
    kf["selection"], kf["state_cov"] = r.reshape(-1, 1), np.array([[0.8]])
    kf["obs_cov"] = np.array([[0.25]])
    x0, p0 = _level_state(t, y[0]), np.eye(3) * 1e6 * np.nanvar(y)
    kf.initialize_known(t @ x0, t @ p0 @ t.T + 0.8 * np.outer(r, r))  # predicted for k = 0
    ref = z @ kf.filter().filtered_state
    ok = np.isfinite(y)
    assert np.max(np.abs(ref[ok] - ours.filtered[ok])) < 1e-6
    assert ours.exact_steps < 1000  # most samples went through the steady-state IIR path


def test_reverse_arrangements_rejects_a_trend_and_accepts_white_noise():
    rng = np.random.default_rng(3)
    accepted = sum(reverse_arrangements(rng.normal(size=2000)).stationary for _ in range(200))
    assert accepted >= 180  # 5 % level: ~190 of 200 expected
    trend = np.linspace(0, 1.0, 2000) + rng.normal(size=2000)
    assert not reverse_arrangements(trend).stationary


def test_crossovers_are_found_exactly():
    """Two straight tracks crossing at an analytic point; fields linear along track."""
    t = np.linspace(0, 100, 101)
    a = Line("L1", "survey", 10.0 + 0.0 * t, -50 + t, t, 100 + 0.5 * t, np.arange(101))
    b = Line("T1", "tie", -40 + t * 1.0, 0.2 * (-40 + t) + 3.0, t + 500, 200 - t, np.arange(101))
    xs = crossovers([a], [b])
    assert len(xs) == 1
    c = xs[0]
    # x = 10 on L1; on T1, y = 0.2 * 10 + 3 = 5
    assert abs(c.east_m - 10.0) < 1e-9 and abs(c.north_m - 5.0) < 1e-9
    assert abs(c.value_a_nT - (100 + 0.5 * 55)) < 1e-9  # L1 passes y = 5 at t = 55
    assert abs(c.value_b_nT - (200 - 50)) < 1e-9  # T1 passes x = 10 at t = 50


def _noisy_line(line_id, kind, start, end, first_epoch, rng, noise_m=0.5, step_m=0.7):
    """A straight line flown at 7 m/s, 10 Hz, with white position noise on both coordinates;
    the field is 0.01 nT/m east + 0.02 nT/m north."""
    (e0, n0), (e1, n1) = start, end
    f = np.linspace(0.0, 1.0, int(np.hypot(e1 - e0, n1 - n0) / step_m) + 1)
    e = e0 + f * (e1 - e0) + rng.normal(0, noise_m, f.size)
    n = n0 + f * (n1 - n0) + rng.normal(0, noise_m, f.size)
    idx = first_epoch + np.arange(f.size)
    return Line(line_id, kind, e, n, idx * 0.1, 0.01 * e + 0.02 * n, idx)


def test_noisy_grid_has_one_crossover_per_survey_and_tie_line():
    """6 survey x 4 tie lines with 0.5 m position noise: exactly 6 x 4 crossovers, one per
    pair, at the nominal crossing; a tie flown 0-10 deg along a survey line adds none."""
    rng = np.random.default_rng(8)
    xs_east, ys_north = (0.0, 60.0, 120.0, 180.0, 240.0, 300.0), (40.0, 140.0, 240.0, 340.0)
    survey = [
        _noisy_line(
            f"L{k}", "survey", *(((x, -20.0), (x, 420.0))[:: 1 - 2 * (k % 2)]), 10_000 * k, rng
        )
        for k, x in enumerate(xs_east)
    ]
    ties = [
        _noisy_line(
            f"T{k}",
            "tie",
            *(((-20.0, y), (320.0, y))[:: 1 - 2 * (k % 2)]),
            100_000 + 10_000 * k,
            rng,
        )
        for k, y in enumerate(ys_north)
    ]
    xs = crossovers(survey, ties)
    assert len(xs) == 6 * 4
    assert len({(c.line_a, c.line_b) for c in xs}) == 6 * 4
    for c in xs:
        want = (xs_east[int(c.line_a[1:])], ys_north[int(c.line_b[1:])])
        assert np.hypot(c.east_m - want[0], c.north_m - want[1]) < 3.0
        assert c.angle_deg > 80.0
    # transits flown along survey line L2 (x = 120), labelled tie: many raw hits, none
    # of them a crossover
    for deg in (0.0, 4.0, 10.0):
        a = np.radians(deg)
        along = _noisy_line(
            "T9",
            "tie",
            (120.0 - 200 * np.sin(a), 200.0 - 200 * np.cos(a)),
            (120.0 + 200 * np.sin(a), 200.0 + 200 * np.cos(a)),
            900_000,
            rng,
        )
        assert crossovers(survey, [along]) == []
    assert len(crossovers(survey, ties + [along])) == 6 * 4
    lev = level_lines(survey + ties + [along])
    assert len(lev.crossovers) == 6 * 4 and lev.rms_after_nT < 0.1
    # the crossings found once serve every field read along the same tracks; a pair they
    # lack is intersected anew
    shared = track_crossings(survey, ties[1:])
    assert len(shared) == 6 * 3
    for field in (0.0, 3.0):
        moved = [replace(ln, value_nT=ln.value_nT + field * k) for k, ln in enumerate(survey)]
        assert crossovers(moved, ties, crossings=shared) == crossovers(moved, ties)


def test_leveling_removes_line_offsets():
    rng = np.random.default_rng(5)
    lines = []
    truth = lambda e, n: 0.01 * e + 0.02 * n  # noqa: E731
    offsets = {}
    for k in range(6):
        n = np.linspace(0, 500, 400)
        e = np.full(n.size, 100.0 * k)
        off = rng.normal(0, 3)
        offsets[f"L{k}"] = off
        lines.append(
            Line(f"L{k}", "survey", e, n, n + 1000 * k, truth(e, n) + off, np.arange(n.size))
        )
    for k in range(3):
        e = np.linspace(-10, 510, 400)
        n = np.full(e.size, 50.0 + 200 * k)
        lines.append(
            Line(
                f"T{k}",
                "tie",
                e,
                n,
                e + 9000 + 1000 * k,
                truth(e, n) + rng.normal(0, 3),
                np.arange(e.size),
            )
        )
    lev = level_lines(lines)
    assert lev.rms_before_nT > 1.0 and lev.rms_after_nT < 1e-9
    corrected = [off - lev.correction(f"L{k}", 0.0) for k, off in enumerate(offsets.values())]
    assert np.ptp(corrected) < 1e-9  # one common constant remains


def test_minimum_curvature_reproduces_a_smooth_field():
    rng = np.random.default_rng(0)

    def f(x, y):
        return 30 * np.exp(-((x - 350) ** 2 + (y - 1000) ** 2) / (2 * 250**2)) + 0.01 * x

    xs, ys = [], []
    for e0 in np.arange(0, 701, 50):
        y = np.arange(0, 2000, 0.7)
        xs.append(e0 + rng.normal(0, 0.5, y.size))
        ys.append(y)
    x, y = np.concatenate(xs), np.concatenate(ys)
    g = minimum_curvature(x, y, f(x, y), 12.5, mask_distance_m=50)
    gx, gy = np.meshgrid(*g.coordinates())
    ok = np.isfinite(g.values)
    assert np.sqrt(np.mean((g.values[ok] - f(gx, gy)[ok]) ** 2)) < 0.05  # of a 30 nT anomaly
    # cells beyond the mask distance are masked
    far = Grid(g.values, g.east0_m, g.north0_m, g.cell_m)
    assert np.isnan(far.interpolate(np.array([-200.0]), np.array([1000.0]))).all()


# ------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def mapped(tmp_path_factory):
    """A UAV survey over geology the 50 m lines resolve: two induced sources 300-500 m deep
    under the block (a negative margin keeps them inside it), so the largest anomaly is an
    interior peak."""
    sim = run_sim(*MAPPED_SURVEY)
    path = write_simulation(sim, tmp_path_factory.mktemp("m") / "m.mcap")
    flight = read_flight(path)
    seg = segment_flight(flight)
    run = run_compensation(flight, seg, FitSettings(model="agg-tl"))
    return sim, path, flight, seg, run, build_map(flight, seg, run.compensated_nT)


def test_levelled_grid_matches_the_truth_within_noise(mapped):
    """After removing the offset and the unobservable isotropic-induced scale (see
    test_compensate), the levelled grid is the true anomaly to 1.5 x the sensor noise."""
    sim, _p, _f, _s, _r, mr = mapped
    truth = truth_on(sim, mr.grid, mr.frame)
    ok = np.isfinite(truth) & np.isfinite(mr.grid.values)
    x = np.column_stack([np.ones(ok.sum()), truth[ok]])
    coef, *_ = np.linalg.lstsq(x, mr.grid.values[ok], rcond=None)
    rmse = np.sqrt(np.mean((mr.grid.values[ok] - x @ coef) ** 2))
    assert rmse <= 1.5 * sim.truth["noise"]["scalar_nT"]
    # the scale is 1 + tr(A) / 3, the isotropic induced part no calibration observes; its
    # standard error from the residual, with one independent value per line spacing squared
    # (cells are a quarter spacing: 16 cells per independent value)
    trace_third = np.trace(np.array(sim.truth["interference"]["scalar"]["induced"])) / 3
    se = rmse / (np.std(truth[ok]) * np.sqrt(ok.sum() / 16))
    assert abs((coef[1] - 1.0) - trace_third) <= 3 * se + 0.05 * abs(trace_third), (
        coef[1],
        trace_third,
        se,
    )
    assert mr.leveling.rms_after_nT < mr.leveling.rms_before_nT
    assert abs(mr.spacing_m - 50.0) < 1.0 and abs(mr.grid.cell_m - 12.5) < 0.3


def test_anomaly_grid_is_the_map_stage_before_its_filter(mapped):
    """The grid without the ARIMA-Kalman filter (what comparisons of grids use) is the map
    stage's grid cell for cell, and the same lines' levelling."""
    _sim, _p, flight, seg, run, mr = mapped
    gm = anomaly_grid(flight, seg, run.compensated_nT)
    np.testing.assert_array_equal(gm.grid.values, mr.grid.values)
    assert gm.spacing_m == mr.spacing_m
    assert [ln.line_id for ln in gm.lines] == [ln.line_id for ln in mr.lines]
    assert gm.leveling.rms_after_nT == mr.leveling.rms_after_nT


def test_arima_kalman_removes_map_noise_and_keeps_the_peak(mapped):
    """1 nT of white noise added to the map: the ARIMA-Kalman filter (ARIMA signal plus
    known 1 nT measurement noise, identified on the noisy map) lowers the RMSE vs truth by
    >= 30 % and keeps the largest anomaly's peak within 5 %. The product is the zero-phase
    Rauch-Tung-Striebel smoother along the lines. (Fails if identification accepts a
    degenerate fit: see docs/science-paper004.md.)"""
    sim, _p, flight, seg, run, mr = mapped
    truth = truth_on(sim, mr.grid, mr.frame)
    rng = np.random.default_rng(11)
    noisy = mr.grid.with_values(mr.grid.values + rng.normal(0, 1.0, mr.grid.shape))
    seq, order = serialize(noisy, along_north=True)
    model = fit_arima(seq[np.isfinite(seq)], measurement_var=1.0)
    filt = np.full(seq.size, np.nan)
    filt[order] = filter_sequence(seq, model, 1.0)[0]
    filt = filt.reshape(noisy.shape)
    ok = np.isfinite(truth) & np.isfinite(filt)

    def rmse(g):
        d = g[ok] - truth[ok]
        return np.sqrt(np.mean((d - d.mean()) ** 2))

    before, after = rmse(noisy.values), rmse(filt)
    assert after <= 0.7 * before, (before, after)

    def peak(g, r, c):
        """3 x 3 mean about (r, c), relative to the block's median: one cell would measure
        the remaining noise, not whether the filter flattened or shifted the anomaly."""
        return np.mean(g[r - 1 : r + 2, c - 1 : c + 2]) - np.median(g[ok])

    # the anomaly's peak: the truth's maximum among cells whose 3 x 3 neighbourhood is scored
    from scipy.ndimage import minimum_filter

    interior = minimum_filter(ok.astype(int), size=3, mode="constant") == 1
    r, c = np.unravel_index(np.argmax(np.where(interior, truth, -np.inf)), truth.shape)
    assert peak(truth, r, c) > 5.0  # a real anomaly: five times the added 1 nT noise
    assert abs(peak(filt, r, c) - peak(truth, r, c)) <= 0.05 * abs(peak(truth, r, c))


def test_forward_filter_lags_and_removes_less_noise(mapped):
    """Paper 004's causal (forward-only) filter against the map product's zero-phase one, on
    the same 1 nT noisy map, both scored against the true anomaly: the forward filter removes
    less of the added noise (it has only the past) and shifts the anomaly along the lines
    (its error on the noise-free map is larger). docs/science-paper004.md quotes the two
    fractions."""
    sim, _p, _f, _s, _r, mr = mapped
    truth = truth_on(sim, mr.grid, mr.frame)
    rng = np.random.default_rng(11)
    noisy = mr.grid.with_values(mr.grid.values + rng.normal(0, 1.0, mr.grid.shape))
    seq, order = serialize(noisy, along_north=True)
    model = fit_arima(seq[np.isfinite(seq)], measurement_var=1.0)
    clean_seq, _ = serialize(mr.grid, along_north=True)

    def run(x, direction):
        out = np.full(x.size, np.nan)
        out[order] = filter_sequence(x, model, 1.0, direction)[0]
        return out.reshape(noisy.shape)

    ok = np.isfinite(truth) & np.isfinite(noisy.values)

    def rmse(g):
        d = g[ok] - truth[ok]
        return np.sqrt(np.mean((d - d.mean()) ** 2))

    before = rmse(noisy.values)
    removed = {d: 1.0 - rmse(run(seq, d)) / before for d in ("forward", "both")}
    assert 0.0 < removed["forward"] < removed["both"], removed
    assert removed["both"] - removed["forward"] > 0.03, removed  # not a rounding difference
    # on the noise-free map the forward filter distorts (lags) the anomaly more
    lag = {d: rmse(run(clean_seq, d)) for d in ("forward", "both")}
    assert lag["forward"] > lag["both"], lag


def test_map_cli_and_channels(mapped, tmp_path):
    _sim, path, *_ = mapped
    res = tests.cli.run(
        "map",
        str(path),
        "--out",
        str(tmp_path / "o.mcap"),
        "--json",
        str(tmp_path / "s.json"),
        "--arima",
        "2,1,1",
    )
    assert res.returncode == 0, res.stderr
    s = json.loads((tmp_path / "s.json").read_text())["map"]
    for key in ("grid_shape", "cell_m", "crossover_rms_nT", "arima_order", "arima_coefficients"):
        assert key in s
    assert s["arima_order"] == [2, 1, 1] and len(s["arima_coefficients"]["ar"]) == 2
    assert set(s["crossover_rms_nT"]) == {"before", "after"}
    # Foxglove's official Grid and GeoJSON, and every other channel the command added
    assert (
        validate_every_message(
            tmp_path / "o.mcap",
            {
                "/map/frame",
                "/map/anomaly",
                "/map/anomaly_filtered",
                "/map/lines",
                "/map/tracks",
                "/aeromag/log",
                "/flight/segment",
                "/mag/compensated",
                "/compensation/model",
            },
        )
        > 1000
    )
    from mcap.reader import make_reader

    with (tmp_path / "o.mcap").open("rb") as f:
        msgs = {
            c.topic: json.loads(m.data)
            for _s, c, m in make_reader(f).iter_messages(topics=["/map/anomaly", "/map/tracks"])
        }
    g = msgs["/map/anomaly"]
    import base64

    cells = np.frombuffer(base64.b64decode(g["data"]), "<f4")
    assert cells.size == s["grid_shape"][0] * s["grid_shape"][1]
    assert g["column_count"] == s["grid_shape"][1] and g["cell_size"]["x"] == s["cell_m"]
    feats = json.loads(msgs["/map/tracks"]["geojson"])["features"]
    assert {f["properties"]["label"] for f in feats} >= {"survey", "tie", "calibration"}
    for png in ("anomaly", "anomaly_filtered"):
        assert (tmp_path / f"s.{png}.png").stat().st_size > 10000
    bad = tests.cli.run(
        "map",
        str(path),
        "--out",
        str(tmp_path / "x.mcap"),
        "--json",
        str(tmp_path / "x.json"),
        "--arima",
        "two",
    )
    assert bad.returncode == 2 and "--arima 'two'" in bad.stderr


@pytest.mark.slow  # about a minute: eleven full fits on 12 000 cells
def test_order_screening_on_a_long_sequence_keeps_the_full_search_result(monkeypatch):
    """A long map lane (12 000 cells of 12.5 m: anomalies 50-800 m wide, white noise): the
    order search that ranks candidates on the first cells and fits a shortlist on all of them
    smooths the lane as the search fitting every candidate on all cells does."""
    import pipeline.maps.arima as arima
    from pipeline.maps.arima import rts_smooth

    rng = np.random.default_rng(4)
    s = np.arange(12_000) * 12.5
    x = np.zeros(s.size)
    for _ in range(120):
        c, w, a = rng.uniform(0, s[-1]), rng.uniform(50, 800), rng.normal(0, 30)
        x += a / (1 + ((s - c) / w) ** 2) ** 1.5
    y = x + rng.normal(0, 0.5, s.size)
    screened = fit_arima(y, measurement_var=0.25)
    assert screened.tests["screened"], "a sequence this long is screened"
    monkeypatch.setattr(arima, "SCREEN_ABOVE", 10**9)  # every candidate fitted exactly
    full = fit_arima(y, measurement_var=0.25)
    assert not full.tests["screened"]
    a, b = rts_smooth(y, screened, 0.25), rts_smooth(y, full, 0.25)
    # the smoothed lanes agree to a small share of the noise, and both remove most of it
    assert np.sqrt(np.mean((a - b) ** 2)) < 0.05 * 0.5
    assert np.sqrt(np.mean((a - x) ** 2)) < 0.5 * 0.5


def test_map_stage_writes_the_uncertainty_on_the_anomaly_cells(mapped):
    """/map/uncertainty: the anomaly grid's cells and mask, never below the levelling and noise
    terms (the interpolation term adds to them away from the lines), and the channel holds
    those cells (float32)."""
    import base64

    from pipeline.products.channels import map_channels

    _sim, _p, flight, seg, _r, mr = mapped
    s, g = mr.uncertainty, mr.grid
    assert s is not None and s.shape == g.shape and s.cell_m == g.cell_m
    assert (s.east0_m, s.north0_m) == (g.east0_m, g.north0_m)
    assert np.array_equal(np.isfinite(s.values), np.isfinite(g.values))
    v = s.values[np.isfinite(s.values)]
    model = mr.uncertainty_model
    # the demo survey has tie lines: they measure the whole error, floors included
    assert model.method == "tie lines held out" and model.floor_nT == 0.0
    assert v.min() > 0 and v.min() >= model.interpolation_nT(0.0) - 1e-9
    assert v.max() <= np.hypot(model.floor_nT, model.interpolation_nT(1e9)) + 1e-9
    summary = mr.summary()["uncertainty"]
    assert summary["channel"] == "/map/uncertainty" and summary["heldout_rms_nT"] > 0
    chans = {c.topic: c for c in map_channels(flight, seg, mr)}
    msg = chans["/map/uncertainty"].messages[0][1]
    cells = np.frombuffer(base64.b64decode(msg["data"]), "<f4").reshape(g.shape)
    np.testing.assert_array_equal(cells, s.values.astype(np.float32))
    anomaly = chans["/map/anomaly"].messages[0][1]
    assert msg["pose"] == anomaly["pose"] and msg["fields"][0]["name"] == "uncertainty_nT"
