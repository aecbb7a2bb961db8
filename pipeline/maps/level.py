"""Tie-line leveling: crossover differences and a least-squares per-line adjustment."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from shapely import LineString, MultiPoint, Point


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

    def geometry(self) -> LineString:
        return LineString(np.column_stack([self.east_m, self.north_m]))

    def at(self, distance_m: float) -> tuple[float, float]:
        """(value, time) interpolated along track at ``distance_m``."""
        return (float(np.interp(distance_m, self.along_m, self.value_nT)),
                float(np.interp(distance_m, self.along_m, self.time_s)))


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

    @property
    def difference_nT(self) -> float:
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


def crossovers(lines_a: list[Line], lines_b: list[Line]) -> list[Crossover]:
    """Exact track intersections between every line of ``lines_a`` and of ``lines_b``."""
    out = []
    geoms_b = [(lb, lb.geometry()) for lb in lines_b]
    for la in lines_a:
        ga = la.geometry()
        for lb, gb in geoms_b:
            if la is lb or not ga.intersects(gb):
                continue
            for pt in intersection_points(ga.intersection(gb)):
                va, ta = la.at(ga.project(pt))
                vb, tb = lb.at(gb.project(pt))
                if np.isfinite(va) and np.isfinite(vb):
                    out.append(Crossover(la.line_id, lb.line_id, pt.x, pt.y, va, vb, ta, tb))
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
        dc, slope, t0 = self.offsets.get(line_id, (0.0, 0.0, 0.0))
        return dc + slope * (np.asarray(time_s) - t0)

    def to_dict(self) -> dict:
        diffs = np.array([c.difference_nT for c in self.crossovers])
        return {"crossovers": len(self.crossovers), "rms_before_nT": self.rms_before_nT,
                "rms_after_nT": self.rms_after_nT,
                "mean_before_nT": float(diffs.mean()) if diffs.size else None,
                "std_before_nT": float(diffs.std()) if diffs.size else None,
                "offsets_nT": {k: v[0] for k, v in self.offsets.items()},
                "slopes_nT_per_s": {k: v[1] for k, v in self.offsets.items()}}


def level_lines(lines: list[Line], trend: bool = False) -> Leveling:
    """Least-squares line corrections from survey-tie crossovers.

    Every crossover says value_a - corr_a(t_a) = value_b - corr_b(t_b). The corrections are a
    DC per line (plus, with ``trend``, a slope in time about the line's mid-time); the system
    fixes them only up to a common constant, so the minimum-norm solution is taken (the mean
    level is kept).
    """
    survey = [ln for ln in lines if ln.kind == "survey"]
    ties = [ln for ln in lines if ln.kind == "tie"]
    xs = crossovers(survey, ties)
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
    offsets = {lid: (float(sol[col[lid]]), float(sol[len(ids) + col[lid]]) if trend else 0.0,
                     tref[lid]) for lid in ids}
    return Leveling(offsets, rms_before, float(np.sqrt(np.mean(resid**2))), xs, resid)
