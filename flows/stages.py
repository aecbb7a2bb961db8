"""File-level wrappers of pipeline stages, shared by the CLI and the flow tasks.

These read recordings, call pure ``pipeline`` functions and write outputs atomically; they
hold no processing logic of their own.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt

from pipeline import __version__
from pipeline.compensate import FitSettings
from pipeline.compensate.stage import CompensationRun, run_compensation
from pipeline.errors import AeromagError
from pipeline.io.reader import Flight, read_flight
from pipeline.io.writer import OutputChannel, write_json_atomic, write_with_new_channels
from pipeline.outputs import compensated_channel, model_message, segment_channel
from pipeline.plots import lcurve_figure
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
