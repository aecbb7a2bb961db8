"""Steps in the carrier's permanent field, with the vector magnetometer as the reference.

The scalar sensor and the fluxgate measure the same Earth field, geology and day included.
Their difference,

    d(t) = T_scalar(t) - |B_vector(t)|,

is free of the Earth field's changes and holds what the two sensors do not share: the
carrier's interference at the scalar sensor (permanent, induced and eddy terms, functions of
the field's body-frame direction u and size |B|) minus the fluxgate's own errors (offsets,
scale and misalignment: ``|M b + o| ~ |b| + |b| u^T (M - I) u + u . o`` to first order, the
same basis). A change dp of the carrier's permanent field at t_s adds u . dp afterwards:

    d_k = c0 + c1 t_k + a . u_k + |B|_k u_k^T Q u_k + |B|_k^2 C[u_k, u_k, u_k]
          + l (d|B|/dt)_k + |B|_k u_k^T E du_k/dt + sum_j I_jk (g_j . u_k)
          + [t_k > t_s] u_k . dp + e_k

(``Q`` symmetric, six columns; ``C`` the ten cubic monomials of u, what interference outside
the T-L basis leaves over a whole flight's attitudes; ``l`` a timing difference of the two
sensors seen over the ground's gradients; ``E`` the eddy terms, nine columns; ``I_j`` the
recorded auxiliary channels, a current's coupling projected on u; ``c1 t`` a drift of
either sensor). Over the whole flight (lines, ties, turns and calibration at every heading) the
direction-cosine coefficients are pinned on both sides of t_s, so a step shows at its full
size u . dp, whatever heading the lines before and after it were flown on; the crossovers
see only the heading levels' change.

The 1 s means are used (the fluxgate's noise, 0.5-1 nT a reading, averages down; the eddy
terms of manoeuvres largely cancel), the model is prewhitened by an AR(2) of its own
residual (the residual of 1 s means is strongly autocorrelated: turns, manoeuvre blocks,
unmodelled interference), each whitened row is weighted by the residual's local RMS (it
varies tenfold between manoeuvres and straight lines), the F statistics are divided by what
correlation the whitening leaves at a minute's scale, and the scan's maximum F statistic is
compared with its own null distribution (standard normal draws through the same whitened
designs, fixed seed).

Times are seconds from the flight's first epoch; fields nT; u in the body frame (x forward,
y right, z down) as the fluxgate reads it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats
from scipy.ndimage import uniform_filter1d

from pipeline.audit.prewhiten import ar_coefficients, ar_whitener

AR_ORDER = 2
SCAN_SIMULATIONS = 500


@dataclass
class VectorStep:
    """A step in the scalar-minus-vector difference (:func:`vector_reference_step`).

    Attributes
    ----------
    start_s, end_s : float
        Span of the change points the data cannot tell from the likeliest (95 %
        profile-likelihood set), s from the flight's first epoch.
    time_s : float
        The likeliest change point, s.
    size_nT : float
        ``|dp|``, the body-frame change of the permanent field, nT.
    dp_nT : ndarray
        The body-frame change (x forward, y right, z down), nT.
    p_value : float
        The scan's maximum F statistic against its own null distribution.
    f_stat : float
        That maximum F statistic (3 numerator degrees of freedom, on whitened data).
    f_null_95 : float
        95 % point of the scan's maximum F with no step (its null draws).
    ar : tuple of float
        The AR(2) coefficients the model was prewhitened with.
    variance_inflation : float
        The whitened residual's minute means' variance over white noise's (at least 1); the
        F statistics were divided by it.
    """

    start_s: float
    end_s: float
    time_s: float
    size_nT: float
    dp_nT: np.ndarray
    p_value: float
    f_stat: float
    f_null_95: float = float("nan")
    ar: tuple[float, ...] = ()
    variance_inflation: float = 1.0

    def to_dict(self, t0_ns: int) -> dict:
        """The step as an ``unexplained.events`` record with absolute times (ns).

        Parameters
        ----------
        t0_ns : int
            The flight's first epoch, ns; the times here count from it.

        Returns
        -------
        dict
            ``kind`` ("step"), ``start_ns``, ``end_ns``, ``likeliest_ns``, ``size_nT``,
            ``dp_body_nT``, ``p_value`` and ``evidence``.
        """
        return {
            "kind": "step",
            "start_ns": int(t0_ns + round(self.start_s * 1e9)),
            "end_ns": int(t0_ns + round(self.end_s * 1e9)),
            "likeliest_ns": int(t0_ns + round(self.time_s * 1e9)),
            "size_nT": float(self.size_nT),
            "dp_body_nT": [float(x) for x in self.dp_nT],
            "p_value": float(self.p_value),
            "evidence": "vector reference",
        }


def _bin_means(t: np.ndarray, cols: np.ndarray, bin_s: float):
    """Means of the rows of ``cols`` over ``bin_s`` bins of ``t``; the bins' indices."""
    k = np.floor((t - t[0]) / bin_s).astype(int)
    counts = np.bincount(k)
    ok = counts > 0
    sums = np.stack([np.bincount(k, weights=c) for c in cols.T], axis=1)
    return sums[ok] / counts[ok, None], np.flatnonzero(ok)


def difference_design(
    time_s: np.ndarray,
    scalar_nT: np.ndarray,
    vector_nT: np.ndarray,
    aux: dict[str, np.ndarray] | None = None,
    bin_s: float = 1.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The 1 s means of the scalar-minus-vector difference and of the model's columns.

    Parameters
    ----------
    time_s : ndarray
        Epoch times (s), increasing.
    scalar_nT : ndarray
        Scalar total field (nT) at those epochs.
    vector_nT : ndarray
        (n, 3) fluxgate reading at the same epochs, body frame (x forward, y right, z down), nT.
    aux : dict of ndarray, optional
        Recorded auxiliary channels at the epochs (any unit): each adds ``I u`` columns.
    bin_s : float
        Averaging bin, s.

    Returns
    -------
    tb : ndarray
        The bins' centres, s.
    y : ndarray
        The bins' mean difference, nT.
    base : ndarray
        (m, k) the model's columns without a step (see the module docstring).
    u : ndarray
        (m, 3) the bins' mean direction cosines (the step's columns before the switch).
    block : ndarray of int
        Contiguous block of each bin (a new block after a gap of more than 2 bins), for the
        prewhitening.
    """
    b = np.linalg.norm(vector_nT, axis=1)
    ok = np.isfinite(scalar_nT) & np.isfinite(b) & (b > 0)
    # a channel recorded on most epochs joins (its gaps drop those epochs); a sparse one
    # would drop the flight
    aux = {k: np.asarray(v, float) for k, v in (aux or {}).items()}
    aux = {k: v for k, v in aux.items() if np.mean(np.isfinite(v)) >= 0.9}
    for v in aux.values():
        ok &= np.isfinite(v)
    if ok.sum() < 3:
        e = np.empty(0)
        return e, e, np.empty((0, 1)), np.empty((0, 3)), np.empty(0, int)
    t, s, vec, b = time_s[ok], scalar_nT[ok], vector_nT[ok], b[ok]
    u = vec / b[:, None]
    b0 = float(np.median(b))
    # the timing term: d|B|/dt over the ground's gradients (np.gradient on uneven epochs)
    db = np.gradient(b, t) if t.size > 2 else np.zeros_like(b)
    tc = (t - t.mean()) / max(float(np.ptp(t)), 1.0)
    cols = [np.ones_like(t), tc, u[:, 0], u[:, 1], u[:, 2]]
    bs = b / b0  # scaled: a 1e-3 coefficient is b0 * 1e-3 nT
    for i in range(3):
        for j in range(i, 3):
            cols.append(bs * u[:, i] * u[:, j])
    # third order in the direction (a second-order induced field, b Q b / |B|, and any
    # interference outside the T-L basis that is a smooth function of the attitude): fitted
    # over one calibration box it hides in the T-L terms, over a whole flight's headings it
    # leaves nT
    for i in range(3):
        for j in range(i, 3):
            for k in range(j, 3):
                cols.append(bs**2 * u[:, i] * u[:, j] * u[:, k])
    cols.append(db)
    # the eddy terms (and the scalar's interference read a little earlier or later than
    # the fluxgate): |B| u_i du_j/dt, large only while the attitude changes fast
    du = np.gradient(u, t, axis=0) if t.size > 2 else np.zeros_like(u)
    for i in range(3):
        for j in range(3):
            cols.append(bs * u[:, i] * du[:, j])
    for v in aux.values():
        sd = float(np.std(v))
        if sd > 0:
            for i in range(3):
                cols.append((v - v.mean()) / sd * u[:, i])
    x = np.column_stack([s - b, *cols, u])
    means, idx = _bin_means(t, x, bin_s)
    tb = t[0] + (idx + 0.5) * bin_s
    block = np.concatenate([[0], np.cumsum(np.diff(idx) > 2)])
    return tb, means[:, 0], means[:, 1:-3], means[:, -3:], block


def _step_bases(q0: np.ndarray, steps_w: list[np.ndarray]) -> np.ndarray:
    """(n, 3 m) orthonormal bases of the m whitened step designs' parts orthogonal to the
    base's columns (``q0``, orthonormal); zeros for a design the base already spans."""
    out = np.zeros((q0.shape[0], 3 * len(steps_w)))
    for i, sw in enumerate(steps_w):
        s = sw - q0 @ (q0.T @ sw)
        qs, rs = np.linalg.qr(s)
        d = np.abs(np.diag(rs))
        if d.min() > 1e-9 * d.max():
            out[:, 3 * i : 3 * i + 3] = qs
    return out


def _scan_f(y: np.ndarray, q0: np.ndarray, qs: np.ndarray) -> np.ndarray:
    """F statistics (3 numerator df) of each scanned step against the base, (m, columns of
    ``y``): one matrix product for all positions and all columns (the null draws)."""
    y = y if y.ndim == 2 else y[:, None]
    r0 = y - q0 @ (q0.T @ y)
    rss0 = np.sum(r0**2, axis=0)
    dof = q0.shape[0] - q0.shape[1] - 3
    proj = qs.T @ r0
    gain = (proj**2).reshape(-1, 3, y.shape[1]).sum(axis=1)
    return (gain / 3.0) / ((rss0 - gain) / dof)


def scan_vector_reference(
    time_s: np.ndarray,
    scalar_nT: np.ndarray,
    vector_nT: np.ndarray,
    aux: dict[str, np.ndarray] | None = None,
    guard_s: float = 120.0,
    scan_every_s: float = 5.0,
    bin_s: float = 1.0,
    scale_window_s: float = 31.0,
    vif_window_s: float = 60.0,
    seed: int = 0,
) -> VectorStep | None:
    """The likeliest step in the carrier's permanent field against the fluxgate, with its
    scan-corrected p (significant or not; :func:`vector_reference_step` keeps it or not).

    Parameters
    ----------
    time_s : ndarray
        Epoch times (s from the flight's first epoch), increasing.
    scalar_nT : ndarray
        Scalar total field (nT).
    vector_nT : ndarray
        (n, 3) fluxgate reading on the same epochs, body frame (x forward, y right, z down), nT.
    aux : dict of ndarray, optional
        Recorded auxiliary channels on the epochs (a switched current would otherwise be a
        step).
    guard_s : float
        Change points are scanned at least this far from the record's ends (s): the model's
        30-odd direction coefficients need data at varied attitudes on both sides.
    scan_every_s : float
        Spacing of the scanned change points, s.
    bin_s : float
        Averaging bin, s.
    seed : int
        Seed of the null simulations (fixed: the same answer every run).

    Returns
    -------
    VectorStep or None
        The likeliest step; None when the record is too short for the model (fewer than
        four bins a column, or shorter than four guards).
    """
    tb, y, base, u, block = difference_design(time_s, scalar_nT, vector_nT, aux, bin_s)
    n, k0 = base.shape
    if n < 4 * (k0 + 3) or tb[-1] - tb[0] < 4 * guard_s:
        return None
    grid = np.arange(tb[0] + guard_s, tb[-1] - guard_s, scan_every_s)
    steps = [u * (tb > ts)[:, None] for ts in grid]
    # the scan twice: the whitening and the weights below come from the model's residual,
    # and a large step left in it both pulls the AR(2) towards a random walk (which whitens
    # a step into one bin) and raises the local RMS around itself, so the step weighs itself
    # down. The second scan takes both from the residual with the first scan's likeliest
    # step in.
    with_step = None
    for _ in range(2):
        a0 = base if with_step is None else np.column_stack([base, with_step])
        coef0, *_ = np.linalg.lstsq(a0, y, rcond=None)
        phi = ar_coefficients(y - a0 @ coef0, block, AR_ORDER)
        whiten = ar_whitener(phi, block)
        yw, bw = whiten(y), whiten(base)
        # the residual's size varies tenfold over a flight (manoeuvres and turns leave nT
        # of eddy and lagging-eddy field the columns do not hold, straight lines a few
        # tenths): an equal-weight F test let a manoeuvre block's misfit pass for a step (a
        # 40 nT "step" inside a calibration). Each whitened row is weighted by the local RMS
        # of the model's whitened residual (a centred ``scale_window_s`` mean of its square).
        aw = bw if with_step is None else np.column_stack([bw, whiten(with_step)])
        cw, *_ = np.linalg.lstsq(aw, yw, rcond=None)
        r2 = uniform_filter1d((yw - aw @ cw) ** 2, int(scale_window_s / bin_s) | 1, mode="nearest")
        scale = np.sqrt(np.maximum(r2, 0.25 * np.median(r2)))
        yw, bw = yw / scale, bw / scale[:, None]
        # an orthonormal basis of the columns' span: some are (nearly) dependent on the
        # sphere (sum_i u_i^2 = 1, sum_i u_i du_i/dt = 0), which a QR would keep as noise
        # directions
        uu, sv, _ = np.linalg.svd(bw, full_matrices=False)
        q0 = uu[:, sv > 1e-8 * sv[0]]
        k0 = q0.shape[1]
        steps_w = [whiten(st) / scale[:, None] for st in steps]
        qs = _step_bases(q0, steps_w)
        f = _scan_f(yw, q0, qs)[:, 0]
        i = int(np.argmax(f))
        with_step = steps[i]
    nw = yw.size
    # what the AR(2) and the weights leave of the slow correlation, measured on the
    # residual with the likeliest step in (a step would otherwise inflate it): the variance
    # of minute means against that of white noise; the F statistics shrink by it
    q1 = qs[:, 3 * i : 3 * i + 3]
    r1 = yw - q0 @ (q0.T @ yw) - q1 @ (q1.T @ yw)
    m = int(round(vif_window_s / bin_s))
    nb = r1.size // m
    if nb >= 10:
        means = r1[: nb * m].reshape(nb, m).mean(axis=1)
        vif = max(1.0, float(m * np.var(means) / np.var(r1)))
    else:
        vif = 1.0
    f = f / vif
    e = np.random.default_rng(seed).standard_normal((nw, SCAN_SIMULATIONS))
    f_null = _scan_f(e, q0, qs).max(axis=0)
    p = (1 + int(np.sum(f_null >= f[i]))) / (SCAN_SIMULATIONS + 1)
    # the size on the unwhitened data at the likeliest change point
    a = np.column_stack([base, steps[i]])
    coef, *_ = np.linalg.lstsq(a, y, rcond=None)
    dp = coef[-3:]
    # 95 % profile-likelihood set of the change point: RSS within the chi2(1) bound, from
    # the deflated F (a set as wide as the left-over slow correlation warrants)
    rss0 = float(np.sum((yw - q0 @ (q0.T @ yw)) ** 2))
    dof = nw - k0 - 3
    rss = rss0 - 3 * f * rss0 / (dof + 3 * f)  # from F = (gain/3) / ((rss0-gain)/dof)
    s2 = rss[i] / dof
    inside = rss <= rss[i] + stats.chi2.ppf(0.95, 1) * s2
    lo, hi = float(grid[inside].min()), float(grid[inside].max())
    # a change between two scanned points is fitted at one of them, and a bin's mean holds
    # either side of one inside it: the span reaches a scan step and half a bin further
    pad = scan_every_s + 0.5 * bin_s
    return VectorStep(
        lo - pad,
        hi + pad,
        float(grid[i]),
        float(np.linalg.norm(dp)),
        dp,
        p,
        float(f[i]),
        float(np.quantile(f_null, 0.95)),
        tuple(float(x) for x in phi),
        vif,
    )


def vector_reference_step(
    time_s: np.ndarray,
    scalar_nT: np.ndarray,
    vector_nT: np.ndarray,
    aux: dict[str, np.ndarray] | None = None,
    alpha: float = 0.01,
    min_size_nT: float = 1.0,
    min_f_ratio: float = 8.0,
    **scan,
) -> VectorStep | None:
    """A significant step in the carrier's permanent field against the fluxgate
    (:func:`scan_vector_reference`), or None.

    Parameters
    ----------
    time_s, scalar_nT, vector_nT, aux
        As :func:`scan_vector_reference` (s, nT, body-frame nT).
    alpha : float
        Significance of the scan-corrected p.
    min_size_nT : float
        Smallest ``|dp|`` reported, nT.
    min_f_ratio : float
        Smallest ratio of the scan's F statistic to the 95 % point of its null maximum. The
        null (Gaussian, whitened, weighted) is not the whole truth: interference outside the
        model (lagging eddy fields in manoeuvres, unrecorded switched currents) lifts a clean
        flight's F a few times above that point, a step of a few nT lifts it by one to three
        orders of magnitude: the ratio is a margin between the two.
    **scan
        Further arguments of :func:`scan_vector_reference`.

    Returns
    -------
    VectorStep or None
        The likeliest step when its p is below ``alpha`` and ``|dp|`` at least
        ``min_size_nT``.
    """
    step = scan_vector_reference(time_s, scalar_nT, vector_nT, aux, **scan)
    if (
        step is not None
        and step.p_value < alpha
        and step.size_nT >= min_size_nT
        and step.f_stat >= min_f_ratio * step.f_null_95
    ):
        return step
    return None
