"""Settings of the model audit (``[audit]``)."""

from __future__ import annotations

from dataclasses import dataclass, field

from pipeline.audit.crossval import BLOCK_S, N_FOLDS
from pipeline.audit.extended import BandSettings
from pipeline.audit.vector_reference import STEP_MARGIN
from pipeline.defaults import default_field

# the tests outside the null bootstrap's maximum that can name something on a flight: the
# survey's change scan (steps and drift), the calibration legs' step scan and the step
# against the fluxgate (each calibrated by its own null simulation), and a current coupling
# decided on the survey: one test per channel, the crossovers, the switches or both joined
# (Bonferroni over the channels)
EVENT_TESTS = 4


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
    fluxgate_step_margin : float
        Ratio of that test's maximum F to the 95 % point of its Gaussian null that a step
        must reach (dimensionless): the ratio's quantile at :attr:`event_alpha` on simulated
        flights with no step (``benchmarks/bench_fluxgate_step_margin.py``).
    min_leg_ramp_nT : float
        Smallest field change along the calibration legs (RMS, nT) with which a gradient
        seen there confirms a gradient candidate (:mod:`pipeline.audit.legs`).
    min_excess_gradient_nT_per_m : float
        Smallest horizontal gradient beyond the main field's (nT/m) that is named a
        gradient effect.
    min_lag_s : float
        Smallest sensor lag (s) that is named a lag effect.
    flight_alpha, null_draws, null_seed : float, int, int
        The whole selection's false-finding rate with nothing hidden (findings and events
        together: :attr:`event_alpha` for each event test outside the bootstrap's maximum,
        :attr:`maximum_alpha` for the maximum), and the null model's bootstrap that
        measures it (draws, seed).
    min_nuisance_nT : float
        Held-out RMS (nT) a nuisance must remove, with the findings in the model, to stay.
    min_survey_effect_nT : float
        What a current coupling decided by the survey's own evidence, or the diurnal
        correction, must do to the survey lines (RMS, nT) to be named.
    switch_steady_attitude_deg : float
        Largest change of roll and pitch (deg) over a switch's window for a switch read in a
        turn to count as a step of the channel.
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
    # interference outside the scalar-minus-fluxgate model lifts a step-free flight's F above
    # the scan's Gaussian null: the margin is that ratio's quantile at the event test's level
    # over simulated step-free flights (benchmarks/bench_fluxgate_step_margin.py, docs/audit.md)
    fluxgate_step_margin: float = STEP_MARGIN
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
    # the test level of the survey crossovers' check of the null model's nuisance groups
    # (pipeline.audit.survey_guard)
    survey_guard_alpha: float = default_field("audit", "survey_guard_alpha")
    # what a coupling the survey alone decides must do to the lines to be worth naming
    min_survey_effect_nT: float = default_field("audit", "min_survey_effect_nT")
    # a switch in a turn is read only where the bank is held: the interference the model
    # leaves follows the attitude, and a roll-in beside a switch would pass for its step
    switch_steady_attitude_deg: float = default_field("audit", "switch_steady_attitude_deg")
    # a lag estimate moves with the resampling and the eddy columns' differences by a few
    # ms; under 20 ms a lag shifts the anomaly by less than 14 cm along track at 7 m/s (0.6 m
    # at 30 m/s), below a survey's positioning error: not worth a model term
    min_lag_s: float = 0.02

    @property
    def event_alpha(self) -> float:
        """Level of each of the :data:`EVENT_TESTS` event tests outside the bootstrap's
        maximum: ``alpha``, or an equal share of ``flight_alpha`` when that is smaller."""
        return min(self.alpha, self.flight_alpha / (EVENT_TESTS + 1))

    @property
    def maximum_alpha(self) -> float:
        """Level of the null bootstrap's maximum (the findings and the change between
        calibration passes): what of ``flight_alpha`` the event tests leave (Bonferroni:
        the flight's false-finding rate is at most the sum of the levels)."""
        return self.flight_alpha - EVENT_TESTS * self.event_alpha
