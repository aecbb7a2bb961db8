"""The fuzzy-adaptive measurement noise of paper 000: a three-rule Mamdani system.

Input: ROR = tr(C_r) / tr(P_r), the ratio of the actual innovation covariance (mean of r r'
over recent steps) to the one the filter predicts (H (P + Q) H' + R). Output: a factor s with
R_k = s^b R_(k-1). Rules: ROR small -> s small; ROR about one -> s medium (= 1); ROR large ->
s large. Triangular/trapezoidal sets, min implication, max aggregation, centroid
defuzzification. ROR = 1 gives s = 1 exactly, so the controller settles where the filter's
predicted innovations match the actual ones.

Hand-written (about 30 lines) rather than scikit-fuzzy: three fixed rules on one input do
not justify a dependency with its own numpy pinning, and the whole system is evaluated once
per filter step.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def _trap(x: np.ndarray | float, a: float, b: float, c: float, d: float) -> np.ndarray:
    """Trapezoid membership: 0 below a, rising to 1 at b, 1 to c, falling to 0 at d."""
    x = np.asarray(x, float)
    up = np.ones_like(x) if b == a else np.clip((x - a) / (b - a), 0.0, 1.0)
    down = np.ones_like(x) if d == c else np.clip((d - x) / (d - c), 0.0, 1.0)
    return np.minimum(up, down)


@dataclass(frozen=True)
class RorFuzzy:
    """ROR -> s. Input sets on ROR, output sets on s (defaults: s in [0.8, 1.2])."""

    small_in: tuple[float, float, float, float] = (0.0, 0.0, 0.4, 1.0)
    equal_in: tuple[float, float, float, float] = (0.4, 1.0, 1.0, 1.6)
    large_in: tuple[float, float, float, float] = (1.0, 1.6, 1e9, 1e9)
    small_out: tuple[float, float, float, float] = (0.8, 0.85, 0.85, 1.0)
    medium_out: tuple[float, float, float, float] = (0.95, 1.0, 1.0, 1.05)
    large_out: tuple[float, float, float, float] = (1.0, 1.15, 1.15, 1.2)
    grid: int = 201

    def scale(self, ror: float) -> float:
        w = [float(_trap(ror, *self.small_in)), float(_trap(ror, *self.equal_in)),
             float(_trap(ror, *self.large_in))]
        s = np.linspace(self.small_out[0], self.large_out[3], self.grid)
        agg = np.max([np.minimum(wk, _trap(s, *mf)) for wk, mf in
                      zip(w, (self.small_out, self.medium_out, self.large_out), strict=True)],
                     axis=0)
        total = agg.sum()
        return float((s * agg).sum() / total) if total > 0 else 1.0
