"""Steps in the compensated field during the calibration legs.

The crossovers (:mod:`pipeline.audit.survey`) see a change of the carrier's field during the
survey; during calibration there are no crossovers, but each leg is flown on one heading over
quiet ground, so the compensated field along a leg is the Earth field's smooth trend. Per
leg, the 1 s means of the compensated field are modelled as a smooth trend (a cubic in time:
over geology a kilometre-long leg's field curves), and a step at a scanned time inside one
leg (at least ``guard_s`` from its ends, where turns and manoeuvre changes leave transients,
and not where a manoeuvre starts or stops) is tested against it:

    y_k = P_leg(t_k) + c [t_k > t_s] (leg holding t_s only) + e_k

The errors are autocorrelated (manoeuvre-frequency residuals last several seconds: lag-one
correlations of 0.7-0.8 between 1 s means), which a plain or Newey-West t ignores or
under-corrects (clean calibrations then give "steps"). So the model is prewhitened first: an
AR(2) fitted to the no-step residuals (least squares on its lags) filters y and every column
within each leg (Cochrane-Orcutt). The step's t statistic on the whitened data (robust scale)
is compared with the largest of the same scan over seeded standard normal draws: the scan's
own null distribution, exact for white innovations, where Bonferroni over neighbouring,
nearly equal positions is far too conservative. The model (one step inside one of several
independent legs) is not a change-point library's cost, hence the explicit scan.

Steps are looked for one after another (binary segmentation by the same test: each found
step joins the base, the AR(2) is refitted to what is left). One step is an event: the
carrier's permanent field changed. Two or more are a load switched on and off that no
channel records (:func:`is_switching`): a nuisance of the null model
(:func:`switching_nuisance`), not an event.

Times are seconds from the flight's first epoch; sizes nT.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

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
        Two-sided p of the step on the prewhitened data, against the scan's own null
        distribution (corrected for the scanned positions).
    signed_nT : float
        The step with its sign (after minus before), nT.
    leg : int
        Which of the legs used it lies in (in time order).
    """

    start_s: float  # the 1 s bins either side of the step
    end_s: float
    size_nT: float
    p_value: float  # corrected for the scanned positions
    signed_nT: float = 0.0  # the step with its sign (after minus before), nT
    leg: int = -1  # which of the legs used (in time order)

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


def _bins(
    t: np.ndarray, y: np.ndarray, bin_s: float, block: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bin means of time and value, and each bin's manoeuvre block (-2 where the bin holds
    epochs of two blocks: a manoeuvre's edge)."""
    k = np.floor((t - t[0]) / bin_s).astype(int)
    counts = np.bincount(k)
    sums = np.bincount(k, weights=y)
    tb = np.bincount(k, weights=t)
    lo = np.full(counts.size, np.iinfo(np.int64).max)
    hi = np.full(counts.size, np.iinfo(np.int64).min)
    np.minimum.at(lo, k, block)
    np.maximum.at(hi, k, block)
    ok = counts > 0
    return tb[ok] / counts[ok], sums[ok] / counts[ok], np.where(lo == hi, lo, -2)[ok]


def manoeuvre_blocks(manoeuvre: np.ndarray) -> np.ndarray:
    """Each epoch's manoeuvre block (a run of one manoeuvre label, numbered in time order),
    -1 outside manoeuvres (steady flight, no label)."""
    lab = np.asarray(manoeuvre).astype(str)
    active = ~np.isin(lab, ("", "steady", "none"))
    start = active & np.r_[True, lab[1:] != lab[:-1]]
    return np.where(active, np.cumsum(start) - 1, -1)


# a further step closer than this (s) to one found is that step's edge: a step inside a
# 1 s bin, or a load's supply settling over a second, spreads over two or three bins
EDGE_S = 3.0
TREND_DEGREE = 3  # of each leg's Earth-field trend
SCAN_DRAWS = 2000  # null draws of the scan's largest |t| (p resolved to 5e-4)


@dataclass
class _LegMeans:
    """The calibration legs' 1 s means stacked: times (s), values (nT), leg of each row, the
    base design (each leg's Earth-field trend, a polynomial of :data:`TREND_DEGREE`) and the
    scanned step positions (leg, the bins either side, s)."""

    t: np.ndarray
    y: np.ndarray
    which: np.ndarray
    base: np.ndarray
    candidates: list[tuple[int, float, float]]


def _leg_means(
    time_s: np.ndarray,
    compensated_nT: np.ndarray,
    leg: np.ndarray,
    bin_s: float,
    min_leg_s: float,
    guard_s: float,
    block: np.ndarray | None = None,
) -> _LegMeans | None:
    block = np.full(time_s.size, -1) if block is None else np.asarray(block, int)
    legs = []
    for g in np.unique(leg[leg >= 0]):
        sel = (leg == g) & np.isfinite(compensated_nT)
        if sel.sum() < 2:
            continue
        t, y, b = _bins(time_s[sel], compensated_nT[sel], bin_s, block[sel])
        if t[-1] - t[0] >= min_leg_s:
            legs.append((t, y, b))
    if not legs:
        return None
    t_all = np.concatenate([t for t, _, _ in legs])
    which = np.concatenate([np.full(t.size, i) for i, (t, _, _) in enumerate(legs)])
    base, candidates = [], []
    for i, (t, _, b) in enumerate(legs):
        m = (which == i).astype(float)
        # the Earth field along a leg: smooth, but over geology on a kilometre-long leg not
        # a line (a fixed-wing's legs curve by tens of nT): a cubic in time (centred and
        # scaled, for conditioning)
        x = (t_all - t.mean()) / max(float(np.ptp(t)), 1.0)
        base += [m * x**d for d in range(TREND_DEGREE + 1)]
        # interference even in the attitude (second-order terms, rectified eddy decay)
        # has a mean while the carrier manoeuvres, which changes where a manoeuvre starts
        # or stops and settles as its amplitude builds up or dies away: no step of the
        # permanent field is looked for within guard_s of a manoeuvre's edge, as of a leg's
        idx = np.flatnonzero(_clear_of(t, _manoeuvre_edges_s(t, b), guard_s))
        candidates += [
            (i, float(t[a]), float(t[c]))
            for a, c in zip(idx[:-1], idx[1:], strict=True)
            if b[a] == b[c] and b[a] != -2
        ]
    y_all = np.concatenate([y for _, y, _ in legs])
    return _LegMeans(t_all, y_all, which, np.column_stack(base), candidates)


def _manoeuvre_edges_s(t: np.ndarray, block: np.ndarray) -> np.ndarray:
    """Where a leg's manoeuvres start or stop (s): its first and last bin, every bin that
    holds two blocks, and the midpoint between two bins of different blocks."""
    change = np.flatnonzero(block[1:] != block[:-1])
    return np.concatenate([t[[0, -1]], t[block == -2], 0.5 * (t[change] + t[change + 1])])


def _clear_of(t: np.ndarray, edges_s: np.ndarray, guard_s: float) -> np.ndarray:
    """Whether each time of ``t`` (s) lies more than ``guard_s`` from every edge."""
    return np.min(np.abs(t[:, None] - edges_s[None, :]), axis=1) > guard_s


def _step_column(m: _LegMeans, i: int, lo: float, hi: float) -> np.ndarray:
    return ((m.which == i) & (m.t > 0.5 * (lo + hi))).astype(float)


def _edge_columns(m: _LegMeans, step: CalibrationStep) -> list[np.ndarray]:
    """A found step's columns: the step, and a free level for each of the two bins either
    side of it (a step inside a bin, or one that settles over a second, leaves those bins
    between the two levels; unmodelled, they read as a second step next to the first)."""
    col = _step_column(m, step.leg, step.start_s, step.end_s)
    return [col, *((m.t == b).astype(float) for b in (step.start_s, step.end_s))]


def _scale(r: np.ndarray) -> np.ndarray:
    """Robust scale (MAD, the normal's consistent factor) of each column of ``r`` (or of a
    vector): the edges of steps not yet found are outliers in the whitened residual, which
    an RMS would count as noise (a switched load's many steps would hide each other)."""
    return stats.median_abs_deviation(r, axis=0, scale="normal")


def _scan_statistics(
    m: _LegMeans, known: np.ndarray, found: list[CalibrationStep]
) -> tuple[np.ndarray, np.ndarray, list[tuple[int, float, float]], np.ndarray]:
    """The whitened scan: each candidate step's column with the base (``known``) projected
    out and normalised (n, m), the base's orthonormal basis, the candidates (at least
    :data:`EDGE_S` from the steps ``found``) and the whitened data."""
    resid = m.y - known @ np.linalg.lstsq(known, m.y, rcond=None)[0]
    # AR(2) of the residual by least squares on its own lags, and its filter, within legs
    whiten = ar_whitener(ar_coefficients(resid, m.which, 2), m.which)
    taken = [0.5 * (f.start_s + f.end_s) for f in found]
    cands = [c for c in m.candidates if all(abs(0.5 * (c[1] + c[2]) - t) >= EDGE_S for t in taken)]
    yw, bw = whiten(m.y), whiten(known)
    q = np.linalg.svd(bw, full_matrices=False)[0]
    c = whiten(np.column_stack([_step_column(m, *x) for x in cands] or [np.zeros(m.y.size)]))
    c = c - q @ (q.T @ c)
    return c / np.maximum(np.linalg.norm(c, axis=0), 1e-12), q, cands, yw


def _scan_p_value(t_max: float, cols: np.ndarray, q: np.ndarray, draws: int = SCAN_DRAWS) -> float:
    """The scan's largest |t| (``t_max``) against its own null distribution: independent
    standard normal innovations through the same projection and scale
    (``draws``, fixed seed: the same result on every run). The statistic is free of the
    noise's scale and of the base's coefficients, so the simulation is exact for white
    innovations; it replaces Bonferroni, which neighbouring, nearly equal positions make
    far too conservative."""
    e = np.random.default_rng(0).standard_normal((q.shape[0], draws))
    e = e - q @ (q.T @ e)
    top = np.max(np.abs(cols.T @ e), axis=0) / _scale(e)
    return float((1 + np.count_nonzero(top >= t_max)) / (draws + 1))


def _next_step(
    m: _LegMeans, known: np.ndarray, found: list[CalibrationStep], alpha: float, min_size_nT: float
) -> CalibrationStep | None:
    """The most significant further step beside the columns ``known`` (the base and the
    steps ``found`` so far), at least :data:`EDGE_S` from those, if it passes the test and
    the size rule."""
    if m.y.size <= known.shape[1] + 2 + len(found):
        return None
    cols, q, cands, yw = _scan_statistics(m, known, found)
    if not cands:
        return None
    # the whitened innovations' scale without a further step (the null draws take theirs
    # the same way)
    r0 = yw - q @ (q.T @ yw)
    t = cols.T @ r0 / _scale(r0)
    j = int(np.argmax(np.abs(t)))
    i, lo, hi = cands[j]
    # the size from the unwhitened data at the located step (whitening trades a step's
    # level for its edge and biases the coefficient when phi is near the unit circle)
    # and its two edge bins free (a step inside a bin leaves that bin between the levels)
    edges = _edge_columns(m, CalibrationStep(lo, hi, 0.0, 1.0, leg=i))
    size = float(np.linalg.lstsq(np.column_stack([known, *edges]), m.y, rcond=None)[0][-3])
    a = np.column_stack([known, edges[0]])
    # a step stands out of its leg's own second-to-second scatter; an oscillation (a gimbal,
    # say) that the whitening models well enough to make a "step" significant does not. The
    # scatter of first differences (robust) is blind to other steps in the leg, which a
    # level RMS would count as scatter (a switched load's many steps)
    res_leg = (m.y - a @ np.linalg.lstsq(a, m.y, rcond=None)[0])[m.which == i]
    scatter = float(_scale(np.diff(res_leg))) / np.sqrt(2)
    if abs(size) < max(min_size_nT, 3.0 * scatter):
        return None
    p = _scan_p_value(float(abs(t[j])), cols, q)
    return CalibrationStep(lo, hi, abs(size), p, signed_nT=size, leg=i) if p < alpha else None


def calibration_steps(
    time_s: np.ndarray,
    compensated_nT: np.ndarray,
    leg: np.ndarray,
    alpha: float = 0.01,
    min_size_nT: float = 0.0,
    guard_s: float = 5.0,
    bin_s: float = 1.0,
    min_leg_s: float = 30.0,
    max_steps: int = 1,
    block: np.ndarray | None = None,
) -> list[CalibrationStep]:
    """The significant steps inside the calibration legs, found one after another.

    Each round scans every position for one more step beside those already found (their
    columns in the base, the AR(2) refitted to what is left) and keeps it when its
    scan-corrected p is below ``alpha``; the scan stops at the first round without one or at
    ``max_steps``.

    Parameters
    ----------
    time_s : ndarray
        Epoch times (s).
    compensated_nT : ndarray
        Compensated total field (nT) at those epochs; NaN where missing.
    leg : ndarray of int
        Calibration leg of each epoch (one heading of one pass), -1 outside calibration.
    alpha : float
        Significance of each round after the scan correction.
    min_size_nT : float
        Smallest step worth reporting (nT).
    guard_s, bin_s, min_leg_s : float
        Margin (s) kept from each leg's ends, averaging bin (s), shortest leg used (s).
    max_steps : int
        Most steps looked for.
    block : ndarray of int, optional
        Manoeuvre block of each epoch (:func:`manoeuvre_blocks`; -1 outside manoeuvres):
        no step is looked for at a block's edges.

    Returns
    -------
    list of CalibrationStep
        In the order found (the most significant first).
    """
    m = _leg_means(time_s, compensated_nT, leg, bin_s, min_leg_s, guard_s, block)
    if m is None or not m.candidates:
        return []
    found: list[CalibrationStep] = []
    known = m.base
    while len(found) < max_steps:
        step = _next_step(m, known, found, alpha, min_size_nT)
        if step is None:
            break
        found.append(step)
        known = np.column_stack([known, *_edge_columns(m, step)])
    return found


def is_switching(steps: list[CalibrationStep]) -> bool:
    """Whether the calibration's steps are a load switched on and off rather than one event.

    A change of the carrier's permanent field (a moved part, a load left on) happens once;
    a field that steps again and again is a current no channel records, switched at
    random or regular times: part of the null model's nuisances, not an event.
    """
    return len(steps) >= 2


def switching_nuisance(
    time_s: np.ndarray,
    compensated_nT: np.ndarray,
    leg: np.ndarray,
    steps: list[CalibrationStep],
    guard_s: float = 5.0,
    bin_s: float = 1.0,
    min_leg_s: float = 30.0,
    block: np.ndarray | None = None,
) -> dict:
    """The switched current :func:`is_switching` recognised, as an ``unexplained.nuisances``
    record: ``{"name": "unrecorded_current", "heldout_gain", "estimate"}``.

    The gain is the fraction of the calibration legs' 1 s-mean residual RMS (about each
    leg's Earth-field trend) the steps remove, in-sample: a switched level has no form to
    carry to held-out data (its times are what the data show). ``estimate``: ``form``
    ("switching"), ``switches`` found, ``step_nT`` (the median size, nT), ``rms_nT`` (the
    steps' share of the 1 s-mean residual, nT) and ``times_s`` (each step's middle, s
    from the flight's first epoch). The same arguments as :func:`calibration_steps`.
    """
    m = _leg_means(time_s, compensated_nT, leg, bin_s, min_leg_s, guard_s, block)
    cols = [c for st in steps for c in _edge_columns(m, st)]
    known = np.column_stack([m.base, *cols])

    def rms(a: np.ndarray) -> float:
        return float(np.sqrt(np.mean((m.y - a @ np.linalg.lstsq(a, m.y, rcond=None)[0]) ** 2)))

    before, after = rms(m.base), rms(known)
    return {
        "name": "unrecorded_current",
        "heldout_gain": float(1.0 - after / before) if before > 0 else 0.0,
        "estimate": {
            "form": "switching",
            "switches": len(steps),
            "step_nT": float(np.median([st.size_nT for st in steps])),
            "rms_nT": float(np.sqrt(max(before**2 - after**2, 0.0))),
            "times_s": sorted(0.5 * (st.start_s + st.end_s) for st in steps),
        },
    }
