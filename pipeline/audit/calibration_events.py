"""Steps in the compensated field during the calibration legs.

The crossovers (:mod:`pipeline.audit.survey`) see a change of the carrier's field during the
survey; during calibration there are no crossovers, but each leg is flown on one heading over
quiet ground, so the compensated field along a leg is the Earth field's smooth trend. Per
leg, the 1 s means of the compensated field are modelled as a line, and a step at a scanned
time inside one leg (at least ``guard_s`` from its ends, where turns and manoeuvre changes
leave transients) is tested against it:

    y_k = a_leg + b_leg t_k + c [t_k > t_s] (leg holding t_s only) + e_k

The errors are autocorrelated (manoeuvre-frequency residuals last several seconds), so the
step's t statistic uses a heteroscedasticity-and-autocorrelation-consistent covariance
(statsmodels OLS, Newey-West) and is Bonferroni-corrected over the scanned positions. The
model (one step inside one of several independent legs) is not a change-point library's cost,
hence the explicit scan.

Times are seconds from the flight's first epoch; sizes nT.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class CalibrationStep:
    start_s: float  # the 1 s bins either side of the step
    end_s: float
    size_nT: float
    p_value: float  # Bonferroni over the scanned positions

    def to_dict(self, t0_ns: int) -> dict:
        return {"kind": "step", "start_ns": int(t0_ns + round(self.start_s * 1e9)),
                "end_ns": int(t0_ns + round(self.end_s * 1e9)), "size_nT": self.size_nT,
                "p_value": self.p_value, "evidence": "calibration residual"}


def _bins(t: np.ndarray, y: np.ndarray, bin_s: float) -> tuple[np.ndarray, np.ndarray]:
    k = np.floor((t - t[0]) / bin_s).astype(int)
    counts = np.bincount(k)
    sums = np.bincount(k, weights=y)
    tb = np.bincount(k, weights=t)
    ok = counts > 0
    return tb[ok] / counts[ok], sums[ok] / counts[ok]


def calibration_steps(time_s: np.ndarray, compensated_nT: np.ndarray, leg: np.ndarray,
                      alpha: float = 0.01, min_size_nT: float = 0.0, guard_s: float = 5.0,
                      bin_s: float = 1.0, min_leg_s: float = 30.0) -> list[CalibrationStep]:
    """The most significant step inside a calibration leg, if any.

    Parameters
    ----------
    time_s : ndarray
        Epoch times (s).
    compensated_nT : ndarray
        Compensated total field (nT) at those epochs; NaN where missing.
    leg : ndarray of int
        Calibration leg of each epoch (one heading of one pass), -1 outside calibration.
    alpha : float
        Significance after the scan correction.
    min_size_nT : float
        Smallest step worth reporting (nT).
    guard_s, bin_s, min_leg_s : float
        Margin (s) kept from each leg's ends, averaging bin (s), shortest leg used (s).

    Returns
    -------
    list of CalibrationStep
        At most one (the best scanned position).
    """
    import statsmodels.api as sm

    legs = []
    for g in np.unique(leg[leg >= 0]):
        sel = (leg == g) & np.isfinite(compensated_nT)
        if sel.sum() < 2:
            continue
        t, y = _bins(time_s[sel], compensated_nT[sel], bin_s)
        if t[-1] - t[0] >= min_leg_s:
            legs.append((t, y))
    if not legs:
        return []
    # the base design: a level and a slope per leg (centred times, for conditioning)
    t_all = np.concatenate([t for t, _ in legs])
    y_all = np.concatenate([y for _, y in legs])
    which = np.concatenate([np.full(t.size, i) for i, (t, _) in enumerate(legs)])
    base = []
    for i, (t, _) in enumerate(legs):
        m = (which == i).astype(float)
        base += [m, m * (t_all - t.mean())]
    base = np.column_stack(base)
    candidates = []
    for i, (t, _) in enumerate(legs):
        inner = (t > t[0] + guard_s) & (t < t[-1] - guard_s)
        idx = np.flatnonzero(inner)
        for a, b in zip(idx[:-1], idx[1:], strict=True):
            candidates.append((i, float(t[a]), float(t[b])))
    if not candidates:
        return []
    coef0, *_ = np.linalg.lstsq(base, y_all, rcond=None)
    rss0 = float(np.sum((y_all - base @ coef0) ** 2))
    best = None
    for i, lo, hi in candidates:
        step = ((which == i) & (t_all > 0.5 * (lo + hi))).astype(float)
        a = np.column_stack([base, step])
        coef, *_ = np.linalg.lstsq(a, y_all, rcond=None)
        gain = rss0 - float(np.sum((y_all - a @ coef) ** 2))
        if best is None or gain > best[0]:
            best = (gain, i, lo, hi, step)
    _, i, lo, hi, step = best
    fit = sm.OLS(y_all, np.column_stack([base, step])).fit(
        cov_type="HAC", cov_kwds={"maxlags": int(np.ceil(10.0 / bin_s))})
    size = float(fit.params[-1])
    p = min(1.0, float(fit.pvalues[-1]) * len(candidates))
    if p < alpha and abs(size) >= min_size_nT:
        return [CalibrationStep(lo, hi, abs(size), p)]
    return []
