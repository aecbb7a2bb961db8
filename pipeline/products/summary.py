"""The summary document: one builder for every command's ``*.summary.json`` (and the audit's
JSON), so that a section means the same thing whichever command wrote it.

Every summary starts with ``aeromag_version`` and ``input`` (what was read); the stage
sections follow in the flow's order (``config``, ``despike``, ``segments``, ``compensation``,
``audit``, ``vector``, ``map``, ``navigation``, ``quality``), then anything a command adds,
then ``figures`` and ``outputs``. Values are plain JSON (NaN becomes null).
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import numpy as np

from pipeline import __version__
from pipeline.flight import Flight
from pipeline.io.series import NS

SEGMENT_LABELS = ("calibration", "survey", "tie", "validation", "turn", "transit")
# the audit's keys a post-flight summary carries (the audit command writes all of them)
AUDIT_KEYS = (
    "baseline",
    "findings",
    "extended_model",
    "unexplained_rms_nT",
    "noise_floor_nT",
    "band_noise_floor_nT",
    "unexplained",
    "gain",
    "null_calibration",
)


def jsonable(v: Any) -> Any:
    """Plain JSON values (numpy scalars to float, NaN to null)."""
    if isinstance(v, dict):
        return {str(k): jsonable(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [jsonable(x) for x in v]
    if isinstance(v, bool | str) or v is None:
        return v
    if isinstance(v, int | np.integer):
        return int(v)
    if isinstance(v, Path):
        return str(v)
    f = float(v)
    return f if np.isfinite(f) else None


def build_summary(
    flight: Flight,
    *,
    config: Any = None,
    despiked: Any = None,
    seg: Any = None,
    compensation: dict[str, Any] | None = None,
    audit: Any = None,
    audit_full: bool = False,
    vector: Any = None,
    map_run: Any = None,
    enhancements: list[str] | None = None,
    navigation: Any = None,
    quality: Any = None,
    figures: dict[str, Any] | None = None,
    outputs: dict[str, Any] | None = None,
    **extra: Any,
) -> dict[str, Any]:
    """The summary document of one run.

    Parameters
    ----------
    flight : Flight
        The recording read (the ``input`` section).
    config : pipeline.config.Config, optional
        The configuration used (``config``: version, hash, source).
    despiked : pipeline.despike.DespikeResult, optional
        The despike step's result.
    seg : pipeline.segment.Segmentation, optional
        The segmentation (``segments``: epochs per label, passes, boxes).
    compensation : dict, optional
        The compensation section as the command has it (one run's summary, or
        ``{"final": model, model: run summary, ...}``).
    audit : pipeline.audit.AuditResult, optional
        The audit; ``audit_full`` puts its whole JSON at the top level (the audit command),
        otherwise the :data:`AUDIT_KEYS` go into ``audit``.
    vector, map_run, quality : optional
        Stage results with a ``summary()`` method.
    enhancements : list of str, optional
        Enhancement grids made from the map (``map.enhancements``).
    navigation : NavigationRun or str, optional
        The navigation run, or why it was skipped (``navigation.skipped``).
    figures, outputs : dict, optional
        Name -> path of the figures and output files.
    **extra
        Further top-level keys of the command, placed after the stage sections.

    Returns
    -------
    dict
        Plain JSON values.
    """
    s: dict[str, Any] = {"aeromag_version": __version__, "input": flight_summary(flight)}
    if config is not None:
        s["config"] = {
            "version": config["config_version"],
            "hash": config.hash,
            "source": config.source,
        }
    if despiked is not None:
        s["despike"] = despiked.summary()
    if seg is not None:
        s["segments"] = {
            "source": seg.source,
            "epochs": {lab: int(seg.mask(lab).sum()) for lab in SEGMENT_LABELS},
            "calibration_passes": len(seg.passes()),
            "boxes": len(seg.boxes()),
        }
    if compensation is not None:
        s["compensation"] = compensation
    if audit is not None:
        aj = audit.to_json()
        if audit_full:
            s.update(aj)
        else:
            s["audit"] = {k: aj[k] for k in AUDIT_KEYS}
    if vector is not None:
        s["vector"] = vector.summary()
    if map_run is not None:
        s["map"] = map_run.summary()
        if enhancements:
            s["map"]["enhancements"] = sorted(enhancements)
    if isinstance(navigation, str):
        s["navigation"] = {"skipped": navigation}
    elif navigation is not None:
        s["navigation"] = navigation.summary()
    if quality is not None:
        s["quality"] = quality.summary()
    s.update(extra)
    if figures is not None:
        s["figures"] = {k: str(v) for k, v in figures.items()}
    if outputs is not None:
        s["outputs"] = {k: str(v) for k, v in outputs.items()}
    return jsonable(s)


def sha256_file(path: str | Path, block: int = 1 << 20) -> str:
    """Hex SHA-256 of a file, read in ``block``-byte pieces."""
    h = hashlib.sha256()
    with Path(path).open("rb") as f:
        while chunk := f.read(block):
            h.update(chunk)
    return h.hexdigest()


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
