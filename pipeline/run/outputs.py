"""What a run writes: figures, the output recording with its new channels, the summary,
the reports, the Foxglove layout and the exports, each atomically (the summary last: its
presence marks a recording as done).

:func:`write_outputs` is the post-flight flow's write step; the single-stage commands
(:mod:`pipeline.run.commands`) share :func:`save_figure`, :func:`refuse_existing` and
:func:`model_channels` with it.
"""

from __future__ import annotations

import os
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import numpy as np

from pipeline.config import Config
from pipeline.errors import AeromagError, missing_file
from pipeline.flight import Flight
from pipeline.io.writer import (
    OutputChannel,
    atomic_output,
    write_json_atomic,
    write_text_atomic,
    write_with_new_channels,
)
from pipeline.products.channels import (
    compensated_channel,
    despike_channels,
    enhancement_channels,
    field_channel,
    grid_channel,
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
    navigability_figure,
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
    navigability_lines,
    navigation_lines,
    quality_lines,
)
from pipeline.products.markdown import report_markdown
from pipeline.products.summary import build_summary, jsonable, run_metadata
from pipeline.run.fields import final_field, fom_settings
from pipeline.run.steps import FlightResults, enhancement_grids, enhancement_skipped


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


def require_readable(path: Path) -> None:
    """Raise a one-line AeromagError when ``path`` is not a file."""
    if not path.is_file():
        raise missing_file(path)


def require_writable(path: Path, folder: bool = False) -> None:
    """Raise a one-line AeromagError when ``path`` (a file to write; a folder with
    ``folder``) cannot be made: something in the way is a file, not a folder, or the
    nearest existing folder cannot be written. Checked before the work, not after it."""
    path = Path(path)
    if folder and path.exists() and not path.is_dir():
        raise AeromagError("cannot write here: a file, not a folder", file=path)
    if not folder and path.is_dir():
        raise AeromagError("cannot write here: a folder, not a file", file=path)
    near = path if folder else path.parent
    while not near.exists() and near != near.parent:
        near = near.parent
    if not near.is_dir():
        raise AeromagError(f"cannot write here: {near} is a file, not a folder", file=path)
    if not os.access(near, os.W_OK | os.X_OK):
        raise AeromagError(f"cannot write here: {near} is not writable", file=path)


def refuse_existing(
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


def model_channels(flight: Flight, runs: dict, audit) -> tuple[list[OutputChannel], str]:
    """The compensated fields of every run (the final one as ``/mag/compensated``, the others
    as ``/mag/compensated/<model>``) and their ``/compensation/model``; with the final
    model's label ("" when there is none)."""
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


def peak_memory_mb() -> float:
    """Peak resident memory of this process so far, MB (Linux reports KiB)."""
    import resource

    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)


def _compensation_products(flight: Flight, r: FlightResults, cfg: Config, out: dict) -> dict:
    """Log lines, channels and figures of the compensation runs and the audit (into
    ``out``); returns the summary's ``compensation`` section."""
    from pipeline.compensate import bandpassed
    from pipeline.products.figures import compensation_figure

    for run in r.runs.values():
        out["lines"] += compensation_lines(run)
    channels, final = model_channels(flight, r.runs, r.audit)
    out["channels"] += channels
    last = list(r.runs.values())[-1]
    if last.model.lcurve is not None:
        out["figures"]["lcurve"] = lcurve_figure(last.model.lcurve, f"L-curve, {last.model.model}")
    t = flight.data["time_s"].to_numpy()
    band, poles = fom_settings(cfg)  # the configured band, as every FOM
    out["figures"]["compensation"] = compensation_figure(
        t,
        bandpassed(t, flight.data["scalar_nT"].to_numpy(), band, poles),
        {m: bandpassed(t, run.compensated_nT, band, poles) for m, run in r.runs.items()},
        r.seg.passes(),
        band,
    )
    return {"final": final, **{m: run.summary() for m, run in r.runs.items()}}


def flight_products(r: FlightResults, cfg: Config) -> dict[str, Any]:
    """Everything the post-flight stages' results become before they are written.

    Returns
    -------
    dict
        ``lines`` (the ``/aeromag/log`` lines), ``channels`` (the new channels, the log
        first), ``figures`` (name -> matplotlib figure), ``compensation`` (the summary's
        section or None) and ``grids`` (the enhancements: topic -> grid).
    """
    from pipeline.audit.report import figures as audit_figures
    from pipeline.audit.report import finding_channel
    from pipeline.audit.report import log_lines as audit_log_lines

    flight, seg = r.flight, r.seg
    out: dict[str, Any] = {"lines": ingest_lines(flight), "channels": [], "figures": {}}
    lines, channels, figures = out["lines"], out["channels"], out["figures"]
    if r.why:
        lines.append((LOG_INFO, r.why))
    lines += despike_lines(r.despiked)
    channels += despike_channels(flight, r.despiked)
    if seg is not None:
        channels.append(segment_channel(flight, seg))
        if (
            flight.has("lat_deg", "lon_deg")
            and np.isfinite(flight.data[["lat_deg", "lon_deg"]].to_numpy(float)).all(axis=1).any()
        ):
            figures["flight_map"] = flight_map(flight, seg)
    out["compensation"] = _compensation_products(flight, r, cfg, out) if r.runs else None
    if r.audit is not None:
        lines += audit_log_lines(r.audit)
        channels.append(finding_channel(flight, r.audit))
        figures.update({f"audit_{k}": v for k, v in audit_figures(r.audit, flight).items()})
    if isinstance(r.vector, str):
        lines.append((LOG_WARNING, f"vector: skipped: {r.vector}"))
    elif r.vector is not None:
        v = r.vector
        channels.append(vector_channel(flight, v.output_topic, v.vectors_nT, v.method))
        lines.append((LOG_INFO, f"vector: {v.method} -> {v.output_topic}"))
    out["grids"] = {}
    if r.map_skipped:
        lines.append((LOG_WARNING, f"map: skipped: {r.map_skipped}"))
    if r.map_run is not None:
        lines += map_lines(r.map_run)
        channels += map_channels(flight, seg, r.map_run)
        figures.update(map_figures(r.map_run))
        if cfg["enhance"]["enabled"]:
            out["grids"] = grids = enhancement_grids(r.map_run, cfg)
            channels += enhancement_channels(grids, cfg.enhance_settings(), int(flight.time_ns[0]))
            figures.update(enhancement_figures(grids, cfg.enhance_settings(), r.map_run.lines))
            lines.append((LOG_INFO, f"enhance: {', '.join(grids)}"))
            lines += [
                (LOG_WARNING, f"enhance: {why}") for why in enhancement_skipped(r.map_run, cfg)
            ]
    if r.nav is not None:
        lines += navigation_lines(r.nav)
        if not isinstance(r.nav, str):
            channels += navigation_channels(r.nav)
            figures.update(navigation_figures(r.nav))
    if r.navigability is not None:
        lines += navigability_lines(r.navigability)
        if not isinstance(r.navigability, str):
            grid = r.navigability[0]
            t0 = int(flight.time_ns[0])
            channels.append(grid_channel("/map/navigability", t0, grid, "navigability_m"))
            figures["navigability"] = navigability_figure(grid, r.map_run.lines)
    if r.quality is not None:
        lines += quality_lines(r.quality)
        channels += quality_channels(flight, r.quality)
        figures.update(quality_figures(r.quality))
    channels.insert(0, log_channel(flight, lines, "postflight"))
    return out


def _navigability_summary(result) -> dict[str, Any]:
    """The summary's ``navigability`` block: ``aeromag navigability``'s JSON, or
    ``{"skipped": why}``; nothing when the step was not enabled."""
    if result is None:
        return {}
    return {"navigability": {"skipped": result} if isinstance(result, str) else result[1]}


def write_outputs(
    recording: str,
    out_dir: str,
    cfg: Config,
    results: FlightResults,
    timings: dict[str, float] | None = None,
) -> dict[str, Any]:
    """The post-flight write step: every output, each written atomically; the summary last
    (its presence marks the recording as done).

    ``timings`` (stage -> seconds of the stages before) goes into the summary as
    ``timings_s`` with this stage's own time (``write``, up to the summary itself), with the
    process's peak resident memory so far (``peak_memory_mb``).

    Returns
    -------
    dict
        The summary (as written to ``<stem>.summary.json``).
    """
    t_start = time.perf_counter()
    r = results
    stem, out = Path(recording).stem, Path(out_dir)
    paths = output_paths(recording, out_dir)
    made = flight_products(r, cfg)
    meta = {
        "aeromag.run": {
            **run_metadata(),
            "config_hash": cfg.hash,
            "config_version": str(cfg["config_version"]),
        }
    }
    # the figures render (Agg, PNG) while the recording is written: the two share no state
    # and each spends much of its time outside the interpreter lock
    with ThreadPoolExecutor(1, thread_name_prefix="aeromag-figures") as pool:
        figures = pool.submit(
            lambda: {n: save_figure(f, out / f"{stem}.{n}.png") for n, f in made["figures"].items()}
        )
        write_with_new_channels(recording, paths["mcap"], made["channels"], metadata=meta)
        try:
            paths.update(figures.result())
        except BaseException:  # nothing half-written: the recording goes with its figures
            paths["mcap"].unlink(missing_ok=True)
            raise
    summary = build_summary(
        r.flight,
        config=cfg,
        despiked=r.despiked,
        seg=r.seg,
        compensation=made["compensation"],
        audit=r.audit,
        vector=None if isinstance(r.vector, str) else r.vector,
        map_run=r.map_run,
        enhancements=list(made["grids"]),
        navigation=r.nav,
        quality=r.quality,
        **_navigability_summary(r.navigability),
    )
    images = {k: v for k, v in paths.items() if k not in DOCUMENTS}
    report = report_markdown(stem, summary, {k: v.name for k, v in images.items()})
    write_text_atomic(paths["report"], report)
    write_text_atomic(paths["report_html"], render_html(stem, summary, images))
    write_json_atomic(paths["layout"], recording_layout(paths["mcap"]))
    exports: dict[str, list[str]] = {}
    if r.map_run is not None and cfg["export"]["formats"]:
        from pipeline.export import export_recording

        exports = export_recording(
            paths["mcap"], out, cfg["export"]["formats"], written=made["channels"]
        )
    summary |= jsonable(
        {
            "exports": exports,
            "outputs": paths,
            "channels_written": sorted({c.topic for c in made["channels"] if c.messages}),
        }
    )
    summary["timings_s"] = {
        k: round(v, 3)
        for k, v in {**(timings or {}), "write": time.perf_counter() - t_start}.items()
    }
    summary["peak_memory_mb"] = peak_memory_mb()
    write_json_atomic(paths["summary"], summary)
    return summary
