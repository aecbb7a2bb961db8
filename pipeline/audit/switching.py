"""A current's coupling seen where the current switches: the scalar field steps with it.

A load that is switched (a payload, a strobe, a heater) changes its current within a sample
or two. A coupling of c nT per unit (a vector in the body frame) then steps the scalar
reading by dI (u . c) as it switches, u the field's direction (body frame). The calibration fit's
band-pass keeps little of a step, and a current that switches rarely may switch only a
few times during the calibration; but every switch of the whole flight shows it, the survey
included, where the field changes slowly along a straight line. Each switch gives one step:
the compensated field fitted, over a few seconds on either side, as a line (geology and the
diurnal vary slowly over those seconds) plus a multiple of the channel itself. Regressing the steps
on dI estimates the coupling from data the calibration fit never saw, and predicting each step from
the others (leave-one-out) measures the gain.

The steps are not equally good: a switch over rough ground (a fast carrier crosses an anomaly's
flank within the window) leaves the line a poor model of the geology, and one such step can
outweigh all the others in an ordinary least-squares coupling. Each step therefore carries the
standard error of its window's fit (inflated for the residual's autocorrelation) and the
coupling is their weighted mean, its spread scaled up by the steps' excess scatter when they
scatter more than their errors say.

Hand-written: no library fits steps at known instants (ruptures finds unknown ones).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from pipeline.audit.evidence import HeldOut, paired_point_gain, weighted_rms

# fitted on each side of a switch: a load settles within seconds, while over longer windows a
# fast carrier's geology is no longer a line (6 s: 360 m at 60 m/s)
WINDOW_S = 3.0
# placebo alignments of a channel against the field (:func:`placebo_inflation`): enough for a
# median; each at least a minute from the true one, longer than a load's settling
PLACEBO_SHIFTS = 60
PLACEBO_MIN_SHIFT_S = 60.0


@dataclass(frozen=True)
class SwitchSteps:
    """The field's steps at a channel's switches.

    Attributes
    ----------
    time_s : ndarray, shape (k,)
        Switch instants, s.
    change : ndarray, shape (k,)
        The channel's change across each switch (its unit).
    step_nT : ndarray, shape (k,)
        The compensated field's change with the channel across each switch, nT.
    step_se_nT : ndarray, shape (k,)
        Standard error of each step, nT.
    direction : ndarray, shape (k, 3), or None
        The field's mean direction cosines (body frame: x forward, y right, z down) over
        each switch's window, when given.
    """

    time_s: np.ndarray
    change: np.ndarray
    step_nT: np.ndarray
    step_se_nT: np.ndarray
    direction: np.ndarray | None = None


@dataclass(frozen=True)
class SwitchCoupling:
    """A channel's coupling estimated from its switches (:func:`switch_coupling`)."""

    total_field_nT_per_unit: float  # k: the field's change per unit of the channel
    se_nT_per_unit: float  # its standard error
    p_value: float  # t-test of k against none
    switches: int
    heldout: HeldOut  # leave-one-out steps without and with the coupling


def switch_instants(
    time_s: np.ndarray, channel: np.ndarray, span_s: float = 1.0, min_jump_sigma: float = 8.0
) -> np.ndarray:
    """Times (s) where ``channel`` switches: its change over ``span_s`` exceeds
    ``min_jump_sigma`` robust standard deviations of such changes (MAD) and 5 % of its
    range. A load that settles over seconds changes little from one sample to the next, so
    changes are taken over ``span_s``; each run of large changes counts once, at the middle
    of its largest change."""
    t = np.asarray(time_s, float)
    x = np.asarray(channel, float)
    if t.size < 20:
        return np.array([])
    k = max(1, int(round(span_s / float(np.median(np.diff(t))))))
    d = x[k:] - x[:-k]
    ok = np.isfinite(d)
    if ok.sum() < 10:
        return np.array([])
    sigma = float(stats.median_abs_deviation(d[ok], scale="normal"))
    span = float(np.nanpercentile(x, 99) - np.nanpercentile(x, 1))
    if span <= 0:
        return np.array([])
    big = np.flatnonzero(
        ok & (np.abs(np.where(ok, d, 0.0)) > max(min_jump_sigma * sigma, 0.05 * span))
    )
    if big.size == 0:
        return np.array([])
    runs = np.split(big, np.flatnonzero(np.diff(big) > k) + 1)
    out = []
    for r in runs:
        i = r[np.argmax(np.abs(d[r]))]
        out.append(0.5 * (t[i] + t[i + k]))
    return np.array(out)


def switch_steps(
    time_s: np.ndarray,
    field_nT: np.ndarray,
    channel: np.ndarray,
    usable: np.ndarray | None = None,
    window_s: float = WINDOW_S,
    direction: np.ndarray | None = None,
    instants_s: np.ndarray | None = None,
) -> SwitchSteps | None:
    """The field's change with the channel around each clean switch of ``channel``.

    Within ``window_s`` of a switch the field is fitted as a line (the slow field: geology
    along track, the diurnal) plus k times the channel itself, so a load that settles over
    seconds is followed as it settles; the step is k times the channel's change.

    Parameters
    ----------
    time_s : ndarray, shape (n,)
        Epoch times, s.
    field_nT : ndarray, shape (n,)
        Compensated scalar field, nT.
    channel : ndarray, shape (n,)
        The candidate channel (e.g. a current, A).
    usable : ndarray of bool, shape (n,), optional
        Epochs whose field may be used (e.g. not in turns).
    window_s : float
        Half-width of the fit window around a switch, s.
    direction : ndarray, shape (n, 3), optional
        The field's direction cosines (body frame), averaged over each window into
        ``SwitchSteps.direction``.
    instants_s : ndarray, optional
        The channel's switch times (s) when already known (:func:`switch_instants`).

    Returns
    -------
    SwitchSteps or None
        None when fewer than 4 switches have clean windows (no other switch, no gap, every
        epoch usable and finite).
    """
    t = np.asarray(time_s, float)
    y = np.asarray(field_nT, float)
    x = np.asarray(channel, float)
    use = np.ones(t.size, bool) if usable is None else np.asarray(usable, bool)
    inst = switch_instants(t, x) if instants_s is None else np.sort(np.asarray(instants_s))
    fits = _window_fits(t, y, x, use, inst, window_s)
    if fits is None or fits[0].size < 4:
        return None
    keep, a, b, change, step, se = fits
    u = None
    if direction is not None:
        dirs = np.asarray(direction, float)
        u = np.array([np.nanmean(dirs[i:j], axis=0) for i, j in zip(a, b, strict=True)])
    return SwitchSteps(inst[keep], change, step, se, u)


def _window_fits(
    t: np.ndarray, y: np.ndarray, x: np.ndarray, use: np.ndarray, inst: np.ndarray, window_s: float
) -> tuple[np.ndarray, ...] | None:
    """Every clean switch's window fitted at once (:func:`switch_steps`; the placebo
    alignments ask for thousands of windows, which one least-squares call each would spend
    most of their time setting up): (kept switch indices, window starts, ends, the channel's
    changes, the steps (nT) and their standard errors (nT)); None without a clean window.

    Each window's samples are centred on their means before the normal equations are
    formed (the field is ~50 000 nT, its steps tenths of a nT): the line's slope and the
    channel's coefficient do not change with the centring."""
    if inst.size == 0:
        return None
    lo, hi = inst - window_s, inst + window_s
    # another switch inside the window would mix two steps
    crowded = np.zeros(inst.size, bool)
    crowded[1:] |= inst[:-1] > lo[1:]
    crowded[:-1] |= inst[1:] < hi[:-1]
    a = np.searchsorted(t, lo)
    b = np.searchsorted(t, hi)
    bad = np.r_[0, np.cumsum(~use | ~np.isfinite(y) | ~np.isfinite(x))]
    ok = ~crowded & (b - a >= 10) & (bad[b] - bad[np.minimum(a, b)] == 0)
    if not ok.any():
        return None
    keep = np.flatnonzero(ok)
    a, b, ts = a[keep], b[keep], inst[keep]
    width = b - a
    col = np.arange(int(width.max()))
    inside = col[None, :] < width[:, None]
    idx = np.minimum(a[:, None] + col[None, :], t.size - 1)
    tt = t[idx] - ts[:, None]
    # both sides of the switch (not the record's end) and no sampling gap
    both = np.any(inside & (tt > 0), axis=1) & np.any(inside & (tt < 0), axis=1)
    gaps = np.where(inside[:, 1:], np.diff(tt, axis=1), 0.0).max(axis=1) <= 0.1 * window_s
    good = both & gaps
    keep, a, b, width, inside, idx, tt = (v[good] for v in (keep, a, b, width, inside, idx, tt))
    if keep.size == 0:
        return None
    w = inside.astype(float)
    after = inside & (tt > 0)
    before = inside & (tt < 0)
    xx, yy = x[idx], y[idx]
    change = (xx * after).sum(1) / after.sum(1) - (xx * before).sum(1) / before.sum(1)

    def centred(v):
        return (v - (v * w).sum(1, keepdims=True) / width[:, None]) * w

    cols = np.stack([w, centred(tt), centred(xx)], axis=2)  # (windows, samples, 3)
    yc = centred(yy)
    gram = np.einsum("wsi,wsj->wij", cols, cols)
    det = np.linalg.det(gram)
    solvable = np.isfinite(det) & (np.abs(det) > 0)
    gram[~solvable] = np.eye(3)
    inv = np.linalg.inv(gram)
    coef = np.einsum("wij,wsj,ws->wi", inv, cols, yc)
    resid = (yc - np.einsum("wsi,wi->ws", cols, coef)) * w
    dof = width - 3
    s2 = (resid**2).sum(1) / np.maximum(dof, 1)
    var = s2 * inv[:, 2, 2]
    rho = _lag1_correlations(resid, width)
    rho = np.clip(np.where(np.isfinite(rho), rho, 0.0), 0.0, 0.99)
    se = np.sqrt(var * (1.0 + rho) / (1.0 - rho))
    fine = solvable & (dof >= 3) & np.isfinite(se) & (se > 0)
    step = coef[:, 2] * change
    se = se * np.abs(change)
    return keep[fine], a[fine], b[fine], change[fine], step[fine], se[fine]


def _lag1_correlations(r: np.ndarray, width: np.ndarray) -> np.ndarray:
    """Pearson correlation of each row's ``r[:m-1]`` with its ``r[1:m]``, m the row's
    ``width`` (0 for a constant row): the residual's lag-1 autocorrelation per window."""
    col = np.arange(r.shape[1] - 1)
    pair = (col[None, :] < (width - 1)[:, None]).astype(float)
    m = np.maximum(width - 1, 1)[:, None]
    lead, lag = r[:, :-1], r[:, 1:]
    da = (lead - (lead * pair).sum(1, keepdims=True) / m) * pair
    db = (lag - (lag * pair).sum(1, keepdims=True) / m) * pair
    den = np.sqrt((da**2).sum(1) * (db**2).sum(1))
    num = (da * db).sum(1)
    return np.divide(num, den, out=np.zeros_like(num), where=den > 0)


def switch_coupling(steps: SwitchSteps, inflation: float = 1.0) -> SwitchCoupling | None:
    """Coupling as the total field sees it, k nT per unit, from the steps: step = k dI
    (weighted least squares through the origin, weights 1 / se^2; the field's direction
    changes little between switches, so the vector c = k u is not resolved), its t-test
    against no coupling (the standard error scaled by the steps' reduced chi-square when it
    exceeds 1, and by ``inflation``, :func:`placebo_inflation`) and the leave-one-out gain:
    each step predicted by the fit to the others against predicting 0, as weighted RMS (nT)
    and a one-sided signed-rank test of the standardised squares
    (:func:`pipeline.audit.evidence.paired_point_gain`; a t-test suits them badly: a few
    precise steps dominate the squares). None: fewer than 4 switches."""
    g, y, se_y = steps.change, steps.step_nT, steps.step_se_nT
    n = y.size
    if n < 4 or not np.any(g):
        return None
    coef, cov, r, h = _weighted_fit(g[:, None], y, se_y)
    k, se = float(coef[0]), float(np.sqrt(cov[0, 0])) * max(inflation, 1.0)
    p = float(2 * stats.t.sf(abs(k) / se, n - 1)) if se > 0 else 0.0
    loo = r / np.clip(1.0 - h, 1e-9, None)
    w = 1.0 / se_y**2
    z = np.sqrt(w)
    test = paired_point_gain(y * z, loo * z, rank=True)
    heldout = HeldOut(weighted_rms(y, w), weighted_rms(loo, w), test.p_value, n)
    return SwitchCoupling(
        total_field_nT_per_unit=k,
        se_nT_per_unit=se,
        p_value=p,
        switches=int(n),
        heldout=heldout,
    )


def placebo_inflation(
    time_s: np.ndarray,
    field_nT: np.ndarray,
    channel: np.ndarray,
    usable: np.ndarray | None = None,
    shifts: int = PLACEBO_SHIFTS,
    instants_s: np.ndarray | None = None,
) -> float:
    """How much wider the coupling's t statistic spreads on this flight than Student's t
    says, where no coupling can act: the channel's record moved circularly in time against
    the field by ``shifts`` offsets spread over the flight (none within
    ``PLACEBO_MIN_SHIFT_S`` of the true alignment), each shifted record's switches fitted as
    :func:`switch_steps` and :func:`switch_coupling` do. The step errors come from each
    window's own residual; a field whose structure the windows' line misreads (interference
    the model leaves that changes within seconds) makes every step's error too small, the
    same at placebo switches as at true ones. Returned: the median of |t| / the median |t| of
    Student's t with each fit's degrees of freedom, at least 1 (1 with fewer than ten
    placebo fits). ``instants_s``: the channel's switch times (s) when already known
    (:func:`switch_instants`)."""
    t = np.asarray(time_s, float)
    x = np.asarray(channel, float)
    if t.size < 20:
        return 1.0
    span = float(t[-1] - t[0])
    inst = switch_instants(t, x) if instants_s is None else np.asarray(instants_s, float)
    at = np.searchsorted(t, inst)  # moved with the record, found once
    ratios = []
    for off in np.linspace(PLACEBO_MIN_SHIFT_S, span - PLACEBO_MIN_SHIFT_S, shifts):
        k = int(np.searchsorted(t, t[0] + off))
        if k <= 0 or k >= t.size:
            continue
        moved = t[(at - k) % t.size]
        st = switch_steps(t, field_nT, np.roll(x, -k), usable=usable, instants_s=moved)
        got = None if st is None else _coupling_t(st)
        if got is not None:
            t_stat, n = got
            ratios.append(t_stat / float(stats.t.ppf(0.75, n - 1)))
    if len(ratios) < 10:
        return 1.0
    return max(1.0, float(np.median(ratios)))


def _coupling_t(steps: SwitchSteps) -> tuple[float, int] | None:
    """|t| of the coupling :func:`switch_coupling` fits to ``steps`` and the number of
    steps, without its held-out test; None where it would give no coupling or no spread."""
    g, y, se_y = steps.change, steps.step_nT, steps.step_se_nT
    if y.size < 4 or not np.any(g):
        return None
    coef, cov, _, _ = _weighted_fit(g[:, None], y, se_y)
    se = float(np.sqrt(cov[0, 0]))
    return (abs(float(coef[0])) / se, int(y.size)) if se > 0 else None


def _weighted_fit(
    a: np.ndarray, y: np.ndarray, se: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Weighted least squares of ``y`` on the columns of ``a`` (weights 1 / se^2): the
    coefficients, their covariance scaled by the reduced chi-square when it exceeds 1 (the
    steps scatter more than their errors say), the residuals and the leverages. Raises
    ``LinAlgError`` when the columns are singular."""
    sw = 1.0 / se
    aw = a * sw[:, None]
    inv = np.linalg.inv(aw.T @ aw)
    coef = inv @ aw.T @ (y * sw)
    r = y - a @ coef
    chi2 = float(np.sum((r * sw) ** 2)) / (y.size - a.shape[1])
    leverage = np.einsum("ij,jk,ik->i", aw, inv, aw)
    return coef, max(chi2, 1.0) * inv, r, leverage


@dataclass(frozen=True)
class SwitchBodyCoupling:
    """A channel's coupling as a body-frame vector, from its switches at different
    headings (:func:`switch_body_coupling`)."""

    vector_nT_per_unit: np.ndarray  # (3,) body frame: x forward, y right, z down
    covariance: np.ndarray  # (3, 3)
    nT_per_unit: float  # |c|
    ci95: tuple[float, float]  # of |c|


def switch_body_coupling(
    steps: SwitchSteps, min_switches: int = 6, inflation: float = 1.0
) -> SwitchBodyCoupling | None:
    """The coupling as a body-frame vector c: each switch's step is dI (u . c), u the field's
    direction then; switches read at different headings (survey lines, ties) resolve c's
    horizontal components, which a calibration whose current hardly varies cannot. Weighted
    least squares (weights 1 / se^2, covariance scaled by the reduced chi-square when above
    1); the interval of |c| is the range of |c'| over the ellipsoid (c' - c)' C^-1 (c' - c)
    <= t^2 (Student t, k - 3 degrees of freedom): the profile of the norm, which does not
    carry the upward bias of a noisy vector's length that percentiles of |c'| do. None:
    fewer than ``min_switches`` switches or no directions. ``inflation`` scales the
    standard errors as in :func:`switch_coupling`."""
    if steps.direction is None or steps.step_nT.size < max(min_switches, 4):
        return None
    u = steps.direction
    ok = np.all(np.isfinite(u), axis=1)
    if ok.sum() < max(min_switches, 4):
        return None
    y = steps.step_nT[ok]
    try:
        c, cov, _, _ = _weighted_fit(steps.change[ok, None] * u[ok], y, steps.step_se_nT[ok])
    except np.linalg.LinAlgError:
        return None
    cov = cov * max(inflation, 1.0) ** 2  # the placebos' spread (:func:`placebo_inflation`)
    n = y.size
    t = float(stats.t.ppf(0.975, n - 3))
    # the ellipsoid's surface: c + t L z for unit z (L L' = C), on a fixed set of directions
    z = _unit_directions()
    try:
        pts = c + t * z @ np.linalg.cholesky(cov).T
    except np.linalg.LinAlgError:
        return None
    norms = np.linalg.norm(pts, axis=1)
    inside = float(c @ np.linalg.solve(cov, c)) <= t * t  # the origin inside: |c| may be 0
    lo = 0.0 if inside else float(norms.min())
    return SwitchBodyCoupling(c, cov, float(np.linalg.norm(c)), (lo, float(norms.max())))


def _unit_directions(n: int = 2000) -> np.ndarray:
    """``n`` directions spread evenly over the unit sphere (a Fibonacci lattice)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z * z)
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])
