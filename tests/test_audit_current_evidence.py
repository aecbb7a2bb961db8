"""The electrical current's evidence outside the calibration, joined: the survey's
crossovers and the channel's switches (``pipeline.audit.hypotheses.electrical_current``):
their leave-one-out predictions confirm the calibration's test together (C5), their
coupling estimates decide together (C3)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from scipy import stats

from pipeline.audit.extended import ModelSpec
from pipeline.audit.hypotheses.electrical_current import _by_both, _by_the_survey, joined_coupling
from pipeline.audit.result import Evaluation
from pipeline.audit.settings import AuditSettings
from pipeline.audit.survey import SurveyCoupling
from pipeline.audit.switching import SwitchCoupling, SwitchSteps, switch_coupling
from pipeline.compensate.heldout import HeldOut


def held(reduction: float, p: float, n: int = 20) -> HeldOut:
    return HeldOut(1.0, 1.0 - reduction, p, n)


def _ctx(amplitude_A: float = 1.0):
    """A context with one current channel (a square wave of ``amplitude_A`` along the
    survey) and a calibration the coupling leaves as it is (the known coupling's held-out
    gain: 10 %)."""
    t = np.arange(2000.0)
    data = SimpleNamespace(
        aux={"payload": amplitude_A * np.sign(np.sin(t / 90.0))}, aux_units={"payload": "A"}
    )
    return SimpleNamespace(
        s=AuditSettings(),
        data=data,
        mask=np.ones(t.size, bool),
        seg=SimpleNamespace(mask=lambda *labels: t > 500.0),
        heldout=lambda current, ext: held(0.1, 0.02, 40),
    )


def _ev() -> Evaluation:
    est = {"switch_total_field_nT_per_unit": 2.9, "survey_total_field_nT_per_unit": 3.2}
    return Evaluation(
        "electrical_current",
        "electrical_current:payload",
        est,
        None,
        held(0.18, 1e-4, 70),
        ModelSpec(aux=("payload",)),
    )


def test_crossovers_and_few_switches_together_confirm_what_neither_can_alone():
    """Six switches: the switches' leave-one-out sign-flip test has no p under 1/64, above
    alpha 0.01 however large the coupling; the crossovers' leave-one-out p 0.026 is above it
    too. Different data, so Fisher joins them: 0.0036 confirms the calibration's test; the
    coupling tests (3e-6, 7e-5) joined decide it outside the calibration."""
    ctx, ev = _ctx(), _ev()
    sc = SurveyCoupling(3.2, (2.2, 4.2), 3e-6, 60)
    sw = SwitchCoupling(2.9, 0.3, 7e-5, 6, held(0.78, 1 / 64, 6))
    _by_both(ctx, ev, (sc, held(0.45, 0.026)), sw)
    assert ev.confirmed_gain and not ev.decided_outside
    assert 0.003 < ev.confirm_p < 0.004
    _by_the_survey(ctx, ev, ModelSpec(), "payload", (sc, held(0.45, 0.026)), sw)
    assert ev.decided_outside
    assert ev.estimate["confirmed_by"] == "survey crossovers and channel switches"
    # the joined k lies between the two, nearer the more precise switches
    assert 2.9 < ev.estimate["survey_joined_total_field_nT_per_unit"] < 3.05
    # the crossovers predict their own data alone: their own rules decide, nothing joined
    ev = _ev()
    _by_both(ctx, ev, (sc, held(0.45, 0.002)), sw)
    assert "joint_heldout_p_value" not in ev.estimate
    # one of the two does not predict its own data: nothing joined
    ev = _ev()
    _by_both(ctx, ev, (sc, held(0.45, 0.4)), sw)
    assert not ev.decided_outside and ev.confirm_p is None
    # the switches do not show a coupling (its t-test): nothing joined
    ev = _ev()
    weak = SwitchCoupling(0.3, 0.3, 0.3, 6, held(0.78, 1 / 64, 6))
    _by_both(ctx, ev, (sc, held(0.45, 0.026)), weak)
    assert not ev.decided_outside and "joint_heldout_p_value" not in ev.estimate


def test_with_no_coupling_the_joined_evidence_decides_at_most_at_alpha():
    """No coupling that predicts held-out data: the worst case, where both coupling tests
    pass anyway (interference that follows the channel on the data they were fitted on),
    and the two leave-one-out tests uniform and independent (the sign-flip test of n
    switches on its grid of 2^-n); the share of flights the joined evidence confirms stays
    within alpha (3 binomial errors). Either test alone at alpha would double it."""
    rng = np.random.default_rng(5)
    ctx, draws, confirmed = _ctx(), 4000, 0
    for _ in range(draws):
        ev = _ev()
        p_sg = rng.uniform()
        grid = 2.0 ** rng.integers(4, 13)  # 4-12 switches
        p_loo = np.ceil(rng.uniform() * grid) / grid
        sc = SurveyCoupling(3.0, (2.0, 4.0), 1e-6, 60)
        sw = SwitchCoupling(3.0, 0.3, 1e-6, 6, held(0.3, p_loo, 6))
        _by_both(ctx, ev, (sc, held(0.3, p_sg)), sw)
        confirmed += ev.confirmed_gain
    alpha = ctx.s.alpha
    assert confirmed / draws <= alpha + 3 * np.sqrt(alpha * (1 - alpha) / draws)


def _crossover_coupling(rng, k: float, n: int = 40) -> SurveyCoupling:
    """The crossovers' regression of differences on the channel's difference, with a
    Student interval (as :func:`pipeline.audit.survey.survey_coupling`)."""
    g = rng.choice([-2.0, -1.0, 1.0, 2.0], size=n)
    fit = stats.linregress(g, k * g + rng.normal(0.0, 1.5, n))
    half = stats.t.ppf(0.975, n - 2) * fit.stderr
    return SurveyCoupling(fit.slope, (fit.slope - half, fit.slope + half), fit.pvalue, n)


def _switch_coupling(rng, k: float, n: int) -> SwitchCoupling:
    """The switches' weighted fit of steps on the channel's changes (few steps: Student's t
    on n - 1 degrees of freedom), steps of unequal precision."""
    change = rng.choice([-1.5, 1.5], size=n)
    se = rng.uniform(0.1, 0.6, n)
    steps = SwitchSteps(np.arange(n) * 60.0, change, k * change + rng.normal(0.0, se), se)
    return switch_coupling(steps)


def test_the_joined_coupling_test_holds_its_level_with_no_coupling():
    """No coupling: crossovers (40 differences) and switches (4-10 steps, Student's t on few
    degrees of freedom) each give a p on its own scale; the joined test's false rate at
    0.05 and 0.01 stays within 3 binomial errors (the switches' own test is conservative:
    their scatter only ever widens its error), and it rejects at all."""
    rng = np.random.default_rng(11)
    p = np.array(
        [
            joined_coupling(
                _crossover_coupling(rng, 0.0), _switch_coupling(rng, 0.0, rng.integers(4, 11))
            ).p_value
            for _ in range(3000)
        ]
    )
    for level in (0.05, 0.01):
        assert np.mean(p < level) <= level + 3 * np.sqrt(level * (1 - level) / p.size)
    assert np.mean(p < 0.1) > 0.02


def test_the_joined_coupling_test_is_more_powerful_than_either_alone():
    """A coupling of 0.15 nT/A each source sees weakly: the joined test finds it (p < 0.01)
    more often than either source's own test, and its estimate is unbiased."""
    rng = np.random.default_rng(12)
    rows = []
    for _ in range(400):
        sc, sw = _crossover_coupling(rng, 0.15), _switch_coupling(rng, 0.15, 8)
        j = joined_coupling(sc, sw)
        rows.append(
            (sc.p_value < 0.01, sw.p_value < 0.01, j.p_value < 0.01, j.total_field_nT_per_unit)
        )
    a = np.array(rows, float)
    assert a[:, 2].mean() > max(a[:, 0].mean(), a[:, 1].mean()) + 0.05
    assert abs(a[:, 3].mean() - 0.15) < 0.02
    # one source alone: its own test
    sc = _crossover_coupling(rng, 0.5)
    assert joined_coupling(sc, None).p_value == pytest.approx(sc.p_value, rel=0.2)
    assert joined_coupling(None, None) is None


def test_a_significant_coupling_too_small_for_the_survey_is_not_decided():
    """Many crossovers and switches make a tiny coupling significant; it is decided only
    when k times the channel's spread along the lines reaches ``min_survey_effect_nT``."""
    sc = SurveyCoupling(0.05, (0.04, 0.06), 1e-9, 400)
    sw = SwitchCoupling(0.05, 0.005, 1e-9, 40, held(0.5, 1e-4, 40))
    ctx, ev = _ctx(amplitude_A=0.2), _ev()  # 0.05 nT/A x 0.2 A: 0.01 nT on the lines
    _by_the_survey(ctx, ev, ModelSpec(), "payload", (sc, held(0.5, 1e-4)), sw)
    assert not ev.decided_outside
    assert ev.estimate["survey_effect_nT"] == pytest.approx(0.01, rel=0.05)
    ctx, ev = _ctx(amplitude_A=1.0), _ev()  # 0.05 nT on the lines
    _by_the_survey(ctx, ev, ModelSpec(), "payload", (sc, held(0.5, 1e-4)), sw)
    assert ev.decided_outside


def test_one_survey_test_per_channel_picked_by_the_evidence_present():
    """Both kinds of evidence: only their joint test decides (a strong source alone does
    not when the other contradicts it); one kind: its own test, and only when it also
    predicts its own data leave-one-out."""
    ctx = _ctx(amplitude_A=1.0)
    sc = SurveyCoupling(3.2, (2.2, 4.2), 1e-7, 60)
    against = SwitchCoupling(-3.0, 0.6, 1e-6, 12, held(0.5, 1e-3, 12))
    ev = _ev()
    _by_the_survey(ctx, ev, ModelSpec(), "payload", (sc, held(0.45, 1e-4)), against)
    assert not ev.decided_outside
    assert ev.estimate["survey_joined_p_value"] > 0.05
    # the crossovers alone: decided when they predict their own data ...
    ev = _ev()
    _by_the_survey(ctx, ev, ModelSpec(), "payload", (sc, held(0.45, 1e-4)), None)
    assert ev.decided_outside and ev.estimate["confirmed_by"] == "survey crossovers"
    assert "survey_joined_p_value" not in ev.estimate
    # ... and not when they do not
    ev = _ev()
    _by_the_survey(ctx, ev, ModelSpec(), "payload", (sc, held(0.45, 0.3)), None)
    assert not ev.decided_outside
    # the switches alone, which predict each other
    sw = SwitchCoupling(2.9, 0.3, 7e-8, 12, held(0.78, 1e-3, 12))
    ev = _ev()
    _by_the_survey(ctx, ev, ModelSpec(), "payload", (None, None), sw)
    assert ev.decided_outside and ev.estimate["confirmed_by"] == "channel switches"


def test_a_current_the_survey_decided_is_kept_at_refine_while_its_evidence_shows_it():
    """Refine re-tests a finding with the others in the model: one the survey decided keeps
    its acceptance while that test still shows it (p < alpha, same sign, mattering), even
    where the calibration's rival now holds it back; not when the evidence faded, turned or
    never decided it."""
    from pipeline.audit.decide import still_shown_outside

    ctx = _ctx()
    accepted = _ev()
    accepted.decided_outside, accepted.outside = True, (0.002, 3.0)
    again = _ev()
    again.held_back = True
    for outside, kept in [
        ((0.004, 2.8), True),  # above the channels' Bonferroni level, still below alpha
        ((0.2, 2.8), False),  # faded
        ((0.004, -2.8), False),  # turned
        (None, False),  # no longer predicts its data or no longer matters
    ]:
        again.outside = outside
        assert still_shown_outside(ctx, accepted, again) is kept
    accepted.decided_outside = False  # decided on the calibration: the rival stands
    again.outside = (0.004, 2.8)
    assert not still_shown_outside(ctx, accepted, again)
    # the decision records the test's p and estimate only when they can decide
    sc = SurveyCoupling(3.2, (2.2, 4.2), 1e-7, 60)
    ev = _ev()
    _by_the_survey(ctx, ev, ModelSpec(), "payload", (sc, held(0.45, 0.3)), None)
    assert ev.outside is None
    ev = _ev()
    _by_the_survey(ctx, ev, ModelSpec(), "payload", (sc, held(0.45, 1e-4)), None)
    assert ev.outside == (pytest.approx(1e-7), pytest.approx(3.2))
