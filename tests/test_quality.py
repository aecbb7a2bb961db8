"""Quality statistics: overlap geometry, heading error per model, noise, QC, outputs."""

from __future__ import annotations

import json

import numpy as np
import pytest

import tests.cli
from pipeline.compensate import FitSettings
from pipeline.compensate.stage import run_compensation
from pipeline.io.reader import read_flight
from pipeline.quality import (
    QualitySettings,
    Track,
    group_stats,
    overlap_pairs,
    qc,
    run_quality,
    track_intersections,
)
from pipeline.segment import segment_flight
from pipeline.simulate import write_simulation
from tests.conftest import run_sim, sha256
from tests.recordings import validate_every_message


def _track(line_id, kind, e, n, first_epoch):
    idx = first_epoch + np.arange(e.size)
    h = float(np.degrees(np.arctan2(e[-1] - e[0], n[-1] - n[0])) % 360)
    return Track(line_id, kind, idx, np.asarray(e, float), np.asarray(n, float), h)


def _field_on(tracks, f, size):
    out = np.full(size, np.nan)
    for t in tracks:
        out[t.index] = f(t.east_m, t.north_m)
    return out


# --------------------------------------------------------------------------------------------
# geometry against analytic solutions
def test_intersections_are_found_exactly_on_crossing_tracks():
    """Diagonal y = 0.5 x + 3 crossing x = 30.3 and x = 71.9: crossings at analytic points,
    a linear field interpolated along track to them has the analytic value on both sides."""
    rng = np.random.default_rng(5)
    xv = np.sort(rng.uniform(0, 100, 160))  # irregular along-track sampling
    val = _track("V0010", "validation", xv, 0.5 * xv + 3.0, 0)
    yk = np.sort(rng.uniform(-10, 110, 140))
    m1 = _track("L0010", "survey", np.full(yk.size, 30.3), yk, 1000)
    m2 = _track("L0020", "survey", np.full(yk.size, 71.9), yk[::-1], 2000)
    far = _track("L0030", "survey", np.full(yk.size, 250.0), yk, 3000)  # never crossed
    tracks = [val, m1, m2, far]
    ov = track_intersections([val], [m1, m2, far])
    assert ov.count == 2
    order = np.argsort(ov.east_m)
    np.testing.assert_allclose(ov.east_m[order], [30.3, 71.9], atol=1e-9)
    np.testing.assert_allclose(ov.north_m[order], [0.5 * 30.3 + 3, 0.5 * 71.9 + 3], atol=1e-9)
    assert list(ov.map_line[order]) == ["L0010", "L0020"]

    def plane(e, n):
        return 2.0 * e - 3.0 * n + 7.0

    field = _field_on(tracks, plane, 4000)
    va, vb = ov.values(field)
    np.testing.assert_allclose(va, plane(ov.east_m, ov.north_m), atol=1e-9)
    np.testing.assert_allclose(vb, plane(ov.east_m, ov.north_m), atol=1e-9)
    # a DC on one survey line shows as that line's offset only
    shifted = field.copy()
    shifted[m1.index] += 1.5
    d = ov.differences(shifted)
    np.testing.assert_allclose(d[order], [-1.5, 0.0], atol=1e-9)


def _noisy(line_id, kind, start, end, first_epoch, rng, noise_m=0.5, step_m=0.7):
    """A straight track from ``start`` to ``end`` (east, north m) sampled every ``step_m``
    (7 m/s at 10 Hz) with white position noise of ``noise_m`` on both coordinates."""
    (e0, n0), (e1, n1) = start, end
    f = np.linspace(0.0, 1.0, int(np.hypot(e1 - e0, n1 - n0) / step_m) + 1)
    e = e0 + f * (e1 - e0) + rng.normal(0, noise_m, f.size)
    n = n0 + f * (n1 - n0) + rng.normal(0, noise_m, f.size)
    return _track(line_id, kind, e, n, first_epoch)


def _grid(
    rng,
    survey_east=(50, 150, 250, 350, 450),
    tie_north=(80, 180, 280, 380),
    north=(-20.0, 520.0),
    east=(-20.0, 520.0),
):
    """Noisy serpentine north-south survey lines and east-west tie lines across them."""
    tracks = []
    for k, x in enumerate(survey_east):
        a, b = (x, north[0]), (x, north[1])
        tracks.append(
            _noisy(f"L{k:04d}", "survey", *((a, b) if k % 2 == 0 else (b, a)), 100_000 * k, rng)
        )
    for k, y in enumerate(tie_north):
        a, b = (east[0], y), (east[1], y)
        tracks.append(
            _noisy(
                f"T{k:04d}",
                "tie",
                *((a, b) if k % 2 == 0 else (b, a)),
                10_000_000 + 100_000 * k,
                rng,
            )
        )
    return tracks


@pytest.mark.parametrize("angle_deg", [0.0, 3.0, 10.0])
def test_track_flown_along_another_is_no_intersection(angle_deg):
    """A transit flown along a tie line (0-10 deg, 0.5 m noise on both) wiggles across it
    many times; tracks meeting below the minimum crossing angle do not intersect."""
    rng = np.random.default_rng(int(10 * angle_deg) + 1)
    tie = _noisy("T0010", "tie", (0.0, 0.0), (0.0, 1000.0), 0, rng)
    a = np.radians(angle_deg)
    along = _noisy(
        "V0010",
        "validation",
        (-500 * np.sin(a), 500 - 500 * np.cos(a)),
        (500 * np.sin(a), 500 + 500 * np.cos(a)),
        100_000,
        rng,
    )
    raw = tie.geometry().intersection(along.geometry())
    assert len(getattr(raw, "geoms", [raw])) >= 3  # what counting raw hits would give
    assert track_intersections([along], [tie]).count == 0


def test_x_lines_over_a_noisy_grid_intersect_as_the_geometry_says():
    """An X of two validation lines over 5 survey x 4 tie lines, all with 0.5 m noise: each
    diagonal crosses every line once (45 deg), so 2 x (5 + 4) intersections, each one point
    at the analytic crossing."""
    rng = np.random.default_rng(21)
    mapped = _grid(rng)
    x_lines = [
        _noisy("V0010", "validation", (0.0, 0.0), (500.0, 500.0), 50_000_000, rng),
        _noisy("V0020", "validation", (0.0, 500.0), (500.0, 0.0), 60_000_000, rng),
    ]
    ov = track_intersections(x_lines, mapped)
    assert ov.count == 2 * (5 + 4)
    pairs = list(zip(ov.validation_line, ov.map_line, strict=True))
    assert len(set(pairs)) == ov.count  # one per pair of lines
    for v, m, e, n in zip(ov.validation_line, ov.map_line, ov.east_m, ov.north_m, strict=True):
        line = next(t for t in mapped if t.line_id == m)
        along_x = float(np.mean(line.east_m)) if m.startswith("L") else float(np.mean(line.north_m))
        # the diagonal's analytic crossing with that line (45 deg: noise moves it ~1 m)
        if m.startswith("L"):
            want = (along_x, along_x if v == "V0010" else 500.0 - along_x)
        else:
            want = (along_x if v == "V0010" else 500.0 - along_x, along_x)
        assert np.hypot(e - want[0], n - want[1]) < 3.0, (v, m, e, n, want)


def test_x_lines_of_a_narrow_block_cross_only_the_tie_lines_at_30_degrees():
    """The independent generator's block: 5 survey lines 1 km long at 50 m spacing, 3 tie
    lines, an X corner to corner. The diagonals meet the survey lines at 11.3 deg, so at the
    default 30 deg only the 2 x 3 tie-line crossings count; at 5 deg the 2 x 3 interior
    survey-line crossings count too (the corners, where both tracks end, never do)."""
    rng = np.random.default_rng(4)
    mapped = _grid(
        rng,
        survey_east=(0, 50, 100, 150, 200),
        tie_north=(100, 500, 900),
        north=(0.0, 1000.0),
        east=(-50.0, 250.0),
    )
    x_lines = [
        _noisy("V0010", "validation", (0.0, 0.0), (200.0, 1000.0), 50_000_000, rng),
        _noisy("V0020", "validation", (0.0, 1000.0), (200.0, 0.0), 60_000_000, rng),
    ]
    ov = track_intersections(x_lines, mapped)
    assert ov.count == 6 and set(ov.map_line) == {"T0000", "T0001", "T0002"}
    shallow = track_intersections(x_lines, mapped, min_angle_deg=5.0)
    assert shallow.count == 12
    assert sorted(set(shallow.map_line) - set(ov.map_line)) == ["L0001", "L0002", "L0003"]


def test_pairs_are_every_sample_pair_within_the_distance():
    e = np.arange(0.0, 50.0, 0.7)
    val = _track("V0010", "validation", e, e, 0)
    mp = _track("L0010", "survey", np.full(80, 20.2), np.arange(80) * 0.7, 500)
    ov = overlap_pairs([val], [mp], 0.5)
    # brute force
    d = np.hypot(val.east_m[:, None] - mp.east_m[None], val.north_m[:, None] - mp.north_m[None])
    assert ov.count == int((d <= 0.5).sum()) > 0
    assert np.all(ov.distance_m <= 0.5)
    assert overlap_pairs([val], [mp], 0.01).count == int((d <= 0.01).sum())


def test_heading_dc_offsets_have_confidence_intervals():
    """A +0.4 nT offset on northbound lines appears in its heading group, not in the other."""
    rng = np.random.default_rng(2)
    xv = np.linspace(0, 400, 600)
    vals = [_track("V0010", "validation", xv, xv, 0)]  # 45 deg to the lines
    mapped = [
        _track(
            f"L{k:04d}",
            "survey",
            np.full(300, 20.0 + 40 * k),
            np.linspace(0, 800, 300)[:: 1 if k % 2 == 0 else -1],
            1000 + 300 * k,
        )
        for k in range(10)
    ]
    field = rng.normal(0, 0.05, 5000)
    for t in mapped:
        if t.heading_deg < 90 or t.heading_deg > 270:
            field[t.index] += 0.4
    ov = track_intersections(vals, mapped)
    groups = {g["map_heading_deg"]: g for g in group_stats(ov.differences(field), ov)}
    assert set(groups) == {0.0, 180.0}
    north, south = groups[0.0], groups[180.0]
    assert abs(north["mean_nT"] + 0.4) < north["ci_nT"] + 0.02
    assert abs(south["mean_nT"]) < south["ci_nT"] + 0.02
    assert north["ci_nT"] < 0.2


def test_4th_difference_noise_within_10_percent_of_injected_white_noise():
    rng = np.random.default_rng(9)
    tracks, field = [], np.zeros(12 * 3000)
    for k in range(12):
        n = np.arange(3000) * 0.7  # 7 m/s at 10 Hz
        t = _track(f"L{k:04d}", "survey", np.full(n.size, 50.0 * k), n, 3000 * k)
        tracks.append(t)
        geology = 80 * np.exp(-(((n - 900) / 150) ** 2)) + 0.3 * n + 25 * np.sin(n / 120)
        field[t.index] = geology + rng.normal(0, 0.05, n.size)
    res = qc.line_noise(tracks, field, threshold_nT=0.1)
    assert res["median_nT"] == pytest.approx(0.05, rel=0.10)
    for v in res["per_line_nT"].values():
        assert v == pytest.approx(0.05, rel=0.10)
    assert res["lines_over"] == []
    field[tracks[3].index] += rng.normal(0, 0.2, 3000)
    assert qc.line_noise(tracks, field, threshold_nT=0.1)["lines_over"] == ["L0003"]


def test_qc_checks_flag_what_is_out_of_tolerance():
    n = np.arange(0, 1000, 0.7)
    tracks = [
        _track(f"L{k:04d}", "survey", np.full(n.size, 50.0 * k), n, k * n.size) for k in range(5)
    ]
    # line 2 drifts 20 m towards line 3 over its second half
    tracks[2] = _track("L0002", "survey", 100.0 + np.clip(n - 500, 0, None) * 0.04, n, 2 * n.size)
    sp = qc.line_spacing(tracks, 0.0, 0.25)
    assert sp["nominal_m"] == pytest.approx(50.0, abs=0.5)
    assert sp["pairs_over"] == ["L0001-L0002", "L0002-L0003"]
    up = np.zeros(5 * n.size)
    up[tracks[4].index] = np.where(n > 600, 14.0, 0.0)
    h = qc.flight_height(tracks, up, 10.0)
    assert h["lines_over"] == ["L0004"]
    t = np.arange(5 * n.size) * 0.1
    sp = qc.speed_excursions(tracks, t, 0.2)
    assert sp["median_m_s"] == pytest.approx(7.0, rel=1e-6) and sp["spans"] == []
    ts = np.arange(0, 7200.0, 1.0)
    base = 48000 + 3 * np.sin(2 * np.pi * ts / 5400)
    assert qc.diurnal_check(ts, base, 300.0, 5.0)["spans_over"] == []
    storm = base + np.where(
        (ts > 3000) & (ts < 3200), 12.0 * np.sin(np.pi * (ts - 3000) / 200), 0.0
    )
    assert qc.diurnal_check(ts, storm, 300.0, 5.0)["spans_over"]


# --------------------------------------------------------------------------------------------
# paper 002, section 3.2: heading error of T-L vs AGG-TL on the demo survey
def _demo_quality(tmp_path_factory, gradient: bool):
    folder = tmp_path_factory.mktemp("q002")
    sim = run_sim("demo", 7, [f"effects.geomagnetic_gradient.enabled={str(gradient).lower()}"])
    flight = read_flight(write_simulation(sim, folder / "f.mcap"))
    seg = segment_flight(flight)
    fields = {"raw": flight.data["scalar_nT"].to_numpy()}
    for m in ("tl18", "agg-tl"):
        fields[m] = run_compensation(flight, seg, FitSettings(model=m)).compensated_nT
    # the demo's X (2000 m x 700 m block, corner to corner) meets the survey lines at 19.3 deg:
    # below the default minimum crossing angle, which would leave only its 2 x 3 tie crossings
    q = run_quality(
        flight, seg, fields, tl_alias="tl18", settings=QualitySettings(min_crossing_angle_deg=15.0)
    )
    # the simulated sensor noise (white + drift) as it enters B_val - B_map at the same points
    at = np.searchsorted(sim.series["time_ns"], flight.time_ns)
    noise_rms = float(
        np.sqrt(np.nanmean(q.intersections.differences(sim.series["noise_nT"][at]) ** 2))
    )
    # the noise-free field at the sensor (no carrier) at the flight's epochs
    return q.summary(), noise_rms, sim, q, sim.series["earth_total_nT"][at]


@pytest.fixture(scope="module")
def demo_with_gradient(tmp_path_factory):
    return _demo_quality(tmp_path_factory, True)


@pytest.fixture(scope="module")
def demo_without_gradient(tmp_path_factory):
    return _demo_quality(tmp_path_factory, False)


def test_agg_tl_removes_the_heading_error_tl_leaves_over_a_gradient(demo_with_gradient):
    s, noise_rms, sim, _, _ = demo_with_gradient
    assert sim.truth["noise"]["scalar_nT"] == 0.05
    he = s["intersection_rms_nT"]  # noise_rms is the noise at the intersections
    assert s["intersections"] >= 30 and s["overlap_pairs"] >= 30
    assert he["tl"] >= 2.0 * he["agg_tl"], he
    assert he["agg_tl"] <= 1.5 * noise_rms, (he, noise_rms)
    assert he["raw"] > 10 * he["tl"]
    # the same ordering holds on the other two statistics
    assert s["overlap_pair_rms_nT"]["tl"] > s["overlap_pair_rms_nT"]["agg_tl"]
    assert s["interpolated_rms_nT"]["tl"] > s["interpolated_rms_nT"]["agg_tl"]
    # the white-noise floor estimated from the data is the simulated one
    assert s["noise_4th_diff_nT"] == pytest.approx(0.05, rel=0.10)
    assert s["crossover_rms_nT"]["after"] < s["crossover_rms_nT"]["before"]


def test_without_gradient_tl_and_agg_tl_agree(demo_without_gradient):
    s, noise_rms, _, _, _ = demo_without_gradient
    he = s["intersection_rms_nT"]
    assert he["agg_tl"] == pytest.approx(he["tl"], rel=0.10), he
    assert he["tl"] <= 1.5 * noise_rms


def test_headline_heading_error_is_the_papers_pair_statistic_and_says_so(demo_with_gradient):
    """Paper 002 §3.2's overlap statistic is pairs closer than 0.5 m: the headline uses it
    when there are pairs, names it, and keeps the intersections next to it."""
    s, _, _, _, _ = demo_with_gradient
    assert s["overlap_m"] == pytest.approx(0.5) and s["overlap_pairs"] >= 10
    assert s["heading_error_method"] == "pairs"
    assert "paper 002" in s["heading_error_methods"]["pairs"]
    for st in s["states"]:
        assert s["heading_error_rms_nT"][st] == pytest.approx(
            s["overlap_pair_rms_nT"][st], rel=1e-12
        )
        inter = s["heading_error"]["intersections"]["by_state"][st]["rms_nT"]
        assert s["intersection_rms_nT"][st] == pytest.approx(inter, rel=1e-12)
    # over the 0.45 nT/m gradient the pairs carry gradient x distance: above the intersections
    assert s["heading_error_rms_nT"]["agg_tl"] > s["intersection_rms_nT"]["agg_tl"]


def test_headline_falls_back_to_intersections_without_enough_pairs(demo_with_gradient):
    import dataclasses

    assert QualitySettings().min_overlap_pairs == 10  # from default_config.toml
    _, _, _, q, _ = demo_with_gradient
    few = dataclasses.replace(
        q, settings=dataclasses.replace(q.settings, min_overlap_pairs=q.pairs.count + 1)
    )
    s = few.summary()
    assert s["heading_error_method"] == "intersections"
    assert s["heading_error_rms_nT"] == s["intersection_rms_nT"]
    assert s["overlap_pair_rms_nT"] == q.summary()["overlap_pair_rms_nT"]


# --------------------------------------------------------------------------------------------
# the command
def test_quality_command_writes_summary_plots_and_valid_channels(tmp_path):
    sim = run_sim("uav-small", 3)
    src = write_simulation(sim, tmp_path / "small.mcap")
    before = sha256(src)
    out, js = tmp_path / "q.mcap", tmp_path / "q.json"
    res = tests.cli.run(
        "quality",
        str(src),
        "--json",
        str(js),
        "--out",
        str(out),
        "--overlap-m",
        "0.7",
    )
    assert res.returncode == 0, res.stderr[-2000:]
    assert sha256(src) == before
    s = json.loads(js.read_text())["quality"]
    for key in ("heading_error_rms_nT", "interpolated_rms_nT", "overlap_pair_rms_nT"):
        assert {"raw", "tl", "tl16", "tl18", "agg_tl"} <= set(s[key]), key
    assert s["overlap_m"] == 0.7 and s["overlap_pairs"] > 0
    # the X (600 m x 300 m block, corner to corner) meets the survey lines at 26.6 deg, below
    # the default 30, and the two tie lines only at its corners: no intersection
    assert s["min_crossing_angle_deg"] == 30.0 and s["intersections"] == 0
    assert s["overlap_pair_rms_nT"]["raw"] > s["overlap_pair_rms_nT"]["agg_tl"]
    # no intersection, pairs: the headline is the paper's pair statistic
    assert s["heading_error_method"] == "pairs"
    assert s["heading_error_rms_nT"] == s["overlap_pair_rms_nT"]
    assert all(v is None for v in s["intersection_rms_nT"].values())
    assert s["crossover_rms_nT"]["before"] is not None and s["noise_4th_diff_nT"] > 0
    assert len(s["fom_boxes"]) == 12
    assert "heading error" in res.stdout and "agg_tl" in res.stdout
    for name in ("heading_error", "validation_profiles", "crossovers"):
        assert (tmp_path / f"q.{name}.png").stat().st_size > 10000
    assert (
        validate_every_message(
            out,
            {"/quality/heading_error", "/quality/crossovers", "/aeromag/log", "/flight/segment"},
        )
        > 0
    )
    from tests.recordings import records

    topics = {m[0] for m in records(out)[0]}
    assert {"/quality/heading_error", "/quality/crossovers", "/aeromag/log"} <= topics
    # a processed recording is assessed with its own compensated channels
    res = tests.cli.run(
        "quality",
        str(out),
        "--json",
        str(tmp_path / "again.json"),
    )
    assert res.returncode == 0, res.stderr[-2000:]
    again = json.loads((tmp_path / "again.json").read_text())["quality"]
    assert again["states"] == ["raw", "tl16", "tl18", "agg_tl"]
    for k, v in s["interpolated_rms_nT"].items():  # (pairs: the first run used --overlap-m)
        assert again["interpolated_rms_nT"][k] == pytest.approx(v, rel=1e-9)


def _line(start: int, east_m: np.ndarray, north_m: np.ndarray, heading_deg: float) -> Track:
    return Track(f"L{start}", "x", start + np.arange(east_m.size), east_m, north_m, heading_deg)


def test_gradient_removed_pairs_leave_the_heading_error_alone():
    """A linear field and one level per line: a pair as measured carries gradient x offset,
    the gradient-removed pair exactly the lines' level difference, on crossing tracks (both
    components) and on parallel ones (the along-track part; the cross-track part stays)."""
    from pipeline.quality.overlap import gradient_removed_differences

    s = np.arange(-60.0, 60.0, 0.83)
    val = _line(0, s, np.full(s.size, 0.31), 90.0)
    cross = _line(s.size, np.full(s.size, 0.17), s + 0.29, 0.0)
    par = _line(2 * s.size, s + 0.4, np.full(s.size, 0.02), 90.0)
    g_e, g_n = 0.43, -0.27  # nT/m
    east = np.concatenate([val.east_m, cross.east_m, par.east_m])
    north = np.concatenate([val.north_m, cross.north_m, par.north_m])
    level = np.repeat([0.12, -0.05, 0.30], s.size)
    field = g_e * east + g_n * north + level
    for mapped, want in ((cross, 0.17), (par, -0.18 + g_n * (0.31 - 0.02))):
        pairs = overlap_pairs([val], [mapped], 0.5)
        assert pairs.count >= 1
        measured = pairs.differences(field)
        assert np.max(np.abs(measured - want)) > 0.1  # gradient x offset, as measured
        # a window shorter than the sample spacing still holds three samples
        for half_span_m in (10.0, 0.3):
            removed = gradient_removed_differences(pairs, [val, mapped], field, half_span_m)
            np.testing.assert_allclose(removed, want, atol=1e-9)


@pytest.mark.parametrize("which", ["demo_with_gradient", "demo_without_gradient"])
def test_gradient_removed_pairs_of_the_true_field_are_near_zero(which, request):
    """The simulator's noise-free field (dipole geology, and a 0.45 nT/m gradient on one of
    the flights: neither is linear over the +-10 m slope windows the estimator assumes):
    its pairs as measured differ by geology and gradient x offset, the gradient-removed ones
    by about what its own intersections do (interpolation between samples)."""
    from pipeline.quality.overlap import difference_stats, gradient_removed_differences

    _, _, _, q, truth = request.getfixturevalue(which)
    s = q.settings
    measured = difference_stats(q.pairs.differences(truth))["rms_nT"]
    removed = difference_stats(
        gradient_removed_differences(
            q.pairs, q.tracks, truth, s.pair_slope_half_span_m, s.min_crossing_angle_deg
        )
    )
    inter = difference_stats(q.intersections.differences(truth))["rms_nT"]
    assert removed["count"] == q.pairs.count  # every pair has slopes on both tracks
    assert removed["rms_nT"] < 0.5 * measured, (removed, measured)
    assert removed["rms_nT"] < 1.5 * inter + 0.01, (removed, inter)
