"""Hand-built recordings for tests, written with the plain mcap Writer (an independent tool:
it follows only the documented channel contract, not our simulator's habits)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from mcap.writer import CompressionType, IndexType, Writer

from pipeline.io.schemas import schema_bytes

NS = 1_000_000_000
T0 = 1_780_000_000 * NS


def ts(ns: int) -> dict[str, int]:
    return {"sec": ns // NS, "nsec": ns % NS}


def build(
    path: Path,
    messages: list[tuple[str, int, Any]],
    *,
    schema_of: dict[str, str] | None = None,
    encoding: dict[str, str] | None = None,
    summary: bool = True,
    extra: callable | None = None,
    compression: CompressionType = CompressionType.ZSTD,
    chunk_size: int = 1 << 20,
) -> Path:
    """Write ``messages`` = [(topic, log_time_ns, payload dict | bytes)] in the given order.

    ``schema_of`` maps topic -> schema name (default: by the contract); ``encoding`` overrides
    a topic's message encoding; ``extra(writer)`` may add attachments/metadata.
    """
    default = {
        "/mag/scalar": "aeromag.ScalarField",
        "/mag/vector": "aeromag.VectorField",
        "/ins/attitude": "aeromag.Attitude",
        "/gnss/fix": "foxglove.LocationFix",
        "/base/scalar": "aeromag.ScalarField",
        "/plan/line": "aeromag.LineMarker",
    }
    schema_of = {**default, **(schema_of or {})}
    with open(path, "wb") as f:
        if summary:
            w = Writer(f, compression=compression, chunk_size=chunk_size)
        else:  # like a logger that died before writing its summary: readable by linear scan
            w = Writer(
                f,
                compression=CompressionType.NONE,
                index_types=IndexType.NONE,
                repeat_channels=False,
                repeat_schemas=False,
                use_statistics=False,
                use_summary_offsets=False,
            )
        w.start()
        chans: dict[str, int] = {}
        for topic, t, payload in messages:
            if topic not in chans:
                name = schema_of.get(topic, "aeromag.Scalar" if topic.startswith("/aux/") else "")
                try:
                    data = schema_bytes(name)
                except KeyError:
                    data = b"{}"
                sid = w.register_schema(name=name, encoding="jsonschema", data=data)
                chans[topic] = w.register_channel(
                    topic=topic, schema_id=sid, message_encoding=(encoding or {}).get(topic, "json")
                )
            data = payload if isinstance(payload, bytes) else json.dumps(payload).encode()
            w.add_message(chans[topic], log_time=t, data=data, publish_time=t)
        if extra:
            extra(w)
        w.finish()
    return path


def scalar(t: int, v: float, sensor: str = "s1") -> dict:
    return {"timestamp": ts(t), "sensor_id": sensor, "total_nT": v}


def vector(t: int, x: float, y: float, z: float) -> dict:
    return {"timestamp": ts(t), "sensor_id": "v1", "x_nT": x, "y_nT": y, "z_nT": z}


def attitude(t: int, r: float, p: float, y: float) -> dict:
    return {"timestamp": ts(t), "roll_deg": r, "pitch_deg": p, "yaw_deg": y}
