"""Regressor (design-matrix) columns of the Tolles-Lawson models.

All come from the vector magnetometer B (body frame: x forward, y right, z down, nT) and its
direction cosines u = B/|B|; time derivatives are central differences (np.gradient, one-sided
at the ends).

- ``tl16`` (paper 002, eqs. 6-10): 3 permanent u_i; 5 induced u_i u_j (i <= j, u_z^2 dropped
  because sum u_i^2 = 1); 8 eddy u_i u'_j (u_z u_z' dropped because sum u_i u_i' = 0).
- ``tl18`` (MagNav.jl style): 3 permanent u_i; 6 induced u_i B_j / Bt_scale (i <= j); 9 eddy
  u_i dB_j/dt / Bt_scale; Bt_scale = 50 000 nT. Coefficients are then nT-sized: a true
  induced matrix A and eddy matrix E give (A_ij + A_ji) Bt_scale (i < j), A_ii Bt_scale and
  E_ij Bt_scale.
- position (AGG-TL, paper 002 eqs. 11-21): e, n, e^2, e n, n^2, up in metres from a reference.
"""

from __future__ import annotations

import numpy as np

BT_SCALE_NT = 50_000.0
AXES = "xyz"
PAIRS_UPPER = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]


def direction_cosines(b_nT: np.ndarray) -> np.ndarray:
    b = np.asarray(b_nT, float)
    return b / np.linalg.norm(b, axis=1, keepdims=True)


def _permanent(u: np.ndarray) -> tuple[list[np.ndarray], list[str]]:
    """Permanent-field columns: the direction cosines themselves."""
    return [u[:, i] for i in range(3)], [f"perm_u{a}" for a in AXES]


def tl16_terms(b_nT: np.ndarray, time_s: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """The 16 classic T-L columns from direction cosines, (n, 16)."""
    u = direction_cosines(b_nT)
    du = np.gradient(u, time_s, axis=0)
    cols, names = _permanent(u)
    for i, j in PAIRS_UPPER[:-1]:  # u_z^2 dropped
        cols.append(u[:, i] * u[:, j])
        names.append(f"ind_u{AXES[i]}u{AXES[j]}")
    for i in range(3):
        for j in range(3):
            if i == j == 2:  # u_z u_z' dropped
                continue
            cols.append(u[:, i] * du[:, j])
            names.append(f"eddy_u{AXES[i]}du{AXES[j]}")
    return np.column_stack(cols), names


def tl18_terms(b_nT: np.ndarray, time_s: np.ndarray,
               bt_scale_nT: float = BT_SCALE_NT) -> tuple[np.ndarray, list[str]]:
    """The 18 MagNav-style columns, (n, 18)."""
    b = np.asarray(b_nT, float)
    u = direction_cosines(b)
    db = np.gradient(b, time_s, axis=0)
    cols, names = _permanent(u)
    for i, j in PAIRS_UPPER:
        cols.append(u[:, i] * b[:, j] / bt_scale_nT)
        names.append(f"ind_u{AXES[i]}B{AXES[j]}")
    for i in range(3):
        for j in range(3):
            cols.append(u[:, i] * db[:, j] / bt_scale_nT)
            names.append(f"eddy_u{AXES[i]}dB{AXES[j]}")
    return np.column_stack(cols), names


def position_terms(east_m: np.ndarray, north_m: np.ndarray,
                   up_m: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """AGG-TL position columns: second-order horizontal Taylor terms and height, (n, 6)."""
    e, n, u = (np.asarray(a, float) for a in (east_m, north_m, up_m))
    return (np.column_stack([e, n, e * e, e * n, n * n, u]),
            ["pos_e", "pos_n", "pos_ee", "pos_en", "pos_nn", "pos_up"])


def tl18_truth_coefficients(permanent_nT, induced, eddy_s,
                            bt_scale_nT: float = BT_SCALE_NT) -> np.ndarray:
    """The tl18 coefficients that a carrier with interference (p, A, E) has, to first order."""
    a, e = np.asarray(induced, float), np.asarray(eddy_s, float)
    ind = [(a[i, j] + a[j, i]) * bt_scale_nT if i != j else a[i, i] * bt_scale_nT
           for i, j in PAIRS_UPPER]
    return np.concatenate([np.asarray(permanent_nT, float), ind, (e * bt_scale_nT).ravel()])
