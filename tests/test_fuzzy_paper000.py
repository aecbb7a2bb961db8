"""Paper 000's fuzzy-adaptive R in the paper's own configuration (docs/science-paper000.md):
the predicted innovation variance is ~500x the observed, R runs to its clamp within ~100
samples and the result is the fixed-R filter's."""

from __future__ import annotations

import numpy as np

from pipeline.vector.component import ComponentKF
from pipeline.vector.fuzzy import RorFuzzy
from pipeline.vector.scenarios import rotating_carrier


class _Recording:
    def __init__(self) -> None:
        self.fuzzy, self.rors = RorFuzzy(), []

    def scale(self, ror: float) -> float:
        self.rors.append(ror)
        return self.fuzzy.scale(ror)


def test_paper_configuration_fuzzy_r_equals_fixed_r():
    fl = rotating_carrier(n=2000, seed=0)
    args = (fl.earth_nT, fl.earth_rate_nT_s, fl.measured_nT)
    fixed = ComponentKF.paper(scaled=True, fuzzy=False)
    p_fixed = fixed.run(*args)
    fz = ComponentKF.paper(scaled=True, fuzzy=False)
    rec = _Recording()
    fz.fuzzy = rec
    p_fuzzy = fz.run(*args)
    assert np.median(rec.rors[30:100]) < 0.01  # ROR ~ 0.002: "small" fires every step
    floor = np.flatnonzero(fz.history.r_scale <= fz.r_bounds[0] * (1 + 1e-9))
    assert floor.size and floor[0] < 300
    np.testing.assert_allclose(p_fuzzy.state(True), p_fixed.state(True), rtol=1e-5)
