"""The map's error model against the true field of dipole geology (which the model, an
error binned by the distance to the lines, does not assume): calibrated on average, growing
away from the lines, with tie lines held out and, without ties, with survey lines held out."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline.compensate import FitSettings
from pipeline.compensate.stage import run_compensation
from pipeline.io.reader import read_flight
from pipeline.maps.gridders import LineData, MinimumCurvatureGridder
from pipeline.maps.stage import MapSettings, anomaly_grid, lines_noise_nT, map_uncertainty
from pipeline.maps.uncertainty import (
    TIE_METHOD,
    along_line_interpolation_error,
    error_correlation_length,
    fit_uncertainty,
    uncertainty_grid,
)
from pipeline.physics.dipoles import DipoleSource, dipole_field_ned_nT, total_field_anomaly_nT
from pipeline.segment import segment_flight
from tests.recordings import INDEPENDENT

B_MAIN = np.array([18_000.0, 1_000.0, 48_000.0])  # NED, nT


def geology(rng: np.random.Generator, n: int = 40) -> list[DipoleSource]:
    """Dipoles 40-200 m under a 1 km x 1 km block, moments of a few 1e4 A m^2."""
    return [
        DipoleSource(
            float(rng.uniform(-600, 600)),
            float(rng.uniform(-600, 600)),
            float(-rng.uniform(40, 200)),
            tuple(rng.normal(0, 3e4, 3)),
        )
        for _ in range(n)
    ]


def anomaly(src, e, n):
    return total_field_anomaly_nT(dipole_field_ned_nT(src, e, n, np.zeros_like(e)), B_MAIN)


def survey(src, rng, spacing_m=50.0, noise_nT=0.05, level_nT=0.1):
    """North-south lines at ``spacing_m``, a sample every 5 m, two east-west ties; each line
    with a level error and white noise."""
    cols = {k: [] for k in ("e", "n", "v", "line", "kind")}
    along = np.arange(-500.0, 500.0 + 1e-9, 5.0)
    lines = [("survey", x) for x in np.arange(-500.0, 500.0 + 1e-9, spacing_m)]
    lines += [("tie", y) for y in (-300.0, 300.0)]
    for k, (kind, off) in enumerate(lines):
        e, n = (
            (np.full_like(along, off), along)
            if kind == "survey"
            else (along, np.full_like(along, off))
        )
        v = anomaly(src, e, n) + rng.normal(0, noise_nT, along.size) + rng.normal(0, level_nT)
        for key, val in zip(("e", "n", "v"), (e, n, v), strict=True):
            cols[key].append(val)
        cols["line"].append(np.full(along.size, f"L{k}"))
        cols["kind"].append(np.full(along.size, kind))
    c = {k: np.concatenate(v) for k, v in cols.items()}
    return LineData(c["e"], c["n"], np.zeros_like(c["e"]), c["v"], c["line"], c["kind"])


def test_along_line_spline_error_of_a_cubic_is_zero_and_of_a_sine_grows_midway():
    s = np.arange(0.0, 2000.0, 5.0)

    def line(v):
        return LineData(np.zeros_like(s), s, np.zeros_like(s), v, np.full(s.size, "a"), None)

    # a natural cubic spline reproduces a straight line exactly
    _, e2 = along_line_interpolation_error(line(3.0 + 0.01 * s), 100.0)
    assert np.nanmax(e2) < 1e-12
    # a 400 m sine between knots 100 m apart: small error, largest midway between knots
    d, e2 = along_line_interpolation_error(line(np.sin(2 * np.pi * s / 400.0)), 100.0)
    assert e2[-1] > 4 * e2[1] > 0
    assert np.sqrt(e2[-1]) < 0.05


def elongated(rng: np.random.Generator, strike_deg: float, n: int = 12) -> list[DipoleSource]:
    """Dipole chains 1 km long along ``strike_deg`` (from north), 30-80 m deep: dykes."""
    a = np.radians(strike_deg)
    along = np.array([np.sin(a), np.cos(a)])
    out = []
    for _ in range(n):
        c, depth, m = rng.uniform(-600, 600, 2), rng.uniform(30, 80), rng.normal(0, 3e3, 3)
        for s in np.arange(-500.0, 501.0, 20.0):
            p = c + s * along
            out.append(DipoleSource(float(p[0]), float(p[1]), -depth, tuple(m)))
    return out


def _check(seed, ties=True, src=None):
    """(mean squared error, mean sigma^2) inside the block, and the mid-gap / on-line means
    of error^2 and sigma^2 (nT^2); ``ties=False`` drops the tie lines before the fit (the
    survey-line method), ``src`` replaces the random geology."""
    rng = np.random.default_rng(seed)
    src = geology(rng) if src is None else src
    spacing, noise, level = 50.0, 0.05, 0.1
    data = survey(src, rng, spacing, noise, level)
    cell = spacing / 4.0
    fit_on = data if ties else data.subset(data.kind == "survey")
    model = fit_uncertainty(
        fit_on, lambda: MinimumCurvatureGridder(cell, np.inf), spacing, noise, level
    )
    assert (model.method == TIE_METHOD) == ties
    # the error's correlation length is measured (not the spacing's stand-in), and bounded
    # by what the held-out lines can show: the summed lags
    assert spacing <= model.correlation_length_m <= 16 * spacing
    grid = MinimumCurvatureGridder(cell, 2 * spacing).fit(data).grid_
    sigma = uncertainty_grid(model, grid, data)
    ge, gn = np.meshgrid(*grid.coordinates())
    truth = anomaly(src, ge.ravel(), gn.ravel()).reshape(ge.shape)
    err = grid.values - truth
    # inside the survey block (the grid's edge extrapolates); the map's mean level is
    # arbitrary (a constant no levelling can know)
    inside = np.isfinite(err) & (np.abs(ge) < 450) & (np.abs(gn) < 450)
    e2 = (err[inside] - np.median(err[inside])) ** 2
    s2 = sigma.values[inside] ** 2
    d = np.abs(((ge[inside] + 500.0) % spacing) - spacing / 2)  # 0 midway, spacing/2 on a line
    mid, on = d < spacing / 8, d > 3 * spacing / 8
    return e2.mean(), s2.mean(), (e2[mid].mean(), s2[mid].mean(), e2[on].mean(), s2[on].mean())


def ou_lines(rng, length_m, noise_nT, n_lines=40, step_m=5.0, line_m=2000.0):
    """Misfit series along held-out lines: an exponentially correlated error (1 nT, e-folding
    ``length_m``; two-sided integral ``2 length_m``) plus white noise."""
    s = np.arange(0.0, line_m, step_m)
    a = np.exp(-step_m / length_m) if length_m > 0 else 0.0
    out = []
    for _ in range(n_lines):
        x = np.empty(s.size)
        x[0] = rng.normal()
        for k in range(1, s.size):
            x[k] = a * x[k - 1] + np.sqrt(1 - a**2) * rng.normal()
        out.append((s, x + rng.normal(0, noise_nT, s.size)))
    return out


@pytest.mark.parametrize("length_m", [60.0, 150.0])
def test_error_correlation_length_of_an_exponentially_correlated_error(length_m):
    rng = np.random.default_rng(11)
    spacing = 50.0
    # measured across twice the spacing: the two-sided integral 2 L, halved
    clean = error_correlation_length(ou_lines(rng, length_m, 0.0), spacing, 2 * spacing)
    assert clean == pytest.approx(length_m, rel=0.2)
    # white noise three times the error's own spread does not shorten it (lag zero unused)
    noisy = error_correlation_length(ou_lines(rng, length_m, 3.0), spacing, 2 * spacing)
    assert noisy == pytest.approx(length_m, rel=0.3)
    # a position held over two samples is no step: the same lines, each sample twice
    lines = ou_lines(rng, length_m, 0.0)
    twice = [(np.repeat(d, 2), np.repeat(x, 2)) for d, x in lines]
    once = error_correlation_length(lines, spacing, 2 * spacing)
    assert error_correlation_length(twice, spacing, 2 * spacing) == pytest.approx(once, rel=0.05)
    # a position glitch of a million kilometres splits a line, no more: same length, no
    # bins spanning the jump
    jumped = [(np.where(np.arange(d.size) >= d.size // 2, d + 1e9, d), x) for d, x in lines]
    assert error_correlation_length(jumped, spacing, 2 * spacing) == pytest.approx(once, rel=0.1)


def test_error_correlation_length_of_white_noise_is_the_spacing():
    rng = np.random.default_rng(12)
    assert error_correlation_length(ou_lines(rng, 0.0, 1.0), 50.0, 100.0) == 50.0
    assert np.isnan(error_correlation_length([], 50.0, 100.0))


@pytest.mark.parametrize("ties", [True, False], ids=["tie-lines", "survey-lines"])
def test_uncertainty_is_calibrated_against_the_true_field(ties):
    """Over eight geologies the map's true error and its sigma agree in RMS to within the
    geology's own scatter; on each, within a factor of a few (a sigma per cell that depends
    only on the distance to the lines cannot know where the sources lie)."""
    rows = [_check(seed, ties) for seed in range(1, 9)]
    e2, s2 = np.array([r[0] for r in rows]), np.array([r[1] for r in rows])
    pooled = np.sqrt(e2.sum() / s2.sum())
    assert 0.6 < pooled < 1.5, pooled
    each = np.sqrt(e2 / s2)
    assert np.all((each > 0.15) & (each < 3.0)), each
    for _, _, (e_mid, s_mid, e_on, s_on) in rows:
        # the error grows away from the lines, and so does sigma
        assert e_mid > e_on and s_mid > s_on


def test_tie_lines_measure_the_error_where_the_geology_runs_along_the_lines():
    """Dykes striking 30 degrees off the lines: the field varies along the lines far faster
    than across them, so the along-line shape scaled by held-out survey lines (isotropy)
    puts sigma well below the true error; the held-out tie lines, which measure across the
    lines at the survey's own spacing, do not."""

    def ratio(ties):
        rows = [
            _check(seed, ties, elongated(np.random.default_rng(100 + seed), 30.0))
            for seed in range(4)
        ]
        return np.sqrt(sum(r[0] for r in rows) / sum(r[1] for r in rows))

    tie, survey_lines = ratio(True), ratio(False)
    assert 0.7 < tie < 1.4, tie
    assert survey_lines > 1.4, survey_lines


def test_lines_along_one_track_fall_back_to_the_survey_lines():
    """Survey lines flown end to end along one track span no area: no tie sample lies
    between them, so the survey-line method measures the error (no geometry error)."""
    s = np.arange(0.0, 1000.0, 5.0)
    tie_e = np.linspace(-100.0, 100.0, 41)
    e = np.concatenate([np.zeros(3 * s.size), tie_e])
    n = np.concatenate([s, s + 1000.0, s + 2000.0, np.full(tie_e.size, 500.0)])
    line = np.repeat(["A", "B", "C", "T"], [s.size, s.size, s.size, tie_e.size])
    kind = np.where(line == "T", "tie", "survey")
    data = LineData(e, n, np.zeros_like(e), np.sin(n / 100.0) + 0.01 * e, line, kind)
    model = fit_uncertainty(data, lambda: MinimumCurvatureGridder(12.5, np.inf), 50.0, 0.05, 0.05)
    assert model.method != TIE_METHOD


def test_too_few_lines_is_an_error():
    rng = np.random.default_rng(0)
    data = survey(geology(rng, 5), rng, spacing_m=500.0)
    keep = np.isin(data.line, ["L0", "L1"])
    with pytest.raises(ValueError, match="three survey lines"):
        fit_uncertainty(data.subset(keep), lambda: MinimumCurvatureGridder(50.0), 500.0, 0.1, 0.1)


@pytest.mark.parametrize("name", ["independent_none", "realism_none"])
def test_sigma_is_not_too_small_on_independent_recordings(name):
    """On flights made by a generator that is not aeromag's (``tests.recordings.INDEPENDENT``),
    the map stage's sigma against the map's error from the truth's dipoles (a plane and gain
    fitted, the datum no map can know): never too small (RMS of error / sigma at most 1.5)
    and not uselessly large (at least 0.2)."""
    truth_path = INDEPENDENT / f"{name}.truth.json"
    if not truth_path.exists():
        pytest.skip(f"{truth_path} not present")
    truth = json.loads(truth_path.read_text())
    flight = read_flight(INDEPENDENT / f"{name}.mcap")
    seg = segment_flight(flight)
    comp = run_compensation(flight, seg, FitSettings(model="tl18")).compensated_nT
    gm = anomaly_grid(flight, seg, comp, MapSettings())
    sigma, model, _ = map_uncertainty(
        gm.data, gm.grid, gm.spacing_m, lines_noise_nT(gm.lines), gm.leveling
    )
    assert model.method == TIE_METHOD
    # the truth's local frame (its own mapping, written in the truth file) at the cells
    lf = truth["local_frame"]
    gx, gy = np.meshgrid(*gm.grid.coordinates())
    lat, lon, _ = gm.frame.to_geodetic(gx, gy)
    north = np.radians(lat - lf["origin_lat"]) * lf["r_meridian_m"]
    east = (
        np.radians(lon - lf["origin_lon"])
        * lf["r_prime_vertical_m"]
        * np.cos(np.radians(lf["origin_lat"]))
    )
    up = float(np.nanmedian(flight.data["alt_m"].to_numpy(float)[seg.mask("survey")]))
    src = [
        DipoleSource(d["east_m"], d["north_m"], -d["depth_m"], tuple(d["moment_ned_Am2"]))
        for d in truth["anomaly"]["dipoles"]
    ]
    b = dipole_field_ned_nT(
        src, east.ravel(), north.ravel(), np.full(east.size, up - lf["ground_alt_m"])
    )
    main = np.broadcast_to(np.asarray(truth["main_field"]["ned_nT"], float), b.shape)
    true = total_field_anomaly_nT(b, main).reshape(gx.shape)
    s = truth["survey"]
    block = (
        np.isfinite(gm.grid.values)
        & (east > s["east_min"] + 10)
        & (east < s["east_max"] - 10)
        & (north > s["north_min"] + 25)
        & (north < s["north_max"] - 25)
    )
    x = np.column_stack([np.ones(block.sum()), gx[block], gy[block], true[block]])
    coef, *_ = np.linalg.lstsq(x, gm.grid.values[block], rcond=None)
    err = gm.grid.values[block] - x @ coef
    z = float(np.sqrt(np.mean((err / sigma.values[block]) ** 2)))
    assert 0.2 <= z <= 1.5, z


def test_a_line_missing_over_a_stretch_raises_sigma_there():
    """A survey line not flown over 400 m (a hole, or a gap in the recording): the cells
    over it lie a spacing from the nearest data, where held-out lines measure the error
    (a held-out line is a line missing). Over six geologies the map's error there stays
    within its sigma's reach (median ratio of RMS error to RMS sigma at most 1.5; with
    sigma held at its half-spacing value it was 4.1)."""
    ratios = []
    for seed in range(6):
        rng = np.random.default_rng(100 + seed)
        src = geology(rng)
        data = survey(src, rng, 50.0, 0.05, 0.1)
        hole = (data.kind == "survey") & (np.abs(data.east_m) < 1) & (np.abs(data.north_m) < 200)
        data = data.subset(~hole)
        model = fit_uncertainty(
            data, lambda: MinimumCurvatureGridder(12.5, np.inf), 50.0, 0.05, 0.1
        )
        grid = MinimumCurvatureGridder(12.5, 50.0).fit(data).grid_
        sigma = uncertainty_grid(model, grid, data)
        ge, gn = np.meshgrid(*grid.coordinates())
        err = grid.values - anomaly(src, ge.ravel(), gn.ravel()).reshape(ge.shape)
        inside = np.isfinite(err) & (np.abs(ge) < 450) & (np.abs(gn) < 450)
        over = inside & (np.abs(ge) < 13) & (np.abs(gn) < 150)
        e2 = np.mean((err[over] - np.median(err[inside])) ** 2)
        ratios.append(np.sqrt(e2 / np.mean(sigma.values[over] ** 2)))
    assert np.median(ratios) <= 1.5, ratios
