"""Survey-side evidence of the audit (issue 16, item 2), on synthetic crossovers whose
truth is known: heading levels, a step, a drift, a lag, a current coupling."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.audit.evidence import f_test_p, least_squares_rss
from pipeline.audit.survey import (
    CrossoverSet,
    _candidate_gaps,
    _step_columns,
    heading_levels,
    scan_p_value,
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


def test_the_scan_correction_holds_its_level_and_is_sharper_than_bonferroni():
    """Over clean surveys the scan-corrected p of the best step is about uniform (at most
    its level's share below 0.05, with sampling room), and a step of a size crossovers
    barely show is significant where Bonferroni's bound is not (nearby change points are nearly the
    same test)."""
    below = 0
    for seed in range(60):
        rng, ha, hb, ta, tb, d = crossings(200 + seed)
        d = d + rng.normal(0, 0.5, d.size)  # the crossovers' geology scatter
        x = CrossoverSet(d, ta, tb, ha, hb)
        below += len(survey_events(x, 0.05, 0.0)) > 0
    assert below <= 7  # 3 expected; P(>= 8 | 5 %) < 0.03
    rng, ha, hb, ta, tb, d = crossings(5)
    size = np.array([0.24, -0.16, 0.2, 0.16])
    d = d + rng.normal(0, 0.5, d.size) + size[ha] * (ta > 1800) - size[hb] * (tb > 1800)
    x = CrossoverSet(d, ta, tb, ha, hb)
    base = heading_levels(x)
    ps, designs = [], []
    for lo, hi in _candidate_gaps(x, 2):
        cols, _ = _step_columns(x, 0.5 * (lo + hi))
        designs.append(np.column_stack([base, cols]))
        r0, k0, _ = least_squares_rss(base, d)
        r1, k1, _ = least_squares_rss(designs[-1], d)
        ps.append(f_test_p(r0, k0, r1, k1, d.size))
    p_min = min(ps)
    p = scan_p_value(p_min, base, designs, len(designs))
    # significant at 0.01 where Bonferroni's bound (0.02) is not
    assert p_min <= p < 0.01 < min(1.0, p_min * len(designs))
