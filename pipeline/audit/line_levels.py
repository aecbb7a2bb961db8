"""Crossover differences under random line levels: the step scan's null model.

Every flown line carries a level error of its own (the unmodelled part of the carrier's
interference on that heading and attitude, the day's variation at that hour, a switched
load's state while the line was flown): that is what tie-line levelling removes. A
crossover difference ``d = e_a - e_b`` therefore holds the levels of its two lines beside
per-reading noise,

    d = X beta + Z a + eps,   a ~ N(0, rho sigma^2 I),   eps ~ N(0, sigma^2 I),

with ``Z`` the line incidence (+1 for line a, -1 for line b). Read as independent
readings, two lines' levels differing look like a step between them. Under this model a
change of level counts as a step only when the lines on each side share it beyond their
own scatter.

The variance ratio ``rho`` is profiled by maximum likelihood on a grid (rotated once into
the eigenbasis of ``Z Z^T``, so each grid value is a weighted least-squares solve).
A scan's statistic is the largest likelihood ratio over its candidate designs; its null
distribution comes from a parametric bootstrap of the fitted null model (the ratio
is free of ``sigma`` and ``beta``, so the draws need only ``rho``), the same scan on each
draw. statsmodels' ``MixedLM`` fits one grouping at a time, not the signed crossed
incidence of two lines per difference, hence this small dedicated fit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import orth

# rho = line-level variance / per-reading variance: 0, then 1e-2 .. 3e2 (levels from a
# hundredth of the reading noise to 17 times its size)
RHO_GRID = np.r_[0.0, np.logspace(-2.0, 2.5, 15)]
# candidates of :func:`scan_statistics` stacked into one batched SVD
BATCH = 128


def line_incidence(line_a: np.ndarray, line_b: np.ndarray) -> np.ndarray:
    """(n, lines) incidence ``Z``: +1 in line a's column, -1 in line b's."""
    names = sorted(set(map(str, line_a)) | set(map(str, line_b)))
    col = {k: i for i, k in enumerate(names)}
    z = np.zeros((len(line_a), len(names)))
    rows = np.arange(len(line_a))
    z[rows, [col[str(k)] for k in line_a]] += 1.0
    z[rows, [col[str(k)] for k in line_b]] -= 1.0
    return z


@dataclass
class LineLevelModel:
    """The eigenbasis of ``Z Z^T`` (``q``, eigenvalues ``lam``) and the rho grid."""

    q: np.ndarray
    lam: np.ndarray
    rho: np.ndarray

    @classmethod
    def of(cls, z: np.ndarray | None, n: int) -> LineLevelModel:
        """The model of incidence ``z`` (None: independent readings, rho = 0 only)."""
        if z is None or z.shape[1] == 0:
            return cls(np.eye(n), np.zeros(n), np.zeros(1))
        lam, q = np.linalg.eigh(z @ z.T)
        return cls(q, np.clip(lam, 0.0, None), RHO_GRID)

    def rotate(self, a: np.ndarray) -> np.ndarray:
        """``Q^T a``: rows into the eigenbasis."""
        return self.q.T @ a

    def scale(self) -> np.ndarray:
        """(grid, n) standard deviation of each rotated row per rho (sigma = 1)."""
        return np.sqrt(1.0 + self.rho[:, None] * self.lam[None, :])

    def loglik(self, rss: np.ndarray, n: int) -> np.ndarray:
        """Profile log-likelihood (sigma profiled out, constants dropped) per rho; ``rss``
        (grid, ...) the weighted residual sums of squares."""
        logdet = np.sum(np.log(self.scale() ** 2), axis=1)
        shape = (-1,) + (1,) * (rss.ndim - 1)
        return -0.5 * n * np.log(rss / n) - 0.5 * logdet.reshape(shape)


def _orth(a: np.ndarray) -> np.ndarray:
    """Orthonormal basis of ``a``'s column space (scipy's ``orth``; none for no columns)."""
    return orth(a, rcond=1e-10) if a.shape[1] else np.zeros((a.shape[0], 0))


def _explained(e: np.ndarray, qb: np.ndarray, res: np.ndarray) -> np.ndarray:
    """(m, draws) sum of squares of ``res`` (n, draws) each of the m stacked designs ``e``
    (m, n, k) takes beyond the orthonormal basis ``qb``: an orthonormal basis of its columns'
    part outside ``qb``'s span. Directions under 1e-10 of the candidate's own largest
    column are dropped: a candidate inside the null design's span adds nothing (relative to
    what is left after the projection, its rounding noise would pass for a direction)."""
    if e.shape[2] == 0:
        return np.zeros((e.shape[0], res.shape[1]))
    r = e - qb @ np.matmul(qb.T, e)
    u, sv, _ = np.linalg.svd(r, full_matrices=False)
    own = np.max(np.linalg.norm(e, axis=1), axis=1, keepdims=True)
    kept = sv > 1e-10 * own
    proj = np.matmul(np.swapaxes(u, 1, 2), res) * kept[:, :, None]
    return np.sum(proj**2, axis=1)


def scan_statistics(
    model: LineLevelModel, base: np.ndarray, extras: list[np.ndarray], y: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Likelihood ratios of each design ``[base, extra]`` against ``base``.

    Parameters
    ----------
    model : LineLevelModel
    base : ndarray
        (n, k0) design of the null model.
    extras : list of ndarray
        Each candidate's added columns (n, k_c).
    y : ndarray
        (n,) data or (n, draws).

    Returns
    -------
    lr : ndarray
        (candidates, draws) 2 x the profile log-likelihood gain.
    rho0 : ndarray
        (draws,) the null model's maximum-likelihood rho.
    rho1 : ndarray
        (candidates, draws) each candidate's rho.
    """
    y = y.reshape(y.shape[0], -1)
    n = y.shape[0]
    yr, br = model.rotate(y), model.rotate(base)
    er = [model.rotate(e) for e in extras]
    sd = model.scale()
    rss0 = np.empty((sd.shape[0], y.shape[1]))
    rss1 = np.empty((len(extras), sd.shape[0], y.shape[1]))
    # candidates with as many columns are stacked, BATCH at a time: one batched SVD per
    # batch and rho instead of one per candidate (a survey's scan has a candidate per gap
    # between readings, so all of them at once would grow with the readings squared)
    groups: dict[int, list[int]] = {}
    for c, e in enumerate(er):
        groups.setdefault(e.shape[1], []).append(c)
    batches = [cs[i : i + BATCH] for cs in groups.values() for i in range(0, len(cs), BATCH)]
    for g, s in enumerate(sd):
        yw, qb = yr / s[:, None], _orth(br / s[:, None])
        res = yw - qb @ (qb.T @ yw)
        rss0[g] = np.sum(res**2, axis=0)
        for cs in batches:
            e = np.stack([er[c] for c in cs]) / s[None, :, None]
            rss1[cs, g] = rss0[g] - _explained(e, qb, res)
    tiny = 1e-300
    l0 = model.loglik(np.maximum(rss0, tiny), n)
    l1 = model.loglik(np.maximum(rss1.transpose(1, 0, 2), tiny), n)  # (grid, cand, draws)
    lr = 2.0 * (l1.max(axis=0) - l0.max(axis=0)[None, :])
    return (
        np.maximum(lr, 0.0),
        model.rho[np.argmax(l0, axis=0)],
        model.rho[np.argmax(l1, axis=0)],
    )


def null_draws(model: LineLevelModel, rho0: float, draws: int, seed: int) -> np.ndarray:
    """(n, draws) data of the null model with ratio ``rho0`` (sigma 1, beta 0), seeded."""
    e = np.random.default_rng(seed).standard_normal((model.q.shape[0], draws))
    return model.q @ (np.sqrt(1.0 + rho0 * model.lam)[:, None] * e)


def gls_coefficients(model: LineLevelModel, a: np.ndarray, y: np.ndarray, rho: float):
    """Generalised least-squares coefficients of ``y`` on ``a`` at ratio ``rho``."""
    s = np.sqrt(1.0 + rho * model.lam)
    coef, *_ = np.linalg.lstsq(model.rotate(a) / s[:, None], model.rotate(y) / s, rcond=None)
    return coef
