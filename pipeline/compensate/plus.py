"""``tl-plus``: tl18 plus the term groups the calibration's held-out blocks support.

Candidate groups (column builders in :mod:`pipeline.compensate.nuisance`, shared with the
audit):

- ``eddy_decay``: the field's change through a first-order response, on the nine tl18
  eddy directions, its time constant chosen among :data:`TAU_GRID_S` (0.02-1 s) by the
  held-out residual;
- ``second_order``: induced terms quadratic in the field and the squared-rate terms;
- ``current:<name>``: each recorded ``/aux`` channel coupling along a fixed body direction;
- ``attitude_rates``: roll, pitch and yaw rates (when the attitude is recorded).

Forward selection: each round fits every remaining group beside the current model on the
held-out folds of :mod:`pipeline.compensate.heldout` (contiguous blocks, buffered by the
band-pass's support, band-passed within each fold); the group with the smallest held-out
residual enters when it lowers the held-out RMS by at least ``extension_min_gain`` and two
paired tests against the current model, adjusted over that round's candidates, give p below
``extension_alpha``: the audit's test over 10-s blocks (Holm) and the test with the held-out
fold as the unit (:func:`pipeline.compensate.heldout.fold_test_max`: the sign-flip test's
maximum statistic over the candidates, which share the folds). The second is the
calibrated one: the 10-s blocks of a fold share its fit, and on calibrations with nothing
outside the basis the first alone passes spurious groups far more often than its level.
Groups the audit named (``unexplained.nuisances``) are tried first, each one hypothesis.
The final model is fitted on the whole calibration with the one T-L estimator (band-passed
ridge).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pipeline.compensate.estimator import bandpassed_design
from pipeline.compensate.heldout import (
    Band,
    HeldOutResiduals,
    block_folds,
    filter_support_s,
    fold_log_ratios,
    fold_test_max,
    heldout_gain,
    heldout_residuals,
    linear_predictor,
)
from pipeline.compensate.nuisance import (
    attitude_rate_columns,
    current_columns,
    eddy_decay_columns,
    second_order_columns,
)
from pipeline.compensate.ridge import RidgeSVD
from pipeline.compensate.terms import per_sample_difference, tl18_terms

# the units of a current or voltage channel: only those are offered as coupling groups (a
# temperature or a pressure is not a current, and its slow drift fits calibration noise)
ELECTRICAL_UNITS = frozenset({"A", "mA", "uA", "V", "mV", "kV"})
TAU_GRID_S = tuple(float(t) for t in np.geomspace(0.02, 1.0, 7))
MIN_HELDOUT_S = 120.0  # least calibration time that gives folds worth testing on


def group_columns(
    group: str, meas, tau_s: float = 0.0, difference=per_sample_difference
) -> tuple[np.ndarray, list[str]]:
    """The columns of a term group on every epoch of ``meas`` (a
    :class:`pipeline.compensate.Measurements`); ``difference``: the eddy decay's per-sample
    derivative (:func:`pipeline.compensate.terms.tl18_terms`)."""
    if group == "eddy_decay":
        return eddy_decay_columns(meas.vector_nT, meas.time_s, tau_s, difference=difference)
    if group == "second_order":
        return second_order_columns(meas.vector_nT, meas.time_s)
    if group == "attitude_rates":
        if meas.attitude_deg is None:
            raise ValueError("the attitude-rate terms need the attitude (/ins/attitude)")
        return attitude_rate_columns(*meas.attitude_deg.T, meas.time_s)
    if group.startswith("current:"):
        name = group.split(":", 1)[1]
        if name not in meas.aux:
            raise ValueError(f"no auxiliary channel {name!r} (/aux/{name})")
        return current_columns(meas.vector_nT, meas.aux[name], name)
    raise ValueError(f"unknown term group {group!r}")


def ridge_theta(k: np.ndarray, y: np.ndarray, ridge: float | str) -> np.ndarray:
    """The ridge solution with a given lambda or the L-curve corner (``"auto"``), through
    the normal equations (:meth:`RidgeSVD.from_gram`): held-out folds fit many designs."""
    if k.shape[0] < 2 * k.shape[1]:
        raise ValueError(f"only {k.shape[0]} usable calibration samples for {k.shape[1]} terms")
    solver = RidgeSVD.from_gram(k, y)
    lam = solver.lcurve().lambda_corner if ridge == "auto" else float(ridge)
    return solver.solve(lam)


def candidate_groups(meas) -> list[str]:
    """The groups this recording can offer: eddy decay and second order always, attitude
    rates with an attitude, one current group per recorded auxiliary current or voltage
    channel (unit in :data:`ELECTRICAL_UNITS`) that varies."""
    out = ["eddy_decay", "second_order"]
    if meas.attitude_deg is not None:
        out.append("attitude_rates")
    for name, x in sorted(meas.aux.items()):
        if meas.aux_units.get(name, "") in ELECTRICAL_UNITS and np.nanstd(x) > 0:
            out.append(f"current:{name}")
    return out


def aligned(a: HeldOutResiduals, b: HeldOutResiduals) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Both models' held-out residuals on the epochs they share: (a, b, epoch indices)."""
    common, ia, ib = np.intersect1d(a.where, b.where, assume_unique=True, return_indices=True)
    return a.residual_nT[ia], b.residual_nT[ib], common


@dataclass
class HeldOutSetup:
    """What every held-out evaluation of one calibration shares."""

    meas: Any  # pipeline.compensate.Measurements
    band: Band
    fold: np.ndarray
    buffer_s: float
    ridge: float | str
    # the per-sample derivative of the eddy columns (tl18's and the decay's): MagNav's for
    # the compensation, the audit's its own (:func:`pipeline.compensate.terms.tl18_terms`)
    difference: Any = per_sample_difference
    # band-passed rows (K, y, epochs) of the columns most recently passed as ``beside``
    # (:meth:`linear`), per set of epochs: forward selection tries every group beside them
    _beside: tuple[np.ndarray, dict[bytes, tuple]] | None = field(
        default=None, repr=False, compare=False
    )

    @classmethod
    def of(cls, meas, mask: np.ndarray, settings, difference=per_sample_difference) -> HeldOutSetup:
        """Folds over the calibration epochs ``mask`` (raises ValueError when the calibration
        is too short for held-out blocks)."""
        if settings.band_hz is None:
            raise ValueError(f"{settings.model} needs a band-passed fit (set band_hz)")
        valid = mask & np.isfinite(meas.scalar_nT) & np.all(np.isfinite(meas.vector_nT), axis=1)
        span = float(np.sum(valid)) / meas.rate_hz
        if span < MIN_HELDOUT_S:
            raise ValueError(
                f"{settings.model} needs at least {MIN_HELDOUT_S:g} s of calibration for its "
                f"held-out blocks; the calibration has {span:.0f} s"
            )
        band = Band(tuple(settings.band_hz), settings.poles, settings.trim_s)
        buffer = filter_support_s(band.band_hz, meas.rate_hz, band.poles)
        return cls(meas, band, block_folds(valid), buffer, settings.ridge, difference)

    def linear(self, columns: np.ndarray, beside: np.ndarray | None = None) -> HeldOutResiduals:
        """Held-out residuals of the linear model on ``columns`` (and the columns ``beside``
        them, when given: band-passed once per fold however many models are tried beside
        the same array; the band-pass acts on each column alone, so the rows are the same as
        those of the columns side by side)."""
        m = self.meas
        if beside is None:

            def fit(k: np.ndarray, y: np.ndarray) -> np.ndarray:
                return ridge_theta(k, y, self.ridge)

            pred = linear_predictor(columns, m.scalar_nT, m.time_s, m.rate_hz, self.band, fit)
            return heldout_residuals(pred, m.time_s, self.fold, self.buffer_s)

        def predict(train: np.ndarray, test: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            kf, yf, _ = self._rows(columns, beside, train)
            theta = ridge_theta(kf, yf, self.ridge)
            kt, yt, wt = self._rows(columns, beside, test)
            return yt - kt @ theta, wt

        return heldout_residuals(predict, m.time_s, self.fold, self.buffer_s)

    def _rows(
        self, columns: np.ndarray, beside: np.ndarray, mask: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:func:`bandpassed_design`'s rows of ``[beside, columns]`` on ``mask``, with
        ``beside``'s band-passed rows kept for the next call with the same array."""
        m, b = self.meas, self.band
        # the epochs both parts can use, so each is band-passed over the same blocks
        valid = mask & np.all(np.isfinite(columns), axis=1) & np.all(np.isfinite(beside), axis=1)
        args = (m.scalar_nT, m.time_s, m.rate_hz, valid, b.band_hz, b.poles, b.trim_s)
        if self._beside is None or self._beside[0] is not beside:
            self._beside = (beside, {})
        key = valid.tobytes()
        kept = self._beside[1].get(key)
        if kept is None:
            kept = self._beside[1][key] = bandpassed_design(beside, *args)
        kc, _, _ = bandpassed_design(columns, *args)
        return np.column_stack([kept[0], kc]), kept[1], kept[2]


@dataclass
class GroupTrial:
    """One group's held-out figures in the round it was last tried."""

    group: str
    selected: bool
    heldout_before_nT: float
    heldout_after_nT: float
    p_value: float
    columns: int
    tau_s: float | None = None
    reason: str = ""
    p_value_folds: float = 1.0  # Holm-adjusted, the held-out folds as the unit
    audit: dict | None = None  # the audit's record when it named this group (seeded)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: the figures, the reduction in percent and why it was (not) taken."""
        red = (
            100.0 * (1.0 - self.heldout_after_nT / self.heldout_before_nT)
            if self.heldout_before_nT > 0
            else 0.0
        )
        return {
            "selected": self.selected,
            "columns": self.columns,
            "heldout_before_nT": self.heldout_before_nT,
            "heldout_after_nT": self.heldout_after_nT,
            "reduction_pct": red,
            "p_value_holm": self.p_value,
            "p_value_folds_adjusted": self.p_value_folds,
            "tau_s": self.tau_s,
            "reason": self.reason,
            "seeded_by_audit": self.audit,
        }


@dataclass
class Selection:
    """The groups forward selection took, the held-out residuals of tl18 and of the
    selected model, and every group's trial."""

    groups: list[str]
    tau_s: float | None
    base: HeldOutResiduals
    final: HeldOutResiduals
    trials: dict[str, GroupTrial] = field(default_factory=dict)


def _try(setup: HeldOutSetup, current: np.ndarray, group: str):
    """(columns, held-out residuals, tau) of ``current`` plus ``group`` (eddy decay: the
    time constant with the smallest held-out residual)."""
    taus = TAU_GRID_S if group == "eddy_decay" else (0.0,)
    best = None
    for tau in taus:
        cols, _ = group_columns(group, setup.meas, tau, setup.difference)
        held = setup.linear(cols, beside=current)
        if best is None or held.rms_nT < best[1].rms_nT:
            best = (cols, held, tau if group == "eddy_decay" else None)
    return best


def _why(reduction: float, p: float, p_fold: float, alpha: float, min_gain: float) -> str:
    """Why a group is (not) taken, in words."""
    problems = []
    if reduction < min_gain:
        problems.append(f"held-out reduction {100 * reduction:.1f} % below {100 * min_gain:g} %")
    if p >= alpha:
        problems.append(f"not significant over 10-s blocks (p {p:.2g} >= {alpha:g})")
    if p_fold >= alpha:
        problems.append(f"not significant over the held-out folds (p {p_fold:.2g} >= {alpha:g})")
    return "; ".join(problems) if problems else "lowers the held-out residual"


def _round(setup: HeldOutSetup, current, held, pool, alpha, min_gain, trials):
    """One forward-selection round over ``pool``: every group's trial (into ``trials``)
    and the entering group's (name, columns, held-out residuals, tau), or None."""
    from pipeline.audit.evidence import holm

    t = setup.meas.time_s
    tries = {g: _try(setup, current, g) for g in pool}
    tests, by_fold = {}, {}
    labels = np.unique(setup.fold[setup.fold >= 0])
    for g, (_, h, _) in tries.items():
        a, b, w = aligned(held, h)
        tests[g] = heldout_gain(a, b, t[w])
        by_fold[g] = fold_log_ratios(a, b, setup.fold[w], labels)
    p_adj = dict(zip(tests, holm([v.p_value for v in tests.values()]), strict=True))
    # the candidates share the folds: adjusted jointly, by the largest candidate's gain
    p_fold = fold_test_max(by_fold)
    for g, v in tests.items():
        trials[g] = GroupTrial(
            g,
            False,
            v.rms_before_nT,
            v.rms_after_nT,
            p_adj[g],
            tries[g][0].shape[1],
            tries[g][2],
            _why(v.reduction, p_adj[g], p_fold[g], alpha, min_gain),
            p_fold[g],
            trials[g].audit if g in trials else None,
        )
    passing = [
        g
        for g, v in tests.items()
        if p_adj[g] < alpha and p_fold[g] < alpha and v.reduction >= min_gain
    ]
    if not passing:
        return None
    g = min(passing, key=lambda x: tries[x][1].rms_nT)
    return (g, *tries[g])


def select_groups(
    setup: HeldOutSetup, alpha: float, min_gain: float, seeded: dict[str, dict] | None = None
) -> Selection:
    """:func:`forward_selection`, then the eddy decay's time constant (when taken) refined
    between its grid neighbours (:func:`refine_tau`): the selection's held-out residuals
    and the decay trial's ``tau_s`` are the refined model's."""
    sel = forward_selection(setup, alpha, min_gain, seeded)
    if sel.tau_s is not None:
        sel.tau_s, sel.final = refine_tau(setup, sel.groups, sel.tau_s)
        sel.trials["eddy_decay"].tau_s = sel.tau_s
    return sel


def forward_selection(
    setup: HeldOutSetup, alpha: float, min_gain: float, seeded: dict[str, dict] | None = None
) -> Selection:
    """Forward selection of term groups on the held-out folds (see the module docstring),
    the eddy decay's time constant on :data:`TAU_GRID_S`.

    ``seeded``: groups the audit found (name -> its record, :func:`audit_nuisances`). They
    are tried first, by themselves: a nuisance named before this calibration's held-out
    test is one hypothesis each, not a pick among all candidates, so the Holm adjustment of
    those rounds runs over the seeded groups only. The other groups follow as usual.
    """
    current, _ = tl18_terms(setup.meas.vector_nT, difference=setup.difference)
    base = held = setup.linear(current)
    chosen: list[str] = []
    tau = None
    trials: dict[str, GroupTrial] = {}
    candidates = candidate_groups(setup.meas)
    seeds = [g for g in (seeded or {}) if g in candidates]
    for g in seeds:
        trials[g] = GroupTrial(g, False, np.nan, np.nan, 1.0, 0, audit=seeded[g])
    for phase in (seeds, [g for g in candidates if g not in seeds]):
        left = list(phase)
        while left:
            got = _round(setup, current, held, left, alpha, min_gain, trials)
            if got is None:
                break
            g, cols, held, tau_g = got
            current = np.column_stack([current, cols])
            chosen.append(g)
            trials[g].selected = True
            if tau_g is not None:
                tau = tau_g
            left.remove(g)
    return Selection(chosen, tau, base, held, trials)


def design(setup: HeldOutSetup, groups: list[str], tau_s: float) -> np.ndarray:
    """tl18's columns and those of ``groups`` (eddy decay with ``tau_s``)."""
    k, _ = tl18_terms(setup.meas.vector_nT, difference=setup.difference)
    cols = [group_columns(g, setup.meas, tau_s, setup.difference)[0] for g in groups]
    return np.column_stack([k, *cols])


def refine_tau(
    setup: HeldOutSetup, groups: list[str], tau_s: float
) -> tuple[float, HeldOutResiduals]:
    """The eddy decay's time constant between the grid's neighbours of ``tau_s`` (within
    :data:`TAU_GRID_S`'s range) that minimises the held-out residual of the selected model,
    and its held-out residuals: the grid's steps (a factor of two) leave a mismatched
    response a fraction of the decaying field. Bounded scalar search in log tau."""
    from scipy.optimize import minimize_scalar

    grid = np.log(TAU_GRID_S)
    i = int(np.argmin(np.abs(grid - np.log(tau_s))))
    lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]
    cache: dict[float, HeldOutResiduals] = {}
    # the columns that do not depend on tau, band-passed once
    fixed = design(setup, [g for g in groups if g != "eddy_decay"], tau_s)

    def rms(log_tau: float) -> float:
        if log_tau not in cache:
            eddy, _ = group_columns(
                "eddy_decay", setup.meas, float(np.exp(log_tau)), setup.difference
            )
            cache[log_tau] = setup.linear(eddy, beside=fixed)
        return cache[log_tau].rms_nT

    rms(grid[i])
    minimize_scalar(rms, bounds=(lo, hi), method="bounded", options={"xatol": 0.05, "maxiter": 8})
    best = min(cache, key=lambda x: cache[x].rms_nT)
    return float(np.exp(best)), cache[best]


def audit_nuisances(audit: dict | None) -> dict[str, dict]:
    """The nuisances an audit summary names under ``unexplained.nuisances`` (a list of
    ``{"name", "heldout_gain", "estimate"}``; names as tl-plus's groups: ``eddy_decay``,
    ``second_order``, ``attitude_rates``, ``current:<channel>``), by name. Read
    defensively: an absent key, a malformed entry or an unknown name is left out."""
    items = ((audit or {}).get("unexplained") or {}).get("nuisances") or []
    out: dict[str, dict] = {}
    if not isinstance(items, list):
        return out
    for it in items:
        if not isinstance(it, dict) or not isinstance(it.get("name"), str):
            continue
        name = it["name"]
        known = name in ("eddy_decay", "second_order", "attitude_rates")
        if known or (name.startswith("current:") and len(name) > len("current:")):
            out[name] = {"heldout_gain": it.get("heldout_gain"), "estimate": it.get("estimate")}
    return out
