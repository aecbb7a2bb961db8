"""The field's gradient seen directly along the calibration legs.

The calibration fit band-passes everything (0.1-0.9 Hz by default): it sees a gradient
only through the small position changes the manoeuvres make, so its evidence for one is
weak where the manoeuvres move the carrier little (a fast fixed-wing box). The legs
themselves carry the strongest evidence and the fit throws it away: flown straight at
constant heading, a leg crosses hundreds of metres, and in a field with a gradient g the
compensated reading follows ``g . position``; the carrier's interference, constant on a
steady leg once compensated, cannot make such a ramp.

The estimate: the baseline-compensated field (the day's variation taken out with the base
station, when the recording has one) and the local east/north/up positions, averaged over
blocks of ``block_s`` seconds (the manoeuvres' 3-10 s cycles average out; neighbouring
block means are nearly independent), regressed on position with a level per leg (each
leg's heading error and the day's level). An F-test asks whether the two horizontal
components are zero. Only they are evidence: along a leg the carrier moves hundreds of
metres horizontally at constant attitude, but its height changes with the pitch manoeuvres,
so the vertical component shares its regressor with whatever attitude-driven interference
the compensation left (an uncalibrated fluxgate made -2 nT/m of it on a flat field); it is
estimated, so that it does not bias the others, and reported with that caveat.

This evidence lies below the fit band, so it is independent of the band-passed held-out
test, and the two are combined (Fisher) when the audit weighs a gradient.

Hand-written: a block-averaged least-squares fit with per-leg levels, on numpy and
scipy.stats; no library models calibration legs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from pipeline.audit.evidence import f_test_p, least_squares_rss
from pipeline.compensate.filters import contiguous_blocks
from pipeline.geo.heading import heading_class, pattern_direction_deg

MIN_BLOCK_FILL = 0.5  # share of a block's samples that must be present
# least relative uncertainty of a gradient from positions in a local tangent plane (projection
# and datum scale, GNSS antenna offsets): with hundreds of nT of ramp the statistical error
# alone is 1e-4 of the gradient and smaller than this. The carrier's soft iron usually adds
# more (see :func:`leg_gradient`'s ``scale_uncertainty``)
SCALE_UNCERTAINTY = 1e-3
# the crust's own gradient at the calibration site is part of the field the legs measure, of
# no carrier's making, and nothing in the legs tells it from a gradient effect over the same
# box (a truth document states the effect without it). Its spread is measured on the survey
# (:func:`crust_roughness_ratio`): a window needs this share of its length flown
MIN_WINDOW_COVER = 0.8


@dataclass
class LegGradient:
    """Gradient of the total field along the calibration legs.

    Attributes
    ----------
    gradient_nT_per_m : ndarray
        East, north, up (nT/m), the change of the total field per metre.
    se_nT_per_m : ndarray
        Their standard errors (nT/m): the fit's, with the field's relative scale uncertainty
        times the value and the crust's own gradient at the site
        (:func:`crust_roughness_ratio` times the fit's residual, when measured) added in
        quadrature.
    p_value : float
        F-test that the horizontal (east, north) components are zero.
    blocks, legs : int
        Block means and legs used.
    offsets_m : ndarray
        (blocks, 2) east/north block positions about their leg's mean (m).
    horizontal_cov : ndarray
        (2, 2) covariance of the east and north components ((nT/m)^2), the scale
        uncertainty included, the crust's gradient not (:meth:`excess_p_value` adds it).
    dof : int
        Residual degrees of freedom of the fit.
    crust_se_nT_per_m : float or None
        The crust's gradient spread in :attr:`se_nT_per_m` (nT/m), None when not measured.
    """

    gradient_nT_per_m: np.ndarray
    se_nT_per_m: np.ndarray
    p_value: float
    blocks: int
    legs: int
    offsets_m: np.ndarray
    horizontal_cov: np.ndarray
    dof: int
    crust_se_nT_per_m: float | None = None

    def excess_p_value(self, main_east_north_nT_per_m) -> float:
        """p of the Wald test (F with 2 and :attr:`dof` degrees of freedom) that the
        horizontal gradient equals ``main_east_north_nT_per_m`` (nT/m; the main field's
        own, which long legs measure at p ~ 0 on any flight) give or take the crust's own
        gradient at the box (:attr:`crust_se_nT_per_m`, a random effect of that spread in
        each component; none when not measured): whether the legs see a gradient beyond
        the main field's and the ground's, the estimate's own uncertainty counted. A box
        flown over geology shows the ground's gradient, which is no effect to model."""
        d = self.gradient_nT_per_m[:2] - np.asarray(main_east_north_nT_per_m, float)
        cov = self.horizontal_cov + np.eye(2) * (self.crust_se_nT_per_m or 0.0) ** 2
        w = float(d @ np.linalg.pinv(cov) @ d)
        return float(stats.f.sf(w / 2.0, 2, max(self.dof, 1)))

    @property
    def ramp_rms_nT(self) -> float:
        """RMS of the field change the horizontal gradient makes along the legs (each leg
        about its own level), nT: the size of the evidence, beside its significance."""
        return self.ramp_rms_for(self.gradient_nT_per_m[:2])

    def ramp_rms_for(self, east_north_nT_per_m) -> float:
        """RMS ramp (nT) another horizontal gradient (east, north; nT/m) would make along
        the same legs (e.g. the estimate less the main field's own gradient)."""
        return float(np.sqrt(np.mean((self.offsets_m @ np.asarray(east_north_nT_per_m)) ** 2)))

    def ci95(self) -> np.ndarray:
        """(3, 2) 95 % intervals, nT/m (normal approximation)."""
        g, se = self.gradient_nT_per_m, self.se_nT_per_m
        return np.column_stack([g - 1.96 * se, g + 1.96 * se])


def leg_ids(
    mask: np.ndarray, heading_class: np.ndarray, calibration_pass: np.ndarray, time_s: np.ndarray
) -> np.ndarray:
    """Leg number per epoch (-1 outside the legs): a run of calibration epochs on one heading
    of one pass, split where sampling has a gap.

    Parameters
    ----------
    mask : ndarray of bool
        Calibration epochs.
    heading_class : ndarray of str
        Cardinal direction per epoch (N/E/S/W on the legs, "" elsewhere).
    calibration_pass : ndarray of int
        Calibration pass per epoch.
    time_s : ndarray
        Epoch times (s).
    """
    ids = np.full(mask.size, -1, int)
    card = np.asarray(heading_class).astype(str)
    key = np.char.add(np.char.add(card, ":"), np.asarray(calibration_pass).astype(str))
    n = 0
    for b in contiguous_blocks(mask & (card != ""), np.asarray(time_s, float)):
        # a block may hold several legs (a turn without a gap between them)
        for part in np.split(b, np.flatnonzero(key[b][1:] != key[b][:-1]) + 1):
            ids[part] = n
            n += 1
    return ids


def leg_block_means(
    time_s: np.ndarray,
    values: np.ndarray,
    legs: np.ndarray,
    block_s: float = 10.0,
    min_leg_blocks: int = 3,
) -> tuple[np.ndarray, np.ndarray]:
    """Means of ``values`` over blocks of ``block_s`` seconds along each calibration leg.

    Parameters
    ----------
    time_s : ndarray
        Epoch times (s).
    values : ndarray
        (n, m) columns to average (a field in nT, positions in m ...); an epoch counts only
        where all are finite.
    legs : ndarray of int
        Leg number per epoch (:func:`leg_ids`), -1 outside.
    block_s : float
        Averaging block (s).
    min_leg_blocks : int
        Legs with fewer blocks filled to :data:`MIN_BLOCK_FILL` are left out.

    Returns
    -------
    means : ndarray
        (blocks, m) block means.
    leg_of : ndarray of int
        Leg of each block.
    """
    t, v = np.asarray(time_s, float), np.asarray(values, float)
    rows, leg_of = [], []
    for leg in np.unique(legs[legs >= 0]):
        sel = np.flatnonzero(legs == leg)
        key = np.floor((t[sel] - t[sel[0]]) / block_s).astype(int)
        expected = block_s / max(np.median(np.diff(t[sel])) if sel.size > 1 else block_s, 1e-9)
        found = []
        for k in np.unique(key):
            s = sel[key == k]
            ok = s[np.all(np.isfinite(v[s]), axis=1)]
            if ok.size >= MIN_BLOCK_FILL * expected:
                found.append(v[ok].mean(axis=0))
        if len(found) >= min_leg_blocks:
            rows += found
            leg_of += [leg] * len(found)
    return np.asarray(rows).reshape(len(rows), v.shape[1]), np.asarray(leg_of, int)


def leg_gradient(
    time_s: np.ndarray,
    field_nT: np.ndarray,
    enu_m: np.ndarray,
    legs: np.ndarray,
    block_s: float = 10.0,
    min_leg_blocks: int = 3,
    scale_uncertainty: float = SCALE_UNCERTAINTY,
    nuisance: np.ndarray | None = None,
    crust_ratio_per_m: float | None = None,
) -> LegGradient | None:
    """Fit the total field's gradient to block means along the calibration legs.

    Parameters
    ----------
    time_s, field_nT, enu_m : ndarray
        Epoch times (s); compensated total field (nT), day's variation removed where
        possible, NaN: missing; (n, 3) local east, north, up positions (m).
    legs : ndarray of int
        Leg number per epoch (:func:`leg_ids`), -1 outside.
    block_s, min_leg_blocks : float, int
        Averaging block (s); legs with fewer full blocks are left out (a level per leg
        costs one of them).
    scale_uncertainty : float
        Relative uncertainty of the field's scale, added in quadrature to the standard
        errors (at least :data:`SCALE_UNCERTAINTY`): a carrier's isotropic soft iron reads
        a gradient ``1 + a`` times too large (0.3-1 % on small aircraft), which no
        compensation undoes (the induced columns cannot hold ``ux^2 + uy^2 + uz^2 = 1``).
    nuisance : ndarray, optional
        (n, k) columns of interference the compensation may have taken out wrongly, each
        with one coefficient in both models of the test (a fitted channel's ``u I``: a
        coupling wrong by ``dc`` leaves ``dc . u I``, which a switch in a leg makes a ramp).
    crust_ratio_per_m : float, optional
        :func:`crust_roughness_ratio` (1/m): times the fit's residual, the standard error
        of the crust's own gradient at the box. None (no survey): not in the intervals.

    Returns
    -------
    LegGradient or None
        None when fewer than two legs or too few blocks remain for the test.
    """
    extra = np.empty((np.size(field_nT), 0)) if nuisance is None else np.asarray(nuisance, float)
    a, leg_of = leg_block_means(
        time_s,
        np.column_stack([field_nT, enu_m, extra.reshape(np.size(field_nT), -1)]),
        legs,
        block_s,
        min_leg_blocks,
    )
    if len(set(leg_of.tolist())) < 2:
        return None
    levels = (leg_of[:, None] == np.unique(leg_of)[None, :]).astype(float)
    x_full = np.column_stack([a[:, 1:4], levels, a[:, 4:]])
    x_base = np.column_stack([a[:, 3], levels, a[:, 4:]])
    rss_f, k_f, coef = least_squares_rss(x_full, a[:, 0])
    dof = a.shape[0] - k_f
    if dof < 3:
        return None
    # height and the levels: no horizontal terms
    rss_b, k_b, _ = least_squares_rss(x_base, a[:, 0])
    pv = f_test_p(rss_b, k_b, rss_f, k_f, a.shape[0])
    cov = rss_f / dof * np.linalg.pinv(x_full.T @ x_full)
    scale = max(scale_uncertainty, SCALE_UNCERTAINTY)
    crust = None if crust_ratio_per_m is None else crust_ratio_per_m * float(np.sqrt(rss_f / dof))
    # positions about each leg's level: what a horizontal gradient's ramp is made of
    offsets = a[:, 1:3] - levels @ np.linalg.lstsq(levels, a[:, 1:3], rcond=None)[0]
    return LegGradient(
        gradient_nT_per_m=coef[:3],
        se_nT_per_m=np.sqrt(
            np.clip(np.diag(cov)[:3], 0.0, None) + (scale * coef[:3]) ** 2 + (crust or 0.0) ** 2
        ),
        p_value=pv,
        blocks=int(a.shape[0]),
        legs=int(levels.shape[1]),
        offsets_m=offsets,
        horizontal_cov=cov[:2, :2] + np.diag((scale * coef[:2]) ** 2),
        dof=int(dof),
        crust_se_nT_per_m=crust,
    )


def leg_length_m(enu_m: np.ndarray, legs: np.ndarray) -> float | None:
    """Median horizontal length of the calibration legs (m): the scale over which their fit
    averages the field's gradient. None without legs."""
    spans = []
    for leg in np.unique(legs[legs >= 0]):
        xy = np.asarray(enu_m, float)[legs == leg, :2]
        xy = xy[np.all(np.isfinite(xy), axis=1)]
        if xy.shape[0] >= 2:
            # extent along the leg's own direction (its first principal axis)
            c = xy - xy.mean(axis=0)
            axis = np.linalg.svd(c, full_matrices=False)[2][0]
            spans.append(float(np.ptp(c @ axis)))
    return float(np.median(spans)) if spans else None


def _window_line(
    along_m: np.ndarray, time_s: np.ndarray, y: np.ndarray, block_s: float
) -> tuple[float, float, int] | None:
    """Slope (nT/m), residual sum of squares (nT^2) and degrees of freedom of a line fitted
    to ``block_s`` block means of ``y`` along track; None with fewer than 3 blocks."""
    blk = np.floor((time_s - time_s[0]) / block_s)
    ids = np.unique(blk)
    if ids.size < 3:
        return None
    x = np.array([along_m[blk == i].mean() for i in ids])
    v = np.array([y[blk == i].mean() for i in ids])
    c = np.polyfit(x, v, 1)
    r = v - np.polyval(c, x)
    return float(c[0]), float(r @ r), int(ids.size - 2)


def crust_roughness_ratio(
    time_s: np.ndarray,
    field_nT: np.ndarray,
    tracks: list,
    window_m: float,
    block_s: float = 10.0,
    min_windows: int = 4,
) -> tuple[float, int] | None:
    """How much the crust's mean gradient over a stretch varies, per nT of its departure
    from a plane there, measured on the survey (1/m).

    The crust's own gradient at the calibration box is part of what the legs measure and
    nothing in the legs tells it from a gradient effect; what they do show is the crust's
    departure from a plane over the box (their fit's residual). The survey relates the two:
    each straight line (survey and tie tracks) is cut into windows of ``window_m`` metres,
    the field's ``block_s`` block means in each are fitted with a line along track, and the
    ratio is the RMS of the windows' slopes (nT/m, signed along their line direction, less
    each direction's mean: the main field's and any regional gradient are the same
    everywhere) over the RMS of the block means' residuals about their lines (nT). Times
    the legs' residual, it is the spread of the crust's gradient at the box, where crews
    fly over quiet ground. A heading error or a lag shifts a line's level or moves it along
    track, not its slope; noise and compensation errors in the legs' residual make it err
    wide.

    Parameters
    ----------
    time_s : ndarray
        Epoch times (s).
    field_nT : ndarray
        Reduced field per epoch (nT): compensated, main field and day's variation removed.
    tracks : list of pipeline.quality.overlap.Track
        The survey's straight lines (local east/north metres).
    window_m : float
        Window length (m): the calibration legs' length (:func:`leg_length_m`), at most the
        lines' median length.
    block_s : float
        Block of the means (s), as in :func:`leg_gradient`.
    min_windows : int
        Fewest windows beyond one per line direction.

    Returns
    -------
    tuple of (float, int) or None
        The ratio (1/m) and the windows it rests on; None with too few windows or no
        residual.
    """
    lines = [t for t in tracks if t.kind in ("survey", "tie")]
    if not lines or not window_m > 0:
        return None
    # lines shorter than the legs: whole lines
    window_m = min(window_m, float(np.median([t.along_m[-1] for t in lines])))
    ref = pattern_direction_deg(np.array([t.heading_deg for t in lines]))
    slopes: dict[int, list[float]] = {}
    rss, dof = 0.0, 0
    t_all, y_all = np.asarray(time_s, float), np.asarray(field_nT, float)
    for t in lines:
        k = int(heading_class(t.heading_deg, ref))
        y, tt = y_all[t.index], t_all[t.index]
        win = np.floor(t.along_m / window_m)
        for w in np.unique(win):
            sel = (win == w) & np.isfinite(y)
            if sel.sum() < 5 or np.ptp(t.along_m[sel]) < MIN_WINDOW_COVER * window_m:
                continue
            got = _window_line(t.along_m[sel], tt[sel], y[sel], block_s)
            if got is not None:
                # one sign per line axis
                slopes.setdefault(k % 2, []).append(got[0] * (1.0 if k < 2 else -1.0))
                rss, dof = rss + got[1], dof + got[2]
    dev = [np.asarray(v) - np.mean(v) for v in slopes.values() if len(v) >= 2]
    n = sum(v.size for v in dev)
    if n - len(dev) < min_windows or not dof or not rss > 0:
        return None
    spread = np.sqrt(sum(float(v @ v) for v in dev) / (n - len(dev)))
    return float(spread / np.sqrt(rss / dof)), int(n)


def fisher_combined(*p_values: float) -> float:
    """Fisher's combination of independent p-values (chi-squared with 2k degrees of
    freedom); ``scipy.stats.combine_pvalues``."""
    ps = np.clip(np.asarray(p_values, float), 1e-300, 1.0)
    return float(stats.combine_pvalues(ps, method="fisher").pvalue)
