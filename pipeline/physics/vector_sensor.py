"""Fluxgate (vector magnetometer) sensor errors: scale, non-orthogonality and offset.

A common linear error model: m = S N b + o, with S = diag(1 + s) the axis scale factors, N the
lower-triangular non-orthogonality matrix (y axis tilted by a1 towards x; z axis tilted by a2
towards x and a3 towards y) and o the offset. With no errors m = b.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class FluxgateErrors:
    """Scale errors (dimensionless), non-orthogonality angles (deg) and offsets (nT)."""

    scale_error: np.ndarray = field(default_factory=lambda: np.zeros(3))
    nonorthogonality_deg: np.ndarray = field(default_factory=lambda: np.zeros(3))
    offset_nT: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        self.scale_error = np.asarray(self.scale_error, float).reshape(3)
        self.nonorthogonality_deg = np.asarray(self.nonorthogonality_deg, float).reshape(3)
        self.offset_nT = np.asarray(self.offset_nT, float).reshape(3)

    def matrix(self) -> np.ndarray:
        """The 3x3 matrix S N mapping true body-frame field to measured (before offset)."""
        a1, a2, a3 = np.radians(self.nonorthogonality_deg)
        n = np.array(
            [
                [1.0, 0.0, 0.0],
                [np.sin(a1), np.cos(a1), 0.0],
                [
                    np.sin(a2),
                    np.sin(a3) * np.cos(a2),
                    np.sqrt(max(0.0, 1 - np.sin(a2) ** 2 - (np.sin(a3) * np.cos(a2)) ** 2)),
                ],
            ]
        )
        return np.diag(1.0 + self.scale_error) @ n

    def apply(self, b_body_nT: np.ndarray) -> np.ndarray:
        """Measured vectors (n, 3) for true body-frame field vectors (n, 3), nT."""
        return np.asarray(b_body_nT, float) @ self.matrix().T + self.offset_nT

    def to_dict(self) -> dict[str, list]:
        """JSON-ready: scale errors, non-orthogonality angles (deg) and offsets (nT)."""
        return {
            "scale_error": self.scale_error.tolist(),
            "nonorthogonality_deg": self.nonorthogonality_deg.tolist(),
            "offset_nT": self.offset_nT.tolist(),
        }
