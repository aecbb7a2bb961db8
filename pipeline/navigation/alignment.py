"""The INS state at GNSS loss: the covariance a GNSS-aided INS has when the map-aided run starts.

A navigation window is where GNSS is taken away. Before it the INS was aided by GNSS, so its
tilt, velocity and (partly) bias errors are those that position fixes leave, not an
alignment's: a Kalman covariance recursion with position fixes (north, east, altitude, 1 sigma
``gnss_sigma_m``, one per ``fix_interval_s``) along the track flown before the window gives
it, with one fix's variance on the position (GNSS errors are correlated: they do not average
out). Both filters, the CRLB and the INS-only baseline start from this covariance, and the
simulated INS errors are drawn from it, so the map-aided/INS-only ratio compares like with
like (a filter started from an alignment's small tilt would flatter it).
"""

from __future__ import annotations

import numpy as np

from pipeline.navigation.ins import N_INS, InsErrorModel, Trajectory


def gnss_aided_covariance(
    model: InsErrorModel,
    traj: Trajectory,
    gnss_sigma_m: float,
    fix_interval_s: float = 1.0,
) -> np.ndarray:
    """Error covariance (n x n, the model's states) at the end of a GNSS-aided run.

    Parameters
    ----------
    model : InsErrorModel
        The INS grade; the run starts from its alignment covariance
        (:meth:`InsErrorModel.initial_covariance`).
    traj : Trajectory
        The track flown with GNSS (the stretch before the navigation window).
    gnss_sigma_m : float
        One-sigma noise of a position fix, north, east and altitude, m.
    fix_interval_s : float
        Time between fixes, s.

    Returns
    -------
    (n, n) ndarray
        The covariance at the last epoch, its position block with one fix's variance added
        (correlated GNSS errors do not average out); the magnetic bias state keeps its prior
        variance (no magnetometer in the aided run) and no correlation with the INS states.
    """
    if not gnss_sigma_m > 0:
        raise ValueError(f"gnss_sigma_m must be > 0 m, not {gnss_sigma_m!r}")
    phi = model.transitions(traj)
    t = traj.time_s
    qd = model.process_noise(np.diff(t, prepend=t[0]))
    P = model.initial_covariance()
    n = P.shape[0]
    H = np.zeros((3, n))
    H[0, 0] = H[1, 1] = H[2, 2] = 1.0
    r = gnss_sigma_m**2 * np.eye(3)
    next_fix = t[0]
    for k in range(t.size):
        if k:
            P = phi[k] @ P @ phi[k].T
            P[np.diag_indices(n)] += qd[k]
        if t[k] >= next_fix - 1e-9:
            PH = P @ H.T
            P = P - PH @ np.linalg.solve(H @ PH + r, PH.T)
            P = 0.5 * (P + P.T)
            next_fix = t[k] + fix_interval_s
    # GNSS position errors are correlated over minutes (multipath, ionosphere, orbits): the
    # fixes' average is not better than one fix. The recursion above takes them as white and
    # would average hundreds of them down to decimetres; the last fix's own error is added
    # back to the position block instead (independent of the other states to first order).
    P[:3, :3] += r
    out = P.copy()
    out[N_INS:, :] = 0.0
    out[:, N_INS:] = 0.0
    out[N_INS:, N_INS:] = model.initial_covariance()[N_INS:, N_INS:]
    return out
