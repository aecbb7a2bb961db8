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

from functools import cached_property
from typing import Any

import numpy as np

from pipeline.audit.context import AuditContext
from pipeline.audit.decide import select
from pipeline.audit.events import AuditEvents, PassStep, pass_step_key
from pipeline.audit.evidence import band_noise_gain
from pipeline.audit.evidence.lag import EDDY_TAU_GRID_S
from pipeline.audit.extended import FittedModel, ModelSpec, design, simulate_measurement
from pipeline.audit.hypotheses import candidates, geomagnetic_gradient
from pipeline.audit.noise import NoiseFloorBounds, noise_floor_bounds
from pipeline.audit.null_calibration import NullCalibration, calibrate_null
from pipeline.audit.result import AuditResult, Evaluation, alternatives
from pipeline.audit.settings import EVENT_TESTS, AuditSettings
from pipeline.audit.spectrum import manoeuvre_line, periodic_nuisance, residual_spectrum
from pipeline.compensate.filters import bandpass_blocks, bandpass_sos, contiguous_blocks
from pipeline.compensate.model import figure_of_merit
from pipeline.compensate.nuisance import current_columns, second_order_columns
from pipeline.compensate.terms import direction_cosines, position_terms
from pipeline.errors import AeromagError
from pipeline.flight import Flight
from pipeline.maps.reduce import time_window_mean
from pipeline.segment import Segmentation

# the audit's records and settings keep their names here (imported from this module before
# they had homes of their own)
__all__ = [
    "EDDY_TAU_GRID_S",
    "AuditResult",
    "AuditSettings",
    "Auditor",
    "Evaluation",
    "PassStep",
    "alternatives",
    "run_audit",
]


class Auditor(AuditEvents, AuditContext):
    """Runs the audit on one flight (see the module docstring): the context
    (:class:`~pipeline.audit.context.AuditContext`), the event detectors
    (:class:`~pipeline.audit.events.AuditEvents`), the null model's bootstrap and the
    selection (:func:`pipeline.audit.decide.select`) over the candidates of
    :mod:`pipeline.audit.hypotheses`."""

    @cached_property
    def null_calibration(self) -> NullCalibration | None:
        """The selection's maximum statistic under the null model, by parametric bootstrap
        (:func:`pipeline.audit.null_calibration.calibrate_null`); None without the held-out
        folds."""
        nz = self.nuisances
        if nz.setup is None or nz.columns is None:
            return None
        d = self.data if nz.window is None else self.data.take(nz.window)
        cands: dict[str, np.ndarray] = {}
        if d.enu_m is not None:
            cands["geomagnetic_gradient"] = position_terms(*d.enu_m.T)[0]
        rivals: dict[str, str] = {}
        for effect, key in candidates(self, ModelSpec(base=self.s.baseline)):
            if effect == "electrical_current":
                name = key.split(":", 1)[1]
                cands[key] = current_columns(d.vector_nT, d.aux[name], name)[0]
                if not nz.second_order:  # the rival a current must beat (rule C4)
                    rivals[key] = "second_order"
        rival_cols = (
            {"second_order": second_order_columns(d.vector_nT, d.time_s)[0]} if rivals else {}
        )
        # a change of the permanent field between passes is a candidate of the selection
        # too: the event it reports must beat the same null maximum
        u = direction_cosines(d.vector_nT)
        for i, t_s in enumerate(self.pass_gap_middles()):
            cands[pass_step_key(i)] = u * (d.time_s > t_s).astype(float)[:, None]
        try:
            nc = calibrate_null(
                nz.setup,
                nz.columns,
                cands,
                self.s.maximum_alpha,
                self.s.min_gain,
                self.s.null_draws,
                self.s.null_seed,
                rivals,
                rival_cols,
                EVENT_TESTS * self.s.event_alpha,
            )
        except (ValueError, np.linalg.LinAlgError) as exc:
            self.notes.append(f"the null model's bootstrap could not run: {exc}")
            return None
        return nc

    def gradient_from_legs(self, spec: ModelSpec) -> ModelSpec | None:
        """:func:`pipeline.audit.hypotheses.geomagnetic_gradient.gradient_from_legs`."""
        return geomagnetic_gradient.gradient_from_legs(self, spec)

    def run(self, progress=None) -> tuple[ModelSpec, list[Evaluation], list[list[Evaluation]]]:
        """Forward-stepwise selection of the effects (:func:`pipeline.audit.decide.select`),
        from the null model with a permanent-field step where the survey or the calibration
        passes show one (:meth:`permanent_step`).

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
        return select(self, current, progress, lambda: self.null_calibration)


def _final_decay(nuisances: list[dict[str, Any]], final_spec: ModelSpec) -> list[dict[str, Any]]:
    """The nuisances with the eddy decay's time constant the final model holds: a lag named
    beside the decay profiles it anew (the null's, taken without the lag, as
    ``tau_s_without_findings``)."""
    out = []
    for n in nuisances:
        tau = n["estimate"].get("tau_s") if n["name"] == "eddy_decay" else None
        if tau is not None and final_spec.eddy_tau_s > 0 and final_spec.eddy_tau_s != tau:
            n = {**n, "estimate": {**n["estimate"], "tau_s": final_spec.eddy_tau_s}}
            n["estimate"]["tau_s_without_findings"] = tau
        out.append(n)
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
    bounds = _noise_floor_bounds(aud, final_spec, extended)
    sigma = bounds.sensor_nT
    floor_is_bound = bool(bounds.rise > s.max_noise_rise)
    floor = sigma * band_noise_gain(data.rate_hz, s.band.band_hz, s.band.poles)
    if progress:
        progress("survey-side evidence")
    unexplained, white_excess = _unexplained(aud, final_spec, findings, cv_e, r_e, w_e, floor)
    comp_b = aud.compensated(base_spec)
    gain, q_b, q_e = _gain(aud, final_spec, comp_b, comp_e, cv_b, cv_e)
    sim_res, where = _simulated_residuals(aud, baseline, extended, comp_b, comp_e)
    notes = _notes(aud, cv_e, floor, white_excess, bounds, gap)
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


def _noise_floor_bounds(
    aud: Auditor, final_spec: ModelSpec, extended: FittedModel
) -> NoiseFloorBounds:
    """The noise floor's upper bounds (:func:`pipeline.audit.noise.noise_floor_bounds`) from
    the extended model's compensated record."""
    data = aud.data
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
    return bounds


def _unexplained(
    aud: Auditor,
    final_spec: ModelSpec,
    findings: list[Evaluation],
    cv_e: float,
    r_e: np.ndarray,
    w_e: np.ndarray,
    floor: float,
) -> tuple[dict[str, Any], bool]:
    """What the extended model leaves: the events, the nuisances and ambiguities, the
    residual's spectrum and note; and whether the residual's excess is white."""
    data, s = aud.data, aud.s
    # events are what the catalogue model leaves: without the permanent-field step the
    # survey itself showed (which the extended model then absorbs)
    plain = final_spec.with_(permanent_step_s=None)
    cal_events, switched = aud.calibration_events(plain)
    events = aud.survey_evidence(plain) + cal_events
    events += aud.vector_reference_events()
    events += aud.pass_step_events(plain, events)
    named = {f.effect for f in findings}
    unexplained: dict[str, Any] = {
        "events": events,
        "nuisances": _final_decay(aud.nuisances.to_list(), final_spec) + switched,
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
        elif spec_["kind"] == "line":
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
    return unexplained, white_excess


def _gain(
    aud: Auditor,
    final_spec: ModelSpec,
    comp_b: np.ndarray,
    comp_e: np.ndarray,
    cv_b: float,
    cv_e: float,
) -> tuple[dict[str, dict[str, Any]], dict[str, Any] | None, dict[str, Any] | None]:
    """The gain per metric (held-out residual, FOM, the survey's quality figures) and the
    baseline's and extended model's quality figures."""
    flight, seg, data, s = aud.flight, aud.seg, aud.data, aud.s
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
    geometry = _quality_geometry(flight, seg)
    q_b = _quality_figures(flight, seg, comp_b, False, geometry)
    q_e = _quality_figures(flight, seg, comp_e, final_spec.diurnal, geometry)
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
    return gain, q_b, q_e


def _simulated_residuals(
    aud: Auditor,
    baseline: FittedModel,
    extended: FittedModel,
    comp_b: np.ndarray,
    comp_e: np.ndarray,
) -> tuple[dict[str, np.ndarray], np.ndarray | None]:
    """Measured minus simulated (the simulator's physics), band-passed over the calibration
    passes, for the baseline and the extended model; with the epochs they are at."""
    data, s = aud.data, aud.s
    t = data.time_s
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
    return sim_res, where


def _notes(
    aud: Auditor,
    cv_e: float,
    floor: float,
    white_excess: bool,
    bounds: NoiseFloorBounds,
    gap: float,
) -> list[str]:
    """The audit's notes: the auditor's, then on the residual, the noise floor, the folds and
    the baseline's generalisation."""
    s = aud.s
    sigma = bounds.sensor_nT
    floor_is_bound = bool(bounds.rise > s.max_noise_rise)
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
    return notes


def _quality_geometry(flight: Flight, seg: Segmentation):
    """The survey's quality geometry (:func:`pipeline.quality.stage.survey_geometry`) both
    models' figures share; None without a mapped block."""
    from pipeline.maps.stage import map_refusal
    from pipeline.quality.stage import survey_geometry

    if map_refusal(flight, seg) is not None:
        return None
    return survey_geometry(flight, seg)


def _quality_figures(
    flight: Flight, seg: Segmentation, comp: np.ndarray, subtract_base: bool, geometry
) -> dict[str, Any] | None:
    from pipeline.quality.stage import QualitySettings, run_quality

    if geometry is None:
        return None
    q = run_quality(
        flight,
        seg,
        {"raw": flight.data["scalar_nT"].to_numpy(float), "model": comp},
        settings=QualitySettings(subtract_base=subtract_base),
        geometry=geometry,
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
