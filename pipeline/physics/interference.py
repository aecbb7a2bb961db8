"""The carrier's own magnetic field at a sensor (Tolles-Lawson physics).

In the body frame (x forward, y right, z down) the interference vector is

    b_int = p + A b + E db/dt

with ``p`` the permanent (hard-iron) field, ``A`` the induced (soft-iron) matrix acting on the
Earth field ``b`` seen in the body frame, and ``E`` the eddy-current matrix acting on its time
derivative. A scalar sensor reads |b + b_int|; to first order in |b_int|/|b| that is
|b| + u.b_int with u = b/|b| the field direction: the basis of the T-L regression.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class CarrierInterference:
    """Permanent, induced and eddy-current interference at one sensor.

    Parameters
    ----------
    permanent_nT : (3,) body-frame permanent field, nT.
    induced : (3, 3) dimensionless induced-field matrix.
    eddy_s : (3, 3) eddy-current matrix, seconds (nT per nT/s).
    """

    permanent_nT: np.ndarray = field(default_factory=lambda: np.zeros(3))
    induced: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    eddy_s: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))

    def __post_init__(self) -> None:
        self.permanent_nT = np.asarray(self.permanent_nT, float).reshape(3)
        self.induced = np.asarray(self.induced, float).reshape(3, 3)
        self.eddy_s = np.asarray(self.eddy_s, float).reshape(3, 3)

    @classmethod
    def none(cls) -> CarrierInterference:
        """No interference (every term zero)."""
        return cls()

    def vector_nT(self, b_body_nT: np.ndarray, db_dt_body_nT_s: np.ndarray) -> np.ndarray:
        """Interference vectors (n, 3), body frame, nT."""
        b = np.asarray(b_body_nT, float)
        db = np.asarray(db_dt_body_nT_s, float)
        return self.permanent_nT + b @ self.induced.T + db @ self.eddy_s.T

    def scalar_first_order_nT(
        self, b_body_nT: np.ndarray, db_dt_body_nT_s: np.ndarray
    ) -> np.ndarray:
        """First-order scalar interference u . b_int (what T-L models), nT."""
        b = np.asarray(b_body_nT, float)
        u = b / np.linalg.norm(b, axis=-1, keepdims=True)
        return np.einsum("ij,ij->i", u, self.vector_nT(b, db_dt_body_nT_s))

    def to_dict(self) -> dict[str, list]:
        """JSON-ready: permanent field (nT, body frame), induced matrix and eddy matrix (s)."""
        return {
            "permanent_nT": self.permanent_nT.tolist(),
            "induced": self.induced.tolist(),
            "eddy_s": self.eddy_s.tolist(),
        }


def scalar_reading_nT(b_body_nT: np.ndarray, b_interference_nT: np.ndarray) -> np.ndarray:
    """What a total-field sensor reads: |b + b_int| (exact, not linearised), nT."""
    return np.linalg.norm(
        np.asarray(b_body_nT, float) + np.asarray(b_interference_nT, float), axis=-1
    )
