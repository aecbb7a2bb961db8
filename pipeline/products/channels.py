"""Output channels: pipeline results as MCAP messages (schemas in ``schemas/``)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from pipeline.compensate.stage import CompensationRun
from pipeline.flight import Flight
from pipeline.io.writer import OutputChannel
from pipeline.maps.grid import Grid
from pipeline.segment import Segmentation

if TYPE_CHECKING:
    from pipeline.despike import DespikeResult
    from pipeline.quality.stage import QualityRun


def segment_channel(flight: Flight, seg: Segmentation) -> OutputChannel:
    """``/flight/segment``: one message at each change of label, line or manoeuvre."""
    ch = OutputChannel("/flight/segment", "aeromag.Segment")
    for i in seg.changes():
        h = seg.heading_deg[i]
        ch.add(
            int(flight.time_ns[i]),
            {
                "label": str(seg.label[i]),
                "line_id": str(seg.line_id[i]),
                "heading_deg": None if not np.isfinite(h) else round(float(h), 3),
                "manoeuvre": str(seg.manoeuvre[i]),
                "cardinal": str(seg.cardinal[i]),
                "calibration_pass": int(seg.calibration_pass[i]),
                "source": seg.source,
            },
        )
    return ch


def compensated_channel(
    flight: Flight, run: CompensationRun, topic: str = "/mag/compensated"
) -> OutputChannel:
    """Compensated field at every epoch where it exists."""
    return field_channel(flight, topic, run.compensated_nT, run.interference_nT, run.model.model)


def despike_channels(flight: Flight, res: DespikeResult | None) -> list[OutputChannel]:
    """``/mag/despike``: every scalar sample the despike step replaced, at the sample's
    instant; no channel when despiking was off (``res`` None) or found no spike."""
    if res is None or not res.spikes:
        return []
    ch = OutputChannel("/mag/despike", "aeromag.Spike")
    sensor = _sensor_id(flight)
    for i, amp in zip(res.spike_index, res.amplitude_nT, strict=True):
        ch.add(
            int(flight.time_ns[i]),
            {
                "sensor_id": sensor,
                "fiducial": int(i),
                "measured_nT": float(res.values_nT[i] + amp),
                "replaced_nT": float(res.values_nT[i]),
                "amplitude_nT": float(amp),
            },
        )
    return [ch]


def field_channel(
    flight: Flight,
    topic: str,
    compensated_nT: np.ndarray,
    interference_nT: np.ndarray | None,
    model: str,
) -> OutputChannel:
    """An ``aeromag.CompensatedField`` channel from per-epoch arrays; the interference
    defaults to what was removed from the recorded scalar."""
    sensor = _sensor_id(flight)
    comp = np.asarray(compensated_nT, float)
    inter = (
        flight.data["scalar_nT"].to_numpy(float) - comp
        if interference_nT is None
        else np.asarray(interference_nT, float)
    )
    ix = np.flatnonzero(np.isfinite(comp))
    columns = {  # one message per epoch, encoded when written
        "sensor_id": sensor,
        "total_nT": comp[ix],
        "interference_nT": inter[ix],
        "model": model,
    }
    return OutputChannel.columns(topic, "aeromag.CompensatedField", flight.time_ns[ix], columns)


def vector_channel(
    flight: Flight, topic: str, vectors_nT: np.ndarray, method: str
) -> OutputChannel:
    """An ``aeromag.VectorField`` channel (body frame) from per-epoch vectors; the sensor
    id is the fluxgate's with the method that made them."""
    sensor = str(flight.series[flight.topic_of["vector"]].labels["sensor_id"][0])
    v = np.asarray(vectors_nT, float)
    ix = np.flatnonzero(np.all(np.isfinite(v), axis=1))
    xyz = np.ascontiguousarray(v[ix].T)
    columns = {"sensor_id": f"{sensor}-{method}", "x_nT": xyz[0], "y_nT": xyz[1], "z_nT": xyz[2]}
    return OutputChannel.columns(topic, "aeromag.VectorField", flight.time_ns[ix], columns)


def model_message(
    flight: Flight, run: CompensationRun, ch: OutputChannel | None = None
) -> OutputChannel:
    """``/compensation/model``: the fitted model (one message, at the first epoch)."""
    ch = ch or OutputChannel("/compensation/model", "aeromag.CompensationModel")
    m = run.model.to_dict()
    fom = run.fom.total if run.fom else {"uncompensated": None, "compensated": None}
    payload = {
        "sensor_id": _sensor_id(flight),
        "fom_nT": fom,
        **{
            k: m[k]
            for k in (
                "model",
                "terms",
                "coefficients",
                "compensating_terms",
                "lambda",
                "band_hz",
                "poles",
                "trim",
                "samples",
                "fit_residual_nT",
                "calibration_windows_s",
                "gradient_nT_per_m",
            )
        },
    }
    payload["extension"] = m.get("extension")
    # one ns apart so several models on the topic keep their order
    ch.add(int(flight.time_ns[0]) + len(ch.messages), payload)
    return ch


def _sensor_id(flight: Flight) -> str:
    s = flight.series[flight.topic_of["scalar"]]
    return str(s.labels["sensor_id"][0]) if s.labels["sensor_id"].size else ""


# --------------------------------------------------------------------------------------------
# maps
MAP_FRAME = "local_enu"  # x east, y north (m) along the map CRS's axes about /map/frame's origin


def grid_channel(topic: str, time_ns: int, grid, field_name: str = "anomaly_nT") -> OutputChannel:
    """A ``foxglove.Grid`` message: float32 cells, row-major from the south-west corner.

    The pose puts the grid's corner (half a cell south-west of the first cell centre) in the
    ``local_enu`` frame; masked cells are NaN.
    """
    import base64

    ch = OutputChannel(topic, "foxglove.Grid")
    ny, nx = grid.shape
    data = np.ascontiguousarray(grid.values, dtype="<f4").tobytes()
    ch.add(
        int(time_ns),
        {
            "frame_id": MAP_FRAME,
            "pose": {
                "position": {
                    "x": grid.east0_m - grid.cell_m / 2,
                    "y": grid.north0_m - grid.cell_m / 2,
                    "z": 0.0,
                },
                "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
            },
            "column_count": int(nx),
            "cell_size": {"x": float(grid.cell_m), "y": float(grid.cell_m)},
            "row_stride": int(nx * 4),
            "cell_stride": 4,
            "fields": [{"name": field_name, "offset": 0, "type": 7}],  # 7 = FLOAT32
            "data": base64.b64encode(data).decode("ascii"),
        },
    )
    return ch


def map_frame_channel(mr, time_ns: int) -> OutputChannel:
    """``/map/frame``: the georeference of every ``/map/*`` grid (one message).

    The projected CRS the grids were computed in (``crs`` ``EPSG:<code>`` and ``epsg``), the
    ``local_enu`` frame's origin in it (``origin_easting_m``, ``origin_northing_m``: a cell
    centre's easting is the origin's plus the grid pose's x plus (column + 1/2) cells) and in
    WGS-84 (latitude, longitude, ellipsoidal height = the mean survey altitude), the meridian
    convergence there, the survey's UTM zone and the IGRF inclination, declination and
    intensity at the origin on the survey date: what an independent reader needs to place
    the grids and to reduce them to the pole.
    """
    from pipeline.geo.projected import utm_epsg

    f = mr.frame
    total, incl, decl = mr.main_field
    ch = OutputChannel("/map/frame", "aeromag.MapFrame")
    ch.add(
        int(time_ns),
        {
            "frame_id": MAP_FRAME,
            "crs": f.crs,
            "epsg": f.epsg,
            "origin_easting_m": float(f.origin_east_m),
            "origin_northing_m": float(f.origin_north_m),
            "latitude": float(f.lat0_deg),
            "longitude": float(f.lon0_deg),
            "altitude_m": float(f.alt0_m),
            # the zone chosen (the map.crs given may be another grid)
            "utm_epsg": f.epsg if f.epsg in f.zones else int(utm_epsg(f.lat0_deg, f.lon0_deg)),
            "grid_convergence_deg": round(f.convergence_deg(), 9),
            "igrf_inclination_deg": round(incl, 6),
            "igrf_declination_deg": round(decl, 6),
            "igrf_total_nT": round(total, 3),
            # the navigation filter's correlation length for the map's error (only where the
            # map stage measured that error)
            **(
                {"error_correlation_length_m": round(mr.error_length_m, 3)}
                if getattr(mr, "uncertainty_model", None) is not None
                else {}
            ),
        },
    )
    return ch


def line_samples_channel(flight: Flight, mr) -> OutputChannel:
    """``/map/lines``: every sample of the levelled survey and tie lines (what was gridded).

    ``compensated_nT`` is the field the map was reduced from (after any lag shift),
    ``levelled_nT`` = compensated - diurnal - line correction, ``anomaly_nT`` = levelled -
    IGRF (the gridded value); ``raw_nT`` the recorded scalar (null where it has none).
    """
    red = mr.reduction
    igrf = red.igrf_nT
    diurnal = red.diurnal_nT if red.diurnal_nT is not None else np.zeros_like(igrf)
    comp = red.anomaly_nT + igrf + diurnal
    d = flight.data
    lat, lon, alt = (d[c].to_numpy(float) for c in ("lat_deg", "lon_deg", "alt_m"))
    raw = d["scalar_nT"].to_numpy(float)
    idx = np.concatenate([ln.index for ln in mr.lines]).astype(np.int64)
    ids = np.concatenate([np.full(ln.index.size, ln.line_id, object) for ln in mr.lines])
    kinds = np.concatenate([np.full(ln.index.size, ln.kind, object) for ln in mr.lines])
    east = np.concatenate([ln.east_m for ln in mr.lines])
    north = np.concatenate([ln.north_m for ln in mr.lines])
    anomaly = np.concatenate([ln.value_nT for ln in mr.lines])
    order = np.argsort(idx, kind="stable")
    idx, ids, kinds, east, north, anomaly = (
        a[order] for a in (idx, ids, kinds, east, north, anomaly)
    )

    columns = {  # one message per sample, encoded when written (raw_nT: null where NaN)
        "line_id": np.array([str(v) for v in ids], object),
        "kind": np.array([str(v) for v in kinds], object),
        "fiducial": idx,
        "latitude": lat[idx],
        "longitude": lon[idx],
        "altitude_m": alt[idx],
        "east_m": _rounded(east, 3),
        "north_m": _rounded(north, 3),
        "raw_nT": raw[idx],
        "compensated_nT": comp[idx],
        "levelled_nT": anomaly + igrf[idx],
        "anomaly_nT": anomaly,
    }
    return OutputChannel.columns("/map/lines", "aeromag.LineSample", flight.time_ns[idx], columns)


def _rounded(values: np.ndarray, digits: int) -> np.ndarray:
    """Python's ``round`` of each value (correctly rounded in decimal, which ``np.round``
    is not always)."""
    return np.array([round(v, digits) for v in np.asarray(values, float).tolist()], float)


def tracks_channel(
    flight: Flight, seg: Segmentation, time_ns: int, every_s: float = 1.0
) -> OutputChannel:
    """``/map/tracks``: flight lines as a GeoJSON FeatureCollection (lon/lat, ~1 point/s)."""
    import json

    d = flight.data
    lat, lon = d["lat_deg"].to_numpy(float), d["lon_deg"].to_numpy(float)
    rate = 1.0 / float(np.median(np.diff(d["time_s"].to_numpy())))
    step = max(int(round(every_s * rate)), 1)
    feats = []
    for kind in ("survey", "tie", "validation", "calibration"):
        for lid in sorted(set(seg.line_id[seg.mask(kind)])):
            ix = np.flatnonzero((seg.line_id == lid) & seg.mask(kind) & np.isfinite(lat))
            if ix.size < 2:
                continue
            ix = np.r_[ix[::step], ix[-1]]
            feats.append(
                {
                    "type": "Feature",
                    "properties": {"line_id": lid, "label": kind},
                    "geometry": {
                        "type": "LineString",
                        "coordinates": [
                            [round(float(lon[i]), 7), round(float(lat[i]), 7)] for i in ix
                        ],
                    },
                }
            )
    ch = OutputChannel("/map/tracks", "foxglove.GeoJSON")
    ch.add(int(time_ns), {"geojson": json.dumps({"type": "FeatureCollection", "features": feats})})
    return ch


# --------------------------------------------------------------------------------------------
# quality
def _epoch_time_ns(flight: Flight, epoch: np.ndarray) -> np.ndarray:
    """Time (ns) at fractional epochs: exact integer arithmetic at whole epochs."""
    i0 = np.floor(epoch).astype(int)
    i1 = np.minimum(i0 + 1, flight.time_ns.size - 1)
    frac = epoch - i0
    return flight.time_ns[i0] + np.rint(frac * (flight.time_ns[i1] - flight.time_ns[i0])).astype(
        np.int64
    )


def heading_error_channel(flight: Flight, q) -> OutputChannel:
    """``/quality/heading_error``: every overlap point (intersections, then pairs)."""
    from pipeline.quality.stage import state_key

    ch = OutputChannel("/quality/heading_error", "aeromag.HeadingErrorPoint")
    for kind, ov in (("intersection", q.intersections), ("pair", q.pairs)):
        if ov.count == 0:
            continue
        lat, lon, _ = q.frame.to_geodetic(ov.east_m, ov.north_m)
        ta = _epoch_time_ns(flight, ov.validation_epoch())
        tb = _epoch_time_ns(flight, (1 - ov.wb) * ov.b0 + ov.wb * ov.b1)
        diffs = {state_key(s): q.differences[kind][s] for s in q.states}
        for k in range(ov.count):
            ch.add(
                int(ta[k]),
                {
                    "kind": kind,
                    "validation_line": str(ov.validation_line[k]),
                    "map_line": str(ov.map_line[k]),
                    "east_m": round(float(ov.east_m[k]), 3),
                    "north_m": round(float(ov.north_m[k]), 3),
                    "latitude": float(lat[k]),
                    "longitude": float(lon[k]),
                    "distance_m": round(float(ov.distance_m[k]), 4),
                    "validation_heading_deg": round(float(ov.validation_heading_deg[k]), 3),
                    "map_heading_deg": round(float(ov.map_heading_deg[k]), 3),
                    "time_separation_s": round(float(tb[k] - ta[k]) / 1e9, 3),
                    "difference_nT": {
                        s: (float(v[k]) if np.isfinite(v[k]) else None) for s, v in diffs.items()
                    },
                },
            )
    ch.messages.sort(key=lambda m: m[0])
    return ch


def crossover_channel(flight: Flight, q) -> OutputChannel:
    """``/quality/crossovers``: survey-tie crossovers of the final field."""
    from pipeline.quality.stage import state_key

    ch = OutputChannel("/quality/crossovers", "aeromag.Crossover")
    lev = q.leveling
    if lev is None or not lev.crossovers:
        return ch
    t_first = flight.time_ns[0]
    t_rel = flight.data["time_s"].to_numpy(float)
    xs = lev.crossovers
    lat, lon, _ = q.frame.to_geodetic([c.east_m for c in xs], [c.north_m for c in xs])
    for k, c in enumerate(xs):
        later = max(c.time_a_s, c.time_b_s)
        t_ns = int(t_first + round((later - t_rel[0]) * 1e9))
        ch.add(
            t_ns,
            {
                "survey_line": c.line_a,
                "tie_line": c.line_b,
                "east_m": round(float(c.east_m), 3),
                "north_m": round(float(c.north_m), 3),
                "latitude": float(lat[k]),
                "longitude": float(lon[k]),
                "difference_before_nT": float(c.difference_nT),
                "difference_after_nT": float(lev.residuals_nT[k]),
                "time_separation_s": round(float(c.time_b_s - c.time_a_s), 3),
                "field": state_key(q.states[-1]),
            },
        )
    ch.messages.sort(key=lambda m: m[0])
    return ch


# --------------------------------------------------------------------------------------------
# navigation
NAV_FRAME = "nav"


def location_channel(
    topic: str,
    time_ns: np.ndarray,
    lat_deg: np.ndarray,
    lon_deg: np.ndarray,
    alt_m: np.ndarray,
    cov_ne_m2: np.ndarray,
    var_up_m2: float,
) -> OutputChannel:
    """A ``foxglove.LocationFix`` channel; the covariance comes as (N, 2, 2) north/east blocks
    and is written in LocationFix's east-north-up order (type 3, known)."""
    lat, lon, alt = (np.asarray(a, float) for a in (lat_deg, lon_deg, alt_m))
    c = np.asarray(cov_ne_m2, float)

    def payload(k: int) -> dict:  # made when written (one message per epoch)
        pnn, pne, pee = float(c[k, 0, 0]), float(c[k, 0, 1]), float(c[k, 1, 1])
        return {
            "frame_id": NAV_FRAME,
            "latitude": float(lat[k]),
            "longitude": float(lon[k]),
            "altitude": float(alt[k]),
            "position_covariance": [pee, pne, 0.0, pne, pnn, 0.0, 0.0, 0.0, float(var_up_m2)],
            "position_covariance_type": 3,
        }

    return OutputChannel.rows(topic, "foxglove.LocationFix", np.asarray(time_ns), payload)


def navigation_channels(run) -> list[OutputChannel]:
    """``/nav/ins``, ``/nav/map_aided`` (``foxglove.LocationFix``), ``/nav/error``
    (``aeromag.NavigationError``) and ``/nav/innovation`` (``aeromag.NavigationInnovation``)
    of a :class:`pipeline.navigation.stage.NavigationRun`, one message per epoch of its window
    (innovations: per map update)."""
    gm = run.geomap
    t = run.time_ns
    ins_en, aid_en = run.ins_en(), run.aided_en()
    ins_lat, ins_lon = gm.to_geodetic(ins_en[:, 0], ins_en[:, 1])
    aid_lat, aid_lon = gm.to_geodetic(aid_en[:, 0], aid_en[:, 1])
    alt_ins = run.true_alt_m + run.ins_error[:, 2]
    alt_aid = alt_ins - run.result.state[:, 2]
    # the altitude is barometer-aided: its variance is the INS grade's barometer bias
    var_up = float(run.settings_grade().baro_sigma_m ** 2)
    chans = [
        location_channel("/nav/ins", t, ins_lat, ins_lon, alt_ins, run.ins_cov_m2, var_up),
        location_channel(
            "/nav/map_aided", t, aid_lat, aid_lon, alt_aid, run.result.pos_cov_m2, var_up
        ),
    ]
    ei, ea = run.ins_error_ne(), run.aided_error_ne()
    fp, cp = run.result.pos_cov_m2, run.crlb_cov_m2
    f_drms = np.sqrt(np.maximum(fp[:, 0, 0] + fp[:, 1, 1], 0.0))
    c_drms = np.sqrt(np.maximum(cp[:, 0, 0] + cp[:, 1, 1], 0.0))
    seg, sel, upd = run.segment_id, run.selected, run.result.updated

    def err(k: int) -> dict:
        return {
            "segment": str(seg[k]),
            "selected": bool(sel[k]),
            "map_update": bool(upd[k]),
            "ins_north_m": float(ei[k, 0]),
            "ins_east_m": float(ei[k, 1]),
            "ins_horizontal_m": float(np.hypot(*ei[k])),
            "map_aided_north_m": float(ea[k, 0]),
            "map_aided_east_m": float(ea[k, 1]),
            "map_aided_horizontal_m": float(np.hypot(*ea[k])),
            "filter_drms_m": float(f_drms[k]),
            "crlb_drms_m": float(c_drms[k]),
        }

    chans.append(OutputChannel.rows("/nav/error", "aeromag.NavigationError", t, err))
    ix = np.flatnonzero(np.isfinite(run.result.innovation_nT))
    inn, var = run.result.innovation_nT[ix], run.result.innovation_var_nT2[ix]
    z = run.anomaly_nT[ix]
    name = run.settings.filter

    def innovation(k: int) -> dict:
        sd = float(np.sqrt(var[k]))
        return {
            "segment": str(seg[ix[k]]),
            "filter": name,
            "measured_nT": float(z[k]),
            "innovation_nT": float(inn[k]),
            "innovation_sigma_nT": sd,
            "normalised": float(inn[k] / sd) if sd > 0 else 0.0,
        }

    chans.append(
        OutputChannel.rows("/nav/innovation", "aeromag.NavigationInnovation", t[ix], innovation)
    )
    return chans


def map_channels(flight: Flight, seg: Segmentation, mr) -> list[OutputChannel]:
    """Output channels of a map run: ``/map/frame`` (the grids' georeference),
    ``/map/anomaly``, ``/map/anomaly_filtered``, ``/map/uncertainty`` (the anomaly grid's
    1-sigma error per cell, nT, when the survey has three lines or more; ``foxglove.Grid``),
    ``/map/lines`` (the levelled line samples) and ``/map/tracks`` (``foxglove.GeoJSON``).
    """
    t0 = int(flight.time_ns[0])
    out = [
        map_frame_channel(mr, t0),
        grid_channel("/map/anomaly", t0, mr.grid),
        grid_channel("/map/anomaly_filtered", t0, mr.filtered),
    ]
    if mr.uncertainty is not None:
        out.append(grid_channel("/map/uncertainty", t0, mr.uncertainty, "uncertainty_nT"))
    return [*out, line_samples_channel(flight, mr), tracks_channel(flight, seg, t0)]


def enhancement_channels(grids: dict[str, Grid], settings, time_ns: int) -> list[OutputChannel]:
    """``foxglove.Grid`` channels of enhancement grids (topic -> grid), field names from
    the settings' products."""
    names = {p.topic: p.field_name for p in settings.products}
    return [grid_channel(t, time_ns, g, names[t]) for t, g in grids.items()]


def quality_channels(flight: Flight, q: QualityRun) -> list[OutputChannel]:
    """Output channels of a quality run: ``/quality/heading_error``, ``/quality/crossovers``."""
    return [heading_error_channel(flight, q), crossover_channel(flight, q)]
