"""The simulations of papers 000 and 003, as reusable generators (tests and benchmarks).

Frames: body x forward, y right, z down; the Earth field is given in NED and rotated into the
body frame by the attitude (Z-Y-X Euler angles, :mod:`pipeline.geo.frames`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.geo.frames import ned_to_body
from pipeline.vector.component import ComponentParameters

# paper 000, Table 1
PAPER_000 = ComponentParameters(
    np.array([40.0, -100.0, 120.0]),
    np.array([[0.065, 0.1, 0.26], [0.02, 0.5, 0.28], [0.2, 0.26, 0.16]]),
    np.array([[0.1, 0.32, 0.22], [0.13, 0.16, 0.61], [0.16, 0.17, 0.02]]),
)

# a mid-latitude main field (NED, nT): |T| about 52 000 nT, inclination 50 deg
EARTH_NED_NT = np.array([33_000.0, -3_000.0, 40_000.0])


@dataclass
class ComponentFlight:
    """A simulated carrier for component compensation (paper 000).

    Attributes
    ----------
    time_s : ndarray
        Sample times, s.
    earth_nT, earth_rate_nT_s : ndarray, shape (n, 3)
        Earth field T (nT) and dT/dt (nT/s), body frame (x forward, y right, z down).
    measured_nT : ndarray, shape (n, 3)
        Measured T_m with noise, nT.
    noise_nT : ndarray
        Per-sample noise standard deviation, nT.
    truth : ComponentParameters
    """

    time_s: np.ndarray
    earth_nT: np.ndarray  # T, body frame
    earth_rate_nT_s: np.ndarray  # dT/dt, body frame
    measured_nT: np.ndarray  # T_m with noise
    noise_nT: np.ndarray  # per-sample noise sigma (constant or time-varying)
    truth: ComponentParameters


def rotating_carrier(
    n: int = 10_000,
    rate_hz: float = 10.0,
    noise_nT: float | np.ndarray = 5.0,
    params: ComponentParameters = PAPER_000,
    seed: int = 0,
) -> ComponentFlight:
    """A carrier turning steadily in heading while pitching and rolling at other periods
    (a single fixed rotation axis would make dT/dt = w x T, i.e. B indistinguishable from A).
    """
    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate_hz
    yaw = np.degrees(2 * np.pi * t / 97.0)
    pitch = 35.0 * np.sin(2 * np.pi * t / 61.0)
    roll = 50.0 * np.sin(2 * np.pi * t / 37.0 + 0.7)

    def field(tt):
        y = np.degrees(2 * np.pi * tt / 97.0)
        p = 35.0 * np.sin(2 * np.pi * tt / 61.0)
        r = 50.0 * np.sin(2 * np.pi * tt / 37.0 + 0.7)
        return ned_to_body(np.tile(EARTH_NED_NT, (tt.size, 1)), r, p, y)

    earth = ned_to_body(np.tile(EARTH_NED_NT, (n, 1)), roll, pitch, yaw)
    h = 1e-3
    rate = (field(t + h) - field(t - h)) / (2 * h)
    sigma = np.broadcast_to(np.asarray(noise_nT, float), (n,)).copy()
    meas = params.predict(earth, rate) + rng.normal(size=(n, 3)) * sigma[:, None]
    return ComponentFlight(t, earth, rate, meas, sigma, params)


# --------------------------------------------------------------------------------------------
# paper 003: a spinning carrier
GAUSS_NT = 1e5
PAPER_003_FIELD_G = 0.5267


@dataclass
class SpinFlight:
    """Paper 003's spinning carrier (:func:`spinning_carrier`); fields in gauss (G).

    Attributes
    ----------
    time_s : ndarray
    roll_deg, pitch_deg : ndarray
        Spin angle about body x and pitch, deg.
    field_body_G : ndarray, shape (n, 3)
        True field, body frame (x forward, y right, z down).
    measured_G : ndarray, shape (n, 3)
        soft_iron @ true + hard_iron + noise.
    hard_iron_G : ndarray, shape (3,)
    soft_iron : ndarray, shape (3, 3)
    field_ned_G : ndarray, shape (3,)
        The field in NED.
    """

    time_s: np.ndarray
    roll_deg: np.ndarray  # spin angle about body x
    pitch_deg: np.ndarray
    field_body_G: np.ndarray  # true field, body frame
    measured_G: np.ndarray  # with hard and soft iron and noise
    hard_iron_G: np.ndarray
    soft_iron: np.ndarray  # measured = soft_iron @ true + hard_iron
    field_ned_G: np.ndarray


def spinning_carrier(
    rate_hz: float = 500.0,
    duration_s: float = 5.0,
    spin_rev_s: float = 5.0,
    pitch_from_deg: float = 45.0,
    pitch_to_deg: float = -45.0,
    field_G: float = PAPER_003_FIELD_G,
    noise_G: float = 0.0005,
    hard_iron_G=(0.06, -0.035, 0.045),
    soft_iron=((1.06, 0.025, -0.015), (0.025, 0.95, 0.02), (-0.015, 0.02, 1.03)),
    seed: int = 0,
    t0_s: float = 0.0,
) -> SpinFlight:
    """Paper 003's simulation: spin 5 rev/s about the body x axis while the pitch runs
    linearly from +45 to -45 deg over 5 s; |H| = 0.5267 G; white noise 0.0005 G per axis.
    Hard/soft iron are ours (the paper does not list them): tens of mG and a few percent.
    """
    rng = np.random.default_rng(seed)
    t = t0_s + np.arange(int(round(duration_s * rate_hz))) / rate_hz
    frac = (t - t0_s) / duration_s
    pitch = pitch_from_deg + (pitch_to_deg - pitch_from_deg) * frac
    roll = np.degrees(2 * np.pi * spin_rev_s * t) % 360.0
    incl = np.radians(50.0)
    ned = field_G * np.array([np.cos(incl), 0.0, np.sin(incl)])
    body = ned_to_body(np.tile(ned, (t.size, 1)), roll, pitch, np.zeros(t.size))
    hard, soft = np.asarray(hard_iron_G, float), np.asarray(soft_iron, float)
    meas = body @ soft.T + hard + rng.normal(0.0, noise_G, body.shape)
    return SpinFlight(t, roll, pitch, body, meas, hard, soft, ned)
