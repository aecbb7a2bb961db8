"""Carrier interference that the Tolles-Lawson model cannot represent, and sensor filtering.

Tolles-Lawson (T-L) assumes b_int = p + A b + E db/dt: a permanent field, an induced field
*linear* in the body-frame Earth field b, and eddy currents that follow db/dt *instantly*. Real
carriers also have (all body frame, shapes only; the simulator scales each term to a requested
size):

- second-order induced fields, b_i = sum_jk Q_ijk b_j b_k / B_scale (soft iron near saturation);
- eddy currents that decay with an L/R time constant tau: E lowpass_tau(db/dt) instead of
  E db/dt. Only the difference E (lowpass_tau(db/dt) - db/dt) is outside the basis;
- currents that no channel records (a heater, a servo, a radio transmitting), b = I(t) d;
- vibration of conductive parts (rotor arms, motors) through the field: their eddy currents
  follow the jitter's angular rate w, E (-w x b), at frequencies the sensors sample aliased.

:func:`tl18_basis` gives the columns of the MagNav-style tl18 model (plus a constant) from the
*true* field, and :func:`outside_part` the least-squares residual of a scalar series against
them: the share no tl18 calibration can remove.
"""

from __future__ import annotations

import numpy as np
from scipy.signal import lfilter, lfilter_zi

B_SCALE_NT = 50_000.0
PAIRS_UPPER = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def first_order_lowpass(x: np.ndarray, dt_s: float, tau_s: float, axis: int = 0) -> np.ndarray:
    """First-order low-pass dy/dt = (x - y)/tau of a regularly sampled series, along ``axis``.

    Exact for a signal linear between samples (first-order hold), started in steady state on
    the first sample. Group delay tau at low frequency; gain 1/sqrt(1 + (w tau)^2).
    """
    x = np.asarray(x, float)
    if tau_s <= 0:
        return x.copy()
    num, den, zi = first_order_filter(dt_s, tau_s)
    y, _ = lfilter(num, den, x, axis=axis, zi=zi * np.take(x, [0], axis=axis))
    return y


def first_order_filter(dt_s: float, tau_s: float) -> tuple[np.ndarray, np.ndarray, float]:
    """:func:`first_order_lowpass`'s discrete filter at sample interval ``dt_s`` and time
    constant ``tau_s`` (s, > 0): ``(b, a, zi)`` for :func:`scipy.signal.lfilter`, ``zi``
    the state of unit steady state (times the first sample)."""
    a = float(np.exp(-dt_s / tau_s))
    k = tau_s / dt_s * (1.0 - a)
    num, den = np.array([1.0 - k, k - a]), np.array([1.0, -a])
    return num, den, float(lfilter_zi(num, den)[0])


def tl18_basis(b_nT: np.ndarray, db_dt_nT_s: np.ndarray) -> np.ndarray:
    """tl18 columns from the true body field and its derivative, plus a constant, (n, 19).

    u_i (permanent), u_i b_j / B_scale for i <= j (induced), u_i db_j/dt / B_scale (eddy, per
    second: the ``tl18-rate`` columns; on a regularly sampled series they span the same space
    as ``tl18``'s per-sample eddy columns, so :func:`outside_part` is the same for both).
    """
    b = np.asarray(b_nT, float)
    db = np.asarray(db_dt_nT_s, float)
    u = b / np.linalg.norm(b, axis=1, keepdims=True)
    cols = [u[:, i] for i in range(3)]
    cols += [u[:, i] * b[:, j] / B_SCALE_NT for i, j in PAIRS_UPPER]
    cols += [u[:, i] * db[:, j] / B_SCALE_NT for i in range(3) for j in range(3)]
    cols.append(np.ones(b.shape[0]))
    return np.column_stack(cols)


def outside_part(y: np.ndarray, basis: np.ndarray, fit: np.ndarray) -> np.ndarray:
    """``y`` minus its least-squares fit by ``basis`` on the rows ``fit`` (all rows returned)."""
    k = basis[fit]
    scale = np.linalg.norm(k, axis=0)
    scale[scale == 0] = 1.0
    coef, *_ = np.linalg.lstsq(k / scale, y[fit], rcond=None)
    return y - basis @ (coef / scale)


def second_order_vector(b_nT: np.ndarray, q: np.ndarray) -> np.ndarray:
    """b_i = sum_jk Q_ijk b_j b_k / B_scale, (n, 3) nT for Q of shape (3, 3, 3)."""
    b = np.asarray(b_nT, float)
    return np.einsum("ijk,nj,nk->ni", np.asarray(q, float), b, b) / B_SCALE_NT


def lagging_eddy_vector(
    db_dt_nT_s: np.ndarray, dt_s: float, tau_s: float, eddy_s: np.ndarray
) -> np.ndarray:
    """E (lowpass_tau(db/dt) - db/dt): what an L/R-lagging eddy current adds to T-L's E db/dt."""
    db = np.asarray(db_dt_nT_s, float)
    return (first_order_lowpass(db, dt_s, tau_s, axis=0) - db) @ np.asarray(eddy_s, float).T


def vibration_vector(
    b_nT: np.ndarray, angular_rate_rad_s: np.ndarray, eddy_s: np.ndarray
) -> np.ndarray:
    """E (-w x b): eddy field of parts turning at angular rate w through the field b."""
    db = -np.cross(np.asarray(angular_rate_rad_s, float), np.asarray(b_nT, float))
    return db @ np.asarray(eddy_s, float).T
