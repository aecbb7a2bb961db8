"""Recovery over many seeds, against the simulator's truth (``-m slow``: 24 seeds each;
the default run takes a CI-sized subset of 3).

Each flight draws its own manoeuvre schedule (shuffled order, block lengths 15-40 s, periods
4-9 s, amplitudes 4-12 deg), scalar noise (0.02-0.2 nT) and carrier, so no estimator is judged
on the schedule it was tuned on. The simulator's interference is not the fitted basis: the
fluxgate that gives T-L its direction cosines carries the airframe's own field, the eddy
terms act on the continuous dB/dt at 50 Hz (T-L differences 10 Hz samples), and the streams
are sampled at other epochs; the sets below separate that model error from what noise adds.

* **T-L interference, held out.** Fit ``tl18`` on one calibration pass, predict the other
  pass's band-passed interference and compare with the truth. An *oracle* fit of the
  noiseless measurement (the Earth field the sensor sees as it manoeuvres over the ground's
  anomalies, plus the interference) with the same estimator and lambda on the same epochs
  gives the part no tl18 fit can get right on this flight; what noise adds is bounded by its
  expected size through the linear estimator (the held-out rows' prediction variance, with
  the band-passed noise variance inflated for its correlation: n_eff = 2 x 0.8 Hz / rate).
  Claim: the held-out error stays within the oracle's error plus 3x that noise term.
* **AGG-TL gradient.** Random regional gradients (|g| up to 0.5 nT/m) over quiet ground: the
  estimate is within 3 standard errors (inflated for the band's correlation) of the gradient
  the sensor sees: the regional one plus the main field's own (IGRF, ~0.005 nT/m north at
  the site; leaving it out biased every north estimate by 2-4 standard errors).
* **Vector parameters.** Random fluxgate scale, non-orthogonality and offset errors: the batch
  21-parameter fit against the simulator's truth: the calibrated magnitude matches the Earth
  field to 1.5x the fluxgate's noise, and each parameter block is held to the field error it
  makes (the reference field is uncertain by the attitude noise: see test_vector.py).

Measured (``-m slow``): see docs/science.md, "Recovery over seeds".
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pytest

from pipeline.compensate import FitSettings, Measurements, fit_compensation
from pipeline.compensate.estimator import bandpassed_design
from pipeline.compensate.model import tl_terms
from pipeline.compensate.stage import calibration_mask
from pipeline.io.reader import read_flight
from pipeline.segment import segment_flight
from pipeline.simulate import write_simulation
from tests.conftest import run_sim

CI_SEEDS = [101, 102, 103]
SLOW_SEEDS = list(range(200, 224))
BAND = (0.1, 0.9)


def _schedule(seed: int) -> list[str]:
    """Scenario overrides drawn from the seed: noise level and manoeuvre schedule."""
    rng = np.random.default_rng(seed)
    noise = float(rng.choice([0.02, 0.05, 0.1, 0.2]))
    return [
        "calibration.passes=2",
        f"sensors.scalar_noise_nT={noise}",
        "calibration.manoeuvre_order=random",
        "calibration.period_range_s=[4.0,9.0]",
        "calibration.amplitude_range_deg=[4.0,12.0]",
        "calibration.block_duration_s=[15.0,40.0]",
    ]


def _flight(seed: int, extra: list[str] | None = None):
    sim = run_sim("calibration-only", seed, _schedule(seed) + (extra or []))
    fl = read_flight(write_simulation(sim, Path(tempfile.mkdtemp()) / "c.mcap"))
    seg = segment_flight(fl)
    return sim, fl, seg


def heldout_interference(seed: int) -> dict[str, float]:
    """Fit tl18 on pass 1, predict pass 2: errors against the truth (band-passed, nT)."""
    sim, fl, seg = _flight(seed)
    meas = Measurements.from_flight(fl)
    cal = calibration_mask(fl, seg, "auto")
    passes = np.asarray(seg.calibration_pass)
    fit_mask, held_mask = cal & (passes == 1), cal & (passes == 2)
    assert fit_mask.sum() > 1000 and held_mask.sum() > 1000
    model = fit_compensation(meas, fit_mask, FitSettings("tl18", band_hz=BAND))
    k, _ = tl_terms("tl18", meas)
    idx = np.searchsorted(sim.series["time_ns"], fl.time_ns)
    truth = sim.series["interference_nT"][idx]

    def rows(y, mask):
        return bandpassed_design(k, y, meas.time_s, meas.rate_hz, mask, BAND, 4, 20)

    # the oracle: the same estimator and lambda on the noiseless measurement (Earth field as
    # the sensor crosses the ground's anomalies + interference); what it gets wrong on the
    # held-out pass is model error no noise level removes
    noise = sim.series["noise_nT"][idx]
    kf, yf, _ = rows(meas.scalar_nT - noise, fit_mask)
    _, nf, _ = rows(noise, fit_mask)
    kh, th, _ = rows(truth, held_mask)
    gram = kf.T @ kf + model.lambda_ * np.eye(k.shape[1])
    oracle = np.linalg.solve(gram, kf.T @ yf)
    err = float(np.sqrt(np.mean((kh @ model.coefficients - th) ** 2)))
    oracle_err = float(np.sqrt(np.mean((kh @ oracle - th) ** 2)))
    # what noise adds through the linear estimator: cov(theta) = s2 G^-1 K'K G^-1 with s2
    # the band-passed noise variance inflated for its correlation; the held-out prediction
    # variance averaged over the held-out rows
    ginv = np.linalg.inv(gram)
    cov = ginv @ (kf.T @ kf) @ ginv
    s2 = float(np.var(nf)) * meas.rate_hz / (2 * (BAND[1] - BAND[0]))
    noise_term = float(np.sqrt(s2 * np.mean(np.einsum("ij,jk,ik->i", kh, cov, kh))))
    return {
        "error_nT": err,
        "oracle_nT": oracle_err,
        "noise_nT": noise_term,
        "interference_nT": float(np.sqrt(np.mean(th**2))),
        "sensor_noise_nT": float(sim.truth["noise"]["scalar_nT"]),
    }


def gradient_z(seed: int) -> np.ndarray:
    """(estimate - truth) / standard error of AGG-TL's east and north gradient."""
    rng = np.random.default_rng(seed + 7)
    g = rng.uniform(-0.5, 0.5, 2)
    sim, fl, seg = _flight(
        seed,
        [
            "anomaly.dipoles=0",
            "effects.geomagnetic_gradient.enabled=true",
            f"effects.geomagnetic_gradient.east_nT_per_m={g[0]:.4f}",
            f"effects.geomagnetic_gradient.north_nT_per_m={g[1]:.4f}",
        ],
    )
    meas = Measurements.from_flight(fl)
    cal = calibration_mask(fl, seg, "auto")
    agg = fit_compensation(meas, cal, FitSettings("agg-tl", band_hz=BAND))
    est = agg.gradient_nT_per_m()
    sd = dict(zip(agg.terms, agg.coefficient_std, strict=True))
    inflation = np.sqrt(meas.rate_hz / (2 * (BAND[1] - BAND[0])))
    # the sensor sees the main field's own gradient too (IGRF: ~0.005 nT/m north here)
    true = np.asarray(sim.truth["effective"]["gradient_nT_per_m"][:2]) + _main_field_gradient(sim)
    return np.array(
        [
            (est["east"] - true[0]) / (sd["pos_e"] * inflation),
            (est["north"] - true[1]) / (sd["pos_n"] * inflation),
        ]
    )


def _main_field_gradient(sim) -> np.ndarray:
    """East and north gradient of the IGRF total field at the site, nT/m."""
    from datetime import UTC, datetime

    from pipeline.geo.igrf import main_field_gradient_nT_per_m

    site = sim.truth["site"]
    when = datetime.fromtimestamp(sim.truth["start_time_ns"] / 1e9, UTC)
    alt = float(site.get("ground_altitude_m", 0.0)) + 100.0
    return main_field_gradient_nT_per_m(
        float(site["latitude_deg"]), float(site["longitude_deg"]), alt, when
    )[:2]


def vector_field_errors_nT(seed: int) -> tuple[np.ndarray, float, float]:
    """The field error (nT) each recovered vector parameter block makes (permanent, induced
    at the flight's |T|, eddy at 2000 nT/s, as in test_vector.py); the RMS of the calibrated
    vector's magnitude minus the true Earth field over the flight (nT); the fluxgate's noise
    per axis (nT)."""
    from pipeline.vector.stage import component_truth, run_vector

    rng = np.random.default_rng(seed + 11)
    scale = rng.uniform(-0.03, 0.03, 3)
    nonorth = rng.uniform(-1.2, 1.2, 3)
    offset = rng.uniform(-200.0, 200.0, 3)
    vec = [
        "effects.vector_calibration.enabled=true",
        "effects.vector_calibration.scale_error=[{:.4f},{:.4f},{:.4f}]".format(*scale),
        "effects.vector_calibration.nonorthogonality_deg=[{:.3f},{:.3f},{:.3f}]".format(*nonorth),
        "effects.vector_calibration.offset_nT=[{:.1f},{:.1f},{:.1f}]".format(*offset),
    ]
    sim, fl, seg = _flight(seed, ["anomaly.dipoles=0", *vec])
    run = run_vector(fl, seg, "batch")
    tr = component_truth(sim.truth)
    est = run.parameters
    earth = sim.series["earth_total_nT"][np.searchsorted(sim.series["time_ns"], fl.time_ns)]
    t_mag = float(np.median(earth))
    blocks = np.array(
        [
            np.max(np.abs(np.asarray(est["permanent_nT"]) - tr.permanent_nT)),
            np.max(np.abs(np.asarray(est["induced"]) - tr.induced)) * t_mag,
            np.max(np.abs(np.asarray(est["eddy_s"]) - tr.eddy_s)) * 2000.0,
        ]
    )
    magnitude = float(np.sqrt(np.nanmean((np.linalg.norm(run.vectors_nT, axis=1) - earth) ** 2)))
    return blocks, magnitude, float(sim.truth["noise"]["vector_nT"])


# ------------------------------------------------------------------------------------------
def _check_heldout(results: list[dict[str, float]], min_fraction: float) -> None:
    ok = [r["error_nT"] <= r["oracle_nT"] + 3 * r["noise_nT"] for r in results]
    assert np.mean(ok) >= min_fraction, results
    # the fit is worth having on every flight: most of the true interference is removed
    assert all(r["error_nT"] < 0.1 * r["interference_nT"] for r in results), results


@pytest.mark.parametrize("seed", CI_SEEDS)
def test_tl_interference_heldout_within_model_error_plus_noise(seed):
    _check_heldout([heldout_interference(seed)], 1.0)


@pytest.mark.slow
def test_tl_interference_heldout_over_seeds():
    _check_heldout([heldout_interference(s) for s in SLOW_SEEDS], 0.9)


@pytest.mark.parametrize("seed", CI_SEEDS[:2])
def test_agg_tl_gradient_within_three_standard_errors(seed):
    assert np.all(np.abs(gradient_z(seed)) <= 3.0)


@pytest.mark.slow
def test_agg_tl_gradient_over_seeds():
    z = np.concatenate([gradient_z(s) for s in SLOW_SEEDS])
    # 3-sigma coverage >= 90 % of the 48 components; and no wild miss
    assert np.mean(np.abs(z) <= 3.0) >= 0.9, np.round(z, 2)
    assert np.max(np.abs(z)) <= 6.0, np.round(z, 2)


def _check_vector(results, min_fraction: float) -> None:
    blocks = np.array([r[0] for r in results])
    # the calibrated magnitude matches the Earth field to the fluxgate's own noise: the 21
    # parameters together are right (1.5 sigma leaves room for the reference's errors)
    assert all(mag <= 1.5 * noise for _, mag, noise in results), results
    # each block on its own: <= 10 nT of field error (the reference field's per-sample
    # uncertainty; permanent and induced trade off over a box's small attitude range)
    assert np.mean(np.all(blocks <= 10.0, axis=1)) >= min_fraction, np.round(blocks, 1)


@pytest.mark.parametrize("seed", CI_SEEDS[:1])
def test_vector_parameters_recovered(seed):
    _check_vector([vector_field_errors_nT(seed)], 1.0)


@pytest.mark.slow
def test_vector_parameters_over_seeds():
    _check_vector([vector_field_errors_nT(s) for s in SLOW_SEEDS], 0.9)
