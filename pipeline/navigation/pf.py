"""Marginalised (Rao-Blackwellised) particle filter for large initial position errors.

Particles carry the two horizontal position errors (the only states the map measurement is
non-linear in); every other error state is linear and Gaussian given a particle's path and is
estimated by a Kalman filter per particle (Schön, Gustafsson & Nordlund, "Marginalized particle
filters for mixed linear/nonlinear state-space models", IEEE TSP 2005; MagNav.jl's ``mpf`` in
``src/mpf.jl`` follows the same paper). Because the linear part's measurement row (the bias
state) and its dynamics do not depend on the particle, all particles share one Kalman
covariance and differ only in their means: the cost per epoch is one 16-state Riccati step
plus vectorised per-particle means.

Resampling is systematic when the effective sample size drops below half the particles. It is
not regularised: a kernel jitter scaled to the cloud (Musso et al. 2001, even with Liu & West's
shrinkage) blurred away what earlier epochs had learnt whenever the likelihood is a narrow
ridge along a map contour, and the cloud diffused (tried; the estimate walked hundreds of metres
away from the importance-sampling posterior in a few epochs). Diversity comes from a floor on
the position process noise instead.
"""

from __future__ import annotations

import numpy as np

from pipeline.navigation.ekf import FilterResult, MeasurementModel, as_measurement
from pipeline.navigation.map_model import MapModel

# Floor on the position process noise, m^2 per second of flight: the INS model's own is ~0
# (position errors only integrate velocity errors), which leaves resampled particles no
# diversity; the cloud then collapses onto one particle whose velocity error is wrong and
# walks away. Too large a floor swamps what the particles' motion tells the Kalman part about
# the velocity errors, and the cloud lags the INS drift. Measured (benchmarks/bench_navigate.py
# map, 1000 particles, 500 m initial sigma, 4 seeds; demo flight validation lines, seed 0):
# 1e-3: 3 of 4 lost; 1e-2: 2 of 4 lost; 0.1: 3 of 4 recover to ~2 m, demo 4.7 m DRMS;
# 1.0: 4 of 4 recover (one to 23 m) but demo 25 m DRMS (CRLB 2.3 m).
POSITION_DIFFUSION_M2_PER_S = 0.1


def _systematic(weights: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    n = weights.size
    u = (rng.random() + np.arange(n)) / n
    idx = np.searchsorted(np.cumsum(weights), u)
    return np.minimum(idx, n - 1)


def particle_filter(
    phi: np.ndarray,
    qd: np.ndarray,
    p0: np.ndarray,
    z_nT: np.ndarray,
    ins_east_m: np.ndarray,
    ins_north_m: np.ndarray,
    map_model: MapModel | MeasurementModel,
    r_nT2: float,
    seed: int,
    particles: int = 1000,
    update: np.ndarray | None = None,
    times_s: np.ndarray | None = None,
    handover_m: float | None = None,
    handover_s: float = 10.0,
) -> FilterResult:
    """Run the marginalised particle filter (arguments as :func:`pipeline.navigation.ekf.ekf`;
    ``seed`` seeds the particles, ``times_s`` (N,) the epochs, default 10 Hz).

    The reported position covariance is the weighted particle spread; the state is the
    weighted mean of the particles (position) and of their Kalman means (the rest). The
    measurement is the map and the bias (a :class:`MeasurementModel`'s altitude and core terms
    are not used); each particle's likelihood takes the map's error variance at its own
    position, the shared Kalman covariance the particles' weighted mean of it.

    ``handover_m``: once the cloud's DRMS has stayed below this for ``handover_s`` of map
    updates, the particles' mean and full covariance (spread of the positions and of the
    Kalman means, plus the shared Kalman covariance) start the EKF, which runs the rest: the
    particle filter finds the position from a large initial error, the EKF then tracks it
    without the particles' position diffusion (``FilterResult.handover_epoch``).
    """
    meas = as_measurement(map_model)
    rng = np.random.default_rng(seed)
    N, n = qd.shape
    nl = n - 2
    xn = rng.multivariate_normal(np.zeros(2), p0[:2, :2], size=particles)
    xl = np.zeros((particles, nl))
    Pl = np.array(p0[2:, 2:], float)
    logw = np.zeros(particles)
    allow = np.ones(N, bool) if update is None else np.asarray(update, bool)
    z = np.asarray(z_nT, float)
    dt = np.diff(times_s, prepend=times_s[0]) if times_s is not None else np.full(N, 0.1)
    out_x = np.empty((N, n))
    out_p = np.empty((N, 2, 2))
    innov = np.full(N, np.nan)
    svar = np.full(N, np.nan)
    used = np.zeros(N, bool)
    min_eig, max_asym = np.inf, 0.0
    settled = 0
    step_s = float(np.median(dt[1:])) if N > 1 else 0.1
    for k in range(N):
        if k:  # time update k-1 -> k
            F = phi[k]
            An, Anl, Aln, Al = F[:2, :2], F[:2, 2:], F[2:, :2], F[2:, 2:]
            qn = np.maximum(qd[k, :2], POSITION_DIFFUSION_M2_PER_S * dt[k])
            ql = qd[k, 2:]
            mean_n = xn @ An.T + xl @ Anl.T
            Nn = Anl @ Pl @ Anl.T + np.diag(qn)
            Nn = 0.5 * (Nn + Nn.T)
            L = Al @ Pl @ Anl.T @ np.linalg.inv(Nn)
            new_n = mean_n + rng.standard_normal((particles, 2)) @ np.linalg.cholesky(Nn).T
            xl = xl @ Al.T + xn @ Aln.T + (new_n - mean_n) @ L.T
            xn = new_n
            Pl = Al @ Pl @ Al.T - L @ Nn @ L.T
            Pl[np.diag_indices(nl)] += ql
            Pl = 0.5 * (Pl + Pl.T)
        if allow[k] and np.isfinite(z[k]):
            J = meas.jacobian_ned(k)
            pe = ins_east_m[k] - xn[:, 0] * J[0, 0] - xn[:, 1] * J[0, 1]
            pn = ins_north_m[k] - xn[:, 0] * J[1, 0] - xn[:, 1] * J[1, 1]
            m, gx, gy = meas.map_model.value_and_gradient(pe, pn)
            on = np.isfinite(m)
            if on.mean() > 0.5:
                wn = np.exp(logw - logw.max())
                r_i = r_nT2 + meas.map_var_nT2(pe, pn)
                s = Pl[-1, -1] + float(np.average(r_i[on], weights=wn[on] + 1e-300))
                y = np.where(on, z[k] - m - xl[:, -1], 0.0)
                # A particle stands for its share of the cloud, a patch of covariance ~ 4 C / n
                # (C the cloud's covariance, n particles); the map varies across that patch by
                # the gradient times its size, which is added to the particle's likelihood
                # variance (the likelihood averaged over the patch, to first order). Without it
                # a wide cloud on a sharp map collapses onto the few particles that happen to
                # sit on the measured contour, usually the wrong ones; as the cloud shrinks the
                # term vanishes and the exact marginalised likelihood remains.
                cloud = np.cov(xn.T, aweights=wn) * 4.0 / particles
                gx, gy = np.nan_to_num(gx), np.nan_to_num(gy)
                g = np.stack([gx * J[0, 0] + gy * J[1, 0], gx * J[0, 1] + gy * J[1, 1]], axis=1)
                s_i = Pl[-1, -1] + r_i + np.einsum("pi,ij,pj->p", g, cloud, g)
                logw = logw - 0.5 * y * y / s_i - 0.5 * np.log(s_i)
                logw[~on] = -np.inf
                K = Pl[:, -1] / s
                xl = xl + np.outer(y, K)
                Pl = Pl - np.outer(K, K) * s
                Pl = 0.5 * (Pl + Pl.T)
                w = np.exp(logw - logw.max())
                w /= w.sum()
                innov[k] = float(w @ y)
                svar[k] = s
                used[k] = True
                if 1.0 / float(w @ w) < particles / 2:
                    idx = _systematic(w, rng)
                    xn = xn[idx]
                    xl = xl[idx]
                    logw = np.zeros(particles)
        w = np.exp(logw - logw.max())
        w /= w.sum()
        mn = w @ xn
        d = xn - mn
        out_x[k, :2] = mn
        out_x[k, 2:] = w @ xl
        out_p[k] = (d * w[:, None]).T @ d
        if handover_m is not None:
            settled = settled + 1 if used[k] and np.trace(out_p[k]) < handover_m**2 else 0
            if settled * step_s >= handover_s and k < N - 1:
                return _hand_over(
                    k,
                    w,
                    xn,
                    xl,
                    Pl,
                    out_x,
                    out_p,
                    innov,
                    svar,
                    used,
                    min_eig,
                    max_asym,
                    (phi, qd, z, ins_east_m, ins_north_m, meas, r_nT2, allow),
                )
        if k % 100 == 0:
            min_eig = min(min_eig, float(np.linalg.eigvalsh(Pl)[0]))
            max_asym = max(max_asym, float(np.abs(Pl - Pl.T).max()))
    return FilterResult(out_x, out_p, innov, svar, used, min_eig, max_asym)


def _hand_over(k, w, xn, xl, Pl, out_x, out_p, innov, svar, used, min_eig, max_asym, rest):
    """Continue with the EKF from epoch ``k``'s particle posterior (see ``handover_m``)."""
    from pipeline.navigation.ekf import ekf

    phi, qd, z, ins_e, ins_n, map_model, r_nT2, allow = rest
    full = np.hstack([xn, xl])
    mean = w @ full
    d = full - mean
    P = (d * w[:, None]).T @ d
    P[2:, 2:] += Pl
    P = 0.5 * (P + P.T)
    later = allow[k:].copy()
    later[0] = False  # epoch k's measurement is already in the particles
    tail = ekf(
        phi[k:], qd[k:], P, z[k:], ins_e[k:], ins_n[k:], map_model.from_epoch(k), r_nT2, later, mean
    )
    out_x[k:] = tail.state
    out_p[k:] = tail.pos_cov_m2
    innov[k + 1 :] = tail.innovation_nT[1:]
    svar[k + 1 :] = tail.innovation_var_nT2[1:]
    used[k + 1 :] = tail.updated[1:]
    res = FilterResult(
        out_x,
        out_p,
        innov,
        svar,
        used,
        min(min_eig, tail.min_eigenvalue),
        max(max_asym, tail.max_asymmetry),
        rejected=tail.rejected,
    )
    res.handover_epoch = int(k)
    return res
