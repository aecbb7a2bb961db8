"""``tl-nn``: tl18 plus a learned model of its residual (MagNav.jl's m2b idea).

The regressor (scikit-learn's ``HistGradientBoostingRegressor``, or ``MLPRegressor``) maps
carrier-state features to the band-passed tl18 residual of the calibration. Its features are
the tl18 columns, their rates, the attitude and its rates, and every recorded ``/aux``
channel; never position, time, or the measured field itself, so it cannot learn geology or
drift. Its output is band-passed over the flight before it is subtracted, as the fit's
target was: what it says below the band (levels that follow heading) is discarded.

Early stopping on held-out blocks: in each held-out fold (:mod:`pipeline.compensate.heldout`)
the number of boosting iterations (or training epochs) is chosen on the neighbouring block of
the training data, and the final model is trained on the whole calibration for the median
of those numbers. Everything is seeded; the fit is deterministic.
"""

from __future__ import annotations

import copy
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
from sklearn.ensemble import HistGradientBoostingRegressor
from sklearn.neural_network import MLPRegressor
from sklearn.pipeline import make_pipeline
from sklearn.preprocessing import StandardScaler
from threadpoolctl import threadpool_limits

from pipeline.compensate.estimator import bandpassed_design
from pipeline.compensate.heldout import HeldOutResiduals, fold_masks, within
from pipeline.compensate.nuisance import attitude_rate_columns
from pipeline.compensate.plus import ridge_theta
from pipeline.compensate.terms import tl18_terms

# one thread: scikit-learn's OpenMP threads oversubscribe a machine the flow's other
# processes share, and a fit this small gains nothing from them; threadpoolctl limits only
# libraries already loaded, hence scikit-learn's imports at the top
THREADS = 1
MAX_ITER = 150  # boosting iterations / training epochs searched by early stopping
ROUNDS = 2  # tl18, learner, tl18 refitted beside it, learner again
PATIENCE = 30


def features(meas) -> tuple[np.ndarray, list[str], dict[str, list[int]]]:
    """The learner's features at every epoch of ``meas`` and their groups.

    Groups: ``tl_terms`` (the 18 tl18 columns), ``tl_rates`` (their time derivatives, per
    second), ``attitude`` (roll, pitch, sin and cos of yaw), ``attitude_rates`` (rad/s in
    units of 0.2 rad/s) and ``aux:<name>`` per recorded auxiliary channel.

    Raises
    ------
    ValueError
        No attitude (``/ins/attitude``): a feature channel is missing.
    """
    if meas.attitude_deg is None:
        raise ValueError("tl-nn needs the attitude (/ins/attitude) among its features")
    k, names = tl18_terms(meas.vector_nT)
    cols = [k, np.gradient(k, meas.time_s, axis=0)]
    names = names + [f"d_{n}" for n in names]
    groups = {"tl_terms": list(range(18)), "tl_rates": list(range(18, 36))}
    r, p, y = np.radians(meas.attitude_deg).T
    cols.append(np.column_stack([r, p, np.sin(y), np.cos(y)]))
    names += ["roll", "pitch", "sin_yaw", "cos_yaw"]
    groups["attitude"] = list(range(36, 40))
    rates, rn = attitude_rate_columns(*meas.attitude_deg.T, meas.time_s)
    cols.append(rates)
    names += rn
    groups["attitude_rates"] = list(range(40, 43))
    for name, x in sorted(meas.aux.items()):
        groups[f"aux:{name}"] = [len(names)]
        cols.append(np.asarray(x, float)[:, None])
        names.append(f"aux_{name}")
    return np.column_stack(cols), names, groups


def make_learner(kind: str, seed: int, n_iter: int = MAX_ITER):
    """A seeded scikit-learn regressor (features standardised for the MLP)."""
    if kind == "hgb":
        return HistGradientBoostingRegressor(
            learning_rate=0.1,
            max_iter=n_iter,
            max_leaf_nodes=15,
            min_samples_leaf=40,
            l2_regularization=1.0,
            early_stopping=False,
            random_state=seed,
        )
    return make_pipeline(
        StandardScaler(),
        MLPRegressor(
            hidden_layer_sizes=(32, 32),
            alpha=1e-3,
            batch_size=128,
            learning_rate_init=1e-3,
            max_iter=n_iter,
            random_state=seed,
        ),
    )


def _staged_errors(model, x_val: np.ndarray, r_val: np.ndarray) -> np.ndarray:
    """Validation MSE after each boosting iteration (hgb)."""
    return np.array([np.mean((r_val - p) ** 2) for p in model.staged_predict(x_val)])


def train(
    kind: str,
    seed: int,
    x: np.ndarray,
    r: np.ndarray,
    x_val: np.ndarray | None = None,
    r_val: np.ndarray | None = None,
    n_iter: int = MAX_ITER,
) -> tuple[Any, int]:
    """Train on (x, r); with a validation set, stop where its error is least.

    Returns the fitted regressor and its number of iterations (boosting) or epochs (MLP).
    """
    model = make_learner(kind, seed, n_iter)
    if kind == "hgb":
        model.fit(x, r)
        if x_val is None:
            return model, n_iter
        best = int(np.argmin(_staged_errors(model, x_val, r_val))) + 1
        return make_learner(kind, seed, best).fit(x, r), best
    scaler, mlp = model.steps[0][1], model.steps[1][1]
    xs = scaler.fit_transform(x)
    if x_val is None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # ConvergenceWarning: epochs fixed on purpose
            mlp.fit(xs, r)
        return model, n_iter
    xv = scaler.transform(x_val)
    best, best_err, best_model, since = 0, np.inf, None, 0
    for epoch in range(1, n_iter + 1):
        mlp.partial_fit(xs, r)
        err = float(np.mean((r_val - mlp.predict(xv)) ** 2))
        if err < best_err:
            best, best_err, best_model, since = epoch, err, copy.deepcopy(mlp), 0
        else:
            since += 1
            if since >= PATIENCE:
                break
    model.steps[1] = ("mlpregressor", best_model)
    return model, best


@dataclass
class FoldResult:
    """One held-out fold of tl-nn: its residuals, the iterations early stopping chose,
    and each feature group's permutation importance (held-out RMS increase, nT)."""

    residual_nT: np.ndarray
    where: np.ndarray
    n_iter: int
    importance_nT: dict[str, float]


class LearnedFolds:
    """tl-nn's held-out evaluation on the folds of a :class:`~pipeline.compensate.plus.
    HeldOutSetup`."""

    def __init__(self, setup, kind: str, seed: int):
        self.setup, self.kind, self.seed = setup, kind, seed
        self.x, self.names, self.groups = features(setup.meas)
        self.k18, _ = tl18_terms(setup.meas.vector_nT)

    def _bp(self, columns: np.ndarray, mask: np.ndarray):
        m, b = self.setup.meas, self.setup.band
        return bandpassed_design(
            columns, m.scalar_nT, m.time_s, m.rate_hz, mask, b.band_hz, b.poles, b.trim_s
        )

    def fit_joint(
        self,
        mask: np.ndarray,
        val: np.ndarray | None = None,
        n_iter: int = MAX_ITER,
    ) -> tuple[Any, np.ndarray, int]:
        """tl18 and the learner on the calibration epochs ``mask``: (learner, tl18
        coefficients, iterations).

        tl18 first, the learner on its band-passed residual, then tl18 refitted on the field
        less the learner's band-passed output and the learner on the new residual
        (:data:`ROUNDS` rounds): interference outside the basis biases a tl18 fit alone,
        and the learner alone cannot undo that bias. With ``val`` (epochs of ``mask``), the
        learner stops early on them and trains on the epochs of ``mask`` farther than the
        filter's support from them.
        """
        s = self.setup
        rows = mask & np.all(np.isfinite(self.x), axis=1)
        kf, yf, where = self._bp(self.k18, rows)
        theta = ridge_theta(kf, yf, s.ridge)
        x = self.x[where]
        if val is not None:
            is_val = val[where]
            is_fit = ~within(s.meas.time_s, val, s.buffer_s)[where]
        model, it = None, n_iter
        for rnd in range(ROUNDS):
            r = yf - kf @ theta
            if val is None:
                model, it = train(self.kind, self.seed, x, r, n_iter=n_iter)
            else:
                model, it = train(self.kind, self.seed, x[is_fit], r[is_fit], x[is_val], r[is_val])
            if rnd == ROUNDS - 1:
                break
            g = predict(model, np.where(rows[:, None], self.x, np.nan))
            kg, _, _ = self._bp(np.column_stack([self.k18, g]), rows)
            theta = ridge_theta(kf, yf - kg[:, -1], s.ridge)
        return model, theta, it

    def _test_residual(self, model, theta, test: np.ndarray, x: np.ndarray):
        """Band-passed residual of tl18 (``theta``) plus the learner on the test block."""
        rows = test & np.all(np.isfinite(x), axis=1)
        g = predict(model, np.where(rows[:, None], x, np.nan))
        kt, yt, wt = self._bp(np.column_stack([self.k18, g]), rows)
        return yt - kt[:, :-1] @ theta - kt[:, -1], wt

    def fold(self, k: int) -> FoldResult | None:
        """Train on fold ``k``'s training blocks (early stopping on the next block), test
        on its block, and permute each feature group on it."""
        s = self.setup
        t = s.meas.time_s
        fit_mask, test = fold_masks(t, s.fold, k, s.buffer_s)
        if not fit_mask.any() or not test.any():
            return None
        n = int(s.fold.max()) + 1
        val = fit_mask & (s.fold == ((k + 1) if k + 1 < n else k - 1))  # the next block
        model, theta, n_iter = self.fit_joint(fit_mask, val)
        res, wt = self._test_residual(model, theta, test, self.x)
        base = float(np.sqrt(np.mean(res**2)))
        rng = np.random.default_rng(self.seed + k)
        imp = {}
        rows = np.flatnonzero(test)
        for g, cols in self.groups.items():
            xp = self.x.copy()
            perm = rng.permutation(rows)
            xp[np.ix_(rows, cols)] = self.x[np.ix_(perm, cols)]
            rp, _ = self._test_residual(model, theta, test, xp)
            imp[g] = float(np.sqrt(np.mean(rp**2))) - base
        return FoldResult(res, wt, n_iter, imp)


@dataclass
class LearnedEvaluation:
    """tl-nn over every fold: held-out residuals, iterations chosen, group importances."""

    heldout: HeldOutResiduals
    n_iter: int
    importance_nT: dict[str, float]

    def importance_dict(self) -> dict[str, dict[str, float]]:
        """Per feature group: the held-out RMS increase (nT) when the group is permuted,
        and its share of the groups' total (groups that hurt when permuted, shares >= 0)."""
        pos = {g: max(v, 0.0) for g, v in self.importance_nT.items()}
        total = sum(pos.values())
        return {
            g: {
                "heldout_rms_increase_nT": v,
                "share": (pos[g] / total) if total > 0 else 0.0,
            }
            for g, v in sorted(self.importance_nT.items(), key=lambda kv: -kv[1])
        }


def evaluate(folds: LearnedFolds) -> LearnedEvaluation:
    """Every fold of ``folds``; importances averaged over the folds."""
    with threadpool_limits(THREADS):
        out = [f for k in range(int(folds.setup.fold.max()) + 1) if (f := folds.fold(k))]
    if not out:
        raise ValueError("tl-nn: no held-out fold could be trained")
    held = HeldOutResiduals(
        np.concatenate([f.residual_nT for f in out]), np.concatenate([f.where for f in out])
    )
    imp = {g: float(np.mean([f.importance_nT[g] for f in out])) for g in folds.groups}
    return LearnedEvaluation(held, int(np.median([f.n_iter for f in out])), imp)


def fit_final(folds: LearnedFolds, mask: np.ndarray, n_iter: int) -> tuple[Any, np.ndarray]:
    """tl18 and the learner (``n_iter`` iterations) on the whole calibration ``mask``:
    (learner, tl18 coefficients)."""
    with threadpool_limits(THREADS):
        model, theta, _ = folds.fit_joint(mask, None, max(n_iter, 1))
    return model, theta


def predict(model, x: np.ndarray) -> np.ndarray:
    """The learner's output (nT) at the rows of ``x`` (NaN where a feature is not finite)."""
    g = np.full(x.shape[0], np.nan)
    ok = np.all(np.isfinite(x), axis=1)
    with threadpool_limits(THREADS):
        g[ok] = model.predict(x[ok])
    return g
