"""Events the catalogue model leaves: steps and drifts in the survey, in the calibration and
against the fluxgate."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.audit.calibration_events import (
    CalibrationStep,
    calibration_steps,
    is_switching,
    manoeuvre_blocks,
    switching_nuisance,
)
from pipeline.audit.evidence import HeldOut
from pipeline.audit.extended import ModelSpec, design
from pipeline.audit.survey import survey_events
from pipeline.audit.vector_reference import persists_against_fluxgate

# span (s) over which a crossing reading's course over ground is taken: a few samples at
# any rate, short against a turn's 10-30 s
COURSE_WINDOW_S = 2.0
# steps looked for inside the calibration legs: two tell a switched load from one event,
# a few more estimate its size
MAX_SWITCHES = 6
# calibration after a leg step's leg that tells a permanent change from a switched load
# (s), on at least two legs (headings: u . dp differs between them)
PERSIST_MIN_S = 60.0


def pass_step_key(gap: int) -> str:
    """The null bootstrap's key of a permanent-field change in gap ``gap`` between
    calibration passes (:meth:`AuditEvents.pass_steps`)."""
    return f"pass_step:{gap}"


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
        return self.gap_middle_s(self.start_s, self.end_s)

    @staticmethod
    def gap_middle_s(start_s: float, end_s: float) -> float:
        """Where the calibration model puts a change between passes: no calibration sample
        lies in the gap, so any time in it is the same model; its middle (s)."""
        return 0.5 * (start_s + end_s)


class AuditEvents:
    """The event detectors of :class:`pipeline.audit.stage.Auditor` (a mixin over its
    :class:`~pipeline.audit.context.AuditContext`)."""

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
        keep = self._straight_crossings(self._finite_crossovers(spec)[1])
        x = x.subset(keep)
        events = survey_events(x, self.s.event_alpha, self.s.min_event_nT)
        t0 = int(self.flight.time_ns[0])
        return [e.to_dict(t0) for e in events]

    def _straight_crossings(
        self, xs: list, max_turn_deg: float = 15.0, max_height_m: float = 20.0
    ) -> np.ndarray:
        """Which crossovers ``xs`` read the same ground the same way: both lines flying
        straight (the course over ground within ``COURSE_WINDOW_S`` of the reading, a window
        wholly on the line, within ``max_turn_deg`` of the line's mean heading) and at
        heights within ``max_height_m`` of each other. A line's ends can run into its turns
        (a reading whose window runs off the line is in the turn's roll-out, where the
        carrier's interference is the turn's), and a track labelled a tie can be a climbing
        transit; the ground's anomalies change by 0.02-0.1 nT per metre of height, so 20 m
        keeps the error near the crossovers' own scatter."""
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
            lo, hi = i - half, i + half
            if lo < 0 or hi > tt.size - 1:
                return False  # the window runs off the line: read in the turn's roll-out
            de, dn = tr.east_m[hi] - tr.east_m[lo], tr.north_m[hi] - tr.north_m[lo]
            if np.hypot(de, dn) == 0:
                return True
            course = np.degrees(np.arctan2(de, dn))
            return abs((course - tr.heading_deg + 180.0) % 360.0 - 180.0) <= max_turn_deg

        return height_ok & np.array(
            [straight(c.line_a, c.time_a_s) and straight(c.line_b, c.time_b_s) for c in xs],
            bool,
        ).reshape(len(xs))

    def calibration_events(self, spec: ModelSpec) -> tuple[list[dict], list[dict]]:
        """Steps in ``spec``'s compensated field inside the calibration legs
        (:mod:`pipeline.audit.calibration_events`): one step as an ``unexplained.events``
        entry, repeated steps as an unrecorded switched current among
        ``unexplained.nuisances``.

        Returns
        -------
        tuple of list
            The events and the nuisances.
        """
        # everything the model explains removed, its geology terms (position) too: a
        # gradient seen through the manoeuvres' height changes is no step
        fm = self.fit(spec, None, "all")
        des = design(self.data, spec)
        comp = des.y - des.columns @ fm.theta
        t = self.data.time_s
        block = manoeuvre_blocks(self.seg.manoeuvre)
        steps = calibration_steps(
            t,
            comp,
            self.legs,
            self.s.event_alpha,
            self.s.min_event_nT,
            max_steps=MAX_SWITCHES,
            block=block,
        )
        if is_switching(steps) or (steps and not self._persists(spec, steps[0])):
            return [], [switching_nuisance(t, comp, self.legs, steps, block=block)]
        return [e.to_dict(int(self.flight.time_ns[0])) for e in steps], []

    def _persists(self, spec: ModelSpec, step: CalibrationStep) -> bool:
        """Whether a step found inside a leg is a change of the carrier's permanent field.

        One persists: the calibration after the step's leg (or before it,
        :meth:`_after_leg`), on other headings, differs by the change ``u . dp``, so the
        model with it predicts those legs' held-out data better (p < ``alpha``), and better
        than a step at any other leg's middle does beside it (a permutation test at level
        1 / (placebos + 1)). The placebos measure how far the permanent terms move between
        any two stretches of this calibration anyway: a switched load's duty cycle,
        interference outside the model that follows the manoeuvre mix. A step the other
        legs do not carry beyond those was a load switched on and off again (off in a turn,
        say, where no step is looked for): a switched current, a nuisance. With too little
        calibration on either side of the leg nothing tells them apart; the step stays an
        event."""
        t_s = 0.5 * (step.start_s + step.end_s)
        if self._switched_off_after_its_leg(t_s):
            return False
        after = self._after_leg(t_s)
        if after is None:
            return True
        with_step = spec.with_(permanent_step_s=t_s)
        held = self.heldout(spec, lambda train, k: with_step, where=after)
        if held.p_value >= self.s.alpha:
            return False
        for t_k in self._leg_middles(exclude=self._leg_at(t_s)):
            where = self._after_leg(t_k)
            if where is None:
                continue
            placebo = with_step.with_(further_steps_s=(t_k,))
            gain = self.heldout(with_step, lambda train, k, p=placebo: p, where=where)
            if gain.reduction >= held.reduction:
                return False
        return True

    def _switched_off_after_its_leg(self, t_s: float) -> bool:
        """Whether the scalar-minus-fluxgate record shows the step at ``t_s`` switched off
        again before the next leg or line flown after its leg: a load on for the rest of
        its leg fits it better than a change to the record's end
        (:func:`pipeline.audit.vector_reference.persists_against_fluxgate`). The
        difference holds no Earth field, so the later readings weigh in on any heading; the
        held-out legs below cannot tell this case, for a step's transient inside its own
        leg pulls a fit without it wherever it is. It only ever makes a step a switched
        load: a load switched off later, or a change, is for the tests below."""
        t = self.data.time_s
        span = self._leg_span(t_s)
        if span is None:
            return False
        end = span[1]
        flown = (self.legs >= 0) | self.seg.mask("survey", "tie", "validation")
        nxt = t[flown & (t > end)]
        window = (end, float(nxt.min()) if nxt.size else end)
        persists = persists_against_fluxgate(
            t,
            self.data.scalar_nT,
            self.fluxgate_calibrated,
            t_s,
            window,
            self.data.aux,
            design=self.fluxgate_difference,
        )
        return persists is False

    def _after_leg(self, t_s: float) -> np.ndarray | None:
        """The calibration after the leg holding ``t_s`` (bool per epoch), or else before it:
        the first side that lasts :data:`PERSIST_MIN_S` on at least two legs (headings:
        ``u . dp`` differs between them); None when neither does. The step's model is the
        same either way (permanent terms free on each side), so either side tests it."""
        t = self.data.time_s
        lo, hi = self._leg_span(t_s) or (t_s, t_s)
        for side in (self.mask & (t > hi), self.mask & (t < lo)):
            legs = np.unique(self.legs[side & (self.legs >= 0)])
            if side.sum() >= PERSIST_MIN_S * self.data.rate_hz and legs.size >= 2:
                return side
        return None

    def _leg_span(self, t_s: float) -> tuple[float, float] | None:
        """The first and last epoch (s) of the calibration leg holding ``t_s`` (None: the
        epoch nearest ``t_s`` is on no leg)."""
        leg = self._leg_at(t_s)
        if leg < 0:
            return None
        t = self.data.time_s[self.legs == leg]
        return float(t.min()), float(t.max())

    def _leg_at(self, t_s: float) -> int:
        """The calibration leg of the epoch nearest ``t_s`` (-1: none)."""
        return int(self.legs[int(np.argmin(np.abs(self.data.time_s - t_s)))])

    def _leg_middles(self, exclude: int) -> list[float]:
        """The middle time (s) of every calibration leg but ``exclude``."""
        t = self.data.time_s
        legs = [k for k in np.unique(self.legs) if k >= 0 and k != exclude]
        return [float(np.median(t[self.legs == k])) for k in legs]

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
        step = self.fluxgate_step
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
        and the passes' unmodelled interference differs a little). Like every candidate of
        the selection, its held-out gain on the null bootstrap's folds must also reach the
        gate of the whole selection's maximum statistic (:attr:`null_calibration`): the
        event then has the flight-level false rate the findings have.
        Kept per model. Hand-written: the test is the audit's own nested and held-out pair,
        which no change-point library computes on a regression's coefficients.
        """
        if spec in self._pass_steps:
            return self._pass_steps[spec]
        gaps = self.pass_gaps()
        nc = self.null_calibration
        out = []
        for i, (lo, hi) in enumerate(gaps):
            if nc is not None and not nc.passes(pass_step_key(i)):
                continue
            ext = spec.with_(permanent_step_s=PassStep.gap_middle_s(lo, hi))
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

    def pass_gaps(self) -> list[tuple[float, float]]:
        """(end of the earlier pass, start of the later one), s, for every pair of
        consecutive calibration passes."""
        t = self.data.time_s
        return [
            (float(t[a[-1]]), float(t[b[0]]))
            for a, b in zip(self.passes[:-1], self.passes[1:], strict=True)
        ]

    def pass_gap_middles(self) -> list[float]:
        """The middle (s) of each gap of :meth:`pass_gaps`: where the calibration model puts
        a change of the permanent field between the passes (:attr:`PassStep.middle_s`)."""
        return [PassStep.gap_middle_s(lo, hi) for lo, hi in self.pass_gaps()]

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
