"""Human-readable products of a run: the log channel and the summary document."""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import numpy as np

from pipeline import __version__
from pipeline.flight import Flight
from pipeline.io.reader import NS
from pipeline.io.writer import OutputChannel

LOG_TOPIC = "/aeromag/log"
LOG_INFO, LOG_WARNING = 2, 3  # foxglove.Log levels


def sha256_file(path: str | Path, block: int = 1 << 20) -> str:
    """Hex SHA-256 of a file, read in ``block``-byte pieces."""
    h = hashlib.sha256()
    with Path(path).open("rb") as f:
        while chunk := f.read(block):
            h.update(chunk)
    return h.hexdigest()


def log_channel(flight: Flight, lines: list[tuple[int, str]], stage: str) -> OutputChannel:
    """foxglove.Log messages (``/aeromag/log``), stamped at the flight's first epoch.

    ``lines`` are (level, text) pairs.
    """
    ch = OutputChannel(LOG_TOPIC, "foxglove.Log")
    t0 = int(flight.time_ns[0])
    for k, (level, text) in enumerate(lines):
        # one ns apart keeps the viewer's order equal to the report's order
        ch.add(
            t0 + k,
            {"level": level, "message": text, "name": f"aeromag.{stage}", "file": "", "line": 0},
        )
    return ch


def ingest_lines(flight: Flight) -> list[tuple[int, str]]:
    """What ingest found: streams, rates, alignment and problems."""
    lines = [
        (
            LOG_INFO,
            f"ingest: {flight.source.name}: {len(flight.time_ns)} epochs on "
            f"{flight.topic_of['scalar']} over {flight.data['time_s'].iloc[-1]:.1f} s",
        )
    ]
    for topic, s in sorted(flight.series.items()):
        lines.append(
            (
                LOG_INFO,
                f"ingest: {topic} ({s.rule.schema_name}): {s.time_ns.size} "
                f"samples at {s.rate_hz:.2f} Hz",
            )
        )
    for t in flight.unknown_topics:
        lines.append((LOG_INFO, f"ingest: {t}: outside the channel contract, copied unchanged"))
    for note in flight.notes:
        lines.append((LOG_WARNING, f"ingest: {note}"))
    return lines


def flight_summary(flight: Flight) -> dict[str, Any]:
    """The ``input`` section of a summary document."""
    t = flight.time_ns
    t0 = int(t[0])

    def rel(ns):
        return None if ns is None else round((ns - t0) / NS, 3)

    dropped = {}
    for topic, s in sorted(flight.series.items()):
        if s.dropped_ns.size:
            dropped[topic] = {
                "samples": int(s.dropped_ns.size),
                "of": int(s.n_messages),
                "ranges_s": [[rel(a), rel(b)] for a, b in s.dropped_ranges_ns()],
                "problems": s.problems,
            }
    return {
        "file": str(flight.source),
        "sha256": sha256_file(flight.source),
        "start_ns": int(t[0]),
        "end_ns": int(t[-1]),
        "duration_s": float((t[-1] - t[0]) / NS),
        "epochs": int(t.size),
        "topics": {
            topic: {
                "schema": s.rule.schema_name,
                "samples": int(s.time_ns.size),
                "rate_hz": None if not np.isfinite(s.rate_hz) else round(s.rate_hz, 4),
            }
            for topic, s in sorted(flight.series.items())
        },
        "unknown_topics": flight.unknown_topics,
        "gaps": [
            {"topic": g.topic, "start_s": (g.start_ns - int(t[0])) / NS, "duration_s": g.duration_s}
            for g in flight.gaps
        ],
        "notes": flight.notes,
        "dropped": dropped,
        "losses": [
            {
                "offset": x.offset,
                "reason": x.reason,
                "start_s": rel(x.start_ns),
                "end_s": rel(x.end_ns),
                "bytes_lost": x.bytes_lost,
                "description": x.describe(t0),
            }
            for x in flight.losses
        ],
    }


def run_metadata() -> dict[str, str]:
    """The ``aeromag.run`` MCAP metadata record's fields (the aeromag version)."""
    return {"aeromag_version": __version__}
