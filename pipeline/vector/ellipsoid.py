"""Ellipsoid calibration of a vector magnetometer, batch and online (paper 003).

Hard iron (a fixed field o) and soft iron (a matrix S, measured = S b + o) turn the sphere of
true field vectors into an ellipsoid: a x^2 + b y^2 + c z^2 + d xy + e xz + g yz + l x + m y +
n z + p = 0. The trivial solution (all zero) is removed by fixing p = -1, valid whenever the
hard iron is smaller than the field (the origin lies inside the ellipsoid); then
h(m) theta = 1 with h = [x^2, y^2, z^2, xy, xz, yz, x, y, z] and theta the other nine
coefficients over -p. The calibration b = W (m - o) follows from the quadric: centre
o = -A^-1 v / 2, and W = |H| sqrt(A / k) (symmetric root; k = 1 + o' A o), so |b| = |H|. A
symmetric soft-iron matrix is recovered exactly; any rotation in S is not observable from
magnitudes. Body frame throughout (x forward, y right, z down).

Online: a Kalman filter on theta (constant state, h(m_k) as the measurement row, measurement
1, noise from the sensor noise: f = |b|^2/|H|^2 - 1 varies by about 2 sigma / |H|),
initialised either naively (the sphere |m| = |H|, large covariance) or from a prior batch
fit of earlier data with its covariance ("prior calibration" of the paper).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import sqrtm


def quadric_rows(m: np.ndarray) -> np.ndarray:
    """Measurement rows h(m) = [x^2, y^2, z^2, xy, xz, yz, x, y, z], one per row of ``m`` (n, 3)."""
    m = np.asarray(m, float)
    x, y, z = m[:, 0], m[:, 1], m[:, 2]
    return np.column_stack([x * x, y * y, z * z, x * y, x * z, y * z, x, y, z])


@dataclass(frozen=True)
class Ellipsoid:
    """Quadric coefficients (p = -1) and the field magnitude they are scaled to."""

    theta: np.ndarray
    field: float
    covariance: np.ndarray | None = None

    @property
    def matrix(self) -> np.ndarray:
        """The symmetric 3x3 matrix A of the quadric's quadratic part."""
        a, b, c, d, e, g = self.theta[:6]
        return np.array([[a, d / 2, e / 2], [d / 2, b, g / 2], [e / 2, g / 2, c]])

    @property
    def centre(self) -> np.ndarray:
        """Hard iron o (same unit as the measurements)."""
        return -0.5 * np.linalg.solve(self.matrix, self.theta[6:9])

    @property
    def soft_iron_inverse(self) -> np.ndarray:
        """W with b = W (m - o), |b| = field (symmetric)."""
        o = self.centre
        k = 1.0 + o @ self.matrix @ o
        w = np.real(sqrtm(self.matrix / k)) * self.field
        return 0.5 * (w + w.T)

    def valid(self) -> bool:
        """Whether A is positive definite (the quadric is an ellipsoid)."""
        try:
            return bool(np.all(np.linalg.eigvalsh(self.matrix) > 0))
        except np.linalg.LinAlgError:
            return False

    def calibrate(self, m: np.ndarray) -> np.ndarray:
        """Calibrated vectors b = W (m - o) for measured vectors ``m`` (n, 3), body frame, in the
        measurements' unit (|b| close to ``field``).
        """
        return (np.asarray(m, float) - self.centre) @ self.soft_iron_inverse.T

    def to_dict(self) -> dict:
        """JSON-ready: hard iron (centre), soft-iron inverse W, field magnitude and theta."""
        return {
            "hard_iron": [float(v) for v in self.centre],
            "soft_iron_inverse": self.soft_iron_inverse.tolist(),
            "field": self.field,
            "theta": [float(v) for v in self.theta],
        }


def fit_ellipsoid(m: np.ndarray, field: float, noise: float | None = None) -> Ellipsoid:
    """Batch least-squares fit of the quadric (p = -1) with its coefficient covariance.

    ``noise``: per-axis sensor noise (same unit as ``m``); default from the fit residual.
    """
    m = np.asarray(m, float)
    m = m[np.all(np.isfinite(m), axis=1)]
    if m.shape[0] < 20:
        raise ValueError(f"only {m.shape[0]} vectors for an ellipsoid fit")
    d = quadric_rows(m)
    theta, *_ = np.linalg.lstsq(d, np.ones(m.shape[0]), rcond=None)
    r = d @ theta - 1.0
    var = (2.0 * noise / field) ** 2 if noise else float(np.mean(r**2))
    cov = var * np.linalg.pinv(d.T @ d)
    return Ellipsoid(theta, float(field), 0.5 * (cov + cov.T))


def sphere(field: float) -> Ellipsoid:
    """The naive start: |m| = field, no hard or soft iron."""
    return Ellipsoid(np.r_[np.full(3, 1.0 / field**2), np.zeros(6)], float(field))


@dataclass
class EllipsoidKF:
    """Online quadric estimation (constant state; process noise ``q`` per step, relative)."""

    start: Ellipsoid
    p0: np.ndarray
    noise: float  # per-axis sensor noise, measurement unit
    q_rel: float = 0.0
    theta: np.ndarray = field(init=False)
    p: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.theta = np.asarray(self.start.theta, float).copy()
        self.p = np.asarray(self.p0, float).copy()

    @classmethod
    def naive(cls, field: float, noise: float, sigma_rel: float = 1.0) -> EllipsoidKF:
        """Sphere start with a covariance of ``sigma_rel`` x each coefficient's natural size
        (1/field^2 for the quadratic, 1/field for the linear terms)."""
        scale = np.r_[np.full(6, 1.0 / field**2), np.full(3, 1.0 / field)]
        return cls(sphere(field), np.diag((sigma_rel * scale) ** 2), noise)

    @classmethod
    def from_prior(cls, prior: Ellipsoid, noise: float, inflate: float = 1000.0) -> EllipsoidKF:
        """Start at a prior batch fit with its covariance inflated ``inflate`` times: the
        prior then weighs like a handful of samples, so it sets the starting point without
        holding the filter back when the carrier has changed since (with 10x, a prior whose
        hard iron was 8 mG off took 3.78 s to converge instead of 0.05 s in paper 003's
        simulation, each sample scored with the state before its update)."""
        return cls(prior, inflate * prior.covariance, noise)

    def run(self, m: np.ndarray, update: np.ndarray | None = None) -> np.ndarray:
        """Filter every vector; returns the state after each sample (n, 9).

        ``update`` (bool per sample): measurement updates only where true; elsewhere the
        state is carried (a straight survey line says nothing about an ellipsoid).

        The state each sample met *before* its own update is kept in ``states_before``
        (n, 9): score a filter with those (:func:`magnitude_error`), since a state already
        updated on a sample fits that sample by construction.
        """
        rows = quadric_rows(m)
        upd = np.ones(rows.shape[0], bool) if update is None else np.asarray(update, bool)
        r = (2.0 * self.noise / self.start.field) ** 2
        q = np.diag((self.q_rel * np.abs(self.theta)) ** 2) if self.q_rel else None
        out = np.zeros((rows.shape[0], 9))
        self.states_before = np.zeros((rows.shape[0], 9))
        for k, h in enumerate(rows):
            self.states_before[k] = self.theta
            if q is not None:
                self.p = self.p + q
            if upd[k] and np.all(np.isfinite(h)):
                ph = self.p @ h
                s = h @ ph + r
                g = ph / s
                self.theta = self.theta + g * (1.0 - h @ self.theta)
                ikh = np.eye(9) - np.outer(g, h)
                self.p = ikh @ self.p @ ikh.T + r * np.outer(g, g)
                self.p = 0.5 * (self.p + self.p.T)
            out[k] = self.theta
        self.min_eig = float(np.linalg.eigvalsh(self.p)[0])
        return out

    def ellipsoid(self) -> Ellipsoid:
        """The current state as an :class:`Ellipsoid`, with the filter's covariance."""
        return Ellipsoid(self.theta.copy(), self.start.field, self.p.copy())


def magnitude_error(states: np.ndarray, m: np.ndarray, field: float) -> np.ndarray:
    """|b_k| - field, each sample m_k calibrated by ``states[k]``, in m's unit.

    For an honest online score pass the states *before* each sample's update
    (:attr:`EllipsoidKF.states_before`): the state after the update has already fitted m_k
    (with a tight prior it "converges" at the first sample).
    """
    out = np.full(m.shape[0], np.nan)
    for k in range(m.shape[0]):
        e = Ellipsoid(states[k], field)
        if e.valid():
            out[k] = np.linalg.norm(e.calibrate(m[k : k + 1])) - field
    return out


def convergence_time(
    time_s: np.ndarray, error: np.ndarray, threshold: float, hold_s: float
) -> float | None:
    """Online convergence detection: the first time from which the error (e.g. the running
    RMS of the magnitude error) stays below ``threshold`` for ``hold_s`` and never again
    exceeds it. None if it never settles."""
    bad = ~(np.abs(error) <= threshold)
    idx = np.flatnonzero(bad)
    k = 0 if idx.size == 0 else idx[-1] + 1
    if k >= time_s.size or time_s[-1] - time_s[k] < hold_s:
        return None
    return float(time_s[k] - time_s[0])


def running_rms(x: np.ndarray, n: int) -> np.ndarray:
    """RMS over the last ``n`` samples (NaN treated as a large error)."""
    x2 = np.where(np.isfinite(x), x * x, 1e30)
    c = np.r_[0.0, np.cumsum(x2)]
    k = np.arange(1, x.size + 1)
    lo = np.maximum(k - n, 0)
    return np.sqrt((c[k] - c[lo]) / (k - lo))


def roll_from_radial(b_body: np.ndarray, b_unrolled: np.ndarray) -> np.ndarray:
    """Spin (roll) angle, deg, from the radial components (y, z) of the body-frame field.

    ``b_unrolled`` is the same field in the frame that has yaw and pitch but no roll (from
    the reference field and the other attitude angles); rolling by phi rotates its (y, z)
    components by -phi.
    """
    a = np.degrees(
        np.arctan2(b_unrolled[..., 2], b_unrolled[..., 1])
        - np.arctan2(b_body[..., 2], b_body[..., 1])
    )
    return np.mod(a, 360.0)


def angle_error_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle differences a - b, deg, wrapped to [-180, 180)."""
    return (np.asarray(a) - np.asarray(b) + 180.0) % 360.0 - 180.0
