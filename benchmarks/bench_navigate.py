"""Speed of map-aided navigation: the EKF over one hour of 10 Hz data (issue 18's target
<= 10 s on 2 cores), with the INS model and the CRLB timed apart, and the particle filter.

    .venv/bin/python benchmarks/bench_navigate.py [--hours 1] [--rate 10] [--pf-seconds 300]

A navigation-grade INS flies a racetrack (60 m/s, 6 km legs) over a smooth random anomaly map
(16 km square, 50 m cells, 300 m correlation, 50 nT RMS) with a 0.1 nT magnetometer. Printed:
seconds for the transition matrices (the model), the INS simulation, the EKF, the CRLB and
the PF (1000 particles over ``--pf-seconds``), and the EKF's and CRLB's DRMS against the
truth. Exits non-zero when the EKF takes longer than 10 s per hour of 10 Hz data or its DRMS
is not below a fifth of the INS-only one.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
from report import finish

from pipeline.navigation.crlb import crlb
from pipeline.navigation.ekf import ekf
from pipeline.navigation.ins import GRADES, InsErrorModel, Trajectory, simulate_ins_errors
from pipeline.navigation.map_model import MapModel
from pipeline.navigation.pf import particle_filter
from pipeline.simulate.navigation import racetrack, random_field_map


def drms(err: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1))))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hours", type=float, default=1.0)
    ap.add_argument("--rate", type=float, default=10.0)
    ap.add_argument("--pf-seconds", type=float, default=300.0)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    mm = MapModel(random_field_map(1, size_m=16_000.0, cell_m=50.0, correlation_m=300.0))
    t, e, n = racetrack(a.hours * 3600.0, a.rate)
    traj = Trajectory.from_track(t, n, e, np.zeros_like(t), 45.0 + n / 111_000.0)
    model = InsErrorModel(GRADES["navigation"])
    sigma = 0.1
    z = mm.value(e, n) + np.random.default_rng(a.seed + 100).normal(0, sigma, t.size)
    clock = time.perf_counter()
    phi = model.transitions(traj)
    qd = model.process_noise(np.diff(t, prepend=t[0]))
    t_model = time.perf_counter() - clock
    clock = time.perf_counter()
    x = simulate_ins_errors(model, traj, a.seed, phi)
    t_ins = time.perf_counter() - clock
    p0 = model.initial_covariance()
    ins_e, ins_n = e + x[:, 1], n + x[:, 0]
    clock = time.perf_counter()
    res = ekf(phi, qd, p0, z, ins_e, ins_n, mm, sigma**2)
    t_ekf = time.perf_counter() - clock
    clock = time.perf_counter()
    bound = crlb(phi, qd, p0, e, n, mm, sigma**2)
    t_crlb = time.perf_counter() - clock
    k = int(a.pf_seconds * a.rate)
    clock = time.perf_counter()
    pf = particle_filter(
        phi[:k], qd[:k], p0, z[:k], ins_e[:k], ins_n[:k], mm, sigma**2, a.seed + 1, times_s=t[:k]
    )
    t_pf = time.perf_counter() - clock
    per_hour = (t_model + t_ekf) * 3600.0 / (t[-1] - t[0])
    ins_drms, ekf_drms = drms(x[:, :2]), drms(x[:, :2] - res.state[:, :2])
    rows = [
        ("epochs", f"{t.size} ({a.hours:g} h at {a.rate:g} Hz)"),
        ("INS model (transition matrices)", f"{t_model:.2f} s"),
        ("INS simulation", f"{t_ins:.2f} s"),
        ("EKF", f"{t_ekf:.2f} s"),
        ("EKF + model, per hour of data", f"{per_hour:.2f} s (target <= 10 s)"),
        ("CRLB", f"{t_crlb:.2f} s"),
        (f"PF, 1000 particles, {a.pf_seconds:g} s of data", f"{t_pf:.2f} s"),
        ("DRMS INS-only", f"{ins_drms:.1f} m"),
        ("DRMS EKF", f"{ekf_drms:.2f} m"),
        ("DRMS CRLB", f"{np.sqrt(np.mean(bound[:, 0, 0] + bound[:, 1, 1])):.2f} m"),
        ("DRMS PF (its span)", f"{drms(x[:k, :2] - pf.state[:, :2]):.2f} m"),
    ]
    errors = []
    if per_hour > 10.0:
        errors.append(f"EKF + model take {per_hour:.1f} s per hour of 10 Hz data (> 10 s)")
    if ekf_drms > ins_drms / 5:
        errors.append(f"EKF DRMS {ekf_drms:.1f} m is not below INS-only / 5")
    return finish(rows, errors)


if __name__ == "__main__":
    sys.exit(main())
