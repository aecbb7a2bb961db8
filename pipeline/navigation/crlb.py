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
