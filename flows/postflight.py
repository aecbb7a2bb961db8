"""The post-flight flow: ingest -> segment -> compensate (T-L baselines and AGG-TL) -> map ->
quality -> write.

Tasks are thin wrappers of ``pipeline`` functions; all logic lives there.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from prefect import flow, task

from flows.stages import (
    compensation_lines,
    map_channels,
    map_figures,
    map_lines,
    quality_channels,
    quality_fields,
    quality_figures,
    quality_lines,
    save_figure,
    tl_alias,
    try_segment,
)
from pipeline import __version__
from pipeline.compensate import FitSettings, bandpassed
from pipeline.compensate.stage import CompensationRun, run_compensation
from pipeline.io.reader import Flight, read_flight
from pipeline.io.writer import OutputChannel, write_json_atomic, write_with_new_channels
from pipeline.maps.stage import MapRun, build_map
from pipeline.outputs import compensated_channel, model_message, segment_channel
from pipeline.plots import compensation_figure, lcurve_figure
from pipeline.quality.stage import QualityRun, fom_table, run_quality
from pipeline.report import LOG_INFO, flight_summary, ingest_lines, log_channel, run_metadata
from pipeline.segment import Segmentation

BASELINES, GRADIENT_AWARE = ("tl16", "tl18"), "agg-tl"


def output_paths(recording: str | Path, out_dir: str | Path) -> dict[str, Path]:
    stem = Path(recording).stem
    out = Path(out_dir)
    return {"mcap": out / f"{stem}.processed.mcap", "summary": out / f"{stem}.summary.json"}


@task(name="ingest")
def ingest(recording: str) -> Flight:
    return read_flight(recording)


@task(name="segment")
def segment(flight: Flight) -> tuple[Segmentation | None, str]:
    return try_segment(flight)


@task(name="compensate")
def compensate(flight: Flight, seg: Segmentation | None, model: str) -> CompensationRun:
    return run_compensation(flight, seg, FitSettings(model=model))


@task(name="map")
def make_map(flight: Flight, seg: Segmentation, compensated_nT) -> MapRun:
    return build_map(flight, seg, compensated_nT)


@task(name="quality")
def assess_quality(flight: Flight, seg: Segmentation,
                   runs: dict[str, CompensationRun]) -> QualityRun:
    fields, _, _ = quality_fields(flight, seg, runs)
    t = flight.data["time_s"].to_numpy(float)
    fom = fom_table(t, fields["raw"], {m: r.compensated_nT for m, r in runs.items()},
                    seg.boxes()) if seg.boxes() else None
    return run_quality(flight, seg, fields, tl_alias(fields), fom)


@task(name="write-outputs")
def write_outputs(recording: str, out_dir: str, channels: list[OutputChannel],
                  summary: dict[str, Any], figures: dict[str, Any]) -> dict[str, str]:
    paths = output_paths(recording, out_dir)
    for name, fig in figures.items():
        paths[name] = save_figure(fig, Path(out_dir) / f"{Path(recording).stem}.{name}.png")
    write_with_new_channels(recording, paths["mcap"], channels,
                            metadata={"aeromag.run": run_metadata()})
    summary = {**summary, "outputs": {k: str(v) for k, v in paths.items()},
               "channels_written": sorted({c.topic for c in channels if c.messages})}
    write_json_atomic(paths["summary"], summary)
    return {k: str(v) for k, v in paths.items()}


@flow(name="postflight", log_prints=False)
def postflight(recording: str, out_dir: str) -> dict[str, Any]:
    """Process one flight recording into an output MCAP and a summary JSON in ``out_dir``."""
    recording, out_dir = str(recording), str(out_dir)
    flight = ingest(recording)
    lines = ingest_lines(flight)
    channels: list[OutputChannel] = []
    summary: dict[str, Any] = {"aeromag_version": __version__, "input": flight_summary(flight)}
    figures: dict[str, Any] = {}
    seg, why = segment(flight)
    if why:
        lines.append((LOG_INFO, why))
    if seg is not None:
        channels.append(segment_channel(flight, seg))
        summary["segments"] = {"source": seg.source,
                               "epochs": {lab: int(seg.mask(lab).sum()) for lab in
                                          ("calibration", "survey", "tie", "validation",
                                           "turn", "transit")},
                               "calibration_passes": len(seg.passes()),
                               "boxes": len(seg.boxes())}
    if flight.has("vector_x_nT") and seg is not None and seg.passes():
        models = [*BASELINES] + ([GRADIENT_AWARE] if flight.has("lat_deg", "alt_m") else [])
        runs = {m: compensate(flight, seg, m) for m in models}
        final = models[-1]
        model_ch = OutputChannel("/compensation/model", "aeromag.CompensationModel")
        for m, run in runs.items():
            lines += compensation_lines(run)
            topic = "/mag/compensated" if m == final else f"/mag/compensated/{m}"
            channels.append(compensated_channel(flight, run, topic))
            model_message(flight, run, model_ch)
        channels.append(model_ch)
        summary["compensation"] = {"final": final, **{m: r.summary() for m, r in runs.items()}}
        lc = runs[final].model.lcurve
        if lc is not None:
            figures["lcurve"] = lcurve_figure(lc, f"L-curve, {final}")
        t = flight.data["time_s"].to_numpy()
        figures["compensation"] = compensation_figure(
            t, bandpassed(t, flight.data["scalar_nT"].to_numpy(), (0.1, 0.9), 4),
            {m: bandpassed(t, r.compensated_nT, (0.1, 0.9), 4) for m, r in runs.items()},
            seg.passes())
        if seg.mask("survey").sum() > 100 and flight.has("lat_deg", "alt_m"):
            mr = make_map(flight, seg, runs[final].compensated_nT)
            lines += map_lines(mr)
            channels += map_channels(flight, seg, mr)
            summary["map"] = mr.summary()
            figures.update(map_figures(mr))
            q = assess_quality(flight, seg, runs)
            lines += quality_lines(q)
            channels += quality_channels(flight, q)
            summary["quality"] = q.summary()
            figures.update(quality_figures(q))
    channels.insert(0, log_channel(flight, lines, "postflight"))
    outputs = write_outputs(recording, out_dir, channels, summary, figures)
    return {**summary, "outputs": outputs}
