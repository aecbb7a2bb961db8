"""A lag and decaying eddy currents that the calibration cannot tell apart are reported as a
tie, not named by rule; each finding lists what came second."""

from __future__ import annotations

from pathlib import Path

import pytest

from pipeline.audit import run_audit
from pipeline.audit.evidence import HeldOut
from pipeline.audit.stage import Evaluation, alternatives, ambiguities
from pipeline.io.reader import read_flight
from pipeline.segment import segment_flight

RECORDINGS = Path(__file__).resolve().parents[1].parent / "shared" / "recordings"


def _held(before: float, after: float) -> HeldOut:
    return HeldOut(before, after, 0.001, 40)


def test_ambiguities_keep_each_candidates_last_tie_and_drop_accepted_ones():
    tie = {"candidates": ["sensor_lag", "eddy_decay"], "heldout_gain": {"sensor_lag": 0.1}}
    first = Evaluation("sensor_lag", "sensor_lag", {}, None, None, None, ambiguity=tie)
    later = Evaluation("sensor_lag", "sensor_lag", {}, None, None, None)
    other = Evaluation("diurnal", "diurnal", {}, None, None, None, ambiguity=tie, accepted=True)
    assert ambiguities([[first, other]]) == [tie]
    # re-tested in a later round without a tie: the last word counts
    assert ambiguities([[first], [later]]) == []


def test_alternatives_list_the_rival_then_the_round_on_the_same_metric():
    lag = Evaluation(
        "sensor_lag",
        "sensor_lag",
        {"eddy_decay": {"alone": {"reduction_pct": 12.0}}},
        None,
        _held(1.0, 0.8),
        None,
    )
    cur = Evaluation("electrical_current", "electrical_current:a", {}, None, _held(1.0, 0.9), None)
    flux = Evaluation("vector_calibration", "vector_calibration", {}, None, _held(1.0, 0.2), None)
    flux.metric = "heldout_fluxgate_residual_rms"
    out = alternatives(lag, [[cur, lag, flux]])
    assert [a["name"] for a in out] == ["eddy_decay", "electrical_current:a"]
    assert out[0]["heldout_gain"] == pytest.approx(0.12)
    assert out[1]["heldout_gain"] == pytest.approx(0.1)


@pytest.mark.skipif(
    not (RECORDINGS / "realism_none.mcap").is_file(),
    reason="the independent recordings are not beside the repository",
)
def test_out_of_basis_physics_is_no_lag_on_an_independent_flight():
    """An independent generator's flight with nothing hidden but eddy currents that decay,
    second-order induced terms and an unrecorded switching current: no finding, and the tie
    between a lag and the decay said out loud."""
    flight = read_flight(RECORDINGS / "realism_none.mcap")
    res = run_audit(flight, segment_flight(flight))
    out = res.to_json()
    assert out["findings"] == []
    ties = out["unexplained"]["ambiguities"]
    assert [sorted(t["candidates"]) for t in ties] == [["eddy_decay", "sensor_lag"]]
    assert set(ties[0]["heldout_gain"]) == {"sensor_lag", "eddy_decay"}
