"""The model audit: what the baseline simulation of a measured flight gets wrong, and why.

1. Fit the baseline (T-L on the calibration passes) and simulate the measured flight with the
   simulator's physics (:func:`pipeline.audit.extended.simulate_measurement`); the residual
   measured - simulated on the calibration passes (band-passed) and the disagreement between
   lines (crossovers, validation overlaps) are what the model gets wrong.
2. Candidate effects, each a physical extension with its own regressors or test, are tried
   forward-stepwise: in each round every remaining candidate gets a nested-model test
   (F-test and BIC on the thinned band-passed calibration data; for the diurnal on the
   survey's crossovers and the calibration legs' block means; Holm correction over the
   round's candidates) **and** a held-out test: fitted without the held-out samples (other
   calibration pass, or alternate chunks of a single pass; for the diurnal, whose
   correction fits nothing, validation overlaps or each crossover and leg block predicted
   from the others), it must lower the held-out residual significantly (one-sided paired
   test over 10 s blocks or points) and by at least ``min_gain``. The vector calibration is
   judged on the fluxgate itself (its held-out magnitude mismatch, beyond a tolerance).
   Evidence the band-pass hardly sees can confirm a candidate: the calibration legs' ramps
   (a gradient), the survey's crossovers and a channel's switches (a current coupling), the
   fluxgate's record along the lines (a lag). The best passing
   candidate joins the model; the round repeats until none passes.
3. The extended model re-runs compensation, reduction and the quality figures, and the gain
   is measured: held-out residual, FOM, heading error at validation intersections, crossovers.
4. Structure left above the noise floor that no candidate explains is reported as such.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field
from datetime import UTC, datetime
from functools import cached_property
from typing import Any

import numpy as np
from scipy.optimize import curve_fit, minimize_scalar

from pipeline.audit.calibration_events import calibration_steps
from pipeline.audit.crossval import (
    BLOCK_S,
    N_FOLDS,
    calibration_strata,
    jackknife_ci95,
    passwise_folds,
    stratified_block_folds,
)
from pipeline.audit.decide import LagVersusDecay, significant
from pipeline.audit.diurnal import DiurnalSet, diurnal_evidence
from pipeline.audit.evidence import (
    HeldOut,
    NestedTest,
    band_noise_gain,
    heldout_gain,
    holm,
    nested_test,
    paired_point_gain,
    profile_f_test,
    thinning_step,
)
from pipeline.audit.extended import (
    LAG_RESPONSES,
    AuditData,
    BandSettings,
    CalibrationRows,
    FittedModel,
    ModelSpec,
    calibration_rows,
    design,
    fit_model,
    lag_cost,
    simulate_measurement,
)
from pipeline.audit.legs import (
    LegGradient,
    fisher_combined,
    leg_block_means,
    leg_gradient,
    leg_ids,
)
from pipeline.audit.noise import noise_floor_bounds
from pipeline.audit.nuisances import Nuisance, NuisanceSelection, select_nuisances
from pipeline.audit.null_calibration import NullCalibration, calibrate_null
from pipeline.audit.spectrum import manoeuvre_line, periodic_nuisance, residual_spectrum
from pipeline.audit.survey import (
    CrossoverSet,
    SurveyCoupling,
    SurveyHeading,
    SurveyLag,
    heading_levels,
    survey_coupling,
    survey_coupling_gain,
    survey_events,
    survey_heading,
    survey_lag,
)
from pipeline.audit.switching import (
    SwitchCoupling,
    SwitchSteps,
    switch_body_coupling,
    switch_coupling,
    switch_steps,
)
from pipeline.audit.timing import combined_interval, timing_lag
from pipeline.audit.vector_cal import fit_vector_calibration
from pipeline.audit.vector_reference import vector_reference_step
from pipeline.compensate.filters import bandpass_blocks, bandpass_sos, contiguous_blocks
from pipeline.compensate.model import figure_of_merit
from pipeline.compensate.nuisance import current_columns
from pipeline.compensate.stage import calibration_mask
from pipeline.compensate.terms import BT_SCALE_NT, direction_cosines, position_terms
from pipeline.defaults import default_field
from pipeline.errors import AeromagError
from pipeline.flight import Flight
from pipeline.geo.heading import heading_class, pattern_direction_deg
from pipeline.maps.reduce import BASE_SMOOTHING_S, time_window_mean
from pipeline.segment import Segmentation

# models whose band-passed calibration rows the auditor keeps (a fold loop uses two or three
# at a time; each is the calibration's rows x the model's columns, a few MB)
ROWS_CACHED = 8
# eddy currents' decay times tried (s): a carrier skin's L/R from a sample to well past
# the manoeuvres' shortest periods
EDDY_TAU_GRID_S = (0.05, 0.1, 0.2, 0.3, 0.5, 0.7, 1.0, 1.5)
# a decay time constant within this ratio of a lag is the same first-order response
SAME_RESPONSE_RATIO = 1.5
# span (s) over which a crossing reading's course over ground is taken: a few samples at
# any rate, short against a turn's 10-30 s
COURSE_WINDOW_S = 2.0


@dataclass
class AuditSettings:
    """Settings of the model audit (``[audit]``).

    Attributes
    ----------
    baseline : str
        Baseline T-L term set (``tl18`` or ``tl16``).
    alpha : float
        Significance level: family-wise per round for the F-tests (Holm), and of the held-out
        test.
    min_gain : float
        Smallest held-out RMS reduction (fraction) worth a model term.
    band : BandSettings
        Band-pass of the fits and residuals.
    block_s : float
        Block length of the held-out comparison, s.
    unexplained_factor : float
        Held-out residual / noise floor above which leftover structure is reported.
    max_lag_s : float
        Largest sensor lag searched (either sign), s.
    n_folds, block_s_cv : int, float
        Held-out folds, and the length of their blocks (s).
    max_generalization_gap : float
        Held-out / fit residual above which a warning is given.
    max_noise_rise : float
        The compensated record's white level in the upper half of the band over that in its
        quietest band above which the noise floor is reported as an upper bound.
    min_event_nT : float
        Smallest step or drift in the survey worth an event, nT.
    min_vector_step_nT : float
        Smallest change ``|dp|`` of the carrier's permanent field (body frame, nT) that the
        scalar-minus-fluxgate test (:mod:`pipeline.audit.vector_reference`) reports.
    min_leg_ramp_nT : float
        Smallest field change along the calibration legs (RMS, nT) with which a gradient
        seen there confirms a gradient candidate (:mod:`pipeline.audit.legs`).
    min_excess_gradient_nT_per_m : float
        Smallest horizontal gradient beyond the main field's (nT/m) that is named a
        gradient effect.
    min_lag_s : float
        Smallest sensor lag (s) that is named a lag effect.
    flight_alpha, null_draws, null_seed : float, int, int
        The whole selection's false-finding rate with nothing hidden, and the null model's
        bootstrap that measures it (draws, seed).
    min_nuisance_nT : float
        Held-out RMS (nT) a nuisance must remove, with the findings in the model, to stay.
    fluxgate_tolerance : float
        Largest attitude-dependent disagreement of the vector magnetometer's magnitude with
        the scalar field (held-out RMS, as a fraction of the field) that counts as a
        calibrated fluxgate.
    """

    # baseline, alpha, min_gain: the shipped configuration's [audit] values
    baseline: str = default_field("audit", "baseline")
    alpha: float = default_field("audit", "alpha")  # family-wise, per round (Holm)
    # smallest held-out RMS reduction worth a model term (fraction)
    min_gain: float = default_field("audit", "min_gain")
    band: BandSettings = field(default_factory=BandSettings)
    block_s: float = 10.0
    unexplained_factor: float = 1.5  # held-out residual / noise floor that counts as structure
    max_lag_s: float = 1.0
    n_folds: int = N_FOLDS  # held-out folds, each with blocks of every heading x manoeuvre
    block_s_cv: float = BLOCK_S
    max_generalization_gap: float = 2.0  # held-out / fit residual above this: a warning
    # the compensated record's upper-band over quietest-band white level above which the
    # noise floor is reported as an upper bound (white noise reads 1.04; interference that
    # rises with frequency, such as aliased airframe jitter, reads well above)
    max_noise_rise: float = 1.5
    min_event_nT: float = 0.3  # smallest step or drift in the survey worth an event
    # smallest |dp| of a permanent-field step against the fluxgate worth an event (nT)
    min_vector_step_nT: float = 1.0
    # a fluxgate reads the carrier's own field at it too (tens of nT on a UAV), which a
    # calibration absorbs as well; sensor errors worth naming are what a data sheet calls an
    # uncalibrated sensor: 0.05 % of the field (25 nT at 50 000 nT) is 0.03 deg of direction
    # or a 0.05 % scale, where low-cost fluxgates leave the factory at 0.5-2 % and 0.3-1 deg
    fluxgate_tolerance: float = 5e-4
    # the crust adds regional gradients of a few nT/km everywhere, which no main-field model
    # holds and long legs measure; a calibration site's gradient is an effect to model above
    # that, from 5 nT/km on (the manoeuvres' 10-50 m moves make 0.05-0.25 nT of it in the
    # band, the noise floor's order)
    min_excess_gradient_nT_per_m: float = 0.005
    # a gradient seen along the calibration legs confirms a gradient candidate when it is
    # significant and changes the field along the legs by at least this much (RMS, nT): a
    # real but negligible gradient (quiet ground, the main field's own) confirms nothing
    min_leg_ramp_nT: float = 0.5
    # the whole selection's false-finding rate on a flight with nothing hidden, and the
    # parametric bootstrap of the null model that measures it (pipeline.audit.null_calibration)
    flight_alpha: float = default_field("audit", "flight_alpha")
    null_draws: int = default_field("audit", "null_draws")
    null_seed: int = default_field("audit", "null_seed")
    # the interference a nuisance must remove to stay in the model beside the findings
    min_nuisance_nT: float = default_field("audit", "min_nuisance_nT")
    # a lag estimate moves with the resampling and the eddy columns' differences by a few
    # ms; under 20 ms a lag shifts the anomaly by less than 14 cm along track at 7 m/s (0.6 m
    # at 30 m/s), below a survey's positioning error: not worth a model term
    min_lag_s: float = 0.02


@dataclass
class Evaluation:
    """One candidate in one round."""

    effect: str
    key: str
    estimate: dict[str, Any]
    test: NestedTest | None
    heldout: HeldOut | None
    spec: ModelSpec | None
    p_adjusted: float = 1.0
    accepted: bool = False
    reason: str = ""
    metric: str = "heldout_calibration_residual_rms"
    ci95: dict[str, Any] = field(default_factory=dict)  # same keys as estimate: [lo, hi]
    held_back: bool = False  # a competing explanation fits as well: never accepted
    # p of independent evidence below the fit band (the calibration legs' gradient), combined
    # with the held-out p (Fisher) when present
    confirm_p: float | None = None
    # evidence the band-passed calibration hardly sees shows the extension's gain on its
    # own (the survey's crossovers or a channel's switches predicted leave-one-out, p <
    # alpha, by min_gain): the calibration's held-out gain then only needs to be positive
    # (a current that switches rarely during calibration)
    confirmed_gain: bool = False
    # the candidate's own evidence outside the calibration decides (a channel's switches over
    # the whole flight: a nested test and a held-out test of their own, both at alpha; the
    # calibration legs' ramps for a gradient); the calibration then only must not contradict
    # it (its held-out residual not worse by min_gain): a load switched a few times during a
    # calibration that band-passes its steps away, or a gradient seen only through the
    # manoeuvres' small moves, leaves the calibration's tests blind to it
    decided_outside: bool = False

    @property
    def heldout_p(self) -> float:
        """The held-out p-value the decision uses: the band-passed held-out test's, combined
        (Fisher) with ``confirm_p`` when the candidate has independent evidence."""
        if self.heldout is None:
            return 1.0
        if self.confirm_p is None:
            return self.heldout.p_value
        return fisher_combined(self.heldout.p_value, self.confirm_p)

    def passes(self, s: AuditSettings) -> bool:
        """Whether the candidate qualifies under ``s``: not held back, tested, Holm-adjusted
        F-test p and held-out p below ``alpha``, BIC lower, held-out reduction at least
        ``min_gain``.
        """
        if self.decided_outside:
            return (
                not self.held_back
                and self.heldout is not None
                and self.heldout.reduction > -s.min_gain
            )
        return (
            not self.held_back
            and self.test is not None
            and self.heldout is not None
            and self.p_adjusted < s.alpha
            and self.test.delta_bic < 0
            and self.heldout_p < s.alpha
            and self.gain_suffices(s)
        )

    def gain_suffices(self, s: AuditSettings) -> bool:
        """The held-out reduction reaches ``min_gain`` (or is positive where the survey
        confirmed the gain, ``confirmed_gain``)."""
        if self.heldout is None:
            return False
        if self.confirmed_gain:
            return self.heldout.reduction > 0
        return self.heldout.reduction >= s.min_gain

    def why_not(self, s: AuditSettings) -> str:
        """Why the candidate does not pass: its recorded reason, else the failed criteria ("; ")."""
        if self.reason:
            return self.reason
        if self.decided_outside and self.heldout is not None:
            return (
                f"the calibration contradicts the evidence outside it: held-out residual "
                f"{-100 * self.heldout.reduction:+.1f} % (more than {100 * s.min_gain:.0f} %)"
            )
        out = []
        if self.test is None or self.p_adjusted >= s.alpha:
            out.append(f"F-test p {self.p_adjusted:.3g} (Holm) >= {s.alpha}")
        if self.test is not None and self.test.delta_bic >= 0:
            out.append(f"delta BIC {self.test.delta_bic:+.1f}")
        if self.heldout is not None and self.heldout_p >= s.alpha:
            if self.confirm_p is None:
                out.append(f"held-out p {self.heldout.p_value:.3g} >= {s.alpha}")
            else:
                out.append(
                    f"held-out p {self.heldout.p_value:.3g} with the independent evidence's "
                    f"{self.confirm_p:.3g}: {self.heldout_p:.3g} >= {s.alpha}"
                )
        if self.heldout is not None and not self.gain_suffices(s):
            out.append(
                f"held-out gain {100 * self.heldout.reduction:.1f} % < {100 * s.min_gain:.0f} %"
            )
        return "; ".join(out)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready record of the candidate: estimates and 95 % intervals, test statistics,
        held-out gain (nT) and the decision.
        """
        return {
            "effect": self.effect,
            "key": self.key,
            "estimate": self.estimate,
            "estimate_ci95": self.ci95,
            "delta_bic": None if self.test is None else self.test.delta_bic,
            "p_value": None if self.test is None else self.test.p_value,
            "p_value_holm": self.p_adjusted,
            "f": None if self.test is None else self.test.f,
            "heldout": None if self.heldout is None else self.heldout.to_dict(),
            "heldout_p_combined": None if self.confirm_p is None else self.heldout_p,
            "decided_outside_calibration": self.decided_outside,
            "gain": None
            if self.heldout is None
            else {
                "metric": self.metric,
                "before_nT": self.heldout.rms_before_nT,
                "after_nT": self.heldout.rms_after_nT,
            },
            "accepted": self.accepted,
            "reason": self.reason,
        }


@dataclass
class AuditResult:
    """Everything the audit produced for one flight.

    The baseline and extended fits, the accepted findings and every round's candidates,
    held-out residuals and noise floors (nT), unexplained structure, the gain per metric, the
    compensated fields (``"baseline"``, ``"extended"``; nT per epoch), the measured-vs-simulated
    residuals on the calibration epochs ``residual_epochs``, the quality summaries, the inputs
    and the notes. Event times are absolute via ``t0_ns``.
    """

    baseline: FittedModel
    extended: FittedModel
    findings: list[Evaluation]
    rounds: list[list[Evaluation]]
    heldout_baseline_nT: float
    heldout_extended_nT: float
    band_noise_floor_nT: float  # the sensor's white noise through the calibration band-pass
    sensor_noise_nT: float  # the sensor's white noise per sample, from the record itself
    unexplained: dict[str, Any] | None
    gain: dict[str, dict[str, float | None]]
    compensated: dict[str, np.ndarray]  # "baseline", "extended"
    simulated: dict[str, np.ndarray]  # measured-vs-simulated residual, band-passed, cal epochs
    residual_epochs: np.ndarray
    quality: dict[str, Any]  # "baseline"/"extended" quality summaries (or empty)
    data: AuditData
    passes: list[np.ndarray]
    notes: list[str]
    generalization_gap: float = float("nan")  # baseline held-out / fit residual
    passwise_heldout_nT: float | None = None  # leave-one-pass-out, with two or more passes
    t0_ns: int = 0  # the flight's first epoch (event times are absolute)
    # the three upper bounds the noise floor is the least of (pipeline.audit.noise)
    noise_floor_bounds_nT: dict[str, float] | None = None
    noise_floor_is_upper_bound: bool = False  # the record's white level rises with frequency
    # the null model's bootstrap (pipeline.audit.null_calibration), JSON-ready; None: not run
    null_calibration: dict[str, Any] | None = None

    def to_json(self) -> dict[str, Any]:
        """AUDIT.json (issue 6 contract plus details)."""
        return {
            "baseline": {
                "model": self.baseline.spec.base,
                "residual_rms_nT": self.heldout_baseline_nT,
                "fit_residual_nT": self.baseline.fit_residual_nT,
                "generalization_gap": self.generalization_gap,
                "passwise_residual_rms_nT": self.passwise_heldout_nT,
                "lambda": self.baseline.lambda_,
            },
            "findings": [
                {
                    "effect": f.effect,
                    "estimate": f.estimate,
                    "estimate_ci95": f.ci95,
                    "delta_bic": f.test.delta_bic if f.test else None,
                    "p_value": f.test.p_value if f.test else None,
                    "p_value_holm": f.p_adjusted,
                    "heldout_p_value": f.heldout.p_value if f.heldout else None,
                    "heldout_p_combined": None if f.confirm_p is None else f.heldout_p,
                    "decided_outside_calibration": f.decided_outside,
                    "gain": {
                        "metric": f.metric,
                        "before_nT": f.heldout.rms_before_nT,
                        "after_nT": f.heldout.rms_after_nT,
                    }
                    if f.heldout
                    else None,
                    "alternatives": alternatives(f, self.rounds),
                }
                for f in self.findings
            ],
            "extended_model": self.extended.spec.label(),
            "unexplained_rms_nT": self.heldout_extended_nT,
            # the sensor's white noise per sample (issue 16 item 4); the held-out residuals,
            # band-passed, compare with band_noise_floor_nT
            "noise_floor_nT": self.sensor_noise_nT,
            "band_noise_floor_nT": self.band_noise_floor_nT,
            "noise_floor_bounds_nT": self.noise_floor_bounds_nT,
            # True: broadband interference rising with frequency lies under the floor, which
            # then bounds the sensor's noise from above rather than measuring it
            "noise_floor_is_upper_bound": self.noise_floor_is_upper_bound,
            "unexplained": self.unexplained,  # {"events": [...], "note", "spectrum", ...}
            "sensor_noise_nT": self.sensor_noise_nT,
            "gain": self.gain,
            "extended": {
                "residual_rms_nT": self.heldout_extended_nT,
                "fit_residual_nT": self.extended.fit_residual_nT,
                "lambda": self.extended.lambda_,
                "terms": self.extended.names,
                "coefficients": [float(c) for c in self.extended.theta],
            },
            "null_calibration": self.null_calibration,
            "rounds": [[e.to_dict() for e in r] for r in self.rounds],
            "notes": self.notes,
        }


# --------------------------------------------------------------------------------------------
def _fold_masks(fold: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """(train, test) epoch masks of each fold number in ``fold`` (-1: not calibration)."""
    inside = fold >= 0
    return [(inside & (fold != k), fold == k) for k in np.unique(fold[inside])]


@dataclass
class PassStep:
    """A change of the carrier's permanent field between two calibration passes
    (:meth:`Auditor.pass_steps`).

    Attributes
    ----------
    start_s, end_s : float
        End of the earlier pass and start of the later one, s from the flight's first
        epoch: the change happened somewhere between them.
    p_value : float
        F-test p of the change, Bonferroni-corrected over the gaps between passes.
    heldout : HeldOut
        Held-out calibration residuals without and with the change.
    """

    start_s: float
    end_s: float
    p_value: float
    heldout: HeldOut

    @property
    def middle_s(self) -> float:
        """The gap's middle (s), where the calibration model puts the change."""
        return 0.5 * (self.start_s + self.end_s)


class Auditor:
    """Runs the audit on one flight (see the module docstring)."""

    def __init__(self, flight: Flight, seg: Segmentation, settings: AuditSettings):
        self.flight, self.seg, self.s = flight, seg, settings
        self.mask = calibration_mask(flight, seg, "auto")
        self.data = AuditData.from_flight(flight, self.mask)
        self.passes = seg.passes()
        strata = calibration_strata(
            seg.cardinal,
            seg.manoeuvre,
            flight.data["yaw_deg"].to_numpy(float)
            if flight.has("yaw_deg")
            else np.zeros(self.mask.size),
        )
        self.fold = stratified_block_folds(
            self.data.time_s, self.mask, strata, settings.n_folds, settings.block_s_cv
        )
        self.folds = _fold_masks(self.fold)
        self.pass_fold = passwise_folds(self.mask, self.passes)
        self.step = thinning_step(self.data.rate_hz, settings.band.band_hz)
        self.notes: list[str] = []
        self._fit_cache: dict[tuple, FittedModel] = {}
        # each model's band-passed calibration rows, shared by its fits and residuals over
        # the folds (the design spans the whole flight: building it once per fit made the
        # audit grow with the survey); the last few models only
        self._rows_cache: OrderedDict[ModelSpec, CalibrationRows] = OrderedDict()
        self._crossover_cache: dict[tuple, tuple] = {}
        self._compensated: dict[ModelSpec, np.ndarray] = {}
        self._geometry: tuple | None = None
        self._pass_steps: dict[ModelSpec, list[PassStep]] = {}
        self.ambiguities: list[dict[str, Any]] = []

    @cached_property
    def nuisances(self) -> NuisanceSelection:
        """The carrier's physics outside the T-L basis the held-out calibration supports
        (:func:`pipeline.audit.nuisances.select_nuisances`): part of the null model."""
        return select_nuisances(self.flight, self.mask, self.s.band, self.s.alpha, self.s.min_gain)

    @cached_property
    def null_calibration(self) -> NullCalibration | None:
        """The selection's maximum statistic under the null model, by parametric bootstrap
        (:func:`pipeline.audit.null_calibration.calibrate_null`); None without the held-out
        folds."""
        nz = self.nuisances
        if nz.setup is None or nz.columns is None:
            return None
        d = self.data
        cands: dict[str, np.ndarray] = {}
        if d.enu_m is not None:
            cands["geomagnetic_gradient"] = position_terms(*d.enu_m.T)[0]
        for effect, key in self.candidates(ModelSpec(base=self.s.baseline)):
            if effect == "electrical_current":
                name = key.split(":", 1)[1]
                cands[key] = current_columns(d.vector_nT, d.aux[name], name)[0]
        try:
            return calibrate_null(
                nz.setup,
                nz.columns,
                cands,
                self.s.flight_alpha,
                self.s.min_gain,
                self.s.null_draws,
                self.s.null_seed,
            )
        except (ValueError, np.linalg.LinAlgError) as exc:
            self.notes.append(f"the null model's bootstrap could not run: {exc}")
            return None

    def null_spec(self) -> ModelSpec:
        """The null model: the baseline with the nuisances the data support."""
        nz = self.nuisances
        return ModelSpec(
            base=self.s.baseline,
            eddy_tau_s=nz.eddy_tau_s,
            second_order=nz.second_order,
        )

    @cached_property
    def legs(self) -> np.ndarray:
        """Calibration leg of each epoch (one heading of one pass), -1 elsewhere
        (:func:`pipeline.audit.legs.leg_ids`)."""
        return leg_ids(self.mask, self.seg.cardinal, self.seg.calibration_pass, self.data.time_s)

    @cached_property
    def base_smoothed_nT(self) -> np.ndarray:
        """The base station's reading on the scalar epochs, smoothed over
        ``BASE_SMOOTHING_S`` (nT; read-only: shared)."""
        base = time_window_mean(
            self.data.time_s, self.flight.data["base_nT"].to_numpy(float), BASE_SMOOTHING_S
        )
        base.flags.writeable = False
        return base

    def compensated(self, spec: ModelSpec) -> np.ndarray:
        """``spec``'s compensated field (fitted on all of the calibration) at every epoch,
        nT; kept per model, read-only: the survey, leg and fluxgate tests of one round ask
        for the same model's."""
        if spec not in self._compensated:
            comp, _ = self.fit(spec, None, "all").compensate(self.data)
            comp.flags.writeable = False
            self._compensated[spec] = comp
        return self._compensated[spec]

    def rows(self, spec: ModelSpec) -> CalibrationRows:
        """``spec``'s band-passed calibration rows (:func:`calibration_rows`), kept for the
        most recently used models."""
        got = self._rows_cache.get(spec)
        if got is None:
            got = calibration_rows(self.data, spec, self.mask, self.s.band)
            self._rows_cache[spec] = got
            while len(self._rows_cache) > ROWS_CACHED:
                self._rows_cache.popitem(last=False)
        else:
            self._rows_cache.move_to_end(spec)
        return got

    # -- fitting helpers ------------------------------------------------------------------
    def fit(
        self, spec: ModelSpec, keep: np.ndarray | None, key: str, ridge: str | None = None
    ) -> FittedModel:
        """``spec`` fitted on the calibration rows of ``keep``, band-passed over the whole
        calibration. Fold fits (``keep`` given) choose ridge lambda by inner
        cross-validation over the training folds; the fit on all of the calibration (``keep``
        None: estimates, compensated outputs) uses the L-curve corner as the compensation
        stage does — cross-validation cannot see the directions the band-pass removes (the
        compensated field's level), the L-curve keeps them small."""
        ridge = ridge or ("auto" if keep is None else "cv")
        ck = (spec, key, ridge)
        if ck not in self._fit_cache:
            self._fit_cache[ck] = fit_model(
                self.data,
                spec,
                self.mask,
                self.s.band,
                ridge=ridge,
                keep=keep,
                folds=self.fold,
                rows=self.rows(spec),
            )
        return self._fit_cache[ck]

    def heldout(self, before, after_for_fold) -> HeldOut:
        """Held-out band-passed residuals of two models over the folds; ``after_for_fold``
        builds the extended spec from the training mask (parameters estimated there);
        ``before`` is a spec, or like ``after_for_fold`` a builder of one."""
        rb, ra, tt = [], [], []
        for k, (train, test) in enumerate(self.folds):
            spec_b = before(train, k) if callable(before) else before
            mb = self.fit(spec_b, train, f"fold{k}")
            spec_a = after_for_fold(train, k)
            ma = self.fit(spec_a, train, f"fold{k}")
            r0, w0 = mb.residual_bp(
                self.data, self.mask, self.s.band, keep=test, rows=self.rows(spec_b)
            )
            r1, w1 = ma.residual_bp(
                self.data, self.mask, self.s.band, keep=test, rows=self.rows(spec_a)
            )
            common, i0, i1 = np.intersect1d(w0, w1, return_indices=True)
            rb.append(r0[i0])
            ra.append(r1[i1])
            tt.append(self.data.time_s[common])
        return heldout_gain(
            np.concatenate(rb), np.concatenate(ra), np.concatenate(tt), self.s.block_s
        )

    def _nested(
        self, spec: ModelSpec, extra: np.ndarray | None = None, ext_spec: ModelSpec | None = None
    ) -> NestedTest:
        """Nested test on the whole calibration: ``spec``'s columns vs ``ext_spec``'s (or
        plus the unfiltered ``extra`` columns), band-passed on the same blocks."""
        des = design(self.data, spec)
        if ext_spec is not None:
            des_e = design(self.data, ext_spec)
            cols_e = des_e.columns
        else:
            cols_e = np.column_stack([des.columns, extra])
        valid = (
            self.mask
            & np.isfinite(des.y)
            & np.all(np.isfinite(cols_e), axis=1)
            & np.all(np.isfinite(des.columns), axis=1)
        )
        blocks = contiguous_blocks(valid, self.data.time_s)
        sos = bandpass_sos(self.s.band.band_hz, self.data.rate_hz, self.s.band.poles)
        kb, _ = bandpass_blocks(des.columns, blocks, sos, self.s.band.trim_at(self.data.rate_hz))
        ke, _ = bandpass_blocks(cols_e, blocks, sos, self.s.band.trim_at(self.data.rate_hz))
        yf, _ = bandpass_blocks(des.y, blocks, sos, self.s.band.trim_at(self.data.rate_hz))
        return nested_test(yf, kb, ke, self.step)

    def _lag_profile_test(self, spec: ModelSpec, lag_s: float) -> NestedTest:
        """The lag's profile-likelihood F-test beside ``spec``'s columns (the record delayed
        by ``lag_s`` against not): beside decayed eddy columns, which span the lag's
        linearisation (a first-order response), only the delay of the whole reading tells a
        late sensor (:func:`pipeline.audit.evidence.profile_f_test`)."""
        d0, d1 = design(self.data, spec), design(self.data, spec.with_(lag_s=lag_s))
        valid = (
            self.mask
            & np.isfinite(d0.y)
            & np.isfinite(d1.y)
            & np.all(np.isfinite(d0.columns), axis=1)
        )
        blocks = contiguous_blocks(valid, self.data.time_s)
        sos = bandpass_sos(self.s.band.band_hz, self.data.rate_hz, self.s.band.poles)
        trim = self.s.band.trim_at(self.data.rate_hz)
        kb, _ = bandpass_blocks(d0.columns, blocks, sos, trim)
        y0, _ = bandpass_blocks(d0.y, blocks, sos, trim)
        y1, _ = bandpass_blocks(d1.y, blocks, sos, trim)
        return profile_f_test(y0, y1, kb, self.step)

    # -- candidates -----------------------------------------------------------------------
    def candidates(self, current: ModelSpec) -> list[tuple[str, str]]:
        """Candidate effects not yet in ``current``, as (effect, key) pairs.

        The geomagnetic gradient (with positions), sensor lag, the diurnal (with a base station),
        each auxiliary channel with an electrical unit that varies over the
        calibration (key ``electrical_current:<name>``) and the vector calibration.
        """
        out = []
        if (
            not current.gradient
            and current.known_gradient_nT_per_m is None
            and self.data.enu_m is not None
        ):
            out.append(("geomagnetic_gradient", "geomagnetic_gradient"))
        if not current.lag_s:
            out.append(("sensor_lag", "sensor_lag"))
        if not current.diurnal and self.flight.has("base_nT"):
            out.append(("diurnal", "diurnal"))
        for name, x in self.data.aux.items():
            if (
                name in current.aux
                or name in dict(current.known_aux)
                or not _electrical(self.data.aux_units.get(name, ""))
            ):
                continue
            xc = x[self.mask]
            if np.isfinite(xc).sum() > 100 and np.nanstd(xc) > 1e-9:
                out.append(("electrical_current", f"electrical_current:{name}"))
        if current.vector_cal is None:
            out.append(("vector_calibration", "vector_calibration"))
        return out

    def evaluate(self, current: ModelSpec, effect: str, key: str) -> Evaluation:
        """Test candidate ``key`` of ``effect`` against ``current`` (``_eval_<effect>``).

        A candidate whose fit fails (``ValueError``, ``LinAlgError``) comes back untested, with the
        reason.
        """
        try:
            return getattr(self, f"_eval_{effect}")(current, key)
        except (ValueError, np.linalg.LinAlgError) as exc:
            return Evaluation(
                effect, key, {}, None, None, None, reason=f"could not be tested: {exc}"
            )

    def _eval_geomagnetic_gradient(self, current: ModelSpec, key: str) -> Evaluation:
        ext = current.with_(gradient=True)
        test = self._nested(current, ext_spec=ext)
        held = self.heldout(current, lambda train, k: ext)

        def gradient(fm: FittedModel) -> dict[str, float]:
            c = dict(zip(fm.names, fm.theta, strict=True))
            return {
                "east_nT_per_m": float(c["pos_e"]),
                "north_nT_per_m": float(c["pos_n"]),
                "up_nT_per_m": float(c["pos_up"]),
            }

        est = gradient(self.fit(ext, None, "all"))
        folds = [gradient(self.fit(ext, tr, f"fold{k}")) for k, (tr, _) in enumerate(self.folds)]
        ev = Evaluation(
            "geomagnetic_gradient", key, est, test, held, ext, ci95=jackknife_ci95(est, folds)
        )
        # the direct evidence, below the fit band: the compensated field's ramps along the
        # straight legs. Far more precise than the band-passed position terms (which see the
        # gradient only through the manoeuvres' small moves), so it is the reported estimate;
        # the fit's own values stay as fit_*
        legs = self.leg_gradient(current)
        main = self._main_field_gradient()  # IGRF's (east, north, up), nT/m, or None
        if legs is not None:
            for k in ("east_nT_per_m", "north_nT_per_m", "up_nT_per_m"):
                ev.estimate[f"fit_{k}"] = ev.estimate.pop(k)
                ev.ci95[f"fit_{k}"] = ev.ci95.pop(k)
            ci = legs.ci95()
            for i, k in enumerate(("east_nT_per_m", "north_nT_per_m", "up_nT_per_m")):
                ev.estimate[k] = float(legs.gradient_nT_per_m[i])
                ev.ci95[k] = [float(ci[i, 0]), float(ci[i, 1])]
            ev.estimate["calibration_legs_p_value"] = legs.p_value
            ev.estimate["calibration_legs_ramp_rms_nT"] = legs.ramp_rms_nT
            ev.estimate["calibration_legs_blocks"] = legs.blocks
            for k in ("p_value", "ramp_rms_nT", "blocks"):
                ev.ci95[f"calibration_legs_{k}"] = None
            excess, p_excess, why_not = self._leg_gradient_verdict(legs, main)
            ev.estimate["calibration_legs_excess_ramp_rms_nT"] = excess
            ev.estimate["calibration_legs_excess_p_value"] = p_excess
            ev.ci95["calibration_legs_excess_ramp_rms_nT"] = None
            ev.ci95["calibration_legs_excess_p_value"] = None
            if why_not:
                ev.held_back, ev.reason = True, why_not
            if not ev.held_back:
                ev.confirm_p = p_excess
                # the legs measured a gradient that matters (beyond the regional, ramping
                # along the legs); the band-passed calibration sees it only through the
                # manoeuvres' small moves, so it need only not contradict it
                ev.decided_outside = True
                # the legs measured the gradient: it can also be taken out of the reading
                # instead of fitted as position columns, which see it only through the
                # manoeuvres' moves and may extrapolate between blocks; the form that
                # lowers the held-out residual more is the extension
                known = self._with_legs_gradient(current, legs)
                held_known = self.heldout(current, lambda train, k: known)
                if held_known.reduction > held.reduction:
                    ev.spec, ev.heldout = known, held_known
        # independent evidence: a gradient during calibration biases the heading terms, which
        # the survey's crossovers show as heading levels (and levels that change across the
        # survey); the extended model should flatten them
        before, after = self.survey_heading(current), self.survey_heading(ev.spec)
        if before is not None and after is not None:
            survey = {
                "survey_heading_spread_before_nT": before.spread_nT,
                "survey_heading_spread_after_nT": after.spread_nT,
                "survey_heading_p_value": before.p_value,
                "survey_heading_position_p_value": before.position_p_value,
            }
            ev.estimate.update(survey)
            ev.ci95.update({k: None for k in survey})
        # the fitted gradient is the total field's: the main field's own (IGRF) is part of it
        if main is not None:
            for axis, v in zip(("east", "north", "up"), main, strict=True):
                ev.estimate[f"main_field_{axis}_nT_per_m"] = float(v)
                # computed, not estimated: its interval is the value itself
                ev.ci95[f"main_field_{axis}_nT_per_m"] = [float(v), float(v)]
        return ev

    def _leg_gradient_verdict(
        self, legs: LegGradient, main: np.ndarray | None
    ) -> tuple[float, float, str | None]:
        """(ramp RMS of the legs' gradient beyond the main field's, nT; p of its excess over
        the main field's; why it is no gradient effect to model, or None).

        A gradient that is the main field's own (IGRF: ~0.005 nT/m, 0.7 nT along a 500 m
        leg) is no effect to model; a recording made without it (a flat main field) shows
        none, so both the gradient and its excess over IGRF must be large and ramp, and the
        excess must be significant (:meth:`LegGradient.excess_p_value` < alpha).
        """
        igrf = main[:2] if main is not None else np.zeros(2)
        horizontal = legs.gradient_nT_per_m[:2]
        excess = legs.ramp_rms_for(horizontal - igrf)
        size = min(float(np.hypot(*horizontal)), float(np.hypot(*(horizontal - igrf))))
        ramp = min(legs.ramp_rms_nT, excess)
        p_excess = legs.excess_p_value(igrf)
        why_not = None
        if p_excess >= self.s.alpha:
            # the size below is a point estimate: with a few blocks per leg, or nuisance
            # columns that share the ramps, it can exceed the threshold by its error alone
            why_not = (
                "the calibration legs' gradient is not distinguishable from the main field's "
                f"(p {p_excess:.2g} >= {self.s.alpha:g})"
            )
        elif size < self.s.min_excess_gradient_nT_per_m:
            why_not = (
                f"the calibration legs' gradient beyond the main field's, {1e3 * size:.2f} "
                f"nT/km, is a regional one (< {1e3 * self.s.min_excess_gradient_nT_per_m:g}"
                " nT/km): not a gradient effect to model"
            )
        elif ramp < self.s.min_leg_ramp_nT:
            # the legs measure a gradient far better than the position columns do; when
            # they see none beyond the main field's, the columns' gain is something else
            # they happen to fit (a current, second-order terms)
            why_not = (
                "the calibration legs show no gradient beyond the main field's (ramp "
                f"{ramp:.2f} nT RMS < "
                f"{self.s.min_leg_ramp_nT:g}): the position terms fit something else"
            )
        return excess, p_excess, why_not

    @staticmethod
    def _with_legs_gradient(spec: ModelSpec, legs: LegGradient) -> ModelSpec:
        """``spec`` with the legs' horizontal gradient taken out of the reading (their
        vertical component is not evidence, :mod:`pipeline.audit.legs`)."""
        g_e, g_n, _ = (float(g) for g in legs.gradient_nT_per_m)
        return spec.with_(known_gradient_nT_per_m=(g_e, g_n, 0.0))

    def gradient_from_legs(self, spec: ModelSpec) -> ModelSpec | None:
        """``spec`` with the horizontal gradient the calibration legs measure taken out of
        the reading, when they measure one that matters (p < alpha and no reason against
        it in :meth:`_leg_gradient_verdict`, which tests its excess over the main field's,
        as for the gradient's own candidate); else None."""
        legs = self.leg_gradient(spec)
        if legs is None:
            return None
        if self._leg_gradient_verdict(legs, self._main_field_gradient())[2]:
            return None
        return self._with_legs_gradient(spec, legs)

    def _main_field_gradient(self) -> np.ndarray | None:
        """IGRF's total-field gradient (east, north, up; nT/m) at the calibration site."""
        from pipeline.geo.igrf import main_field_gradient_nT_per_m

        f = self.flight
        if not f.has("lat_deg", "lon_deg", "alt_m"):
            return None
        d = f.data
        sel = self.mask & np.isfinite(d["lat_deg"].to_numpy(float))
        if not sel.any():
            return None
        lat, lon, alt = (
            float(np.mean(d[c].to_numpy(float)[sel])) for c in ("lat_deg", "lon_deg", "alt_m")
        )
        when = datetime.fromtimestamp(float(f.time_ns[np.flatnonzero(sel)[0]]) / 1e9, UTC)
        return main_field_gradient_nT_per_m(lat, lon, alt, when)

    def _lag_estimate(self, current: ModelSpec, keep: np.ndarray | None, key: str) -> float:
        """The lag minimising the refitted model's residual (see :meth:`_lag_fit`)."""
        return self._lag_fit(current, keep, key)[0]

    def _lag_fit(
        self, current: ModelSpec, keep: np.ndarray | None, key: str
    ) -> tuple[float, float]:
        """(lag s, residual RMS nT at it): a coarse grid over +-``max_lag_s`` (the eddy
        terms absorb part of a lag, so a linearised estimate with the baseline's
        coefficients is biased low), then a bounded 1-D refinement. (0, inf) when the
        calibration is too short to refit."""
        # the L-curve's lambda even in a fold: with cross-validation's (often tiny) lambda
        # the eddy terms absorb part of the lag and bias it low
        lam = self.fit(current, keep, key, ridge="auto").lambda_
        try:
            cost = lag_cost(
                self.data, current, self.mask, self.s.band, lam, self.s.max_lag_s, keep=keep
            )
        except ValueError:
            return 0.0, np.inf
        step = 0.05
        grid = np.arange(-self.s.max_lag_s, self.s.max_lag_s + step / 2, step)
        costs = [cost(float(t)) for t in grid]
        best = float(grid[int(np.argmin(costs))])
        res = minimize_scalar(
            cost, bounds=(best - step, best + step), method="bounded", options={"xatol": 1e-4}
        )
        return float(res.x), float(res.fun)

    def _lag_response(self, current: ModelSpec) -> tuple[str, float, dict[str, float]]:
        """A pure delay or a first-order sensor filter: the response whose best lag leaves
        the smaller calibration residual (both have one parameter, so no penalty), and that
        lag (s) on all calibration data; beside them, the lag (s) every model form finds
        (each response, with and without eddy currents with a time constant), keyed
        ``<response>`` and ``<response>_eddy_rate``."""
        fits = {r: self._lag_fit(current.with_(lag_response=r), None, "all") for r in LAG_RESPONSES}
        best = min(LAG_RESPONSES, key=lambda r: fits[r][1])  # ties: the first, a delay
        forms = {}
        for r in LAG_RESPONSES:
            for rate in (False, True):
                spec = current.with_(lag_response=r, eddy_rate=rate)
                fit = fits[r] if rate == current.eddy_rate else self._lag_fit(spec, None, "all")
                forms[f"{r}_eddy_rate" if rate else r] = fit[0]
        return best, fits[best][0], forms

    def _lag_beside_eddy_decay(self, current: ModelSpec) -> dict[str, float]:
        """The lag (s) each response finds beside eddy currents decaying with the best time
        constant (:meth:`_eddy_decay_tau`), on all calibration data, keyed by response."""
        decay = current.with_(eddy_rate=False, eddy_tau_s=self._eddy_decay_tau(current))
        return {
            r: self._lag_estimate(decay.with_(lag_response=r), None, "all") for r in LAG_RESPONSES
        }

    def _eval_sensor_lag(self, current: ModelSpec, key: str) -> Evaluation:
        # the response form is the flight's, chosen once on all calibration data
        response, lag, forms = self._lag_response(current)
        current = current.with_(lag_response=response)
        des = design(self.data, current)
        dy = np.gradient(des.y, self.data.time_s)
        test = self._nested(current, extra=dy[:, None])
        lags = {}

        def ext_for(train, k):
            lags[k] = self._lag_estimate(current, train, f"fold{k}")
            return current.with_(lag_s=lags[k])

        held = self.heldout(current, ext_for)
        # the competing cause of a lag-like residual: eddy currents with a time constant
        # (the carrier's, not the sensor's); a late sensor delays its whole reading, which
        # the extra eddy columns cannot mimic (checked in _beyond)
        est = {
            "lag_s": lag,
            "response": current.lag_response,
            "lag_by_fold_s": [lags[k] for k in sorted(lags)],
        }
        sl = self.survey_lag(current)
        if sl is not None:  # independent evidence: the survey's crossovers
            est.update(
                survey_lag_s=sl.lag_s,
                survey_lag_ci95_s=list(sl.ci95_s),
                survey_lag_p_value=sl.p_value,
            )
        ci = jackknife_ci95({"lag_s": lag}, [{"lag_s": lags[k]} for k in sorted(lags)])
        # the folds' spread is the statistical error only. The calibration cannot tell the
        # model forms apart (a delay or a sensor filter; eddy currents that decay or not) and
        # each reads a lag-like residual as a different lag, so the interval spans the lags
        # of every form (their spread far exceeds the folds')
        est["lag_by_model_form_s"] = forms
        # and beside eddy currents that decay with their best time constant, which take part
        # of a lag-like residual: the truth can lie between that lag and the forms' above
        beside_decay = self._lag_beside_eddy_decay(current)
        est["lag_beside_eddy_decay_s"] = beside_decay
        if ci.get("lag_s") is not None:
            every = [*forms.values(), *beside_decay.values()]
            ci["lag_s"] = [min(ci["lag_s"][0], *every), max(ci["lag_s"][1], *every)]
        ev = Evaluation(
            "sensor_lag",
            key,
            est,
            test,
            held,
            current.with_(lag_s=lag),
            ci95={**ci, **{k: None for k in est if k not in ci}},
        )
        if current.eddy_tau_s > 0:  # the null model holds eddy currents that decay
            return self._lag_beside_decay_nuisance(ev, current, lags, sl)
        self._beyond(
            ev,
            current.with_(eddy_rate=True),
            current.with_(eddy_rate=True, lag_s=lag),
            "eddy currents with a time constant",
            "a late sensor",
        )
        # only a lag every model form agrees on, each at least what the sampling resolves
        # (decaying eddy currents read as a small delay alone, as none beside the rate
        # columns); or a lag that eddy currents decaying with their best time constant, the
        # rate columns' whole form, leave in one response at least: the rate columns' nine
        # free coefficients also take up a true lag
        smallest = self.s.min_lag_s
        beside_most = max(beside_decay.values())
        decay_as_well = False
        if (
            ev.held_back
            and not current.eddy_rate
            and abs(lag) >= smallest
            and (min(forms.values()) > smallest or beside_most >= smallest)
        ):
            decay_as_well = self._lag_over_eddy_decay(ev, current, held, lags, lag)
        elif not ev.held_back and not current.eddy_rate and not current.eddy_tau_s:
            decay_as_well = self._decay_explains_lag(ev, current, held)
        # a decay no slower than the lag is the sensor's own first-order response, no rival
        # cause: there is no tie for the timing along the lines to break
        if decay_as_well and not self._slower_than_lag(ev.estimate["eddy_decay"]["tau_s"], lag):
            decay_as_well = False
        beside_decay_least = min(beside_decay.values())
        beside_a_decay = False
        if (
            ev.held_back
            and not current.eddy_rate
            and not current.eddy_tau_s
            and abs(lag) >= smallest
            and beside_decay_least >= smallest
        ):
            beside_a_decay = self._lag_beyond_eddy_decay(ev, current)
        tl = self._fluxgate_timing(current, ev)
        if tl is not None:  # independent evidence: the fluxgate along the lines
            # independent timing that disagrees with every calibration form: the truth may lie
            # with either, so the interval spans both
            lo, hi = ev.ci95["lag_s"] or (lag, lag)
            if not lo <= tl.lag_s <= hi:
                ev.ci95["lag_s"] = [min(lo, tl.ci95_s[0]), max(hi, tl.ci95_s[1])]
        # the calibration cannot tell the two apart, the survey can: eddy currents do not
        # move anomalies along track, a late sensor does (against the crossovers, and
        # against the fluxgate's record of the same anomalies)
        for name, other in (("survey crossovers", sl), ("the fluxgate along the lines", tl)):
            if (
                ev.held_back
                and other is not None
                and other.p_value < self.s.alpha
                and other.ci95_s[0] <= lag <= other.ci95_s[1]
            ):
                ev.held_back = False
                ev.reason = ""
                est["confirmed_by"] = name
        # the calibration cannot tell a late sensor from eddy currents that decay: the
        # timing along the lines breaks the tie when it says the scalar is not late at all:
        # below zero, not merely below the calibration's lag (whose forms can read a true
        # lag high), and only when neither timing's interval holds the lag (one timing can be
        # far off on a small survey)
        timing = combined_interval([o for o in (sl, tl) if o is not None])
        holds_lag = any(o.ci95_s[0] <= lag <= o.ci95_s[1] for o in (sl, tl) if o is not None)
        if (
            (decay_as_well or beside_a_decay)
            and timing is not None
            and timing[2] < 0.0
            and not holds_lag
        ):
            ev.held_back = True
            ev.reason = (
                f"eddy currents that decay with a time constant explain the calibration's "
                f"residual as well as a lag, and the timing along the lines puts the lag at "
                f"{timing[0]:.3f} s [{timing[1]:.3f}, {timing[2]:.3f}]: the scalar sensor is "
                "not late"
            )
        # nor is it late when the decay leaves the lag, refitted beside it, nothing the
        # sampling resolves, unless the timing along the lines says it is late (a true lag
        # keeps a resolvable part of itself beside a slower decay)
        if (
            decay_as_well
            and not ev.held_back
            and beside_most < smallest
            and not (timing is not None and timing[1] > 0.0)
        ):
            ev.held_back = True
            ev.reason = (
                f"eddy currents that decay over {ev.estimate['eddy_decay']['tau_s']:g} s "
                f"explain the calibration's residual as well as a lag, and beside them the lag "
                f"is {1e3 * beside_most:.1f} ms, under {1e3 * smallest:.0f} ms: the decay "
                "is the cause"
            )
        if abs(lag) < smallest:
            ev.held_back = True
            ev.reason = (
                f"a lag of {1e3 * lag:.1f} ms is under {1e3 * smallest:.0f} ms (min_lag_s): "
                "within the resampling's own error, not a lag to model"
            )
        return ev

    def _fluxgate_timing(self, current: ModelSpec, ev: Evaluation):
        """The lag the fluxgate's record along the lines gives (:func:`timing_lag`), recorded
        in ``ev.estimate``; None without it."""
        tl = timing_lag(
            self.data.time_s,
            self.compensated(current),
            self.data.vector_nT,
            self.seg.mask("survey", "tie", "validation"),
            self.data.rate_hz,
            self.s.max_lag_s,
        )
        if tl is not None:
            ev.estimate.update(
                fluxgate_lag_s=tl.lag_s,
                fluxgate_lag_ci95_s=list(tl.ci95_s),
                fluxgate_lag_p_value=tl.p_value,
            )
            ev.ci95.update(fluxgate_lag_s=None, fluxgate_lag_ci95_s=None, fluxgate_lag_p_value=None)
        return tl

    def _timing_says(self, lag: float, sl, tl) -> str:
        """What the timing along the lines (survey crossovers ``sl``, the fluxgate ``tl``)
        says of a lag of ``lag`` s: ``"holds"`` (one is significant and its interval holds
        the lag), ``"excludes"`` (their combined interval lies below it) or ``"silent"``."""
        found = [o for o in (sl, tl) if o is not None]
        if any(o.p_value < self.s.alpha and o.ci95_s[0] <= lag <= o.ci95_s[1] for o in found):
            return "holds"
        both = combined_interval(found)
        return "excludes" if both is not None and both[2] < lag else "silent"

    def _lag_beside_decay_nuisance(
        self, ev: Evaluation, current: ModelSpec, fold_lags: dict[int, float], sl
    ) -> Evaluation:
        """The lag against the null model's eddy decay (:class:`LagVersusDecay`): named when
        it lowers held-out data beside the decay, or when the two tie and the timing along the
        lines holds it; a tie the timing cannot break is an ambiguity (``self.ambiguities``)
        and nothing is named."""
        s = self.s
        lag = float(ev.estimate["lag_s"])
        smallest = s.min_lag_s
        ev.test = self._lag_profile_test(current, lag)
        tl = self._fluxgate_timing(current, ev)
        plain = current.with_(eddy_tau_s=0.0)
        lag_plain = self._lag_estimate(plain, None, "all")
        decay_alone = self.heldout(plain, lambda train, k: current)
        decay_beyond = self.heldout(
            plain.with_(lag_s=lag_plain), lambda train, k: current.with_(lag_s=fold_lags[k])
        )
        lag_alone = None
        if not (ev.heldout.p_value < s.alpha and ev.heldout.reduction >= s.min_gain):
            lag_alone = self.heldout(
                plain,
                lambda train, k: plain.with_(lag_s=self._lag_estimate(plain, train, f"plain{k}")),
            )
        vs = LagVersusDecay(ev.heldout, lag_alone, decay_alone, decay_beyond)
        if vs.tie(s.alpha, s.min_gain):
            # the rivals as the null model would take each: the whole reading delayed, or
            # the decayed eddy terms beside T-L's (held-out data weigh their sizes)
            def lag_model(train, k):
                return plain.with_(lag_s=self._lag_estimate(plain, train, f"plain{k}"))

            vs.lag_over_decay = self.heldout(current, lag_model)
            vs.decay_over_lag = self.heldout(lag_model, lambda train, k: current)
        verdict = vs.verdict(s.alpha, s.min_gain, self._timing_says(lag_plain, sl, tl))
        tau = current.eddy_tau_s
        ev.estimate["eddy_decay"] = {"tau_s": tau, "alone": decay_alone.to_dict()}
        ev.estimate["against_eddy_decay"] = {"verdict": verdict, **vs.to_dict()}
        ev.ci95.update(eddy_decay=None, against_eddy_decay=None)
        self.ambiguities = [a for a in self.ambiguities if "sensor_lag" not in a["candidates"]]
        if abs(lag_plain) < smallest and abs(lag) < smallest:
            verdict = "none"
        if verdict == "lag" and vs.lag_dominates(s.alpha, s.min_gain):
            self._lag_in_place_of_decay(ev, plain, lag_plain)
        elif verdict == "lag" and lag_alone is not None:  # the tie, broken
            by_physics = significant(vs.lag_over_decay, s.alpha, s.min_gain)
            ev.estimate.update(
                lag_s=lag_plain,
                confirmed_by="the lag model over the decay model"
                if by_physics
                else "the timing along the lines",
            )
            ev.heldout, ev.spec, ev.decided_outside = lag_alone, plain.with_(lag_s=lag_plain), True
            lo, hi = ev.ci95.get("lag_s") or (lag, lag)
            ev.ci95["lag_s"] = [min(lo, lag_plain), max(hi, lag_plain)]
        elif verdict == "lag" and self._timing_says(lag, sl, tl) == "holds":
            # the lines' timing (what a late sensor delays and a decay does not) confirms it
            ev.estimate["confirmed_by"] = "the timing along the lines"
            ev.decided_outside = True
        elif verdict == "ambiguous":
            ev.held_back = True
            ev.reason = (
                f"eddy currents decaying over {tau:.3g} s and a lag of {lag_plain:.3f} s each "
                "explain the calibration's residual and neither adds to the other; the timing "
                "along the lines does not decide: an ambiguity, nothing named"
            )
            self.ambiguities.append(vs.ambiguity())
        elif verdict == "none":
            ev.held_back = True
            ev.reason = (
                f"beside eddy currents decaying over {tau:.3g} s the lag lowers held-out data "
                f"by {100 * ev.heldout.reduction:.1f} % (p {ev.heldout.p_value:.2g}): not a "
                "late sensor"
            )
        return ev

    def _lag_in_place_of_decay(self, ev: Evaluation, plain: ModelSpec, lag_s: float) -> None:
        """The lag takes the null model's eddy decay's place: it lowers held-out data beside
        the decay and the decay adds nothing beside it, so the null model the data support
        with a late sensor holds no decay; the lag is tested (nested F, held out) and
        estimated against that null model."""
        ev.test = self._lag_profile_test(plain, lag_s)
        ev.heldout = self.heldout(
            plain, lambda train, k: plain.with_(lag_s=self._lag_estimate(plain, train, f"fold{k}"))
        )
        ev.spec = plain.with_(lag_s=lag_s)
        ev.estimate.update(lag_s=lag_s, replaces="eddy_decay")
        # the interval was read beside the decay; it must hold the estimate without it too
        lo, hi = ev.ci95.get("lag_s") or (lag_s, lag_s)
        ev.ci95["lag_s"] = [min(lo, lag_s), max(hi, lag_s)]

    def _eddy_decay_tau(self, current: ModelSpec) -> float:
        """The time constant (s) of decaying eddy currents (:func:`eddy_decay` columns beside
        the T-L ones) that leaves the smallest calibration residual, on
        :data:`EDDY_TAU_GRID_S` (the null model's, chosen on held-out data, when it has one)."""
        if current.eddy_tau_s > 0:
            return current.eddy_tau_s
        fits = {
            tau: self.fit(current.with_(eddy_tau_s=tau), None, "all", ridge="auto")
            for tau in EDDY_TAU_GRID_S
        }
        return min(fits, key=lambda tau: fits[tau].fit_residual_nT)

    @staticmethod
    def _same_response(tau_s: float, lag_s: float) -> bool:
        """Whether eddy currents decaying with ``tau_s`` and a lag of ``lag_s`` are one
        first-order response: a sensor filter of tau and eddy currents decaying with tau
        differ in the calibration only beyond second order in w tau (the T-L eddy columns
        take the first order of either), while eddy currents that do decay read as a lag far
        shorter than their time constant."""
        return abs(np.log(tau_s / max(abs(lag_s), 1e-9))) <= np.log(SAME_RESPONSE_RATIO)

    @staticmethod
    def _slower_than_lag(tau_s: float, lag_s: float) -> bool:
        """Whether a decay time constant ``tau_s`` from :data:`EDDY_TAU_GRID_S` is slower
        than a lag of ``lag_s`` by more than the grid resolves: beyond the grid's first value
        at or above the lag (a decay on the grid step next to the lag can be the sensor's own
        first-order response)."""
        above = [g for g in EDDY_TAU_GRID_S if g >= abs(lag_s)]
        return bool(above) and tau_s > above[0]

    def _decay_explains_lag(self, ev: Evaluation, current: ModelSpec, held: HeldOut) -> bool:
        """Whether eddy currents decaying with a fitted time constant predict held-out
        calibration data at least as well as the lag, and the lag, refitted beside them in
        each fold, adds nothing (recorded in ``ev.estimate["eddy_decay"]``).

        The eddy-rate columns are only the decay's first order in w tau: a slow decay can
        pass that test as a short lag. The calibration alone cannot settle it either way
        (a true lag and a decay leave about the same held-out residual), so this only
        marks the tie for the timing along the lines to break. The lag is refitted beside
        the decay because the decay's columns absorb part of it.
        """
        alone, adds = self._weigh_lag_beyond_eddy_decay(ev, current)
        return alone.rms_after_nT <= held.rms_after_nT and not adds

    def _weigh_lag_beyond_eddy_decay(
        self, ev: Evaluation, current: ModelSpec
    ) -> tuple[HeldOut, bool]:
        """:meth:`_weigh_eddy_decay` of the lag, refitted in each training fold beside the
        decay, against the decay alone (under ``"lag_beyond_decay"``)."""
        return self._weigh_eddy_decay(
            ev,
            current,
            lambda decay: decay,
            lambda decay, train, k: decay.with_(
                lag_s=self._lag_estimate(decay, train, f"decay{k}")
            ),
            "lag_beyond_decay",
        )

    def _weigh_eddy_decay(
        self, ev: Evaluation, current: ModelSpec, before, after_for_fold, key: str
    ) -> tuple[HeldOut, bool]:
        """Eddy currents decaying with the best-fitting time constant against a lag: their
        held-out gain alone, and whether ``after_for_fold(decay, train, k)`` adds to
        ``before(decay)`` (p < alpha, by ``min_gain``); both go into
        ``ev.estimate["eddy_decay"]`` (the second under ``key``)."""
        tau = self._eddy_decay_tau(current)
        decay = current.with_(eddy_tau_s=tau)
        alone = self.heldout(current, lambda train, k: decay)
        beyond = self.heldout(before(decay), lambda train, k: after_for_fold(decay, train, k))
        ev.estimate.setdefault("eddy_decay", {}).update(
            {"tau_s": tau, "alone": alone.to_dict(), key: beyond.to_dict()}
        )
        ev.ci95["eddy_decay"] = None
        return alone, beyond.p_value < self.s.alpha and beyond.reduction >= self.s.min_gain

    def _lag_beyond_eddy_decay(self, ev: Evaluation, current: ModelSpec) -> bool:
        """Release a lag held back by the eddy-rate alternative when it adds to eddy currents
        decaying with the best time constant (the lag refitted in each training fold; p <
        alpha and at least ``min_gain`` on held-out data): a late sensor beside a carrier
        whose eddy currents decay. Called only when the lag refitted beside that decay stays
        at least ``min_lag_s`` in every response (the decay does not take it).

        The eddy-rate columns are nine free coefficients, the decay's first order in w tau,
        and take up a true lag as well as the decay; the decay's columns with a fitted time
        constant are the alternative whole, and what the lag adds to them is the sensor's.
        """
        adds = self._weigh_lag_beyond_eddy_decay(ev, current)[1]
        if adds:
            ev.held_back = False
            ev.reason = ""
            ev.estimate["beside"] = "eddy currents that decay with a time constant"
            ev.ci95["beside"] = None
        return adds

    def _lag_over_eddy_decay(
        self,
        ev: Evaluation,
        current: ModelSpec,
        held: HeldOut,
        fold_lags: dict[int, float],
        lag: float,
    ) -> bool:
        """Release a lag held back by the eddy-rate alternative when it predicts held-out data
        better than eddy currents that decay with a time constant, or they better it by less
        than ``min_gain`` or with the lag's own time constant (:meth:`_same_response`; a tie
        goes to the one-parameter lag), and they add nothing beyond the lag. Returns whether
        the release was such a tie (for the timing along the lines to break, as in
        :meth:`_decay_explains_lag`).

        The eddy-rate columns are the decay's first order in w tau; on a multicopter's brisk
        manoeuvres they mimic a true lag about as well as the lag itself, so that test cannot
        decide. Decaying eddy columns with a fitted time constant can: they add nothing
        beyond a true lag, and predict slowly decaying eddy currents better than a lag does.
        A sensor filter and a decay with about its time constant are one response.
        """
        alone, adds = self._weigh_eddy_decay(
            ev,
            current,
            lambda decay: current.with_(lag_s=lag),
            lambda decay, train, k: decay.with_(lag_s=fold_lags[k]),
            "beyond_lag",
        )
        # the decay not better than the lag by min_gain, or with the lag's own time constant
        # (one response, :meth:`_same_response`): the lag wins, a tie if not outright
        better = alone.rms_after_nT < (1 - self.s.min_gain) * held.rms_after_nT
        same = self._same_response(ev.estimate["eddy_decay"]["tau_s"], lag)
        if (not better or same) and not adds:
            ev.held_back = False
            ev.reason = ""
            ev.estimate["preferred_over"] = "eddy currents that decay with a time constant"
            ev.ci95["preferred_over"] = None
            return alone.rms_after_nT <= held.rms_after_nT
        return False

    def _eval_electrical_current(self, current: ModelSpec, key: str) -> Evaluation:
        name = key.split(":", 1)[1]
        ext = current.with_(aux=current.aux + (name,))
        test = self._nested(current, ext_spec=ext)
        held = self.heldout(current, lambda train, k: ext)
        u = direction_cosines(self.data.vector_nT)
        inside = np.all(np.isfinite(u), axis=1)

        def coupling(fm: FittedModel) -> dict[str, Any]:
            c = fm.coefficient(f"aux_{name}_u")
            mag = float(np.linalg.norm(c))
            # what the scalar sensor sees: the coupling projected on the field direction
            return {
                "channel": f"/aux/{name}",
                "nT_per_unit": mag,
                "total_field_nT_per_unit": float(np.mean(u[inside] @ c)),
                "unit": self.data.aux_units.get(name, ""),
                "direction_body": [float(v) for v in c / mag] if mag > 0 else None,
            }

        est = coupling(self.fit(ext, None, "all"))
        folds = [coupling(self.fit(ext, tr, f"fold{k}")) for k, (tr, _) in enumerate(self.folds)]
        ci = jackknife_ci95(est, folds)
        sc = self.survey_coupling(current, name)
        if sc is not None:  # independent evidence: the survey's crossovers
            est.update(
                survey_total_field_nT_per_unit=sc.nT_per_unit,
                survey_ci95=list(sc.ci95),
                survey_p_value=sc.p_value,
            )
            ci.update(
                {
                    k: None
                    for k in ("survey_total_field_nT_per_unit", "survey_ci95", "survey_p_value")
                }
            )
        ev = Evaluation("electrical_current", key, est, test, held, ext, ci95=ci)
        sg = self.survey_coupling_gain(current, name)
        if sc is not None and sg is not None:
            ev.estimate["survey_heldout"] = sg.to_dict()
            ev.ci95["survey_heldout"] = None
            # the crossovers are survey data, independent of the calibration's: a coupling
            # they show (p < alpha) and that predicts them leave-one-out by min_gain confirms
            # the calibration's held-out test; its leave-one-out p joins the held-out p
            # (Fisher), the two together must reach alpha
            if sc.p_value < self.s.alpha and sg.reduction >= self.s.min_gain:
                ev.confirm_p, ev.confirmed_gain = sg.p_value, True
        steps = self.switch_steps(current, name)
        sw = None if steps is None else switch_coupling(steps)
        body = None if steps is None else switch_body_coupling(steps)
        if body is not None:
            # the calibration's three columns can take up other interference that follows
            # the manoeuvres, and the switches may be read at few headings: the interval of |c|
            # spans both estimates'
            ev.estimate.update(
                switch_nT_per_unit=body.nT_per_unit,
                switch_vector_body_nT_per_unit=[float(v) for v in body.vector_nT_per_unit],
            )
            ev.ci95["switch_nT_per_unit"] = list(body.ci95)
            ev.ci95["switch_vector_body_nT_per_unit"] = None
            cal = ev.ci95.get("nT_per_unit")
            if cal is not None:
                ev.ci95["nT_per_unit"] = [min(cal[0], body.ci95[0]), max(cal[1], body.ci95[1])]
        if sw is not None:
            ev.estimate.update(
                switch_total_field_nT_per_unit=sw.total_field_nT_per_unit,
                switch_p_value=sw.p_value,
                switches=sw.switches,
                switch_heldout=sw.heldout.to_dict(),
            )
            ev.ci95.update(
                {
                    k: None
                    for k in (
                        "switch_total_field_nT_per_unit",
                        "switch_p_value",
                        "switches",
                        "switch_heldout",
                    )
                }
            )
            # the field's steps where the channel switches, over the whole flight: evidence
            # the calibration's band-pass hardly sees (a rarely switched load); it confirms
            # when the steps predict each other (leave-one-out) significantly, since many
            # switches make a negligible coupling significant too
            if (
                sw.p_value < self.s.alpha
                and sw.heldout.p_value < self.s.alpha
                and sw.heldout.reduction >= self.s.min_gain
            ):
                p = sw.heldout.p_value
                # the better of two confirmations, Bonferroni-corrected for the choice
                ev.confirm_p = p if ev.confirm_p is None else min(1.0, 2 * min(ev.confirm_p, p))
                ev.confirmed_gain = True
                # the steps' own test, Bonferroni over the channels tested, decides alone:
                # the band-passed calibration is blind to a load it sees switch a few times
                n_channels = sum(e == "electrical_current" for e, _ in self.candidates(current))
                if sw.p_value * max(1, n_channels) < self.s.alpha:
                    self._decide_by_switches(ev, current, name, sw)
        # a current that follows the manoeuvres (a motor's) can stand in for interference
        # that is not linear in the field or in the rates: the coupling is named only when it
        # explains held-out data better than the second-order terms do
        self._beyond(
            ev,
            current.with_(second_order=True),
            ext.with_(second_order=True),
            "second-order induced and eddy terms",
            "a current coupling",
        )
        return ev

    def _decide_by_switches(
        self, ev: Evaluation, current: ModelSpec, name: str, sw: SwitchCoupling
    ) -> None:
        """Let channel ``name``'s switches decide ``ev`` (``Evaluation.decided_outside``):
        the calibration's held-out test then only checks that the extension does not make
        the calibration worse. The extension is the form that lowers the calibration's
        held-out residual more: the calibration's three body columns (``ev.spec``), or the
        switches' total-field coupling taken out as known (``ModelSpec.known_aux``), which
        has nothing to fit. Three free columns of a channel that the band-passed
        calibration hardly sees fit other residual (ramps along the calibration legs, which
        a gradient then takes); where the calibration does see the current, its columns
        also hold the coupling's components across the field, which the known one lacks.
        The calibration's fit of the coupling stays the reported estimate."""
        known = current.with_(known_aux=current.known_aux + ((name, sw.total_field_nT_per_unit),))
        held_known = self.heldout(current, lambda train, k: known)
        ev.decided_outside = True
        form = "calibration_columns"
        if ev.heldout is None or held_known.reduction > ev.heldout.reduction:
            ev.spec, ev.heldout = known, held_known
            form = "switch_total_field_nT_per_unit"
        ev.estimate["compensated_with"] = form
        ev.ci95["compensated_with"] = None

    def _beyond(
        self, ev: Evaluation, alt: ModelSpec, both: ModelSpec, alt_name: str, what: str
    ) -> None:
        """Hold ``ev`` back unless its extension still lowers held-out data (p < alpha, by
        ``min_gain``) in a model that already has the competing explanation ``alt``."""
        beyond = self.heldout(alt, lambda train, k: both)
        ev.estimate["beyond_alternative"] = {"alternative": alt_name, **beyond.to_dict()}
        ev.ci95["beyond_alternative"] = None
        # the survey's own confirmation already tells the two apart (its lines are flown
        # steadily, where the alternative is a level per heading): the calibration then only
        # has to agree in direction
        if ev.decided_outside:  # a switch's step is no function of the attitude
            return
        holds = (
            beyond.reduction > 0
            if ev.confirmed_gain
            else beyond.p_value < self.s.alpha and beyond.reduction >= self.s.min_gain
        )
        if not holds:
            ev.reason = (
                f"{alt_name} explain the residual about as well: with them in the "
                f"model it lowers held-out data by {100 * beyond.reduction:.1f} % "
                f"(p {beyond.p_value:.2g}); not {what}"
            )
            ev.held_back = True

    def _eval_vector_calibration(self, current: ModelSpec, key: str) -> Evaluation:
        """The fluxgate's errors, judged on the fluxgate itself.

        Its magnitude |m| should equal the scalar field (compensated, smoothed over 2 s): the
        in-sample test asks whether the mismatch depends on attitude (offsets through u,
        scale and non-orthogonality through u u); the held-out test fits the calibration on
        each fold's training blocks and compares the held-out mismatch before (less the
        training mean: a constant is no sensor error) and after. The scalar compensation's
        own held-out gain is reported beside it (``compensation_*``): T-L absorbs most of a
        fluxgate's errors, so that gain is small even for large errors and would hide them.
        """
        comp = self.compensated(current)
        ref = time_window_mean(self.data.time_s, comp, 2.0)  # the Earth field, noise smoothed
        m = self.data.vector_nT
        sel = self.mask & np.isfinite(ref) & np.all(np.isfinite(m), axis=1)
        mismatch = np.linalg.norm(m, axis=1) - ref
        u = direction_cosines(m)
        quad = np.column_stack(
            [u[:, i] * u[:, j] for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2))]
        )
        ones = np.ones((m.shape[0], 1))
        # attitude dependence of |m| - B: offsets (u) and scale/non-orthogonality (u u)
        test = nested_test(
            mismatch[sel], ones[sel], np.column_stack([ones, u, quad])[sel], max(self.step, 5)
        )

        fold_vc = {}

        def ext_for(train, k):
            # the reference level from the all-calibration fit (a fold's cross-validated
            # lambda leaves the compensated field's level free, see Auditor.fit)
            ok = train & sel
            fold_vc[k] = fit_vector_calibration(m[ok], ref[ok])
            return current.with_(vector_cal=fold_vc[k])

        compensation = self.heldout(current, ext_for)
        before, after, when = [], [], []
        for k, (train, test_epochs) in enumerate(self.folds):
            t = test_epochs & sel
            before.append(mismatch[t] - np.mean(mismatch[train & sel]))
            after.append(np.linalg.norm(fold_vc[k].apply(m[t]), axis=1) - ref[t])
            when.append(self.data.time_s[t])
        held = heldout_gain(
            np.concatenate(before), np.concatenate(after), np.concatenate(when), self.s.block_s
        )
        vc = fit_vector_calibration(m[sel], ref[sel])
        est = {
            **vc.sensor_errors(),
            "mismatch_rms_before_nT": vc.residual_before_nT,
            "mismatch_rms_after_nT": vc.residual_after_nT,
            "compensation_rms_before_nT": compensation.rms_before_nT,
            "compensation_rms_after_nT": compensation.rms_after_nT,
        }
        ci = jackknife_ci95(
            vc.sensor_errors(), [fold_vc[k].sensor_errors() for k in sorted(fold_vc)]
        )
        ev = Evaluation(
            "vector_calibration",
            key,
            est,
            test,
            held,
            current.with_(vector_cal=vc),
            metric="heldout_fluxgate_mismatch_rms",
            ci95={**ci, **{k: None for k in est if k not in ci}},
        )
        tolerance_nT = self.s.fluxgate_tolerance * float(np.nanmedian(ref[sel]))
        if held.rms_before_nT < tolerance_nT:
            ev.reason = (
                f"the fluxgate agrees with the scalar field to {held.rms_before_nT:.1f} nT "
                f"held out (tolerance {tolerance_nT:.0f} nT): its errors and the carrier's "
                "field at it are too small to name"
            )
            ev.held_back = True
        return ev

    def _crossover_data(self, spec: ModelSpec, smooth_s: float = 0.0):
        """Crossover and validation-overlap differences of ``spec``'s compensated field,
        reduced by IGRF only (and smoothed along track over ``smooth_s``), with the
        base-station difference at each; also the crossovers themselves and each line's
        heading class (0..3, in steps of 90 deg from the survey's line direction). Kept per
        model and smoothing: the survey tests of one round ask for the same model's several
        times."""
        ck = (spec, smooth_s)
        if ck not in self._crossover_cache:  # the same model's crossovers serve several tests
            self._crossover_cache[ck] = self._crossover_data_of(spec, smooth_s)
        return self._crossover_cache[ck]

    def _survey_geometry(self) -> tuple[np.ndarray, np.ndarray, list]:
        """What the crossovers of every model share, computed once: the IGRF total field
        (nT) and the smoothed base station (nT) at each epoch, and the flight's tracks."""
        if self._geometry is None:
            from pipeline.geo.local import LocalFrame
            from pipeline.maps.reduce import igrf_total_nT
            from pipeline.quality.stage import flight_tracks

            d = self.flight.data
            lat, lon, alt = (d[c].to_numpy(float) for c in ("lat_deg", "lon_deg", "alt_m"))
            igrf = igrf_total_nT(self.flight.time_ns, lat, lon, alt)
            base = self.base_smoothed_nT
            sel = self.seg.mask("survey")
            frame = LocalFrame(float(np.nanmean(lat[sel])), float(np.nanmean(lon[sel])))
            e, n, _ = frame.to_enu(lat, lon)
            igrf.flags.writeable = False  # shared: never changed
            self._geometry = igrf, base, flight_tracks(self.seg, e, n)
        return self._geometry

    def _crossover_data_of(self, spec: ModelSpec, smooth_s: float):
        """:meth:`_crossover_data`, computed."""
        from pipeline.maps.level import Line, crossovers
        from pipeline.quality.overlap import track_intersections

        igrf, base, tracks = self._survey_geometry()
        red = self.compensated(spec) - igrf
        if smooth_s > 0:
            red = time_window_mean(self.data.time_s, red, smooth_s)
        t = self.data.time_s

        survey = [Line.from_track(tr, t, red) for tr in tracks if tr.kind == "survey"]
        ties = [Line.from_track(tr, t, red) for tr in tracks if tr.kind == "tie"]
        xs = crossovers(survey, ties)
        # heading classes relative to the survey's own line direction, not to north
        ref = pattern_direction_deg(
            np.array([tr.heading_deg for tr in tracks if tr.kind in ("survey", "tie")])
        )
        heading = {tr.line_id: int(heading_class(tr.heading_deg, ref)) for tr in tracks}
        dx = np.array([c.difference_nT for c in xs])
        db = np.array([np.interp(c.time_a_s, t, base) - np.interp(c.time_b_s, t, base) for c in xs])
        val = [tr for tr in tracks if tr.kind == "validation"]
        ov = track_intersections(val, [tr for tr in tracks if tr.kind in ("survey", "tie")])
        return dx, db, ov, red, base, xs, heading

    def _eval_diurnal(self, current: ModelSpec, key: str) -> Evaluation:
        """The diurnal: does ``current``'s compensated field follow the base station where the
        survey's lines cross and along the calibration legs
        (:func:`pipeline.audit.diurnal.diurnal_evidence`)? With enough validation overlaps
        (8) those are the held-out points instead."""
        sets = [s for s in (self._diurnal_crossovers(current), self._diurnal_legs(current)) if s]
        ev_d = diurnal_evidence(sets)
        if ev_d is None:
            return Evaluation(
                "diurnal",
                key,
                {},
                None,
                None,
                None,
                reason="no survey crossovers or calibration legs with base-station variation",
            )
        held, metric = ev_d.heldout, "heldout_crossover_and_leg_rms"
        if self.flight.has("lat_deg", "lon_deg", "alt_m") and self.seg.mask("validation").any():
            _, _, ov, red, base, _, _ = self._crossover_data(current, smooth_s=1.0)
            if ov.count >= 8:
                held = paired_point_gain(ov.differences(red), ov.differences(red - base))
                metric = "heldout_validation_overlap_rms"
        est = {
            "base_coefficient": ev_d.coefficient,
            # the evidence's size: crossovers and calibration-leg blocks used, and left out
            # as gross errors
            "crossovers": ev_d.used.get("crossovers", 0),
            "leg_blocks": ev_d.used.get("legs", 0),
            "screened_out": sum(ev_d.screened_out.values()),
            **_diurnal_shape(self.data.time_s, self.base_smoothed_nT),
        }
        ev = Evaluation(
            "diurnal",
            key,
            est,
            ev_d.test,
            held,
            current.with_(diurnal=True),
            ci95={"base_coefficient": list(ev_d.ci95)},
        )
        ev.metric = metric
        return ev

    def _diurnal_crossovers(self, spec: ModelSpec) -> DiurnalSet | None:
        """The survey's crossovers as a diurnal data set: ``spec``'s crossover differences
        (smoothed over 1 s along track: a second averages the sensor noise out of each
        reading, the diurnal changes over minutes), a level per heading, the base station's
        difference between the two readings."""
        if not (self.flight.has("lat_deg", "lon_deg", "alt_m") and self.seg.mask("tie").any()):
            return None
        dx, db, _, _, _, xs, heading = self._crossover_data(spec, smooth_s=1.0)
        if dx.size == 0:
            return None
        return DiurnalSet(
            "crossovers",
            dx,
            heading_levels(_crossover_set(dx, xs, heading)),
            db,
            drift_s=np.array([c.time_a_s - c.time_b_s for c in xs]),
        )

    def _diurnal_legs(self, spec: ModelSpec) -> DiurnalSet | None:
        """The calibration legs as a diurnal data set: 10 s block means of ``spec``'s
        compensated field along each leg (the manoeuvres' cycles average out), a level per
        leg and the east/north/up position (the ground's gradient), the base station's block
        mean (:func:`pipeline.audit.legs.leg_block_means`)."""
        if self.data.enu_m is None:
            return None
        a, leg_of = leg_block_means(
            self.data.time_s,
            np.column_stack(
                [self.compensated(spec), self.base_smoothed_nT, self.data.enu_m, self.data.time_s]
            ),
            self.legs,
            self.s.block_s,
        )
        if leg_of.size == 0:
            return None
        levels = (leg_of[:, None] == np.unique(leg_of)[None, :]).astype(float)
        return DiurnalSet(
            "legs",
            a[:, 0],
            np.column_stack([levels, a[:, 2:5]]),
            a[:, 1],
            group=leg_of,
            drift_s=a[:, 5],
        )

    def _survey_crossovers(self, spec: ModelSpec) -> tuple[CrossoverSet, np.ndarray] | None:
        """The survey's crossover differences of ``spec``'s compensated field, smoothed over
        1 s along track (7-15 m at survey speeds, well inside the smoothest anomaly at survey
        height: it averages the sensor noise out of each reading) and less the base
        station's difference (the day's variation, never the carrier's), with the reduced
        field along the flight; None without enough crossovers (8)."""
        if not (
            self.flight.has("lat_deg", "lon_deg", "alt_m", "base_nT")
            and self.seg.mask("tie").any()
            and self.seg.mask("survey").any()
        ):
            return None
        dx, db, _, red, _, xs, heading = self._crossover_data(spec, smooth_s=1.0)
        if dx.size < 8:
            return None
        return _crossover_set(dx - db, xs, heading), red

    def survey_evidence(self, spec: ModelSpec) -> list[dict[str, Any]]:
        """Steps and drifts in ``spec``'s compensated field seen at survey/tie crossovers
        (:mod:`pipeline.audit.survey`), as ``unexplained.events`` entries.

        Crossings not read on the same ground the same way are left out
        (:meth:`_straight_crossings`: in a turn, or on a climbing transit labelled a tie):
        such readings are tens of nT off, enough to make or displace a step. The
        calibration legs' heading levels do not join: a box's geology is not linear over a
        leg, so the legs' levels differ from the survey's by as much as a real step shows.
        """
        got = self._survey_crossovers(spec)
        if got is None:
            return []
        x = got[0]
        _, _, _, _, _, xs, _ = self._crossover_data(spec, smooth_s=1.0)
        keep = self._straight_crossings(xs)
        x = x.subset(keep)
        events = survey_events(x, self.s.alpha, self.s.min_event_nT)
        t0 = int(self.flight.time_ns[0])
        return [e.to_dict(t0) for e in events]

    def _straight_crossings(
        self, xs: list, max_turn_deg: float = 15.0, max_height_m: float = 20.0
    ) -> np.ndarray:
        """Which crossovers ``xs`` read the same ground the same way: both lines flying
        straight (the course over ground within ``COURSE_WINDOW_S`` of the reading within
        ``max_turn_deg`` of the line's mean heading) and at heights within
        ``max_height_m`` of each other. A line's ends can run into its turns, and a track
        labelled a tie can be a climbing transit; the ground's anomalies change by
        0.02-0.1 nT per metre of height, so 20 m keeps the error near the crossovers'
        own scatter."""
        alt = self.flight.data["alt_m"].to_numpy(float)
        t_all = self.data.time_s
        t_a = np.array([c.time_a_s for c in xs], float)
        t_b = np.array([c.time_b_s for c in xs], float)
        height_ok = np.abs(np.interp(t_a, t_all, alt) - np.interp(t_b, t_all, alt)) <= max_height_m
        _, _, tracks = self._survey_geometry()
        by_id = {tr.line_id: tr for tr in tracks}
        half = max(1, int(round(0.5 * COURSE_WINDOW_S * self.data.rate_hz)))

        def straight(line_id: str, time_s: float) -> bool:
            tr = by_id[line_id]
            tt = t_all[tr.index]
            i = int(np.clip(np.searchsorted(tt, time_s), 0, tt.size - 1))
            lo, hi = max(0, i - half), min(tt.size - 1, i + half)
            de, dn = tr.east_m[hi] - tr.east_m[lo], tr.north_m[hi] - tr.north_m[lo]
            if hi == lo or np.hypot(de, dn) == 0:
                return True
            course = np.degrees(np.arctan2(de, dn))
            return abs((course - tr.heading_deg + 180.0) % 360.0 - 180.0) <= max_turn_deg

        return height_ok & np.array(
            [straight(c.line_a, c.time_a_s) and straight(c.line_b, c.time_b_s) for c in xs],
            bool,
        ).reshape(len(xs))

    def calibration_events(self, spec: ModelSpec) -> list[dict[str, Any]]:
        """A step in ``spec``'s compensated field inside a calibration leg
        (:mod:`pipeline.audit.calibration_events`), as ``unexplained.events`` entries."""
        # everything the model explains removed, its geology terms (position) too: a
        # gradient seen through the manoeuvres' height changes is no step
        fm = self.fit(spec, None, "all")
        des = design(self.data, spec)
        comp = des.y - des.columns @ fm.theta
        steps = calibration_steps(
            self.data.time_s, comp, self.legs, self.s.alpha, self.s.min_event_nT
        )
        t0 = int(self.flight.time_ns[0])
        return [e.to_dict(t0) for e in steps]

    def vector_reference_events(self) -> list[dict[str, Any]]:
        """A step in the carrier's permanent field against the fluxgate
        (:mod:`pipeline.audit.vector_reference`), as ``unexplained.events`` entries.

        The scalar-minus-fluxgate difference over the whole flight holds no Earth field, so
        a step shows at its full size ``u . dp`` at every heading flown after it; the
        crossovers see only the heading levels' change, which tie lines flown after the step
        absorb. The recorded auxiliary channels enter its model, so that a switched current
        is no step.
        Independent of the calibration model: the raw readings only.
        """
        d = self.data
        step = vector_reference_step(
            d.time_s, d.scalar_nT, d.vector_nT, d.aux, self.s.alpha, self.s.min_vector_step_nT
        )
        if step is None:
            return []
        return [step.to_dict(int(self.flight.time_ns[0]))]

    def pass_steps(self, spec: ModelSpec) -> list[PassStep]:
        """Gaps between consecutive calibration passes across which ``spec``'s permanent
        field changed, each tested on its own (:class:`PassStep`).

        A permanent-field step at any time between two passes is the same calibration model
        (no calibration sample lies between them): ``spec`` plus the body-frame change of the
        permanent field after the gap's middle (three columns, u dp). It counts when its
        F-test (Bonferroni over the gaps), BIC and held-out test (the stratified folds: every
        fold trains on both passes) all favour it. The held-out test is the one that decides:
        the F-test alone is far too optimistic (the calibration residual is autocorrelated
        and the passes' unmodelled interference differs a little).
        Kept per model. Hand-written: the test is the audit's own nested and held-out pair,
        which no change-point library computes on a regression's coefficients.
        """
        if spec in self._pass_steps:
            return self._pass_steps[spec]
        t = self.data.time_s
        gaps = [
            (float(t[a[-1]]), float(t[b[0]]))
            for a, b in zip(self.passes[:-1], self.passes[1:], strict=True)
        ]
        out = []
        for lo, hi in gaps:
            ext = spec.with_(permanent_step_s=0.5 * (lo + hi))
            try:
                test = self._nested(spec, ext_spec=ext)
                held = self.heldout(spec, lambda train, k, ext=ext: ext)
            except (ValueError, np.linalg.LinAlgError):
                continue
            p = min(1.0, test.p_value * len(gaps))
            if p < self.s.alpha and test.delta_bic < 0 and held.p_value < self.s.alpha:
                out.append(PassStep(lo, hi, p, held))
        self._pass_steps[spec] = out
        return out

    def pass_step_events(self, spec: ModelSpec, located: list[dict[str, Any]]) -> list[dict]:
        """``spec``'s permanent-field change between calibration passes (:meth:`pass_steps`)
        as one ``unexplained.events`` step spanning the gaps where it was found, unless a
        step in ``located`` (the survey's or the legs', absolute ns) already lies inside
        that span: it says where, this only that the passes disagree."""
        found = self.pass_steps(spec)
        if not found:
            return []
        t0 = int(self.flight.time_ns[0])
        lo_ns = t0 + int(round(min(g.start_s for g in found) * 1e9))
        hi_ns = t0 + int(round(max(g.end_s for g in found) * 1e9))
        if any(
            e["kind"] == "step" and e["end_ns"] >= lo_ns and e["start_ns"] <= hi_ns for e in located
        ):
            return []
        best = min(found, key=lambda g: g.heldout.p_value)
        return [
            {
                "kind": "step",
                "start_ns": lo_ns,
                "end_ns": hi_ns,
                "size_nT": self._pass_step_size(spec, best),
                # the larger of the two tests' p over the gaps: the held-out one in practice
                "p_value": max(max(g.p_value, g.heldout.p_value) for g in found),
                "f_test_p_value": max(g.p_value for g in found),
                "evidence": "calibration passes",
            }
        ]

    def _pass_step_size(self, spec: ModelSpec, g: PassStep) -> float:
        """Size (nT) of the permanent field's change at gap ``g``: the body-frame change
        ``|dp|`` fitted on all of the calibration."""
        fm = self.fit(spec.with_(permanent_step_s=g.middle_s), None, "all")
        idx = [list(fm.names).index(f"perm_step_u{a}") for a in "xyz"]
        return float(np.linalg.norm(np.asarray(fm.theta)[idx]))

    def survey_lag(self, spec: ModelSpec) -> SurveyLag | None:
        """The lag seen at the survey's crossovers (:func:`pipeline.audit.survey.survey_lag`)."""
        got = self._survey_crossovers(spec)
        if got is None:
            return None
        cs, red = got
        t = self.data.time_s
        ok = np.isfinite(red)
        rate = np.full(t.size, np.nan)
        rate[ok] = np.gradient(red[ok], t[ok])
        return survey_lag(cs, np.interp(cs.time_a_s, t, rate), np.interp(cs.time_b_s, t, rate))

    def leg_gradient(self, spec: ModelSpec) -> LegGradient | None:
        """The total field's gradient along the calibration legs, from ``spec``'s compensated
        field (the base station's smoothed reading taken out when the recording has one;
        :func:`pipeline.audit.legs.leg_gradient`)."""
        if self.data.enu_m is None:
            return None
        comp = self.compensated(spec)
        if self.flight.has("base_nT"):
            comp = comp - self.base_smoothed_nT
        # the carrier's isotropic soft iron scales the reading and no fit can see it (it is
        # the induced columns' missing sum); its anisotropic part, which the fit does see, is
        # of the same order on real carriers, so the largest fitted induced coefficient
        # stands for the scale's uncertainty
        fm = self.fit(spec, None, "all")
        induced = [abs(v) for n, v in zip(fm.names, fm.theta, strict=True) if n.startswith("ind_")]
        scale = max(induced, default=0.0) / BT_SCALE_NT
        # the channels whose coupling the model fitted or took as measured: a coupling wrong
        # by dc leaves dc . u times the channel, which a switch within a leg makes a ramp
        channels = dict.fromkeys([*spec.aux, *(name for name, _ in spec.known_aux)])
        u = direction_cosines(self.data.vector_nT)
        nuisance = (
            np.column_stack([u * self.data.aux[c][:, None] for c in channels]) if channels else None
        )
        return leg_gradient(
            self.data.time_s,
            comp,
            self.data.enu_m,
            self.legs,
            scale_uncertainty=scale,
            nuisance=nuisance,
        )

    def survey_heading(self, spec: ModelSpec) -> SurveyHeading | None:
        """``spec``'s heading error seen at the survey's crossovers, and whether it changes
        across the survey (:func:`pipeline.audit.survey.survey_heading`)."""
        got = self._survey_crossovers(spec)
        if got is None:
            return None
        cs = got[0]
        return survey_heading(cs, cs.east_m / 1000.0, cs.north_m / 1000.0)

    def _crossover_channel(
        self, spec: ModelSpec, name: str
    ) -> tuple[CrossoverSet, np.ndarray, np.ndarray] | None:
        """``spec``'s survey crossovers with channel ``name`` at their two readings (smoothed
        over 1 s, as the crossovers are)."""
        got = self._survey_crossovers(spec)
        if got is None:
            return None
        cs = got[0]
        t = self.data.time_s
        aux = time_window_mean(t, self.data.aux[name], 1.0)
        return cs, np.interp(cs.time_a_s, t, aux), np.interp(cs.time_b_s, t, aux)

    def survey_coupling(self, spec: ModelSpec, name: str) -> SurveyCoupling | None:
        """Channel ``name``'s coupling seen at the survey's crossovers
        (:func:`pipeline.audit.survey.survey_coupling`)."""
        got = self._crossover_channel(spec, name)
        return None if got is None else survey_coupling(*got)

    def switch_steps(self, spec: ModelSpec, name: str) -> SwitchSteps | None:
        """The steps of ``spec``'s compensated field where channel ``name`` switches, with
        the field's direction at each (:func:`pipeline.audit.switching.switch_steps`)."""
        return switch_steps(
            self.data.time_s,
            self.compensated(spec),
            self.data.aux[name],
            # compensation is weakest in turns, and in the calibration's manoeuvres a load
            # that follows them (a motor's current, the bus voltage) changes with the
            # attitude, so a residual there would pass for a coupling
            usable=~self.seg.mask("turn", "calibration"),
            direction=direction_cosines(self.data.vector_nT),
        )

    def survey_coupling_gain(self, spec: ModelSpec, name: str) -> HeldOut | None:
        """Leave-one-out gain of channel ``name``'s coupling at the survey's crossovers
        (:func:`pipeline.audit.survey.survey_coupling_gain`)."""
        got = self._crossover_channel(spec, name)
        return None if got is None else survey_coupling_gain(*got)

    # -- the whole audit ------------------------------------------------------------------
    def cv_residual(
        self, spec: ModelSpec, fold: np.ndarray | None = None, tag: str = "fold"
    ) -> tuple[float, np.ndarray, np.ndarray]:
        """Held-out band-passed residual RMS (nT) of ``spec`` over the folds (stratified
        blocks by default; ``fold`` e.g. leave-one-pass-out), with its rows in epoch order."""
        folds = self.folds if fold is None else _fold_masks(fold)
        r, tt = [], []
        for k, (train, test) in enumerate(folds):
            m = self.fit(spec, train, f"{tag}{k}")
            rr, w = m.residual_bp(
                self.data, self.mask, self.s.band, keep=test, rows=self.rows(spec)
            )
            r.append(rr)
            tt.append(w)
        rc, wc = np.concatenate(r), np.concatenate(tt)
        order = np.argsort(wc, kind="stable")
        return float(np.sqrt(np.mean(rc**2))), rc[order], wc[order]

    def permanent_step(self, spec: ModelSpec) -> float | None:
        """The time (s) of a step the survey's crossovers show, when calibration data lie on
        both sides of it, else the middle of the gap between calibration passes across
        which the permanent field changed (:meth:`pass_steps`, the most significant held
        out): the passes then saw two different permanent fields, which no catalogue effect
        explains but a current or a drift would imitate, so the baseline allows the
        permanent field to change there."""
        steps = [e for e in self.survey_evidence(spec) if e["kind"] == "step"]
        t_cal = self.data.time_s[self.mask]
        known = self.gradient_from_legs(spec) if steps else None
        if known is not None and not any(e["kind"] == "step" for e in self.survey_evidence(known)):
            # a gradient mis-compensated in the heading terms moves the crossovers' levels
            # as the lines move across it, which reads as a step; the gradient is a candidate
            # of its own
            self.notes.append(
                "the survey's step goes with the gradient the calibration legs measure: "
                "not taken for a change of the carrier's permanent field"
            )
            steps = []
        if steps:
            t0 = int(self.flight.time_ns[0])
            e = steps[0]  # in the middle of its likeliest gap (the event spans several)
            t_s = 0.5 * (e["likeliest_start_ns"] + e["likeliest_end_ns"] - 2 * t0) / 1e9
            if min((t_cal < t_s).sum(), (t_cal > t_s).sum()) >= 60 * self.data.rate_hz:
                self.notes.append(
                    f"the survey shows a step at {t_s:.0f} s between calibration passes: the "
                    "calibration model lets the carrier's permanent field change there"
                )
                return float(t_s)
        found = self.pass_steps(spec)
        if not found:
            return None
        g = min(found, key=lambda g: g.heldout.p_value)
        self.notes.append(
            f"the calibration passes either side of {g.start_s:.0f}-{g.end_s:.0f} s saw "
            f"different permanent fields (held-out p {g.heldout.p_value:.2g}): the calibration "
            "model lets the carrier's permanent field change between them"
        )
        return g.middle_s

    def run(self, progress=None) -> tuple[ModelSpec, list[Evaluation], list[list[Evaluation]]]:
        """Forward-stepwise selection of the effects.

        Starts from the baseline (with a permanent-field step where the survey shows one). Each
        round tests every candidate, Holm-adjusts the F-test p-values of the tested ones and
        accepts the passing candidate with the largest held-out reduction; it stops when none
        passes. The accepted effects are then re-estimated together (:meth:`refine`).

        Parameters
        ----------
        progress : callable, optional
            Called with a message before each candidate's test.

        Returns
        -------
        tuple
            (final model spec, accepted findings in order, every round's evaluations).
        """
        current = self.null_spec()
        current = current.with_(permanent_step_s=self.permanent_step(current))
        findings: list[Evaluation] = []
        rounds: list[list[Evaluation]] = []
        while True:
            cands = self.candidates(current)
            if not cands:
                break
            evals = []
            for effect, key in cands:
                if progress:
                    progress(f"round {len(rounds) + 1}: testing {key}")
                evals.append(self.evaluate(current, effect, key))
            tested = [e for e in evals if e.test is not None]
            for e, p in zip(tested, holm([e.test.p_value for e in tested]), strict=True):
                e.p_adjusted = p
            rounds.append(evals)
            self._calibrated_gate(evals)
            passing = [e for e in evals if e.passes(self.s)]
            for e in evals:
                if not e.passes(self.s) and not e.reason:
                    e.reason = e.why_not(self.s)
            if not passing:
                break
            # the fluxgate's gain is measured on the fluxgate, not on the scalar residual, so
            # it does not compete: a scalar-field effect goes first when one passes
            best = max(passing, key=lambda e: (e.metric == Evaluation.metric, e.heldout.reduction))
            best.accepted = True
            findings.append(best)
            for e in passing:
                if e is not best:
                    e.reason = "passed; re-tested in the next round with the better one in"
            current = self.admit_nuisances(best.spec, best.effect)
        return self.refine(self.prune_nuisances(current), findings), findings, rounds

    def admit_nuisances(self, spec: ModelSpec, finding: str) -> ModelSpec:
        """Add to ``spec`` each nuisance group it lacks that, with the findings so far in the
        model, lowers held-out data as :meth:`prune_nuisances` requires one to stay: the
        field of an effect not yet modelled (a gradient's, along the manoeuvres) can hide a
        nuisance from the selection on the baseline, and the next candidates are judged
        against the null model the data support."""
        trials = []
        if spec.eddy_tau_s == 0:
            tau = self._eddy_decay_tau(spec)
            trials.append(("eddy_decay", spec.with_(eddy_tau_s=tau), {"tau_s": tau}))
        if not spec.second_order:
            trials.append(("second_order", spec.with_(second_order=True), {}))
        for name, trial, est in trials:
            try:
                h = self.heldout(self._fold_lag(spec), self._fold_lag(trial))
            except (ValueError, np.linalg.LinAlgError):
                continue
            if self._nuisance_matters(h):
                spec = trial
                self.nuisances.nuisances.append(Nuisance(name, float(h.reduction), est))
                self.notes.append(
                    f"the nuisance {name} lowers held-out data by {100 * h.reduction:.1f} % "
                    f"(p {h.p_value:.2g}) with the {finding.replace('_', ' ')} in the model: "
                    "taken into the null model"
                )
        return spec

    def _nuisance_matters(self, h: HeldOut) -> bool:
        """Whether a nuisance's held-out comparison ``h`` holds it in the model: p below
        ``alpha``, at least ``min_gain`` of the RMS and ``min_nuisance_nT`` of interference."""
        removed_nT = float(np.sqrt(max(h.rms_before_nT**2 - h.rms_after_nT**2, 0.0)))
        return (
            h.p_value < self.s.alpha
            and h.reduction >= self.s.min_gain
            and removed_nT >= self.s.min_nuisance_nT
        )

    def prune_nuisances(self, spec: ModelSpec) -> ModelSpec:
        """Drop from ``spec`` each nuisance that no longer lowers held-out data with the
        findings in the model (p < ``alpha``, by ``min_gain`` and ``min_nuisance_nT`` of
        interference; each model with its own lag): taken before the catalogue
        effects, a nuisance can have followed part of one (a gradient's field moves with the
        manoeuvres' small displacements). Kept nuisances stay in ``self.nuisances``; the
        dropped ones are noted."""
        off = {"eddy_decay": {"eddy_tau_s": 0.0}, "second_order": {"second_order": False}}
        kept = []
        for n in self.nuisances.nuisances:
            without = spec.with_(**off[n.name])
            if without == spec:
                continue
            try:
                h = self.heldout(self._fold_lag(without), self._fold_lag(spec))
            except (ValueError, np.linalg.LinAlgError):
                kept.append(n)
                continue
            if self._nuisance_matters(h):
                kept.append(n)
                continue
            removed_nT = float(np.sqrt(max(h.rms_before_nT**2 - h.rms_after_nT**2, 0.0)))
            spec = without
            self.notes.append(
                f"the nuisance {n.name} taken before the catalogue effects lowers held-out data "
                f"by {100 * h.reduction:.1f} % (p {h.p_value:.2g}; {removed_nT:.3f} nT of "
                f"interference, {self.s.min_nuisance_nT:g} nT matters) with the findings in the "
                "model: dropped"
            )
        self.nuisances.nuisances = kept
        return spec

    def _fold_lag(self, spec: ModelSpec):
        """A held-out builder of ``spec`` whose lag, when it has one, is estimated on each
        fold's training rows with the spec's own other terms: a lag fitted beside a nuisance
        is not the lag of the model without it (a decay takes part of a delay), so a model
        judged with another model's lag would be judged unfairly."""

        def build(train, k):
            if spec.lag_s == 0:
                return spec
            return spec.with_(lag_s=self._lag_estimate(spec.with_(lag_s=0.0), train, f"fold{k}"))

        return build

    def _calibrated_gate(self, evals: list[Evaluation]) -> None:
        """Hold back a candidate judged on the scalar calibration whose held-out gain beside
        the null model does not reach the gate the null model's bootstrap sets for the whole
        selection (:attr:`null_calibration`); a candidate its own evidence outside the
        calibration decides is not judged there."""
        nc = self.null_calibration
        if nc is None:
            return
        for e in evals:
            if e.decided_outside or e.held_back or not e.passes(self.s) or nc.passes(e.key):
                continue
            e.held_back = True
            e.reason = (
                f"its held-out gain beside the null model, {100 * nc.observed_gain[e.key]:.1f} %,"
                f" is below the {100 * nc.gate_gain:.1f} % the null model's bootstrap sets for "
                f"the whole selection at a flight-level rate of {nc.alpha:g}"
            )

    @staticmethod
    def without(spec: ModelSpec, f: Evaluation) -> ModelSpec:
        """``spec`` with finding ``f``'s extension taken out."""
        if f.effect == "geomagnetic_gradient":
            return spec.with_(gradient=False, known_gradient_nT_per_m=None)
        if f.effect == "sensor_lag":
            return spec.with_(lag_s=0.0, lag_response="delay")
        if f.effect == "diurnal":
            return spec.with_(diurnal=False)
        if f.effect == "vector_calibration":
            return spec.with_(vector_cal=None)
        name = f.key.split(":", 1)[1]
        return spec.with_(
            aux=tuple(a for a in spec.aux if a != name),
            known_aux=tuple(a for a in spec.known_aux if a[0] != name),
        )

    def refine(self, spec: ModelSpec, findings: list[Evaluation]) -> ModelSpec:
        """Re-estimate every accepted effect with all the others in the model.

        An effect accepted early was estimated while later ones were still unmodelled (a
        lag estimated before a current coupling is biased by it); the estimates reported
        are these, with the others present. The acceptance statistics stay those of the
        round that accepted the effect. An effect that, with the others present, a
        competing explanation or its own direct evidence now rejects (``held_back``) is
        dropped from ``findings`` (in place) and from the model (a current's steps inside the
        calibration legs ramp like a gradient until the current is in the model).
        """
        order = sorted(findings, key=lambda f: f.effect != "sensor_lag")  # lag first
        for f in order:
            e = self.evaluate(self.without(spec, f), f.effect, f.key)
            if e.held_back:
                spec = self.without(spec, f)
                findings.remove(f)
                f.accepted = False
                f.reason = f"dropped with the other findings in the model: {e.reason}"
                continue
            if not e.estimate:
                continue
            f.estimate = {**e.estimate, "at_acceptance": f.estimate}
            # estimated values in the spec (a lag, a vector calibration, a measured
            # gradient) take the re-estimate; switched-on columns are refitted anyway
            if e.spec is not None and (
                f.effect in ("sensor_lag", "vector_calibration")
                or e.spec.known_gradient_nT_per_m is not None
            ):
                spec = e.spec
        return spec


def _crossover_set(difference_nT: np.ndarray, xs: list, heading: dict) -> CrossoverSet:
    """The crossovers ``xs`` with their differences ``difference_nT`` (nT), reading times,
    heading classes (``heading``: line id -> 0..3) and where the lines cross (m)."""
    return CrossoverSet(
        difference_nT,
        np.array([c.time_a_s for c in xs]),
        np.array([c.time_b_s for c in xs]),
        np.array([heading[c.line_a] for c in xs]),
        np.array([heading[c.line_b] for c in xs]),
        np.array([c.east_m for c in xs]),
        np.array([c.north_m for c in xs]),
    )


def _electrical(unit: str) -> bool:
    """A channel that can carry a current coupling: a current or a voltage (a load's
    proxy), or one whose unit the recording does not say. A temperature, a pressure ...
    changes the carrier's field too, but that is not an electrical current."""
    u = unit.strip()
    return u == "" or u in {"A", "mA", "uA", "kA", "V", "mV"}


def _diurnal_shape(time_s: np.ndarray, base: np.ndarray) -> dict[str, float | None]:
    """Amplitude and period of the base-station variation (a sinusoid fitted to it)."""
    ok = np.isfinite(base)
    t, b = time_s[ok], base[ok] - np.nanmean(base)
    span = float(t[-1] - t[0]) if t.size else 0.0
    if t.size < 20 or span <= 0:
        return {"amplitude_nT": None, "period_s": None}
    best = None
    for p0 in (span / 2, span, 2 * span):
        try:
            par, _ = curve_fit(
                lambda x, a, p, ph, c: a * np.sin(2 * np.pi * x / p + ph) + c,
                t,
                b,
                p0=[np.std(b) * 1.4, p0, 0.0, 0.0],
                maxfev=20_000,
            )
        except (RuntimeError, ValueError):
            continue
        r = np.mean((b - (par[0] * np.sin(2 * np.pi * t / par[1] + par[2]) + par[3])) ** 2)
        if best is None or r < best[0]:
            best = (r, par)
    if best is None:
        return {"amplitude_nT": float(np.ptp(b) / 2), "period_s": None}
    a, p = abs(float(best[1][0])), abs(float(best[1][1]))
    # a period much longer than the record is not determined: report the range instead
    return {
        "amplitude_nT": a if p < 4 * span else float(np.ptp(b) / 2),
        "period_s": p if p < 4 * span else None,
    }


def _quality_figures(
    flight: Flight, seg: Segmentation, comp: np.ndarray, subtract_base: bool
) -> dict[str, Any] | None:
    from pipeline.quality.stage import QualitySettings, run_quality

    if not (seg.mask("survey").sum() > 100 and flight.has("lat_deg", "alt_m")):
        return None
    q = run_quality(
        flight,
        seg,
        {"raw": flight.data["scalar_nT"].to_numpy(float), "model": comp},
        settings=QualitySettings(subtract_base=subtract_base),
    )
    s = q.summary()
    xo = q.crossover_stats()
    # the audit judges its gain at the exact intersections (only heading error and noise
    # remain there; pairs add gradient x distance), and says so; the pair figure rides along
    return {
        "heading_error_rms_nT": s["intersection_rms_nT"]["model"],
        "heading_error_method": "intersections",
        "overlap_pair_rms_nT": s["overlap_pair_rms_nT"]["model"],
        "crossover_rms_nT": xo["before"]["rms_nT"] if xo["count"] else None,
        "interpolated_rms_nT": s["interpolated_rms_nT"]["model"],
        "intersections": s["intersections"],
        "by_heading": s["heading_error"]["intersections"]["by_state"]["model"]["by_heading"],
    }


def alternatives(finding: Evaluation, rounds: list[list[Evaluation]]) -> list[dict[str, Any]]:
    """What came second to ``finding``: the rival explanation it was weighed against (its
    held-out gain alone), then the other candidates of the round it was accepted in, by
    held-out gain (fraction of the held-out residual removed, on the finding's own metric)."""
    out: list[dict[str, Any]] = []
    decay = finding.estimate.get("eddy_decay") if isinstance(finding.estimate, dict) else None
    if isinstance(decay, dict) and decay.get("alone"):
        out.append({"name": "eddy_decay", "heldout_gain": decay["alone"]["reduction_pct"] / 100.0})
    for r in rounds:
        if any(e is finding for e in r):
            # gains on the same metric only (the fluxgate's is measured on the fluxgate)
            others = [
                e
                for e in r
                if e is not finding and e.heldout is not None and e.metric == finding.metric
            ]
            others.sort(key=lambda e: -e.heldout.reduction)
            out += [{"name": e.key, "heldout_gain": e.heldout.reduction} for e in others]
            break
    return out


def run_audit(
    flight: Flight, seg: Segmentation, settings: AuditSettings | None = None, progress=None
) -> AuditResult:
    """Audit ``flight`` (see the module docstring)."""
    s = settings or AuditSettings()
    if not seg.passes():
        raise AeromagError(
            "the audit needs a calibration pass (no manoeuvres found)",
            file=flight.source,
            channel="/ins/attitude",
        )
    aud = Auditor(flight, seg, s)
    final_spec, findings, rounds = aud.run(progress)
    data = aud.data
    base_spec = ModelSpec(base=s.baseline)
    baseline = aud.fit(base_spec, None, "all")
    extended = aud.fit(final_spec, None, "all")
    if progress:
        progress("measuring the gain")
    cv_b, _, _ = aud.cv_residual(base_spec)
    cv_e, r_e, w_e = aud.cv_residual(final_spec)
    # like with like: the in-sample residual with lambda chosen as in the folds
    fit_cv = aud.fit(base_spec, None, "all", ridge="cv").fit_residual_nT
    gap = cv_b / fit_cv if fit_cv > 0 else float("nan")
    passwise = (
        aud.cv_residual(base_spec, aud.pass_fold, "pass")[0] if aud.pass_fold is not None else None
    )
    comp_e = aud.compensated(final_spec)
    delay = final_spec.lag_s if final_spec.lag_response == "delay" else 0.0
    bounds = noise_floor_bounds(
        data.scalar_nT,
        comp_e,
        extended.compensate(data)[1] if delay else None,  # the design again: delays only
        data.time_s,
        data.rate_hz,
        delay_s=delay,
    )
    sigma = bounds.sensor_nT
    floor_is_bound = bool(bounds.rise > s.max_noise_rise)
    floor = sigma * band_noise_gain(data.rate_hz, s.band.band_hz, s.band.poles)
    if progress:
        progress("survey-side evidence")
    # events are what the catalogue model leaves: without the permanent-field step the
    # survey itself showed (which the extended model then absorbs)
    plain = final_spec.with_(permanent_step_s=None)
    events = aud.survey_evidence(plain) + aud.calibration_events(plain)
    events += aud.vector_reference_events()
    events += aud.pass_step_events(plain, events)
    named = {f.effect for f in findings}
    unexplained: dict[str, Any] = {
        "events": events,
        "nuisances": aud.nuisances.to_list(),
        "ambiguities": [a for a in aud.ambiguities if not named.intersection(a["candidates"])],
        "note": None,
        "spectrum": residual_spectrum(r_e, data.rate_hz, s.band),
    }
    spec_ = unexplained["spectrum"]
    white_excess = cv_e > s.unexplained_factor * floor and spec_["kind"] == "white"
    if cv_e > s.unexplained_factor * floor and not white_excess:
        unexplained.update(
            {
                "rms_nT": cv_e,
                "band_noise_floor_nT": floor,
                "ratio": cv_e / floor,
                "dominant_frequency_hz": spec_["dominant_frequency_hz"],
                "note": (
                    f"held-out calibration residual {cv_e:.4f} nT is {cv_e / floor:.1f}x the "
                    f"noise floor {floor:.4f} nT and no candidate effect explains it; "
                    f"its spectrum: {spec_['description']}"
                ),
            }
        )
        driven = spec_["kind"] == "line" and manoeuvre_line(
            r_e, data.vector_nT[w_e], data.rate_hz, spec_["dominant_frequency_hz"], s.alpha
        )
        if driven:
            unexplained["note"] += (
                "; the line is coherent with the attitude: the carrier's interference outside "
                "the model's forms, not an event"
            )
        if spec_["kind"] == "line" and not driven:
            # a line of its own through the calibration: periodic interference no channel
            # records, part of the null model's nuisances rather than an event in time
            unexplained["nuisances"].append(periodic_nuisance(spec_, cv_e))
            unexplained["note"] += (
                "; not coherent with the attitude: periodic interference no channel records "
                "(unexplained.nuisances: unrecorded_current)"
            )
    for e in events:
        if e["kind"] in ("step", "drift") and not unexplained["note"]:
            where = {
                "survey crossovers": "in the survey (crossovers",
                "calibration passes": "between calibration passes (held-out calibration fit",
                "vector reference": "against the fluxgate (scalar minus vector magnitude",
            }.get(e["evidence"], "during calibration (calibration residual")
            unexplained["note"] = (
                f"{e['kind']} of {e['size_nT']:.2f} nT {where}, "
                f"p {e['p_value']:.2g}); not a catalogue effect"
            )
    comp_b = aud.compensated(base_spec)
    t = data.time_s
    boxes = seg.boxes()
    fom_b = (
        figure_of_merit(t, data.scalar_nT, comp_b, boxes, s.band.band_hz, s.band.poles).total
        if boxes
        else None
    )
    fom_e = (
        figure_of_merit(t, data.scalar_nT, comp_e, boxes, s.band.band_hz, s.band.poles).total
        if boxes
        else None
    )
    q_b = _quality_figures(flight, seg, comp_b, subtract_base=False)
    q_e = _quality_figures(flight, seg, comp_e, subtract_base=final_spec.diurnal)
    gain = {
        "heldout_calibration_residual_rms_nT": {"before": cv_b, "after": cv_e},
        "fom_nT": {
            "before": fom_b["compensated"] if fom_b else None,
            "after": fom_e["compensated"] if fom_e else None,
        },
        "heading_error_rms_nT": {
            "before": q_b["heading_error_rms_nT"] if q_b else None,
            "after": q_e["heading_error_rms_nT"] if q_e else None,
            "heading_error_method": "intersections",
        },
        "overlap_pair_rms_nT": {
            "before": q_b["overlap_pair_rms_nT"] if q_b else None,
            "after": q_e["overlap_pair_rms_nT"] if q_e else None,
        },
        "crossover_rms_nT": {
            "before": q_b["crossover_rms_nT"] if q_b else None,
            "after": q_e["crossover_rms_nT"] if q_e else None,
        },
        # the map gridded from the other lines, interpolated along the validation lines
        "interpolated_map_rms_nT": {
            "before": q_b["interpolated_rms_nT"] if q_b else None,
            "after": q_e["interpolated_rms_nT"] if q_e else None,
        },
    }
    # measured vs simulated (simulator physics), band-passed over the calibration passes
    sim_res, where = {}, None
    sos = bandpass_sos(s.band.band_hz, data.rate_hz, s.band.poles)
    for name, fm, comp in (("baseline", baseline, comp_b), ("extended", extended, comp_e)):
        earth = time_window_mean(t, comp, 20.0)
        resid = design(data, fm.spec).measured_nT - simulate_measurement(data, fm, earth)
        valid = aud.mask & np.isfinite(resid)
        rr, ww = bandpass_blocks(
            resid, contiguous_blocks(valid, t), sos, s.band.trim_at(data.rate_hz)
        )
        if where is None:
            where = ww
        full = np.full(t.size, np.nan)
        full[ww] = rr
        sim_res[name] = full[where]
    notes = list(aud.notes)
    if white_excess:
        # flat in the band: no model term can follow it; broadband interference faster than
        # the sample rate resolves (vibration, attitude jitter) looks exactly like this
        notes.append(
            f"the held-out residual {cv_e:.4f} nT is {cv_e / floor:.1f}x the white-noise "
            f"floor {floor:.4f} nT but flat in the band, like white noise: broadband "
            "interference the sample rate cannot resolve, not structure a model term "
            "could follow"
        )
    if floor_is_bound:
        notes.append(
            f"the noise floor {sigma:.4f} nT is an upper bound on the sensor's own noise: "
            f"the compensated record's white level rises from {bounds.quietest_band_nT:.4f} nT "
            f"in its quietest band to {bounds.upper_band_nT:.4f} nT in the upper half of the "
            "band, the mark of broadband interference faster than the sample rate resolves "
            "(airframe jitter driving eddy currents), which adds to the sensor's noise at "
            "every frequency and cannot be told apart from it"
        )
    notes.append(
        f"held out: {len(aud.folds)} folds of {s.block_s_cv:g} s blocks, each "
        "holding every heading x manoeuvre; ridge lambda by inner cross-validation"
    )
    if gap > s.max_generalization_gap:
        notes.append(
            f"warning: the baseline's held-out residual is {gap:.1f}x its fit "
            f"residual (> {s.max_generalization_gap:g}): the calibration does not "
            "determine the model well; findings are less certain"
        )
    quality = {"baseline": q_b, "extended": q_e} if q_b else {}
    return AuditResult(
        baseline,
        extended,
        findings,
        rounds,
        cv_b,
        cv_e,
        floor,
        sigma,
        unexplained,
        gain,
        {"baseline": comp_b, "extended": comp_e},
        sim_res,
        where,
        quality,
        data,
        aud.passes,
        notes,
        gap,
        passwise,
        int(flight.time_ns[0]),
        bounds.to_dict(),
        floor_is_bound,
        None if aud.null_calibration is None else aud.null_calibration.to_dict(),
    )
