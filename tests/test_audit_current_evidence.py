"""The electrical current's evidence outside the calibration, joined: the survey's
crossovers and the channel's switches (``pipeline.audit.hypotheses.electrical_current``)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from pipeline.audit.extended import ModelSpec
from pipeline.audit.hypotheses.electrical_current import _by_both
from pipeline.audit.result import Evaluation
from pipeline.audit.settings import AuditSettings
from pipeline.audit.survey import SurveyCoupling
from pipeline.audit.switching import SwitchCoupling
from pipeline.compensate.heldout import HeldOut


def held(reduction: float, p: float, n: int = 20) -> HeldOut:
    return HeldOut(1.0, 1.0 - reduction, p, n)


def _ctx():
    """A context with one current channel and a calibration the coupling leaves as it is
    (the known coupling's held-out gain: 10 %)."""
    t = np.arange(2000.0)
    data = SimpleNamespace(aux={"payload": np.sign(np.sin(t / 90.0))}, aux_units={"payload": "A"})
    return SimpleNamespace(
        s=AuditSettings(),
        data=data,
        mask=np.ones(t.size, bool),
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


def test_crossovers_and_few_switches_together_decide_what_neither_can_alone():
    """Six switches: the switches' leave-one-out sign-flip test has no p under 1/64, above
    alpha 0.01 however large the coupling; the crossovers' leave-one-out p 0.026 is above it
    too. Different data, so Fisher joins them: 0.0036, and the coupling tests (3e-6, 7e-5)
    decide it outside the calibration."""
    ctx, ev = _ctx(), _ev()
    sc = SurveyCoupling(3.2, (2.2, 4.2), 3e-6, 60)
    sw = SwitchCoupling(2.9, 0.3, 7e-5, 6, held(0.78, 1 / 64, 6))
    _by_both(ctx, ev, ModelSpec(), "payload", (sc, held(0.45, 0.026)), sw)
    assert ev.decided_outside and ev.confirmed_gain
    assert 0.003 < ev.confirm_p < 0.004
    assert ev.estimate["confirmed_by"].startswith("the survey's crossovers")
    # the crossovers predict their own data alone: their own rules decide, nothing joined
    ev = _ev()
    _by_both(ctx, ev, ModelSpec(), "payload", (sc, held(0.45, 0.002)), sw)
    assert "joint_heldout_p_value" not in ev.estimate
    # one of the two does not predict its own data: nothing joined
    ev = _ev()
    _by_both(ctx, ev, ModelSpec(), "payload", (sc, held(0.45, 0.4)), sw)
    assert not ev.decided_outside and ev.confirm_p is None
    # the switches do not show a coupling (its t-test): nothing joined
    ev = _ev()
    weak = SwitchCoupling(0.3, 0.3, 0.3, 6, held(0.78, 1 / 64, 6))
    _by_both(ctx, ev, ModelSpec(), "payload", (sc, held(0.45, 0.026)), weak)
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
        _by_both(ctx, ev, ModelSpec(), "payload", (sc, held(0.3, p_sg)), sw)
        confirmed += ev.confirmed_gain
    alpha = ctx.s.alpha
    assert confirmed / draws <= alpha + 3 * np.sqrt(alpha * (1 - alpha) / draws)
