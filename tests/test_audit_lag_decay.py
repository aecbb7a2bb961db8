"""A late sensor against eddy currents that decay: the audit's tie-break on three flights of
the full benchmark (benchmarks/bench_audit_variety.py, whose seeds they are).

The calibration cannot tell a first-order sensor response from decaying eddy currents of
the carrier: both read as a lag. The audit holds a lag back when a decay explains the
calibration as well, leaves the lag nothing beside it, and is clearly slower than the lag
(`pipeline.audit.hypotheses.lag_decay.slower_than_lag`); a decay as quick as the lag is the
sensor's own response.
A lag the eddy-rate columns take up is weighed against the decay when the decay leaves it.
All three flights are multicopters with interference outside the tl18 basis. About 2 minutes, so
they run with ``-m slow`` (the default suite is at its 15-minute budget); the grid check runs
by default.
"""

from __future__ import annotations

import pytest

from pipeline.audit.evidence.lag import EDDY_TAU_GRID_S
from pipeline.audit.hypotheses.lag_decay import slower_than_lag
from pipeline.simulate.audit_trials import correct, one_flight


@pytest.mark.slow
@pytest.mark.parametrize(
    ("kind", "seed", "why"),
    [
        # gradient, no lag; eddy currents of 0.5 nT decaying over 1.2 s: the delay they
        # put into the calibration is the decay's, not a late sensor's
        ("geomagnetic_gradient", 7110, "a slow decay is no late sensor"),
        # a true 0.1 s first-order sensor lag and eddy currents decaying over 1.5 s: the
        # null model's decay takes the lag, which then gains nothing beside it
        pytest.param(
            "sensor_lag",
            2026206,
            "a decay as quick as the lag is the sensor",
            marks=pytest.mark.xfail(
                strict=True,
                reason="a 0.1 s first-order lag beside eddy decay is taken by the null "
                "model's decay (docs/audit.md, Results: a lag missed on 1 of 6)",
            ),
        ),
        # a true 0.1 s delay, no decaying eddy currents: the eddy-rate columns take it
        # while the best decay leaves part of it, so the lag is weighed against the decay
        ("sensor_lag", 7213, "the rate columns take a lag the decay leaves"),
    ],
)
def test_lag_against_decaying_eddy_currents(kind, seed, why, tmp_path):
    row = one_flight(kind, seed, tmp_path)
    assert correct(row), (why, row["named"])
    if kind == "sensor_lag":
        lag = row["estimates"]["sensor_lag"]["lag_s"]
        assert 0.05 < lag < 0.2


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
