"""Fitting a compensation model by name: the linear T-L / AGG-TL fits
(:mod:`pipeline.compensate.model`) or tl18's extensions chosen on held-out calibration
(:mod:`pipeline.compensate.extension`). A module of its own, so that the extensions, which
build on the linear fit, and the linear fit do not import each other."""

from __future__ import annotations

import numpy as np

from pipeline.compensate.agg_choice import fit_agg_auto
from pipeline.compensate.agg_legs import fit_agg_with_legs
from pipeline.compensate.extension import fit_extension
from pipeline.compensate.model import (
    EXTENSIONS,
    CompensationModel,
    FitSettings,
    Measurements,
    design_of,
    fit_columns,
)


def fit_compensation(
    meas: Measurements,
    calibration_mask: np.ndarray,
    settings: FitSettings | None = None,
    legs: np.ndarray | None = None,
    base_nT: np.ndarray | None = None,
    seeded: dict[str, dict] | None = None,
) -> CompensationModel:
    """Fit a compensation model on the epochs of ``calibration_mask``.

    ``legs`` (calibration leg per epoch, :func:`pipeline.audit.legs.leg_ids`) and
    ``base_nT`` (the base station's field on the scalar epochs) give AGG-TL the calibration
    legs' gradient (:mod:`pipeline.compensate.agg_legs`; ``agg_gradient = "auto"``: when
    held-out calibration data do not prefer the fit's, :mod:`pipeline.compensate.agg_choice`);
    without ``legs`` it is fitted from the band-passed position columns alone. ``seeded``:
    tl-plus's term groups the audit named (:func:`pipeline.compensate.plus.audit_nuisances`),
    tried first.

    Raises
    ------
    ValueError
        No usable calibration samples, a band that does not fit the sample rate, or AGG-TL
        without positions.
    """
    s = settings or FitSettings()
    mask = np.asarray(calibration_mask, bool)
    if s.model in EXTENSIONS:
        return fit_extension(meas, mask, s, seeded)
    if s.model == "agg-tl" and s.agg_gradient != "fit" and legs is not None and meas.has_position:
        if s.agg_gradient == "auto":
            return fit_agg_auto(meas, mask, s, legs, base_nT)
        return fit_agg_with_legs(meas, mask, s, legs, base_nT)
    k_full, names, n_tl, reference = design_of(s, meas, mask)
    return fit_columns(meas, mask, s, k_full, names, n_tl, reference)
