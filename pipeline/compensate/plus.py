"""``tl-plus``: tl18 plus the term groups the calibration's held-out blocks support.

Candidate groups (column builders in :mod:`pipeline.compensate.nuisance`, shared with the
audit):

- ``eddy_decay``: the nine tl18 eddy columns through a first-order response, its time
  constant chosen among :data:`TAU_GRID_S` (0.02-1 s) by the held-out residual;
- ``second_order``: induced terms quadratic in the field and the squared-rate terms;
- ``current:<name>``: each recorded ``/aux`` channel coupling along a fixed body direction;
- ``attitude_rates``: roll, pitch and yaw rates (when the attitude is recorded).

Forward selection: each round fits every remaining group beside the current model on the
held-out folds of :mod:`pipeline.compensate.heldout` (contiguous blocks, buffered by the
band-pass's support, band-passed within each fold); the group with the smallest held-out
residual enters when the paired held-out test against the current model gives a
Holm-adjusted p below ``extension_alpha`` (over that round's candidates) and lowers the
held-out RMS by at least ``extension_min_gain``. The final model is fitted on the whole
calibration with the one T-L estimator (band-passed ridge).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pipeline.compensate.heldout import (
    Band,
    HeldOutResiduals,
    block_folds,
    consistent,
    filter_support_s,
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
from pipeline.compensate.terms import tl18_terms

# the units of a current or voltage channel: only those are offered as coupling groups (a
# temperature or a pressure is not a current, and its slow drift fits calibration noise)
ELECTRICAL_UNITS = frozenset({"A", "mA", "uA", "V", "mV", "kV"})
TAU_GRID_S = tuple(float(t) for t in np.geomspace(0.02, 1.0, 7))
MIN_HELDOUT_S = 120.0  # least calibration time that gives folds worth testing on


def group_columns(group: str, meas, tau_s: float = 0.0) -> tuple[np.ndarray, list[str]]:
    """The columns of a term group on every epoch of ``meas`` (a
    :class:`pipeline.compensate.Measurements`)."""
    if group == "eddy_decay":
        k, names = tl18_terms(meas.vector_nT)
        return eddy_decay_columns(k, names, meas.time_s, tau_s)
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

    @classmethod
    def of(cls, meas, mask: np.ndarray, settings) -> HeldOutSetup:
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
        return cls(meas, band, block_folds(valid), buffer, settings.ridge)

    def linear(self, columns: np.ndarray) -> HeldOutResiduals:
        """Held-out residuals of the linear model on ``columns``."""
        m = self.meas

        def fit(k: np.ndarray, y: np.ndarray) -> np.ndarray:
            return ridge_theta(k, y, self.ridge)

        pred = linear_predictor(columns, m.scalar_nT, m.time_s, m.rate_hz, self.band, fit)
        return heldout_residuals(pred, m.time_s, self.fold, self.buffer_s)


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
            "tau_s": self.tau_s,
            "reason": self.reason,
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
        cols, _ = group_columns(group, setup.meas, tau)
        held = setup.linear(np.column_stack([current, cols]))
        if best is None or held.rms_nT < best[1].rms_nT:
            best = (cols, held, tau if group == "eddy_decay" else None)
    return best


def _why(reduction: float, p: float, steady: bool, alpha: float, min_gain: float) -> str:
    """Why a group is (not) taken, in words."""
    problems = []
    if reduction < min_gain:
        problems.append(f"held-out reduction {100 * reduction:.1f} % below {100 * min_gain:g} %")
    if p >= alpha:
        problems.append(f"not significant (p {p:.2g} >= {alpha:g})")
    if not steady:
        problems.append("not lower in all held-out blocks but one")
    return "; ".join(problems) if problems else "lowers the held-out residual"


def select_groups(setup: HeldOutSetup, alpha: float, min_gain: float) -> Selection:
    """Forward selection of term groups on the held-out folds (see the module docstring)."""
    from pipeline.audit.evidence import holm

    current, _ = tl18_terms(setup.meas.vector_nT)
    base = held = setup.linear(current)
    chosen: list[str] = []
    tau = None
    trials: dict[str, GroupTrial] = {}
    left = candidate_groups(setup.meas)
    t = setup.meas.time_s
    while left:
        tries = {g: _try(setup, current, g) for g in left}
        tests, steady = {}, {}
        for g, (_, h, _) in tries.items():
            a, b, w = aligned(held, h)
            tests[g] = heldout_gain(a, b, t[w])
            steady[g] = consistent(a, b, setup.fold[w])
        p_adj = dict(zip(tests, holm([v.p_value for v in tests.values()]), strict=True))
        for g, v in tests.items():
            why = _why(v.reduction, p_adj[g], steady[g], alpha, min_gain)
            trials[g] = GroupTrial(
                g,
                False,
                v.rms_before_nT,
                v.rms_after_nT,
                p_adj[g],
                tries[g][0].shape[1],
                tries[g][2],
                why,
            )
        passing = [
            g
            for g, v in tests.items()
            if p_adj[g] < alpha and v.reduction >= min_gain and steady[g]
        ]
        if not passing:
            break
        g = min(passing, key=lambda x: tries[x][1].rms_nT)
        cols, held, tau_g = tries[g]
        current = np.column_stack([current, cols])
        chosen.append(g)
        trials[g].selected = True
        if tau_g is not None:
            tau = tau_g
        left.remove(g)
    return Selection(chosen, tau, base, held, trials)
