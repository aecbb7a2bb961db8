"""The long block survey the scaling benchmark flies (issues 35 and 37): the ``uav-block``
scenario's plan is 45 lines x 2 km at 50 m, 3 ties, the X lines and one calibration box,
about 5 h at 10 Hz."""

from __future__ import annotations

import numpy as np

from pipeline.simulate import Scenario
from pipeline.simulate.trajectory import build_trajectory, plan_legs


def test_block_plan_has_the_benchmark_shape():
    sc = Scenario.load("uav-block")
    legs = plan_legs(sc)
    survey = [g for g in legs if g.label == "survey"]
    ties = [g for g in legs if g.label == "tie"]
    val = [g for g in legs if g.label == "validation"]
    cal = [g for g in legs if g.label == "calibration"]
    assert len(survey) == 45 and all(abs(g.length_m - 2000.0) < 1e-6 for g in survey)
    np.testing.assert_allclose(np.diff(sorted(g.start_en[0] for g in survey)), 50.0)
    assert len(ties) == 3 and all(abs(g.length_m - 2200.0) < 1e-6 for g in ties)
    np.testing.assert_allclose(np.diff(sorted(g.start_en[1] for g in ties)), 1000.0)
    assert len(val) == 2 and all(abs(g.length_m - np.hypot(2200, 2000)) < 1e-6 for g in val)
    assert len(cal) == 4  # one box: four headings
    assert sc["sensors"]["scalar_rate_hz"] == 10.0


def test_block_flight_lasts_about_five_hours():
    hours = build_trajectory(Scenario.load("uav-block")).duration_s / 3600
    assert 4.8 <= hours <= 5.2
