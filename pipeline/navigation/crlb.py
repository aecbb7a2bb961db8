"""Posterior Cramér-Rao lower bound on the position error along the track.

For linear Gaussian dynamics and a measurement ``z = map(p) + b + v`` with Gaussian ``v``, the
posterior information obeys Tichavský et al.'s recursion (IEEE TSP 1998)
``J_k = (Q + Phi J_{k-1}^-1 Phi^T)^-1 + H_k^T R^-1 H_k``, with the Jacobian taken at the *true*
position (its expectation over the state replaced by the value on the true track, as MagNav.jl's
``crlb`` in ``src/ekf_&_crlb.jl`` does). In covariance form this is a Kalman covariance
recursion linearised on the truth, which is how it is computed here.
"""

from __future__ import annotations

import numpy as np

from pipeline.navigation.ekf import MeasurementModel, as_measurement
from pipeline.navigation.map_model import MapModel


def crlb(
    phi: np.ndarray,
    qd: np.ndarray,
    p0: np.ndarray,
    true_east_m: np.ndarray,
    true_north_m: np.ndarray,
    map_model: MapModel | MeasurementModel,
    r_nT2: float,
    update: np.ndarray | None = None,
    full_cov: bool = False,
) -> np.ndarray:
    """Lower bound on the (north, east) position error covariance, (N, 2, 2) m^2 (with
    ``full_cov``: the whole (N, n, n) covariance, in the model's states).

    ``update`` (N,) marks the epochs with a map measurement (default: where the true position
    is on the map). ``map_model``: the measurement's Jacobian at zero error on the true track
    (a bare map: ``h = map + b``). ``r_nT2``: the sensor's noise variance (nT^2); a
    :class:`MeasurementModel`'s map error variance on the true track is added.
    """
    meas = as_measurement(map_model)
    N, n = qd.shape
    on = meas.map_model.inside(true_east_m, true_north_m)
    allow = on if update is None else (np.asarray(update, bool) & on)
    rows = meas.jacobians_at(true_east_m, true_north_m, n)
    # the map's error variance on the true track joins the sensor's
    r = r_nT2 + np.broadcast_to(meas.map_var_nT2(true_east_m, true_north_m), (N,))
    P = np.array(p0, float)
    out = np.empty((N, n, n) if full_cov else (N, 2, 2))
    for k in range(N):
        if k:
            F = phi[k]
            P = F @ P @ F.T
            P[np.diag_indices(n)] += qd[k]
        if allow[k]:
            H = rows[k]
            PH = P @ H
            P = P - np.outer(PH, PH) / (float(H @ PH) + r[k])
            P = 0.5 * (P + P.T)
        out[k] = P if full_cov else P[:2, :2]
    return out


def crlb_final(
    phi: np.ndarray,
    qd: np.ndarray,
    p0: np.ndarray,
    true_east_m: np.ndarray,
    true_north_m: np.ndarray,
    meas: MapModel | MeasurementModel,
    r_nT2: float,
) -> np.ndarray:
    """The bound of :func:`crlb` at the last epoch of M tracks of the same shape at once,
    (M, 2, 2) m^2 (north, east): the same recursion, batched over the tracks (the
    navigability map's lines into every cell share their transitions).

    ``true_east_m``, ``true_north_m``: (M, N) map-frame positions; ``phi`` (N, n, n) and ``qd``
    (N, n) are shared. ``meas`` must not carry per-epoch arrays (a track's altitude above the
    map, core-field gradients): they belong to one track.
    """
    meas = as_measurement(meas)
    if meas.alt_above_map_m is not None or meas.core_grad is not None:
        raise ValueError("crlb_final: a measurement with per-epoch arrays is one track's")
    e, nn = np.asarray(true_east_m, float), np.asarray(true_north_m, float)
    M, N = e.shape
    n = qd.shape[1]
    on = meas.map_model.inside(e.ravel(), nn.ravel()).reshape(M, N)
    rows = meas.jacobians_at(e.ravel(), nn.ravel(), n).reshape(M, N, n)
    rows[~on] = 0.0  # no update off the map (and no NaN gradients in the batch)
    r = r_nT2 + np.broadcast_to(meas.map_var_nT2(e.ravel(), nn.ravel()), (M * N,)).reshape(M, N)
    P = np.array(np.broadcast_to(p0, (M, n, n)), float)
    diag = np.arange(n)
    for k in range(N):
        if k:
            P = phi[k] @ P @ phi[k].T
            P[:, diag, diag] += qd[k]
        if on[:, k].any():
            H = rows[:, k]
            PH = np.einsum("mij,mj->mi", P, H)
            s = np.einsum("mi,mi->m", H, PH) + r[:, k]
            gain = np.divide(1.0, s, out=np.zeros(M), where=on[:, k])
            P = P - gain[:, None, None] * PH[:, :, None] * PH[:, None, :]
            P = 0.5 * (P + P.transpose(0, 2, 1))
    return P[:, :2, :2]
