"""The day's variation (diurnal) seen against the base station, on the lines and on the legs.

A diurnal variation D(t) adds the same field to the airborne reading and to the base station's
(the survey's few kilometres are small against the variation's scale), so a base-station
correction subtracts the base station's reading at coefficient 1. Whether the airborne field
follows the base station is seen wherever the carrier's other contributions can be levelled
out:

* where the survey's lines cross, the same ground is read twice: the crossover difference is
  the two headings' level difference plus D(t_a) - D(t_b), and the base station's difference
  between the two readings is the regressor;
* along each calibration leg (straight, constant heading, over a few hundred metres), block
  means of the compensated field are the leg's level (heading error, day's level) plus the
  ground's gradient times position plus D(t), and the base station's block mean is the
  regressor. Its legs are flown minutes away from the survey: on a short survey near a turning
  point of the variation the crossovers see little of it, the calibration more.

Both data sets are fitted together by weighted least squares (each scaled by its own residual
standard deviation; a level, position or heading column belongs to one set, the base-station
coefficient is shared): a one-sided F-test of the coefficient (the variation's sign is known),
and a held-out check of the correction itself, which fits nothing: each crossover and each
leg block predicted from the others (leave-one-out) without and with the base station
subtracted at coefficient 1, each error weighted by its prediction's precision (1 - h) /
sigma^2: the prediction's variance is its set's residual variance sigma^2, as in the fit,
over one minus its leverage h, so the gain is the held-out likelihood's; the p is a
permutation test within each set (does the correction lower the weighted held-out sum of
squares more than the same corrections dealt to the points at random, i.e. does the base
station's reading belong to the times it was taken at?), the sets' p-values combined
(Fisher: independent data). Gross errors (a crossing read in a turn) would decide a
least-squares fit of a dozen points: each set is screened first by a biweight fit of the
same model, and the points it gives no weight are left out.

The coefficient's interval takes the wider of the least-squares standard error and a
two-way cluster one built from delete-one-group jackknives (the least-squares one takes the
points as independent, which the blocks of one leg are not, nor the crossovers on one survey
line or one tie line: they share that line's error), with Student t on the matching degrees
of freedom. No allowance is added: a slow drift of the airborne level moves
the coefficient by its own projection on the variation, which is in the residual the
jackknife resamples; a drift fitted beside the coefficient leaves it undetermined wherever
the variation is nearly linear over the flight.

Sizes in nT, times in s.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import stats

from pipeline.audit.evidence import HeldOut, NestedTest, nested_test, weighted_rms
from pipeline.audit.legs import fisher_combined

SHUFFLES = 4999  # random deals of the permutation test: p resolved to 2e-4


@dataclass
class DiurnalSet:
    """One data set of the diurnal test: observations ``y`` (nT), the nuisance columns
    ``nuisance`` fitted beside the base station (levels, positions), and the base-station
    term ``base_nT`` (what the base station says the variation adds to each observation)."""

    name: str  # "crossovers" or "legs"
    y: np.ndarray
    nuisance: np.ndarray
    base_nT: np.ndarray
    # the unit of independent error of each row (a leg's id, a crossover's survey line);
    # None: each row its own
    group: np.ndarray | None = None
    # a second unit whose error the rows share (a crossover's tie line); None: as group
    cross_group: np.ndarray | None = None

    def take(self, rows: np.ndarray) -> DiurnalSet:
        """The set's ``rows`` (a boolean mask)."""
        return DiurnalSet(
            self.name,
            self.y[rows],
            self.nuisance[rows],
            self.base_nT[rows],
            None if self.group is None else self.group[rows],
            None if self.cross_group is None else self.cross_group[rows],
        )

    def groups(self) -> np.ndarray:
        """Group id of each row (:attr:`group`, or one group per row)."""
        return np.arange(self.y.size) if self.group is None else np.asarray(self.group)

    def cross_groups(self) -> np.ndarray:
        """Second group id of each row (:attr:`cross_group`, or :meth:`groups`)."""
        return self.groups() if self.cross_group is None else np.asarray(self.cross_group)


@dataclass
class DiurnalEvidence:
    """The base station's coefficient in the airborne field (:func:`diurnal_evidence`).

    Attributes
    ----------
    coefficient : float
        Fitted coefficient of the base-station term (1 when the airborne field varies as the
        base station does), dimensionless.
    ci95 : tuple of float
        Its 95 % interval.
    test : NestedTest
        The sets' nuisance columns plus the base-station term against the nuisance columns
        alone (weighted); p one-sided (a positive coefficient).
    heldout : HeldOut
        Leave-one-out errors without and with the correction at coefficient 1, over all
        points, as precision-weighted RMS (nT; each error weighted by (1 - h) / sigma^2, its
        set's residual variance sigma^2 as in the fit and its leverage h); its p each set's
        permutation test, combined over the sets (Fisher).
    used : dict
        Points used per set.
    screened_out : dict
        Points left out as gross errors per set.
    """

    coefficient: float
    ci95: tuple[float, float]
    test: NestedTest
    heldout: HeldOut
    used: dict[str, int]
    screened_out: dict[str, int]


def _screen(s: DiurnalSet) -> np.ndarray:
    """Rows of ``s`` a biweight fit of its model (nuisance + base term) gives weight."""
    # the model's own module: statsmodels.api imports the formula machinery too
    from statsmodels.robust.norms import TukeyBiweight
    from statsmodels.robust.robust_linear_model import RLM

    a = np.column_stack([s.nuisance, s.base_nT])
    try:
        return RLM(s.y, a, M=TukeyBiweight()).fit().weights > 0
    except (ValueError, np.linalg.LinAlgError):  # a singular design: no screening
        return np.ones(s.y.size, bool)


def _loo(a: np.ndarray):
    """The leave-one-out error map of least squares on ``a`` and each row's predictive weight.

    Returns a function of ``v`` ((n,) or (n, m)) giving each row's error predicted by the fit
    to the other rows (the ordinary residual over one minus its leverage h), and 1 - h: the
    prediction's variance is the noise's over 1 - h, so a row the others barely determine
    (a leg's lone block, h near 1) has an error of almost no weight in the held-out
    likelihood rather than one amplified by 1 / (1 - h)."""
    u, sv, _ = np.linalg.svd(a, full_matrices=False)
    q = u[:, sv > (sv.max() if sv.size else 0.0) * 1e-10]  # a basis of the column space
    one_less_h = np.clip(1.0 - np.sum(q**2, axis=1), 1e-9, None)
    w = 1.0 / one_less_h

    def errors(v: np.ndarray) -> np.ndarray:
        r = v - q @ (q.T @ v)
        return r * (w if r.ndim == 1 else w[:, None])

    return errors, one_less_h


def _matched_p(a: np.ndarray, y: np.ndarray, g: np.ndarray, rng: np.random.Generator) -> float:
    """One-sided p that the correction ``g`` lowers the leave-one-out misfit of ``y`` (levels
    ``a`` refitted; each error weighted by its prediction's precision, :func:`_loo`) more
    than the same corrections dealt to the points at random: a permutation test of the
    held-out sum of squares (:data:`SHUFFLES` deals). It asks whether the base station's
    reading belongs to the times it was taken at, at the size the correction applies; unlike
    a point-by-point sign or rank test it is not diluted by the points the correction barely
    changes."""
    loo, one_less_h = _loo(a)
    e_y = loo(y)
    observed = float(np.sum(one_less_h * (e_y - loo(g)) ** 2))
    dealt = loo(np.stack([rng.permutation(g) for _ in range(SHUFFLES)], axis=1))
    shuffled = np.sum(one_less_h[:, None] * (e_y[:, None] - dealt) ** 2, axis=0)
    return float((1 + np.sum(shuffled <= observed)) / (SHUFFLES + 1))


def _two_way_se(x: np.ndarray, y: np.ndarray, groups: np.ndarray) -> tuple[float, int]:
    """Standard error of the last coefficient of the least-squares fit of ``y`` on ``x``
    with errors shared within either of two groupings (``groups``: (n, 2) ids; a
    crossover shares its survey line's error and its tie line's), and its degrees of
    freedom: the two-way cluster variance of Cameron, Gelbach and Miller (2011), V_a + V_b
    - V_ab, each term a delete-one-group jackknife's (V_ab: groups of rows that share both),
    at least either one-way variance, on the fewer groups less one. With one grouping
    (both columns equal) it is that grouping's jackknife."""
    se_a, df_a = _jackknife_se(x, y, groups[:, 0])
    if np.array_equal(groups[:, 0], groups[:, 1]):
        return se_a, df_a
    se_b, df_b = _jackknife_se(x, y, groups[:, 1])
    if min(df_a, df_b) == 0:
        return 0.0, 0
    both = np.unique(groups, axis=0, return_inverse=True)[1].ravel()
    se_ab, _ = _jackknife_se(x, y, both)
    var = max(se_a**2 + se_b**2 - se_ab**2, se_a**2, se_b**2)
    return float(np.sqrt(var)), min(df_a, df_b)


def _jackknife_se(x: np.ndarray, y: np.ndarray, group: np.ndarray) -> tuple[float, int]:
    """Delete-one-group jackknife standard error of the last coefficient of the
    least-squares fit of ``y`` on ``x`` and its degrees of freedom (groups less one; 0, 0
    with fewer than 3 groups). A left-out group's own columns (its leg's level) fall out of
    the fit as zero columns."""
    ids = np.unique(group)
    if ids.size < 3:
        return 0.0, 0
    theta = np.array(
        [np.linalg.lstsq(x[group != i], y[group != i], rcond=None)[0][-1] for i in ids]
    )
    g = ids.size
    return float(np.sqrt((g - 1) / g * np.sum((theta - theta.mean()) ** 2))), g - 1


def _usable(s: DiurnalSet) -> tuple[DiurnalSet, float, int] | None:
    """``s`` ready for the stacked fit: its non-finite rows dropped, gross errors screened
    out (:func:`_screen`) and the base term less its part in the nuisance columns' span; with
    its residual standard deviation (nT) and the number of rows screened out. None with too
    few rows for its columns (4 more) or without base-station variation."""
    ok = np.isfinite(s.y) & np.isfinite(s.base_nT) & np.all(np.isfinite(s.nuisance), axis=1)
    s = s.take(ok)
    k = s.nuisance.shape[1] + 1
    if s.y.size < k + 4 or np.std(s.base_nT) == 0:
        return None
    keep = _screen(s)
    if keep.sum() < k + 4:
        return None
    t = s.take(keep)
    if np.std(t.base_nT) == 0:
        return None
    # the base term less its part in the nuisance columns' span (a leg's level absorbs
    # the base station's tens of thousands of nT): the same fit, well conditioned, and
    # the same leave-one-out errors for the correction at coefficient 1
    g_c = t.base_nT - t.nuisance @ np.linalg.lstsq(t.nuisance, t.base_nT, rcond=None)[0]
    t = replace(t, base_nT=g_c)
    a = np.column_stack([t.nuisance, t.base_nT])
    coef, *_ = np.linalg.lstsq(a, t.y, rcond=None)
    r = t.y - a @ coef
    sigma = float(np.sqrt(r @ r / (t.y.size - k)))
    if not sigma > 0:
        return None
    return t, sigma, int(s.y.size - t.y.size)


def _stacked(
    kept: list[tuple[DiurnalSet, float]],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The usable sets stacked, each in units of its own residual standard deviation: the
    nuisance columns (block-diagonal: each set has its own levels), the measurements, the
    base term (shared), each row's standard deviation (nT) and each row's two groups
    ((n, 2): a set's own groups, :meth:`DiurnalSet.groups` and
    :meth:`DiurnalSet.cross_groups`)."""
    n_cols = [t.nuisance.shape[1] for t, _ in kept]
    x0 = np.zeros((sum(t.y.size for t, _ in kept), sum(n_cols)))
    y, g, sig, grp = [], [], [], []
    row = col = 0
    for i, ((t, sigma), m) in enumerate(zip(kept, n_cols, strict=True)):
        x0[row : row + t.y.size, col : col + m] = t.nuisance / sigma
        y.append(t.y / sigma)
        g.append(t.base_nT / sigma)
        sig.append(np.full(t.y.size, sigma))
        grp.append(
            np.column_stack(
                [
                    np.full(t.y.size, i),
                    np.unique(t.groups(), return_inverse=True)[1],
                    np.unique(t.cross_groups(), return_inverse=True)[1],
                ]
            )
        )
        row += t.y.size
        col += m
    y, g, sig = (np.concatenate(v) for v in (y, g, sig))
    grp = np.concatenate(grp)
    grp = np.column_stack(
        [np.unique(grp[:, [0, j]], axis=0, return_inverse=True)[1].ravel() for j in (1, 2)]
    )
    return x0, y, g, sig, grp


def diurnal_evidence(sets: list[DiurnalSet]) -> DiurnalEvidence | None:
    """Does the airborne field follow the base station? (module docstring)

    Parameters
    ----------
    sets
        The data sets (crossovers, calibration legs); a set with non-finite rows has them
        dropped, one with fewer points than its columns need (4 more) or without any
        base-station variation is left out.

    Returns
    -------
    DiurnalEvidence or None
        None when no set is usable.
    """
    kept, used, screened = [], {}, {}
    for s in sets:
        got = _usable(s)
        if got is None:
            continue
        t, sigma, out = got
        kept.append((t, sigma))
        used[s.name] = int(t.y.size)
        screened[s.name] = out
    if not kept:
        return None
    x0, y, g, sig, grp = _stacked(kept)
    x1 = np.column_stack([x0, g])
    test = nested_test(y, x0, x1, 1)
    n, k = x1.shape
    coef, *_ = np.linalg.lstsq(x1, y, rcond=None)
    r = y - x1 @ coef
    cov = float(r @ r) / (n - k) * np.linalg.pinv(x1.T @ x1)
    c, se = float(coef[-1]), float(np.sqrt(max(cov[-1, -1], 0.0)))
    se_jack, df_jack = _two_way_se(x1, y, grp)
    df = n - k
    if se_jack > se:  # the groups, not the points, are the independent data: their count
        se, df = se_jack, df_jack
    half = float(stats.t.ppf(0.975, df)) * se
    # the variation's sign is known (the base station sees the same field): one-sided, from
    # the two-sided F-test of one column (F = t^2)
    test = replace(test, p_value=0.5 * test.p_value if c > 0 else 1.0 - 0.5 * test.p_value)
    # the nuisance columns are block-diagonal: the stacked leave-one-out errors are each
    # set's own; each set gets its own permutation test (deals within a set only) and the
    # sets' p-values, from independent data, are combined (Fisher); a fixed seed keeps the
    # audit reproducible
    # the held-out errors weighted by their predictions' precision, (1 - leverage) over the
    # set's variance (a Gaussian held-out likelihood): in plain nT a set of crossovers read
    # to a nanotesla would drown calibration-leg blocks read to a tenth
    loo, one_less_h = _loo(x0)
    before, after = loo(y) * sig, loo(y - g) * sig
    precision = one_less_h / sig**2
    rng = np.random.default_rng(0)
    ps = [_matched_p(t.nuisance, t.y, t.base_nT, rng) for t, _ in kept]
    held = HeldOut(
        weighted_rms(before, precision),
        weighted_rms(after, precision),
        fisher_combined(*ps),
        int(before.size),
    )
    return DiurnalEvidence(c, (c - half, c + half), test, held, used, screened)
