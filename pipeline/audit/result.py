"""The audit's records: one candidate's evaluation, the whole result, and their JSON."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pipeline.audit.evidence import HeldOut, NestedTest
from pipeline.audit.extended import AuditData, FittedModel, ModelSpec
from pipeline.audit.legs import fisher_combined
from pipeline.audit.settings import AuditSettings


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
    # the model whose refit gives the estimate (a lag's, lag 0): its interval re-estimates
    # it there
    estimated_in: ModelSpec | None = None
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
    # (p, estimate) of the one test by which evidence outside the calibration can decide the
    # candidate (a current's survey test and its k), set when that evidence predicts its own
    # data and the estimate matters to the survey, else None: what keeps a finding so decided
    # when the model around it changes (decide.refine)
    outside: tuple[float, float] | None = None

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
            "outside_p_value": None if self.outside is None else self.outside[0],
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
