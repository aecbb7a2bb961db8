"""``aeromag navigate``: a recording re-flown with a simulated INS aided by a map, with the
post-flight flow's navigation settings (``[navigate]``) and log lines."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.config import Config
from pipeline.errors import AeromagError
from pipeline.io.writer import OutputChannel, write_json_atomic, write_with_new_channels
from pipeline.navigation.navigability import navigability_map, track_speed_mps
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


def parse_headings(text: str) -> tuple[float, ...]:
    """``--heading``: ``all`` (0, 45, 90, 135: every direction, a line and its reverse alike
    to first order) or one heading in degrees from grid north."""
    if str(text).strip().lower() == "all":
        return (0.0, 45.0, 90.0, 135.0)
    try:
        h = float(text)
    except ValueError:
        raise AeromagError(f"--heading {text!r}: use degrees from grid north or all") from None
    if not np.isfinite(h):
        raise AeromagError(f"--heading {text!r}: use degrees from grid north or all")
    return (h % 360.0,)


def navigability_recording(
    src: Path,
    out_path: Path,
    cfg: Config,
    speed_mps: float | None = None,
    heading: str = "all",
) -> dict[str, Any]:
    """``aeromag navigability``: the map of a processed recording turned into the position
    CRLB a vehicle reaches flying into each cell
    (:func:`pipeline.navigation.navigability.navigability_map`), written as
    ``/map/navigability`` (``foxglove.Grid``, m) on a copy of the recording.

    The map is ``/map/<navigate.map>`` with its ``/map/uncertainty`` (else ``[navigate]
    map_sigma_nT``); the sensor's noise the white noise of the recording's ``/mag/compensated``;
    ``speed_mps`` None: the recording's median ground speed.
    """
    from pipeline.io.reader import read_flight
    from pipeline.navigation.map_io import read_map
    from pipeline.noise import white_noise_nT
    from pipeline.products.channels import grid_channel
    from pipeline.run.fields import existing_compensated

    headings = parse_headings(heading)
    if speed_mps is not None and not (np.isfinite(speed_mps) and speed_mps > 0):
        raise AeromagError(f"--speed {speed_mps!r}: a speed in m/s must be > 0")
    nav = cfg.navigation_settings()
    nav.check()
    geomap = read_map(src, f"/map/{cfg['navigate']['map']}")
    flight = read_flight(src)
    comp = existing_compensated(flight)
    if not comp:
        raise AeromagError(
            "no compensated field (run `aeromag process` on it first)",
            file=src,
            channel="/mag/compensated",
        )
    sensor = white_noise_nT(list(comp.values())[-1])
    flight.require("lat_deg", "lon_deg", purpose="navigability (the survey's speed)")
    if speed_mps is None:
        speed_mps = track_speed_mps(flight, geomap)
        if not np.isfinite(speed_mps):
            raise AeromagError(
                "the track does not move: give --speed", file=src, channel="/gnss/fix"
            )
    present = set(flight.all_topics)
    refuse_existing(
        src, [OutputChannel("/map/navigability", "")], present, "use the recording without it"
    )
    grid, summary = navigability_map(flight, geomap, float(sensor), nav, speed_mps, headings)
    channel = grid_channel("/map/navigability", int(flight.time_ns[0]), grid, "navigability_m")
    write_with_new_channels(src, out_path, [channel], metadata={"aeromag.run": run_metadata()})
    return summary
