"""The map stage: reduce -> lines -> level -> grid -> ARIMA + Kalman filter -> grids."""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any

import numpy as np

from pipeline.defaults import default_field
from pipeline.errors import AeromagError
from pipeline.flight import Flight
from pipeline.geo.heading import pattern_direction_deg
from pipeline.geo.igrf import main_field_direction
from pipeline.geo.projected import GridFrame, survey_positions
from pipeline.maps.arima import (
    ArimaModel,
    KalmanResult,
    fit_arima,
    kalman_filter,
    normality,
    reverse_arrangements,
    rts_smooth,
)
from pipeline.maps.grid import Grid, minimum_curvature
from pipeline.maps.gridders import LineData, MinimumCurvatureGridder
from pipeline.maps.level import MIN_CROSSING_ANGLE_DEG, Leveling, Line, level_lines
from pipeline.maps.microlevel import MicroLevel, microlevel_lines
from pipeline.maps.reduce import Reduction, reduce_to_anomaly
from pipeline.maps.uncertainty import MapUncertainty, fit_uncertainty, uncertainty_grid
from pipeline.noise import white_noise_nT
from pipeline.segment import Segmentation

# Samples used to identify the ARIMA model (the filter runs on all of them). 20 000 cells span
# many lines of a large map; fewer risk identifying the model on one quiet corner (5000 did,
# in benchmarks/bench_maps.py). Exact likelihood with measurement noise: ~1.5 s per candidate.
ARIMA_SAMPLE_LIMIT = 20_000


def parse_arima(value: str | tuple[int, int, int]) -> str | tuple[int, int, int]:
    """``map.arima``: ``"auto"`` or ``"p,d,q"`` (or a tuple) -> ``"auto"`` or ``(p, d, q)``."""
    if value == "auto" or isinstance(value, tuple):
        return value
    try:
        p, d, q = (int(v) for v in str(value).split(","))
    except ValueError:
        raise ValueError(f"map.arima {value!r}: use auto or p,d,q (e.g. 2,1,1)") from None
    return (p, d, q)


@dataclass
class MapSettings:
    """How the map stage grids, levels and filters (the ``[map]`` keys of the configuration;
    lengths in m, noise in nT)."""

    # the keys of [map] default to the shipped configuration's values (0 there: None here)
    cell_m: float | None = default_field("map", "cell_m", lambda v: v or None)  # None: spacing/4
    # EPSG code of the projected CRS to grid in (map.crs; None: the survey's UTM zone)
    crs_epsg: int | None = None
    arima: str | tuple[int, int, int] = default_field("map", "arima", parse_arima)
    # linear-in-time line corrections besides the DC
    level_trend: bool = default_field("map", "level_trend")
    lag_s: float = 0.0
    # measurement noise for the Kalman filter (None: estimated)
    noise_nT: float | None = default_field("map", "noise_nT", lambda v: v or None)
    mask_spacings: float = 1.0  # mask cells farther than this many line spacings from data
    # smooth (Rauch-Tung-Striebel, zero phase: the map product) | forward (paper 004)
    direction: str = default_field("map", "direction")
    min_crossing_angle_deg: float = MIN_CROSSING_ANGLE_DEG  # shallower: no crossover
    # minimum_curvature | equivalent_sources | auto (by line-held-out cross-validation)
    gridder: str = default_field("map", "gridder")
    # a DEM (GeoTIFF, heights above the WGS-84 ellipsoid): the map is predicted draped at
    # dem_clearance_m above it by equivalent sources ("" = on the flight surface)
    dem_path: str = default_field("map", "dem_path")
    dem_clearance_m: float = default_field("map", "dem_clearance_m")
    # micro-levelling of the grid (pipeline.maps.microlevel); lengths 0: multiples of the
    # line spacing
    microlevel: bool = default_field("map", "microlevel")
    microlevel_wavelength_m: float = default_field("map", "microlevel_wavelength_m")
    microlevel_along_m: float = default_field("map", "microlevel_along_m")
    microlevel_clip_nT: float = default_field("map", "microlevel_clip_nT")


def grid_noise_nT(grid: Grid, along_north: bool) -> np.ndarray:
    """The white-noise level of the grid itself, per lane (nT, grid-shaped).

    A minimum-curvature grid is not the raw samples: a cell on a flight line is the block
    mean of many samples (noise / sqrt(samples per cell)), and cells between lines are
    interpolated from them (smaller, correlated noise). Each lane (a row of cells along the
    flight-line direction) gets the white-noise estimate of its own cells
    (:func:`pipeline.noise.white_noise_nT`); lanes with too
    few cells take the median of the others.
    """
    vals = grid.values.T if along_north else grid.values
    per = np.array([white_noise_nT(lane) for lane in vals])
    ok = np.isfinite(per) & (per > 0)
    fill = float(np.median(per[ok])) if ok.any() else float("nan")
    per = np.where(ok, per, fill)
    out = np.broadcast_to(per[:, None], vals.shape)
    return np.ascontiguousarray(out.T if along_north else out)


def filter_sequence(
    seq: np.ndarray,
    model: ArimaModel,
    measurement_var: float | np.ndarray,
    direction: str = "smooth",
) -> tuple[np.ndarray, KalmanResult]:
    """Kalman-filter a serialised map. ``forward`` is paper 004's causal filter, which lags
    along the lines; ``smooth`` (``both``: its former name) is the fixed-interval
    Rauch-Tung-Striebel smoother (statsmodels), the optimal zero-phase estimate under the
    model: each cell uses the cells before and after it. ``measurement_var`` (nT^2): one value
    or one per sample (the smoother takes the per-sample ones; the forward filter their
    median).

    Returns the filtered sequence and the forward filter's result (whose gain is reported).
    """
    if direction not in ("smooth", "both", "forward"):
        raise ValueError(f"unknown filter direction {direction!r} (smooth or forward)")
    var = np.asarray(measurement_var, float)
    scalar = float(np.nanmedian(var[np.isfinite(seq)])) if var.ndim else float(var)
    fwd = kalman_filter(seq, model, scalar)
    if direction == "forward":
        return fwd.filtered, fwd
    return rts_smooth(seq, model, var), fwd


def serialize(grid: Grid, along_north: bool) -> tuple[np.ndarray, np.ndarray]:
    """The grid in acquisition order: along the lines, serpentine (index into ravel order)."""
    ny, nx = grid.shape
    idx = np.arange(ny * nx).reshape(ny, nx)
    lanes = idx.T if along_north else idx  # a lane follows one flight-line direction
    order = np.concatenate([lane if k % 2 == 0 else lane[::-1] for k, lane in enumerate(lanes)])
    return grid.values.ravel()[order], order


def filter_grid(
    grid: Grid,
    along_north: bool,
    arima: str | tuple[int, int, int] = "auto",
    noise_nT: float | None = None,
    direction: str = "smooth",
    sample_limit: int = ARIMA_SAMPLE_LIMIT,
    max_p: int = 3,
    max_q: int = 2,
    sensor_noise_nT: float | None = None,
) -> tuple[Grid, ArimaModel, KalmanResult, float, str, dict[str, Any]]:
    """ARIMA identification and Kalman filtering/smoothing of a grid along its lines.

    The grid is serialised in acquisition order; the model is identified (BIC) on a
    contiguous stretch holding ``sample_limit`` cells with masked cells kept as missing (the
    likelihood never joins the cells on either side of a gap) as an ARIMA signal plus white
    noise of the grid's own level (per lane, :func:`grid_noise_nT`, unless ``noise_nT`` is
    given); then ``direction`` = smooth runs the Rauch-Tung-Striebel smoother. Where no lane
    is long enough to read the grid's own level (lines of a few cells), the survey lines'
    white noise ``sensor_noise_nT`` stands in: an upper bound, the cells being means of
    several samples.

    Returns the filtered grid, the model, the forward filter, the median measurement noise
    (nT), where the noise came from, and the sequence tests.
    """
    seq, order = serialize(grid, along_north)
    finite = np.flatnonzero(np.isfinite(seq))
    if finite.size < 10:
        raise ValueError("fewer than 10 finite cells to filter")
    last = finite[min(sample_limit, finite.size) - 1]
    ident = seq[finite[0] : last + 1]
    ident_finite = ident[np.isfinite(ident)]
    tests: dict[str, Any] = {
        "reverse_arrangements": reverse_arrangements(ident_finite).to_dict(),
        "normality": normality(ident_finite),
        "samples_for_identification": int(ident_finite.size),
    }
    if noise_nT is not None:
        noise_cells = np.full(seq.size, float(noise_nT))
        source = "given"
    else:
        # the noise of the grid itself, per lane: not the raw samples' (block means and
        # interpolation between lines make it several times smaller, and lane-dependent)
        noise_cells = grid_noise_nT(grid, along_north).ravel()[order]
        source = "4th difference of the grid, per lane"
        if not np.isfinite(noise_cells[finite]).any() and sensor_noise_nT is not None:
            noise_cells = np.full(seq.size, float(sensor_noise_nT))
            source = "the survey lines' sensor noise (lanes too short for the grid's own)"
        if not np.isfinite(noise_cells[finite]).any():
            raise ValueError("no lane is long enough to read the grid's noise: set [map] noise_nT")
    var_cells = noise_cells**2
    noise = float(np.sqrt(np.nanmedian(var_cells[finite])))
    tests["grid_noise_nT_range"] = [
        float(np.nanmin(noise_cells[finite])),
        float(np.nanmax(noise_cells[finite])),
    ]
    arima_order = None if arima == "auto" else tuple(arima)
    model = fit_arima(ident, order=arima_order, measurement_var=noise**2, max_p=max_p, max_q=max_q)
    filt = np.full(grid.values.size, np.nan)
    filt[order], kf = filter_sequence(seq, model, var_cells, direction)
    return grid.with_values(filt.reshape(grid.shape)), model, kf, noise, source, tests


@dataclass
class MapRun:
    """One map stage's results: the frame (east/north/up m along the projected CRS's axes
    about an origin near the survey's centroid), the reduction to anomaly, the levelled
    lines, the line spacing (m), the anomaly grid and its ARIMA-Kalman-filtered version (nT),
    the filter's model and run, and what the gridder and micro-levelling did."""

    frame: GridFrame
    reduction: Reduction
    lines: list[Line]
    leveling: Leveling
    spacing_m: float
    grid: Grid
    filtered: Grid
    model: ArimaModel
    kalman: KalmanResult
    noise_nT: float
    noise_source: str
    direction: str = "smooth"
    sequence_tests: dict[str, Any] = field(default_factory=dict)
    # IGRF at the frame origin on the survey's mid date: (total nT, inclination, declination deg)
    main_field: tuple[float, float, float] = (float("nan"),) * 3
    # the gridder used and its cross-validation scores (pipeline.maps.gridders)
    gridder: dict[str, Any] = field(default_factory=lambda: {"method": "minimum_curvature"})
    microlevel: MicroLevel | None = None
    # the grid's 1-sigma error per cell, nT (pipeline.maps.uncertainty; None: fewer than
    # three survey lines, nothing to hold out) and its model, or why there is none
    uncertainty: Grid | None = None
    uncertainty_model: MapUncertainty | None = None
    uncertainty_note: str = ""
    # the field mapped: a compensation model's name, "extended" (the audit's), or "raw" (the
    # despiked scalar, uncompensated: no model could be fitted)
    field: str = "compensated"

    @property
    def error_length_m(self) -> float:
        """How far along a track the map's error stays the same (m): the uncertainty model's
        measured correlation length, else the line spacing."""
        if self.uncertainty_model is None:
            return float(self.spacing_m)
        return self.uncertainty_model.error_length_m

    @property
    def grid_declination_deg(self) -> float:
        """The IGRF declination from grid north (deg): the true one less the meridian
        convergence at the frame's origin (what a reduction to the pole on the grid takes)."""
        return self.main_field[2] - self.frame.convergence_deg()

    def summary(self) -> dict[str, Any]:
        """The ``map`` block of the summary JSON (shapes, origin, crossovers, levelling,
        gridder, ARIMA model, Kalman settings, anomaly range)."""
        ny, nx = self.grid.shape
        return {
            "field": self.field,
            "grid_shape": [ny, nx],
            "cell_m": self.grid.cell_m,
            "origin": {
                "east_m": self.grid.east0_m,
                "north_m": self.grid.north0_m,
                "latitude_deg": self.frame.lat0_deg,
                "longitude_deg": self.frame.lon0_deg,
                "altitude_m": self.frame.alt0_m,
                "crs": self.frame.crs,
                "epsg": self.frame.epsg,
                "easting_m": self.frame.origin_east_m,
                "northing_m": self.frame.origin_north_m,
                "first_cell_easting_m": self.frame.origin_east_m + self.grid.east0_m,
                "first_cell_northing_m": self.frame.origin_north_m + self.grid.north0_m,
                "crs_choice": self.frame.note,
                "utm_zones_spanned": list(self.frame.zones),
            },
            "main_field": {
                "total_nT": self.main_field[0],
                "inclination_deg": self.main_field[1],
                "declination_deg": self.main_field[2],
                "grid_declination_deg": self.grid_declination_deg,
            },
            "line_spacing_m": self.spacing_m,
            "lines": {
                "survey": sum(ln.kind == "survey" for ln in self.lines),
                "tie": sum(ln.kind == "tie" for ln in self.lines),
            },
            "crossover_rms_nT": {
                "before": self.leveling.rms_before_nT,
                "after": self.leveling.rms_after_nT,
            },
            "leveling": self.leveling.to_dict(),
            "gridder": self.gridder,
            "microlevel": (
                {"enabled": True, **self.microlevel.summary()}
                if self.microlevel is not None
                else {"enabled": False}
            ),
            "arima_order": list(self.model.order),
            "arima_coefficients": {
                "ar": [float(v) for v in self.model.ar],
                "ma": [float(v) for v in self.model.ma],
                "integrated_ar": [float(v) for v in self.model.integrated_ar()],
            },
            "arima": self.model.to_dict(),
            "kalman": {
                "measurement_noise_nT": self.noise_nT,
                "noise_source": self.noise_source,
                "process_noise_var_nT2": float(self.model.sigma2),
                "direction": self.direction,
                "smoother": (
                    "Rauch-Tung-Striebel (statsmodels)" if self.direction != "forward" else None
                ),
                "steady_gain": [float(g) for g in self.kalman.gain_steady],
                "exact_steps": self.kalman.exact_steps,
            },
            "sequence_tests": self.sequence_tests,
            "uncertainty": self._uncertainty_summary(),
            "anomaly_range_nT": [
                float(np.nanmin(self.grid.values)),
                float(np.nanmax(self.grid.values)),
            ],
        }

    def _uncertainty_summary(self) -> dict[str, Any]:
        if self.uncertainty is None or self.uncertainty_model is None:
            return {"channel": None, "note": self.uncertainty_note}
        v = self.uncertainty.values[np.isfinite(self.uncertainty.values)]
        return {
            "channel": "/map/uncertainty",
            **self.uncertainty_model.describe(),
            "median_nT": float(np.median(v)) if v.size else None,
            "max_nT": float(np.max(v)) if v.size else None,
            "note": self.uncertainty_note,
        }


def _line_data(lines: list[Line], up_m: np.ndarray) -> LineData:
    """The levelled lines as the gridders' :class:`LineData` (local east/north/up m, nT)."""
    return LineData(
        np.concatenate([ln.east_m for ln in lines]),
        np.concatenate([ln.north_m for ln in lines]),
        np.concatenate([up_m[ln.index] for ln in lines]),
        np.concatenate([ln.value_nT for ln in lines]),
        np.concatenate([np.full(ln.index.size, ln.line_id, dtype=object) for ln in lines]),
        np.concatenate([np.full(ln.index.size, ln.kind, dtype=object) for ln in lines]),
    )


def lines_noise_nT(lines: list[Line]) -> float:
    """The sensor's white noise (nT, 1 sigma): the median over the survey lines of
    :func:`pipeline.noise.white_noise_nT`."""
    return float(
        np.nanmedian(
            [white_noise_nT(ln.value_nT, ln.time_s) for ln in lines if ln.kind == "survey"]
        )
    )


def map_uncertainty(
    data: LineData, grid: Grid, spacing_m: float, sensor_nT: float, leveling: Leveling
) -> tuple[Grid | None, MapUncertainty | None, str]:
    """The grid's 1-sigma error per cell (nT; :mod:`pipeline.maps.uncertainty`), its model and
    a note. Held-out lines are predicted by unmasked minimum curvature whatever the map's
    gridder (refitting equivalent sources once per fold costs minutes; where they were chosen
    their cross-validated misfit was the lower, so the sigma errs on the large side). The
    levelling term is the crossover RMS after levelling over sqrt(2) (each crossover holds two
    lines' level errors)."""
    level = leveling.rms_after_nT / np.sqrt(2.0) if np.isfinite(leveling.rms_after_nT) else 0.0
    noise = sensor_nT if np.isfinite(sensor_nT) else 0.0
    try:
        model = fit_uncertainty(
            data,
            lambda: MinimumCurvatureGridder(grid.cell_m, np.inf),
            spacing_m,
            float(noise),
            float(level),
        )
    except ValueError as exc:
        return None, None, f"no /map/uncertainty: {exc}"
    how = "held-out lines predicted by minimum curvature"
    return uncertainty_grid(model, grid, data), model, how


def _lines(seg: Segmentation, e, n, t, v) -> list[Line]:
    out = []
    for kind in ("survey", "tie"):
        for lid in sorted(set(seg.line_id[seg.mask(kind)])):
            ix = np.flatnonzero(
                (seg.line_id == lid) & seg.mask(kind) & np.isfinite(v) & np.isfinite(e)
            )
            if ix.size >= 10:
                out.append(Line(lid, kind, e[ix], n[ix], t[ix], v[ix], ix))
    return out


@dataclass
class GriddedMap:
    """The map stage up to the grid (before the ARIMA-Kalman filter): the frame, the
    reduction to anomaly, the levelled lines, their heading from grid north (deg) and
    spacing (m), the anomaly grid (nT), the lines' data, the gridder and micro-levelling."""

    frame: GridFrame
    reduction: Reduction
    lines: list[Line]
    leveling: Leveling
    heading_deg: float
    spacing_m: float
    grid: Grid
    data: LineData
    gridder: dict[str, Any]
    microlevel: MicroLevel | None


def anomaly_grid(
    flight: Flight,
    seg: Segmentation,
    compensated_nT: np.ndarray,
    settings: MapSettings | None = None,
) -> GriddedMap:
    """Reduce, level and grid a compensated flight's lines: :func:`build_map` without the
    ARIMA-Kalman filter and the uncertainty grid (what a comparison of grids needs)."""
    s = settings or MapSettings()
    flight.require("lat_deg", "lon_deg", "alt_m", purpose="mapping")
    d = flight.data
    lat, lon, alt = (d[c].to_numpy(float) for c in ("lat_deg", "lon_deg", "alt_m"))
    frame, e, n, up = survey_positions(
        lat, lon, alt, seg.mask("survey"), s.crs_epsg, flight.source, "no survey lines found to map"
    )
    base = d["base_nT"].to_numpy(float) if flight.has("base_nT") else None
    red = reduce_to_anomaly(flight.time_ns, compensated_nT, lat, lon, alt, base, s.lag_s)
    t = d["time_s"].to_numpy(float)
    lines = _lines(seg, e, n, t, red.anomaly_nT)
    lev = level_lines(lines, trend=s.level_trend, min_angle_deg=s.min_crossing_angle_deg)
    for ln in lines:
        ln.value_nT = ln.value_nT - lev.correction(ln.line_id, ln.time_s)
    # line spacing: cross-track offsets of the survey lines; the heading from grid north
    # (true heading less the meridian convergence: degrees at a zone's edge)
    # as an axis (lines and their reciprocals): a median of headings mod 180 straddles
    # 0/180 on north-south lines and can come out east-west
    true_heading = pattern_direction_deg(seg.heading_deg[seg.mask("survey")], fold=2)
    heading = float(np.mod(true_heading - frame.convergence_deg(), 180.0))
    along = np.array([np.sin(np.radians(heading)), np.cos(np.radians(heading))])
    across = np.array([along[1], -along[0]])
    offs = np.sort(
        [
            np.median(ln.east_m * across[0] + ln.north_m * across[1])
            for ln in lines
            if ln.kind == "survey"
        ]
    )
    spacing = float(np.median(np.diff(offs))) if offs.size > 1 else 50.0
    cell = s.cell_m or spacing / 4.0
    pts = [(ln.east_m, ln.north_m, ln.value_nT) for ln in lines]
    ge, gn, gv = (np.concatenate([p[k] for p in pts]) for k in range(3))
    grid = minimum_curvature(
        ge, gn, gv, cell, mask_distance_m=s.mask_spacings * spacing, crs=frame.grid_crs
    )
    micro = None
    if s.microlevel:
        micro = microlevel_lines(
            lines,
            grid,
            heading,
            spacing,
            s.microlevel_wavelength_m,
            s.microlevel_along_m,
            s.microlevel_clip_nT,
        )
        for ln in lines:
            if ln.kind == "survey" and ln.line_id in micro.corrections:
                ln.value_nT = ln.value_nT - micro.corrections[ln.line_id]
        gv = np.concatenate([ln.value_nT for ln in lines])
        regrid = minimum_curvature(
            ge, gn, gv, cell, mask_distance_m=s.mask_spacings * spacing, crs=frame.grid_crs
        )
        change = regrid.values - grid.values
        change = change[np.isfinite(change)]
        micro.grid_change_rms_nT = float(np.sqrt(np.mean(change**2))) if change.size else 0.0
        grid = regrid
    data = _line_data(lines, up)
    grid, gridder = _regrid(flight, data, grid, frame, spacing, s)
    return GriddedMap(frame, red, lines, lev, heading, spacing, grid, data, gridder, micro)


# the fewest survey epochs worth a map: a few seconds of line do not make a grid
MIN_SURVEY_EPOCHS = 100


def map_refusal(flight: Flight, seg: Segmentation | None) -> str | None:
    """Why the flight gets no map (one line, said in the log and the reports), or None."""
    if seg is None:
        return "no segmentation"
    n = int(seg.mask("survey").sum())
    if n <= MIN_SURVEY_EPOCHS:
        return (
            f"{n} survey epochs: no block of straight, parallel survey lines was found in the "
            "track (segments: "
            + ", ".join(f"{k} {int(seg.mask(k).sum())}" for k in ("tie", "validation", "transit"))
            + " epochs)"
        )
    if not flight.has("lat_deg", "lon_deg", "alt_m"):
        return "no positions (/gnss/fix)"
    return None


def build_map(
    flight: Flight,
    seg: Segmentation,
    compensated_nT: np.ndarray,
    settings: MapSettings | None = None,
    field: str = "compensated",
) -> MapRun:
    """Anomaly grid (:func:`anomaly_grid`) and its ARIMA-Kalman-filtered version from a
    compensated flight, with the grid's uncertainty; ``field`` names what
    ``compensated_nT`` is (:attr:`MapRun.field`)."""
    s = settings or MapSettings()
    gm = anomaly_grid(flight, seg, compensated_nT, s)
    frame, red, lines, lev, spacing, grid, data = (
        gm.frame,
        gm.reduction,
        gm.lines,
        gm.leveling,
        gm.spacing_m,
        gm.grid,
        gm.data,
    )
    # ARIMA + Kalman along the flight lines
    along = np.array([np.sin(np.radians(gm.heading_deg)), np.cos(np.radians(gm.heading_deg))])
    along_north = abs(along[1]) >= abs(along[0])
    sensor = lines_noise_nT(lines)
    try:
        filtered, model, kf, noise, source, tests = filter_grid(
            grid, along_north, s.arima, s.noise_nT, s.direction, sensor_noise_nT=sensor
        )
    except ValueError as exc:
        raise AeromagError(
            f"map filter: {exc}", file=flight.source, channel="/mag/compensated"
        ) from None
    tests["sensor_noise_nT"] = sensor
    sigma, sigma_model, sigma_note = map_uncertainty(data, grid, spacing, sensor, lev)
    when = datetime.fromtimestamp(float(np.median(flight.time_ns)) / 1e9, tz=UTC)
    _, total, incl, decl = main_field_direction(frame.lat0_deg, frame.lon0_deg, frame.alt0_m, when)
    return MapRun(
        frame,
        red,
        lines,
        lev,
        spacing,
        grid,
        filtered,
        model,
        kf,
        noise,
        source,
        s.direction,
        tests,
        (total, incl, decl),
        gm.gridder,
        gm.microlevel,
        sigma,
        sigma_model,
        sigma_note,
        field,
    )


def _regrid(
    flight: Flight,
    data: LineData,
    grid: Grid,
    frame: GridFrame,
    spacing_m: float,
    s: MapSettings,
) -> tuple[Grid, dict[str, Any]]:
    """The configured gridder's map on the minimum-curvature grid's cells (and mask):
    unchanged for ``minimum_curvature`` on the flight surface; with a DEM, draped at the
    clearance above it by equivalent sources."""
    from pipeline.maps.gridders import GRIDDERS, choose_gridder, grid_on

    method = s.gridder
    if method not in GRIDDERS:
        raise AeromagError(f"map.gridder {method!r}: use {', '.join(GRIDDERS)}", file=flight.source)
    if method == "minimum_curvature" and not s.dem_path:
        return grid, {"method": method}
    height: np.ndarray | float = 0.0  # the frame's origin: the mean survey altitude
    if s.dem_path:
        from pipeline.maps.dem import dem_heights_m

        gx, gy = np.meshgrid(*grid.coordinates())
        lat, lon, _ = frame.to_geodetic(gx, gy)
        height = dem_heights_m(s.dem_path, lat, lon) + s.dem_clearance_m - frame.alt0_m
        if method != "equivalent_sources":  # minimum curvature cannot continue a field
            method = "equivalent_sources"
    choice = choose_gridder(data, method, grid.cell_m, spacing_m, s.mask_spacings * spacing_m)
    out = grid_on(choice, data, grid, height)
    info = choice.describe()
    if s.dem_path:
        info["dem"] = {"path": str(s.dem_path), "clearance_m": float(s.dem_clearance_m)}
    return out, info
