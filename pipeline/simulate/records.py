"""A scalar magnetometer's along-line record with known parts: geology-like anomalies, manoeuvre
interference, a current step and white noise (the despiking and noise-estimation test bed).
"""

from __future__ import annotations

import numpy as np

RECORD_NOISE_NT = 0.05  # nT, the record's white noise by default
RECORD_RATE_HZ = 10.0


def record(
    seed: int, n: int = 36_000, noise_nT: float = RECORD_NOISE_NT, rate_hz: float = RECORD_RATE_HZ
) -> tuple[np.ndarray, np.ndarray]:
    """``n`` samples at ``rate_hz`` (by default one hour at 10 Hz) flown at 30 m/s: 40
    dipole-like anomalies (20-400 m wide, ~50 nT), manoeuvre interference (0.08-0.5 Hz, up
    to 10 nT, modulated), a 2 nT current step at 1200 s, white noise of ``noise_nT``.

    Returns
    -------
    (time s, field nT)
    """
    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate_hz
    s = 30.0 * t
    geo = np.zeros(n)
    for _ in range(40):
        c, w, a = rng.uniform(0, s[-1]), rng.uniform(20, 400), rng.normal(0, 50)
        geo += a / (1 + ((s - c) / w) ** 2) ** 1.5
    man = np.zeros(n)
    for f, a in ((0.08, 10.0), (0.2, 8.0), (0.33, 5.0), (0.5, 3.0)):
        man += a * np.sin(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi))
    man *= 1 + 0.5 * np.sin(2 * np.pi * t / 300)
    step = np.where(t > 1200, 2.0, 0.0)
    return t, 50_000 + geo + man + step + rng.normal(0, noise_nT, n)
