"""File-level wrappers of pipeline stages, shared by the CLI and the flow tasks.

These read recordings, call pure ``pipeline`` functions and write outputs atomically; they
hold no processing logic of their own.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import numpy as np

from pipeline import __version__
from pipeline.compensate import FitSettings
from pipeline.compensate.stage import CompensationRun, run_compensation
from pipeline.errors import AeromagError
from pipeline.io.reader import Flight, read_flight
from pipeline.io.writer import OutputChannel, write_json_atomic, write_with_new_channels
from pipeline.maps.stage import MapSettings, build_map
from pipeline.outputs import (
    compensated_channel,
    grid_channel,
    model_message,
    segment_channel,
    tracks_channel,
)
from pipeline.plots import lcurve_figure, map_figure
from pipeline.report import LOG_INFO, flight_summary, ingest_lines, log_channel, run_metadata
from pipeline.segment import Segmentation, segment_flight


def try_segment(flight: Flight) -> tuple[Segmentation | None, str]:
    """Segment when the recording allows it; otherwise say why not."""
    if not (flight.has("plan_kind") or flight.has("lat_deg", "lon_deg")):
        return None, "segmentation skipped: no /gnss/fix and no /plan/line"
    return segment_flight(flight), ""


def save_figure(fig, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.partial.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    tmp.replace(path)
    return path


def compensation_lines(run: CompensationRun) -> list[tuple[int, str]]:
    m = run.model
    fom = run.fom.total if run.fom else None
    text = (f"compensate: {m.model}: {len(m.terms)} terms, lambda {m.lambda_:.3g}, "
            f"{m.n_fit} samples, fit residual {m.fit_residual_nT:.4f} nT")
    if fom and fom["uncompensated"] is not None:
        text += f", FOM {fom['uncompensated']:.2f} -> {fom['compensated']:.2f} nT"
    lines = [(LOG_INFO, text)]
    g = m.gradient_nT_per_m()
    if g:
        lines.append((LOG_INFO, f"compensate: {m.model}: gradient at the calibration site "
                                f"{g['east']:.3f} E, {g['north']:.3f} N, {g['up']:.3f} U nT/m"))
    return lines


def compensate_recording(src: Path, dst: Path, summary_path: Path, settings: FitSettings,
                         calibration: str = "auto", scalar_topic: str | None = None,
                         vector_topic: str | None = None) -> dict[str, Any]:
    """``aeromag compensate``: fit one model and write the output recording and summary."""
    flight = read_flight(src, scalar_topic=scalar_topic, vector_topic=vector_topic)
    flight.require("vector_x_nT", purpose="compensation")
    seg, why = try_segment(flight)
    run = run_compensation(flight, seg, settings, calibration)
    lines = ingest_lines(flight) + ([(LOG_INFO, why)] if why else []) + compensation_lines(run)
    channels: list[OutputChannel] = [log_channel(flight, lines, "compensate")]
    if seg is not None:
        channels.append(segment_channel(flight, seg))
    channels += [compensated_channel(flight, run), model_message(flight, run)]
    summary = {"aeromag_version": __version__, **run.summary(),
               "calibration": calibration, "scalar_topic": flight.topic_of["scalar"],
               "vector_topic": flight.topic_of.get("vector"), "input": flight_summary(flight)}
    if run.model.lcurve is not None:
        png = summary_path.with_name(summary_path.stem + ".lcurve.png")
        save_figure(lcurve_figure(run.model.lcurve, f"L-curve, {run.model.model}"), png)
        summary["lcurve_png"] = str(png)
    write_with_new_channels(src, dst, channels, metadata={"aeromag.run": run_metadata()})
    summary["outputs"] = {"mcap": str(dst), "summary": str(summary_path)}
    write_json_atomic(summary_path, summary)
    return summary


def require_readable(path: Path) -> None:
    if not path.is_file():
        raise AeromagError("file not found", file=path)


# --------------------------------------------------------------------------------------------
def existing_compensated(flight: Flight) -> np.ndarray | None:
    """``/mag/compensated`` already in the recording (an earlier run), on the flight epochs."""
    from pipeline.io.contract import rule_for_topic
    from pipeline.io.reader import decode_topic, read_topics

    raw = read_topics(flight.source, ["/mag/compensated"]).topics.get("/mag/compensated")
    if raw is None or not raw.count:
        return None
    s = decode_topic(raw, rule_for_topic("/mag/compensated"))
    if s.time_ns.size < 2:
        return None
    t0 = flight.time_ns[0]
    return np.interp((flight.time_ns - t0) / 1e9, (s.time_ns - t0) / 1e9,
                     s.values["total_nT"], left=np.nan, right=np.nan)


def map_channels(flight: Flight, seg: Segmentation, mr) -> list[OutputChannel]:
    t0 = int(flight.time_ns[0])
    return [grid_channel("/map/anomaly", t0, mr.grid),
            grid_channel("/map/anomaly_filtered", t0, mr.filtered),
            tracks_channel(flight, seg, t0)]


def map_figures(mr) -> dict[str, object]:
    lo, hi = np.nanpercentile(mr.grid.values, [1, 99])
    return {"anomaly": map_figure(mr.grid, mr.lines, "levelled anomaly (nT)", lo, hi),
            "anomaly_filtered": map_figure(mr.filtered, mr.lines,
                                           f"ARIMA{tuple(mr.model.order)} + Kalman filtered",
                                           lo, hi)}


def map_lines(mr) -> list[tuple[int, str]]:
    s = mr.summary()
    return [(LOG_INFO, f"map: grid {s['grid_shape'][0]} x {s['grid_shape'][1]} cells of "
                       f"{s['cell_m']:.2f} m, line spacing {s['line_spacing_m']:.1f} m"),
            (LOG_INFO, f"map: crossover RMS {s['crossover_rms_nT']['before']:.3f} -> "
                       f"{s['crossover_rms_nT']['after']:.3f} nT "
                       f"({s['leveling']['crossovers']} crossovers)"),
            (LOG_INFO, f"map: ARIMA{tuple(s['arima_order'])} "
                       f"ar {np.round(s['arima_coefficients']['ar'], 4).tolist()} "
                       f"ma {np.round(s['arima_coefficients']['ma'], 4).tolist()}; "
                       f"Kalman measurement noise {s['kalman']['measurement_noise_nT']:.3f} nT")]


def map_recording(src: Path, dst: Path, summary_path: Path, settings: MapSettings) -> dict:
    """``aeromag map``: segment and compensate when needed, then grid, level and filter."""
    flight = read_flight(src)
    seg, why = try_segment(flight)
    if seg is None:
        raise AeromagError(f"mapping needs the flight lines: {why}", file=src,
                           channel="/gnss/fix")
    present = set(read_topics_names(src))
    channels: list[OutputChannel] = []
    lines = ingest_lines(flight)
    comp = existing_compensated(flight)
    summary: dict[str, Any] = {"aeromag_version": __version__, "input": flight_summary(flight)}
    if comp is None:
        model = "agg-tl" if flight.has("lat_deg", "alt_m") else "tl16"
        run = run_compensation(flight, seg, FitSettings(model=model))
        comp = run.compensated_nT
        lines += compensation_lines(run)
        channels += [compensated_channel(flight, run), model_message(flight, run)]
        summary["compensation"] = run.summary()
    else:
        lines.append((LOG_INFO, "map: using /mag/compensated from the recording"))
    mr = build_map(flight, seg, comp, settings)
    lines += map_lines(mr)
    channels += [segment_channel(flight, seg), *map_channels(flight, seg, mr)]
    channels.insert(0, log_channel(flight, lines, "map"))
    channels = [c for c in channels if c.topic not in present]
    figures = {}
    for name, fig in map_figures(mr).items():
        figures[name] = str(save_figure(fig, summary_path.with_name(
            f"{summary_path.stem}.{name}.png")))
    write_with_new_channels(src, dst, channels, metadata={"aeromag.run": run_metadata()})
    summary.update({"map": mr.summary(), "figures": figures,
                    "outputs": {"mcap": str(dst), "summary": str(summary_path)}})
    write_json_atomic(summary_path, summary)
    return summary


def read_topics_names(path: Path) -> list[str]:
    from mcap.reader import make_reader

    with path.open("rb") as f:
        summ = make_reader(f).get_summary()
    return [c.topic for c in summ.channels.values()] if summ else []
