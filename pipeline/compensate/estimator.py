"""The one Tolles-Lawson estimator: band-passed ridge regression over calibration blocks.

Every compensation fit in aeromag goes through here: the post-flight models
(:func:`pipeline.compensate.fit_compensation`: ``tl16``, ``tl18``, ``agg-tl``) and the audit's
extended models (:func:`pipeline.audit.extended.fit_model`), which are term sets of the same
regression. The fit (paper 002, MagNav.jl's ``create_TL_coef``): the design columns and the
measured field are band-passed (zero-phase Butterworth) within each contiguous block of the
fitted epochs, the filter's edge samples are trimmed, and the ridge solution is taken with a
given lambda, the L-curve corner (``"auto"``) or lambda chosen by cross-validation over folds
(``"cv"``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.compensate.filters import (
    bandpass_blocks,
    bandpass_sos,
    contiguous_blocks,
    trim_samples,
)
from pipeline.compensate.ridge import LCurve, RidgeSVD


def bandpassed_design(
    columns: np.ndarray,
    y_nT: np.ndarray,
    time_s: np.ndarray,
    rate_hz: float,
    mask: np.ndarray,
    band_hz: tuple[float, float] | None,
    poles: int,
    trim_s: float,
    keep: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows of the regression: ``(K, y, epoch indices)``.

    Parameters
    ----------
    columns : ndarray, shape (n, p)
        Design columns at every epoch (T-L terms in nT, or any further regressors).
    y_nT : ndarray, shape (n,)
        Measured scalar field, nT.
    time_s, rate_hz
        Epoch times (s) and the sample rate (Hz) the band is normalised by.
    mask : ndarray of bool, shape (n,)
        Epochs to fit; epochs with a non-finite value or column are left out, and the rest
        is split into contiguous blocks (also at sampling gaps).
    band_hz, poles, trim_s
        Band-pass within each block (``poles``: order of the low-pass prototype), then drop
        ``trim_s`` seconds (nearest sample at ``rate_hz``) at both block ends.
        ``band_hz=None``: no filter and no trim.
    keep : ndarray of bool, shape (n,), optional
        Keep only the rows of these epochs, band-passed with all of ``mask`` (cross-validation
        folds select rows of the once-filtered calibration).
    """
    valid = mask & np.isfinite(y_nT) & np.all(np.isfinite(columns), axis=1)
    blocks = contiguous_blocks(valid, time_s)
    if band_hz is None:
        where = np.concatenate(blocks) if blocks else np.zeros(0, int)
        kf, yf = columns[where], y_nT[where]
    else:
        sos = bandpass_sos(band_hz, rate_hz, poles)
        trim = trim_samples(trim_s, rate_hz)
        # the record beside the columns, each block filtered in one call (the filter acts
        # on each column alone: the same numbers as two calls, at half the calls' overhead)
        idx = np.concatenate(blocks) if blocks else np.zeros(0, int)
        ends = np.cumsum([b.size for b in blocks])
        local = [np.arange(e - b.size, e) for e, b in zip(ends, blocks, strict=True)]
        flat = columns.reshape(columns.shape[0], -1)
        both, at = bandpass_blocks(np.column_stack([flat[idx], y_nT[idx]]), local, sos, trim)
        kf = np.ascontiguousarray(both[:, :-1]).reshape((-1,) + columns.shape[1:])
        yf, where = both[:, -1].copy(), idx[at]
    if keep is not None:
        rows = keep[where]
        kf, yf, where = kf[rows], yf[rows], where[rows]
    return kf, yf, where


@dataclass
class RidgeFit:
    """A ridge solution of one set of rows.

    ``coefficient_std`` (one sigma: the residual variance times the least-squares covariance
    of the coefficients, in the SVD's well-determined subspace) is computed only when asked
    for; ``lcurve`` only with ``ridge="auto"``.
    """

    theta: np.ndarray
    lambda_: float
    residual_rms: float
    n_rows: int
    lcurve: LCurve | None = None
    coefficient_std: np.ndarray | None = None


def fit_ridge(
    k: np.ndarray,
    y: np.ndarray,
    ridge: float | str = "auto",
    folds: np.ndarray | None = None,
    uncertainty: bool = False,
) -> RidgeFit:
    """Ridge regression of ``y`` on ``k`` with a given or chosen lambda.

    Parameters
    ----------
    k, y
        Rows from :func:`bandpassed_design`.
    ridge
        A lambda (in the units of ``k'k``), ``"auto"`` (L-curve corner) or ``"cv"``
        (cross-validation over the fold number of each row, ``folds``; see
        :mod:`pipeline.audit.crossval`).
    uncertainty
        Also return each coefficient's standard deviation.

    Raises
    ------
    ValueError
        Fewer than two rows per coefficient, or ``"cv"`` without folds.
    """
    if k.shape[0] < 2 * k.shape[1]:
        raise ValueError(f"only {k.shape[0]} usable calibration samples for {k.shape[1]} terms")
    lcurve = None
    if ridge == "cv" and not uncertainty:
        from pipeline.audit.crossval import choose_lambda

        if folds is None:
            raise ValueError("ridge 'cv' needs the fold numbers")
        lam = choose_lambda(k, y, folds).best
        # the normal equations' eigendecomposition (p x p) instead of an SVD of the rows:
        # fold fits are most of the audit's fits, and lambda is the cross-validated one
        w, v = np.linalg.eigh(k.T @ k)
        theta = v @ ((v.T @ (k.T @ y)) / (np.clip(w, 0.0, None) + lam))
        std = None
    else:
        solver = RidgeSVD(k, y)
        if ridge == "auto":
            lcurve = solver.lcurve()
            lam = lcurve.lambda_corner
        elif ridge == "cv":
            from pipeline.audit.crossval import choose_lambda

            if folds is None:
                raise ValueError("ridge 'cv' needs the fold numbers")
            lam = choose_lambda(k, y, folds).best
        else:
            lam = float(ridge)
        theta = solver.solve(lam)
        std = None
    resid = y - k @ theta
    if uncertainty:
        dof = max(k.shape[0] - k.shape[1], 1)
        sigma2 = float(resid @ resid) / dof
        s_pos = solver.s[solver.s > solver.s.max() * 1e-12]
        v = solver.vt[: s_pos.size].T
        std = np.sqrt(sigma2 * np.sum((v / s_pos) ** 2, axis=1))
    return RidgeFit(
        theta, float(lam), float(np.sqrt(np.mean(resid**2))), int(k.shape[0]), lcurve, std
    )
