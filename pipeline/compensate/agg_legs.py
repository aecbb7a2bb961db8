"""AGG-TL with the calibration legs' gradient as a constraint.

The band-passed AGG-TL fit sees a gradient only through the small position changes the
manoeuvres make, so on a single calibration pass its position coefficients are poorly
determined and their error leaks into the heading (permanent and induced) terms. The legs
flown straight between the manoeuvres carry far better evidence: the compensated field
ramps along them by ``g . position`` over hundreds of metres. The one estimator of that
gradient is the audit's (:func:`pipeline.audit.legs.leg_gradient`); this module feeds it
the plain AGG-TL fit's compensated field (the base station's smoothed reading taken out
when recorded), then refits AGG-TL with the horizontal gradient fixed at the legs' value:
``g_e e + g_n n`` is taken out of the reading and the remaining position columns
(curvature and height) are fitted as before. Where the legs give no estimate (no
segmentation, fewer than two usable legs) the plain fit stands and the model says why.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from pipeline.compensate.model import (
    CompensationModel,
    FitSettings,
    Measurements,
    design_of,
    fit_columns,
)
from pipeline.compensate.terms import BT_SCALE_NT
from pipeline.geo.local import LocalFrame

HORIZONTAL = ("pos_e", "pos_n")


def _enu(meas: Measurements, reference: dict[str, float]) -> np.ndarray:
    frame = LocalFrame(
        reference["latitude_deg"], reference["longitude_deg"], reference["altitude_m"]
    )
    return np.column_stack(frame.to_enu(meas.lat_deg, meas.lon_deg, meas.alt_m))


def _smoothed(time_s: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The base station's reading smoothed as the reduction smooths it
    (:data:`pipeline.maps.reduce.BASE_SMOOTHING_S`)."""
    from pipeline.maps.reduce import BASE_SMOOTHING_S, time_window_mean

    return time_window_mean(time_s, x, BASE_SMOOTHING_S)


def fit_agg_with_legs(
    meas: Measurements,
    mask: np.ndarray,
    s: FitSettings,
    legs: np.ndarray,
    base_nT: np.ndarray | None = None,
    design: tuple[np.ndarray, list[str], int, dict[str, float]] | None = None,
) -> CompensationModel:
    """AGG-TL on the calibration epochs ``mask`` with the horizontal gradient fixed at the
    one the calibration legs measure.

    Parameters
    ----------
    meas, mask, s
        As :func:`pipeline.compensate.fit.fit_compensation` (``s.model`` is ``agg-tl``).
    legs : ndarray of int
        Calibration leg per epoch (:func:`pipeline.audit.legs.leg_ids`), -1 elsewhere.
    base_nT : ndarray, optional
        The base station's total field on the scalar epochs (nT): the day's variation,
        which would otherwise ramp along a leg, is taken out of the legs' field.
    design : tuple, optional
        :func:`pipeline.compensate.model.design_of`'s output to use instead of the one of
        ``mask`` (held-out folds share the whole calibration's position reference).

    Returns
    -------
    CompensationModel
        ``gradient_evidence`` says which gradient was used (east, north in nT/m, their
        standard errors, the legs' F-test p) or why the plain fit stands.
    """
    # imported here: the audit's package imports the compensation stage at load time
    from pipeline.audit.legs import leg_gradient

    k, names, n_tl, reference = design or design_of(s, meas, mask)
    plain = fit_columns(meas, mask, s, k, names, n_tl, reference)
    comp = meas.scalar_nT - k[:, :n_tl] @ plain.coefficients[:n_tl]
    if base_nT is not None and np.isfinite(base_nT).any():
        comp = comp - _smoothed(meas.time_s, base_nT)
    enu = _enu(meas, reference)
    # the carrier's isotropic soft iron scales the reading unseen; the largest fitted induced
    # coefficient stands for that scale's uncertainty (as in the audit)
    induced = [
        abs(v) for n, v in zip(names, plain.coefficients, strict=True) if n.startswith("ind_")
    ]
    lg = leg_gradient(
        meas.time_s,
        np.where(mask, comp, np.nan),
        enu,
        np.where(mask, legs, -1),
        scale_uncertainty=max(induced, default=0.0) / BT_SCALE_NT,
    )
    if lg is None:
        plain.gradient_evidence = {
            "source": "band-passed fit",
            "reason": "the calibration legs give no gradient estimate (fewer than two legs "
            "with enough steady blocks)",
        }
        return plain
    g_e, g_n = (float(v) for v in lg.gradient_nT_per_m[:2])
    keep = [i for i, n in enumerate(names) if n not in HORIZONTAL]
    ramp = g_e * enu[:, 0] + g_n * enu[:, 1]
    shifted = replace(meas, scalar_nT=meas.scalar_nT - ramp)
    fixed = fit_columns(shifted, mask, s, k[:, keep], [names[i] for i in keep], n_tl, reference)
    theta = np.zeros(len(names))
    theta[keep] = fixed.coefficients
    theta[names.index("pos_e")], theta[names.index("pos_n")] = g_e, g_n
    std = None
    if fixed.coefficient_std is not None:
        std = np.zeros(len(names))
        std[keep] = fixed.coefficient_std
        std[names.index("pos_e")], std[names.index("pos_n")] = lg.se_nT_per_m[:2]
    model = replace(fixed, terms=list(names), coefficients=theta, coefficient_std=std)
    model.gradient_evidence = {
        "source": "calibration legs",
        "east_nT_per_m": g_e,
        "north_nT_per_m": g_n,
        "east_se_nT_per_m": float(lg.se_nT_per_m[0]),
        "north_se_nT_per_m": float(lg.se_nT_per_m[1]),
        "legs_p_value": float(lg.p_value),
        "legs": lg.legs,
        "blocks": lg.blocks,
        "fit_east_nT_per_m": float(plain.coefficients[names.index("pos_e")]),
        "fit_north_nT_per_m": float(plain.coefficients[names.index("pos_n")]),
        "reason": "the horizontal gradient is fixed at the calibration legs' estimate "
        "(block means along the straight legs, far more precise than the band-passed "
        "position columns)",
    }
    return model
