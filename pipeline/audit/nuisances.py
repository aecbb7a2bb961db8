"""The carrier's physics outside the T-L basis, taken into the audit's null model first.

A catalogue effect is named only when it beats the null **with** the nuisances the data
support. The nuisance groups are :mod:`pipeline.compensate.plus`'s (one home for the design
columns, :mod:`pipeline.compensate.nuisance`, and for the buffered contiguous held-out folds,
:mod:`pipeline.compensate.heldout`):

- ``eddy_decay``: eddy currents decaying with a time constant tau (0.02-1 s), tau chosen by
  the held-out residual on ``tl-plus``'s grid, then refined between the grid's neighbours
  (the grid's steps are a factor 1.9: a 0.107 s decay read as 0.074 or 0.14 s leaves part of
  itself for a lag to take);
- ``second_order``: induced terms quadratic in the field and the squared-rate terms.

Recorded currents are catalogue effects (``electrical_current``), not nuisances, and the
attitude rates have no place in the audit's model forms; neither is offered here. Slow drift
and 1/f noise lie below the fit band, which removes them. A current that no channel records
has no columns here: a residual line it leaves is told from an event by its coherence with
the attitude (:func:`pipeline.audit.spectrum.manoeuvre_line`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy.optimize import minimize_scalar

from pipeline.audit.extended import AUDIT_DIFFERENCE
from pipeline.compensate.heldout import calibration_window
from pipeline.compensate.model import Measurements
from pipeline.compensate.plus import (
    TAU_GRID_S,
    HeldOutSetup,
    Selection,
    forward_selection,
    group_columns,
)
from pipeline.compensate.terms import tl18_terms
from pipeline.flight import Flight

# the nuisance groups whose columns the audit's model (pipeline.audit.extended.ModelSpec) holds
NULL_GROUPS = ("eddy_decay", "second_order")


@dataclass(frozen=True)
class _FitSettings:
    """What :meth:`HeldOutSetup.of` reads: the fit band and the ridge."""

    band_hz: tuple[float, float]
    poles: int
    trim_s: float
    ridge: float | str = "auto"
    model: str = "the audit's null model"


@dataclass
class Nuisance:
    """One nuisance group the null model took.

    Attributes
    ----------
    name : str
        Group name as in :mod:`pipeline.compensate.plus` (``eddy_decay``, ``second_order``).
    heldout_gain : float
        Fraction of the held-out residual RMS it removed (beside the groups taken before it).
    estimate : dict
        Its parameters (``eddy_decay``: ``tau_s``, the decay time constant, s).
    survey_guard : dict or None
        The survey crossovers' check of its terms
        (:meth:`pipeline.audit.survey_guard.CrossoverCheck.to_dict` and
        ``applied_to_survey``); None when not checked.
    """

    name: str
    heldout_gain: float
    estimate: dict[str, Any]
    survey_guard: dict[str, Any] | None = None

    def to_dict(self) -> dict[str, Any]:
        """The contract's record: ``{"name", "heldout_gain", "estimate"}``, and
        ``survey_guard`` when the survey checked it."""
        out = {"name": self.name, "heldout_gain": self.heldout_gain, "estimate": self.estimate}
        if self.survey_guard is not None:
            out["survey_guard"] = self.survey_guard
        return out


def decay_time_constant(setup: HeldOutSetup, others: np.ndarray) -> float:
    """The eddy currents' decay time constant (s): the one whose decayed eddy columns, in
    place of T-L's instantaneous ones beside the columns ``others`` (the T-L terms less the
    eddy ones, and the other groups), leave the smallest held-out residual; on ``tl-plus``'s
    grid (0.02-1 s), then a bounded search in log tau between the best point's neighbours.

    With T-L's instantaneous eddy columns beside them, decayed columns of another time
    constant mix with those into about the same response, so the time constant is read from
    the decay alone: the physical one, not the mixture's.
    """
    m = setup.meas

    def cost(log_tau: float) -> float:
        cols, _ = group_columns("eddy_decay", m, float(np.exp(log_tau)), setup.difference)
        return setup.linear(cols, beside=others).rms_nT

    grid = np.log(np.asarray(TAU_GRID_S))
    costs = [cost(g) for g in grid]
    i = int(np.argmin(costs))
    lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]
    res = minimize_scalar(cost, bounds=(lo, hi), method="bounded", options={"xatol": 0.03})
    return float(np.exp(res.x if res.fun <= costs[i] else grid[i]))


def _null_measurements(flight: Flight) -> Measurements:
    """The flight's compensation inputs without what is no nuisance here: recorded channels
    (catalogue candidates) and the attitude (its rate terms are no audit model form)."""
    return replace(Measurements.from_flight(flight), aux={}, aux_units={}, attitude_deg=None)


@dataclass
class NuisanceSelection:
    """The nuisances the null model took and the held-out figures behind them."""

    nuisances: list[Nuisance]
    selection: Selection | None
    note: str = ""
    setup: HeldOutSetup | None = None  # the buffered held-out folds the groups were tested on
    columns: np.ndarray | None = None  # the null model's design (T-L and the groups taken)
    # the flight's epoch of each of the setup's rows (None: the rows are the flight's)
    window: np.ndarray | None = None

    @property
    def eddy_tau_s(self) -> float:
        """The decay time constant the null model takes (s; 0 without eddy decay)."""
        for n in self.nuisances:
            if n.name == "eddy_decay":
                return float(n.estimate["tau_s"])
        return 0.0

    @property
    def second_order(self) -> bool:
        """Whether the null model takes the second-order terms."""
        return any(n.name == "second_order" for n in self.nuisances)

    def to_list(self) -> list[dict[str, Any]]:
        """``unexplained.nuisances``."""
        return [n.to_dict() for n in self.nuisances]


def select_nuisances(
    flight: Flight, mask: np.ndarray, band, alpha: float, min_gain: float
) -> NuisanceSelection:
    """:func:`select_from` on the flight's inputs less its recorded channels and attitude,
    on the epochs the calibration's fits read
    (:func:`pipeline.compensate.heldout.calibration_window`; ``window`` of the result)."""
    meas = _null_measurements(flight)
    idx = calibration_window(meas.time_s, mask)
    out = select_from(meas.take(idx), mask[idx], band, alpha, min_gain)
    out.window = idx
    return out


def select_from(
    meas: Measurements, mask: np.ndarray, band, alpha: float, min_gain: float
) -> NuisanceSelection:
    """Forward selection of the nuisance groups on the calibration epochs ``mask``
    (:func:`pipeline.compensate.plus.forward_selection`: held-out paired test at ``alpha``, Holm
    over each round, at least ``min_gain`` of the held-out RMS, lower in all folds but one),
    the decay's time constant then estimated on held-out data (:func:`decay_time_constant`).

    Parameters
    ----------
    meas : Measurements
        Time (s), scalar field (nT) and body-frame vector field (x forward, y right, z down;
        nT); recorded channels and attitude, when present, offer ``tl-plus``'s other groups.
    mask : ndarray of bool
        Calibration epochs.
    band : BandSettings
        The fit band (Hz), the filter's poles and trim.
    alpha, min_gain : float
        Test level and least held-out RMS reduction (fraction) of a group.
    """
    settings = _FitSettings(tuple(band.band_hz), band.poles, band.trim_s)
    try:
        setup = HeldOutSetup.of(meas, mask, settings, difference=AUDIT_DIFFERENCE)
        sel = forward_selection(setup, alpha, min_gain)
    except (ValueError, np.linalg.LinAlgError) as exc:
        return NuisanceSelection([], None, f"no nuisance tested: {exc}")
    tl, names = tl18_terms(meas.vector_nT, difference=AUDIT_DIFFERENCE)
    out, cols = [], [tl]
    for g in sel.groups:
        trial = sel.trials[g]
        est: dict[str, Any] = {}
        if g == "eddy_decay":
            instant = [i for i, n in enumerate(names) if not n.startswith("eddy_")]
            others = [tl[:, instant]] + [
                group_columns(h, meas, 0.0, AUDIT_DIFFERENCE)[0] for h in sel.groups if h != g
            ]
            est["tau_s"] = decay_time_constant(setup, np.column_stack(others))
        cols.append(group_columns(g, meas, est.get("tau_s", 0.0), AUDIT_DIFFERENCE)[0])
        gain = 1.0 - trial.heldout_after_nT / trial.heldout_before_nT
        out.append(Nuisance(g, float(gain), est))
    return NuisanceSelection(
        [n for n in out if n.name in NULL_GROUPS], sel, "", setup, np.column_stack(cols)
    )
