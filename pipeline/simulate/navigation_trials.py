"""Monte Carlo trials of map-aided navigation on a map with errors: is the filter no worse than
the INS alone, and is it consistent (NEES, NIS)?

A trial flies a racetrack over a smooth random anomaly field (the truth) with a simulated
INS (errors drawn from the covariance a GNSS-aided INS has at GNSS loss,
:func:`pipeline.navigation.alignment.gnss_aided_covariance`) and a magnetometer with white
noise and a slowly drifting bias (the filters' catch-all state, :func:`magnetometer_bias`).
The filter navigates on a *different* map: the truth plus a map error made of a smooth field
(the interpolation error between lines, correlated over a line spacing), white noise per cell
(gridding noise) and a constant (a levelling/datum offset), none of which the filter's model
generates. The filter is told the error's size (the map's 1 sigma, as ``/map/uncertainty``
would give it) or a fixed value (``told_map_sigma_nT``, as ``[navigate] map_sigma_nT``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter

from pipeline.maps.grid import Grid
from pipeline.navigation.alignment import gnss_aided_covariance
from pipeline.navigation.ekf import (
    MeasurementModel,
    correlated_error_scale,
    ekf,
    gate_sigma_of,
)
from pipeline.navigation.ins import GRADES, InsErrorModel, Trajectory, simulate_ins_errors
from pipeline.navigation.map_model import MapModel, wiener_smooth
from pipeline.simulate.navigation import racetrack, random_field_map


@dataclass
class Trial:
    """One trial's settings: seed, sensor noise and map error (nT, 1 sigma), the map error's
    split (smooth field, white noise per cell: fractions of its variance; the rest is the
    constant offset's), its correlation length (m), duration (s), rate (Hz), the map sigma the
    filter is told (None: the true one) and the innovation gate's probability (0: none)."""

    seed: int
    sensor_nT: float
    map_error_nT: float
    smooth_fraction: float = 0.5
    noise_fraction: float = 0.3
    correlation_m: float = 200.0
    duration_s: float = 1200.0
    rate_hz: float = 2.0
    told_map_sigma_nT: float | None = None
    gate_probability: float = 0.9999
    # the length the filter takes the map error to be correlated over (0: white)
    told_length_m: float = 200.0
    bias_prior: bool = True
    smooth_map: bool = True
    grade: str = "navigation"
    # the true anomaly field: correlation length (m) and RMS (nT) of the random field
    field_correlation_m: float = 300.0
    field_rms_nT: float = 50.0


def map_error_field(
    seed: int,
    grid: Grid,
    sigma_nT: float,
    smooth_fraction: float,
    noise_fraction: float,
    correlation_m: float,
) -> np.ndarray:
    """A map error of 1-sigma ``sigma_nT`` on ``grid``'s cells: a smooth random field (its
    ``smooth_fraction`` of the variance, Gaussian-correlated over ``correlation_m``), white
    noise per cell (``noise_fraction``) and one constant (the rest). ``correlation_m`` is the
    smooth field's integral scale along a line (the integral of its autocorrelation, what
    ``[navigate] map_error_length_m`` means): white noise smoothed by a Gaussian of standard
    deviation ``s`` has a Gaussian autocorrelation of standard deviation ``s sqrt(2)``, whose
    integral is ``2 sqrt(pi) s``."""
    rng = np.random.default_rng(seed)
    s_cells = correlation_m / (2.0 * np.sqrt(np.pi)) / grid.cell_m
    smooth = gaussian_filter(rng.standard_normal(grid.shape), s_cells)
    smooth *= np.sqrt(smooth_fraction) * sigma_nT / smooth.std()
    noise = rng.normal(0.0, np.sqrt(noise_fraction) * sigma_nT, grid.shape)
    offset = np.sqrt(max(1.0 - smooth_fraction - noise_fraction, 0.0)) * sigma_nT
    return smooth + noise + offset * rng.choice([-1.0, 1.0])


def magnetometer_bias(
    model: InsErrorModel, phi: np.ndarray, qd: np.ndarray, var0_nT2: float, seed: int
) -> np.ndarray:
    """One realisation (nT, per epoch) of the magnetometer's slowly varying bias, the
    first-order Gauss-Markov catch-all the filters carry (``mag_bias_nT`` over
    ``mag_bias_tau_s``; :meth:`InsErrorModel.process_noise`): initial variance ``var0_nT2``,
    then ``b_k = phi_k b_(k-1) + w_k`` with the filters' own transition and driving noise."""
    rng = np.random.default_rng(seed)
    w = rng.standard_normal(qd.shape[0]) * np.sqrt(qd[:, -1])
    b = np.empty(qd.shape[0])
    b[0] = np.sqrt(var0_nT2) * rng.standard_normal()
    for k in range(1, b.size):
        b[k] = phi[k, -1, -1] * b[k - 1] + w[k]
    return b


def run_trial(trial: Trial, truth: Grid | None = None) -> dict[str, float]:
    """One trial: DRMS (m) of the INS alone and map-aided, the CRLB-free filter's time-mean
    position NEES (2 dof) and NIS (1 dof), their per-epoch series (``nees``, ``nis``: NaN
    where no update) and the gate's rejections."""
    tr = trial
    if truth is None:
        truth = random_field_map(
            1000 + tr.seed,
            size_m=16_000.0,
            correlation_m=tr.field_correlation_m,
            rms_nT=tr.field_rms_nT,
        )
    err = map_error_field(
        tr.seed, truth, tr.map_error_nT, tr.smooth_fraction, tr.noise_fraction, tr.correlation_m
    )
    true_map = MapModel(truth)
    told = tr.map_error_nT if tr.told_map_sigma_nT is None else tr.told_map_sigma_nT
    used_map = MapModel(truth.with_values(truth.values + err))
    left = 1.0
    if tr.smooth_map:
        smooth, _, left = wiener_smooth(used_map.grid, told)
        used_map = MapModel(smooth)
    t, e, n = racetrack(tr.duration_s, tr.rate_hz)
    traj = Trajectory.from_track(t, n, e, np.zeros_like(t), 45.0 + n / 111_000.0)
    model = InsErrorModel(GRADES[tr.grade])
    phi = model.transitions(traj)
    qd = model.process_noise(np.diff(t, prepend=t[0]))
    # the covariance at GNSS loss: an aided run over the first 300 s of the same track
    k = int(300.0 * tr.rate_hz)
    head = Trajectory(
        traj.time_s[:k],
        traj.lat_rad[:k],
        traj.vel_ned_mps[:k],
        traj.force_ned_mps2[:k],
        traj.c_nb[:k],
    )
    p0 = gnss_aided_covariance(model, head, 3.0)
    bias = magnetometer_bias(model, phi, qd, p0[-1, -1], 20_000 + tr.seed)
    p0[-1, -1] += told**2 if tr.bias_prior else 0.0
    x = simulate_ins_errors(model, traj, tr.seed, phi, p0=p0)
    rng = np.random.default_rng(10_000 + tr.seed)
    z = true_map.value(e, n) + bias + rng.normal(0.0, tr.sensor_nT, t.size)
    step = 60.0 / tr.rate_hz  # racetrack speed (m/s) over the rate
    scale = correlated_error_scale(tr.told_length_m, step)
    meas = MeasurementModel(used_map, map_sigma_nT=told, map_var_scale=scale, map_var_left=left)
    gate = gate_sigma_of(tr.gate_probability) if tr.gate_probability > 0 else None
    res = ekf(phi, qd, p0, z, e + x[:, 1], n + x[:, 0], meas, tr.sensor_nT**2, gate_sigma=gate)
    aided = x[:, :2] - res.state[:, :2]
    nees = np.einsum("ki,kij,kj->k", aided, np.linalg.inv(res.pos_cov_m2), aided)
    nis = res.innovation_nT**2 / res.innovation_var_nT2

    def drms(a):
        return float(np.sqrt(np.mean(np.sum(a**2, axis=1))))

    return {
        "seed": tr.seed,
        "sensor_nT": tr.sensor_nT,
        "map_error_nT": tr.map_error_nT,
        "told_map_sigma_nT": told,
        "ins_only_m": drms(x[:, :2]),
        "map_aided_m": drms(aided),
        "nees_mean": float(np.mean(nees)),
        "nis_mean": float(np.nanmean(nis)),
        "rejected": int(res.rejected),
        "updates": int(res.updated.sum()),
        "nees": nees,
        "nis": nis,
    }
