"""The survey crossovers' check of the null model's nuisance groups
(:mod:`pipeline.audit.survey_guard`) on synthetic crossovers whose truth is known: terms that
extrapolate badly to the lines are caught, a level per heading is not damage, and on terms
that change nothing the check's false rate is its level."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.audit.survey import CrossoverSet, heading_levels
from pipeline.audit.survey_guard import compare_crossovers

ALPHA, MIN_GAIN = 0.05, 0.05


def crossings(rng, lines=8, ties=4, noise_nT=0.2):
    """Crossovers of ``lines`` survey lines (headings 0 and 2 alternating) with ``ties``
    ties (1 and 3), heading levels of a few nT and reading noise: (line of each, heading
    columns, the differences)."""
    la = np.repeat(np.arange(lines), ties)
    lb = np.tile(np.arange(ties), lines)
    ha, hb = 2 * (la % 2), 1 + 2 * (lb % 2)
    level = np.array([0.0, 3.0, -2.0, 1.0])
    d = level[ha] - level[hb] + rng.normal(0, noise_nT, la.size)
    x = CrossoverSet(d, np.zeros(la.size), np.ones(la.size), ha, hb)
    return la, heading_levels(x), d


@pytest.mark.parametrize("seed", range(5))
def test_terms_that_scatter_the_crossovers_are_worse_and_needed_the_other_way(seed):
    rng = np.random.default_rng(seed)
    line, levels, d = crossings(rng)
    scattered = d + rng.normal(0, 0.6, d.size)  # a group extrapolating badly to the lines
    check = compare_crossovers(line, levels, scattered, d)
    assert check.worse(ALPHA, MIN_GAIN) and not check.better(ALPHA, MIN_GAIN)
    assert check.rms_with_nT > 2 * check.rms_without_nT
    back = compare_crossovers(line, levels, d, scattered)  # the group removes that scatter
    assert back.better(ALPHA, MIN_GAIN) and not back.worse(ALPHA, MIN_GAIN)


def test_a_level_per_heading_is_not_damage():
    """A group that shifts each heading's level (which levelling removes) but nothing else."""
    rng = np.random.default_rng(7)
    line, levels, d = crossings(rng)
    shifted = d + levels @ np.array([1.5, -0.8, 2.0])
    check = compare_crossovers(line, levels, shifted, d)
    assert abs(check.rms_with_nT - check.rms_without_nT) < 1e-9
    assert not check.worse(ALPHA, MIN_GAIN) and not check.better(ALPHA, MIN_GAIN)


def test_too_few_lines_to_judge():
    rng = np.random.default_rng(3)
    line, levels, d = crossings(rng, lines=2)
    assert compare_crossovers(line, levels, d + 1.0, d) is None


def test_terms_that_change_nothing_are_called_worse_at_most_at_the_tests_level():
    """Both models' crossovers carry the same readings and independent small misfits of
    the same size: the group is neither better nor worse, and the check (test and size)
    calls it worse on at most ALPHA of 400 surveys (binomial 99 % upper margin)."""
    rng = np.random.default_rng(11)
    calls = 0
    for _ in range(400):
        line, levels, d = crossings(rng, lines=int(rng.integers(3, 12)))
        a, b = (d + rng.normal(0, 0.1, d.size) for _ in range(2))
        calls += compare_crossovers(line, levels, a, b).worse(ALPHA, 0.0)
    assert calls <= 400 * ALPHA + 2.33 * np.sqrt(400 * ALPHA * (1 - ALPHA))
