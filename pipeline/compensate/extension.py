"""The fitted extensions of tl18 (``tl-plus``, ``tl-nn``) and their held-out guard.

An extension is used only when it beats tl18 on the calibration's held-out blocks by the
paired tests of :mod:`pipeline.compensate.heldout` (one-sided p below ``extension_alpha``
over 10-s blocks and with the held-out fold as the unit, held-out RMS lower by at least
``extension_min_gain``); otherwise the model keeps tl18's
coefficients and says why (``extension.used`` false, ``extension.reason``). The survey's
crossover guard (:func:`pipeline.compensate.stage.crossover_guard`) can revert it too.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from pipeline.compensate.heldout import fold_test, folds_improved, heldout_gain
from pipeline.compensate.model import (
    CompensationModel,
    FitSettings,
    Measurements,
    bandpassed,
    fit_columns,
    tl_terms,
)
from pipeline.compensate.plus import HeldOutSetup, aligned, group_columns, select_groups
from pipeline.compensate.terms import direction_cosines

if TYPE_CHECKING:  # the correction's module reads the audit's legs; imported where applied
    from pipeline.compensate.heading_levels import HeadingCorrection


@dataclass
class ExtendedModel(CompensationModel):
    """tl18 plus term groups (tl-plus) or a learned residual model (tl-nn).

    ``groups`` / ``tau_s``: tl-plus's selected groups (their columns follow tl18's in
    ``terms``) and the eddy decay's time constant (s); ``learner``: tl-nn's fitted
    regressor on :func:`pipeline.compensate.learned.features`, None when not used;
    ``extension``: JSON-ready record of the held-out comparison and the decision.
    """

    groups: list[str] = field(default_factory=list)
    tau_s: float | None = None
    learner: Any = None
    extension: dict[str, Any] = field(default_factory=dict)
    # tl18 fitted alone (coefficients, their standard deviations, lambda): what a reverted
    # extension applies (the extension's own tl18 part is fitted beside its other terms)
    tl18: tuple[np.ndarray, np.ndarray | None, float] | None = None
    # tl-plus: the calibration legs' heading levels as a permanent field, kept when the
    # survey's crossovers confirm it (pipeline.compensate.heading_levels)
    heading: HeadingCorrection | None = None

    @property
    def used(self) -> bool:
        """Whether the extension is applied (else the model is tl18's)."""
        return bool(self.extension.get("used"))

    def interference_nT(self, meas: Measurements) -> np.ndarray:
        """tl18's interference plus the selected groups' (tl-plus) or the learner's output
        band-passed over the flight (tl-nn), nT."""
        k, _ = tl_terms("tl18", meas)
        cols = [k] + [group_columns(g, meas, self.tau_s or 0.0)[0] for g in self.groups]
        out = np.column_stack(cols) @ self.coefficients[: self.n_tl]
        if self.learner is not None:
            from pipeline.compensate.learned import features, predict

            g = predict(self.learner, features(meas)[0])
            s = self.settings
            out = out + np.nan_to_num(bandpassed(meas.time_s, g, s.band_hz, s.poles))
        if self.heading is not None:
            out = out + self.heading.interference_nT(direction_cosines(meas.vector_nT))
        return out

    def revert(self, reason: str, guard: str) -> ExtendedModel:
        """This model with tl18's coefficients only, saying why (``guard``: which test)."""
        n18 = 18
        ext = {**self.extension, "used": False, "reason": reason, "guard": guard}
        theta, std, lam = self.tl18
        return replace(
            self,
            terms=self.terms[:n18],
            coefficients=theta,
            coefficient_std=std,
            lambda_=lam,
            n_tl=n18,
            groups=[],
            tau_s=None,
            learner=None,
            extension=ext,
            heading=None,
        )

    def to_dict(self) -> dict[str, Any]:
        """:meth:`CompensationModel.to_dict` plus ``extension`` and ``base_terms`` tl18."""
        d = super().to_dict()
        d["base_terms"] = "tl18"
        d["extension"] = self.extension
        return d


def _base_fit(meas: Measurements, mask: np.ndarray, s: FitSettings, groups, tau):
    k, names = tl_terms("tl18", meas)
    cols, all_names = [k], list(names)
    for g in groups:
        c, n = group_columns(g, meas, tau or 0.0)
        cols.append(c)
        all_names += n
    kk = np.column_stack(cols)
    return fit_columns(meas, mask, s, kk, all_names, kk.shape[1])


def _own(m: CompensationModel) -> tuple[np.ndarray, np.ndarray | None, float]:
    return m.coefficients.copy(), m.coefficient_std, m.lambda_


def _decision(s: FitSettings, before, after, where_t, fold) -> tuple[bool, str, dict]:
    test = heldout_gain(before, after, where_t)
    better, n = folds_improved(before, after, fold)
    p_fold = fold_test(before, after, fold)
    ok = (
        test.p_value < s.extension_alpha
        and p_fold < s.extension_alpha
        and test.reduction >= s.extension_min_gain
    )
    if ok:
        why = (
            f"held-out residual {test.rms_after_nT:.4f} nT against tl18's "
            f"{test.rms_before_nT:.4f} nT (p {test.p_value:.2g})"
        )
    else:
        why = (
            f"does not beat tl18 on held-out calibration blocks: {test.rms_after_nT:.4f} nT "
            f"against {test.rms_before_nT:.4f} nT ({100 * test.reduction:.1f} % lower, "
            f"p {test.p_value:.2g}, lower in {better} of {n} blocks; needs >= "
            f"{100 * s.extension_min_gain:g} % at p < {s.extension_alpha:g} over 10-s "
            f"blocks and over the folds, p {p_fold:.2g} there)"
        )
    return (
        ok,
        why,
        {
            **test.to_dict(),
            "p_value_folds": p_fold,
            "blocks_improved": better,
            "held_out_blocks": n,
        },
    )


def fit_extension(
    meas: Measurements, mask: np.ndarray, s: FitSettings, seeded: dict[str, dict] | None = None
) -> ExtendedModel:
    """Fit ``s.model`` (tl-plus or tl-nn) on the calibration epochs ``mask`` and decide on
    held-out blocks whether it replaces tl18. ``seeded``: tl-plus's groups the audit named
    (:func:`pipeline.compensate.plus.audit_nuisances`), tried first.

    Raises
    ------
    ValueError
        Too little calibration for the held-out blocks, or a feature channel missing.
    """
    setup = HeldOutSetup.of(meas, mask, s)
    if s.model == "tl-plus":
        sel = select_groups(setup, s.extension_alpha, s.extension_min_gain, seeded)
        base = _base_fit(meas, mask, s, sel.groups, sel.tau_s)
        alone = _base_fit(meas, mask, s, [], None) if sel.groups else base
        a, b, w = aligned(sel.base, sel.final)
        ok, why, test = _decision(s, a, b, meas.time_s[w], setup.fold[w])
        if not sel.groups:
            why = "no term group lowers the held-out residual; tl18 kept"
        ext = {
            "used": bool(ok and sel.groups),
            "reason": why,
            "guard": "heldout",
            "heldout_test": test,
            "candidate_heldout_residual_nT": float(np.sqrt(np.mean(b**2))),
            "tl18_heldout_residual_nT": float(np.sqrt(np.mean(a**2))),
            "term_groups": {g: t.to_dict() for g, t in sel.trials.items()},
            "eddy_tau_s": sel.tau_s,
            "seeded_by_audit": sorted(seeded or {}),
        }
        model = ExtendedModel(
            **vars(base), groups=sel.groups, tau_s=sel.tau_s, extension=ext, tl18=_own(alone)
        )
        return model if ext["used"] else model.revert(why, "heldout")
    from pipeline.compensate.learned import LearnedFolds, evaluate, fit_final

    folds = LearnedFolds(setup, s.learner, s.seed)
    ev = evaluate(folds)
    tl18 = setup.linear(folds.k18)
    a, b, w = aligned(tl18, ev.heldout)
    ok, why, test = _decision(s, a, b, meas.time_s[w], setup.fold[w])
    base = _base_fit(meas, mask, s, [], None)
    alone = _own(base)
    ext = {
        "used": bool(ok),
        "reason": why,
        "guard": "heldout",
        "learner": s.learner,
        "iterations": ev.n_iter,
        "heldout_test": test,
        "candidate_heldout_residual_nT": float(np.sqrt(np.mean(b**2))),
        "tl18_heldout_residual_nT": float(np.sqrt(np.mean(a**2))),
        "feature_importance": ev.importance_dict(),
    }
    if ok:
        learner, theta = fit_final(folds, mask, ev.n_iter)
        base = replace(base, coefficients=theta, coefficient_std=None)
    else:
        learner = None
    model = ExtendedModel(**vars(base), learner=learner, extension=ext, tl18=alone)
    return model if ok else model.revert(why, "heldout")
