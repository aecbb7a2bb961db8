"""Ridge regression through the SVD, and the L-curve choice of the ridge parameter.

theta = (K'K + lambda I)^-1 K'y = V diag(s / (s^2 + lambda)) U'y. The SVD is computed once, so
the whole L-curve (residual norm vs solution norm over lambda) costs almost nothing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class LCurve:
    """Residual and solution norms over a lambda grid, and the chosen corner."""

    lambdas: np.ndarray
    residual_norm: np.ndarray
    solution_norm: np.ndarray
    curvature: np.ndarray
    corner: int

    @property
    def lambda_corner(self) -> float:
        """The lambda at the L-curve corner."""
        return float(self.lambdas[self.corner])


class RidgeSVD:
    """Ridge solutions of one least-squares problem for any lambda."""

    def __init__(self, k: np.ndarray, y: np.ndarray):
        self.u, self.s, self.vt = np.linalg.svd(np.asarray(k, float), full_matrices=False)
        y = np.asarray(y, float)
        self.beta = self.u.T @ y
        self.outside2 = max(float(y @ y - self.beta @ self.beta), 0.0)  # part K cannot reach

    @classmethod
    def from_gram(cls, k: np.ndarray, y: np.ndarray) -> RidgeSVD:
        """The same solutions from the normal equations' eigendecomposition (p x p) instead
        of an SVD of the rows: many times faster for tall designs (held-out folds fit
        hundreds), at the cost of squaring the condition number (fine below ~1e7).
        :meth:`solve_for` is not available (no left singular vectors)."""
        k, y = np.asarray(k, float), np.asarray(y, float)
        w, v = np.linalg.eigh(k.T @ k)
        order = np.argsort(w)[::-1]
        w, v = w[order], v[:, order]
        keep = w > max(w[0], 0.0) * 1e-15  # rounding noise of a singular K'K is not signal
        self = cls.__new__(cls)
        self.u = None
        self.s = np.sqrt(w[keep])
        self.vt = v[:, keep].T
        self.beta = (self.vt @ (k.T @ y)) / self.s
        self.outside2 = max(float(y @ y - self.beta @ self.beta), 0.0)
        return self

    def solve(self, lam: float) -> np.ndarray:
        """The ridge solution theta = (K'K + lam I)^-1 K'y for ``lam``."""
        return self.vt.T @ (self.s / (self.s**2 + lam) * self.beta)

    def solve_for(self, y: np.ndarray, lam: float) -> np.ndarray:
        """The ridge solution for another right-hand side (n,) or several (n, m) with the
        same matrix."""
        uy = self.u.T @ np.asarray(y, float)
        f = self.s / (self.s**2 + lam)
        return self.vt.T @ (f[:, None] * uy if uy.ndim == 2 else f * uy)

    def norms(self, lam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residual norm |K theta - y| and solution norm |theta| of the ridge solution for each
        lambda of ``lam`` (two arrays of its length).
        """
        lam = np.asarray(lam, float)[:, None]
        s2 = self.s**2
        res = np.sqrt(np.sum((lam / (s2 + lam) * self.beta) ** 2, axis=1) + self.outside2)
        sol = np.sqrt(np.sum((self.s / (s2 + lam) * self.beta) ** 2, axis=1))
        return res, sol

    def lcurve(self, n: int = 400) -> LCurve:
        """Maximum curvature of (log residual norm, log solution norm) over log lambda.

        The grid spans two decades below the smallest squared singular value to one above
        the largest; the corner is searched away from the grid's ends.
        """
        s2 = self.s[self.s > 0] ** 2
        lams = np.logspace(np.log10(s2.min()) - 2, np.log10(s2.max()) + 1, n)
        res, sol = self.norms(lams)
        x, y, t = np.log(res), np.log(sol), np.log(lams)
        dx, dy = np.gradient(x, t), np.gradient(y, t)
        ddx, ddy = np.gradient(dx, t), np.gradient(dy, t)
        kappa = (dx * ddy - dy * ddx) / np.maximum((dx**2 + dy**2) ** 1.5, 1e-300)
        edge = max(n // 50, 2)
        corner = edge + int(np.argmax(kappa[edge:-edge]))
        return LCurve(lams, res, sol, kappa, corner)


def ridge_solve(k: np.ndarray, y: np.ndarray, lam: float) -> np.ndarray:
    """The ridge solution theta = (K'K + lam I)^-1 K'y (one lambda; :class:`RidgeSVD` for many)."""
    return RidgeSVD(k, y).solve(lam)
