"""Held-out evidence that never extrapolates: stratified blocked cross-validation.

A calibration pass is a handful of distinct situations: each cardinal heading flown steady and
with roll, pitch and yaw oscillations, and the turns between legs. Holding out whole 30-s
chunks (or one manoeuvre block) asks the model to predict a heading x manoeuvre combination it
never saw in training: the poorly determined directions of the T-L solution then dominate the
"held-out" residual even on a flight with nothing hidden (ten times the fit residual and
more). Here every fold holds short blocks
from **every** stratum (heading x manoeuvre, turns by heading octant), so training always
contains each situation and the held-out residual measures what the model gets wrong, not
how it extrapolates.

Blocks are short but the band-pass is not: the design is band-passed once over the whole
calibration (contiguous blocks), and folds select rows of the band-passed data. Ridge lambda
is chosen inside the training folds by inner cross-validation over the same blocks (never on
the held-out rows).

No library offers folds stratified by an arbitrary label *and* blocked in time (scikit-learn's
``StratifiedGroupKFold`` balances class proportions, not coverage of every class per fold, and
is not a dependency here), hence the small hand-written assignment.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.compensate.ridge import RidgeSVD

N_FOLDS = 5
BLOCK_S = 6.0  # about one manoeuvre period: short enough for every stratum to reach each fold


def calibration_strata(
    cardinal: np.ndarray, manoeuvre: np.ndarray, heading_deg: np.ndarray
) -> np.ndarray:
    """Stratum label per epoch: ``N:roll`` ... on calibration legs, ``turn:<octant>``
    elsewhere (turns between legs sweep the heading: their octants are distinct situations).

    Parameters
    ----------
    cardinal, manoeuvre
        Segmentation labels per epoch ("" off calibration legs).
    heading_deg
        Measured heading (yaw, degrees clockwise from true north) per epoch.
    """
    octant = np.floor(((np.nan_to_num(heading_deg) % 360.0) + 22.5) / 45.0).astype(int) % 8
    on_leg = (cardinal != "") & (manoeuvre != "")
    leg = np.char.add(np.char.add(cardinal.astype(str), ":"), manoeuvre.astype(str))
    turn = np.char.add("turn:", octant.astype(str))
    return np.where(on_leg, leg, turn)


def stratified_block_folds(
    time_s: np.ndarray,
    mask: np.ndarray,
    strata: np.ndarray,
    n_folds: int = N_FOLDS,
    block_s: float = BLOCK_S,
    seed: int = 0,
) -> np.ndarray:
    """Fold number (0 .. n_folds-1) per epoch inside ``mask``, -1 outside.

    Each stratum's epochs are cut into contiguous blocks of ``block_s`` seconds, and the
    blocks are dealt to the folds in turn from a random first fold (seeded), so that every
    fold holds about 1/n_folds of every stratum.
    """
    t = np.asarray(time_s, float)
    fold = np.full(t.size, -1, int)
    rng = np.random.default_rng(seed)
    idx = np.flatnonzero(mask)
    if idx.size == 0:
        return fold
    dt = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    for label in sorted(set(strata[idx].tolist())):
        sel = idx[strata[idx] == label]
        # a new block where the stratum is interrupted or block_s has elapsed
        brk = np.flatnonzero((np.diff(sel) > 1) | (np.diff(t[sel]) > 3 * dt)) + 1
        starts = np.r_[0, brk]
        block = np.zeros(sel.size, int)
        b = 0
        for s, e in zip(starts, np.r_[brk, sel.size], strict=True):
            k = np.floor((t[sel[s:e]] - t[sel[s]]) / block_s).astype(int)
            block[s:e] = b + k
            b += int(k.max()) + 1
        first = int(rng.integers(n_folds))
        fold[sel] = (block + first) % n_folds
    return fold


def passwise_folds(mask: np.ndarray, passes: list[np.ndarray]) -> np.ndarray | None:
    """Fold = calibration pass (leave one pass out), or None with fewer than two passes."""
    inside = [p[mask[p]] for p in passes if mask[p].any()]
    if len(inside) < 2:
        return None
    fold = np.full(mask.size, -1, int)
    for k, p in enumerate(inside):
        fold[p] = k
    return fold


def lambda_grid(s2: np.ndarray, n: int = 25) -> np.ndarray:
    """Ridge values from far below the smallest to the largest squared singular value
    ``s2`` (the eigenvalues of K'K) of the design."""
    s2 = np.asarray(s2, float)
    s2 = s2[s2 > 0]
    return np.logspace(np.log10(s2.min()) - 4, np.log10(s2.max()), n)


@dataclass
class CVLambda:
    """Inner cross-validation of the ridge parameter."""

    lambdas: np.ndarray
    mse: np.ndarray  # mean squared held-out residual per lambda, nT^2
    se: np.ndarray  # its standard error over the groups
    best: float  # the one-standard-error choice (see choose_lambda)


def choose_lambda(
    k: np.ndarray, y: np.ndarray, groups: np.ndarray, lambdas: np.ndarray | None = None
) -> CVLambda:
    """Ridge lambda by cross-validation over ``groups`` (fold labels of the rows).

    The largest lambda whose held-out mean squared residual is within one standard error
    of the minimum (Hastie, Tibshirani & Friedman, *Elements of Statistical Learning*,
    sec. 7.10): the band-pass leaves T-L directions that the data hardly see (the isotropic
    induced part, |B| / s, is nearly constant), and the bare minimum lets them drift by
    thousands of nT in the compensated field's level without changing the held-out fit.
    With a single group the L-curve corner is used instead.
    """
    k = np.asarray(k, float)
    y = np.asarray(y, float)
    labels = np.unique(groups)
    if labels.size < 2:
        full = RidgeSVD(k, y)
        lams = lambda_grid(full.s**2) if lambdas is None else np.asarray(lambdas, float)
        return CVLambda(
            lams,
            np.full(lams.size, np.nan),
            np.full(lams.size, np.nan),
            full.lcurve().lambda_corner,
        )
    # Each training set's normal equations are the total minus the held-out group's, so one
    # pass over the rows and a p x p eigendecomposition per group replace an SVD of every
    # training matrix (the audit chooses lambda ~100 times a flight, and those SVDs were
    # most of its time). Squared singular values = eigenvalues of K'K.
    gram = {
        g: (k[groups == g].T @ k[groups == g], k[groups == g].T @ y[groups == g]) for g in labels
    }
    g_all = sum(v[0] for v in gram.values())
    b_all = sum(v[1] for v in gram.values())
    if lambdas is None:
        s2 = np.linalg.eigvalsh(g_all)
        # eigenvalues of a numerically singular K'K come out as rounding noise, not zero
        lams = lambda_grid(s2[s2 > s2.max() * 1e-15])
    else:
        lams = np.asarray(lambdas, float)
    per = np.zeros((labels.size, lams.size))
    for j, g in enumerate(labels):
        test = groups == g
        w, v = np.linalg.eigh(g_all - gram[g][0])
        w = np.clip(w, 0.0, None)
        vb = v.T @ (b_all - gram[g][1])
        theta = v @ (vb[:, None] / (w[:, None] + lams[None, :]))  # (p, n_lambda)
        r = y[test][:, None] - k[test] @ theta
        per[j] = np.mean(r**2, axis=0)
    mse = per.mean(axis=0)
    se = per.std(axis=0, ddof=1) / np.sqrt(labels.size)
    i = int(np.argmin(mse))
    ok = np.flatnonzero(mse <= mse[i] + se[i])
    return CVLambda(lams, mse, se, float(lams[ok.max()]))


def jackknife_ci95(estimate: dict, by_fold: list[dict]) -> dict:
    """95 % intervals of every numeric entry of ``estimate`` from the same quantity estimated
    on each fold's training data (delete-a-group jackknife: variance (K-1)/K sum (x_k -
    mean)^2, Student t with K-1 degrees of freedom), centred on the full-data estimate.

    Lists give a list of intervals; non-numeric entries (channel names, units) give None.
    """
    from scipy import stats

    k = len(by_fold)
    t = float(stats.t.ppf(0.975, k - 1)) if k >= 2 else float("nan")

    def interval(full, folds):
        x = np.asarray(folds, float)
        if k < 2 or not np.all(np.isfinite(x)):
            return None
        half = t * float(np.sqrt((k - 1) / k * np.sum((x - x.mean()) ** 2)))
        return [float(full) - half, float(full) + half]

    out: dict = {}
    for key, val in estimate.items():
        vals = [f.get(key) for f in by_fold]
        if isinstance(val, bool) or val is None or any(v is None for v in vals):
            out[key] = None
        elif isinstance(val, int | float):
            out[key] = interval(val, vals)
        elif isinstance(val, list | tuple) and val and all(isinstance(v, int | float) for v in val):
            out[key] = [interval(val[i], [v[i] for v in vals]) for i in range(len(val))]
        else:
            out[key] = None
    return out


def widest_ci95(cis: list[dict]) -> dict:
    """Per key of several :func:`jackknife_ci95` results (one per grouping of the same
    data), the widest interval: for a list, entry by entry; None where every one is None."""

    def width(iv):
        return -1.0 if iv is None else iv[1] - iv[0]

    out: dict = {}
    for key in cis[0] if cis else {}:
        vals = [c.get(key) for c in cis]
        if any(isinstance(v, list) and v and isinstance(v[0], list | type(None)) for v in vals):
            n = max(len(v) for v in vals if isinstance(v, list))
            out[key] = [
                max((v[i] for v in vals if isinstance(v, list) and len(v) > i), key=width)
                for i in range(n)
            ]
        else:
            out[key] = max(vals, key=width)
    return out
