"""Body and navigation frames.

Body frame: x forward, y right (starboard), z down. Navigation frame: NED (north, east, down).
Attitude is the Z-Y-X Euler sequence (yaw = true heading clockwise from north, then pitch
nose-up, then roll right-wing-down) taking NED axes onto body axes, so a body vector v_b maps
to NED as v_n = R v_b with R = Rz(yaw) Ry(pitch) Rx(roll).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def attitude_rotation(roll_deg, pitch_deg, yaw_deg) -> Rotation:
    """Rotation body -> NED for Z-Y-X Euler angles in degrees (arrays broadcast)."""
    r, p, y = np.broadcast_arrays(
        np.asarray(roll_deg, float), np.asarray(pitch_deg, float), np.asarray(yaw_deg, float)
    )
    angles = np.stack([y.ravel(), p.ravel(), r.ravel()], axis=-1)
    if y.ndim == 0:  # scalar angles: one rotation, so a single vector stays a single vector
        angles = angles[0]
    # Upper-case "ZYX" = intrinsic rotations, i.e. the aerospace yaw-pitch-roll sequence.
    return Rotation.from_euler("ZYX", angles, degrees=True)


def ned_to_body(v_ned, roll_deg, pitch_deg, yaw_deg) -> np.ndarray:
    """Express NED vectors (..., 3) in the body frame."""
    return attitude_rotation(roll_deg, pitch_deg, yaw_deg).inv().apply(np.asarray(v_ned, float))


def body_to_ned(v_body, roll_deg, pitch_deg, yaw_deg) -> np.ndarray:
    """Express body-frame vectors (..., 3) in NED."""
    return attitude_rotation(roll_deg, pitch_deg, yaw_deg).apply(np.asarray(v_body, float))
