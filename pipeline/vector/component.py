"""Vector (component) compensation of a fluxgate: the 21-parameter model of paper 000.

In the body frame (x forward, y right, z down), the measured field is

    T_m = T + T_p + A T + B dT/dt

with T the Earth field (a reference model rotated by the measured attitude), T_p the
permanent field, A (3x3) the induced and B (3x3) the eddy-current matrix. y = T_m - T is
linear in x = [T_p, A (row-major), B (row-major)]: y = H x with the 3 x 21 matrix
H = [s I, I (x) T', I (x) dT/dt'] (s = 1, or 1000 in the *scaled* form where the permanent
states are in uT: with s = 1 their columns are 5 orders smaller than the others and the
filter hardly moves them).

Estimators: :func:`batch_fit` (least squares over all samples, the honest baseline for
constant parameters) and :class:`ComponentKF` (constant-state Kalman filter, optionally with
the fuzzy-adaptive measurement noise of :mod:`pipeline.vector.fuzzy`). Units: nT, s.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pipeline.defaults import default_value
from pipeline.vector.fuzzy import RorFuzzy

N_STATES = 21
UT_SCALE = 1000.0  # nT per uT: the scaled permanent columns


@dataclass(frozen=True)
class ComponentParameters:
    """T_p (nT), A and B (3x3; B in s)."""

    permanent_nT: np.ndarray
    induced: np.ndarray
    eddy_s: np.ndarray

    @classmethod
    def from_state(cls, x: np.ndarray, scaled: bool) -> ComponentParameters:
        """Parameters from a 21-element state [T_p, A row-major, B row-major]; with ``scaled`` the
        state's T_p is in uT (converted to nT).
        """
        x = np.asarray(x, float)
        s = UT_SCALE if scaled else 1.0
        return cls(x[:3] * s, x[3:12].reshape(3, 3), x[12:21].reshape(3, 3))

    def state(self, scaled: bool) -> np.ndarray:
        """The 21-element state [T_p, A row-major, B row-major]; T_p in uT if ``scaled``."""
        s = UT_SCALE if scaled else 1.0
        return np.r_[
            np.asarray(self.permanent_nT) / s, np.ravel(self.induced), np.ravel(self.eddy_s)
        ]

    def predict(self, t_nT: np.ndarray, dt_nT_s: np.ndarray) -> np.ndarray:
        """The measured field this model predicts for Earth field T (n, 3)."""
        return (
            t_nT
            + self.permanent_nT
            + t_nT @ np.asarray(self.induced).T
            + dt_nT_s @ np.asarray(self.eddy_s).T
        )

    def compensate(self, m_nT: np.ndarray, dt_nT_s: np.ndarray) -> np.ndarray:
        """Invert the model: T = (I + A)^-1 (T_m - T_p - B dT/dt)."""
        rhs = m_nT - self.permanent_nT - dt_nT_s @ np.asarray(self.eddy_s).T
        return np.linalg.solve(np.eye(3) + np.asarray(self.induced), rhs.T).T

    def to_dict(self) -> dict:
        """JSON-ready: permanent field (nT, body frame), induced matrix and eddy matrix (s)."""
        return {
            "permanent_nT": [float(v) for v in self.permanent_nT],
            "induced": np.asarray(self.induced).tolist(),
            "eddy_s": np.asarray(self.eddy_s).tolist(),
        }


def design(t_nT: np.ndarray, dt_nT_s: np.ndarray, scaled: bool) -> np.ndarray:
    """H for every sample: (n, 3, 21)."""
    t, dt = np.asarray(t_nT, float), np.asarray(dt_nT_s, float)
    n = t.shape[0]
    h = np.zeros((n, 3, N_STATES))
    s = UT_SCALE if scaled else 1.0
    for i in range(3):
        h[:, i, i] = s
        h[:, i, 3 + 3 * i : 6 + 3 * i] = t
        h[:, i, 12 + 3 * i : 15 + 3 * i] = dt
    return h


def batch_fit(
    t_nT: np.ndarray, dt_nT_s: np.ndarray, m_nT: np.ndarray
) -> tuple[ComponentParameters, float, ComponentParameters]:
    """Least squares over all samples: the parameters, the residual RMS (nT) and the
    parameters' standard errors (from the residual variance, white noise assumed)."""
    h = design(t_nT, dt_nT_s, scaled=True).reshape(-1, N_STATES)
    y = (np.asarray(m_nT, float) - t_nT).reshape(-1)
    ok = np.isfinite(y) & np.all(np.isfinite(h), axis=1)
    col = np.sqrt(np.mean(h[ok] ** 2, axis=0))  # equilibrate the columns
    x, *_ = np.linalg.lstsq(h[ok] / col, y[ok], rcond=None)
    x = x / col
    r = y[ok] - h[ok] @ x
    sigma2 = float(r @ r) / max(r.size - N_STATES, 1)
    hs = h[ok] / col
    cov = sigma2 * np.linalg.pinv(hs.T @ hs) / np.outer(col, col)
    return (
        ComponentParameters.from_state(x, scaled=True),
        float(np.sqrt(np.mean(r**2))),
        ComponentParameters.from_state(np.sqrt(np.diag(cov)), scaled=True),
    )


@dataclass
class KFHistory:
    """What :meth:`ComponentKF.run` did at every sample (n samples).

    Attributes
    ----------
    states : ndarray, shape (n, 21)
        State after the sample's update (permanent block in uT when scaled).
    innovations : ndarray, shape (n, 3)
        y - H x before the update (nT).
    r_scale : ndarray, shape (n,)
        tr(R_k) / tr(R_0) used in the update.
    r_nT2 : ndarray, shape (n,)
        tr(R_k) / 3: the per-axis measurement variance used in the update (nT^2).
    ror : ndarray, shape (n,)
        tr(C_r) / tr(P_r), actual over predicted innovation covariance on the last
        ``window`` innovations (dimensionless); NaN without fuzzy R or where the sample is
        missing.
    min_eig : ndarray, shape (n,)
        Smallest eigenvalue of P after the update (every 50th sample and the last; NaN
        elsewhere).
    asym : ndarray, shape (n,)
        max |P - P'| before symmetrising.
    """

    states: np.ndarray
    innovations: np.ndarray
    r_scale: np.ndarray
    r_nT2: np.ndarray
    ror: np.ndarray
    min_eig: np.ndarray
    asym: np.ndarray


@dataclass
class ComponentKF:
    """Constant-state Kalman filter of the 21 parameters (paper 000).

    ``fuzzy``: adapt R each step by R_k = s_k^b R_(k-1), s_k from the Mamdani system on the
    ratio of actual to predicted innovation covariance (ROR) over the steps of the last
    ``window_s`` seconds (``sample_s``: the interval between the filtered samples, s; needed
    with fuzzy R), R_k / R_0 clamped to ``r_bounds``. ``window_s``, ``b`` and ``r_bounds``
    default to ``[vector] fuzzy_window_s``, ``fuzzy_exponent`` and ``fuzzy_r_bounds`` of the
    shipped configuration. The covariance update uses Joseph's form (symmetric positive definite by
    construction). ROR and R of every step are kept in ``history`` (:class:`KFHistory`).

    Units: x0 and the state in the model's units (permanent in uT when ``scaled``, else nT;
    A dimensionless; B in s), P0 and Q in the state's units squared, R in nT^2.
    """

    x0: np.ndarray
    p0: np.ndarray
    q: np.ndarray
    r: np.ndarray
    scaled: bool = True
    fuzzy: RorFuzzy | None = None
    window_s: float = field(
        default_factory=lambda: float(default_value("vector", "fuzzy_window_s"))
    )
    sample_s: float | None = None
    b: float = field(default_factory=lambda: float(default_value("vector", "fuzzy_exponent")))
    r_bounds: tuple[float, float] = field(  # R_k stays within these multiples of R_0
        default_factory=lambda: tuple(float(v) for v in default_value("vector", "fuzzy_r_bounds"))
    )
    history: KFHistory | None = field(default=None, repr=False)

    @classmethod
    def paper(cls, scaled: bool = True, fuzzy: bool = False) -> ComponentKF:
        """Paper 000's Table 1 settings: X0, P0 = 100 I, Q = 1e-5 I, R = 1e-3 I."""
        x0 = np.r_[np.zeros(3), np.full(9, 0.01), np.full(9, 0.02)]
        return cls(
            x0,
            100.0 * np.eye(N_STATES),
            1e-5 * np.eye(N_STATES),
            1e-3 * np.eye(3),
            scaled,
            RorFuzzy() if fuzzy else None,
        )

    def configure(self, vector: dict[str, Any]) -> ComponentKF:
        """Take the fuzzy-R settings of a ``[vector]`` configuration table (``fuzzy_window_s``,
        ``fuzzy_exponent``, ``fuzzy_r_bounds``, ``fuzzy_ror_*``, ``fuzzy_s_*``; missing keys
        keep their current values). Fuzzy R is switched on. Returns self."""
        if "fuzzy_window_s" in vector:
            self.window_s = float(vector["fuzzy_window_s"])
        if "fuzzy_exponent" in vector:
            self.b = float(vector["fuzzy_exponent"])
        if "fuzzy_r_bounds" in vector:
            lo, hi = (float(v) for v in vector["fuzzy_r_bounds"])
            self.r_bounds = (lo, hi)
        if not self.window_s > 0 or not 0.0 < self.r_bounds[0] <= 1.0 <= self.r_bounds[1]:
            raise ValueError(
                "vector.fuzzy_window_s > 0 and fuzzy_r_bounds = [lo <= 1, hi >= 1] with lo > 0"
            )
        self.fuzzy = RorFuzzy.from_values(vector)
        return self

    def window_steps(self) -> int:
        """Steps in ``window_s`` at the sample interval ``sample_s`` (nearest, at least one).

        Raises
        ------
        ValueError
            ``sample_s`` not set.
        """
        if self.sample_s is None or not self.sample_s > 0:
            raise ValueError("fuzzy R needs the sample interval (ComponentKF.sample_s, s)")
        return max(int(round(self.window_s / self.sample_s)), 1)

    def run(self, t_nT: np.ndarray, dt_nT_s: np.ndarray, m_nT: np.ndarray) -> ComponentParameters:
        """Filter the samples in order and return the final parameters.

        Parameters
        ----------
        t_nT : ndarray, shape (n, 3)
            Earth field T, body frame (x forward, y right, z down), nT.
        dt_nT_s : ndarray, shape (n, 3)
            Its time derivative dT/dt, body frame, nT/s.
        m_nT : ndarray, shape (n, 3)
            Measured field T_m, body frame, nT. Samples with a non-finite value get the time
            update only (state carried).

        Returns
        -------
        ComponentParameters
            The state after the last sample; every step is kept in ``history``.
        """
        h_all = design(t_nT, dt_nT_s, self.scaled)
        y_all = np.asarray(m_nT, float) - np.asarray(t_nT, float)
        n = y_all.shape[0]
        x, p, r = self.x0.astype(float).copy(), self.p0.astype(float).copy(), self.r.copy()
        eye = np.eye(N_STATES)
        states, innov = np.zeros((n, N_STATES)), np.zeros((n, 3))
        rs, mins, asym = np.ones(n), np.zeros(n), np.zeros(n)
        r_nt2, rors = np.full(n, np.trace(self.r) / 3.0), np.full(n, np.nan)
        recent: list[np.ndarray] = []
        r0 = np.trace(self.r)
        window = self.window_steps() if self.fuzzy is not None else 0
        for k in range(n):
            h, y = h_all[k], y_all[k]
            p = p + self.q
            if not np.all(np.isfinite(y)):
                states[k], rs[k], r_nt2[k] = x, np.trace(r) / r0, np.trace(r) / 3.0
                mins[k] = np.nan
                continue
            nu = y - h @ x
            if self.fuzzy is not None:
                recent.append(np.outer(nu, nu))
                if len(recent) > window:
                    recent.pop(0)
                c_r = np.mean(recent, axis=0)
                p_r = h @ p @ h.T + r
                ror = float(np.trace(c_r) / np.trace(p_r))
                rors[k] = ror
                r = self.fuzzy.scale(ror) ** self.b * r
                ratio = np.trace(r) / r0
                if not self.r_bounds[0] <= ratio <= self.r_bounds[1]:
                    r = r * (np.clip(ratio, *self.r_bounds) / ratio)
            s = h @ p @ h.T + r
            gain = np.linalg.solve(s, h @ p).T  # P H' S^-1 (S symmetric)
            x = x + gain @ nu
            ikh = eye - gain @ h
            p = ikh @ p @ ikh.T + gain @ r @ gain.T
            asym[k] = float(np.max(np.abs(p - p.T)))
            p = 0.5 * (p + p.T)
            states[k], innov[k], rs[k] = x, nu, np.trace(r) / r0
            r_nt2[k] = np.trace(r) / 3.0
            if k % 50 == 0 or k == n - 1:
                mins[k] = float(np.linalg.eigvalsh(p)[0])
            else:
                mins[k] = np.nan
        self.history = KFHistory(states, innov, rs, r_nt2, rors, mins, asym)
        return ComponentParameters.from_state(x, self.scaled)


def convergence_sample(states: np.ndarray, reference: np.ndarray, rel_tol: float = 0.02) -> int:
    """First sample from which the RMS relative error of the states (against ``reference``:
    the truth in a simulation, else the final estimate) stays within ``rel_tol``."""
    rel = np.sqrt(np.mean(((states - reference) / np.abs(reference)) ** 2, axis=1))
    idx = np.flatnonzero(rel > rel_tol)
    return int(idx[-1] + 1) if idx.size else 0
