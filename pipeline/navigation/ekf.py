"""Extended Kalman filter on the INS error states with the map as measurement.

The measurement is the compensated anomaly ``z`` (IGRF and diurnal removed as for the map)
against the map at the position the INS indicates corrected by the filter's estimate,
``h(x) = map(p_ins - dp) + b`` (``b`` the magnetometer/map bias state), with the map's
altitude term and the core field's change when given (:class:`MeasurementModel`); the
Jacobian is the map gradient: ``H = [-dmap/dN, -dmap/dE, -dmap/dup, 0 ... 0, 1]``. MagNav.jl's
``ekf`` in ``src/ekf_&_crlb.jl`` has the same structure (it linearises on latitude/longitude
radians) and reproduces its test numbers (``tests/test_magnav_peer.py``).
The covariance update is Joseph's form and symmetrised each step, which keeps it symmetric
positive definite in floating point.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.navigation.map_model import MapModel


@dataclass
class FilterResult:
    """Output of a navigation filter over N epochs.

    Attributes
    ----------
    state : (N, n) estimated error states (indicated minus true; see ``ins.STATE_NAMES``)
    pos_cov_m2 : (N, 2, 2) covariance of the (north, east) position error, m^2
    innovation_nT : (N,) measurement minus prediction (NaN where no update)
    innovation_var_nT2 : (N,) its predicted variance
    updated : (N,) bool, a map measurement was used
    min_eigenvalue : smallest eigenvalue of the covariance over the run (SPD check)
    max_asymmetry : largest |P - P^T| over the run
    handover_epoch : epoch at which a particle filter handed over to the EKF (None: never)
    rejected : map measurements refused by the innovation gate
    cov : (N, n, n) the full covariance after each epoch (``ekf(..., full_cov=True)``)
    """

    state: np.ndarray
    pos_cov_m2: np.ndarray
    innovation_nT: np.ndarray
    innovation_var_nT2: np.ndarray
    updated: np.ndarray
    min_eigenvalue: float
    max_asymmetry: float
    handover_epoch: int | None = None  # particle filter -> EKF (see pf.particle_filter)
    rejected: int = 0  # measurements refused by the innovation gate
    cov: np.ndarray | None = None  # (N, n, n) full covariance, when asked for


@dataclass
class MeasurementModel:
    """The magnetic measurement ``h(x)`` and its Jacobian ``H`` of the filters and the CRLB.

    ``h(x) = map(p_ins - dp) + dmap/dup (alt_ins - dalt - map_alt) + core(p_ins - dp) + b``
    with ``x`` the error states (indicated minus true; ``dp`` the north/east position error in
    metres, ``dalt`` the altitude error, ``b`` the bias state). MagNav's ``get_h`` / ``get_H``
    with ``der_mapS`` and ``core=true``; ``H`` is the whole Jacobian of that ``h``, with the
    altitude term's derivatives (MagNav's ``get_H`` leaves them out when the map is 2-D).

    Parameters
    ----------
    map_model : MapModel
        The anomaly map (its frame: east/north of :class:`~pipeline.maps.grid.Grid`).
    map_scale : (N, 2) ndarray or None
        Map-frame units per metre of (north, east) position error at each epoch (None: 1, a
        map in local metres; a map in latitude/longitude radians: ``1/R``, ``1/(R cos lat)``).
    vertical : MapModel or None
        The map's vertical derivative, d/d up, nT/m (None: no altitude term).
    alt_above_map_m : (N,) ndarray or None
        The INS-indicated altitude minus the map's, m (with ``vertical``).
    core_grad : (N, 3) ndarray or None
        Gradient of the core field's total intensity (IGRF) at the INS-indicated position, d/d
        (north, east, up), nT/m, when the measurement is the total field rather than the
        anomaly (None: anomaly). Its value at the indicated position is either in ``core_nT``
        or already subtracted from the measurement (``aeromag navigate`` reduces the total
        field with the IGRF at the indicated position, as the map was reduced); the field at
        the estimated position is that value plus the gradient times the correction (the IGRF
        curves over hundreds of km: the second-order term is below 0.01 nT for a 1 km error).
    core_nT : (N,) ndarray or None
        The core field's total intensity at the indicated position, nT (None: subtracted).
    """

    map_model: MapModel
    map_scale: np.ndarray | None = None
    vertical: MapModel | None = None
    alt_above_map_m: np.ndarray | None = None
    core_grad: np.ndarray | None = None
    core_nT: np.ndarray | None = None

    def evaluate(self, k: int, x: np.ndarray, east: float, north: float):
        """``h(x)`` (NaN off the map) and ``H`` (n,) at epoch ``k`` for the indicated position
        ``east``, ``north`` in the map's frame."""
        sn, se = (1.0, 1.0) if self.map_scale is None else self.map_scale[k]
        e, n = east - x[1] * se, north - x[0] * sn
        m, ge, gn = self.map_model.at(e, n)
        H = np.zeros(x.size)
        H[0], H[1], H[-1] = -gn * sn, -ge * se, 1.0
        h = m + x[-1]
        if self.vertical is not None and self.alt_above_map_m is not None:
            dv, dve, dvn = self.vertical.at(e, n)
            if np.isfinite(dv):
                dz = self.alt_above_map_m[k] - x[2]
                h += dv * dz
                H[0] -= dvn * sn * dz
                H[1] -= dve * se * dz
                H[2] -= dv
        if self.core_grad is not None:
            g = self.core_grad[k]
            h -= g[0] * x[0] + g[1] * x[1] + g[2] * x[2]
            H[:3] -= g
            if self.core_nT is not None:
                h += self.core_nT[k]
        return h, H

    def jacobians_at(self, east: np.ndarray, north: np.ndarray, n: int) -> np.ndarray:
        """``H`` (N, n) at zero error for every epoch at once (the CRLB's rows on the true
        track): the same rows as :meth:`evaluate`, vectorised."""
        N = np.size(east)
        sn, se = (np.ones(N), np.ones(N)) if self.map_scale is None else self.map_scale.T
        _, ge, gn = self.map_model.value_and_gradient(east, north)
        H = np.zeros((N, n))
        H[:, 0], H[:, 1], H[:, -1] = -gn * sn, -ge * se, 1.0
        if self.vertical is not None and self.alt_above_map_m is not None:
            dv, dve, dvn = self.vertical.value_and_gradient(east, north)
            ok = np.isfinite(dv)
            dz = np.asarray(self.alt_above_map_m, float)
            H[ok, 0] -= (dvn * sn * dz)[ok]
            H[ok, 1] -= (dve * se * dz)[ok]
            H[ok, 2] -= dv[ok]
        if self.core_grad is not None:
            H[:, :3] -= self.core_grad
        return H


def as_measurement(map_model: MapModel | MeasurementModel) -> MeasurementModel:
    """A :class:`MeasurementModel` (a bare map: the anomaly of the map alone)."""
    return map_model if isinstance(map_model, MeasurementModel) else MeasurementModel(map_model)


def ekf(
    phi: np.ndarray,
    qd: np.ndarray,
    p0: np.ndarray,
    z_nT: np.ndarray,
    ins_east_m: np.ndarray,
    ins_north_m: np.ndarray,
    map_model: MapModel | MeasurementModel,
    r_nT2: float,
    update: np.ndarray | None = None,
    x0: np.ndarray | None = None,
    check_every: int = 100,
    gate_sigma: float | None = None,
    full_cov: bool = False,
) -> FilterResult:
    """Run the EKF.

    Parameters
    ----------
    phi : (N, n, n) transition matrices (``phi[k]``: epoch k-1 -> k)
    qd : (N, n) diagonal discrete process noise
    p0 : (n, n) initial covariance
    z_nT : (N,) measured anomaly, nT
    ins_east_m, ins_north_m : (N,) INS-indicated position in the map's frame
    map_model : MapModel or MeasurementModel (a bare map: ``h = map + b``)
    r_nT2 : measurement noise variance (sensor plus map), nT^2
    update : (N,) bool, epochs allowed to use the map (default: all)
    x0 : (n,) initial state (default zero)
    check_every : the covariance's eigenvalues are checked every this many epochs
    gate_sigma : innovations beyond this many predicted sigmas are rejected (None, the
        default: none are). Measured on the demo flight's validation lines: a 5-sigma gate
        changes nothing for the navigation grade (0-1 rejections in 6071 updates) and stops the
        tactical grade's re-acquisition after the dead-reckoned turn (DRMS 110 -> 1335 m and
        50 -> 567 m on seeds 1 and 2), so it is off unless asked for.
    full_cov : keep the full (N, n, n) covariance in ``FilterResult.cov`` (default: only the
        position block)
    """
    meas = as_measurement(map_model)
    N, n = qd.shape
    x = np.zeros(n) if x0 is None else np.array(x0, float)
    P = np.array(p0, float)
    out_x = np.empty((N, n))
    out_p = np.empty((N, 2, 2))
    cov = np.empty((N, n, n)) if full_cov else None
    innov = np.full(N, np.nan)
    svar = np.full(N, np.nan)
    used = np.zeros(N, bool)
    allow = np.ones(N, bool) if update is None else np.asarray(update, bool)
    z = np.asarray(z_nT, float)
    eye = np.eye(n)
    min_eig, max_asym = np.inf, 0.0
    rejected = 0
    for k in range(N):
        if k:
            F = phi[k]
            x = F @ x
            P = F @ P @ F.T
            P[np.diag_indices(n)] += qd[k]
        if allow[k] and np.isfinite(z[k]):
            m, H = meas.evaluate(k, x, ins_east_m[k], ins_north_m[k])
            if np.isfinite(m):
                PH = P @ H
                s = float(H @ PH) + r_nT2
                K = PH / s
                r = z[k] - m
                if gate_sigma is not None and r * r > gate_sigma**2 * s:
                    rejected += 1
                    m = np.nan
            if np.isfinite(m):
                x = x + K * r
                A = eye - np.outer(K, H)
                P = A @ P @ A.T + np.outer(K, K) * r_nT2
                innov[k], svar[k], used[k] = r, s, True
        max_asym = max(max_asym, float(np.abs(P - P.T).max()))
        P = 0.5 * (P + P.T)
        if k % check_every == 0:
            min_eig = min(min_eig, float(np.linalg.eigvalsh(P)[0]))
        out_x[k] = x
        out_p[k] = P[:2, :2]
        if cov is not None:
            cov[k] = P
    return FilterResult(
        out_x, out_p, innov, svar, used, min_eig, max_asym, rejected=rejected, cov=cov
    )
