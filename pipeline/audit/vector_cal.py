"""Scalar calibration of a vector magnetometer (fluxgate) against the scalar magnetometer.

The fluxgate's linear error model (see :mod:`pipeline.physics.vector_sensor`) is
m = S N b + o; the calibration inverts it as b = M (m - o) with M lower-triangular. Only the
magnitude of b is known (the compensated scalar field, the same Earth field to within the
sensors' separation), so the nine parameters are fitted by non-linear least squares on
| |M (m - o)| - B_ref |. Body frame throughout (x forward, y right, z down).

What is observable: the carrier's own field at the fluxgate (hard iron p_v, soft iron A_v)
is indistinguishable from sensor offset and scale, so the estimates are o + S N p_v and
S N (I + A_v). A prior towards M = I, o = 0 keeps the combinations
that level flight leaves unexcited (z scale vs z offset) from wandering; it is loose (5 %,
2000 nT), so it never competes with the data where they do say something.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

_TRIL = np.tril_indices(3)


@dataclass(frozen=True)
class VectorCalibration:
    """b = matrix @ (m - offset_nT): the calibrated body-frame field from the measured one."""

    matrix: tuple[tuple[float, ...], ...]
    offset_nT: tuple[float, float, float]
    residual_before_nT: float = float("nan")  # RMS of |m| - B_ref
    residual_after_nT: float = float("nan")  # RMS of |b| - B_ref
    samples: int = 0

    def apply(self, m_nT: np.ndarray) -> np.ndarray:
        """Calibrated body-frame field b = M (m - o), nT, for measured vectors ``m_nT`` (n, 3)."""
        return (np.asarray(m_nT, float) - np.asarray(self.offset_nT)) @ np.asarray(self.matrix).T

    def sensor_errors(self) -> dict[str, list[float]]:
        """The equivalent sensor errors: scale, non-orthogonality (deg), offset (nT)."""
        sn = np.linalg.inv(np.asarray(self.matrix))
        scale = np.linalg.norm(sn, axis=1) - 1.0
        n = sn / np.linalg.norm(sn, axis=1, keepdims=True)
        a1 = np.degrees(np.arcsin(np.clip(n[1, 0], -1, 1)))
        a2 = np.arcsin(np.clip(n[2, 0], -1, 1))
        a3 = np.degrees(np.arcsin(np.clip(n[2, 1] / max(np.cos(a2), 1e-12), -1, 1)))
        return {
            "scale_error": [float(v) for v in scale],
            "nonorthogonality_deg": [float(a1), float(np.degrees(a2)), float(a3)],
            "offset_nT": [float(v) for v in self.offset_nT],
        }

    def to_dict(self) -> dict:
        """JSON-ready: the equivalent sensor errors, the matrix, the residuals before and after (nT)
        and the samples fitted.
        """
        return {
            **self.sensor_errors(),
            "matrix": [list(r) for r in self.matrix],
            "residual_before_nT": self.residual_before_nT,
            "residual_after_nT": self.residual_after_nT,
            "samples": self.samples,
        }


def fit_vector_calibration(
    m_nT: np.ndarray,
    reference_nT: np.ndarray,
    prior_scale: float = 0.05,
    prior_offset_nT: float = 2000.0,
    fit_sigma_nT: float = 1.0,
    max_samples: int = 20_000,
) -> VectorCalibration:
    """Fit M (lower-triangular) and o so that |M (m - o)| matches ``reference_nT``.

    Parameters
    ----------
    m_nT : (n, 3) measured vectors, body frame, nT.
    reference_nT : (n,) field magnitude from the scalar magnetometer, nT.
    prior_scale, prior_offset_nT : one-sigma widths of the prior M = I, o = 0 (loose: they
        only pin the directions the data leave undetermined).
    fit_sigma_nT : the magnitude misfit the data are weighted by.
    max_samples : the fit uses at most this many evenly spaced samples.
    """
    m = np.asarray(m_nT, float)
    ref = np.asarray(reference_nT, float)
    ok = np.all(np.isfinite(m), axis=1) & np.isfinite(ref)
    m, ref = m[ok], ref[ok]
    if m.shape[0] < 50:
        raise ValueError(f"only {m.shape[0]} samples to calibrate the vector magnetometer")
    step = max(1, m.shape[0] // max_samples)
    ms, rs = m[::step], ref[::step]

    def unpack(x):
        mat = np.zeros((3, 3))
        mat[_TRIL] = x[:6]
        return mat, x[6:] * 100.0  # offsets in units of 100 nT: comparable steps

    eye = np.eye(3)[_TRIL]

    def residuals(x):
        mat, off = unpack(x)
        fit = (np.linalg.norm((ms - off) @ mat.T, axis=1) - rs) / fit_sigma_nT
        prior = np.r_[(x[:6] - eye) / prior_scale, x[6:] * 100.0 / prior_offset_nT]
        return np.r_[fit, prior]

    x0 = np.r_[eye, np.zeros(3)]
    sol = least_squares(
        residuals, x0, method="lm", x_scale=np.r_[np.full(6, 1e-3), np.full(3, 0.1)]
    )
    mat, off = unpack(sol.x)
    before = float(np.sqrt(np.mean((np.linalg.norm(m, axis=1) - ref) ** 2)))
    after = float(np.sqrt(np.mean((np.linalg.norm((m - off) @ mat.T, axis=1) - ref) ** 2)))
    return VectorCalibration(
        tuple(tuple(float(v) for v in r) for r in mat),
        (float(off[0]), float(off[1]), float(off[2])),
        before,
        after,
        int(ms.shape[0]),
    )
