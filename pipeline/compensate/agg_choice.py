"""AGG-TL's horizontal gradient chosen by held-out calibration data (``agg_gradient = "auto"``).

The calibration legs' gradient (:mod:`pipeline.compensate.agg_legs`) is the better evidence
over quiet ground, and biased where the box lies over geology (the legs' ramps carry the
crust's own gradient). Both fits are refitted on the held-out folds of
:mod:`pipeline.compensate.heldout` (the legs' gradient estimated from each fold's training
epochs only) and compared on the same band-passed held-out rows with the guards' paired
tests: the legs' gradient is kept unless the band-passed fit beats it there (one-sided p
below ``extension_alpha`` over 10-s blocks and with the fold as the unit, held-out RMS lower
by at least ``extension_min_gain``). ``gradient_evidence`` records the choice, both held-out
residuals and the tests.
"""

from __future__ import annotations

import numpy as np

from pipeline.compensate.agg_legs import fit_agg_with_legs
from pipeline.compensate.estimator import bandpassed_design
from pipeline.compensate.heldout import fold_test, heldout_gain, heldout_residuals
from pipeline.compensate.model import (
    CompensationModel,
    FitSettings,
    Measurements,
    design_of,
    fit_columns,
)
from pipeline.compensate.plus import HeldOutSetup, aligned

LEGS = "calibration legs"


def _predictor(meas: Measurements, s: FitSettings, design, fit_on):
    """A fold predictor: ``fit_on(train)`` gives the coefficients over ``design``'s columns;
    the test block is band-passed alone and its residual returned."""
    k = design[0]

    def predict(train: np.ndarray, test: np.ndarray):
        theta = fit_on(train)
        kt, yt, wt = bandpassed_design(
            k, meas.scalar_nT, meas.time_s, meas.rate_hz, test, s.band_hz, s.poles, s.trim_s
        )
        return yt - kt @ theta, wt

    return predict


def _heldout_record(setup: HeldOutSetup, r_fit, r_legs, s: FitSettings) -> tuple[bool, dict]:
    """(whether the band-passed fit beats the legs' gradient held out, the figures)."""
    a, b, w = aligned(r_legs, r_fit)
    test = heldout_gain(a, b, setup.meas.time_s[w])
    p_fold = fold_test(a, b, setup.fold[w])
    fit_better = (
        test.p_value < s.extension_alpha
        and p_fold < s.extension_alpha
        and test.reduction >= s.extension_min_gain
    )
    return fit_better, {
        "legs_heldout_residual_nT": test.rms_before_nT,
        "fit_heldout_residual_nT": test.rms_after_nT,
        "fit_better_pct": 100.0 * test.reduction,
        "p_fit_better": test.p_value,
        "p_fit_better_folds": p_fold,
    }


def _figures(held: dict) -> str:
    """The held-out comparison in a reason's words."""
    return (
        f"({held['fit_heldout_residual_nT']:.4f} against {held['legs_heldout_residual_nT']:.4f}"
        f" nT, p {held['p_fit_better']:.2g}, folds p {held['p_fit_better_folds']:.2g})"
    )


def fit_agg_auto(
    meas: Measurements,
    mask: np.ndarray,
    s: FitSettings,
    legs: np.ndarray,
    base_nT: np.ndarray | None = None,
) -> CompensationModel:
    """AGG-TL with the calibration legs' gradient unless held-out calibration data say the
    band-passed fit's is better (module docstring). Arguments as
    :func:`pipeline.compensate.agg_legs.fit_agg_with_legs`; ``gradient_evidence`` gains
    ``choice`` ("legs" or "fit"), ``heldout`` (both held-out residuals, nT, and the tests'
    p) and ``reason``."""
    design = design_of(s, meas, mask)
    with_legs = fit_agg_with_legs(meas, mask, s, legs, base_nT, design)
    ev = dict(with_legs.gradient_evidence)
    if ev.get("source") != LEGS:  # no legs' estimate: the plain fit, and why
        with_legs.gradient_evidence = {**ev, "choice": "fit"}
        return with_legs
    plain = fit_columns(meas, mask, s, *design)
    # the chosen gradient under east/north_nT_per_m, each source's under its own prefix
    ev["legs_east_nT_per_m"], ev["legs_north_nT_per_m"] = ev["east_nT_per_m"], ev["north_nT_per_m"]
    fit_ev = {**ev, "east_nT_per_m": ev["fit_east_nT_per_m"]}
    fit_ev["north_nT_per_m"] = ev["fit_north_nT_per_m"]
    try:
        setup = HeldOutSetup.of(meas, mask, s)
    except ValueError as exc:
        plain.gradient_evidence = {**fit_ev, "source": "band-passed fit", "choice": "fit"}
        plain.gradient_evidence["reason"] = f"no held-out comparison ({exc}); the fit's kept"
        return plain

    def fit_theta(train: np.ndarray) -> np.ndarray:
        return fit_columns(meas, train, s, *design).coefficients

    def legs_theta(train: np.ndarray) -> np.ndarray:
        return fit_agg_with_legs(meas, train, s, legs, base_nT, design).coefficients

    r_fit, r_legs = (
        heldout_residuals(_predictor(meas, s, design, f), meas.time_s, setup.fold, setup.buffer_s)
        for f in (fit_theta, legs_theta)
    )
    fit_better, held = _heldout_record(setup, r_fit, r_legs, s)
    if fit_better:
        plain.gradient_evidence = {
            **fit_ev,
            "source": "band-passed fit",
            "choice": "fit",
            "heldout": held,
            "reason": "the band-passed fit's gradient beats the legs' on held-out "
            f"calibration blocks {_figures(held)}: the legs' ramps carry more than the "
            "gradient at the manoeuvres",
        }
        return plain
    with_legs.gradient_evidence = {
        **ev,
        "choice": "legs",
        "heldout": held,
        "reason": ev["reason"] + "; the band-passed fit's does not beat it on held-out "
        f"calibration blocks {_figures(held)}",
    }
    return with_legs
