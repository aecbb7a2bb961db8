"""Crustal anomaly sources: point dipoles with an analytic field.

B(r) = mu0/(4 pi) (3 (m.r^) r^ - m) / |r|^3; with mu0/(4 pi) = 1e-7 T m/A this is
100 nT m^3/(A m^2) x (3 (m.r^) r^ - m)/|r|^3 for m in A m^2 and r in metres.
Positions are local east/north/up metres; moments and fields are NED.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MU0_OVER_4PI_NT = 100.0  # nT m^3 / (A m^2)


@dataclass
class DipoleSource:
    """A point dipole at (east_m, north_m, up_m) with moment (north, east, down), A m^2."""

    east_m: float
    north_m: float
    up_m: float
    moment_ned_A_m2: tuple[float, float, float]


def dipole_field_ned_nT(sources: list[DipoleSource], east_m, north_m, up_m) -> np.ndarray:
    """Summed field of ``sources`` at observation points, (n, 3) NED, nT."""
    e = np.atleast_1d(np.asarray(east_m, float))
    n = np.atleast_1d(np.asarray(north_m, float))
    u = np.atleast_1d(np.asarray(up_m, float))
    out = np.zeros((e.size, 3))
    for s in sources:
        # separation in NED: north, east, down (down = -(up))
        r = np.stack([n - s.north_m, e - s.east_m, -(u - s.up_m)], axis=-1)
        dist = np.linalg.norm(r, axis=-1, keepdims=True)
        rhat = r / dist
        m = np.asarray(s.moment_ned_A_m2, float)
        out += MU0_OVER_4PI_NT * (3.0 * (rhat @ m)[:, None] * rhat - m) / dist**3
    return out


def total_field_anomaly_nT(b_anomaly_ned_nT: np.ndarray, b_main_ned_nT: np.ndarray) -> np.ndarray:
    """Exact total-field anomaly |B_main + b| - |B_main| (what a scalar survey maps), nT."""
    bm = np.asarray(b_main_ned_nT, float)
    return np.linalg.norm(bm + b_anomaly_ned_nT, axis=-1) - np.linalg.norm(bm, axis=-1)
