"""The quality stage: how well each processing state agrees with itself where lines overlap.

Every field (raw, each compensation model) is first reduced the same way as for the map
(IGRF and, with a base station, the diurnal removed) so that differences between two passes
over one point come from the processing, not from time. The statistics are those of paper
002 §3.2 plus the checks a survey contract asks for:

* heading error at overlap points between the validation ("X") lines and the map lines
  (survey and tie): exact track intersections (tracks meeting at ``min_crossing_angle_deg``
  or more) and sample pairs closer than ``overlap_m``;
* the map gridded from each field's **unlevelled** lines, interpolated (bilinear) at every
  validation sample inside the map: leveling would absorb part of the heading error that this
  figure is meant to show;
* tie-line crossovers before and after leveling (final field);
* per-line 4th-difference noise, flight-height and line-spacing deviation, speed excursions,
  the diurnal chord test, and the calibration FOM table.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pipeline.defaults import default_field
from pipeline.flight import Flight
from pipeline.geo.projected import GridFrame, survey_positions
from pipeline.maps.grid import Grid, minimum_curvature_fields
from pipeline.maps.level import (
    MIN_CROSSING_ANGLE_DEG,
    CrossingMap,
    Leveling,
    Line,
    level_lines,
    track_crossings,
)
from pipeline.maps.reduce import reduce_to_anomaly
from pipeline.quality import qc
from pipeline.quality.overlap import (
    OverlapSet,
    Track,
    difference_stats,
    gradient_removed_differences,
    group_stats,
    overlap_pairs,
    track_intersections,
)
from pipeline.segment import Segmentation

MAX_GRID_NODES = 250_000  # 500 x 500: a survey block's grid is thousands of nodes

# summary keys of the processing states (model names are ids with "-"; JSON keys use "_")
RAW = "raw"


def state_key(name: str) -> str:
    """Summary (JSON) key of a processing state: model ids use "-", keys "_"."""
    return name.replace("-", "_")


@dataclass
class QualitySettings:
    """Settings of the quality stage (``[quality]``).

    Attributes
    ----------
    overlap_m : float
        Validation and map samples closer than this (m) form a pair.
    noise_threshold_nT : float
        4th-difference noise above which a line is flagged, nT.
    height_tolerance_m : float
        Allowed deviation of a line's height from the survey's median, m.
    spacing_tolerance_fraction, speed_tolerance_fraction : float
        Allowed deviation of the line spacing and of the ground speed, as fractions of their
        nominal (median) values.
    diurnal_chord_s, diurnal_tolerance_nT : float
        The base-station chord test: window (s) and allowed departure from the chord (nT).
    cell_fraction : float
        Grid cell as a fraction of the line spacing.
    subtract_base : bool
        Remove the base-station diurnal in the reduction.
    min_crossing_angle_deg : float
        Tracks meeting at a shallower angle (deg) form no intersection or crossover.
    min_overlap_pairs : int
        Pairs needed for the headline heading error to use them (else the intersections).
    pair_slope_half_span_m : float
        Half the along-track window (m) of the slopes that give a pair's gradient
        (:func:`~pipeline.quality.overlap.gradient_removed_differences`).
    crs_epsg : int or None
        EPSG code of the projected CRS positions are in (None: the survey's UTM zone), as
        the map stage's (:func:`pipeline.geo.projected.survey_frame`).
    """

    # the keys of [quality] default to the shipped configuration's values
    overlap_m: float = default_field("quality", "overlap_m")  # pair threshold (paper 002: 0.5 m)
    # 4th-difference noise above which a line is flagged
    noise_threshold_nT: float = default_field("quality", "noise_threshold_nT")
    height_tolerance_m: float = default_field("quality", "height_tolerance_m")
    spacing_tolerance_fraction: float = default_field("quality", "spacing_tolerance_fraction")
    speed_tolerance_fraction: float = default_field("quality", "speed_tolerance_fraction")
    diurnal_chord_s: float = default_field("quality", "diurnal_chord_s")
    diurnal_tolerance_nT: float = default_field("quality", "diurnal_tolerance_nT")
    cell_fraction: float = 0.25  # grid cell as a fraction of the line spacing
    subtract_base: bool = True  # remove the base-station diurnal in the reduction
    # tracks meeting at a shallower angle are no intersection or crossover (config: map)
    min_crossing_angle_deg: float = MIN_CROSSING_ANGLE_DEG
    # the headline heading error is paper 002's pair statistic when at least this many pairs
    # exist, else the track intersections (config: quality.min_overlap_pairs)
    min_overlap_pairs: int = default_field("quality", "min_overlap_pairs")
    # the map's projected CRS (config: map.crs; None: the survey's UTM zone)
    crs_epsg: int | None = None
    # half window of the along-track slopes that take a pair's gradient x distance out: a
    # few samples even on a fixed-wing (6 m apart at 60 m/s, 10 Hz), well under the
    # wavelengths of geology seen from a survey's height
    pair_slope_half_span_m: float = 10.0


@dataclass
class Profile:
    """A validation line with the map interpolated along it (for the Fig. 6-style plot)."""

    line_id: str
    distance_m: np.ndarray
    validation_nT: dict[str, np.ndarray]
    interpolated_nT: dict[str, np.ndarray]


@dataclass
class QualityRun:
    """What the quality stage computed for one flight.

    The processing states compared (raw first), the map's frame (east/north/up m) and tracks,
    the validation-vs-map overlap points (intersections and pairs) with each state's
    differences (nT), the interpolated-map statistics, profiles, grids, the final field's
    leveling, the QC checks, the calibration FOM table, the settings and the notes.
    """

    states: list[str]  # processing states compared, raw first
    tl_alias: str | None  # the T-L model reported under "tl"
    frame: GridFrame
    tracks: list[Track]
    intersections: OverlapSet
    pairs: OverlapSet
    differences: dict[str, dict[str, np.ndarray]]  # kind -> state -> B_val - B_map
    interpolated: dict[str, dict]  # state -> stats
    profiles: list[Profile]
    grids: dict[str, Grid]
    leveling: Leveling | None
    qc: dict[str, Any]
    fom: list[dict] | None
    settings: QualitySettings
    notes: list[str] = field(default_factory=list)

    def _keyed(self, per_state: dict[str, Any]) -> dict[str, Any]:
        out = {state_key(s): per_state[s] for s in self.states}
        if self.tl_alias:
            out["tl"] = per_state[self.tl_alias]
        return out

    def heading_error_rms_nT(self, kind: str = "intersection") -> dict[str, float | None]:
        """RMS (nT; None without differences) of the validation-minus-map differences of ``kind``
        (``"intersection"``, ``"pair"`` or ``"pair_gradient_removed"``), per state key (and
        ``"tl"`` for the T-L alias).
        """
        return self._keyed(
            {s: difference_stats(self.differences[kind][s])["rms_nT"] for s in self.states}
        )

    @property
    def heading_error_method(self) -> str:
        """Which statistic the headline ``heading_error_rms_nT`` is: ``"pairs"`` (paper 002
        §3.2: validation and map samples closer than ``overlap_m``, compared as measured) when
        there are at least ``min_overlap_pairs`` of them, else ``"intersections"`` (exact
        track crossings, both fields interpolated along track)."""
        return (
            "pairs"
            if self.pairs.count >= max(self.settings.min_overlap_pairs, 1)
            else "intersections"
        )

    def headline_rms_nT(self) -> dict[str, float | None]:
        """``heading_error_rms_nT``: the statistic :attr:`heading_error_method` names."""
        return self.heading_error_rms_nT(
            "pair" if self.heading_error_method == "pairs" else "intersection"
        )

    def noise_floor_nT(self) -> float | None:
        """RMS the intersection differences would have from white sensor noise alone.

        The per-sample noise is the lines' median 4th-difference estimate; interpolating at a
        crossing weights two samples on either track, so the difference's variance is
        sigma^2 [(1-wa)^2 + wa^2 + (1-wb)^2 + wb^2]. Slow drift is not included.
        """
        sigma = self.qc.get("noise", {}).get("median_nT")
        ov = self.intersections
        if sigma is None or ov.count == 0:
            return None
        w = (1 - ov.wa) ** 2 + ov.wa**2 + (1 - ov.wb) ** 2 + ov.wb**2
        return float(sigma * np.sqrt(np.mean(w)))

    def crossover_stats(self) -> dict[str, Any]:
        """Tie-line crossover differences before and after leveling (RMS, mean, standard deviation;
        nT) and their count; ``before``/``after`` are None without leveling or crossovers.
        """
        lev = self.leveling
        if lev is None or not lev.crossovers:
            return {"count": 0, "before": None, "after": None}
        before = np.array([c.difference_nT for c in lev.crossovers])
        after = np.asarray(lev.residuals_nT)
        return {
            "count": int(before.size),
            "before": {
                "rms_nT": float(np.sqrt(np.mean(before**2))),
                "mean_nT": float(before.mean()),
                "std_nT": float(before.std()),
            },
            "after": {
                "rms_nT": float(np.sqrt(np.mean(after**2))),
                "mean_nT": float(after.mean()),
                "std_nT": float(after.std()),
            },
        }

    def summary(self) -> dict[str, Any]:
        """The ``quality`` section of the summary JSON."""
        kinds = {}
        for kind, ov in (("intersections", self.intersections), ("pairs", self.pairs)):
            k = "intersection" if kind == "intersections" else "pair"
            kinds[kind] = {
                "count": ov.count,
                **({"max_distance_m": self.settings.overlap_m} if k == "pair" else {}),
                "by_state": self._keyed(
                    {
                        s: {
                            **difference_stats(self.differences[k][s]),
                            "by_heading": group_stats(self.differences[k][s], ov),
                        }
                        for s in self.states
                    }
                ),
            }
        xo = self.crossover_stats()
        noise = self.qc.get("noise", {})
        return {
            "states": [state_key(s) for s in self.states],
            "tl_alias": self.tl_alias,
            # headline: paper 002's statistic (pairs < overlap_m) when there are enough
            # pairs; which one it is: heading_error_method; both are always given below
            "heading_error_rms_nT": self.headline_rms_nT(),
            "heading_error_method": self.heading_error_method,
            "heading_error_methods": HEADING_ERROR_METHODS,
            "intersection_rms_nT": self.heading_error_rms_nT("intersection"),
            "overlap_pairs": self.pairs.count,
            "overlap_pair_rms_nT": self.heading_error_rms_nT("pair"),
            "overlap_pair_gradient_removed_rms_nT": self.heading_error_rms_nT(
                "pair_gradient_removed"
            ),
            "overlap_m": self.settings.overlap_m,
            "intersections": self.intersections.count,
            "min_crossing_angle_deg": self.settings.min_crossing_angle_deg,
            "heading_error_noise_floor_nT": self.noise_floor_nT(),
            "heading_error": kinds,
            "interpolated_rms_nT": self._keyed(
                {s: self.interpolated[s]["rms_nT"] for s in self.states}
            ),
            "interpolated": self._keyed(self.interpolated),
            "crossover_rms_nT": {
                "before": xo["before"]["rms_nT"] if xo["count"] else None,
                "after": xo["after"]["rms_nT"] if xo["count"] else None,
            },
            "crossovers": xo,
            "noise_4th_diff_nT": noise.get("median_nT"),
            "qc": self.qc,
            "fom_boxes": self.fom,
            "notes": self.notes,
        }


HEADING_ERROR_METHODS = {
    "pairs": "paper 002 §3.2: RMS of B_validation - B_map over sample pairs closer than "
    "overlap_m (paper: 0.5 m), compared as measured (adds gradient x distance)",
    "pairs_gradient_removed": "the pairs less the field's own change across each pair's "
    "offset, its gradient from the slopes along both tracks (not the paper's statistic)",
    "intersections": "exact track intersections of the validation lines with the survey and "
    "tie lines, both fields interpolated along track to the crossing (only "
    "heading error and noise remain; not the paper's statistic)",
}


def _circmean_deg(a: np.ndarray) -> float:
    r = np.radians(a[np.isfinite(a)])
    return float(np.degrees(np.arctan2(np.sin(r).mean(), np.cos(r).mean())) % 360.0)


def flight_tracks(
    seg: Segmentation,
    east_m: np.ndarray,
    north_m: np.ndarray,
    kinds=("survey", "tie", "validation"),
    min_samples: int = 10,
) -> list[Track]:
    """The straight lines of the given kinds, as tracks with finite positions."""
    out = []
    ok = np.isfinite(east_m) & np.isfinite(north_m)
    for kind in kinds:
        sel = seg.mask(kind) & ok
        for lid in sorted(set(seg.line_id[sel])):
            ix = np.flatnonzero(sel & (seg.line_id == lid))
            if ix.size >= min_samples:
                out.append(
                    Track(
                        str(lid),
                        kind,
                        ix,
                        east_m[ix],
                        north_m[ix],
                        _circmean_deg(seg.heading_deg[ix]),
                    )
                )
    return out


def _interpolated(
    grid: Grid, tracks: list[Track], val: np.ndarray, east: np.ndarray, north: np.ndarray
) -> tuple[np.ndarray, list[tuple[Track, np.ndarray]]]:
    diffs, per_line = [], []
    for t in tracks:
        g = grid.interpolate(east[t.index], north[t.index])
        per_line.append((t, g))
        diffs.append(val[t.index] - g)
    return (np.concatenate(diffs) if diffs else np.zeros(0)), per_line


@dataclass
class SurveyGeometry:
    """What the quality figures of every field flown along one flight share: the survey's
    frame and positions (m), its tracks, the validation lines' overlap points with the map
    lines and where the survey lines cross the ties (:func:`survey_geometry`)."""

    frame: GridFrame
    east_m: np.ndarray
    north_m: np.ndarray
    up_m: np.ndarray
    tracks: list[Track]
    intersections: OverlapSet
    pairs: OverlapSet
    tie_crossings: CrossingMap


def survey_geometry(
    flight: Flight, seg: Segmentation, settings: QualitySettings | None = None
) -> SurveyGeometry:
    """The flight's :class:`SurveyGeometry` in the map stage's frame (same positions, same
    CRS: crossovers placed as the map's). Raises AeromagError without a mapped block."""
    s = settings or QualitySettings()
    flight.require("lat_deg", "lon_deg", "alt_m", purpose="quality statistics")
    d = flight.data
    lat, lon, alt = (d[c].to_numpy(float) for c in ("lat_deg", "lon_deg", "alt_m"))
    frame, east, north, up = survey_positions(
        lat,
        lon,
        alt,
        seg.mask("survey"),
        s.crs_epsg,
        flight.source,
        "no survey lines found: quality statistics need a mapped block",
    )
    tracks = flight_tracks(seg, east, north)
    mapped = [tr for tr in tracks if tr.kind in ("survey", "tie")]
    validation = [tr for tr in tracks if tr.kind == "validation"]
    return SurveyGeometry(
        frame,
        east,
        north,
        up,
        tracks,
        track_intersections(validation, mapped, s.min_crossing_angle_deg),
        overlap_pairs(validation, mapped, s.overlap_m),
        track_crossings(
            [tr for tr in tracks if tr.kind == "survey"],
            [tr for tr in tracks if tr.kind == "tie"],
            s.min_crossing_angle_deg,
        ),
    )


def run_quality(
    flight: Flight,
    seg: Segmentation,
    fields: dict[str, np.ndarray],
    tl_alias: str | None = None,
    fom: list[dict] | None = None,
    settings: QualitySettings | None = None,
    geometry: SurveyGeometry | None = None,
) -> QualityRun:
    """Quality figures of every processing state in ``fields`` (name -> nT per epoch).

    ``fields`` should start with ``raw`` and end with the final model; ``tl_alias`` names the
    T-L baseline reported under the key ``tl`` (the one with AGG-TL's own term set).
    ``geometry``: :func:`survey_geometry` of this flight with these settings, when several
    calls share it.
    """
    s = settings or QualitySettings()
    g = geometry if geometry is not None else survey_geometry(flight, seg, s)
    d = flight.data
    lat, lon, alt = (d[c].to_numpy(float) for c in ("lat_deg", "lon_deg", "alt_m"))
    t = d["time_s"].to_numpy(float)
    frame, east, north, up, tracks = g.frame, g.east_m, g.north_m, g.up_m, g.tracks
    base = d["base_nT"].to_numpy(float) if flight.has("base_nT") else None
    # IGRF and diurnal are the same for every state: reduce a zero field once
    offset = -reduce_to_anomaly(
        flight.time_ns, np.zeros(t.size), lat, lon, alt, base if s.subtract_base else None
    ).anomaly_nT
    reduced = {name: np.asarray(f, float) - offset for name, f in fields.items()}

    mapped = [tr for tr in tracks if tr.kind in ("survey", "tie")]
    survey = [tr for tr in tracks if tr.kind == "survey"]
    validation = [tr for tr in tracks if tr.kind == "validation"]
    notes = []
    if not validation:
        notes.append(
            "no validation lines: heading error at overlap points and the "
            "interpolated comparison need the diagonal X flight"
        )
    inter, pairs = g.intersections, g.pairs
    diffs = {
        "intersection": {n: inter.differences(v) for n, v in reduced.items()},
        "pair": {n: pairs.differences(v) for n, v in reduced.items()},
        "pair_gradient_removed": {
            n: gradient_removed_differences(
                pairs, tracks, v, s.pair_slope_half_span_m, s.min_crossing_angle_deg
            )
            for n, v in reduced.items()
        },
    }

    heading = _circmean_deg(np.mod(np.array([tr.heading_deg for tr in survey]), 180.0) * 2) / 2
    spacing = qc.line_spacing(survey, heading, s.spacing_tolerance_fraction)
    spacing_m = spacing["nominal_m"] or 50.0
    # a spacing measured from mislabelled tracks (a transit taken for a line beside one it
    # crosses) can come out at millimetres: a grid of that cell over the block would never
    # be solved, so the cell keeps the grid under MAX_GRID_NODES and the note says so
    ge_all = np.concatenate([tr.east_m for tr in mapped])
    gn_all = np.concatenate([tr.north_m for tr in mapped])
    area_m2 = float(np.ptp(ge_all) * np.ptp(gn_all))
    cell_m = s.cell_fraction * spacing_m
    if area_m2 / cell_m**2 > MAX_GRID_NODES:
        cell_m = float(np.sqrt(area_m2 / MAX_GRID_NODES))
        notes.append(
            f"line spacing {spacing_m:.3g} m is implausible for a {np.sqrt(area_m2):.0f} m "
            f"block: the quality grids use {cell_m:.1f} m cells"
        )
        spacing_m = cell_m / s.cell_fraction
    interp, profiles = {}, {}
    # every state's samples lie at the same positions: one system for all of them
    at = np.concatenate([tr.index for tr in mapped])
    grids = minimum_curvature_fields(
        ge_all,
        gn_all,
        {name: v[at] for name, v in reduced.items()},
        cell_m,
        mask_distance_m=spacing_m,
        crs=frame.grid_crs,
    )
    for name, v in reduced.items():
        grid = grids[name]
        diff, per_line = _interpolated(grid, validation, v, east, north)
        st = difference_stats(diff)
        st["samples_outside_map"] = int(np.isnan(diff).sum())
        interp[name] = st
        profiles[name] = per_line
    prof = [
        Profile(
            tr.line_id,
            tr.along_m,
            {n: reduced[n][tr.index] for n in reduced},
            {n: profiles[n][k][1] for n in reduced},
        )
        for k, tr in enumerate(validation)
    ]

    final = list(fields)[-1]
    lines = [
        Line.from_track(tr, t, reduced[final])
        for tr in mapped
        if np.isfinite(reduced[final][tr.index]).all()
    ]
    lev = (
        level_lines(lines, min_angle_deg=s.min_crossing_angle_deg, crossings=g.tie_crossings)
        if lines
        else None
    )
    checks = {
        "field": state_key(final),
        "noise": qc.line_noise(mapped, reduced[final], s.noise_threshold_nT),
        "flight_height": qc.flight_height(mapped, up, s.height_tolerance_m),
        "line_spacing": spacing,
        "speed": qc.speed_excursions(mapped, t, s.speed_tolerance_fraction),
    }
    if base is not None:
        checks["diurnal"] = qc.diurnal_check(t, base, s.diurnal_chord_s, s.diurnal_tolerance_nT)
    else:
        checks["diurnal"] = {"available": False}
    return QualityRun(
        list(fields),
        tl_alias if tl_alias in fields else None,
        frame,
        tracks,
        inter,
        pairs,
        diffs,
        interp,
        prof,
        grids,
        lev,
        checks,
        fom,
        s,
        notes,
    )


def fom_table(
    time_s: np.ndarray,
    raw_nT: np.ndarray,
    fields: dict[str, np.ndarray],
    boxes: list,
    band_hz: tuple[float, float] | None = None,
    poles: int | None = None,
) -> list[dict]:
    """The calibration FOM per box (pass, heading, manoeuvre): uncompensated and each model,
    in the fit band ``band_hz`` / ``poles`` (None: the shipped configuration's; pass the
    configured band so the table agrees with the compensation stage's FOM)."""
    from pipeline.compensate.model import figure_of_merit

    rows: list[dict] = []
    for name, f in fields.items():
        fom = figure_of_merit(time_s, raw_nT, f, boxes, band_hz, poles)
        for k, r in enumerate(fom.boxes):
            if len(rows) <= k:
                rows.append(
                    {
                        key: r[key]
                        for key in ("pass", "cardinal", "manoeuvre", "samples", "uncompensated_nT")
                    }
                )
            rows[k][f"{state_key(name)}_nT"] = r["compensated_nT"]
    return rows
