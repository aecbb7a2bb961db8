"""Label every epoch of a flight and find the 12 calibration boxes.

With ``/plan/line`` the planned segments are used as recorded. Without it the labels are
inferred, never read from a simulator:

1. the horizontal track (local metres) is simplified by Douglas-Peucker (shapely/GEOS) with a
   tolerance larger than manoeuvre sway and GNSS noise; runs between vertices lasting at least
   ``min_leg_s`` are straight legs, and each leg's ends are refined to where the track leaves
   the fitted line by more than the local noise (sub-second precision);
2. a leg with sustained roll, pitch or yaw oscillation is a **calibration** leg; its epochs
   are split into roll / pitch / yaw / steady by oscillation amplitude (Hilbert envelope),
   and the leg's heading gives the cardinal direction (the 4 x 3 = 12 boxes of the FOM);
3. other legs are grouped by orientation: the orientation with the most line length is the
   **survey** direction, legs within ``parallel_tol_deg`` of it that overlap the survey block
   are survey lines, legs perpendicular to it crossing the block are **tie** lines, and legs
   crossing it diagonally are **validation** lines; each keeps only its longest part flown at
   the block's heights (``block_height_tol_m``); anything else is **transit**;
4. epochs between legs are a **turn** when both neighbours belong to the same block (survey
   area, or one calibration pass), else **transit**.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy.ndimage import uniform_filter1d
from scipy.signal import hilbert
from shapely import LineString

from pipeline.errors import AeromagError
from pipeline.flight import Flight
from pipeline.geo.heading import cardinal_name, pattern_direction_deg
from pipeline.geo.local import local_east_north

LABELS = ("calibration", "survey", "tie", "validation", "turn", "transit")
MANOEUVRES = ("roll", "pitch", "yaw")
SURVEY_BLOCK = {"survey", "tie", "validation"}


@dataclass
class SegmentParams:
    """Tunables of the inference (units in names)."""

    simplify_tol_m: float = 5.0  # Douglas-Peucker tolerance: > sway (~1.6 m) and GNSS noise
    min_leg_s: float = 20.0  # shorter straight runs are part of a turn or transit
    end_tol_floor_m: float = 0.2  # leg-end refinement: smallest distance-from-line tolerance
    roll_active_deg: float = 2.5  # oscillation amplitude that counts as a manoeuvre
    pitch_active_deg: float = 1.5
    yaw_active_deg: float = 1.5
    min_active_s: float = 8.0  # sustained activity that makes a leg a calibration leg
    min_swings: int = 4  # ... and it must alternate: at least two full oscillations
    min_survey_lines: int = 3  # fewer parallel lines are not a survey block
    # share of a block's line positions (its offsets' span over the spacing) that its lines
    # fill: a skipped or moved line leaves some empty, scattered legs leave most
    min_grid_fill: float = 0.5
    parallel_tol_deg: float = 8.0  # survey / tie orientation tolerance
    # a line of the block reads the field the others read only at their height: the part of
    # a leg farther than this outside the block's heights (a robust 3-sigma range of the
    # survey lines' altitudes) is a transit climbing to, leaving or crossing the block at
    # another height; a drape's terrain following widens the range and stays inside it
    block_height_tol_m: float = 50.0
    pass_gap_s: float = 180.0  # calibration legs closer in time than this form one pass
    # a heading this far from the leg's own is a turn, not a manoeuvre of the leg: far above
    # a calibration box's yaw swings (5-10 deg), far below a turn between legs (90-180 deg)
    turn_deg: float = 30.0


@dataclass
class Box:
    """One of the 12 calibration manoeuvre boxes of a pass."""

    calibration_pass: int
    cardinal: str
    manoeuvre: str
    index: np.ndarray  # epoch indices

    @property
    def name(self) -> str:
        """Box name ``C<pass><cardinal>-<manoeuvre>``, e.g. ``C1N-roll``."""
        return f"C{self.calibration_pass}{self.cardinal}-{self.manoeuvre}"


@dataclass
class Segmentation:
    """Per-epoch labels (arrays aligned with the flight's epochs)."""

    label: np.ndarray
    line_id: np.ndarray
    heading_deg: np.ndarray  # mean heading of the leg (track), NaN in turns and transits
    manoeuvre: np.ndarray  # roll | pitch | yaw | steady on calibration legs, else ""
    cardinal: np.ndarray  # N | E | S | W on calibration legs, else ""
    calibration_pass: np.ndarray  # 1, 2, ... on calibration epochs, else 0
    source: str  # "plan" or "inferred"
    notes: list[str] = field(default_factory=list)

    def mask(self, *labels: str) -> np.ndarray:
        """Epochs carrying any of the given labels.

        Parameters
        ----------
        *labels : str
            Some of ``LABELS`` (calibration, survey, tie, validation, turn, transit).

        Returns
        -------
        ndarray of bool
            One per flight epoch.
        """
        return np.isin(self.label, labels)

    def boxes(self) -> list[Box]:
        """Calibration boxes (pass, cardinal, manoeuvre) in flight order."""
        out: dict[tuple[int, str, str], list[int]] = {}
        sel = np.flatnonzero((self.label == "calibration") & np.isin(self.manoeuvre, MANOEUVRES))
        for i in sel:
            out.setdefault(
                (int(self.calibration_pass[i]), str(self.cardinal[i]), str(self.manoeuvre[i])), []
            ).append(int(i))
        return [Box(p, c, m, np.asarray(ix)) for (p, c, m), ix in out.items()]

    def passes(self) -> list[np.ndarray]:
        """Epoch index span (first..last, turns included) of each calibration pass."""
        out = []
        for p in sorted(set(self.calibration_pass[self.calibration_pass > 0].tolist())):
            ix = np.flatnonzero(self.calibration_pass == p)
            out.append(np.arange(ix[0], ix[-1] + 1))
        return out

    def changes(self) -> list[int]:
        """Epoch indices where label, line, manoeuvre or cardinal changes (the first too)."""
        keys = pd.DataFrame({"l": self.label, "i": self.line_id, "m": self.manoeuvre})
        changed = (keys != keys.shift()).any(axis=1).to_numpy().copy()
        changed[0] = True
        return np.flatnonzero(changed).tolist()


# --------------------------------------------------------------------------------------------
def _circmean_deg(a: np.ndarray, period: float = 360.0) -> float:
    ang = np.radians(np.asarray(a, float) * 360.0 / period)
    return float(
        np.degrees(np.arctan2(np.nanmean(np.sin(ang)), np.nanmean(np.cos(ang))))
        * period
        / 360.0
        % period
    )


def _angle_diff(a: float, b: float, period: float = 360.0) -> float:
    return abs((a - b + period / 2) % period - period / 2)


def _fill_nan(x: np.ndarray) -> np.ndarray:
    ok = np.isfinite(x)
    if ok.all() or not ok.any():
        return x
    idx = np.arange(x.size)
    return np.interp(idx, idx[ok], x[ok])


@dataclass
class _Leg:
    i0: int
    i1: int  # inclusive
    heading_deg: float
    kind: str = ""
    active_s: dict[str, float] = field(default_factory=dict)
    along: tuple[float, float] = (0.0, 0.0)
    offset: float = 0.0
    line_id: str = ""
    calibration_pass: int = 0
    cardinal: str = ""  # heading class relative to the calibration pattern's direction


def _straight_runs(e: np.ndarray, n: np.ndarray, t: np.ndarray, p: SegmentParams) -> list[_Leg]:
    coords = np.column_stack([e, n])
    simple = LineString(coords).simplify(p.simplify_tol_m, preserve_topology=False)
    # map the kept vertices back to epoch indices (they are a subset of the input points)
    lookup: dict[tuple[float, float], list[int]] = {}
    for i, xy in enumerate(map(tuple, coords)):
        lookup.setdefault(xy, []).append(i)
    verts: list[int] = []
    for xy in simple.coords:
        cands = [i for i in lookup.get(tuple(xy), []) if not verts or i > verts[-1]]
        if cands:
            verts.append(cands[0])
    legs = []
    for a, b in zip(verts[:-1], verts[1:], strict=True):
        if t[b] - t[a] >= p.min_leg_s:
            d = coords[b] - coords[a]
            legs.append(_Leg(a, b, float(np.degrees(np.arctan2(d[0], d[1])) % 360)))
    # merge consecutive collinear runs split by a small excursion
    merged: list[_Leg] = []
    for leg in legs:
        if (
            merged
            and leg.i0 == merged[-1].i1
            and _angle_diff(leg.heading_deg, merged[-1].heading_deg) < 3.0
        ):
            prev = merged[-1]
            d = coords[leg.i1] - coords[prev.i0]
            merged[-1] = _Leg(prev.i0, leg.i1, float(np.degrees(np.arctan2(d[0], d[1])) % 360))
        else:
            merged.append(leg)
    return merged


def _refine_ends(
    leg: _Leg, e: np.ndarray, n: np.ndarray, t: np.ndarray, lo: int, hi: int, p: SegmentParams
) -> _Leg:
    """Move each leg end to where the track leaves the leg's line by more than its noise.

    The line is fitted to the leg's central 80 %. Each end first walks outward from the core
    while the track stays within a coarse tolerance above the core's own deviation (manoeuvre
    sway, metres), then back inward to the first epoch within the fine tolerance: 4x the
    track's high-frequency noise, from second differences, which smooth sway does not
    inflate. Leg ends are flown steady, so the fine tolerance finds where the turn begins.
    """
    span = leg.i1 - leg.i0
    core = slice(leg.i0 + span // 10, leg.i1 - span // 10 + 1)
    xy = np.column_stack([e, n])
    x = xy[core]
    centre = x.mean(axis=0)
    _, _, vt = np.linalg.svd(x - centre, full_matrices=False)
    normal = np.array([-vt[0, 1], vt[0, 0]])
    dist = np.abs((xy - centre) @ normal)
    d2 = np.diff((xy[core] - centre) @ normal, 2)
    noise = 1.4826 * np.median(np.abs(d2 - np.median(d2))) / np.sqrt(6.0) if d2.size else 0.0
    fine = max(p.end_tol_floor_m, 4.0 * noise)
    coarse = max(fine, p.simplify_tol_m)  # no in-leg deviation exceeds the simplification tol

    start = core.start
    while start - 1 >= lo and dist[start - 1] <= coarse:
        start -= 1
    while start < core.start and dist[start] > fine:
        start += 1
    end = core.stop - 1
    while end + 1 <= hi and dist[end + 1] <= coarse:
        end += 1
    while end > core.stop - 1 and dist[end] > fine:
        end -= 1
    d = xy[end] - xy[start]
    return _Leg(start, end, float(np.degrees(np.arctan2(d[0], d[1])) % 360))


def _without_turns_in_place(flight: Flight, leg: _Leg, t: np.ndarray, p: SegmentParams) -> _Leg:
    """``leg`` less a turn at either end that the track does not show: a multicopter turns
    in place (hovering) between legs, so its position stays on the leg's line while its
    heading swings by the turn. Such an end, where the heading leaves the leg's own by more
    than ``turn_deg`` up to the leg's end, is cut back to where that swing began
    (:func:`_turn_start`). Legs that would fall under ``min_leg_s`` are kept whole."""
    yaw = flight.data["yaw_deg"].to_numpy()[leg.i0 : leg.i1 + 1]
    if yaw.size < 3 or not np.all(np.isfinite(yaw)):
        return leg
    dev = _deviation(flight, leg, "yaw")
    dev = dev - np.median(dev)  # the leg's own heading, robust to the turn's share
    hi = _turn_start(dev, p.turn_deg)
    lo = dev.size - 1 - _turn_start(dev[::-1], p.turn_deg)  # the same, read backwards
    i0, i1 = leg.i0 + lo, leg.i0 + hi
    if (i0, i1) == (leg.i0, leg.i1) or t[i1] - t[i0] < p.min_leg_s:
        return leg
    return _Leg(i0, i1, leg.heading_deg, kind=leg.kind, line_id=leg.line_id)


def _turn_start(dev: np.ndarray, turn_deg: float) -> int:
    """Index of the last epoch before a turn that ends the series ``dev`` (heading from the
    leg's own, deg): the last passage through the leg's heading before the run of epochs
    beyond ``turn_deg`` that reaches the end. The last index when it ends in no turn."""
    far = np.abs(dev) > turn_deg
    if not far[-1]:
        return dev.size - 1
    first = dev.size - 1 - int(np.argmin(far[::-1]))  # first epoch of the trailing far run
    back = np.flatnonzero(np.sign(dev[:first]) != np.sign(dev[first]))
    return int(back[-1]) if back.size else dev.size - 1


def _deviation(flight: Flight, leg: _Leg, axis: str) -> np.ndarray:
    """Attitude deviation from the leg's own level (yaw: from its mean heading), degrees."""
    col = {"roll": "roll_deg", "pitch": "pitch_deg", "yaw": "yaw_deg"}[axis]
    a = flight.data[col].to_numpy()[leg.i0 : leg.i1 + 1].astype(float)
    if axis == "yaw":
        return np.nan_to_num((a - _circmean_deg(a) + 180.0) % 360.0 - 180.0)
    return np.nan_to_num(a - np.nanmedian(a))


def _activity(flight: Flight, leg: _Leg, p: SegmentParams, rate: float) -> dict[str, np.ndarray]:
    """Oscillation amplitude of roll, pitch and yaw within a leg, degrees.

    The analytic-signal (Hilbert) envelope follows a manoeuvre's amplitude sample by sample,
    where a moving RMS would smear it by half its window; a 1 s mean removes the ripple.
    """
    w = max(int(1.0 * rate), 1)
    return {
        a: uniform_filter1d(np.abs(hilbert(_deviation(flight, leg, a))), w, mode="nearest")
        for a in MANOEUVRES
    }


def _swings(
    flight: Flight, leg: _Leg, act: dict[str, np.ndarray], thr: dict[str, float]
) -> dict[str, int]:
    """Swings of each axis' deviation where it is active: passages from beyond
    +0.75 x its threshold to beyond -0.75 x (or back), counted with that hysteresis.

    Without hysteresis the small wobble of a cruise leg around its level counted as swings
    wherever the envelope of a one-sided excursion (a multicopter's pitch as it stops and
    turns at a line's end) spread over the leg: tie lines were taken for calibration."""
    out = {}
    for axis in MANOEUVRES:
        a = _deviation(flight, leg, axis)
        level = 0.75 * thr[axis]
        side = np.where(a > level, 1, np.where(a < -level, -1, 0))
        side = side[(side != 0) & (act[axis] >= thr[axis])]
        out[axis] = int(np.count_nonzero(side[1:] != side[:-1]))
    return out


def _thresholds(p: SegmentParams) -> dict[str, float]:
    return {"roll": p.roll_active_deg, "pitch": p.pitch_active_deg, "yaw": p.yaw_active_deg}


def _label_manoeuvres(act: dict[str, np.ndarray], p: SegmentParams, rate: float) -> np.ndarray:
    """roll / pitch / yaw / steady for each epoch of a calibration leg."""
    thr = _thresholds(p)
    # an axis is manoeuvring where its amplitude exceeds 15 % of its own peak on this leg
    # (the ramps of a tapered manoeuvre included), and at least half the detection threshold
    rel = {a: max(0.5 * thr[a], 0.15 * float(act[a].max())) for a in MANOEUVRES}
    score = np.stack([act[a] / rel[a] for a in MANOEUVRES])
    best = np.argmax(score, axis=0)
    lab = np.where(score.max(axis=0) >= 1.0, np.array(MANOEUVRES, dtype=object)[best], "steady")
    # runs shorter than 2 s take the label of the longer neighbour
    min_run = max(int(2.0 * rate), 1)
    runs = np.flatnonzero(np.concatenate([[True], lab[1:] != lab[:-1]]))
    bounds = list(runs) + [lab.size]
    for k in range(len(runs)):
        a, b = bounds[k], bounds[k + 1]
        if b - a < min_run:
            left = lab[a - 1] if a > 0 else None
            right = lab[b] if b < lab.size else None
            lab[a:b] = left if left is not None else right
    return lab


def _from_plan(flight: Flight) -> tuple[np.ndarray, np.ndarray]:
    kind = flight.data["plan_kind"].to_numpy().astype(object)
    line = flight.data["plan_line_id"].to_numpy().astype(object)
    kind = np.where(np.isin(kind, LABELS), kind, "transit")
    return kind, line


def segment_flight(
    flight: Flight, params: SegmentParams | None = None, use_plan: bool = True
) -> Segmentation:
    """Label every epoch of ``flight``.

    Needs GNSS position (and attitude for the manoeuvre boxes) unless the recording carries
    ``/plan/line``, whose labels are then used as recorded.

    Raises
    ------
    AeromagError
        Neither ``/plan/line`` nor a position channel is present.
    """
    p = params or SegmentParams()
    d = flight.data
    nep = len(d)
    t = d["time_s"].to_numpy()
    rate = 1.0 / max(float(np.median(np.diff(t))), 1e-6)
    label = np.full(nep, "transit", dtype=object)
    line_id = np.full(nep, "", dtype=object)
    heading = np.full(nep, np.nan)
    manoeuvre = np.full(nep, "", dtype=object)
    cardinal = np.full(nep, "", dtype=object)
    cpass = np.zeros(nep, dtype=int)
    notes: list[str] = []
    has_att = flight.has("roll_deg", "pitch_deg", "yaw_deg")

    if use_plan and flight.has("plan_kind", "plan_line_id"):
        label, line_id = _from_plan(flight)
        source = "plan"
        legs = []
        for lab_run in _runs(label, line_id):
            a, b, lab, lid = lab_run
            leg = _Leg(a, b, float("nan"), kind=lab, line_id=lid)
            if flight.has("lat_deg", "lon_deg"):
                e, n = _local_en(flight)
                dd = np.array([e[b] - e[a], n[b] - n[a]])
                leg.heading_deg = float(np.degrees(np.arctan2(dd[0], dd[1])) % 360)
            elif has_att:
                leg.heading_deg = _circmean_deg(d["yaw_deg"].to_numpy()[a : b + 1])
            legs.append(leg)
        _assign_passes([lg for lg in legs if lg.kind == "calibration"], t, p)
    else:
        if not flight.has("lat_deg", "lon_deg"):
            raise AeromagError(
                "segmentation needs /gnss/fix (or /plan/line) to find the lines",
                file=flight.source,
                channel="/gnss/fix",
            )
        source = "inferred"
        e, n = _local_en(flight)
        runs = _straight_runs(e, n, t, p)
        legs = []
        for k, run in enumerate(runs):
            lo = runs[k - 1].i1 if k > 0 else 0
            hi = runs[k + 1].i0 if k + 1 < len(runs) else nep - 1
            leg = _refine_ends(run, e, n, t, lo, hi, p)
            legs.append(_without_turns_in_place(flight, leg, t, p) if has_att else leg)
        _classify(flight, legs, e, n, t, p, rate, has_att)
        if not has_att:
            notes.append("no /ins/attitude: calibration legs cannot be recognised")

    for leg in legs:
        sl = slice(leg.i0, leg.i1 + 1)
        label[sl] = leg.kind
        line_id[sl] = leg.line_id
        if leg.kind in ("calibration", *SURVEY_BLOCK):
            heading[sl] = leg.heading_deg
        if leg.kind == "calibration":
            cpass[sl] = leg.calibration_pass
            cardinal[sl] = leg.cardinal
            if has_att:
                manoeuvre[sl] = _label_manoeuvres(_activity(flight, leg, p, rate), p, rate)
    if source == "inferred":
        _label_gaps(label, legs)
    return Segmentation(label, line_id, heading, manoeuvre, cardinal, cpass, source, notes)


def _runs(label: np.ndarray, line_id: np.ndarray):
    key = np.array([f"{a}\x00{b}" for a, b in zip(label, line_id, strict=True)], dtype=object)
    starts = np.flatnonzero(np.concatenate([[True], key[1:] != key[:-1]]))
    ends = np.concatenate([starts[1:] - 1, [key.size - 1]])
    for a, b in zip(starts, ends, strict=True):
        yield int(a), int(b), str(label[a]), str(line_id[a])


def _local_en(flight: Flight) -> tuple[np.ndarray, np.ndarray]:
    lat = _fill_nan(flight.data["lat_deg"].to_numpy().astype(float))
    lon = _fill_nan(flight.data["lon_deg"].to_numpy().astype(float))
    try:
        return local_east_north(lat, lon)
    except ValueError:
        raise AeromagError(
            "no valid position in the recording", file=flight.source, channel="/gnss/fix"
        ) from None


def _assign_passes(cal: list[_Leg], t: np.ndarray, p: SegmentParams) -> None:
    # the legs' classes are relative to the box's own direction (a box flown at 45 deg puts
    # its legs on north-based sector boundaries)
    ref = pattern_direction_deg(
        np.array([lg.heading_deg for lg in cal]), np.array([t[lg.i1] - t[lg.i0] for lg in cal])
    )
    npass = 0
    seen: set[str] = set()
    for k, leg in enumerate(cal):
        card = leg.cardinal = cardinal_name(leg.heading_deg, ref)
        # a new pass after a long break, or when a heading comes round again
        if k == 0 or t[leg.i0] - t[cal[k - 1].i1] > p.pass_gap_s or card in seen:
            npass += 1
            seen = set()
        seen.add(card)
        leg.calibration_pass = npass
        if not leg.line_id:
            leg.line_id = f"C{npass}{card}"


def _classify(
    flight: Flight, legs: list[_Leg], e, n, t, p: SegmentParams, rate: float, has_att: bool
) -> None:
    thr = _thresholds(p)
    for leg in legs:
        leg.kind = "transit"
        if has_att:
            act = _activity(flight, leg, p, rate)
            leg.active_s = {a: float((act[a] >= thr[a]).sum() / rate) for a in MANOEUVRES}
            swings = _swings(flight, leg, act, thr)
            # sustained *and* oscillating: a turn's bank is one-sided, a manoeuvre alternates
            if any(
                leg.active_s[a] >= p.min_active_s and swings[a] >= p.min_swings for a in MANOEUVRES
            ):
                leg.kind = "calibration"
    cal = [lg for lg in legs if lg.kind == "calibration"]
    _assign_passes(cal, t, p)
    rest = [lg for lg in legs if lg.kind != "calibration"]
    if not rest:
        return
    length = np.array([np.hypot(e[lg.i1] - e[lg.i0], n[lg.i1] - n[lg.i0]) for lg in rest])
    orient = np.array([lg.heading_deg % 180.0 for lg in rest])
    # Candidate line directions: the 180-deg-periodic directions carrying line length. The
    # longest is not always the survey's: transits, the straights of a distant calibration
    # box and the tie lines can each out-length short survey lines, so every distinct peak
    # is tried and the direction giving the most distinct lines (offsets) on a regular grid
    # inside one block wins (ties: more length): a transit flown out and back, or a box's
    # straights flown on each pass, repeat one offset; a survey steps across its block.
    cand = np.arange(0.0, 180.0, 1.0)
    score = np.array(
        [
            length[np.array([_angle_diff(o, c, 180.0) for o in orient]) <= p.parallel_tol_deg].sum()
            for c in cand
        ]
    )
    peaks: list[float] = []
    for c in cand[np.argsort(-score, kind="stable")]:
        if score[int(c)] <= 0:
            break
        if all(_angle_diff(c, q, 180.0) > 2 * p.parallel_tol_deg for q in peaks):
            peaks.append(float(c))
    best, best_peak = None, None
    for peak in peaks:
        found = _survey_block(rest, e, n, orient, length, peak, p)
        if found is not None and (best is None or found[-2:] > best[-2:]):
            best, best_peak = found, peak
    if best is None:
        return
    if best_peak != peaks[-1]:  # each try re-projects the legs: project on the winner again
        best = _survey_block(rest, e, n, orient, length, best_peak, p)
    survey, spacing, main, along, across, _, _ = best
    for lg in survey:
        lg.kind = "survey"
    offs = np.array([lg.offset for lg in survey])
    lo = float(np.median([lg.along[0] for lg in survey]))
    hi = float(np.median([lg.along[1] for lg in survey]))
    xlo, xhi = offs.min() - spacing / 4, offs.max() + spacing / 4
    for lg in rest:
        if lg.kind == "survey":
            continue
        ang = _angle_diff(lg.heading_deg % 180.0, main, 180.0)
        a_mid = 0.5 * (lg.along[0] + lg.along[1])
        # cross-track extent of a non-parallel leg, from its end points
        c0 = e[lg.i0] * across[0] + n[lg.i0] * across[1]
        c1 = e[lg.i1] * across[0] + n[lg.i1] * across[1]
        crosses = min(max(c0, c1), xhi) - max(min(c0, c1), xlo) > 0.5 * (xhi - xlo)
        if (
            ang >= 90.0 - p.parallel_tol_deg
            and crosses
            and (lo - spacing / 4 <= a_mid <= hi + spacing / 4)
        ):
            lg.kind = "tie"
        elif (
            p.parallel_tol_deg < ang < 90.0 - p.parallel_tol_deg and crosses and (lo <= a_mid <= hi)
        ):
            lg.kind = "validation"
    _keep_block_heights(flight, legs, e, n, t, p)
    _name_lines(rest, spacing)


def _keep_block_heights(
    flight: Flight, legs: list[_Leg], e: np.ndarray, n: np.ndarray, t: np.ndarray, p: SegmentParams
) -> None:
    """Cut each line of the block (survey, tie, validation) to its longest run of epochs at
    the block's heights: the survey lines' median altitude (m) +- 3 robust standard
    deviations (1.4826 MAD) of their altitudes + ``block_height_tol_m``. A cut line's ends
    are refined again on what is left (the line fitted to the whole leg leaned towards the
    cut part); a run shorter than ``min_leg_s`` leaves a transit. A descent to the first
    line flown along its track, or a transit crossing the block at cruise height, is so not
    read as a line; nothing changes without an altitude channel."""
    if not flight.has("alt_m"):
        return
    alt = flight.data["alt_m"].to_numpy(float)
    h = [alt[lg.i0 : lg.i1 + 1] for lg in legs if lg.kind == "survey"]
    h = np.concatenate(h) if h else np.empty(0)
    h = h[np.isfinite(h)]
    if h.size == 0:
        return
    mid = float(np.median(h))
    half = 3.0 * 1.4826 * float(np.median(np.abs(h - mid))) + p.block_height_tol_m

    def level_run(i0: int, i1: int) -> tuple[int, int] | None:
        """The longest run of epochs in i0..i1 at the block's heights (a missing altitude
        does not cut a line)."""
        ok = ~(np.abs(alt[i0 : i1 + 1] - mid) > half)
        edges = np.flatnonzero(np.diff(np.r_[0, ok.astype(np.int8), 0]))
        if edges.size == 0:
            return None
        k = int(np.argmax(edges[1::2] - edges[::2]))
        return i0 + int(edges[2 * k]), i0 + int(edges[2 * k + 1]) - 1

    for k, lg in enumerate(legs):
        if lg.kind not in SURVEY_BLOCK:
            continue
        run = level_run(lg.i0, lg.i1)
        if run == (lg.i0, lg.i1):
            continue  # wholly at the block's heights: the line as it was found
        if run is not None:
            lo = legs[k - 1].i1 if k > 0 else 0
            hi = legs[k + 1].i0 if k + 1 < len(legs) else t.size - 1
            ref = _refine_ends(_Leg(run[0], run[1], lg.heading_deg), e, n, t, lo, hi, p)
            lg.heading_deg = ref.heading_deg
            run = level_run(ref.i0, ref.i1)
        if run is None or t[run[1]] - t[run[0]] < p.min_leg_s:
            lg.kind = "transit"  # named lines only come after this (``_name_lines``)
        else:
            lg.i0, lg.i1 = run


def _survey_block(
    rest: list[_Leg],
    e: np.ndarray,
    n: np.ndarray,
    orient: np.ndarray,
    length: np.ndarray,
    peak_deg: float,
    p: SegmentParams,
):
    """The survey lines if the lines run along ``peak_deg`` (mod 180): parallel legs that
    share the block's along-track extent and sit on the line-spacing grid. Sets each leg's
    ``along`` extent and cross-track ``offset`` for that direction. Returns ``(lines,
    spacing_m, direction_deg, along, across, distinct_lines, length_m)`` or None (too few
    lines); a line flown twice at one offset is one of ``distinct_lines``."""
    near = np.array([_angle_diff(o, peak_deg, 180.0) <= p.parallel_tol_deg for o in orient])
    # refine about the length-weighted mean of the legs near the peak, then re-select
    w = length[near]
    main = _circmean_deg(
        np.repeat(orient[near], np.maximum(1, (w / w.max() * 20).astype(int))), 180.0
    )
    near = np.array([_angle_diff(o, main, 180.0) <= p.parallel_tol_deg for o in orient])
    along = np.array([np.sin(np.radians(main)), np.cos(np.radians(main))])
    across = np.array([along[1], -along[0]])
    for lg in rest:
        a0 = e[lg.i0] * along[0] + n[lg.i0] * along[1]
        a1 = e[lg.i1] * along[0] + n[lg.i1] * along[1]
        lg.along = (min(a0, a1), max(a0, a1))
        mid = (lg.i0 + lg.i1) // 2
        lg.offset = e[mid] * across[0] + n[mid] * across[1]
    par = [lg for lg, ok in zip(rest, near, strict=True) if ok]
    if not par:
        return None
    # the survey block: the along-track extent shared by most parallel lines
    lo = float(np.median([lg.along[0] for lg in par]))
    hi = float(np.median([lg.along[1] for lg in par]))
    survey = [lg for lg in par if min(lg.along[1], hi) - max(lg.along[0], lo) >= 0.5 * (hi - lo)]
    if len(survey) < p.min_survey_lines:
        return None
    # Survey lines sit on the line-spacing grid; a straight flown along the block edge between
    # two other lines (a turn) does not.
    offs = np.array([lg.offset for lg in survey])
    uniq = np.unique(np.round(offs / 5.0) * 5.0)
    spacing = float(np.median(np.diff(uniq))) if uniq.size > 1 else 0.0
    if spacing > 0:

        def grid_miss(ref: float) -> np.ndarray:
            frac = (offs - ref) / spacing
            return np.abs(frac - np.round(frac)) * spacing

        # the grid passes through the line offset that puts the most lines on it
        ref = max(offs, key=lambda r: int((grid_miss(r) <= spacing / 4).sum()))
        on_grid = grid_miss(ref) <= spacing / 4
        survey = [lg for lg, ok in zip(survey, on_grid, strict=True) if ok]
    # lines flown twice at one offset (a repeat) count once
    distinct = (
        np.unique(np.round(np.array([lg.offset for lg in survey]) / max(spacing, 1.0) * 2))
        if survey
        else []
    )
    if len(distinct) < p.min_survey_lines:
        return None
    # a block's lines fill its grid: legs whose offsets leave most grid positions between
    # them empty (a transit out and back and a box's straights, a few metres apart on a
    # grid of that step) are not one
    if spacing > 0 and len(distinct) < p.min_grid_fill * (np.ptp(distinct) / 2 + 1):
        return None
    total = float(sum(np.hypot(e[lg.i1] - e[lg.i0], n[lg.i1] - n[lg.i0]) for lg in survey))
    return survey, spacing, main, along, across, len(distinct), total


def _name_lines(legs: list[_Leg], spacing: float) -> None:
    def cluster(values: list[float], tol: float) -> list[int]:
        order = np.argsort(values)
        ids = [0] * len(values)
        cur, last = 0, None
        for i in order:
            if last is not None and values[i] - last > tol:
                cur += 1
            ids[i] = cur
            last = values[i]
        return ids

    for kind, prefix, key in (("survey", "L", "offset"), ("tie", "T", "along_mid")):
        group = [lg for lg in legs if lg.kind == kind]
        if not group:
            continue
        vals = [lg.offset if key == "offset" else 0.5 * (lg.along[0] + lg.along[1]) for lg in group]
        tol = max(spacing / 4, 5.0) if kind == "survey" else max(spacing, 20.0)
        ids = cluster(vals, tol)
        seen: dict[int, int] = {}
        for lg, k in zip(group, ids, strict=True):
            seen[k] = seen.get(k, 0) + 1
            lg.line_id = f"{prefix}{10 * (k + 1):04d}" + (f"-{seen[k]}" if seen[k] > 1 else "")
    for k, lg in enumerate([lg for lg in legs if lg.kind == "validation"]):
        lg.line_id = f"V{10 * (k + 1):04d}"


def _label_gaps(label: np.ndarray, legs: list[_Leg]) -> None:
    """Epochs between lines: a turn within a block (survey area, or one calibration pass),
    else transit. Straight transit legs between two lines of one block are part of the turn."""
    lines = [lg for lg in legs if lg.kind != "transit"]
    for prev, nxt in zip(lines[:-1], lines[1:], strict=True):
        gap = slice(prev.i1 + 1, nxt.i0)
        same = (prev.kind in SURVEY_BLOCK and nxt.kind in SURVEY_BLOCK) or (
            prev.kind == nxt.kind == "calibration" and prev.calibration_pass == nxt.calibration_pass
        )
        label[gap] = "turn" if same else "transit"
