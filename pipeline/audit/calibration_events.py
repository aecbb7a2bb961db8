"""Steps in the compensated field during the calibration legs.

The crossovers (:mod:`pipeline.audit.survey`) see a change of the carrier's field during the
survey; during calibration there are no crossovers, but each leg is flown on one heading over
quiet ground, so the compensated field along a leg is the Earth field's smooth trend. Per
leg, the 1 s means of the compensated field are modelled as a line, and a step at a scanned
time inside one leg (at least ``guard_s`` from its ends, where turns and manoeuvre changes
leave transients) is tested against it:

    y_k = a_leg + b_leg t_k + c [t_k > t_s] (leg holding t_s only) + e_k

The errors are autocorrelated (manoeuvre-frequency residuals last several seconds: lag-one
correlations of 0.7-0.8 between 1 s means), which a plain or Newey-West t ignores or
under-corrects (clean calibrations then give "steps"). So the model
is prewhitened first: an AR(2) fitted to the no-step residuals (least squares on its lags)
filters y and every column within each leg (Cochrane-Orcutt), and the step's t statistic on
the whitened data is Bonferroni-corrected over the scanned positions. The model (one step
inside one of several independent legs) is not a change-point library's cost, hence the
explicit scan.

Times are seconds from the flight's first epoch; sizes nT.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.audit.prewhiten import ar_coefficients, ar_whitener


@dataclass
class CalibrationStep:
    """A step in the compensated field inside one calibration leg (:func:`calibration_steps`).

    Attributes
    ----------
    start_s, end_s : float
        The 1 s bins either side of the step, s from the flight's first epoch.
    size_nT : float
        Step size (magnitude), nT.
    p_value : float
        Two-sided p of the step on the prewhitened data, Bonferroni-corrected over the
        scanned positions.
    """

    start_s: float  # the 1 s bins either side of the step
    end_s: float
    size_nT: float
    p_value: float  # Bonferroni over the scanned positions

    def to_dict(self, t0_ns: int) -> dict:
        """The step as an unexplained-event record, with absolute times.

        Parameters
        ----------
        t0_ns : int
            The flight's first epoch, ns (the recording's time base); ``start_s`` and ``end_s``
            are counted from it.

        Returns
        -------
        dict
            ``kind`` ("step"), ``start_ns``, ``end_ns``, ``size_nT``, ``p_value`` and ``evidence``.
        """
        return {
            "kind": "step",
            "start_ns": int(t0_ns + round(self.start_s * 1e9)),
            "end_ns": int(t0_ns + round(self.end_s * 1e9)),
            "size_nT": self.size_nT,
            "p_value": self.p_value,
            "evidence": "calibration residual",
        }


def _bins(t: np.ndarray, y: np.ndarray, bin_s: float) -> tuple[np.ndarray, np.ndarray]:
    k = np.floor((t - t[0]) / bin_s).astype(int)
    counts = np.bincount(k)
    sums = np.bincount(k, weights=y)
    tb = np.bincount(k, weights=t)
    ok = counts > 0
    return tb[ok] / counts[ok], sums[ok] / counts[ok]


def calibration_steps(
    time_s: np.ndarray,
    compensated_nT: np.ndarray,
    leg: np.ndarray,
    alpha: float = 0.01,
    min_size_nT: float = 0.0,
    guard_s: float = 5.0,
    bin_s: float = 1.0,
    min_leg_s: float = 30.0,
) -> list[CalibrationStep]:
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
    from scipy import stats

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
    coef0, *_ = np.linalg.lstsq(base, y_all, rcond=None)
    resid = y_all - base @ coef0
    # AR(2) of the residual by least squares on its own lags, and its filter, within legs
    phi = ar_coefficients(resid, which, 2)
    whiten = ar_whitener(phi, which)
    yw, bw = whiten(y_all), whiten(base)
    n, k = bw.shape
    candidates = []
    for i, (t, _) in enumerate(legs):
        inner = (t > t[0] + guard_s) & (t < t[-1] - guard_s)
        idx = np.flatnonzero(inner)
        for a, b in zip(idx[:-1], idx[1:], strict=True):
            candidates.append((i, float(t[a]), float(t[b])))
    if not candidates or n <= k + 2:
        return []
    best = None
    for i, lo, hi in candidates:
        step = ((which == i) & (t_all > 0.5 * (lo + hi))).astype(float)
        a = np.column_stack([bw, whiten(step)])
        coef, *_ = np.linalg.lstsq(a, yw, rcond=None)
        r = yw - a @ coef
        s2 = float(r @ r) / (n - k - 1)
        cov = s2 * np.linalg.pinv(a.T @ a)
        tval = coef[-1] / np.sqrt(cov[-1, -1])
        if best is None or abs(tval) > abs(best[0]):
            best = (tval, lo, hi, step)
    tval, lo, hi, step = best
    # the size from the unwhitened data at the located step (whitening trades a step's
    # level for its edge and biases the coefficient when phi is near the unit circle)
    a = np.column_stack([base, step])
    coef = np.linalg.lstsq(a, y_all, rcond=None)[0]
    size = float(coef[-1])
    # a step stands out of its leg's own residual; an oscillation (a gimbal, say) that the
    # whitening models well enough to make a "step" significant does not
    leg_rms = float(np.sqrt(np.mean((y_all - a @ coef)[which == which[step > 0][0]] ** 2)))
    p = min(1.0, 2 * float(stats.t.sf(abs(tval), n - k - 1)) * len(candidates))
    if p < alpha and abs(size) >= max(min_size_nT, 3.0 * leg_rms):
        return [CalibrationStep(lo, hi, abs(size), p)]
    return []
