"""Tie-line leveling: crossover differences and a least-squares per-line adjustment.

A crossing of two flown tracks is where their polylines intersect **and** the tracks meet at
``min_crossing_angle_deg`` or more (:func:`crossing_points`). Two noisy, nearly parallel tracks
(a transit flown along a tie line, two passes over one point) otherwise "cross" wherever the
noise makes them wiggle across each other, hundreds of times.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from shapely import LineString, MultiPoint, Point

from pipeline.defaults import default_value

# the shallowest angle at which two tracks count as crossing (map.min_crossing_angle_deg)
MIN_CROSSING_ANGLE_DEG: float = default_value("map", "min_crossing_angle_deg")
# a track's local direction at a crossing: the principal axis of its samples from the last
# one at least this far (straight line, m) and CHORD_SAMPLES samples before the crossing to
# the first one as far after it, so that position noise on one short segment (or a hover at a
# line end) does not decide the angle
CHORD_M = 10.0
CHORD_SAMPLES = 3
# hits of one pair of tracks this close (m, divided by the sine of the crossing angle: noise
# spreads the hits of a shallow crossing along the tracks), or this few samples apart on both
# tracks, are one crossing that noise made wiggle
MERGE_M = 5.0
MERGE_SAMPLES = 3
# samples either side of a crossing searched first for the chord's ends (the whole track
# only when they are not there): a track's local direction should not cost its length
_NEAR_SAMPLES = 64


@dataclass
class Line:
    """One flown line: positions (local east/north m), time (s) and field values (nT)."""

    line_id: str
    kind: str  # survey | tie | validation
    east_m: np.ndarray
    north_m: np.ndarray
    time_s: np.ndarray
    value_nT: np.ndarray
    index: np.ndarray  # epoch indices in the flight

    def __post_init__(self) -> None:
        d = np.hypot(np.diff(self.east_m), np.diff(self.north_m))
        self.along_m = np.r_[0.0, np.cumsum(d)]

    @classmethod
    def from_track(cls, track, time_s: np.ndarray, value_nT: np.ndarray) -> Line:
        """A flight track (``line_id``, ``kind``, ``east_m``, ``north_m`` and the flight
        epochs ``index``, e.g. :func:`pipeline.quality.stage.flight_tracks`'s) with the
        flight's times (s) and field values (nT) on its epochs."""
        ix = track.index
        return cls(
            track.line_id, track.kind, track.east_m, track.north_m, time_s[ix], value_nT[ix], ix
        )

    def geometry(self) -> LineString:
        """The track as a shapely LineString in local east/north metres."""
        return LineString(np.column_stack([self.east_m, self.north_m]))

    def at(self, distance_m: float) -> tuple[float, float]:
        """(value, time) interpolated along track at ``distance_m``."""
        return (
            float(np.interp(distance_m, self.along_m, self.value_nT)),
            float(np.interp(distance_m, self.along_m, self.time_s)),
        )


@dataclass
class Crossover:
    """Where two lines cross: both fields interpolated along track to the crossing."""

    line_a: str
    line_b: str
    east_m: float
    north_m: float
    value_a_nT: float
    value_b_nT: float
    time_a_s: float
    time_b_s: float
    angle_deg: float = float("nan")  # between the local track directions, 0..90

    @property
    def difference_nT(self) -> float:
        """Line a's value minus line b's at the crossing, nT."""
        return self.value_a_nT - self.value_b_nT


def intersection_points(geom) -> list[Point]:
    """The points of a shapely intersection result (point, multipoint or collection)."""
    if geom.is_empty:
        return []
    if isinstance(geom, Point):
        return [geom]
    if isinstance(geom, MultiPoint):
        return list(geom.geoms)
    return [g for g in getattr(geom, "geoms", []) if isinstance(g, Point)]


@dataclass
class Crossing:
    """Where two tracks cross: the point, the distance along either track, the angle."""

    east_m: float
    north_m: float
    along_a_m: float
    along_b_m: float
    angle_deg: float


def _local_direction(
    east: np.ndarray, north: np.ndarray, along: np.ndarray, x: float, y: float, s: float
) -> tuple[np.ndarray, float]:
    """The track's direction at the point (x, y) that lies ``s`` m along it (principal axis
    of the samples CHORD_M and CHORD_SAMPLES either side), and the point's distance (straight
    line, m) to the nearer of the track's first and last sample."""
    n = east.size
    k = int(np.clip(np.searchsorted(along, s, side="right") - 1, 0, n - 2))  # segment k, k+1

    def dist(lo: int, hi: int) -> np.ndarray:
        return np.hypot(east[lo:hi] - x, north[lo:hi] - y)

    stop = max(k + 2 - CHORD_SAMPLES, 0)  # samples 0 .. stop-1 are CHORD_SAMPLES or more before
    start = k + CHORD_SAMPLES
    # the chord's ends are near the crossing: look there first, the whole track only if not
    lo = max(stop - _NEAR_SAMPLES, 0)
    back = np.flatnonzero(dist(lo, stop) >= CHORD_M) + lo
    if not back.size and lo > 0:
        back = np.flatnonzero(dist(0, stop) >= CHORD_M)
    i = int(back[-1]) if back.size else 0
    hi = min(start + _NEAR_SAMPLES, n)
    ahead = np.flatnonzero(dist(start, hi) >= CHORD_M) + start if start < n else np.zeros(0, int)
    if not ahead.size and hi < n:
        ahead = np.flatnonzero(dist(start, n) >= CHORD_M) + start
    j = int(ahead[0]) if ahead.size else n - 1
    to_end = float(min(np.hypot(east[0] - x, north[0] - y), np.hypot(east[-1] - x, north[-1] - y)))
    xy = np.column_stack([east[i : j + 1], north[i : j + 1]])
    xy = xy - xy.mean(axis=0)
    if not np.any(xy):
        return np.zeros(2), to_end
    return np.linalg.svd(xy, full_matrices=False)[2][0], to_end


def _angle_deg(u: np.ndarray, v: np.ndarray) -> float:
    """The angle between two undirected directions, 0..90 degrees (0 if either is zero)."""
    nu, nv = float(np.hypot(*u)), float(np.hypot(*v))
    if nu == 0.0 or nv == 0.0:
        return 0.0
    c = min(abs(float(u @ v)) / (nu * nv), 1.0)
    return float(np.degrees(np.arccos(c)))


def _reach_m(angle_deg):
    """How far apart noise spreads the hits of one crossing at ``angle_deg``: MERGE_M at right
    angles, more as the tracks get more parallel."""
    return MERGE_M / np.sin(np.radians(np.clip(angle_deg, 1.0, 90.0)))


def _merge(hits: list[Crossing], along_a: np.ndarray, along_b: np.ndarray) -> list[Crossing]:
    """One crossing per group of hits closer than MERGE_M / sin(angle) or MERGE_SAMPLES
    samples on both tracks (single linkage); the group's middle hit along track ``a``
    represents it."""
    if len(hits) < 2:
        return hits
    hits = sorted(hits, key=lambda h: h.along_a_m)
    xy = np.array([[h.east_m, h.north_m] for h in hits])
    reach = _reach_m(np.array([h.angle_deg for h in hits]))
    ka = np.searchsorted(along_a, [h.along_a_m for h in hits])
    kb = np.searchsorted(along_b, [h.along_b_m for h in hits])
    dist = np.hypot(xy[:, None, 0] - xy[None, :, 0], xy[:, None, 1] - xy[None, :, 1])
    close = (dist <= np.maximum(reach[:, None], reach[None])) | (
        (np.abs(ka[:, None] - ka[None]) <= MERGE_SAMPLES)
        & (np.abs(kb[:, None] - kb[None]) <= MERGE_SAMPLES)
    )
    group = np.full(len(hits), -1)
    for g in range(len(hits)):
        if group[g] >= 0:
            continue
        todo, group[g] = [g], g
        while todo:
            m = todo.pop()
            new = np.flatnonzero(close[m] & (group < 0))
            group[new] = g
            todo.extend(new.tolist())
    out = []
    for g in np.unique(group):
        members = np.flatnonzero(group == g)
        out.append(hits[members[members.size // 2]])
    return out


def crossing_points(
    a,
    b,
    min_angle_deg: float = MIN_CROSSING_ANGLE_DEG,
    geom_a: LineString | None = None,
    geom_b: LineString | None = None,
) -> list[Crossing]:
    """The crossings of two tracks (anything with ``east_m``, ``north_m``, ``along_m``).

    Exact polyline intersections, kept where the local track directions (over CHORD_M and
    CHORD_SAMPLES either side) meet at ``min_angle_deg`` or more, and not where both
    tracks end (one leg turning into the next, a hover between them: within CHORD_M, or the
    merge reach of a shallow crossing, of an end of each); hits of the same crossing that
    position noise made wiggle are merged into one.
    """
    ga = geom_a if geom_a is not None else LineString(np.column_stack([a.east_m, a.north_m]))
    gb = geom_b if geom_b is not None else LineString(np.column_stack([b.east_m, b.north_m]))
    if not ga.intersects(gb):
        return []
    hits = []
    for pt in intersection_points(ga.intersection(gb)):
        sa, sb = ga.project(pt), gb.project(pt)
        da, end_a = _local_direction(a.east_m, a.north_m, a.along_m, pt.x, pt.y, sa)
        db, end_b = _local_direction(b.east_m, b.north_m, b.along_m, pt.x, pt.y, sb)
        angle = _angle_deg(da, db)
        corner = max(end_a, end_b) < max(CHORD_M, float(_reach_m(angle)))
        if angle >= min_angle_deg and not corner:
            hits.append(Crossing(pt.x, pt.y, sa, sb, angle))
    return _merge(hits, a.along_m, b.along_m)


# where two sets of tracks cross, by (kind, line id) of either track: geometry only
CrossingMap = dict[tuple[str, str, str, str], list[Crossing]]


def _pair_key(a, b) -> tuple[str, str, str, str]:
    return (a.kind, a.line_id, b.kind, b.line_id)


def track_crossings(
    tracks_a: list, tracks_b: list, min_angle_deg: float = MIN_CROSSING_ANGLE_DEG
) -> CrossingMap:
    """:func:`crossing_points` of every track of ``tracks_a`` with every track of
    ``tracks_b`` (anything with ``kind``, ``line_id``, ``east_m``, ``north_m``, ``along_m``):
    the geometry every field read along the same tracks shares, so that the crossovers of
    several fields (:func:`crossovers`' ``crossings``) find it once."""
    out: CrossingMap = {}
    geoms_b = [(tb, LineString(np.column_stack([tb.east_m, tb.north_m]))) for tb in tracks_b]
    for ta in tracks_a:
        ga = LineString(np.column_stack([ta.east_m, ta.north_m]))
        for tb, gb in geoms_b:
            if ta is not tb:
                out[_pair_key(ta, tb)] = crossing_points(ta, tb, min_angle_deg, ga, gb)
    return out


def crossovers(
    lines_a: list[Line],
    lines_b: list[Line],
    min_angle_deg: float = MIN_CROSSING_ANGLE_DEG,
    crossings: CrossingMap | None = None,
) -> list[Crossover]:
    """Track crossings (:func:`crossing_points`) of every line of ``lines_a`` with every line
    of ``lines_b``, both fields interpolated along track to the crossing.

    ``crossings``: :func:`track_crossings` of the tracks these lines were read along (same
    positions, same ``min_angle_deg``); a pair of lines it lacks is intersected here.
    """
    out = []
    geoms: dict[int, LineString] = {}

    def geometry(line: Line) -> LineString:
        if id(line) not in geoms:
            geoms[id(line)] = line.geometry()
        return geoms[id(line)]

    for la in lines_a:
        for lb in lines_b:
            if la is lb:
                continue
            found = None if crossings is None else crossings.get(_pair_key(la, lb))
            if found is None:
                found = crossing_points(la, lb, min_angle_deg, geometry(la), geometry(lb))
            for c in found:
                va, ta = la.at(c.along_a_m)
                vb, tb = lb.at(c.along_b_m)
                if np.isfinite(va) and np.isfinite(vb):
                    out.append(
                        Crossover(
                            la.line_id, lb.line_id, c.east_m, c.north_m, va, vb, ta, tb, c.angle_deg
                        )
                    )
    return out


@dataclass
class Leveling:
    """Per-line corrections; ``correction(line_id, t)`` is subtracted from the line."""

    offsets: dict[str, tuple[float, float, float]]  # line -> (dc nT, slope nT/s, t_ref s)
    rms_before_nT: float
    rms_after_nT: float
    crossovers: list[Crossover] = field(default_factory=list)
    residuals_nT: np.ndarray | None = None

    def correction(self, line_id: str, time_s: np.ndarray) -> np.ndarray:
        """Correction (nT) of line ``line_id`` at times ``time_s`` (s): dc + slope (t - t_ref); zero
        for a line without an adjustment.
        """
        dc, slope, t0 = self.offsets.get(line_id, (0.0, 0.0, 0.0))
        return dc + slope * (np.asarray(time_s) - t0)

    def to_dict(self) -> dict:
        """JSON-ready summary: crossover count, RMS before and after, mean and standard deviation of
        the crossover differences before (nT), per-line offsets (nT) and slopes (nT/s).
        """
        diffs = np.array([c.difference_nT for c in self.crossovers])
        return {
            "crossovers": len(self.crossovers),
            "rms_before_nT": self.rms_before_nT,
            "rms_after_nT": self.rms_after_nT,
            "mean_before_nT": float(diffs.mean()) if diffs.size else None,
            "std_before_nT": float(diffs.std()) if diffs.size else None,
            "offsets_nT": {k: v[0] for k, v in self.offsets.items()},
            "slopes_nT_per_s": {k: v[1] for k, v in self.offsets.items()},
        }


def level_lines(
    lines: list[Line],
    trend: bool = False,
    min_angle_deg: float = MIN_CROSSING_ANGLE_DEG,
    crossings: CrossingMap | None = None,
) -> Leveling:
    """Least-squares line corrections from survey-tie crossovers (``crossings``: as
    :func:`crossovers`').

    Every crossover says value_a - corr_a(t_a) = value_b - corr_b(t_b). The corrections are a
    DC per line (plus, with ``trend``, a slope in time about the line's mid-time); the system
    fixes them only up to a common constant, so the minimum-norm solution is taken (the mean
    level is kept). Only tracks meeting at ``min_angle_deg`` or more cross.
    """
    survey = [ln for ln in lines if ln.kind == "survey"]
    ties = [ln for ln in lines if ln.kind == "tie"]
    xs = crossovers(survey, ties, min_angle_deg, crossings)
    ids = sorted({ln.line_id for ln in survey + ties})
    col = {lid: i for i, lid in enumerate(ids)}
    tref = {ln.line_id: float(np.median(ln.time_s)) for ln in survey + ties}
    npar = len(ids) * (2 if trend else 1)
    diffs = np.array([c.difference_nT for c in xs])
    rms_before = float(np.sqrt(np.mean(diffs**2))) if xs else float("nan")
    if not xs:
        return Leveling({}, rms_before, rms_before, xs)
    a = np.zeros((len(xs), npar))
    for r, c in enumerate(xs):
        ia, ib = col[c.line_a], col[c.line_b]
        a[r, ia], a[r, ib] = 1.0, -1.0
        if trend:
            a[r, len(ids) + ia] = c.time_a_s - tref[c.line_a]
            a[r, len(ids) + ib] = -(c.time_b_s - tref[c.line_b])
    sol, *_ = np.linalg.lstsq(a, diffs, rcond=None)
    resid = diffs - a @ sol
    offsets = {
        lid: (float(sol[col[lid]]), float(sol[len(ids) + col[lid]]) if trend else 0.0, tref[lid])
        for lid in ids
    }
    return Leveling(offsets, rms_before, float(np.sqrt(np.mean(resid**2))), xs, resid)
