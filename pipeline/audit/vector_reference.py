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
          + l (d|B|/dt)_k + |B|_k u_k^T E du_k/dt + sum_tau h_tau * (|B| u^T E_tau du/dt)_k
          + sum_j I_jk (g_j . u_k) + [t_k > t_s] u_k . dp + e_k

(``Q`` symmetric, six columns; ``C`` the ten cubic monomials of u, what interference outside
the T-L basis leaves over a whole flight's attitudes; ``l`` a timing difference of the two
sensors seen over the ground's gradients; ``E`` the eddy terms, nine columns, and ``E_tau``
the same through a first-order response ``h_tau`` (eddy currents that decay,
:data:`EDDY_DECAY_TAUS_S`); ``I_j`` the recorded auxiliary channels, a current's coupling
projected on u; ``c1 t`` a drift of either sensor). Over the whole flight (lines, ties,
turns and calibration at every heading) the direction-cosine coefficients are pinned on both
sides of t_s, so a step shows at its full size u . dp, whatever heading the lines before and
after it were flown on; the crossovers see only the heading levels' change.

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
from scipy.signal import lfilter

from pipeline.audit.prewhiten import ar_coefficients, ar_whitener, kept_rows

AR_ORDER = 2
# decay times (s) of the eddy currents the difference's model holds beside the
# instantaneous eddy terms: a carrier skin's L/R of 0.2-1.5 s (the audit's null model takes
# such a decay), which two first-order responses span; faster decays are the eddy terms to
# first order in w tau over 1 s means
EDDY_DECAY_TAUS_S = (0.3, 1.0)
SCAN_SIMULATIONS = 500
# the scan's F over its Gaussian null's 95 % point that a step must reach: that ratio's
# quantile at the event test's level on simulated step-free flights
# (benchmarks/bench_fluxgate_step_margin.py; AuditSettings.fluxgate_step_margin)
STEP_MARGIN = 5.7


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


def bin_means(t: np.ndarray, cols: np.ndarray, bin_s: float):
    """Means of the rows of ``cols`` (n, k) over ``bin_s`` bins of ``t`` (s); the occupied
    bins' indices."""
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
    cols = _difference_columns(t, b, u, [v[ok] for v in aux.values()])
    x = np.column_stack([s - b, *cols, u])
    means, idx = bin_means(t, x, bin_s)
    tb = t[0] + (idx + 0.5) * bin_s
    block = np.concatenate([[0], np.cumsum(np.diff(idx) > 2)])
    return tb, means[:, 0], means[:, 1:-3], means[:, -3:], block


def _difference_columns(
    t: np.ndarray, b: np.ndarray, u: np.ndarray, aux: list[np.ndarray]
) -> list[np.ndarray]:
    """The model's columns of the scalar-minus-vector difference on the epochs (times ``t``,
    s; fluxgate magnitude ``b``, nT, and direction cosines ``u``; the aux channels):
    level, drift, the carrier's permanent, induced, third-order and eddy terms (instantaneous
    and decaying), the timing term and ``I u`` per channel (the module docstring)."""
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
    eddy = [bs * u[:, i] * du[:, j] for i in range(3) for j in range(3)]
    cols += eddy
    # eddy currents that decay: the eddy terms through first-order responses (the epochs
    # taken as evenly spaced at their median step)
    dt = float(np.median(np.diff(t))) if t.size > 2 else 1.0
    for tau in EDDY_DECAY_TAUS_S:
        a = np.exp(-dt / tau)
        cols += [lfilter([1.0 - a], [1.0, -a], c) for c in eddy]
    for v in aux:
        sd = float(np.std(v))
        if sd > 0:
            for i in range(3):
                cols.append((v - v.mean()) / sd * u[:, i])
    return cols


def _span_basis(a: np.ndarray) -> np.ndarray:
    """An orthonormal basis (n, r) of the span of the columns of ``a`` (n, k): its left
    singular vectors above 1e-8 of the largest singular value. Some of the difference's
    columns are (nearly) dependent on the sphere (sum_i u_i^2 = 1, sum_i u_i du_i/dt = 0),
    which a QR would keep as noise directions."""
    uu, sv, _ = np.linalg.svd(a, full_matrices=False)
    return uu[:, sv > 1e-8 * sv[0]]


def _step_bases(q0: np.ndarray, steps_w: list[np.ndarray]) -> np.ndarray:
    """(n, 3 m) orthonormal bases of the m whitened step designs' parts orthogonal to the
    base's columns (``q0``, orthonormal); zeros for a design the base already spans, even in
    part (a direction under 1e-9 of the design's own largest column: relative to what is
    left after the projection, a wholly spanned design's rounding noise would pass)."""
    out = np.zeros((q0.shape[0], 3 * len(steps_w)))
    for i, sw in enumerate(steps_w):
        s = sw - q0 @ (q0.T @ sw)
        qs, rs = np.linalg.qr(s)
        d = np.abs(np.diag(rs))
        if d.min() > 1e-9 * np.linalg.norm(sw, axis=0).max():
            out[:, 3 * i : 3 * i + 3] = qs
    return out


def _suffix_sums(x: np.ndarray) -> np.ndarray:
    """Sums of the rows of ``x`` from each row to the last (one more row: zeros)."""
    out = np.zeros((x.shape[0] + 1, *x.shape[1:]))
    np.cumsum(x[::-1], axis=0, out=out[-2::-1])
    return out


@dataclass
class _StepScan:
    """Every scanned step design at once, without forming any of them.

    The whitened step design of a change before bin j, ``W(u [k >= j])``, equals the whitened
    direction cosines ``W(u)`` on every row at least ``p`` (the AR order) past j, is zero
    before j and differs only on the ``p`` rows from j (the filter reaches back into the
    zeros). So each design's products with the data and the base are sums of ``W(u)``'s row
    products from one row on (suffix sums, computed once) plus ``p`` edge rows: the scan
    costs O(n) whatever the number of change points, where the designs themselves are O(n)
    each. Rows are the whitened, weighted rows (``kept``: their bins).
    """

    wu: np.ndarray  # (nw, 3) W(u) / scale
    start: np.ndarray  # (m,) first row where a design equals wu
    edge_row: np.ndarray  # (m, p) rows of the edge values
    edge: np.ndarray  # (m, p, 3) the designs' values there (0: not a whitened row)
    chol: np.ndarray  # (m, 3, 3) Cholesky factors of the designs' Gram matrices off the base
    ok: np.ndarray  # (m,) False: the base (nearly) spans the design

    @classmethod
    def build(cls, u, tb, grid, phi, kept, wu, scale, q0) -> _StepScan:
        """The scan's designs: ``u`` (n, 3) per bin, ``tb`` the bins' times, ``grid`` the
        change points (s), ``phi`` the AR coefficients, ``kept`` the whitened rows' bins,
        ``wu`` the whitened, weighted ``u``, ``scale`` the rows' weights, ``q0`` the base."""
        p, n, nw = phi.size, u.shape[0], wu.shape[0]
        j = np.searchsorted(tb, grid, side="right")  # the first bin after each change
        start = np.searchsorted(kept, j + p)
        edge_row = np.zeros((j.size, p), int)
        edge = np.zeros((j.size, p, 3))
        for d in range(p):
            k = np.minimum(j + d, n - 1)
            r = np.minimum(np.searchsorted(kept, k), nw - 1)
            v = u[k].copy()
            for lag in range(d):  # the filter's terms that reach rows at or after j
                v -= phi[lag] * u[k - 1 - lag]
            here = (kept[r] == k) & (j + d < n)
            edge_row[:, d] = r
            edge[:, d] = np.where(here[:, None], v / scale[r][:, None], 0.0)
        gram = _suffix_sums(wu[:, :, None] * wu[:, None, :])[start]
        gram += np.einsum("mdi,mdj->mij", edge, edge)
        cross = _suffix_sums(q0[:, :, None] * wu[:, None, :])[start]
        cross += np.einsum("mdk,mdi->mki", q0[edge_row], edge)
        gram -= np.einsum("mki,mkj->mij", cross, cross)
        chol, ok = _cholesky3(gram)
        return cls(wu, start, edge_row, edge, chol, ok)

    def f_stats(self, y: np.ndarray, q0: np.ndarray, chunk: int = 64) -> np.ndarray:
        """F statistics (3 numerator df) of each scanned step against the base, (m, columns
        of ``y``), ``chunk`` columns at a time."""
        y = y if y.ndim == 2 else y[:, None]
        out = np.zeros((self.start.size, y.shape[1]))
        dof = q0.shape[0] - q0.shape[1] - 3
        for c in range(0, y.shape[1], chunk):
            r0 = y[:, c : c + chunk]
            r0 = r0 - q0 @ (q0.T @ r0)
            rss0 = np.sum(r0**2, axis=0)
            b = _suffix_sums(self.wu[:, :, None] * r0[:, None, :])[self.start]
            b += np.einsum("mdi,mdc->mic", self.edge, r0[self.edge_row])
            z0 = b[:, 0] / self.chol[:, 0, 0, None]
            z1 = (b[:, 1] - self.chol[:, 1, 0, None] * z0) / self.chol[:, 1, 1, None]
            z2 = (
                b[:, 2] - self.chol[:, 2, 0, None] * z0 - self.chol[:, 2, 1, None] * z1
            ) / self.chol[:, 2, 2, None]
            gain = np.where(self.ok[:, None], z0**2 + z1**2 + z2**2, 0.0)
            out[:, c : c + chunk] = (gain / 3.0) / ((rss0 - gain) / dof)
        return out


def _cholesky3(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cholesky factors of a stack of 3 x 3 symmetric matrices, and which are positive
    definite with a condition the scan trusts (the factor's diagonal within 1e6 of itself:
    the Gram matrices come from sums, which carry rounding of order 1e-16 of the designs'
    squared size)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        l00 = np.sqrt(a[:, 0, 0])
        l10, l20 = a[:, 1, 0] / l00, a[:, 2, 0] / l00
        l11 = np.sqrt(a[:, 1, 1] - l10**2)
        l21 = (a[:, 2, 1] - l20 * l10) / l11
        l22 = np.sqrt(a[:, 2, 2] - l20**2 - l21**2)
    chol = np.zeros_like(a)
    chol[:, 0, 0], chol[:, 1, 0], chol[:, 2, 0] = l00, l10, l20
    chol[:, 1, 1], chol[:, 2, 1], chol[:, 2, 2] = l11, l21, l22
    d = np.column_stack([l00, l11, l22])
    ok = np.all(np.isfinite(chol.reshape(len(a), -1)), axis=1) & (d.min(axis=1) > 0)
    ok &= d.min(axis=1) > 1e-6 * d.max(axis=1)
    chol[~ok] = np.eye(3)
    return chol, ok


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
    design: tuple[np.ndarray, ...] | None = None,
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
    design : tuple, optional
        :func:`difference_design` of these arguments at ``bin_s``, when the caller has it.

    Returns
    -------
    VectorStep or None
        The likeliest step; None when the record is too short for the model (fewer than
        four bins a column, or shorter than four guards).
    """
    if design is None:
        design = difference_design(time_s, scalar_nT, vector_nT, aux, bin_s)
    tb, y, base, u, block = design
    n, k0 = base.shape
    if n < 4 * (k0 + 3) or tb[-1] - tb[0] < 4 * guard_s:
        return None
    grid = np.arange(tb[0] + guard_s, tb[-1] - guard_s, scan_every_s)
    sp, with_step = _located_scan(tb, y, base, u, block, grid, scale_window_s / bin_s)
    i = sp.best
    vif = _slow_correlation(sp, with_step, vif_window_s / bin_s)
    f = sp.f / vif
    e = np.random.default_rng(seed).standard_normal((sp.yw.size, SCAN_SIMULATIONS))
    f_null = sp.scan.f_stats(e, sp.q0).max(axis=0)
    p = (1 + int(np.sum(f_null >= f[i]))) / (SCAN_SIMULATIONS + 1)
    # the size on the unwhitened data at the likeliest change point
    coef, *_ = np.linalg.lstsq(np.column_stack([base, with_step]), y, rcond=None)
    dp = coef[-3:]
    lo, hi = _change_point_set(sp, f, grid)
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
        tuple(float(x) for x in sp.phi),
        vif,
    )


@dataclass
class _ScanPass:
    """One pass of the change-point scan (:func:`_scan_pass`): the AR coefficients and
    whitener of the model's residual, each bin's weight, the weighted whitened data ``yw``,
    an orthonormal basis ``q0`` of the weighted whitened columns, the scan, its F per change
    point and the likeliest one's index."""

    phi: np.ndarray
    whiten: object
    scale: np.ndarray
    yw: np.ndarray
    q0: np.ndarray
    scan: _StepScan
    f: np.ndarray
    best: int


def _located_scan(tb, y, base, u, block, grid, window_bins: float) -> tuple[_ScanPass, np.ndarray]:
    """The whitened, weighted scan (:func:`_scan_pass`) and its likeliest step's columns.

    The whitening and the weights come from the model's residual, and a large step left in
    it both pulls the AR(2) towards a random walk (which whitens a step into one bin) and
    raises the local RMS around itself, so the step weighs itself down: a scan whitened
    without it can miss it altogether. So the first scan is plain least squares (nothing
    estimated from the residual), and each of two whitened scans takes the AR(2) and the
    weights from the residual with the previous scan's likeliest step in."""
    with_step = u * (tb > grid[_least_squares_best(tb, y, base, u, grid)])[:, None]
    for _ in range(2):
        sp = _scan_pass(tb, y, base, u, block, grid, with_step, window_bins)
        with_step = u * (tb > grid[sp.best])[:, None]
    return sp, with_step


def _least_squares_best(tb, y, base, u, grid) -> int:
    """The index in ``grid`` of the likeliest step ``u [tb > t]`` against ``base`` by
    ordinary least squares (no whitening, equal weights; :class:`_StepScan` with an AR order
    of 0): where the step's three columns take the most of the residual."""
    q0 = _span_basis(base)
    n = y.size
    scan = _StepScan.build(u, tb, grid, np.zeros(0), np.arange(n), u, np.ones(n), q0)
    return int(np.argmax(scan.f_stats(y, q0)[:, 0]))


def _scan_pass(tb, y, base, u, block, grid, with_step, scale_window_bins: float) -> _ScanPass:
    """The F of a step ``u [tb > t]`` at every change point of ``grid`` against ``base``,
    whitened by the AR(2) of the residual of ``base`` (and ``with_step``, the last pass's
    likeliest step, when given) and weighted by that residual's local RMS."""
    a0 = base if with_step is None else np.column_stack([base, with_step])
    coef0, *_ = np.linalg.lstsq(a0, y, rcond=None)
    phi = ar_coefficients(y - a0 @ coef0, block, AR_ORDER)
    whiten, kept = ar_whitener(phi, block), kept_rows(block, AR_ORDER)
    yw, bw = whiten(y), whiten(base)
    # the residual's size varies tenfold over a flight (manoeuvres and turns leave nT of
    # eddy and lagging-eddy field the columns do not hold, straight lines a few tenths): an
    # equal-weight F test let a manoeuvre block's misfit pass for a step (a 40 nT "step"
    # inside a calibration). Each whitened row is weighted by the local RMS of the model's
    # whitened residual (a centred ``scale_window_s`` mean of its square).
    aw = bw if with_step is None else np.column_stack([bw, whiten(with_step)])
    cw, *_ = np.linalg.lstsq(aw, yw, rcond=None)
    r2 = uniform_filter1d((yw - aw @ cw) ** 2, int(scale_window_bins) | 1, mode="nearest")
    scale = np.sqrt(np.maximum(r2, 0.25 * np.median(r2)))
    yw, bw = yw / scale, bw / scale[:, None]
    q0 = _span_basis(bw)
    scan = _StepScan.build(u, tb, grid, phi, kept, whiten(u) / scale[:, None], scale, q0)
    f = scan.f_stats(yw, q0)[:, 0]
    return _ScanPass(phi, whiten, scale, yw, q0, scan, f, int(np.argmax(f)))


def _slow_correlation(sp: _ScanPass, with_step: np.ndarray, window_bins: float) -> float:
    """What the AR(2) and the weights leave of the slow correlation, measured on the
    residual with the likeliest step in (a step would otherwise inflate it): the variance of
    the means over ``window_bins`` bins against that of white noise (at least 1); the F
    statistics shrink by it."""
    q1 = _step_bases(sp.q0, [sp.whiten(with_step) / sp.scale[:, None]])
    r1 = sp.yw - sp.q0 @ (sp.q0.T @ sp.yw) - q1 @ (q1.T @ sp.yw)
    m = int(round(window_bins))
    nb = r1.size // m
    if nb < 10:
        return 1.0
    means = r1[: nb * m].reshape(nb, m).mean(axis=1)
    return max(1.0, float(m * np.var(means) / np.var(r1)))


def _change_point_set(sp: _ScanPass, f: np.ndarray, grid: np.ndarray) -> tuple[float, float]:
    """The 95 % profile-likelihood set of the change point (first and last time, s): the
    change points whose RSS lies within the chi2(1) bound of the likeliest's, from the
    deflated F (a set as wide as the left-over slow correlation warrants)."""
    rss0 = float(np.sum((sp.yw - sp.q0 @ (sp.q0.T @ sp.yw)) ** 2))
    dof = sp.yw.size - sp.q0.shape[1] - 3
    rss = rss0 - 3 * f * rss0 / (dof + 3 * f)  # from F = (gain/3) / ((rss0-gain)/dof)
    s2 = rss[sp.best] / dof
    inside = rss <= rss[sp.best] + stats.chi2.ppf(0.95, 1) * s2
    return float(grid[inside].min()), float(grid[inside].max())


def persists_against_fluxgate(
    time_s: np.ndarray,
    scalar_nT: np.ndarray,
    vector_nT: np.ndarray,
    t_s: float,
    off_window_s: tuple[float, float],
    aux: dict[str, np.ndarray] | None = None,
    bin_s: float = 1.0,
    design: tuple[np.ndarray, ...] | None = None,
) -> bool | None:
    """Whether a change of the carrier's field at ``t_s`` persists, read in the
    scalar-minus-vector difference: ``u . dp`` from ``t_s`` to the record's end fits the
    difference's 1 s means better than the same three columns switched off again at the
    best time inside ``off_window_s`` (a load switched off where no step is looked for, in
    the turn after its leg, say).

    The two models have the same columns and differ only after the switch-off, so the
    smaller residual sum of squares is the likelier; a change that persists leaves ``u .
    dp`` on every later reading (hours of survey), which no early switch-off fits.

    Parameters
    ----------
    time_s, scalar_nT, vector_nT, aux
        As :func:`scan_vector_reference` (s from the flight's first epoch, nT, body-frame nT;
        the fluxgate calibrated against the scalar).
    t_s : float
        The change's time, s.
    off_window_s : tuple of float
        Earliest and latest switch-off times tried, s.
    bin_s : float
        Averaging bin, s.
    design : tuple, optional
        :func:`difference_design` of these arguments at ``bin_s``, when the caller has it.

    Returns
    -------
    bool or None
        None when the record holds too few bins after the window for the model.
    """
    if design is None:
        design = difference_design(time_s, scalar_nT, vector_nT, aux, bin_s)
    tb, y, base, u, _ = design
    after = tb > max(off_window_s[1], t_s)
    if tb.size < 4 * (base.shape[1] + 3) or after.sum() < 2 * (base.shape[1] + 3):
        return None

    # the base's span once; each model then only adds its three step columns' part outside it
    q0 = _span_basis(base)
    r0 = y - q0 @ (q0.T @ y)

    def rss(on: np.ndarray) -> float:
        q1 = _step_bases(q0, [u * on[:, None]])
        return float(np.sum((r0 - q1 @ (q1.T @ r0)) ** 2))

    offs = tb[(tb >= off_window_s[0]) & (tb <= off_window_s[1])]
    offs = offs if offs.size else np.array([off_window_s[0]])
    pulse = min(rss((tb > t_s) & (tb < t_off)) for t_off in offs)
    return rss(tb > t_s) < pulse


def vector_reference_step(
    time_s: np.ndarray,
    scalar_nT: np.ndarray,
    vector_nT: np.ndarray,
    aux: dict[str, np.ndarray] | None = None,
    alpha: float = 0.01,
    min_size_nT: float = 1.0,
    min_f_ratio: float = STEP_MARGIN,
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
        model (lagging eddy fields in manoeuvres, unrecorded switched currents) lifts a
        step-free flight's F above that point. The audit passes the ratio's quantile at the
        test's level over simulated step-free flights
        (``AuditSettings.fluxgate_step_margin``).
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
