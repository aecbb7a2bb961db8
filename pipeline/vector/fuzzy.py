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

The membership functions' breakpoints, the window, the exponent b and the clamp on R are
``[vector] fuzzy_*`` in ``pipeline/default_config.toml`` (reasons: docs/science-paper000.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pipeline.defaults import default_value

Sets = tuple[float, float, float, float]
SET_KEYS = ("ror_small", "ror_equal", "ror_large", "s_small", "s_medium", "s_large")


def _default_set(name: str):
    """default_factory reading ``[vector] fuzzy_<name>`` of the shipped defaults."""
    return lambda: tuple(float(v) for v in default_value("vector", f"fuzzy_{name}"))


def _trap(x: np.ndarray | float, a: float, b: float, c: float, d: float) -> np.ndarray:
    """Trapezoid membership: 0 below a, rising to 1 at b, 1 to c, falling to 0 at d."""
    x = np.asarray(x, float)
    up = np.ones_like(x) if b == a else np.clip((x - a) / (b - a), 0.0, 1.0)
    down = np.ones_like(x) if d == c else np.clip((d - x) / (d - c), 0.0, 1.0)
    return np.minimum(up, down)


@dataclass(frozen=True)
class RorFuzzy:
    """ROR -> s, the factor of R_k = s^b R_(k-1).

    Parameters
    ----------
    ror_small, ror_equal, ror_large : tuple of 4 float
        Trapezoids (a, b, c, d) on ROR (dimensionless), a <= b <= c <= d; a triangle has
        b = c. Defaults: ``[vector] fuzzy_ror_*`` of ``pipeline/default_config.toml``.
    s_small, s_medium, s_large : tuple of 4 float
        Output trapezoids on s (dimensionless, > 0); defaults ``[vector] fuzzy_s_*``.
    grid : int
        Points of the centroid defuzzification over [s_small[0], s_large[3]].
    """

    ror_small: Sets = field(default_factory=_default_set("ror_small"))
    ror_equal: Sets = field(default_factory=_default_set("ror_equal"))
    ror_large: Sets = field(default_factory=_default_set("ror_large"))
    s_small: Sets = field(default_factory=_default_set("s_small"))
    s_medium: Sets = field(default_factory=_default_set("s_medium"))
    s_large: Sets = field(default_factory=_default_set("s_large"))
    grid: int = 201

    def __post_init__(self) -> None:
        for name in SET_KEYS:
            v = getattr(self, name)
            if len(v) != 4 or any(b < a for a, b in zip(v[:-1], v[1:], strict=True)):
                raise ValueError(
                    f"fuzzy_{name}: four non-decreasing numbers (a, b, c, d), got {list(v)}"
                )
        if self.s_small[0] <= 0.0:
            raise ValueError("fuzzy_s_small: the factor s must stay positive")

    @classmethod
    def from_values(cls, vector: dict[str, Any]) -> RorFuzzy:
        """From a ``[vector]`` table of the configuration (keys ``fuzzy_ror_*``,
        ``fuzzy_s_*``; missing ones take the shipped defaults)."""
        return cls(
            **{
                k: tuple(float(x) for x in vector[f"fuzzy_{k}"])
                for k in SET_KEYS
                if f"fuzzy_{k}" in vector
            }
        )

    def scale(self, ror: float) -> float:
        """s for one ROR (min implication, max aggregation, centroid)."""
        w = [
            float(_trap(ror, *self.ror_small)),
            float(_trap(ror, *self.ror_equal)),
            float(_trap(ror, *self.ror_large)),
        ]
        s = np.linspace(self.s_small[0], self.s_large[3], self.grid)
        agg = np.max(
            [
                np.minimum(wk, _trap(s, *mf))
                for wk, mf in zip(w, (self.s_small, self.s_medium, self.s_large), strict=True)
            ],
            axis=0,
        )
        total = agg.sum()
        return float((s * agg).sum() / total) if total > 0 else 1.0
