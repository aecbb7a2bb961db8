"""Held-out calibration residuals that share no noise with the fit, and their paired test.

The calibration epochs are cut into contiguous blocks in time (one fold each). A fold's
model is fitted on the other blocks less a buffer as long as the band-pass filter's support
on each side of the test block, and the band-pass is applied within the training epochs and
within the test block separately: no test row's filtered value depends on a sample the fit
saw, so the held-out residual measures what the model gets wrong, not the noise it fitted.

Two models are compared on the same held-out rows by :func:`heldout_gain`: squared
residuals averaged over blocks of ``block_s`` seconds (close to independent) and the paired
block differences tested with the one-sided Wilcoxon signed-rank test (block differences are
heavy-tailed: an effect shows mostly in the fastest manoeuvres). The audit's extensions are
accepted with the same test. The 10-s blocks of one fold share its fitted coefficients, so
that test alone is not at its level; :func:`fold_test` takes the fold as the unit (ten
folds, an exact sign-flip test over them).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import stats
from scipy.signal import sosfiltfilt

from pipeline.compensate.estimator import bandpassed_design
from pipeline.compensate.filters import bandpass_sos

N_BLOCKS = 10


@dataclass
class HeldOut:
    """Held-out comparison of two models' residuals on the same samples.

    Attributes
    ----------
    rms_before_nT, rms_after_nT : float
        RMS of the base and the extended model's held-out errors, nT (each error weighted
        by its precision where the points are read to different accuracy: crossovers and
        leg blocks, switch steps; :func:`pipeline.audit.evidence.weighted_rms`).
    p_value : float
        One-sided p that the extended model predicts the held-out data better, by the test
        its producer names (:func:`heldout_gain`: Wilcoxon signed-rank over paired blocks;
        points: a t-test or signed-rank test of the paired squares, or a permutation test);
        1 when too few.
    blocks : int
        Blocks (or points) in the paired test.
    """

    rms_before_nT: float
    rms_after_nT: float
    p_value: float
    blocks: int

    @property
    def reduction(self) -> float:
        """Fractional held-out RMS reduction, 1 - after / before (0 when before is 0)."""
        return 1.0 - self.rms_after_nT / self.rms_before_nT if self.rms_before_nT > 0 else 0.0

    def to_dict(self) -> dict:
        """JSON-ready fields, with the reduction in percent (``reduction_pct``)."""
        return {
            "rms_before_nT": self.rms_before_nT,
            "rms_after_nT": self.rms_after_nT,
            "p_value": self.p_value,
            "blocks": self.blocks,
            "reduction_pct": 100.0 * self.reduction,
        }


def heldout_gain(
    r_before: np.ndarray, r_after: np.ndarray, time_s: np.ndarray, block_s: float = 10.0
) -> HeldOut:
    """Is ``r_after`` smaller than ``r_before`` (same samples) beyond what noise explains?"""
    a, b, t = (np.asarray(v, float) for v in (r_before, r_after, time_s))
    ok = np.isfinite(a) & np.isfinite(b)
    a, b, t = a[ok], b[ok], t[ok]
    if a.size < 10:
        return HeldOut(float("nan"), float("nan"), 1.0, 0)
    key = np.floor((t - t.min()) / block_s).astype(int)
    _, inv = np.unique(key, return_inverse=True)
    n = np.bincount(inv)
    d = (np.bincount(inv, a**2) - np.bincount(inv, b**2)) / n
    d = d[n >= 5]
    p = (
        float(stats.wilcoxon(d, alternative="greater").pvalue)
        if d.size > 5 and np.any(d != 0)
        else 1.0
    )
    return HeldOut(float(np.sqrt(np.mean(a**2))), float(np.sqrt(np.mean(b**2))), p, int(d.size))


def folds_improved(r_before: np.ndarray, r_after: np.ndarray, fold: np.ndarray) -> tuple[int, int]:
    """(folds whose mean squared residual ``r_after`` lowers, folds): the blocks of one fold
    share its fitted coefficients, so a gain the 10-s blocks find significant can still come
    from one fold's fit alone."""
    labels = np.unique(fold)
    better = sum(
        float(np.mean(r_after[fold == k] ** 2)) < float(np.mean(r_before[fold == k] ** 2))
        for k in labels
    )
    return int(better), int(labels.size)


EXACT_FOLDS_MAX = 16  # up to 2^16 sign patterns enumerated; beyond, a seeded sample of them


def _sign_patterns(k: int, seed: int) -> tuple[np.ndarray, int]:
    """The sign patterns of a sign-flip test on ``k`` values ((patterns, k) of +-1) and
    what the observed pattern adds to the count: all 2^k (it is among them, 0) up to
    :data:`EXACT_FOLDS_MAX`, else 2^16 drawn with ``seed`` (1)."""
    if k <= EXACT_FOLDS_MAX:
        return 1.0 - 2.0 * ((np.arange(2**k)[:, None] >> np.arange(k)) & 1), 0
    return np.random.default_rng(seed).choice([-1.0, 1.0], size=(2**16, k)), 1


def sign_flip_p(x: np.ndarray, seed: int = 0) -> float:
    """One-sided p that the mean of ``x`` is above 0, by flipping signs: under the null each
    value is symmetric about 0, so every sign pattern is equally likely. Exact over all 2^K
    patterns (the observed one included, so p >= 1/2^K) up to :data:`EXACT_FOLDS_MAX`
    values; beyond, 2^16 patterns drawn with ``seed`` and p = (1 + hits) / (1 + draws)."""
    x = np.asarray(x, float)
    k = x.size
    if k == 0:
        return 1.0
    signs, extra = _sign_patterns(k, seed)
    total = signs @ x
    tol = 1e-12 * float(np.sum(np.abs(x)))  # the observed pattern and its ties count
    hits = int(np.sum(total >= float(np.sum(x)) - tol))
    return float((hits + extra) / (signs.shape[0] + extra))


def fold_test(r_before: np.ndarray, r_after: np.ndarray, fold: np.ndarray) -> float:
    """One-sided p that ``r_after`` is smaller than ``r_before`` with the fold as the unit.

    The folds' fitted coefficients differ and their test blocks are buffered from each
    other's training rows, so the folds are the independent replicates of a held-out
    comparison; the 10-s blocks of one fold are not (they share its fit, and a residual with
    structure longer than 10 s links them). The statistic is the mean over folds of each
    fold's log ratio of mean squared residuals (scale-free), tested by the exact sign-flip
    permutation test (:func:`sign_flip_p`): no normality assumed, and one test, so a gain
    in every fold of K reaches p = 1/2^K (1/1024 with ten folds), small enough to pass
    after Holm over a round's candidates. 1 with fewer than three folds.
    """
    x = fold_log_ratios(r_before, r_after, fold, np.unique(fold))
    x = x[np.isfinite(x)]
    if x.size < 3 or not np.any(x != 0):
        return 1.0
    return sign_flip_p(x)


def fold_log_ratios(
    r_before: np.ndarray, r_after: np.ndarray, fold: np.ndarray, labels: np.ndarray
) -> np.ndarray:
    """Per fold of ``labels``: the log ratio of mean squared residuals before and after
    (NaN where the fold has no rows or a zero mean): :func:`fold_test`'s replicates."""
    out = np.full(len(labels), np.nan)
    for i, k in enumerate(labels):
        sel = fold == k
        if sel.any():
            before, after = np.mean(r_before[sel] ** 2), np.mean(r_after[sel] ** 2)
            if before > 0 and after > 0:
                out[i] = np.log(before / after)
    return out


def fold_test_max(gains: dict[str, np.ndarray], seed: int = 0) -> dict[str, float]:
    """:func:`fold_test` of several candidates on the same folds, adjusted for their number
    by the maximum statistic (Westfall-Young, single step).

    ``gains``: per candidate, :func:`fold_log_ratios` on one common list of folds (NaN: no
    evidence there, taken as 0). Each sign pattern flips a fold for every candidate at once
    (under the null each fold's vector of gains is symmetric about 0), and a candidate's p
    is the share of patterns whose largest candidate statistic reaches its own. This
    controls the chance of any false pass at the level as Holm does, but counts the
    candidates' dependence (they share folds and most columns): with ten folds and six
    candidates Holm lets only a gain in every fold pass (6/1024 > 0.005), this does not.
    Each candidate's statistic is its sum over folds scaled by the root of its sum of
    squares, which no sign pattern changes: on one candidate the plain sign-flip test, and
    every candidate on one scale, so a candidate whose folds swing widely (one that makes
    held-out data much worse) does not take the maximum in most patterns and hide another's
    gain. Exact over all patterns up to :data:`EXACT_FOLDS_MAX` folds, else 2^16 seeded
    draws.
    """
    names = list(gains)
    if not names:
        return {}
    x = np.nan_to_num(np.column_stack([np.asarray(gains[n], float) for n in names]))
    k = x.shape[0]
    if k < 3:
        return dict.fromkeys(names, 1.0)
    signs, extra = _sign_patterns(k, seed)
    scale = np.sqrt(np.sum(x**2, axis=0))
    x = x / np.where(scale > 0, scale, 1.0)
    top = np.max(signs @ x, axis=1)
    observed = x.sum(axis=0)
    tol = 1e-12 * float(np.sum(np.abs(x)))
    out = {}
    for j, n in enumerate(names):
        if not np.any(x[:, j] != 0):
            out[n] = 1.0
            continue
        hits = int(np.sum(top >= observed[j] - tol))
        out[n] = float((hits + extra) / (signs.shape[0] + extra))
    return out


def filter_support_s(
    band_hz: tuple[float, float], rate_hz: float, poles: int, energy: float = 0.999
) -> float:
    """Half-width (s) of the zero-phase band-pass's impulse response holding ``energy`` of
    its energy: how far a sample's noise reaches into its filtered neighbours."""
    sos = bandpass_sos(band_hz, rate_hz, poles)
    n = int(np.ceil(rate_hz * 20.0 / band_hz[0]))  # twenty periods of the lower edge
    x = np.zeros(2 * n + 1)
    x[n] = 1.0
    h2 = sosfiltfilt(sos, x, padtype=None) ** 2
    inside = h2[n] + 2.0 * np.cumsum(0.5 * (h2[n + 1 :] + h2[n - 1 :: -1][:n]))
    k = int(np.searchsorted(inside, energy * h2.sum()))
    return (k + 1) / rate_hz


def block_folds(mask: np.ndarray, n_blocks: int = N_BLOCKS) -> np.ndarray:
    """Fold number per epoch: the epochs of ``mask`` cut into ``n_blocks`` contiguous runs
    of equal count, in time order; -1 outside ``mask``."""
    fold = np.full(mask.size, -1, int)
    idx = np.flatnonzero(mask)
    for k, part in enumerate(np.array_split(idx, n_blocks)):
        fold[part] = k
    return fold


def within(time_s: np.ndarray, mask: np.ndarray, buffer_s: float) -> np.ndarray:
    """Epochs within ``buffer_s`` seconds of an epoch of ``mask`` (those included)."""
    tt = time_s[mask]
    if tt.size == 0:
        return np.zeros(time_s.size, bool)
    pos = np.clip(np.searchsorted(tt, time_s), 1, max(tt.size - 1, 1))
    near = np.minimum(np.abs(time_s - tt[pos - 1]), np.abs(time_s - tt[pos % tt.size]))
    return near <= buffer_s


# A calibration fit reads the calibration epochs and their neighbours: derivatives (a sample
# each side), a re-timed record (the audit's longest lag, 1 s) and a decaying eddy response
# started in steady state, whose start-up falls as exp(-t / tau). Thirty seconds is twenty
# decay times of the slowest decay tried (1.5 s): a start-up below 1e-8 of the column.
CALIBRATION_PAD_S = 30.0


def calibration_window(
    time_s: np.ndarray, mask: np.ndarray, pad_s: float = CALIBRATION_PAD_S
) -> np.ndarray:
    """Indices (time order) of the epochs within ``pad_s`` seconds of an epoch of ``mask``
    (:func:`within`): the part of a flight that columns band-passed over ``mask``'s blocks
    depend on. Columns built on these epochs alone equal those built on the whole flight at
    the epochs of ``mask`` (recursive filters' start-up aside, exp(-``pad_s`` / tau)); a
    calibration of minutes in a flight of hours costs minutes."""
    return np.flatnonzero(within(np.asarray(time_s, float), mask, pad_s))


def fold_masks(
    time_s: np.ndarray, fold: np.ndarray, k: int, buffer_s: float
) -> tuple[np.ndarray, np.ndarray]:
    """(train, test) epoch masks of fold ``k``: test = its block; train = the other blocks
    less every epoch within ``buffer_s`` of a test epoch."""
    test = fold == k
    train = (fold >= 0) & ~within(time_s, test, buffer_s)
    return train, test


@dataclass(frozen=True)
class Band:
    """The fit band: edges (Hz), Butterworth prototype order, seconds trimmed per block end."""

    band_hz: tuple[float, float]
    poles: int
    trim_s: float


# predict(train_mask, test_mask) -> (band-passed held-out residual, epoch indices)
FoldPredictor = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


@dataclass
class HeldOutResiduals:
    """Held-out residuals of one model over every fold, on the fold's test rows."""

    residual_nT: np.ndarray
    where: np.ndarray  # epoch index of each residual

    @property
    def rms_nT(self) -> float:
        """RMS held-out residual, nT."""
        return float(np.sqrt(np.mean(self.residual_nT**2))) if self.residual_nT.size else np.nan


def heldout_residuals(
    predict: FoldPredictor, time_s: np.ndarray, fold: np.ndarray, buffer_s: float
) -> HeldOutResiduals:
    """``predict`` on every fold (:func:`fold_masks`), residuals concatenated in fold order."""
    res, where = [], []
    for k in range(int(fold.max()) + 1):
        train, test = fold_masks(time_s, fold, k, buffer_s)
        if not train.any() or not test.any():
            continue
        r, w = predict(train, test)
        res.append(r)
        where.append(w)
    if not res:
        return HeldOutResiduals(np.zeros(0), np.zeros(0, int))
    return HeldOutResiduals(np.concatenate(res), np.concatenate(where))


def linear_predictor(
    columns: np.ndarray,
    y_nT: np.ndarray,
    time_s: np.ndarray,
    rate_hz: float,
    band: Band,
    fit: Callable[[np.ndarray, np.ndarray], np.ndarray],
) -> FoldPredictor:
    """A fold predictor of a linear model: band-pass and fit (``fit(K, y) -> theta``) on the
    training epochs, band-pass the test block alone and return its residual."""

    def predict(train: np.ndarray, test: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        kf, yf, _ = bandpassed_design(
            columns, y_nT, time_s, rate_hz, train, band.band_hz, band.poles, band.trim_s
        )
        theta = fit(kf, yf)
        kt, yt, wt = bandpassed_design(
            columns, y_nT, time_s, rate_hz, test, band.band_hz, band.poles, band.trim_s
        )
        return yt - kt @ theta, wt

    return predict
