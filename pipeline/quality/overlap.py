"""Overlap points between the validation ("X") lines and the map lines.

Two kinds, as in paper 002 §3.2 and survey practice:

* **intersections**: the exact crossing of two flown tracks (shapely/GEOS polyline
  intersection) that meet at ``min_crossing_angle_deg`` or more
  (:func:`pipeline.maps.level.crossing_points`: nearly parallel noisy tracks do not count, the
  hits of one noisy crossing are one); each field is interpolated along either track to the
  crossing, so the two values refer to the same point and only the heading-dependent error
  and noise remain;
* **pairs**: a validation sample and a map sample closer than a distance threshold
  (0.5 m in the paper), compared as measured.

Positions are east/north metres of the map frame (:class:`pipeline.geo.projected.GridFrame`).
The geometry is found once; :meth:`OverlapSet.differences` then evaluates any field (raw, each
compensation model) on it, so every processing state is compared at exactly the same points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats
from scipy.spatial import cKDTree
from shapely import LineString

from pipeline.geo.heading import heading_class, pattern_direction_deg
from pipeline.maps.level import MIN_CROSSING_ANGLE_DEG, crossing_points


@dataclass
class Track:
    """A flown straight line: its epochs (indices into the flight) and local positions (m).

    ``heading_deg`` is the leg's mean track direction, clockwise from north (NED).
    """

    line_id: str
    kind: str  # survey | tie | validation
    index: np.ndarray
    east_m: np.ndarray
    north_m: np.ndarray
    heading_deg: float

    def __post_init__(self) -> None:
        self.along_m = np.r_[0.0, np.cumsum(np.hypot(np.diff(self.east_m), np.diff(self.north_m)))]

    def geometry(self) -> LineString:
        """The track as a shapely LineString in local east/north metres."""
        return LineString(np.column_stack([self.east_m, self.north_m]))

    def bracket(self, distance_m: float) -> tuple[int, int, float]:
        """The two epochs around ``distance_m`` along track and the weight of the second."""
        k = int(np.clip(np.searchsorted(self.along_m, distance_m) - 1, 0, self.along_m.size - 2))
        span = self.along_m[k + 1] - self.along_m[k]
        w = float(np.clip((distance_m - self.along_m[k]) / span, 0.0, 1.0)) if span > 0 else 0.0
        return int(self.index[k]), int(self.index[k + 1]), w


@dataclass
class OverlapSet:
    """Overlap points of one kind; ``a`` = validation side, ``b`` = map side.

    Each side is two epochs and a weight (equal epochs and weight 0 for a pair): a field's
    value there is ``(1 - w) f[i0] + w f[i1]``.
    """

    kind: str  # intersection | pair
    a0: np.ndarray
    a1: np.ndarray
    wa: np.ndarray
    b0: np.ndarray
    b1: np.ndarray
    wb: np.ndarray
    east_m: np.ndarray
    north_m: np.ndarray
    distance_m: np.ndarray
    validation_line: np.ndarray
    map_line: np.ndarray
    validation_heading_deg: np.ndarray
    map_heading_deg: np.ndarray

    @property
    def count(self) -> int:
        """Number of overlap points."""
        return int(self.a0.size)

    def values(self, field: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(validation value, map value) of ``field`` (one value per flight epoch)."""
        f = np.asarray(field, float)
        va = (1 - self.wa) * f[self.a0] + self.wa * f[self.a1]
        vb = (1 - self.wb) * f[self.b0] + self.wb * f[self.b1]
        return va, vb

    def differences(self, field: np.ndarray) -> np.ndarray:
        """B_validation - B_map at every point (NaN where the field is missing)."""
        va, vb = self.values(field)
        return va - vb

    def validation_epoch(self) -> np.ndarray:
        """The (fractional) flight epoch of each point on the validation side."""
        return (1 - self.wa) * self.a0 + self.wa * self.a1


def _empty(kind: str) -> OverlapSet:
    z, zf, zs = np.zeros(0, int), np.zeros(0), np.zeros(0, dtype=object)
    return OverlapSet(kind, z, z, zf, z, z, zf, zf, zf, zf, zs, zs, zf, zf)


def _build(kind: str, rows: list[tuple]) -> OverlapSet:
    if not rows:
        return _empty(kind)
    cols = list(zip(*rows, strict=True))
    ints = [np.asarray(c, int) for c in (cols[0], cols[1], cols[3], cols[4])]
    return OverlapSet(
        kind,
        ints[0],
        ints[1],
        np.asarray(cols[2], float),
        ints[2],
        ints[3],
        np.asarray(cols[5], float),
        *(np.asarray(c, float) for c in cols[6:9]),
        np.asarray(cols[9], dtype=object),
        np.asarray(cols[10], dtype=object),
        np.asarray(cols[11], float),
        np.asarray(cols[12], float),
    )


def track_intersections(
    validation: list[Track], mapped: list[Track], min_angle_deg: float = MIN_CROSSING_ANGLE_DEG
) -> OverlapSet:
    """Exact crossings of every validation track with every map track that meet at
    ``min_angle_deg`` or more (one per crossing, however noise makes the tracks wiggle)."""
    rows = []
    geoms = [(t, t.geometry()) for t in mapped]
    for v in validation:
        gv = v.geometry()
        for m, gm in geoms:
            for c in crossing_points(v, m, min_angle_deg, gv, gm):
                a0, a1, wa = v.bracket(c.along_a_m)
                b0, b1, wb = m.bracket(c.along_b_m)
                rows.append(
                    (
                        a0,
                        a1,
                        wa,
                        b0,
                        b1,
                        wb,
                        c.east_m,
                        c.north_m,
                        0.0,
                        v.line_id,
                        m.line_id,
                        v.heading_deg,
                        m.heading_deg,
                    )
                )
    rows.sort(key=lambda r: r[0] + r[2])
    return _build("intersection", rows)


def overlap_pairs(
    validation: list[Track], mapped: list[Track], max_distance_m: float = 0.5
) -> OverlapSet:
    """Every (validation sample, map sample) pair closer than ``max_distance_m``."""
    if not validation or not mapped or max_distance_m <= 0:
        return _empty("pair")

    def stack(tracks):
        xy = np.column_stack(
            [
                np.concatenate([t.east_m for t in tracks]),
                np.concatenate([t.north_m for t in tracks]),
            ]
        )
        owner = np.concatenate([np.full(t.index.size, k) for k, t in enumerate(tracks)])
        return xy, np.concatenate([t.index for t in tracks]), owner

    vxy, vidx, vown = stack(validation)
    mxy, midx, mown = stack(mapped)
    d = cKDTree(vxy).sparse_distance_matrix(cKDTree(mxy), max_distance_m, output_type="ndarray")
    d = np.sort(d, order=["i", "j"])
    rows = []
    for i, j, dist in zip(d["i"], d["j"], d["v"], strict=True):
        v, m = validation[vown[i]], mapped[mown[j]]
        rows.append(
            (
                vidx[i],
                vidx[i],
                0.0,
                midx[j],
                midx[j],
                0.0,
                vxy[i, 0],
                vxy[i, 1],
                float(dist),
                v.line_id,
                m.line_id,
                v.heading_deg,
                m.heading_deg,
            )
        )
    return _build("pair", rows)


def difference_stats(diff: np.ndarray) -> dict[str, float | int | None]:
    """RMS, mean, standard deviation and count of the finite differences (nT)."""
    d = np.asarray(diff, float)
    d = d[np.isfinite(d)]
    if d.size == 0:
        return {"rms_nT": None, "mean_nT": None, "std_nT": None, "count": 0}
    return {
        "rms_nT": float(np.sqrt(np.mean(d**2))),
        "mean_nT": float(d.mean()),
        "std_nT": float(d.std(ddof=1)) if d.size > 1 else 0.0,
        "count": int(d.size),
    }


def heading_sector(
    heading_deg: np.ndarray, step_deg: float = 45.0, reference_deg: float = 0.0
) -> np.ndarray:
    """Centre of each heading's ``step_deg`` sector around ``reference_deg``, as '000', '045',
    ... (deg clockwise from north)."""
    k = heading_class(heading_deg, reference_deg, step_deg)
    h = np.mod(reference_deg + k * step_deg, 360.0)
    return np.array([f"{v:03.0f}" for v in h])


def group_stats(diff: np.ndarray, ov: OverlapSet, confidence: float = 0.95) -> list[dict]:
    """The difference's DC offset per (validation heading, map heading) combination.

    A heading error shows as a mean that depends on the pair of headings; the interval is
    Student's t on the group's scatter (``ci_nT`` is its half-width).
    """
    if ov.count == 0:
        return []
    # sectors centred on the survey's own line direction (a survey flown at 22.5 deg would
    # otherwise put its lines on north-based sector boundaries)
    ref = pattern_direction_deg(ov.map_heading_deg)
    va = heading_sector(ov.validation_heading_deg, reference_deg=ref)
    vm = heading_sector(ov.map_heading_deg, reference_deg=ref)
    out = []
    for key in sorted(set(zip(va, vm, strict=True))):
        sel = (va == key[0]) & (vm == key[1]) & np.isfinite(diff)
        d = diff[sel]
        if d.size == 0:
            continue
        ci = (
            float(stats.t.ppf(0.5 + confidence / 2, d.size - 1) * d.std(ddof=1) / np.sqrt(d.size))
            if d.size > 1
            else None
        )
        out.append(
            {
                "validation_heading_deg": float(key[0]),
                "map_heading_deg": float(key[1]),
                "count": int(d.size),
                "mean_nT": float(d.mean()),
                "ci_nT": ci,
                "confidence": confidence,
            }
        )
    return out


def along_track_slopes(track: Track, values: np.ndarray, half_span_m: float) -> np.ndarray:
    """The field's slope along ``track`` at each of its samples (nT/m), and the track's
    direction there (unit east/north): least-squares lines of the field and of the
    positions against the distance along track over the samples within ``half_span_m``.

    Parameters
    ----------
    track : Track
        A straight line (positions in the map frame's east/north metres).
    values : ndarray
        The field at the track's samples (nT; NaN: missing).
    half_span_m : float
        Half the window along track (m); at least 2.5 sample spacings (3 samples at an end).

    Returns
    -------
    ndarray, shape (k, 3)
        Per sample: the slope (nT/m) and the direction (east, north); NaN where the window
        holds fewer than 3 finite samples.
    """
    s = track.along_m - track.along_m.mean()  # centred: the sums below lose no digits
    f = np.asarray(values, float)
    ok = np.isfinite(f)
    if s.size > 1:  # a fast carrier sampled slowly: still three samples at a line's end
        half_span_m = max(half_span_m, 2.5 * float(np.median(np.diff(s))))
    lo = np.searchsorted(s, s - half_span_m, side="left")
    hi = np.searchsorted(s, s + half_span_m, side="right")

    def window_sum(x: np.ndarray) -> np.ndarray:
        c = np.r_[0.0, np.cumsum(np.where(ok, x, 0.0))]
        return c[hi] - c[lo]

    e = track.east_m - track.east_m.mean()
    n_ = track.north_m - track.north_m.mean()
    fc = np.where(ok, f - np.nanmean(f) if ok.any() else 0.0, 0.0)
    count = window_sum(np.ones_like(s))
    ms = window_sum(s) / np.maximum(count, 1)
    sxx = window_sum(s * s) - count * ms**2
    out = np.full((s.size, 3), np.nan)
    good = (count >= 3) & (sxx > 0)
    for k, y in enumerate((fc, e, n_)):
        sxy = window_sum(s * y) - ms * window_sum(y)
        out[good, k] = sxy[good] / sxx[good]
    norm = np.hypot(out[:, 1], out[:, 2])
    out[:, 1:] /= norm[:, None]
    return out


def gradient_removed_differences(
    pairs: OverlapSet,
    tracks: list[Track],
    field: np.ndarray,
    half_span_m: float,
    min_angle_deg: float = MIN_CROSSING_ANGLE_DEG,
) -> np.ndarray:
    """B_validation - B_map at each pair less the field's own change across the pair's
    offset, grad F . (p_validation - p_map) (nT).

    A pair compares samples up to ``overlap_m`` apart as measured, so a survey's gradient
    (a regional 0.5 nT/m over 0.5 m: 0.25 nT) adds to the heading error it is meant to
    show. The horizontal gradient at a pair comes from the field's slopes along its two
    tracks (:func:`along_track_slopes`), which fix both components where the tracks meet at
    ``min_angle_deg`` or more; on nearly parallel tracks only the offset's along-track part is
    taken out (the cross-track gradient is not seen). NaN where a slope is missing.

    Parameters
    ----------
    pairs : OverlapSet
        The pairs (kind ``"pair"``), epochs into the flight.
    tracks : list of Track
        Every track the pairs' epochs lie on.
    field : ndarray
        The field at every flight epoch (nT).
    half_span_m : float
        Half the window of the along-track slopes (m).
    min_angle_deg : float
        Tracks meeting at a shallower angle (deg) give the along-track part only.
    """
    if pairs.count == 0:
        return np.zeros(0)
    f = np.asarray(field, float)
    # per flight epoch: the position and the slope of the track it lies on (NaN off them)
    pos = np.full((f.size, 2), np.nan)
    slope = np.full((f.size, 3), np.nan)
    for tr in tracks:
        pos[tr.index] = np.column_stack([tr.east_m, tr.north_m])
        slope[tr.index] = along_track_slopes(tr, f[tr.index], half_span_m)
    if np.isnan(pos[pairs.a0]).any() or np.isnan(pos[pairs.b0]).any():
        raise ValueError("a pair's epoch lies on none of the tracks given")
    pv, sv, pm, sm = pos[pairs.a0], slope[pairs.a0], pos[pairs.b0], slope[pairs.b0]
    offset = pv - pm
    tv, tm = sv[:, 1:], sm[:, 1:]
    cross = tv[:, 0] * tm[:, 1] - tv[:, 1] * tm[:, 0]
    crossing = np.abs(cross) >= np.sin(np.radians(min_angle_deg))
    # two directions, two slopes: solve t_v . g = s_v, t_m . g = s_m for g (east, north)
    safe = np.where(crossing, cross, 1.0)
    ge = (sv[:, 0] * tm[:, 1] - sm[:, 0] * tv[:, 1]) / safe
    gn = (tv[:, 0] * sm[:, 0] - tm[:, 0] * sv[:, 0]) / safe
    across = ge * offset[:, 0] + gn * offset[:, 1]
    along = sm[:, 0] * np.einsum("ij,ij->i", offset, tm)
    return pairs.differences(f) - np.where(crossing, across, along)
