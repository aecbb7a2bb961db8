"""Compensation when the carrier's interference lies partly outside the tl18 basis.

Until now compensation was only tested on interference the tl18 basis generates itself. Here
the simulator adds interference no T-L model represents (``interference.outside_basis``:
eddy currents with an L/R lag, aliased vibration, an unrecorded switching current, a
second-order induced field) and the fitted model is judged against the simulator's *true*
interference (``interference_nT`` of the truth series), not against its own residual:

* on the survey, the error cannot be smaller than what no tl18 model can represent there
  (``survey_outside_tl18_rms_nT``): a smaller error would mean the truth leaked into the fit;
* on the calibration (in the fitted band) and on the survey, the fit is within 10 % of a
  noise-free fit on the same calibration with the same lambda (the best any tl18 calibration
  can do on this flight), plus three times what the same noise costs without outside-basis
  interference: the remaining error is the outside physics, not the estimator;
* the same flight without the outside-basis part is compensated to below the sensor noise.

Measured (``-m slow``, uav-small): 0.3 nT RMS outside the basis on calibration gives survey
errors of 1.4-5.2 nT against the true interference (the outside part biases the coefficients
and the bias shows up as heading-dependent error on the survey), while the outside part on the
survey itself is only 0.2-0.3 nT; 0.6 nT of second-order induced field (seed 7) leaves 2.1 nT
of a 3.9 nT interference.

Offsets and the isotropic induced scale are removed from survey errors first: a band-passed
calibration cannot observe them (see ``tests/test_compensate.py``). One seed runs by default;
``-m slow`` runs more seeds, sizes and terms.
"""

from __future__ import annotations

import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from pipeline.compensate import FitSettings, Measurements, fit_compensation
from pipeline.compensate.filters import bandpass_blocks, bandpass_sos, contiguous_blocks
from pipeline.compensate.stage import calibration_mask
from pipeline.io.reader import read_flight
from pipeline.segment import segment_flight
from pipeline.simulate import write_simulation
from tests.conftest import run_sim

LINEAR = ("eddy_lag", "vibration", "unrecorded_current")


def _survey_error(pred, true, earth, s):
    """RMS of (pred - true) on ``s`` after removing an offset and a scale of the Earth field."""
    x = np.column_stack([np.ones(s.sum()), earth[s]])
    d = pred[s] - true[s]
    c, *_ = np.linalg.lstsq(x, d, rcond=None)
    return float(np.sqrt(np.mean((d - x @ c) ** 2)))


def evaluate(seed: int, share_nT: float, terms: tuple[str, ...]) -> dict:
    """Fit tl18 on a simulated uav-small flight and score it against the true interference.

    ``share_nT`` is the RMS on calibration outside the tl18 basis, split equally (in squares)
    among ``terms``; 0 gives the same flight (same seed, same noise) without it.
    """
    each = float(share_nT / np.sqrt(len(terms)))
    over = [f"interference.outside_basis.{t}_nT={each!r}" for t in terms] if share_nT else []
    sim = run_sim("uav-small", seed, over)
    fl = read_flight(write_simulation(sim, Path(tempfile.mkdtemp()) / "s.mcap"))
    seg = segment_flight(fl)
    meas = Measurements.from_flight(fl)
    cal = calibration_mask(fl, seg, "auto")
    idx = np.searchsorted(sim.series["time_ns"], fl.time_ns)
    true = sim.series["interference_nT"][idx]
    earth = sim.series["earth_total_nT"][idx]
    model = fit_compensation(meas, cal, FitSettings("tl18"))
    # the best a tl18 calibration can do on this flight: the same fit on the noise-free field
    oracle = fit_compensation(
        replace(meas, scalar_nT=earth + true), cal, FitSettings("tl18", ridge=model.lambda_)
    )
    pred, best = model.interference_nT(meas), oracle.interference_nT(meas)
    srv = seg.mask("survey") & np.isfinite(pred)
    sos = bandpass_sos((0.1, 0.9), meas.rate_hz, 4)
    blocks = contiguous_blocks(cal & np.isfinite(pred), meas.time_s)
    pb, _ = bandpass_blocks(pred, blocks, sos, 20)
    ob_, _ = bandpass_blocks(best, blocks, sos, 20)
    tb, _ = bandpass_blocks(true, blocks, sos, 20)
    n_eff = model.n_fit * 2 * (0.9 - 0.1) / meas.rate_hz  # independent samples in the band
    noise = sim.truth["noise"]["scalar_nT"]
    ob = sim.truth.get("outside_basis_interference") or {}
    return {
        "noise_nT": noise,
        "calibration_error_nT": float(np.sqrt(np.mean((pb - tb) ** 2))),
        "oracle_calibration_error_nT": float(np.sqrt(np.mean((ob_ - tb) ** 2))),
        "noise_bound_nT": noise * np.sqrt(len(model.terms) / n_eff),
        "survey_error_nT": _survey_error(pred, true, earth, srv),
        "oracle_survey_error_nT": _survey_error(best, true, earth, srv),
        "interference_std_nT": float(np.std(true[srv])),
        "calibration_outside_nT": ob.get("calibration_outside_tl18_rms_nT", 0.0),
        "survey_outside_nT": ob.get("survey_outside_tl18_rms_nT") or 0.0,
    }


def check(seed: int, share_nT: float, terms: tuple[str, ...]) -> dict:
    clean = evaluate(seed, 0.0, terms)
    r = evaluate(seed, share_nT, terms)
    # the flight really carries interference outside the basis, of the requested size
    assert r["calibration_outside_nT"] == pytest.approx(share_nT, rel=0.05)
    assert r["survey_outside_nT"] > 0.1 * share_nT
    # survey: never better than the unrepresentable part (the truth did not leak in)
    assert r["survey_error_nT"] >= 0.8 * r["survey_outside_nT"]
    # as good as a noise-free calibration, up to what the noise alone costs
    assert r["calibration_error_nT"] <= (
        1.1 * r["oracle_calibration_error_nT"]
        + 3 * max(clean["calibration_error_nT"], r["noise_bound_nT"])
    )
    assert r["survey_error_nT"] <= (
        1.1 * r["oracle_survey_error_nT"] + 3 * max(clean["survey_error_nT"], r["noise_bound_nT"])
    )
    # compensation still helps: the error is below the interference it removes (a second-
    # order induced field of 0.6 nT outside the basis leaves 2.1 of 3.9 nT, seed 7)
    assert r["survey_error_nT"] < r["interference_std_nT"]
    # without the outside-basis part the same flight is compensated to the noise level
    assert clean["survey_error_nT"] < clean["noise_nT"]
    return r


def test_outside_basis_interference_is_compensated_as_well_as_tl18_can():
    check(3, 0.3, LINEAR)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [4, 5, 6, 7])
@pytest.mark.parametrize("share_nT", [0.3, 0.6])
@pytest.mark.parametrize("terms", [LINEAR, ("second_order",), ("eddy_lag",)])
def test_outside_basis_over_seeds(seed, share_nT, terms):
    check(seed, share_nT, terms)
