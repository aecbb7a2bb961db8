"""The single-stage commands (``aeromag compensate``, ``map``, ``quality``, ``audit``,
``vector``, ``enhance``; ``navigate`` in :mod:`pipeline.run.navigate`): each reads a
recording, runs its stage with the configuration's section (``--config``; a command's
options override its keys, :func:`command_config`) through the same functions as the
post-flight flow (:mod:`pipeline.run.fields`, :mod:`pipeline.run.steps`), and writes its
output recording and summary atomically.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.compensate import EXTENSIONS
from pipeline.compensate.stage import run_compensation
from pipeline.config import Config
from pipeline.despike import DespikeResult
from pipeline.errors import AeromagError
from pipeline.flight import Flight
from pipeline.io.reader import read_flight
from pipeline.io.writer import (
    OutputChannel,
    write_json_atomic,
    write_text_atomic,
    write_with_new_channels,
)
from pipeline.maps.stage import build_map
from pipeline.products.channels import (
    compensated_channel,
    despike_channels,
    enhancement_channels,
    field_channel,
    map_channels,
    model_message,
    quality_channels,
    segment_channel,
    vector_channel,
)
from pipeline.products.figures import lcurve_figure, map_figures, quality_figures
from pipeline.products.log import (
    LOG_INFO,
    compensation_lines,
    despike_lines,
    ingest_lines,
    log_channel,
    map_lines,
    quality_lines,
)
from pipeline.products.summary import build_summary, run_metadata
from pipeline.run.fields import (
    assess_quality,
    compensable,
    configured_models,
    existing_compensated,
    final_compensation,
    quality_fields,
    try_segment,
    uncompensated,
)
from pipeline.run.outputs import model_channels, refuse_existing, save_figure
from pipeline.run.steps import despike_stage, vector_run


class OptionError(AeromagError):
    """A command-line option's value that the configuration refuses (the message names the
    option)."""


def _shown(value) -> str:
    if isinstance(value, str):
        return repr(value)
    return " ".join(str(v) for v in value) if isinstance(value, list | tuple) else str(value)


def command_config(config: Path | None, options: dict[str, tuple[str, object]]) -> Config:
    """The configuration of a single-stage command: ``config`` (a TOML file; None: the
    shipped defaults), checked, with each option given (value not None) overriding its key,
    ``{"--option": ("section.key", value)}``, checked like a file.

    Raises
    ------
    AeromagError
        The file is invalid.
    OptionError
        An option's value is refused (``--option VALUE: section.key ...``).
    """
    cfg = Config.load(config)
    cfg.validate()
    for option, (key, value) in options.items():
        if value is None:
            continue
        try:
            cfg = cfg.with_values({key: list(value) if isinstance(value, tuple) else value})
            cfg.validate()
        except AeromagError as exc:
            raise OptionError(f"{option} {_shown(value)}: {exc.problem}") from None
    return cfg


def read_despiked(
    src: Path, cfg: Config | None, **read_options: Any
) -> tuple[Flight, DespikeResult | None, list[tuple[int, str]]]:
    """A single-stage command's flight, despiked as ``aeromag process`` does when the
    configuration's ``despike.enabled`` (the result and its log line; None and none when not).
    """
    cfg = cfg or Config.load()
    flight = read_flight(src, **read_options)
    if not cfg["despike"]["enabled"]:
        return flight, None, []
    flight, res = despike_stage(flight, cfg)
    return flight, res, despike_lines(res)


def compensate_recording(
    src: Path,
    dst: Path,
    summary_path: Path,
    cfg: Config,
    calibration: str = "auto",
    scalar_topic: str | None = None,
    vector_topic: str | None = None,
) -> dict[str, Any]:
    """``aeromag compensate``: fit the configuration's final model this flight can fit (as
    ``aeromag process``; ``--model`` makes it the only one), with its settings, and write
    the output recording and summary."""
    flight, despiked, dlines = read_despiked(
        src, cfg, scalar_topic=scalar_topic, vector_topic=vector_topic
    )
    flight.require("vector_x_nT", purpose="compensation")
    models = configured_models(flight, cfg) or cfg["compensation"]["models"]
    settings = cfg.fit_settings(models[-1])
    seg, why = try_segment(flight)
    run = run_compensation(flight, seg, settings, calibration)
    lines = ingest_lines(flight) + dlines + ([(LOG_INFO, why)] if why else [])
    lines += compensation_lines(run)
    channels: list[OutputChannel] = [log_channel(flight, lines, "compensate")]
    if seg is not None:
        channels.append(segment_channel(flight, seg))
    channels += [compensated_channel(flight, run), model_message(flight, run)]
    if run.model.model in EXTENSIONS:  # also under its own name, as in the post-flight flow
        channels.append(compensated_channel(flight, run, f"/mag/compensated/{run.model.model}"))
    channels += despike_channels(flight, despiked)
    extra: dict[str, Any] = {}
    if run.model.lcurve is not None:
        png = summary_path.with_name(summary_path.stem + ".lcurve.png")
        save_figure(lcurve_figure(run.model.lcurve, f"L-curve, {run.model.model}"), png)
        extra["lcurve_png"] = str(png)
    write_with_new_channels(src, dst, channels, metadata={"aeromag.run": run_metadata()})
    summary = build_summary(
        flight,
        despiked=despiked,
        **run.summary(),
        compensation={"final": run.model.model, run.model.model: run.summary()},
        calibration=calibration,
        scalar_topic=flight.topic_of["scalar"],
        vector_topic=flight.topic_of.get("vector"),
        **extra,
        outputs={"mcap": dst, "summary": summary_path},
    )
    write_json_atomic(summary_path, summary)
    return summary


def enhance_recording(src: Path, dst: Path, cfg: Config) -> dict[str, Any]:
    """``aeromag enhance``: the configured enhancements of a processed recording's anomaly
    grid, added as ``/map/*`` grid channels to a copy of it (RTP with the IGRF direction of
    its ``/map/frame``)."""
    from pipeline.export.source import MAKE_MAPS, read_map_products
    from pipeline.maps.enhance import enhance, refused

    settings = cfg.enhance_settings()
    mp = read_map_products(src)
    source = mp.grid(settings.source)
    if source is None:
        raise AeromagError(
            f"no /map/{settings.source} grid to enhance: {MAKE_MAPS}",
            file=src,
            channel=f"/map/{settings.source}",
        )
    f = mp.frame
    if not (np.isfinite(f.igrf_inclination_deg) and np.isfinite(f.igrf_declination_deg)):
        raise AeromagError(
            "the map frame has no main-field direction for the reduction to the pole",
            file=src,
            channel="/map/frame",
        )
    try:
        grids = enhance(
            source.grid,
            settings.products,
            f.igrf_inclination_deg,
            f.grid_declination_deg,  # the grid's axes: true declination less convergence
            settings.pad_fraction,
        )
    except ValueError as exc:
        raise AeromagError(f"enhance: {exc}", file=src, channel=source.topic) from None
    skipped = refused(settings.products, f.igrf_inclination_deg)
    if not grids:
        raise AeromagError(
            "; ".join(skipped) or "no enhancement to write", file=src, channel=source.topic
        )
    channels = enhancement_channels(grids, settings, source.time_ns)
    meta = {
        "aeromag.enhance": {
            **run_metadata(),
            "source": source.topic,
            "products": ",".join(grids),
            "inclination_deg": f.igrf_inclination_deg,
            "declination_deg": f.igrf_declination_deg,
        }
    }
    write_with_new_channels(src, dst, channels, metadata=meta)
    return {
        "channels": list(grids),
        "skipped": skipped,
        "source": source.name,
        "inclination_deg": f.igrf_inclination_deg,
        "declination_deg": f.igrf_declination_deg,
        "output": str(dst),
    }


def map_recording(
    src: Path, dst: Path, summary_path: Path, cfg: Config, lag_s: float = 0.0
) -> dict:
    """``aeromag map``: segment and compensate when needed (the configuration's final model,
    with its settings, as ``aeromag process``), then grid, level and filter with ``[map]``
    (``lag_s``: the magnetometer lag removed, s)."""
    flight, despiked, dlines = read_despiked(src, cfg)
    seg, why = try_segment(flight)
    if seg is None:
        raise AeromagError(f"mapping needs the flight lines: {why}", file=src, channel="/gnss/fix")
    present = set(flight.all_topics)
    lines = ingest_lines(flight)
    field = "compensated"
    if existing_compensated(flight) or compensable(flight, seg):
        comp, more, channels, comp_summary = final_compensation(flight, seg, cfg, "map")
    else:  # nothing to fit a model with: the despiked scalar, said in the log
        (field, comp), more, channels, comp_summary = uncompensated(flight), [], [], None
    if comp_summary is not None or field == "raw":  # from the despiked record
        lines += dlines
    else:
        despiked = None  # the recording's own /mag/compensated was used
    lines += more
    mr = build_map(flight, seg, comp, replace(cfg.map_settings(), lag_s=lag_s), field)
    lines += map_lines(mr)
    channels += [segment_channel(flight, seg), *map_channels(flight, seg, mr)]
    channels.insert(0, log_channel(flight, lines, "map"))
    channels = [c for c in channels if c.topic not in present]
    figures = {}
    for name, fig in map_figures(mr).items():
        figures[name] = str(
            save_figure(fig, summary_path.with_name(f"{summary_path.stem}.{name}.png"))
        )
    write_with_new_channels(
        src,
        dst,
        channels,
        metadata={"aeromag.run": run_metadata()},
    )
    summary = build_summary(
        flight,
        despiked=despiked,
        compensation=comp_summary,
        map_run=mr,
        figures=figures,
        outputs={"mcap": dst, "summary": summary_path},
    )
    write_json_atomic(summary_path, summary)
    return summary


def quality_recording(
    src: Path,
    summary_path: Path,
    cfg: Config,
    out: Path | None = None,
) -> dict[str, Any]:
    """``aeromag quality``: every stage it needs (with the configuration's settings), then
    the quality figures, plots, summary."""
    flight, despiked, dlines = read_despiked(src, cfg)
    seg, why = try_segment(flight)
    if seg is None:
        raise AeromagError(
            f"quality statistics need the flight lines: {why}", file=src, channel="/gnss/fix"
        )
    fields, lines, fitted = quality_fields(flight, seg, cfg=cfg)
    q = assess_quality(flight, seg, fields, cfg)
    lines = ingest_lines(flight) + dlines + lines + quality_lines(q)
    figures = {
        name: str(save_figure(fig, summary_path.with_name(f"{summary_path.stem}.{name}.png")))
        for name, fig in quality_figures(q).items()
    }
    outputs = {"summary": summary_path}
    if out is not None:
        present = set(flight.all_topics)
        channels = [log_channel(flight, lines, "quality"), *quality_channels(flight, q)]
        if "/flight/segment" not in present:
            channels.append(segment_channel(flight, seg))
        if fitted:  # keep what was fitted: a later run on the output reuses it
            channels += model_channels(flight, fitted, None)[0]
        refuse_existing(src, channels, present, "give an unprocessed recording")
        write_with_new_channels(src, out, channels, metadata={"aeromag.run": run_metadata()})
        outputs["mcap"] = out
    summary = build_summary(flight, despiked=despiked, quality=q, figures=figures, outputs=outputs)
    write_json_atomic(summary_path, summary)
    return summary


def audit_recording(
    src: Path,
    json_path: Path,
    report_dir: Path,
    cfg: Config,
    out: Path | None = None,
    progress=None,
) -> dict[str, Any]:
    """``aeromag audit``: baseline, candidate effects, extended model, gain, report (the
    scalar despiked first when the configuration's ``despike.enabled``, as ``process``)."""
    from pipeline.audit import run_audit
    from pipeline.audit.report import figures, finding_channel, log_lines, markdown

    flight, despiked, dlines = read_despiked(src, cfg)
    seg, why = try_segment(flight)
    if seg is None:
        raise AeromagError(
            f"the audit needs the calibration passes: {why}", file=src, channel="/gnss/fix"
        )
    flight.require("vector_x_nT", purpose="the model audit")
    res = run_audit(flight, seg, cfg.audit_settings(), progress)
    report_dir.mkdir(parents=True, exist_ok=True)
    images = {
        name: save_figure(fig, report_dir / f"audit_{name}.png").name
        for name, fig in figures(res, flight).items()
    }
    text = markdown(res, Path(src).name, images)
    write_text_atomic(report_dir / "report.md", text)
    report = {
        "markdown": str(report_dir / "report.md"),
        "figures": {k: str(report_dir / v) for k, v in images.items()},
    }
    outputs = None
    if out is not None:
        present = set(flight.all_topics)
        lines = ingest_lines(flight) + dlines + log_lines(res)
        channels = [log_channel(flight, lines, "audit"), finding_channel(flight, res)]
        for topic, comp, model in (
            ("/mag/compensated", res.compensated["extended"], "+".join(res.extended.spec.label())),
            (
                f"/mag/compensated/{res.baseline.spec.base}",
                res.compensated["baseline"],
                res.baseline.spec.base,
            ),
        ):
            if topic not in present:
                channels.append(field_channel(flight, topic, comp, None, model))
        refuse_existing(src, channels, present, "audit the unprocessed recording")
        write_with_new_channels(src, out, channels, metadata={"aeromag.run": run_metadata()})
        outputs = {"mcap": out}
    # NaN (an untestable candidate's figures) becomes null
    j = build_summary(
        flight, despiked=despiked, audit=res, audit_full=True, report=report, outputs=outputs
    )
    write_json_atomic(json_path, j)
    return j


def vector_recording(src: Path, dst: Path, summary_path: Path, cfg: Config) -> dict[str, Any]:
    """``aeromag vector``: calibrate (ellipsoid-kf) or compensate (component-kf, batch) the
    vector magnetometer with ``[vector]`` (its method and fuzzy-R settings, as ``aeromag
    process``) and write its new channel and a summary."""
    method = cfg["vector"]["method"]
    flight = read_flight(src)
    flight.require("vector_x_nT", purpose="the vector stage")
    seg, why = try_segment(flight)
    try:
        run = vector_run(flight, seg, cfg)
    except ValueError as exc:
        raise AeromagError(str(exc), file=src, channel=flight.topic_of.get("vector", "")) from None
    present = set(flight.all_topics)
    if run.output_topic in present:
        raise AeromagError(
            f"the recording already holds {run.output_topic}", file=src, channel=run.output_topic
        )
    ch = vector_channel(flight, run.output_topic, run.vectors_nT, method)
    s = run.summary()
    text = f"vector: {method}: " + ", ".join(
        f"{k} {val['before']:.2f} -> {val['after']:.2f} nT"
        for k, val in s.items()
        if isinstance(val, dict) and "before" in val and not isinstance(val["before"], list)
    )
    lines = ingest_lines(flight) + ([(LOG_INFO, why)] if why else []) + [(LOG_INFO, text)]
    channels = [log_channel(flight, lines, "vector"), ch]
    channels = [c for c in channels if c.topic not in present]
    write_with_new_channels(src, dst, channels, metadata={"aeromag.run": run_metadata()})
    summary = build_summary(flight, vector=run, outputs={"mcap": dst, "summary": summary_path})
    write_json_atomic(summary_path, summary)
    return summary
