"""A late sensor against eddy currents that decay: the audit's tie-break and estimate on
flights of the full benchmark (benchmarks/bench_audit_variety.py, whose seeds they are).

The calibration cannot tell a first-order sensor response from decaying eddy currents of
the carrier: both read as a lag. The audit holds a lag back when a decay explains the
calibration as well, leaves the lag nothing beside it, and is clearly slower than the lag
(`pipeline.audit.hypotheses.decay_rival.slower_than_lag`); a decay as quick as the lag is the
sensor's own response.
A lag the eddy-rate columns take up is weighed against the decay when the decay leaves it; a
tie neither breaks, with the lines' timing silent, is an ambiguity (L10).
All three flights are multicopters with interference outside the tl18 basis. About 2 minutes, so
they run with ``-m slow`` (the default suite is at its 15-minute budget); the grid check runs
by default.
"""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.audit.evidence.lag import EDDY_TAU_GRID_S
from pipeline.audit.extended import ModelSpec
from pipeline.audit.hypotheses.decay_rival import slower_than_lag
from pipeline.audit.stage import _final_decay
from pipeline.simulate.audit_trials import correct, one_flight


@pytest.mark.slow
@pytest.mark.parametrize(
    ("kind", "seed", "why"),
    [
        # gradient, no lag; eddy currents of 0.5 nT decaying over 1.2 s: the delay they
        # put into the calibration is the decay's, not a late sensor's
        ("geomagnetic_gradient", 7110, "a slow decay is no late sensor"),
        # a true 0.1 s first-order sensor lag and eddy currents decaying over 1.5 s: the
        # null model's decay takes the lag; profiled beside the lag it takes the slow one
        ("sensor_lag", 2026206, "a decay profiled beside the lag leaves the lag its own"),
    ],
)
def test_lag_against_decaying_eddy_currents(kind, seed, why, tmp_path):
    row = one_flight(kind, seed, tmp_path)
    assert correct(row), (why, row["named"])
    if kind == "sensor_lag":
        lag = row["estimates"]["sensor_lag"]["lag_s"]
        assert 0.05 < lag < 0.2


@pytest.mark.slow
def test_a_tie_the_lines_cannot_time_is_an_ambiguity(tmp_path):
    # a true 0.1 s delay (0.05 nT of survey error) and a 0.3 s decay each remove 21 % of
    # the held-out calibration residual, neither adds to the other at alpha, and the lines'
    # timing is silent: nothing is named, the tie is reported (L10), not given to the lag
    row = one_flight("sensor_lag", 7213, tmp_path)
    assert row["named"] == [] and row["events"] == 0


def test_slower_than_lag_reads_the_time_constant_grid():
    # the grid's first value at or above the lag is still the same response
    assert EDDY_TAU_GRID_S[:4] == (0.05, 0.1, 0.2, 0.3)
    assert not slower_than_lag(0.2, 0.128)
    assert not slower_than_lag(0.1, 0.128)
    assert slower_than_lag(0.3, 0.128)
    assert slower_than_lag(0.7, 0.236)
    assert slower_than_lag(1.0, -0.076)
    # a lag beyond the grid: no decay on it is slower
    assert not slower_than_lag(1.5, 2.0)


@pytest.mark.slow
def test_a_lag_named_beside_a_decay_is_the_whole_readings_delay(tmp_path):
    # a 0.1 s first-order lag on a fixed-wing flight with interference outside the basis:
    # when the null model takes eddy currents decaying over the lag's own time constant (it
    # did while the eddy columns' derivative fell short), the calibration's lag beside them
    # reads about a third of the truth; the lag reported (and compensated) is the delay of
    # the whole reading either way
    row = one_flight("sensor_lag", 6363201, tmp_path)
    assert row["named"] == ["sensor_lag"]
    est = row["estimates"]["sensor_lag"]
    assert est["lag_s"] == pytest.approx(row["truth"]["effective"]["sensor_lag_s"], abs=0.01)
    assert est.get("lag_beside_decay_s", 0.0) < 0.06
    assert row["covered"] == [True]


@pytest.mark.slow
def test_the_decay_beside_a_lag_is_profiled_anew(tmp_path):
    # a 0.1 s first-order lag and eddy currents decaying over about a second: without a lag
    # the null model's decay takes a time constant near the lag's, beside which the lag
    # gains nothing; profiled with the lag in the model, the decay takes the slow one and the
    # lag is named with its own response
    row = one_flight("sensor_lag", 6565200, tmp_path)
    assert row["named"] == ["sensor_lag"]
    est = row["estimates"]["sensor_lag"]
    assert est["eddy_decay_beside_lag_tau_s"] >= 0.5
    assert est["lag_s"] == pytest.approx(row["truth"]["effective"]["sensor_lag_s"], abs=0.03)
    # the interval's coverage is a rate over flights (the benchmark's), not one flight's


def test_the_reported_decay_is_the_final_models():
    null = [
        {"name": "eddy_decay", "heldout_gain": 0.8, "estimate": {"tau_s": 0.1}},
        {"name": "second_order", "heldout_gain": 0.2, "estimate": {}},
    ]
    out = _final_decay(null, ModelSpec(eddy_tau_s=1.0))
    assert out[0]["estimate"] == {"tau_s": 1.0, "tau_s_without_findings": 0.1}
    assert out[1] == null[1]
    assert null[0]["estimate"] == {"tau_s": 0.1}  # the null's record is not changed
    assert _final_decay(null, ModelSpec(eddy_tau_s=0.1)) == null
    assert _final_decay(null, ModelSpec()) == null


def test_a_lag_named_in_place_of_the_decay_gives_it_back_when_taken_out():
    """Refine re-tests a finding against the model without it: for a lag that took the
    place of the null model's eddy decay that model is the null with its decay, the one the
    lag was named against, not a model with neither."""
    from pipeline.audit.hypotheses import without
    from pipeline.audit.hypotheses.lag_decay import took_the_place_of
    from pipeline.audit.result import Evaluation

    named = ModelSpec(lag_s=0.04, lag_response="first_order", second_order=True)
    ev = Evaluation("sensor_lag", "sensor_lag", {"lag_s": 0.04}, None, None, named)
    assert without(named, ev) == ModelSpec(second_order=True)
    took_the_place_of(ev, 0.3)
    assert without(named, ev) == ModelSpec(second_order=True, eddy_tau_s=0.3)
    assert ev.ci95["in_place_of_eddy_decay_tau_s"] is None


def test_a_ties_survey_difference_is_the_lines_rms_without_their_levels():
    # two explanations' fields differ along each line by a level (levelling takes it out)
    # and a 0.3 nT sinusoid (RMS 0.3 / sqrt 2); off the lines they differ by 50 nT (turns,
    # calibration), which is not the survey's concern
    from types import SimpleNamespace

    from pipeline.audit.evidence.survey_side import lines_difference_nT

    t = np.arange(0.0, 400.0, 0.1)
    on = ((t >= 50) & (t < 150)) | ((t >= 200) & (t < 300))
    wiggle = 0.3 * np.sin(2 * np.pi * t / 10.0)
    other = np.where(t < 175, 4.0, -7.0) + wiggle
    other[~on] = 50.0
    fields = {"a": np.zeros(t.size), "b": other}
    ctx = SimpleNamespace(
        compensated=lambda spec: fields[spec],
        seg=SimpleNamespace(mask=lambda *labels: on),
        data=SimpleNamespace(time_s=t),
    )
    assert lines_difference_nT(ctx, "a", "b") == pytest.approx(0.3 / np.sqrt(2), rel=1e-3)
    fields["b"] = np.where(on, 3.0, 50.0)  # levels only: the map does not depend on the choice
    assert lines_difference_nT(ctx, "a", "b") == pytest.approx(0.0, abs=1e-12)
    ctx.seg = SimpleNamespace(mask=lambda *labels: np.zeros(t.size, bool))
    assert lines_difference_nT(ctx, "a", "b") is None


def test_a_tie_is_said_with_what_it_does_to_the_lines_and_what_separates_it():
    from pipeline.audit.words import ambiguity_text

    a = {
        "candidates": ["sensor_lag", "eddy_decay"],
        "heldout_gain": {"sensor_lag": 0.933, "eddy_decay": 0.912},
        "survey_difference_nT": 0.769,
    }
    text = ambiguity_text(a)
    assert "`sensor_lag` 93.3 %" in text and "`eddy_decay` 91.2 %" in text
    assert "differ by 0.769 nT RMS along the lines" in text
    assert "delays the geology" in text
    del a["survey_difference_nT"]  # an audit without lines
    assert "along the lines (" not in ambiguity_text(a)


def test_a_sensor_filter_reads_the_induced_rate_as_the_eddy_columns_do():
    # why a first-order sensor response and decaying eddy currents tie on a calibration:
    # the rate of T-L's induced terms, d/dt (B u_i u_j), lies in the eddy columns
    # B u_i du_j/dt (B nearly constant), while the permanent terms' rate, du_i/dt, leaves a
    # part outside them once the box turns the field through several headings
    from scipy.spatial.transform import Rotation

    from pipeline.compensate.terms import tl18_rate_terms

    t = np.arange(0.0, 400.0, 0.1)
    roll = 0.3 * np.sin(2 * np.pi * t / 6.0)
    pitch = 0.2 * np.sin(2 * np.pi * t / 5.0 + 1.0)
    yaw = np.radians(90.0) * np.floor(t / 100.0) + 0.02 * np.sin(2 * np.pi * t / 40.0)
    earth_ned = np.array([15000.0, 2000.0, 45000.0])
    b = Rotation.from_euler("xyz", np.c_[roll, pitch, yaw]).inv().apply(earth_ned)
    cols, names = tl18_rate_terms(b, t)
    steady = np.ones(t.size, bool)
    for k in range(1, 4):  # the legs' joins (a jump in heading) are not a rate
        steady[(t > 100 * k - 1) & (t < 100 * k + 1)] = False
    eddy = cols[steady][:, [n.startswith("eddy") for n in names]]
    rng = np.random.default_rng(5)

    def outside(group: str) -> float:
        x = cols[:, [n.startswith(group) for n in names]] @ rng.normal(
            size=sum(n.startswith(group) for n in names)
        )
        rate = np.gradient(x, t)[steady]
        left = rate - eddy @ np.linalg.lstsq(eddy, rate, rcond=None)[0]
        return float(np.linalg.norm(left) / np.linalg.norm(rate))

    assert outside("ind") < 0.01
    assert outside("perm") > 0.02


def test_a_tie_is_a_message_on_the_audit_channel():
    # a viewer of the processed recording sees the tie too, also with no unexplained note
    import json
    from pathlib import Path
    from types import SimpleNamespace

    import jsonschema

    from pipeline.audit.report import finding_channel

    tie = {
        "candidates": ["sensor_lag", "eddy_decay"],
        "heldout_gain": {"sensor_lag": 0.133, "eddy_decay": 0.154},
        "survey_difference_nT": 0.181,
    }
    res = SimpleNamespace(findings=[], unexplained={"events": [], "ambiguities": [tie]})
    ch = finding_channel(SimpleNamespace(time_ns=np.array([10**18])), res)
    assert len(ch.messages) == 1
    t, payload = ch.messages[0]
    assert payload["effect"] == "unexplained" and not payload["accepted"]
    assert payload["estimate"] == tie and "0.181 nT" in payload["message"]
    schema = Path(__file__).parents[1] / "schemas" / "aeromag.AuditFinding.json"
    stamped = {**payload, "timestamp": {"sec": t // 10**9, "nsec": t % 10**9}}
    jsonschema.Draft202012Validator(json.loads(schema.read_text())).validate(stamped)
