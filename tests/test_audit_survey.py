"""Survey-side evidence of the audit (issue 16, item 2), on synthetic crossovers whose
truth is known: heading levels, a step, a drift, a lag, a current coupling."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.audit.survey import (
    CrossoverSet,
    _step_columns,
    survey_coupling,
    survey_coupling_gain,
    survey_events,
    survey_heading,
    survey_lag,
)


def crossings(seed: int, n: int = 40):
    """``n`` crossings of N/S survey lines (headings 0, 2) with E/W ties (1, 3), read at
    random times over an hour; heading levels of a few tenths of a nT; 0.03 nT noise."""
    rng = np.random.default_rng(seed)
    ha = rng.choice([0, 2], n)
    hb = rng.choice([1, 3], n)
    ta = np.sort(rng.uniform(0, 3600, n))
    tb = rng.uniform(0, 3600, n)
    level = np.array([0.0, 0.3, -0.2, 0.1])
    d = level[ha] - level[hb] + rng.normal(0, 0.03, n)
    return rng, ha, hb, ta, tb, d


def test_a_current_coupling_is_measured_from_the_crossovers():
    rng, ha, hb, ta, tb, d = crossings(1)
    ia, ib = rng.choice([0.0, 2.0], ta.size), rng.choice([0.0, 2.0], ta.size)
    k = 0.6  # nT per A
    c = survey_coupling(CrossoverSet(d + k * (ia - ib), ta, tb, ha, hb), ia, ib)
    assert c is not None and c.ci95[0] <= k <= c.ci95[1] and c.p_value < 1e-6
    # no coupling: the interval holds 0
    c0 = survey_coupling(CrossoverSet(d, ta, tb, ha, hb), ia, ib)
    assert c0.ci95[0] <= 0.0 <= c0.ci95[1]


def test_a_channel_that_follows_the_clock_does_not_take_a_step_for_its_coupling():
    """A step of the carrier's permanent field (0.8 nT from 1800 s on) changes every
    crossover whose readings straddle it; a battery's voltage, falling steadily, differs
    most between such readings. Fitted beside the time difference it is rarely significant
    (over 30 seeds); a load that switches at random is still measured beside it."""
    hits = 0
    for seed in range(30):
        rng, ha, hb, ta, tb, d = crossings(200 + seed)
        step = 0.8 * ((ta >= 1800.0).astype(float) - (tb >= 1800.0))
        va, vb = (25.2 - 2e-4 * t + rng.normal(0.0, 0.01, t.size) for t in (ta, tb))
        x = CrossoverSet(d + step, ta, tb, ha, hb)
        c = survey_coupling(x, va, vb)
        hits += c is not None and c.p_value < 0.01
    assert hits <= 3  # binomial: 3 of 30 is above the 99 % point at a 1 % rate
    ia, ib = rng.choice([0.0, 2.0], ta.size), rng.choice([0.0, 2.0], ta.size)
    c = survey_coupling(CrossoverSet(d + step + 0.6 * (ia - ib), ta, tb, ha, hb), ia, ib)
    # the step not modelled is the crossovers' noise here: within three standard errors
    assert abs(c.nT_per_unit - 0.6) < 1.5 * (c.ci95[1] - c.ci95[0]) / 2 and c.p_value < 1e-6


def test_a_load_switched_on_with_a_located_step_does_not_take_it_for_its_coupling():
    """A step of the carrier's permanent field at 1800 s, heading-dependent (a body-frame
    change seen through each heading's direction), and a payload switched on at the same
    moment: the payload's level differs exactly across the step. Without the step the
    crossovers read it as a coupling on every seed; with the fluxgate's step time fitted
    beside it (``step_s``) rarely (30 seeds), and a true coupling of a load that switches at
    random is still measured."""
    bare = beside = 0
    for seed in range(30):
        rng, ha, hb, ta, tb, d = crossings(300 + seed)
        # the step's size at each heading (nT): the vertical part of the body-frame change
        # the same at every heading, the horizontal part turning with it
        dp = 1.0 + 0.4 * np.cos(np.radians([0.0, 90.0, 180.0, 270.0]) + rng.uniform(0, 6.3))
        step = dp[ha] * (ta >= 1800.0) - dp[hb] * (tb >= 1800.0)
        pa, pb = 2.0 * (ta >= 1800.0), 2.0 * (tb >= 1800.0)
        x = CrossoverSet(d + step, ta, tb, ha, hb)
        bare += survey_coupling(x, pa, pb).p_value < 0.01
        c = survey_coupling(x, pa, pb, step_s=1800.0)
        beside += c is not None and c.p_value < 0.01
        gain = survey_coupling_gain(x, pa, pb, step_s=1800.0)
        assert gain is None or gain.reduction < 0.05
    assert bare >= 25 and beside <= 3
    ia, ib = rng.choice([0.0, 2.0], ta.size), rng.choice([0.0, 2.0], ta.size)
    x = CrossoverSet(d + step + 0.6 * (ia - ib), ta, tb, ha, hb)
    c = survey_coupling(x, ia, ib, step_s=1800.0)
    assert c.ci95[0] <= 0.6 <= c.ci95[1] and c.p_value < 1e-6


def test_a_coupling_predicts_crossovers_it_was_not_fitted_on():
    """Leave-one-out: with a coupling the held-out crossover error falls to the noise; without
    one, adding the channel never helps beyond chance (over 30 seeds)."""
    rng, ha, hb, ta, tb, d = crossings(2)
    ia, ib = rng.choice([0.0, 2.0], ta.size), rng.choice([0.0, 2.0], ta.size)
    g = survey_coupling_gain(CrossoverSet(d + 0.6 * (ia - ib), ta, tb, ha, hb), ia, ib)
    assert g.reduction > 0.9 and g.p_value < 1e-3 and g.blocks == ta.size
    # the before error is the coupling's own size (levels cannot absorb it), the after the noise
    assert 0.5 < g.rms_before_nT < 1.5 and g.rms_after_nT < 0.05
    gains = []
    for seed in range(30):
        rng, ha, hb, ta, tb, d = crossings(100 + seed)
        ia, ib = rng.choice([0.0, 2.0], ta.size), rng.choice([0.0, 2.0], ta.size)
        gains.append(survey_coupling_gain(CrossoverSet(d, ta, tb, ha, hb), ia, ib))
    # an extra regressor on noise makes leave-one-out prediction worse, not better
    assert np.median([x.reduction for x in gains]) < 0.0
    assert sum(x.reduction >= 0.05 for x in gains) <= 3


def test_a_lag_is_measured_from_the_crossovers():
    rng, ha, hb, ta, tb, d = crossings(2)
    ra, rb = rng.normal(0, 3.0, ta.size), rng.normal(0, 3.0, ta.size)  # nT/s along track
    tau = 0.15
    lag = survey_lag(CrossoverSet(d - tau * (ra - rb), ta, tb, ha, hb), ra, rb)
    assert lag is not None and lag.ci95_s[0] <= tau <= lag.ci95_s[1]


@pytest.mark.parametrize("t_step", [1200.0, 2500.0])
def test_a_step_is_located_and_a_clean_survey_has_none(t_step):
    rng, ha, hb, ta, tb, d = crossings(3)
    assert survey_events(CrossoverSet(d, ta, tb, ha, hb), 0.01, 0.3) == []
    size = np.array([1.5, -1.0, 0.8, 1.2])  # the step as each heading sees it, nT
    stepped = d + size[ha] * (ta > t_step) - size[hb] * (tb > t_step)
    ev = survey_events(CrossoverSet(stepped, ta, tb, ha, hb), 0.01, 0.3)
    assert [e.kind for e in ev] == ["step"]
    assert ev[0].start_s <= t_step <= ev[0].end_s


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_step_before_the_ties_is_sized_on_the_headings_read_both_sides(seed):
    """Tie lines flown after the step (as crews fly them, after the lines): their headings'
    steps are their levels, only the survey lines' (N, S) are measured, and those are the
    truth; the event spans the step and its likeliest gap lies inside the span."""
    rng, ha, hb, ta, _, d = crossings(seed)
    tb = rng.uniform(3000, 3600, ha.size)  # every tie after the lines
    t_step = 1500.0
    size = np.array([1.5, -1.0, 0.8, 1.2])  # the step as each heading sees it, nT
    stepped = d + size[ha] * (ta > t_step) - size[hb] * (tb > t_step)
    ev = survey_events(CrossoverSet(stepped, ta, tb, ha, hb), 0.01, 0.3)
    assert [e.kind for e in ev] == ["step"]
    by_heading = ev[0].detail["step_by_heading_nT"]
    assert set(by_heading) == {"N", "S"}
    assert by_heading["N"] == pytest.approx(size[0], abs=0.1)
    assert by_heading["S"] == pytest.approx(size[2], abs=0.1)
    assert ev[0].size_nT == pytest.approx(size[0], abs=0.1)
    assert ev[0].start_s <= t_step <= ev[0].end_s
    assert ev[0].start_s <= ev[0].detail["likeliest_start_s"]
    assert ev[0].detail["likeliest_end_s"] <= ev[0].end_s


def test_crossover_set_subset():
    rng, ha, hb, ta, tb, d = crossings(4, 10)
    x = CrossoverSet(d, ta, tb, ha, hb, np.arange(10.0), np.arange(10.0))
    keep = np.arange(10) % 2 == 0
    sub = x.subset(keep)
    assert sub.size == 5 and np.array_equal(sub.east_m, np.arange(0.0, 10.0, 2.0))
    assert np.array_equal(sub.time_b_s, tb[keep]) and np.array_equal(sub.heading_a, ha[keep])


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_heading_levels_and_their_change_across_the_survey(seed):
    """Heading levels (0, 0.3, -0.2, 0.1 nT) are recovered from the crossings' differences
    alone; levels that grow across a 2 km survey are told apart from constant ones; equal
    levels give no evidence."""
    rng, ha, hb, ta, tb, d = crossings(seed, 60)
    east_km = rng.uniform(0.0, 2.0, ha.size)
    north_km = rng.uniform(0.0, 2.0, ha.size)
    h = survey_heading(CrossoverSet(d, ta, tb, ha, hb), east_km, north_km)
    truth = np.array([0.0, 0.3, -0.2, 0.1]) - 0.05
    got = np.array([h.levels_nT[k] for k in ("N", "E", "S", "W")])
    assert np.max(np.abs(got - truth)) < 0.03
    assert h.spread_nT == pytest.approx(0.5, abs=0.04)
    assert h.p_value < 1e-6 and h.position_p_value > 0.001
    # the east level grows by 0.3 nT per km across the survey
    grow = 0.3 * east_km * ((ha == 1).astype(float) - (hb == 1))
    g = survey_heading(CrossoverSet(d + grow, ta, tb, ha, hb), east_km, north_km)
    assert g.position_p_value < 1e-6
    flat = survey_heading(
        CrossoverSet(rng.normal(0, 0.03, ha.size), ta, tb, ha, hb), east_km, north_km
    )
    assert flat.p_value > 0.001 and flat.spread_nT < 0.05


def survey_grid(seed: int, lines: int = 12, ties: int = 4, line_sd: float = 0.0):
    """A survey flown as crews fly it: ``lines`` N/S lines one after another (alternating
    headings 0, 2), then ``ties`` E/W ties (1, 3), each crossing every line once; heading
    levels, per-line levels of ``line_sd`` nT and 0.05 nT reading noise."""
    rng = np.random.default_rng(seed)
    i, j = np.meshgrid(np.arange(lines), np.arange(ties), indexing="ij")
    i, j = i.ravel(), j.ravel()
    ha, hb = np.where(i % 2 == 0, 0, 2), np.where(j % 2 == 0, 1, 3)
    ta = 100.0 + 120.0 * i + 0.5 * j * 120.0 / ties
    tb = 100.0 + 120.0 * lines + 200.0 * j + 200.0 * i / lines
    level = np.array([0.0, 0.3, -0.2, 0.1])
    la, lb = rng.normal(0, line_sd, lines), rng.normal(0, line_sd, ties)
    d = level[ha] - level[hb] + la[i] - lb[j] + rng.normal(0, 0.05, i.size)
    names_a = np.array([f"L{k:03d}" for k in i])
    names_b = np.array([f"T{k:03d}" for k in j])
    return ha, hb, ta, tb, d, names_a, names_b


def test_line_levels_are_not_steps_and_a_shared_step_is():
    """Lines with levels of their own (0.4 nT, eight times the reading noise) give no step
    beyond the test's level over many surveys, where reading the crossovers as independent
    finds steps on most; a 2 nT step (five times the lines' scatter) that the lines after it
    share is found and located."""
    found, found_iid = 0, 0
    for seed in range(40):
        ha, hb, ta, tb, d, la, lb = survey_grid(300 + seed, line_sd=0.4)
        found += len(survey_events(CrossoverSet(d, ta, tb, ha, hb, None, None, la, lb), 0.05)) > 0
        found_iid += len(survey_events(CrossoverSet(d, ta, tb, ha, hb), 0.05)) > 0
    assert found <= 6  # 2 expected at 5 %; P(>= 7 | 5 %) < 0.01
    assert found_iid >= 20
    hit = 0
    for seed in range(10):
        ha, hb, ta, tb, d, la, lb = survey_grid(400 + seed, line_sd=0.4)
        t_step = 100.0 + 120.0 * 6 - 10.0  # between the sixth and seventh line
        size = np.array([2.0, -2.0, 2.0, 2.0])
        d = d + size[ha] * (ta > t_step) - size[hb] * (tb > t_step)
        ev = survey_events(CrossoverSet(d, ta, tb, ha, hb, None, None, la, lb), 0.01, 0.3)
        hit += [e.kind for e in ev] == ["step"] and ev[0].start_s <= t_step <= ev[0].end_s
    assert hit >= 9


def test_one_reading_after_a_change_point_is_no_step():
    """A heading read once after a candidate change point gives that gap no step column
    (it would test one reading, an outlier, not a step)."""
    ha = np.array([0, 0, 0, 0, 2, 2])
    x = CrossoverSet(np.zeros(6), np.array([1.0, 2, 3, 10, 4, 11]), np.full(6, 20.0), ha, 1 + ha)
    cols, which = _step_columns(x, 5.0, 2)
    assert which == [] and cols.shape == (6, 0)
    cols, which = _step_columns(x, 2.5, 2)
    assert which == [0]


def test_the_scan_holds_its_level_on_independent_readings():
    """Over clean surveys read as independent crossovers the bootstrap p of the best step
    is about uniform: at most its level's share below 0.05, with sampling room."""
    below = 0
    for seed in range(60):
        rng, ha, hb, ta, tb, d = crossings(200 + seed)
        d = d + rng.normal(0, 0.5, d.size)  # the crossovers' geology scatter
        x = CrossoverSet(d, ta, tb, ha, hb)
        below += len(survey_events(x, 0.05, 0.0)) > 0
    assert below <= 7  # 3 expected; P(>= 8 | 5 %) < 0.03


def test_a_drift_is_found_and_a_heading_error_growing_across_the_area_is_none():
    """A 2 nT/h drift over the survey is reported (as a drift or, its likeliest reading, a
    step) where the ties' times tell time from place; a heading error that grows across the
    block (1 nT/km on the survey lines' headings), flown line after line so that time
    follows place, is no event once the crossovers say where they are, where read without
    positions it looks like a step."""
    found = 0
    for seed in range(10):
        rng, ha, hb, ta, tb, d = crossings(500 + seed, 60)
        east, north = rng.uniform(0, 2000, ta.size), rng.uniform(0, 2000, ta.size)
        drifted = d + 2.0 / 3600.0 * (ta - tb)
        found += len(survey_events(CrossoverSet(drifted, ta, tb, ha, hb, east, north), 0.01, 0.3))
    assert found >= 9
    false, false_blind = 0, 0
    for seed in range(10):
        ha, hb, ta, tb, d, la, lb = survey_grid(600 + seed, lines=16, ties=4)
        i = np.array([int(k[1:]) for k in la])
        j = np.array([int(k[1:]) for k in lb])
        east, north = 100.0 * i, 500.0 * j
        grow = np.array([1.0, 0.0, -1.0, 0.0]) * 1e-3  # nT per m of east, per heading
        d = d + (grow[ha] - grow[hb]) * east
        x = CrossoverSet(d, ta, tb, ha, hb, east, north, la, lb)
        false += len(survey_events(x, 0.01, 0.3)) > 0
        blind = CrossoverSet(d, ta, tb, ha, hb, None, None, la, lb)
        false_blind += len(survey_events(blind, 0.01, 0.3)) > 0
    assert false <= 1
    assert false_blind >= 5


def test_a_crossing_read_in_a_turns_roll_out_is_left_out():
    """A crossover reading whose course window (2 s) runs off its line's start or end was
    read in the turn's roll-out, where the carrier's interference is the turn's: left out,
    like one read in the turn; readings inside both lines are kept."""
    from types import SimpleNamespace

    import pandas as pd

    from pipeline.audit.events import AuditEvents

    rate = 10.0
    t = np.arange(0.0, 200.0, 1 / rate)
    north = SimpleNamespace(
        line_id="L1",
        index=np.flatnonzero(t < 60),
        heading_deg=0.0,
        east_m=np.zeros(600),
        north_m=30.0 * t[:600],
    )
    east_idx = np.flatnonzero((t >= 100) & (t < 160))
    east = SimpleNamespace(
        line_id="T1",
        index=east_idx,
        heading_deg=90.0,
        east_m=30.0 * (t[east_idx] - 100.0),
        north_m=np.full(east_idx.size, 900.0),
    )
    fake = SimpleNamespace(
        flight=SimpleNamespace(data=pd.DataFrame({"alt_m": np.full(t.size, 100.0)})),
        data=SimpleNamespace(time_s=t, rate_hz=rate),
        _survey_geometry=lambda: (None, None, [north, east]),
    )

    def crossing(ta, tb):
        return SimpleNamespace(time_a_s=ta, time_b_s=tb, line_a="L1", line_b="T1")

    xs = [
        crossing(30.0, 130.0),
        crossing(30.0, 100.0),
        crossing(30.0, 100.5),
        crossing(59.8, 130.0),
    ]
    keep = AuditEvents._straight_crossings(fake, xs)
    assert keep.tolist() == [True, False, False, False]


def test_the_scans_batched_bases_take_what_each_candidates_own_basis_takes():
    # each candidate's columns beyond the null design, stacked with the others of its size:
    # the same sums of squares as scipy's orth of each one alone (one candidate partly in
    # the null design's span), none for a candidate wholly in it, none for an empty one
    from scipy.linalg import orth

    from pipeline.audit.line_levels import _explained

    rng = np.random.default_rng(7)
    n = 60
    base = rng.normal(size=(n, 4))
    qb = orth(base)
    res = rng.normal(size=(n, 5))
    res -= qb @ (qb.T @ res)
    cands = [rng.normal(size=(n, 2)) for _ in range(6)]
    cands.append(np.column_stack([base[:, 0] * 2.0 - base[:, 3], rng.normal(size=n)]))
    cands.append(np.column_stack([base[:, 1], base[:, 2]]))
    got = _explained(np.stack(cands), qb, res)
    for c, e in enumerate(cands[:-1]):
        r = e - qb @ (qb.T @ e)
        qc = orth(r, rcond=1e-10)
        assert got[c] == pytest.approx(np.sum((qc.T @ res) ** 2, axis=0), rel=1e-9, abs=1e-9)
    # wholly inside the span: nothing (its projection's rounding noise is no direction)
    assert np.allclose(got[-1], 0.0, atol=1e-12)
    assert _explained(np.zeros((3, n, 0)), qb, res).shape == (3, 5)


def test_the_scan_in_batches_is_the_scan_one_candidate_at_a_time(monkeypatch):
    # candidates of one to four columns, batched by size across a batch boundary, give each
    # candidate the likelihood ratio and rho of its own fit (a per-candidate loop)
    from pipeline.audit import line_levels
    from pipeline.audit.line_levels import LineLevelModel, scan_statistics

    rng = np.random.default_rng(11)
    n = 80
    z = np.zeros((n, 6))
    z[np.arange(n), rng.integers(0, 6, n)] = 1.0
    z[np.arange(n), rng.integers(0, 6, n)] -= 1.0
    model = LineLevelModel.of(z, n)
    base = np.column_stack([np.ones(n), rng.normal(size=n)])
    cands = [rng.normal(size=(n, int(k))) for k in rng.integers(1, 5, 11)]
    y = rng.normal(size=(n, 3)) + cands[4] @ np.full(cands[4].shape[1], 0.8)[:, None]
    monkeypatch.setattr(line_levels, "BATCH", 2)
    lr, rho0, rho1 = scan_statistics(model, base, cands, y)
    for c, e in enumerate(cands):
        lr_c, rho0_c, rho1_c = scan_statistics(model, base, [e], y)
        assert lr[c] == pytest.approx(lr_c[0], rel=1e-9, abs=1e-9)
        assert np.array_equal(rho1[c], rho1_c[0]) and np.array_equal(rho0, rho0_c)


def test_a_crossover_without_a_difference_is_left_out_of_the_scan():
    """A reading beside a gap in the recording has no difference (NaN): the scan leaves it
    out (a NaN likelihood ratio would otherwise be the scan's largest, with the smallest p)."""
    rng, ha, hb, ta, tb, d = crossings(3)
    d = d.copy()
    d[[5, 17]] = np.nan
    assert survey_events(CrossoverSet(d, ta, tb, ha, hb), 0.01, 0.3) == []


def test_the_audit_of_a_recording_with_a_gap_across_the_survey(tmp_path):
    """An independent recording with a minute missing from every topic in the middle of the
    survey (the base station's too): the crossovers read beside the gap have no base
    difference; the audit leaves them out and names nothing on a flight with nothing
    hidden."""
    from mcap.reader import make_reader

    from pipeline.audit import run_audit
    from pipeline.io.reader import read_flight
    from pipeline.segment import segment_flight
    from tests.mcap_builder import build
    from tests.recordings import INDEPENDENT

    src = INDEPENDENT / "independent_none.mcap"
    if not src.exists():
        pytest.skip(f"{src} not present")
    with src.open("rb") as f:
        msgs = [
            (ch.topic, m.log_time, m.data)
            for _, ch, m in make_reader(f).iter_messages(log_time_order=True)
        ]
    t0 = msgs[0][1]
    lo, hi = t0 + 1_200 * 10**9, t0 + 1_260 * 10**9
    gapped = build(tmp_path / "gap.mcap", [m for m in msgs if not lo <= m[1] < hi])
    flight = read_flight(gapped)
    result = run_audit(flight, segment_flight(flight)).to_json()
    assert result["findings"] == [] and result["unexplained"]["events"] == []
