"""Writing MCAP recordings.

:class:`McapOutput` writes a new recording atomically (temporary file in the destination folder,
renamed into place on success, removed on failure): a reader never sees a half-written file.
:func:`write_with_new_channels` produces the pipeline's output: every input record unchanged
(schemas, channels, message bytes, times, sequence numbers, metadata, attachments) plus new
channels, merged in log-time order. The input is only ever opened for reading.
"""

from __future__ import annotations

import heapq
import os
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import orjson
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from pipeline import __version__
from pipeline.errors import AeromagError
from pipeline.io.contract import MESSAGE_ENCODING, SCHEMA_ENCODING
from pipeline.io.schemas import schema_bytes

NS = 1_000_000_000
PROFILE = ""
LIBRARY = f"aeromag/{__version__}"


def stamp(time_ns: int) -> dict[str, int]:
    """Foxglove-style timestamp ``{"sec", "nsec"}`` of an instant in ns since the Unix epoch."""
    sec, nsec = divmod(int(time_ns), NS)
    return {"sec": sec, "nsec": nsec}


def encode(payload: dict[str, Any]) -> bytes:
    return orjson.dumps(payload, option=orjson.OPT_SERIALIZE_NUMPY)


class McapOutput:
    """Atomic MCAP writer with JSON channels registered by topic and schema name.

    Use as a context manager; on an exception inside the block the partial file is deleted
    and the destination is left as it was.
    """

    def __init__(self, path: str | Path, *, compression: CompressionType = CompressionType.ZSTD,
                 chunk_size: int = 1 << 20):
        self.path = Path(path)
        self._tmp = self.path.with_name(f".{self.path.name}.partial-{os.getpid()}")
        self._compression = compression
        self._chunk_size = chunk_size
        self._schemas: dict[tuple[str, str, bytes], int] = {}
        self._channels: dict[str, int] = {}
        self._sequence: dict[int, int] = {}
        self._stream = None
        self.writer: Writer | None = None

    def __enter__(self) -> McapOutput:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._stream = self._tmp.open("wb")
        self.writer = Writer(self._stream, compression=self._compression,
                             chunk_size=self._chunk_size)
        self.writer.start(profile=PROFILE, library=LIBRARY)
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            if exc_type is None:
                assert self.writer is not None and self._stream is not None
                self.writer.finish()
                self._stream.flush()
                os.fsync(self._stream.fileno())
                self._stream.close()
                os.replace(self._tmp, self.path)
        finally:
            if self._stream is not None and not self._stream.closed:
                self._stream.close()
            if self._tmp.exists():
                self._tmp.unlink()

    def schema_id(self, name: str, encoding: str = SCHEMA_ENCODING,
                  data: bytes | None = None) -> int:
        data = schema_bytes(name) if data is None else data
        key = (name, encoding, data)
        if key not in self._schemas:
            assert self.writer is not None
            self._schemas[key] = self.writer.register_schema(name=name, encoding=encoding,
                                                             data=data)
        return self._schemas[key]

    def channel(self, topic: str, schema_name: str) -> int:
        """Channel id of a JSON topic with one of our schemas (registered on first use)."""
        if topic not in self._channels:
            assert self.writer is not None
            sid = self.schema_id(schema_name)
            self._channels[topic] = self.writer.register_channel(
                topic=topic, message_encoding=MESSAGE_ENCODING, schema_id=sid)
        return self._channels[topic]

    def write(self, channel_id: int, log_time_ns: int, data: bytes,
              publish_time_ns: int | None = None, sequence: int | None = None) -> None:
        assert self.writer is not None
        if sequence is None:
            sequence = self._sequence.get(channel_id, 0)
            self._sequence[channel_id] = sequence + 1
        self.writer.add_message(channel_id=channel_id, log_time=int(log_time_ns), data=data,
                                publish_time=int(log_time_ns if publish_time_ns is None
                                                 else publish_time_ns),
                                sequence=sequence)

    def metadata(self, name: str, data: dict[str, str]) -> None:
        assert self.writer is not None
        self.writer.add_metadata(name=name, data={k: str(v) for k, v in data.items()})


@dataclass
class OutputChannel:
    """A new channel for the output recording.

    ``messages`` are ``(log_time_ns, payload)`` pairs; each payload carries the same instant
    as ``timestamp`` (added here when absent).
    """

    topic: str
    schema_name: str
    messages: list[tuple[int, dict[str, Any]]] = field(default_factory=list)

    def add(self, log_time_ns: int, payload: dict[str, Any]) -> None:
        payload.setdefault("timestamp", stamp(log_time_ns))
        self.messages.append((int(log_time_ns), payload))


def _same_file(a: Path, b: Path) -> bool:
    try:
        return b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def write_with_new_channels(src: str | Path, dst: str | Path, channels: Iterable[OutputChannel],
                            metadata: dict[str, dict[str, str]] | None = None) -> Path:
    """Copy every record of ``src`` unchanged into ``dst`` and add ``channels``.

    Messages of the input and of the new channels are merged in log-time order (ties: input
    first), so a viewer streams the file without seeking back. New topics must not already
    exist in the input.
    """
    src, dst = Path(src), Path(dst)
    if _same_file(src, dst) or src.resolve() == dst.resolve():
        raise AeromagError("output path is the input file; the input is never overwritten",
                           file=dst)
    channels = [c for c in channels if c.messages]
    try:
        with src.open("rb") as stream:
            reader = make_reader(stream, validate_crcs=True)
            summary = reader.get_summary()
            existing = ({c.topic for c in summary.channels.values()} if summary else set())
            clash = sorted(existing & {c.topic for c in channels})
            if clash:
                raise AeromagError("the input already has this output channel; "
                                   "process the original recording instead",
                                   file=src, channel=clash[0])
            with McapOutput(dst) as out:
                id_map: dict[int, int] = {}

                def in_channel(schema, channel) -> int:
                    if channel.id not in id_map:
                        sid = 0
                        if schema is not None and schema.id != 0:
                            sid = out.schema_id(schema.name, schema.encoding, schema.data)
                        id_map[channel.id] = out.writer.register_channel(
                            topic=channel.topic, message_encoding=channel.message_encoding,
                            schema_id=sid, metadata=dict(channel.metadata))
                    return id_map[channel.id]

                if summary is not None:  # keep channels that carry no message, in id order
                    for cid in sorted(summary.channels):
                        ch = summary.channels[cid]
                        in_channel(summary.schemas.get(ch.schema_id), ch)

                def input_records() -> Iterator[tuple[int, int, Any]]:
                    for schema, channel, message in reader.iter_messages(log_time_order=True):
                        yield message.log_time, 0, (schema, channel, message)

                def new_records() -> Iterator[tuple[int, int, Any]]:
                    flat = [(t, 1, (c, p)) for c in channels for t, p in c.messages]
                    flat.sort(key=lambda r: r[0])
                    yield from flat

                for _t, kind, rec in heapq.merge(input_records(), new_records(),
                                                 key=lambda r: (r[0], r[1])):
                    if kind == 0:
                        schema, channel, message = rec
                        out.write(in_channel(schema, channel), message.log_time, message.data,
                                  message.publish_time, message.sequence)
                    else:
                        c, payload = rec
                        out.write(out.channel(c.topic, c.schema_name), _t, encode(payload))
                for att in reader.iter_attachments():
                    out.writer.add_attachment(create_time=att.create_time, log_time=att.log_time,
                                              name=att.name, media_type=att.media_type,
                                              data=att.data)
                for md in reader.iter_metadata():
                    out.metadata(md.name, dict(md.metadata))
                for name, data in (metadata or {}).items():
                    out.metadata(name, data)
    except (McapError, ValueError, struct.error, EOFError) as exc:
        raise AeromagError(f"could not copy the input recording ({type(exc).__name__}: {exc})",
                           file=src) from exc
    return dst


def write_json_atomic(path: str | Path, obj: Any) -> Path:
    """Write a JSON document atomically (temporary file + rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.partial-{os.getpid()}")
    try:
        tmp.write_bytes(orjson.dumps(obj, option=orjson.OPT_INDENT_2 | orjson.OPT_SERIALIZE_NUMPY
                                     | orjson.OPT_NON_STR_KEYS))
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path
