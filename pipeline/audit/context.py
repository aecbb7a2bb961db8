"""The audit's context: one flight's data, calibration mask and folds, with the fits, band-passed
calibration rows, compensated fields and crossovers kept per model."""

from __future__ import annotations

from collections import OrderedDict
from functools import cached_property
from typing import Any

import numpy as np

from pipeline.audit.crossval import calibration_strata, passwise_folds, stratified_block_folds
from pipeline.audit.evidence import (
    HeldOut,
    NestedTest,
    heldout_gain,
    nested_test,
    profile_f_test,
    thinning_step,
)
from pipeline.audit.extended import (
    AuditData,
    CalibrationRows,
    FittedModel,
    ModelSpec,
    calibration_rows,
    design,
    fit_model,
    sensor_filtered,
)
from pipeline.audit.legs import leg_ids
from pipeline.audit.nuisances import NuisanceSelection, select_nuisances
from pipeline.audit.settings import AuditSettings
from pipeline.audit.survey import CrossoverSet
from pipeline.audit.vector_cal import fit_vector_calibration
from pipeline.audit.vector_reference import (
    VectorStep,
    difference_design,
    vector_reference_step,
)
from pipeline.compensate.filters import bandpass_blocks, bandpass_sos, contiguous_blocks
from pipeline.compensate.stage import calibration_mask
from pipeline.flight import Flight
from pipeline.geo.heading import heading_class, pattern_direction_deg
from pipeline.maps.reduce import BASE_SMOOTHING_S, time_window_mean
from pipeline.segment import Segmentation

# models whose band-passed calibration rows the auditor keeps (a fold loop uses two or three
# at a time; each is the calibration's rows x the model's columns, a few MB)
ROWS_CACHED = 8


def _fold_masks(fold: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """(train, test) epoch masks of each fold number in ``fold`` (-1: not calibration)."""
    inside = fold >= 0
    return [(inside & (fold != k), fold == k) for k in np.unique(fold[inside])]


# crossover readings are averaged over this along track (s) where a test compares their
# levels: a second averages the sensor noise out of each reading, the diurnal and the
# carrier's levels change over minutes
CROSSOVER_SMOOTHING_S = 1.0


def crossover_set(difference_nT: np.ndarray, xs: list, heading: dict) -> CrossoverSet:
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
        np.array([c.line_a for c in xs]),
        np.array([c.line_b for c in xs]),
    )


def base_difference(xs: list, time_s: np.ndarray, base_nT: np.ndarray) -> np.ndarray:
    """The base station's difference between each crossover's two readings (nT; ``base_nT``
    on the epochs ``time_s``, s)."""
    ta = np.array([c.time_a_s for c in xs], float)
    tb = np.array([c.time_b_s for c in xs], float)
    return np.interp(ta, time_s, base_nT) - np.interp(tb, time_s, base_nT)


class AuditContext:
    """One flight under audit: its data, calibration mask, folds and the fits, rows,
    compensated fields and crossovers kept per model."""

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
        # each calibration epoch's heading (N, E, S, W; turns) and kind of manoeuvre (roll,
        # pitch, yaw, steady; turns)
        head, _, tail = np.char.partition(strata.astype(str), ":").T
        self.leg_heading = head
        self.manoeuvre_kind = np.where(head == "turn", "turn", tail)
        self.fold = stratified_block_folds(
            self.data.time_s, self.mask, strata, settings.n_folds, settings.block_s_cv
        )
        self.folds = _fold_masks(self.fold)
        self.pass_fold = passwise_folds(self.mask, self.passes)
        self.step = thinning_step(self.data.rate_hz, settings.band.band_hz)
        self.notes: list[str] = []
        self._fit_cache: dict[tuple, FittedModel] = {}
        # each model's lag and its cost, per key (evidence.lag.lag_fit)
        self.lag_fits: dict[tuple, tuple[float, float]] = {}
        # each model's lag weighed beside eddy currents that decay (tau s, the decay alone,
        # the lag beyond it): several rules read the one test (hypotheses.lag_decay)
        self.lag_decay_weighings: dict[ModelSpec, tuple] = {}
        # each model's band-passed calibration rows, shared by its fits and residuals over
        # the folds (the design spans the whole flight: building it once per fit made the
        # audit grow with the survey); the last few models only
        self._rows_cache: OrderedDict[ModelSpec, CalibrationRows] = OrderedDict()
        # the last rows built per model without its lag: a lag search builds the rows of
        # one model at many lags, whose columns are the same (only the scalar moves)
        self._columns_cache: OrderedDict[ModelSpec, CalibrationRows] = OrderedDict()
        self._crossover_cache: dict[tuple, tuple] = {}
        self._compensated: dict[ModelSpec, np.ndarray] = {}
        self._geometry: tuple | None = None
        self._base: dict[float, np.ndarray] = {}  # the base station per averaging window (s)
        # each model's permanent-field changes between passes (events.AuditEvents.pass_steps)
        self._pass_steps: dict[ModelSpec, list] = {}
        self.ambiguities: list[dict[str, Any]] = []

    @cached_property
    def nuisances(self) -> NuisanceSelection:
        """The carrier's physics outside the T-L basis the held-out calibration supports
        (:func:`pipeline.audit.nuisances.select_nuisances`): part of the null model."""
        return select_nuisances(self.flight, self.mask, self.s.band, self.s.alpha, self.s.min_gain)

    @cached_property
    def fluxgate_calibrated(self) -> np.ndarray:
        """The fluxgate reading (n, 3; body frame, nT) calibrated against the scalar, for the
        scalar-minus-fluxgate tests (exactly, not to first order as their model holds its
        errors: their squares reach nT); as recorded when too few readings calibrate it."""
        d = self.data
        try:
            return fit_vector_calibration(d.vector_nT, d.scalar_nT).apply(d.vector_nT)
        except ValueError:
            return d.vector_nT

    @cached_property
    def fluxgate_difference(self) -> tuple[np.ndarray, ...]:
        """The scalar-minus-fluxgate 1 s means and their model's columns
        (:func:`pipeline.audit.vector_reference.difference_design` of the calibrated
        fluxgate and the recorded channels): the step scan and the persistence check share
        them."""
        d = self.data
        return difference_design(d.time_s, d.scalar_nT, self.fluxgate_calibrated, d.aux)

    @cached_property
    def fluxgate_step(self) -> VectorStep | None:
        """A step in the carrier's permanent field located by the scalar-minus-fluxgate test
        (:func:`pipeline.audit.vector_reference.vector_reference_step`; the readings only,
        the fluxgate calibrated against the scalar, the recorded channels in its model), or
        None."""
        d = self.data
        return vector_reference_step(
            d.time_s,
            d.scalar_nT,
            self.fluxgate_calibrated,
            d.aux,
            self.s.event_alpha,
            self.s.min_vector_step_nT,
            self.s.fluxgate_step_margin,
            design=self.fluxgate_difference,
        )

    def null_spec(self) -> ModelSpec:
        """The null model: the baseline with the nuisances the data support."""
        nz = self.nuisances
        return ModelSpec(
            base=self.s.baseline,
            eddy_tau_s=nz.eddy_tau_s,
            second_order=nz.second_order,
        )

    def jackknife_groups(self) -> list[list[tuple[np.ndarray, str]]]:
        """The calibration's groupings for a delete-a-group jackknife of an estimate: by
        kind of manoeuvre (roll, pitch, yaw, steady, turns) and by heading, each a list of
        (training epochs: the calibration without one group, a key naming them for
        :meth:`fit`). A constant of the carrier is the same in every manoeuvre on every
        heading; a misfit outside the model moves it differently in each, a spread the
        stratified folds (each holding every group) hide. A grouping with fewer than two
        groups is left out; with neither, the folds are the groups."""
        groupings = []
        for labels in (self.manoeuvre_kind, self.leg_heading):
            present = sorted(set(labels[self.mask].tolist()))
            if len(present) >= 2:
                groupings.append([(self.mask & (labels != g), f"without-{g}") for g in present])
        return groupings or [[(train, f"fold{k}") for k, (train, _) in enumerate(self.folds)]]

    @cached_property
    def calibration_part(self) -> tuple[AuditData, np.ndarray, np.ndarray]:
        """(data, mask, epoch indices) near the calibration
        (:meth:`AuditData.calibration_part`): where the nested tests build their designs."""
        return self.data.calibration_part(self.mask)

    @cached_property
    def legs(self) -> np.ndarray:
        """Calibration leg of each epoch (one heading of one pass), -1 elsewhere
        (:func:`pipeline.audit.legs.leg_ids`)."""
        return leg_ids(self.mask, self.seg.cardinal, self.seg.calibration_pass, self.data.time_s)

    @cached_property
    def base_smoothed_nT(self) -> np.ndarray:
        """The base station's reading on the scalar epochs, smoothed over
        ``BASE_SMOOTHING_S`` as the reduction smooths it (:meth:`base_over`)."""
        return self.base_over(BASE_SMOOTHING_S)

    def base_over(self, window_s: float) -> np.ndarray:
        """The base station's reading on the scalar epochs, a centred running mean over
        ``window_s`` (s; 0: as read), nT; all NaN without a base station (crossover
        differences then keep the day's variation). Kept per window, read-only: shared."""
        if window_s not in self._base:
            if self.flight.has("base_nT"):
                raw = self.flight.data["base_nT"].to_numpy(float)
                base = time_window_mean(self.data.time_s, raw, window_s)
            else:
                base = np.full(self.data.time_s.size, np.nan)
            base.flags.writeable = False
            self._base[window_s] = base
        return self._base[window_s]

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
            twin = spec.with_(lag_s=0.0, lag_response="delay")
            got = calibration_rows(
                self.data, spec, self.mask, self.s.band, like=self._columns_cache.get(twin)
            )
            for cache, key in ((self._rows_cache, spec), (self._columns_cache, twin)):
                cache[key] = got
                cache.move_to_end(key)
                while len(cache) > ROWS_CACHED:
                    cache.popitem(last=False)
        else:
            self._rows_cache.move_to_end(spec)
        return got

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

    def heldout(self, before, after_for_fold, where: np.ndarray | None = None) -> HeldOut:
        """Held-out band-passed residuals of two models over the folds; ``after_for_fold``
        builds the extended spec from the training mask (parameters estimated there);
        ``before`` is a spec, or like ``after_for_fold`` a builder of one. ``where`` (bool
        per epoch), when given, keeps only those epochs' held-out residuals."""
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
            if where is not None:
                keep = where[common]
                common, i0, i1 = common[keep], i0[keep], i1[keep]
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
        data, mask, idx = self.calibration_part
        des = design(data, spec)
        if ext_spec is not None:
            des_e = design(data, ext_spec)
            cols_e = des_e.columns
        else:
            cols_e = np.column_stack([des.columns, extra[idx]])
        valid = (
            mask
            & np.isfinite(des.y)
            & np.all(np.isfinite(cols_e), axis=1)
            & np.all(np.isfinite(des.columns), axis=1)
        )
        blocks = contiguous_blocks(valid, data.time_s)
        sos = bandpass_sos(self.s.band.band_hz, data.rate_hz, self.s.band.poles)
        kb, _ = bandpass_blocks(des.columns, blocks, sos, self.s.band.trim_at(data.rate_hz))
        ke, _ = bandpass_blocks(cols_e, blocks, sos, self.s.band.trim_at(data.rate_hz))
        yf, _ = bandpass_blocks(des.y, blocks, sos, self.s.band.trim_at(data.rate_hz))
        return nested_test(yf, kb, ke, self.step)

    def _lag_profile_test(self, spec: ModelSpec, lag_s: float) -> NestedTest:
        """The lag's profile-likelihood F-test beside ``spec``'s columns (the record delayed
        by ``lag_s`` against not): beside decayed eddy columns, which span the lag's
        linearisation (a first-order response), only the delay of the whole reading tells a
        late sensor (:func:`pipeline.audit.evidence.profile_f_test`)."""
        data, mask, _ = self.calibration_part
        d0, d1 = design(data, spec), design(data, spec.with_(lag_s=lag_s))
        valid = (
            mask & np.isfinite(d0.y) & np.isfinite(d1.y) & np.all(np.isfinite(d0.columns), axis=1)
        )
        blocks = contiguous_blocks(valid, data.time_s)
        sos = bandpass_sos(self.s.band.band_hz, data.rate_hz, self.s.band.poles)
        trim = self.s.band.trim_at(data.rate_hz)
        kb, at = bandpass_blocks(d0.columns, blocks, sos, trim)
        y0, _ = bandpass_blocks(d0.y, blocks, sos, trim)
        y1, _ = bandpass_blocks(d1.y, blocks, sos, trim)
        if spec.lag_response != "first_order":
            return profile_f_test(y0, y1, kb, self.step)
        dt = 1.0 / data.rate_hz  # the lagged model's rows through the sensor's filter
        k1, y1 = (sensor_filtered(a, at, dt, lag_s) for a in (kb, y1))
        return profile_f_test(y0, y1, kb, self.step, k1)

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

        igrf, base, tracks = self._survey_geometry()
        red = self.compensated(spec) - igrf
        if smooth_s > 0:
            red = time_window_mean(self.data.time_s, red, smooth_s)
        t = self.data.time_s

        survey = [Line.from_track(tr, t, red) for tr in tracks if tr.kind == "survey"]
        ties = [Line.from_track(tr, t, red) for tr in tracks if tr.kind == "tie"]
        xs = crossovers(survey, ties, crossings=self._tie_crossings)
        # heading classes relative to the survey's own line direction, not to north
        ref = pattern_direction_deg(
            np.array([tr.heading_deg for tr in tracks if tr.kind in ("survey", "tie")])
        )
        heading = {tr.line_id: int(heading_class(tr.heading_deg, ref)) for tr in tracks}
        dx = np.array([c.difference_nT for c in xs])
        db = base_difference(xs, t, base)
        return dx, db, self._validation_crossings, red, base, xs, heading

    @cached_property
    def _tie_crossings(self):
        """Where the survey lines cross the tie lines
        (:func:`pipeline.maps.level.track_crossings`): geometry only, the same for every
        model."""
        from pipeline.maps.level import track_crossings

        tracks = self._survey_geometry()[2]
        survey = [tr for tr in tracks if tr.kind == "survey"]
        return track_crossings(survey, [tr for tr in tracks if tr.kind == "tie"])

    @cached_property
    def _validation_crossings(self):
        """The validation lines' crossings with the survey and tie lines
        (:func:`pipeline.quality.overlap.track_intersections`): geometry only, the same for
        every model."""
        from pipeline.quality.overlap import track_intersections

        tracks = self._survey_geometry()[2]
        val = [tr for tr in tracks if tr.kind == "validation"]
        mapped = [tr for tr in tracks if tr.kind in ("survey", "tie")]
        return track_intersections(val, mapped)

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
        d, xs, heading, red = self._finite_crossovers(spec)
        if d.size < 8:
            return None
        return crossover_set(d, xs, heading), red

    def _finite_crossovers(self, spec: ModelSpec) -> tuple[np.ndarray, list, dict, np.ndarray]:
        """``spec``'s survey crossovers (1 s along track, :meth:`_crossover_data`) whose
        difference less the base station's is finite, a reading beside a gap in the
        recording (or the base's) having none: those differences (nT), the crossovers, the
        lines' heading classes and the reduced field along the flight."""
        dx, db, _, red, _, xs, heading = self._crossover_data(spec, smooth_s=CROSSOVER_SMOOTHING_S)
        d = dx - db
        ok = np.isfinite(d)
        return d[ok], [c for c, k in zip(xs, ok, strict=True) if k], heading, red
