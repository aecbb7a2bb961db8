"""An unrecorded periodic (switching) current: a nuisance of the audit's null model.

A load switched on a fixed period (a strobe, a heater's thermostat, a transmitter) that no
channel records couples into the scalar field as I(t) (u . d): a fixed body direction d seen
through the direction cosines u, times a periodic current. Its columns are u_i cos(2 pi k f t)
and u_i sin(2 pi k f t) for the fundamental f and the third harmonic (a square wave's two
strongest; the even ones vanish for an even duty cycle). The frequency comes from the line in
the null model's held-out residual spectrum (:func:`pipeline.audit.spectrum.residual_spectrum`)
and is refined on held-out data; the group is taken when it lowers the held-out residual as
any nuisance group must (:func:`pipeline.compensate.plus.select_groups`'s test).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import minimize_scalar

from pipeline.compensate.heldout import consistent, heldout_gain
from pipeline.compensate.plus import HeldOutSetup, aligned
from pipeline.compensate.terms import direction_cosines

NAME = "periodic_current"
HARMONICS = (1, 3)


def periodic_columns(
    vector_nT: np.ndarray, time_s: np.ndarray, frequency_hz: float
) -> tuple[np.ndarray, list[str]]:
    """Columns u_i cos(2 pi k f t), u_i sin(2 pi k f t) for k in :data:`HARMONICS`
    (dimensionless; body frame x forward, y right, z down), named ``periodic_<k>f_<c|s>u<i>``."""
    u = direction_cosines(np.asarray(vector_nT, float))
    cols, names = [], []
    for k in HARMONICS:
        ph = 2.0 * np.pi * k * frequency_hz * np.asarray(time_s, float)
        for trig, c in ((np.cos(ph), "c"), (np.sin(ph), "s")):
            for i, a in enumerate("xyz"):
                cols.append(u[:, i] * trig)
                names.append(f"periodic_{k}f_{c}u{a}")
    return np.column_stack(cols), names


def _refine_frequency(setup: HeldOutSetup, null_columns: np.ndarray, f0: float, df: float):
    """The frequency (Hz) within ``f0 +- df`` whose columns leave the smallest held-out
    residual beside ``null_columns``: a grid at the calibration's frequency resolution (1 /
    its span), then a bounded search around its best point. Returns (frequency, held-out
    residuals)."""
    m = setup.meas
    span_s = float(np.ptp(m.time_s[setup.fold >= 0]))
    step = 1.0 / max(span_s, 1.0)

    def held(f: float):
        cols, _ = periodic_columns(m.vector_nT, m.time_s, f)
        return setup.linear(np.column_stack([null_columns, cols]))

    grid = np.arange(max(f0 - df, step), f0 + df + step / 2, step)
    costs = [held(float(f)).rms_nT for f in grid]
    best = float(grid[int(np.argmin(costs))])
    res = minimize_scalar(
        lambda f: held(f).rms_nT,
        bounds=(best - step, best + step),
        method="bounded",
        options={"xatol": step / 20},
    )
    f = float(res.x) if res.fun < min(costs) else best
    return f, held(f)


def periodic_nuisance(
    setup: HeldOutSetup,
    null_columns: np.ndarray,
    frequency_hz: float,
    resolution_hz: float,
    alpha: float,
    min_gain: float,
) -> dict | None:
    """The periodic current's nuisance record ``{"name", "heldout_gain", "estimate"}`` when
    its columns at the refined frequency lower the held-out residual of the null model
    (``null_columns``) significantly (one-sided p below ``alpha``), by at least ``min_gain``
    and in all folds but one; None otherwise."""
    before = setup.linear(null_columns)
    f, after = _refine_frequency(setup, null_columns, frequency_hz, resolution_hz)
    a, b, w = aligned(before, after)
    test = heldout_gain(a, b, setup.meas.time_s[w])
    if not (
        test.p_value < alpha and test.reduction >= min_gain and consistent(a, b, setup.fold[w])
    ):
        return None
    return {
        "name": NAME,
        "heldout_gain": float(test.reduction),
        "estimate": {"frequency_hz": f, "p_value": float(test.p_value)},
    }
