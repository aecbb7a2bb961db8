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

from dataclasses import dataclass, replace

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
    innovation_var_nT2 : (N,) its predicted variance (the map's error variance not inflated,
        ``MeasurementModel.map_var_scale``: the spread of one innovation)
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
    ned_to_map : (N, 2, 2) ndarray or None
        Map-frame metres (east, north rows) per metre of (north, east) NED position error
        (columns) at each epoch: a projected map's grid axes are turned from true north by the
        meridian convergence (degrees at a UTM zone's edge) and scaled by the projection. It
        replaces ``map_scale`` when given.
    sigma : MapModel or None
        The map's own 1-sigma error per cell, nT (``/map/uncertainty``, bilinear), read at the
        estimated position; None: ``map_sigma_nT`` everywhere.
    map_sigma_nT : float
        The map's 1-sigma error where no ``sigma`` grid is given, nT.
    map_var_scale : float
        The map's error variance is multiplied by this (>= 1, :func:`correlated_error_scale`):
        the map's error is correlated along the track, and measurements that share it are not
        the independent ones the filter takes them for.
    map_var_left : float
        The share (0-1] of the map's error variance left in the map the filter uses (a Wiener
        filter having taken out its white noise,
        :func:`pipeline.navigation.map_model.wiener_smooth`).

    The measurement's noise variance is the filters' ``r_nT2`` (the sensor's) plus the map's
    (:meth:`map_var_nT2`): the map's error at the estimated position is as random to the filter
    as the sensor's noise.
    """

    map_model: MapModel
    map_scale: np.ndarray | None = None
    vertical: MapModel | None = None
    alt_above_map_m: np.ndarray | None = None
    core_grad: np.ndarray | None = None
    core_nT: np.ndarray | None = None
    ned_to_map: np.ndarray | None = None
    sigma: MapModel | None = None
    map_sigma_nT: float = 0.0
    map_var_scale: float = 1.0
    map_var_left: float = 1.0

    def jacobian_ned(self, k: int | None = None) -> np.ndarray:
        """Map-frame (east, north) metres per (north, east) metre of NED position error:
        (2, 2) at epoch ``k``, or (N, 2, 2) for every epoch (``k`` None; N from ``map_scale``
        or ``ned_to_map``, else one shared (1, 2, 2))."""
        if self.ned_to_map is not None:
            return self.ned_to_map if k is None else self.ned_to_map[k]
        if self.map_scale is None:
            j = np.array([[[0.0, 1.0], [1.0, 0.0]]])
        else:
            sc = np.asarray(self.map_scale, float)
            j = np.zeros((sc.shape[0], 2, 2))
            j[:, 0, 1], j[:, 1, 0] = sc[:, 1], sc[:, 0]
        return j if k is None else j[min(k, j.shape[0] - 1)]

    def estimated_position(self, k: int, x: np.ndarray, east: float, north: float):
        """The position (map frame, m) the INS indicates at ``east``, ``north`` corrected by
        the error states ``x`` (indicated minus true, NED)."""
        J = self.jacobian_ned(k)
        return east - J[0, 0] * x[0] - J[0, 1] * x[1], north - J[1, 0] * x[0] - J[1, 1] * x[1]

    def map_var_nT2(self, east, north) -> np.ndarray:
        """The map's error variance (nT^2) at map-frame positions: the ``sigma`` grid's where
        it has a value (its largest value elsewhere), else ``map_sigma_nT`` squared."""
        k = self.map_var_scale * self.map_var_left
        if self.sigma is None:
            return np.full(np.shape(east), k * self.map_sigma_nT**2)
        s = self.sigma.value(east, north)
        return k * np.where(np.isfinite(s), s, self._sigma_max) ** 2

    @property
    def _sigma_max(self) -> float:
        v = self.sigma.grid.values
        return float(np.nanmax(v)) if np.isfinite(v).any() else self.map_sigma_nT

    def from_epoch(self, k: int) -> MeasurementModel:
        """The model of epochs ``k:`` (its per-epoch arrays sliced), for a filter started at
        epoch ``k``."""

        def cut(a):
            return None if a is None else a[k:]

        return replace(
            self,
            map_scale=cut(self.map_scale),
            alt_above_map_m=cut(self.alt_above_map_m),
            core_grad=cut(self.core_grad),
            core_nT=cut(self.core_nT),
            ned_to_map=cut(self.ned_to_map),
        )

    def evaluate(self, k: int, x: np.ndarray, east: float, north: float):
        """``h(x)`` (NaN off the map) and ``H`` (n,) at epoch ``k`` for the indicated position
        ``east``, ``north`` in the map's frame."""
        J = self.jacobian_ned(k)
        e, n = self.estimated_position(k, x, east, north)
        m, ge, gn = self.map_model.at(e, n)
        H = np.zeros(x.size)
        H[0] = -(ge * J[0, 0] + gn * J[1, 0])
        H[1] = -(ge * J[0, 1] + gn * J[1, 1])
        H[-1] = 1.0
        h = m + x[-1]
        if self.vertical is not None and self.alt_above_map_m is not None:
            dv, dve, dvn = self.vertical.at(e, n)
            if np.isfinite(dv):
                dz = self.alt_above_map_m[k] - x[2]
                h += dv * dz
                H[0] -= (dve * J[0, 0] + dvn * J[1, 0]) * dz
                H[1] -= (dve * J[0, 1] + dvn * J[1, 1]) * dz
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
        J = np.broadcast_to(self.jacobian_ned(), (N, 2, 2))
        _, ge, gn = self.map_model.value_and_gradient(east, north)
        H = np.zeros((N, n))
        H[:, 0] = -(ge * J[:, 0, 0] + gn * J[:, 1, 0])
        H[:, 1] = -(ge * J[:, 0, 1] + gn * J[:, 1, 1])
        H[:, -1] = 1.0
        if self.vertical is not None and self.alt_above_map_m is not None:
            dv, dve, dvn = self.vertical.value_and_gradient(east, north)
            ok = np.isfinite(dv)
            dz = np.asarray(self.alt_above_map_m, float)
            H[ok, 0] -= ((dve * J[:, 0, 0] + dvn * J[:, 1, 0]) * dz)[ok]
            H[ok, 1] -= ((dve * J[:, 0, 1] + dvn * J[:, 1, 1]) * dz)[ok]
            H[ok, 2] -= dv[ok]
        if self.core_grad is not None:
            H[:, :3] -= self.core_grad
        return H


def gate_sigma_of(probability: float) -> float:
    """The innovation gate (in predicted sigmas) that passes ``probability`` of a consistent
    filter's innovations: the square root of the chi-square (1 degree of freedom) quantile."""
    from scipy.stats import chi2

    if not 0.0 < probability < 1.0:
        raise ValueError(f"gate probability {probability!r}: must be in (0, 1)")
    return float(np.sqrt(chi2.ppf(probability, 1)))


def correlated_error_scale(length_m: float, step_m: float) -> float:
    """How much to inflate the variance of an error correlated over ``length_m`` along the
    track (m) for a filter that takes measurements ``step_m`` apart (m) as independent:
    ``max(1, length_m / step_m)``, the number of measurements that share one value of it.
    With it the filter draws one independent measurement's worth of information from each
    correlation length, as it should; without it, it averages the map's error down as if it
    were white noise and trusts its position far more than it may (docs/navigation.md,
    "Map errors")."""
    if not (np.isfinite(step_m) and step_m > 0):
        return 1.0
    return float(max(1.0, length_m / step_m))


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
    r_nT2 : the sensor's noise variance, nT^2; the map's (``MeasurementModel.map_var_nT2`` at
        the estimated position; none for a bare map) is added at each update
    update : (N,) bool, epochs allowed to use the map (default: all)
    x0 : (n,) initial state (default zero)
    check_every : the covariance's eigenvalues are checked every this many epochs
    gate_sigma : innovations beyond this many predicted sigmas are rejected (None: none are;
        ``aeromag navigate`` gates at ``[navigate] gate_probability``, see
        :func:`gate_sigma_of`)
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
                at = meas.estimated_position(k, x, ins_east_m[k], ins_north_m[k])
                mv = float(meas.map_var_nT2(*at))
                rk = r_nT2 + mv
                PH = P @ H
                s = float(H @ PH) + rk
                K = PH / s
                r = z[k] - m
                # one innovation's own spread: the map error's variance as it is (the inflation
                # for its correlation along the track is for the gain, not for one innovation)
                spread = s - mv + mv / meas.map_var_scale
                if gate_sigma is not None and r * r > gate_sigma**2 * spread:
                    rejected += 1
                    m = np.nan
            if np.isfinite(m):
                x = x + K * r
                A = eye - np.outer(K, H)
                P = A @ P @ A.T + np.outer(K, K) * rk
                innov[k], svar[k], used[k] = r, spread, True
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
