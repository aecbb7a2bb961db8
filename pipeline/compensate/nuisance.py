"""Design columns beyond the Tolles-Lawson basis: one home for the audit's nuisances and
``tl-plus``'s term groups.

Every builder takes the body-frame vector field (x forward, y right, z down; nT) on the
scalar epochs and returns ``(columns (n, k), names)``; the columns are interference shapes
(compensating: they are subtracted with their fitted coefficients).

- **eddy decay**: the field's change through a first-order response of time constant tau,
  projected on the field direction like T-L's eddy columns (eddy currents in a conductor
  whose L/R is not short against the manoeuvres);
- **second order**: induced magnetisation quadratic in the field, u_i B_j B_k / s^2, and the
  magnitude's second-order term in the eddy field, quadratic in the rate of change
  (dB_j/dt dB_k/dt);
- **current**: a recorded current or voltage I coupling along a fixed body direction d,
  c I (u . d): the columns I u_x, I u_y, I u_z;
- **attitude rates**: roll, pitch and yaw rates (rad/s; the vibration and rotation of
  conductive parts through the field follow them).
"""

from __future__ import annotations

import numpy as np

from pipeline.compensate.filters import contiguous_blocks
from pipeline.compensate.terms import BT_SCALE_NT, direction_cosines, per_sample_difference
from pipeline.physics.outside_basis import first_order_lowpass

AXES = "xyz"
# a manoeuvre's typical rate of turn (rad/s: 10 deg at a 5 s period): the squared-rate columns
# of the second-order terms in units of it, of the order of one like the others
SECOND_ORDER_RATE_PER_S = 0.2


def eddy_decay(columns: np.ndarray, time_s: np.ndarray, tau_s: float) -> np.ndarray:
    """Eddy columns passed through a first-order response of time constant ``tau_s`` (s),
    per contiguous block of finite samples: eddy currents in a conductor whose circuit's
    L/R is not short against the manoeuvres lag dB/dt instead of following it at once.
    """
    out = np.full(columns.shape, np.nan)
    ok = np.all(np.isfinite(columns), axis=1)
    dt = float(np.median(np.diff(time_s)))
    for b in contiguous_blocks(ok, time_s):
        out[b] = first_order_lowpass(columns[b], dt, tau_s)
    return out


def eddy_decay_columns(
    vector_nT: np.ndarray,
    time_s: np.ndarray,
    tau_s: float,
    bt_scale_nT: float = BT_SCALE_NT,
    difference=per_sample_difference,
) -> tuple[np.ndarray, list[str]]:
    """Decaying eddy columns u_i lowpass_tau(dB_j) / Bt_scale (9; dB per sample by
    ``difference``, as tl18's eddy columns), named ``eddy_u{i}dB{j}_decay``.

    The eddy current is driven by dB/dt and decays with its circuit's L/R, so the first-order
    response acts on the field's change, and its field at the sensor enters the magnitude
    through the present direction u. Filtering tl18's products u_i dB_j instead spans this
    only while u is constant over tau (not in the manoeuvres that excite the eddy terms).
    """
    v = np.asarray(vector_nT, float)
    u = direction_cosines(v)
    decayed = eddy_decay(difference(v), time_s, tau_s)
    cols = np.column_stack(
        [u[:, i] * decayed[:, j] / bt_scale_nT for i in range(3) for j in range(3)]
    )
    return cols, [f"eddy_u{AXES[i]}dB{AXES[j]}_decay" for i in range(3) for j in range(3)]


def second_order_columns(vector_nT: np.ndarray, time_s: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """Second-order induced columns u_i B_j B_k / s^2 (18) and squared-rate columns
    (dB_j/dt dB_k/dt) / (s r)^2 (6; r = :data:`SECOND_ORDER_RATE_PER_S`), dimensionless.

    An eddy field of E dB/dt ~ 0.02 s x 10^4 nT/s = 200 nT (a fixed-wing's) puts 0.4 nT of
    |E dB|^2 / 2|B| into the magnitude, following the squared rates.
    """
    v = np.asarray(vector_nT, float)
    u = direction_cosines(v)
    quad = [(j, k) for j in range(3) for k in range(j, 3)]
    induced = np.column_stack(
        [u[:, i] * v[:, j] * v[:, k] / BT_SCALE_NT**2 for i in range(3) for j, k in quad]
    )
    names = [f"second_u{AXES[i]}B{AXES[j]}B{AXES[k]}" for i in range(3) for j, k in quad]
    rate = np.gradient(v, time_s, axis=0) / (BT_SCALE_NT * SECOND_ORDER_RATE_PER_S)
    squared = np.column_stack([rate[:, j] * rate[:, k] for j, k in quad])
    names += [f"second_dB{AXES[j]}dB{AXES[k]}" for j, k in quad]
    return np.column_stack([induced, squared]), names


def current_columns(
    vector_nT: np.ndarray, channel: np.ndarray, name: str
) -> tuple[np.ndarray, list[str]]:
    """A recorded channel ``channel`` (its own unit) coupling along a fixed body direction:
    I u_x, I u_y, I u_z, named ``aux_<name>_u{x,y,z}``."""
    u = direction_cosines(vector_nT)
    return np.asarray(channel, float)[:, None] * u, [f"aux_{name}_u{a}" for a in AXES]


def attitude_rate_columns(
    roll_deg: np.ndarray, pitch_deg: np.ndarray, yaw_deg: np.ndarray, time_s: np.ndarray
) -> tuple[np.ndarray, list[str]]:
    """Roll, pitch and yaw rates in units of :data:`SECOND_ORDER_RATE_PER_S` (rad/s), yaw
    unwrapped (per contiguous block of finite samples; NaN elsewhere)."""
    att = np.radians(np.column_stack([roll_deg, pitch_deg, yaw_deg]).astype(float))
    out = np.full(att.shape, np.nan)
    ok = np.all(np.isfinite(att), axis=1)
    for b in contiguous_blocks(ok, time_s):
        if b.size > 2:
            a = np.unwrap(att[b], axis=0)
            out[b] = np.gradient(a, time_s[b], axis=0) / SECOND_ORDER_RATE_PER_S
    return out, ["rate_roll", "rate_pitch", "rate_yaw"]
