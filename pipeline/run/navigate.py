"""``aeromag navigate``: a recording re-flown with a simulated INS aided by a map, with the
post-flight flow's navigation settings (``[navigate]``) and log lines."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

from pipeline.config import Config
from pipeline.errors import AeromagError
from pipeline.io.writer import OutputChannel, write_json_atomic, write_with_new_channels
from pipeline.products.channels import navigation_channels, segment_channel
from pipeline.products.log import LOG_INFO, ingest_lines, log_channel, navigation_lines
from pipeline.products.summary import build_summary, run_metadata
from pipeline.run.commands import read_despiked
from pipeline.run.fields import final_compensation, try_segment
from pipeline.run.outputs import refuse_existing

NAV_TOPICS = ("/nav/ins", "/nav/map_aided", "/nav/error", "/nav/innovation")


def navigate_recording(
    src: Path,
    map_path: Path,
    json_out: Path,
    cfg: Config,
    out_path: Path | None = None,
    map_channel: str | None = None,
    **options: Any,
) -> dict[str, Any]:
    """``aeromag navigate``: re-fly the recording with a simulated INS aided by the map.

    The settings are ``[navigate]``'s (filter, INS grade, seed) with each of ``options``
    given (not None: ``filter``, ``ins``, ``seed``, ``segments``, ...) in its place;
    ``map_channel`` None: ``/map/<navigate.map>`` of a recording map. A raw recording is
    despiked (``despike.enabled``) and compensated first (:func:`final_compensation`, as
    ``aeromag map``); a processed one uses its ``/mag/compensated``.
    """
    from pipeline.navigation.map_io import read_map
    from pipeline.navigation.stage import run_navigation, track_coverage

    given = {k: v for k, v in options.items() if v is not None}
    settings = replace(cfg.navigation_settings(), **given)
    settings.check()
    geomap = read_map(map_path, map_channel or f"/map/{cfg['navigate']['map']}")
    flight, despiked, dlines = read_despiked(src, cfg)
    flight.require("lat_deg", "lon_deg", "alt_m", purpose="navigation (the reference track)")
    seg, why = try_segment(flight)
    present = set(flight.all_topics)
    if out_path is not None:
        channels = [OutputChannel(t, "") for t in NAV_TOPICS]
        refuse_existing(src, channels, present, "navigate the original recording")
    if seg is None and settings.segments != "all":
        raise AeromagError(
            f"--segments {settings.segments} needs the flight lines: {why}; use --segments all",
            file=src,
            channel="/gnss/fix",
        )
    track_coverage(flight, seg, geomap, settings)  # fail before compensating
    lines = ingest_lines(flight) + ([(LOG_INFO, why)] if why else [])
    comp, more, channels, comp_summary = final_compensation(flight, seg, cfg, "navigate")
    if comp_summary is not None:  # compensated here, from the despiked record (as `map`)
        lines += dlines
    else:
        despiked = None  # the recording's own /mag/compensated was used
    run = run_navigation(flight, seg, comp, geomap, settings)
    lines += more + navigation_lines(run)
    if out_path is not None:
        out_channels = navigation_channels(run)
        if "/aeromag/log" not in present:  # a processed input keeps its own log (one channel)
            out_channels.insert(0, log_channel(flight, lines, "navigate"))
        if seg is not None and "/flight/segment" not in present:
            out_channels.append(segment_channel(flight, seg))
        out_channels += [c for c in channels if c.topic not in present]
        meta = {"aeromag.run": run_metadata()}
        write_with_new_channels(src, out_path, out_channels, metadata=meta)
    summary = build_summary(
        flight,
        despiked=despiked,
        compensation=comp_summary,
        navigation=run,
        log=[text for _, text in lines],
        outputs={"summary": json_out, **({"mcap": out_path} if out_path else {})},
    )
    write_json_atomic(json_out, summary)
    return summary
