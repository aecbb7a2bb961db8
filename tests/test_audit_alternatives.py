"""Each finding lists what came second: its rival explanation, then the round's other
candidates on the same metric."""

from __future__ import annotations

import pytest

from pipeline.audit.evidence import HeldOut
from pipeline.audit.result import Evaluation, alternatives


def _held(before: float, after: float) -> HeldOut:
    return HeldOut(before, after, 0.001, 40)


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
