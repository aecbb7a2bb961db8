"""File-level wrappers of pipeline stages, shared by the CLI and the flow tasks.

These read recordings, call pure ``pipeline`` functions and write outputs atomically; they
hold no processing logic of their own.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import numpy as np

from pipeline.compensate import EXTENSIONS, FitSettings
from pipeline.compensate.stage import CompensationRun, run_compensation
from pipeline.config import Config
from pipeline.despike import DespikeResult, despike_flight
from pipeline.errors import AeromagError
from pipeline.flight import Flight
from pipeline.io.reader import read_flight
from pipeline.io.writer import (
    OutputChannel,
    atomic_output,
    write_json_atomic,
    write_text_atomic,
    write_with_new_channels,
)
from pipeline.maps.grid import Grid
from pipeline.maps.stage import MapSettings, build_map
from pipeline.products.channels import (
    compensated_channel,
    despike_channels,
    enhancement_channels,
    field_channel,
    map_channels,
    model_message,
    navigation_channels,
    quality_channels,
    segment_channel,
    vector_channel,
)
from pipeline.products.figures import (
    enhancement_figures,
    flight_map,
    lcurve_figure,
    map_figures,
    navigation_figures,
    quality_figures,
)
from pipeline.products.html import render_html
from pipeline.products.layout import recording_layout
from pipeline.products.log import (
    LOG_INFO,
    LOG_WARNING,
    compensation_lines,
    despike_lines,
    ingest_lines,
    log_channel,
    map_lines,
    navigation_lines,
    quality_lines,
)
from pipeline.products.markdown import report_markdown
from pipeline.products.summary import build_summary, jsonable, run_metadata
from pipeline.quality.stage import QualityRun, QualitySettings, fom_table, run_quality
from pipeline.segment import Segmentation, segment_flight


def try_segment(flight: Flight) -> tuple[Segmentation | None, str]:
    """Segment when the recording allows it; otherwise say why not."""
    if not (flight.has("plan_kind") or flight.has("lat_deg", "lon_deg")):
        return None, "segmentation skipped: no /gnss/fix and no /plan/line"
    return segment_flight(flight), ""


def save_figure(fig, path: Path) -> Path:
    """Save a matplotlib figure as PNG (110 dpi) atomically and close it.

    Returns
    -------
    Path
        ``path``.
    """
    with atomic_output(path) as f:
        fig.savefig(f, dpi=110, format="png")
    plt.close(fig)
    return path


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
    settings: FitSettings | None,
    calibration: str = "auto",
    scalar_topic: str | None = None,
    vector_topic: str | None = None,
    cfg: Config | None = None,
) -> dict[str, Any]:
    """``aeromag compensate``: fit one model and write the output recording and summary.
    ``settings`` None: the configuration's final model this flight can fit (as ``aeromag
    process``), with its settings."""
    cfg = cfg or Config.load()
    flight, despiked, dlines = read_despiked(
        src, cfg, scalar_topic=scalar_topic, vector_topic=vector_topic
    )
    flight.require("vector_x_nT", purpose="compensation")
    if settings is None:
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


def require_readable(path: Path) -> None:
    """Raise a one-line AeromagError when ``path`` is not a file."""
    if not path.is_file():
        raise AeromagError("file not found", file=path)


# --------------------------------------------------------------------------------------------
def existing_compensated(flight: Flight) -> dict[str, np.ndarray]:
    """Compensated fields already in the recording (an earlier run), on the flight epochs.

    Returns model id -> nT per epoch, the final ``/mag/compensated`` model last.
    """
    from pipeline.io.contract import rule_for_topic
    from pipeline.io.reader import decode_topic, read_topics

    names = [
        t for t in flight.all_topics if t == "/mag/compensated" or t.startswith("/mag/compensated/")
    ]
    raw = read_topics(flight.source, names).topics if names else {}
    out: dict[str, np.ndarray] = {}
    t0 = flight.time_ns[0]
    for topic in sorted(raw, key=lambda t: (t == "/mag/compensated", t)):
        if not raw[topic].count:
            continue
        s = decode_topic(raw[topic], rule_for_topic(topic))
        if s.time_ns.size < 2:
            continue
        models = s.labels.get("model")
        name = str(models[0]) if models is not None and models.size else topic.rsplit("/", 1)[-1]
        out.pop(name, None)
        out[name] = np.interp(
            (flight.time_ns - t0) / 1e9,
            (s.time_ns - t0) / 1e9,
            s.values["total_nT"],
            left=np.nan,
            right=np.nan,
        )
    return out


def enhance_recording(src: Path, dst: Path, cfg: Config) -> dict[str, Any]:
    """``aeromag enhance``: the configured enhancements of a processed recording's anomaly
    grid, added as ``/map/*`` grid channels to a copy of it (RTP with the IGRF direction of
    its ``/map/frame``)."""
    from pipeline.export.source import MAKE_MAPS, read_map_products
    from pipeline.maps.enhance import enhance

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
            f.igrf_declination_deg,
            settings.pad_fraction,
        )
    except ValueError as exc:
        raise AeromagError(f"enhance: {exc}", file=src, channel=source.topic) from None
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
        "source": source.name,
        "inclination_deg": f.igrf_inclination_deg,
        "declination_deg": f.igrf_declination_deg,
        "output": str(dst),
    }


def configured_models(flight: Flight, cfg: Config) -> list[str]:
    """The configuration's compensation models this flight can fit, in order (the last is
    the final one): AGG-TL needs positions."""
    return [
        m for m in cfg["compensation"]["models"] if m != "agg-tl" or flight.has("lat_deg", "alt_m")
    ]


def final_compensation(
    flight: Flight, seg: Segmentation, cfg: Config, stage: str
) -> tuple[np.ndarray, list[tuple[int, str]], list[OutputChannel], dict | None]:
    """The compensated field of a recording, the way the single-stage commands get it: its
    own ``/mag/compensated`` (an earlier run), else the configuration's final model this flight
    can fit, fitted with its settings as ``aeromag process`` does (no audit).

    Returns
    -------
    compensated_nT : ndarray
        Per epoch, nT.
    lines : list of (int, str)
        Log lines.
    channels : list of OutputChannel
        ``/mag/compensated`` and ``/compensation/model`` when fitted here (else empty).
    summary : dict or None
        The compensation summary when fitted here.
    """
    earlier = existing_compensated(flight)
    if earlier:
        return (
            list(earlier.values())[-1],
            [(LOG_INFO, f"{stage}: using /mag/compensated from the recording")],
            [],
            None,
        )
    models = configured_models(flight, cfg)
    if not models:
        raise AeromagError(
            "no configured compensation model fits this flight (agg-tl needs positions)",
            file=flight.source,
            channel="/gnss/fix",
        )
    run = run_compensation(flight, seg, cfg.fit_settings(models[-1]))
    return (
        run.compensated_nT,
        compensation_lines(run),
        [compensated_channel(flight, run), model_message(flight, run)],
        run.summary(),
    )


def map_recording(
    src: Path, dst: Path, summary_path: Path, settings: MapSettings, cfg: Config | None = None
) -> dict:
    """``aeromag map``: segment and compensate when needed (the configuration's final model,
    with its settings, as ``aeromag process``), then grid, level and filter."""
    cfg = cfg or Config.load()
    flight, despiked, dlines = read_despiked(src, cfg)
    seg, why = try_segment(flight)
    if seg is None:
        raise AeromagError(f"mapping needs the flight lines: {why}", file=src, channel="/gnss/fix")
    present = set(flight.all_topics)
    lines = ingest_lines(flight)
    comp, more, channels, comp_summary = final_compensation(flight, seg, cfg, "map")
    if comp_summary is not None:  # compensated here, from the despiked record
        lines += dlines
    else:
        despiked = None  # the recording's own /mag/compensated was used
    lines += more
    mr = build_map(flight, seg, comp, settings)
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


# --------------------------------------------------------------------------------------------
# quality
def quality_fields(
    flight: Flight,
    seg: Segmentation,
    runs: dict[str, CompensationRun] | None = None,
    cfg: Config | None = None,
) -> tuple[dict[str, np.ndarray], list[tuple[int, str]], dict[str, CompensationRun]]:
    """Raw plus every compensated state: from ``runs``, else from the recording's own
    ``/mag/compensated*`` channels, else fitted here (the configuration's models with its
    settings, as ``aeromag process``; returned too)."""
    fields = {"raw": flight.data["scalar_nT"].to_numpy(float)}
    lines: list[tuple[int, str]] = []
    if runs is not None:  # the caller's runs (possibly none): never fitted here
        fields.update({m: r.compensated_nT for m, r in runs.items()})
        return fields, lines, {}
    earlier = existing_compensated(flight)
    if earlier:
        lines.append(
            (
                LOG_INFO,
                "quality: using the compensated fields in the recording: " + ", ".join(earlier),
            )
        )
        fields.update(earlier)
        return fields, lines, {}
    if not flight.has("vector_x_nT") or not seg.passes():
        lines.append(
            (
                LOG_WARNING,
                "quality: no vector magnetometer or no calibration pass: "
                "only the raw field is assessed",
            )
        )
        return fields, lines, {}
    fitted = {}
    cfg = cfg or Config.load()
    for m in configured_models(flight, cfg):
        fitted[m] = run = run_compensation(flight, seg, cfg.fit_settings(m))
        lines += compensation_lines(run)
        fields[m] = run.compensated_nT
    return fields, lines, fitted


def tl_alias(fields: dict[str, np.ndarray], base: str | None = None) -> str | None:
    """The T-L model reported as ``tl``: the one with AGG-TL's term set ``base`` (None: the
    shipped ``compensation.agg_base``)."""
    base = base or FitSettings(model="agg-tl").base
    return base if base in fields else next((m for m in ("tl18", "tl16") if m in fields), None)


def _refuse_existing(
    src: Path, channels: list[OutputChannel], present: set[str], advice: str
) -> None:
    """One line naming every output channel the recording already holds (all of them, where
    the writer's own check names the first)."""
    clash = sorted({c.topic for c in channels} & present)
    if clash:
        raise AeromagError(
            f"the recording already holds {', '.join(clash)}; {advice} or omit --out",
            file=src,
            channel=clash[0],
        )


def fom_settings(cfg: Config) -> tuple[tuple[float, float], int]:
    """The band and filter order every FOM table of a run is measured in: the configured
    fit band (``compensation.band_hz``, ``poles``), as the compensation stage's own FOM."""
    c = cfg["compensation"]
    return tuple(c["band_hz"]), c["poles"]


def quality_recording(
    src: Path,
    summary_path: Path,
    settings: QualitySettings,
    out: Path | None = None,
    cfg: Config | None = None,
) -> dict[str, Any]:
    """``aeromag quality``: every stage it needs (with the configuration's settings), then
    the quality figures, plots, summary."""
    cfg = cfg or Config.load()
    flight, despiked, dlines = read_despiked(src, cfg)
    seg, why = try_segment(flight)
    if seg is None:
        raise AeromagError(
            f"quality statistics need the flight lines: {why}", file=src, channel="/gnss/fix"
        )
    fields, lines, fitted = quality_fields(flight, seg, cfg=cfg)
    t = flight.data["time_s"].to_numpy(float)
    fom = (
        fom_table(
            t,
            fields["raw"],
            {k: v for k, v in fields.items() if k != "raw"},
            seg.boxes(),
            *fom_settings(cfg),
        )
        if len(fields) > 1 and seg.boxes()
        else None
    )
    q = run_quality(
        flight, seg, fields, tl_alias(fields, cfg["compensation"]["agg_base"]), fom, settings
    )
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
            channels += _model_channels(flight, fitted, None)[0]
        _refuse_existing(src, channels, present, "give an unprocessed recording")
        write_with_new_channels(src, out, channels, metadata={"aeromag.run": run_metadata()})
        outputs["mcap"] = out
    summary = build_summary(flight, despiked=despiked, quality=q, figures=figures, outputs=outputs)
    write_json_atomic(summary_path, summary)
    return summary


# --------------------------------------------------------------------------------------------
# audit
def audit_recording(
    src: Path,
    json_path: Path,
    report_dir: Path,
    settings,
    out: Path | None = None,
    progress=None,
    cfg: Config | None = None,
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
    res = run_audit(flight, seg, settings, progress)
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
        _refuse_existing(src, channels, present, "audit the unprocessed recording")
        write_with_new_channels(src, out, channels, metadata={"aeromag.run": run_metadata()})
        outputs = {"mcap": out}
    # NaN (an untestable candidate's figures) becomes null
    j = build_summary(
        flight, despiked=despiked, audit=res, audit_full=True, report=report, outputs=outputs
    )
    write_json_atomic(json_path, j)
    return j


# --------------------------------------------------------------------------------------------
# vector magnetometer
def vector_recording(src: Path, dst: Path, summary_path: Path, method: str) -> dict[str, Any]:
    """``aeromag vector``: calibrate (ellipsoid-kf) or compensate (component-kf, batch) the
    vector magnetometer and write its new channel and a summary."""
    from pipeline.vector.stage import run_vector

    flight = read_flight(src)
    flight.require("vector_x_nT", purpose="the vector stage")
    seg, why = try_segment(flight)
    try:
        run = run_vector(flight, seg, method)
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


# --------------------------------------------------------------------------------------------
# the post-flight stages (called by flows.postflight, as Prefect tasks or plainly)
class _Validated:
    """The flight read by :func:`validate_recording`, handed once to the ingest step of the
    same process so that checking a recording before the flow does not read it twice."""

    key: tuple[str, int, int] | None = None
    flight: Flight | None = None
    read_s: float = 0.0  # seconds validate_recording spent reading it
    handed_read_s: float = 0.0  # read_s of the flight last handed out by take()

    @staticmethod
    def stat_key(recording: str | Path) -> tuple[str, int, int]:
        st = Path(recording).stat()
        return str(Path(recording).resolve()), st.st_size, st.st_mtime_ns

    @classmethod
    def take(cls, recording: str | Path) -> Flight | None:
        flight, key = cls.flight, cls.key
        cls.key = cls.flight = None  # handed out once: the memory goes with the flow
        cls.handed_read_s = 0.0
        try:
            same = key is not None and key == cls.stat_key(recording)
        except OSError:
            return None
        if same:
            cls.handed_read_s = cls.read_s
        return flight if same else None


def validate_recording(recording: str | Path) -> Flight:
    """Read and check a recording (scan, channel contract, units) before any flow starts,
    so that bad input fails with one line and no Prefect run at all.

    Raises
    ------
    AeromagError
        Missing, empty or unreadable file, no scalar magnetometer, wrong units.
    """
    require_readable(Path(recording))
    t0 = time.perf_counter()
    flight = read_flight(recording)
    _Validated.read_s = time.perf_counter() - t0
    _Validated.key, _Validated.flight = _Validated.stat_key(recording), flight
    return flight


def forget_validated() -> None:
    """Drop the flight kept by :func:`validate_recording` (frees its memory)."""
    _Validated.key = _Validated.flight = None


def ingest_stage(recording: str) -> Flight:
    """Ingest: the flight :func:`validate_recording` read already, else read it now.

    Parameters
    ----------
    recording : str
        Path of the MCAP recording.

    Returns
    -------
    Flight
    """
    return _Validated.take(recording) or read_flight(recording)


def validated_read_s() -> float:
    """Seconds :func:`validate_recording` spent reading the flight that the last
    :func:`ingest_stage` call took over (0 when it read the recording itself): the ingest
    time of a run checked before its flow started."""
    return _Validated.handed_read_s


def despike_stage(flight: Flight, cfg) -> tuple[Flight, DespikeResult]:
    """Despike the primary scalar magnetometer (Hampel test on its 4th difference) with the
    configuration's ``[despike]`` settings.

    Returns
    -------
    Flight
        The flight with the spike samples replaced (the same object when none was found).
    DespikeResult
    """
    return despike_flight(flight, cfg.despike_settings())


def compensate_stage(flight: Flight, seg: Segmentation, model: str, cfg) -> CompensationRun:
    """Compensate: fit ``model`` (``tl16``, ``tl18`` or ``agg-tl``) with the configuration's
    settings.

    Returns
    -------
    CompensationRun
    """
    return run_compensation(flight, seg, cfg.fit_settings(model))


def audit_stage(flight: Flight, seg: Segmentation, cfg):
    """Audit: :func:`pipeline.audit.run_audit` with the configuration's settings.

    Returns
    -------
    AuditResult
    """
    from pipeline.audit import run_audit

    return run_audit(flight, seg, cfg.audit_settings())


def vector_stage(flight: Flight, seg: Segmentation | None, cfg):
    """Vector magnetometer stage with the configured method.

    Returns
    -------
    VectorRun or str
        The run, or the one-line reason it could not run (logged; the other stages go on).
    """
    from pipeline.vector.stage import run_vector

    try:
        return run_vector(flight, seg, cfg["vector"]["method"], settings=cfg["vector"])
    except (AeromagError, ValueError) as exc:
        return str(exc)  # reported in the log; the other stages go on


def final_field(runs: dict[str, CompensationRun], audit) -> tuple[str, np.ndarray] | None:
    """The field the map is made from: the audit's extended model when it found anything,
    else the last configured model."""
    if audit is not None and audit.findings:
        return "extended", audit.compensated["extended"]
    if runs:
        name = list(runs)[-1]
        return name, runs[name].compensated_nT
    return None


def enhancement_grids(map_run, cfg) -> dict[str, Grid]:
    """The configured enhancements of a map run's grid (``enhance.source``), RTP with the
    main field at the map origin (topic -> grid)."""
    from pipeline.maps.enhance import enhance

    st = cfg.enhance_settings()
    grid = map_run.filtered if st.source == "anomaly_filtered" else map_run.grid
    _, incl, decl = map_run.main_field
    try:
        return enhance(grid, st.products, incl, decl, st.pad_fraction)
    except ValueError as exc:
        raise AeromagError(f"enhance: {exc}", channel=f"/map/{st.source}") from None


def map_stage(flight: Flight, seg: Segmentation, comp: np.ndarray, cfg):
    """Map: reduce, level, grid and filter ``comp`` (compensated field, nT, one per epoch).

    Returns
    -------
    MapRun
    """
    return build_map(flight, seg, comp, cfg.map_settings())


def navigate_stage(flight: Flight, seg: Segmentation | None, comp: np.ndarray, map_run, cfg):
    """Navigation on the flight's own map (``[navigate]``): the validation lines flown with a
    simulated INS aided by the map (``navigate.map``), as ``aeromag navigate`` does.

    Returns
    -------
    NavigationRun or str
        The run, or why navigation was skipped (no validation lines, no map, the map not
        covering them): one log line, never an error.
    """
    from pipeline.navigation.map_io import frame_map
    from pipeline.navigation.stage import run_navigation

    if map_run is None:
        return "no map"
    if seg is None or seg.mask("validation").sum() < 10:
        return "no validation lines"
    which = cfg["navigate"]["map"]
    grid = map_run.filtered if which == "anomaly_filtered" else map_run.grid
    geomap = frame_map(grid, map_run.frame, f"/map/{which}", f"this flight's /map/{which}")
    try:
        return run_navigation(flight, seg, comp, geomap, cfg.navigation_settings())
    except AeromagError as exc:
        return exc.problem
    except (ValueError, np.linalg.LinAlgError) as exc:  # reported; the other outputs go on
        return f"{type(exc).__name__}: {exc}"


def quality_stage(flight: Flight, seg: Segmentation, runs: dict, audit, cfg) -> QualityRun:
    """Quality: every processing state (raw, each model, the extended model) compared at
    the validation lines, with the 12-box FOM table when the calibration boxes were found.

    Returns
    -------
    QualityRun
    """
    fields, _, _ = quality_fields(flight, seg, runs, cfg)
    final = final_field(runs, audit)
    if final is not None and final[0] == "extended":
        fields["extended"] = final[1]
    t = flight.data["time_s"].to_numpy(float)
    fom = (
        fom_table(
            t,
            fields["raw"],
            {k: v for k, v in fields.items() if k != "raw"},
            seg.boxes(),
            *fom_settings(cfg),
        )
        if seg.boxes() and len(fields) > 1
        else None
    )
    return run_quality(
        flight,
        seg,
        fields,
        tl_alias(fields, cfg["compensation"]["agg_base"]),
        fom,
        cfg.quality_settings(),
    )


def _model_channels(flight: Flight, runs: dict, audit) -> tuple[list[OutputChannel], str]:
    final = final_field(runs, audit)
    channels: list[OutputChannel] = []
    if final is None:
        return channels, ""
    model_ch = OutputChannel("/compensation/model", "aeromag.CompensationModel")
    for m, run in runs.items():
        topic = "/mag/compensated" if (final[0] == m) else f"/mag/compensated/{m}"
        channels.append(compensated_channel(flight, run, topic))
        model_message(flight, run, model_ch)
    channels.append(model_ch)
    if final[0] == "extended":
        label = "+".join(audit.extended.spec.label())
        channels.append(field_channel(flight, "/mag/compensated", final[1], None, label))
        return channels, label
    return channels, final[0]


def output_paths(recording: str | Path, out_dir: str | Path) -> dict[str, Path]:
    """Where the post-flight outputs of ``recording`` go."""
    stem = Path(recording).stem
    out = Path(out_dir)
    return {
        "mcap": out / f"{stem}.processed.mcap",
        "summary": out / f"{stem}.summary.json",
        "report": out / f"{stem}.report.md",
        "report_html": out / f"{stem}.report.html",
        "layout": out / f"{stem}.layout.json",
    }


# output_paths keys that are not figures
DOCUMENTS = ("mcap", "summary", "report", "report_html", "layout")


@dataclass
class FlightResults:
    """What the post-flight steps made of one flight, handed to :func:`write_stage`.

    ``runs``: each configured model's compensation (model name -> run); ``audit``, ``vector``,
    ``map_run``, ``quality``: the stages' results (None: not run); ``despiked``: the despike
    step's result; ``nav``: :func:`navigate_stage`'s result (a run, a skip reason, or None:
    not enabled); ``why``: why segmentation failed ("" when it did not).
    """

    flight: Flight
    seg: Any = None  # pipeline.segment.Segmentation
    why: str = ""
    runs: dict[str, CompensationRun] = field(default_factory=dict)
    audit: Any = None  # pipeline.audit.AuditResult
    vector: Any = None  # pipeline.vector.stage.VectorRun
    map_run: Any = None  # pipeline.maps.stage.MapRun
    quality: Any = None  # pipeline.quality.QualityRun
    despiked: DespikeResult | None = None
    nav: Any = None  # pipeline.navigation.stage.NavigationRun | str


def write_stage(
    recording: str,
    out_dir: str,
    cfg,
    results: FlightResults,
    timings: dict[str, float] | None = None,
) -> dict[str, Any]:
    """Every output of the post-flight flow, each written atomically; the summary last (its
    presence marks the recording as done).

    ``timings`` (stage -> seconds of the stages before) goes into the summary as
    ``timings_s`` with this stage's own time (``write``, up to the summary itself), with the
    process's peak resident memory so far (``peak_memory_mb``)."""
    t_start = time.perf_counter()
    r = results
    flight, seg, why, runs = r.flight, r.seg, r.why, r.runs
    audit, vector, map_run, quality = r.audit, r.vector, r.map_run, r.quality
    despiked, nav = r.despiked, r.nav
    from pipeline.audit.report import figures as audit_figures
    from pipeline.audit.report import finding_channel
    from pipeline.audit.report import log_lines as audit_log_lines

    stem = Path(recording).stem
    out = Path(out_dir)
    paths = output_paths(recording, out_dir)
    lines = ingest_lines(flight)
    if why:
        lines.append((LOG_INFO, why))
    channels: list[OutputChannel] = []
    figures: dict[str, Any] = {}
    compensation, grids = None, {}
    lines += despike_lines(despiked)
    channels += despike_channels(flight, despiked)
    if seg is not None:
        channels.append(segment_channel(flight, seg))
        if (
            flight.has("lat_deg", "lon_deg")
            and np.isfinite(flight.data[["lat_deg", "lon_deg"]].to_numpy(float)).all(axis=1).any()
        ):
            figures["flight_map"] = flight_map(flight, seg)
    if runs:
        for run in runs.values():
            lines += compensation_lines(run)
        model_channels, final = _model_channels(flight, runs, audit)
        channels += model_channels
        compensation = {"final": final, **{m: r.summary() for m, r in runs.items()}}
        last = list(runs.values())[-1]
        if last.model.lcurve is not None:
            figures["lcurve"] = lcurve_figure(last.model.lcurve, f"L-curve, {last.model.model}")
        t = flight.data["time_s"].to_numpy()
        from pipeline.compensate import bandpassed
        from pipeline.products.figures import compensation_figure

        band, poles = fom_settings(cfg)  # the configured band, as every FOM
        figures["compensation"] = compensation_figure(
            t,
            bandpassed(t, flight.data["scalar_nT"].to_numpy(), band, poles),
            {m: bandpassed(t, r.compensated_nT, band, poles) for m, r in runs.items()},
            seg.passes(),
            band,
        )
    if audit is not None:
        lines += audit_log_lines(audit)
        channels.append(finding_channel(flight, audit))
        figures.update({f"audit_{k}": v for k, v in audit_figures(audit, flight).items()})
    if isinstance(vector, str):
        lines.append((LOG_WARNING, f"vector: skipped: {vector}"))
    elif vector is not None:
        channels.append(
            vector_channel(flight, vector.output_topic, vector.vectors_nT, vector.method)
        )
        lines.append((LOG_INFO, f"vector: {vector.method} -> {vector.output_topic}"))
    if map_run is not None:
        lines += map_lines(map_run)
        channels += map_channels(flight, seg, map_run)
        figures.update(map_figures(map_run))
        if cfg["enhance"]["enabled"]:
            grids = enhancement_grids(map_run, cfg)
            channels += enhancement_channels(grids, cfg.enhance_settings(), int(flight.time_ns[0]))
            figures.update(enhancement_figures(grids, cfg.enhance_settings(), map_run.lines))
            lines.append((LOG_INFO, f"enhance: {', '.join(grids)}"))
    if nav is not None:
        lines += navigation_lines(nav)
        if not isinstance(nav, str):
            channels += navigation_channels(nav)
            figures.update(navigation_figures(nav))
    if quality is not None:
        lines += quality_lines(quality)
        channels += quality_channels(flight, quality)
        figures.update(quality_figures(quality))
    channels.insert(0, log_channel(flight, lines, "postflight"))
    for name, fig in figures.items():
        paths[name] = save_figure(fig, out / f"{stem}.{name}.png")
    meta = {
        "aeromag.run": {
            **run_metadata(),
            "config_hash": cfg.hash,
            "config_version": str(cfg["config_version"]),
        }
    }
    write_with_new_channels(recording, paths["mcap"], channels, metadata=meta)
    summary = build_summary(
        flight,
        config=cfg,
        despiked=despiked,
        seg=seg,
        compensation=compensation,
        audit=audit,
        vector=None if isinstance(vector, str) else vector,
        map_run=map_run,
        enhancements=list(grids),
        navigation=nav,
        quality=quality,
    )
    images = {k: v for k, v in paths.items() if k not in DOCUMENTS}
    report = report_markdown(stem, summary, {k: v.name for k, v in images.items()})
    write_text_atomic(paths["report"], report)
    write_text_atomic(paths["report_html"], render_html(stem, summary, images))
    write_json_atomic(paths["layout"], recording_layout(paths["mcap"]))
    exports: dict[str, list[str]] = {}
    if map_run is not None and cfg["export"]["formats"]:
        from pipeline.export import export_recording

        exports = export_recording(paths["mcap"], out, cfg["export"]["formats"])
    summary |= jsonable(
        {
            "exports": exports,
            "outputs": paths,
            "channels_written": sorted({c.topic for c in channels if c.messages}),
        }
    )
    summary["timings_s"] = {
        k: round(v, 3)
        for k, v in {**(timings or {}), "write": time.perf_counter() - t_start}.items()
    }
    summary["peak_memory_mb"] = peak_memory_mb()
    write_json_atomic(paths["summary"], summary)
    publish_artifact(stem, report)
    return summary


def peak_memory_mb() -> float:
    """Peak resident memory of this process so far, MB (Linux reports KiB)."""
    import resource

    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)


def publish_artifact(stem: str, markdown: str) -> None:
    """The report as a Prefect markdown artifact, when running inside a flow or task."""
    try:
        from prefect.artifacts import create_markdown_artifact
        from prefect.context import get_run_context

        get_run_context()
    except Exception:  # noqa: BLE001 - outside a run: no artifact
        return
    import re

    key = re.sub(r"[^a-z0-9-]", "-", f"aeromag-{stem}".lower())[:100]
    create_markdown_artifact(markdown=markdown, key=key, description="post-flight summary")


# --------------------------------------------------------------------------------------------
# navigation
def navigate_recording(
    src: Path,
    map_path: Path,
    json_out: Path,
    settings,
    out_path: Path | None = None,
    map_channel: str = "/map/anomaly_filtered",
    cfg: Config | None = None,
) -> dict[str, Any]:
    """``aeromag navigate``: re-fly the recording with a simulated INS aided by the map.

    A raw recording is compensated first (:func:`final_compensation`, as ``aeromag map``);
    a processed one uses its ``/mag/compensated``.
    """
    from pipeline.navigation.map_io import read_map
    from pipeline.navigation.stage import run_navigation, track_coverage

    cfg = cfg or Config.load()
    settings.check()
    geomap = read_map(map_path, map_channel)
    flight = read_flight(src)
    flight.require("lat_deg", "lon_deg", "alt_m", purpose="navigation (the reference track)")
    seg, why = try_segment(flight)
    present = set(flight.all_topics)
    nav_topics = ("/nav/ins", "/nav/map_aided", "/nav/error", "/nav/innovation")
    if out_path is not None:
        _refuse_existing(
            src,
            [OutputChannel(t, "") for t in nav_topics],
            present,
            "navigate the original recording",
        )
    if seg is None and settings.segments != "all":
        raise AeromagError(
            f"--segments {settings.segments} needs the flight lines: {why}; use --segments all",
            file=src,
            channel="/gnss/fix",
        )
    track_coverage(flight, seg, geomap, settings)  # fail before compensating
    lines = ingest_lines(flight) + ([(LOG_INFO, why)] if why else [])
    comp, more, channels, comp_summary = final_compensation(flight, seg, cfg, "navigate")
    lines += more
    run = run_navigation(flight, seg, comp, geomap, settings)
    nav = run.summary()
    d = nav["drms_m"]
    lines.append(
        (
            LOG_INFO,
            f"navigate: {settings.filter} on {settings.segments} with a {settings.ins}-grade INS: "
            f"DRMS INS-only {d['ins_only']:.1f} m, map-aided {d['map_aided']:.2f} m, "
            f"CRLB {d['crlb']:.2f} m",
        )
    )
    lines += [(LOG_INFO, f"navigate: {n}") for n in run.notes]
    if out_path is not None:
        out_channels = navigation_channels(run)
        if "/aeromag/log" not in present:  # a processed input keeps its own log (one channel)
            out_channels.insert(0, log_channel(flight, lines, "navigate"))
        if seg is not None and "/flight/segment" not in present:
            out_channels.append(segment_channel(flight, seg))
        out_channels += [c for c in channels if c.topic not in present]
        write_with_new_channels(
            src, out_path, out_channels, metadata={"aeromag.run": run_metadata()}
        )
    summary = build_summary(
        flight,
        compensation=comp_summary,
        navigation=run,
        log=[text for _, text in lines],
        outputs={"summary": json_out, **({"mcap": out_path} if out_path else {})},
    )
    write_json_atomic(json_out, summary)
    return summary
