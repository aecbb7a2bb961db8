"""Writing MCAP recordings.

:class:`McapOutput` writes a new recording atomically (temporary file in the destination folder,
renamed into place on success, removed on failure): a reader never sees a half-written file.
:func:`write_with_new_channels` produces the pipeline's output: every input record unchanged
(schemas, channels, message bytes, times, sequence numbers, metadata, attachments) plus new
channels, merged in log-time order. The input is only ever opened for reading.
"""

from __future__ import annotations

import io
import os
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import orjson
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
    """Serialise one message payload as JSON bytes (numpy arrays and scalars allowed)."""
    return orjson.dumps(payload, option=orjson.OPT_SERIALIZE_NUMPY)


def _output_folder(path: str | Path) -> Path:
    """``path`` with its folder created; a folder that cannot be (a file in the way, no
    permission) is the user's problem, said in one line."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise AeromagError(f"cannot create the output folder: {exc.strerror}", file=path) from exc
    return path


def _opened(tmp: Path, path: Path) -> BinaryIO:
    """``tmp`` opened for writing; a refusal names the output ``path``."""
    try:
        return tmp.open("wb")
    except OSError as exc:
        raise AeromagError(f"cannot write the output: {exc.strerror}", file=path) from exc


@contextmanager
def atomic_output(path: str | Path) -> Iterator[BinaryIO]:
    """A binary stream to a temporary file beside ``path`` (``.NAME.partial-PID``), flushed,
    fsynced and renamed onto ``path`` when the block ends normally, deleted when it raises:
    a reader never sees a half-written file and the destination is left as it was."""
    path = _output_folder(path)
    tmp = path.with_name(f".{path.name}.partial-{os.getpid()}")
    try:
        with _opened(tmp, path) as stream:
            yield stream
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temporary file name beside ``path`` for libraries that write by name (GDAL, HDF5):
    renamed onto ``path`` when the block ends normally, deleted when it raises. The name keeps
    the suffix (``.NAME.partial-PID.tif``) so format drivers chosen by extension still work."""
    path = _output_folder(path)
    tmp = path.with_name(f".{path.stem}.partial-{os.getpid()}{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


class McapOutput:
    """Atomic MCAP writer with JSON channels registered by topic and schema name.

    Use as a context manager; on an exception inside the block the partial file is deleted
    and the destination is left as it was.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        compression: CompressionType = CompressionType.ZSTD,
        chunk_size: int = 1 << 20,
    ):
        self.path = Path(path)
        self._compression = compression
        self._chunk_size = chunk_size
        self._schemas: dict[tuple[str, str, bytes], int] = {}
        self._channels: dict[str, int] = {}
        self._sequence: dict[int, int] = {}
        self.writer: Writer | None = None

    def __enter__(self) -> McapOutput:
        self._output = atomic_output(self.path)
        self.writer = Writer(
            self._output.__enter__(), compression=self._compression, chunk_size=self._chunk_size
        )
        self.writer.start(profile=PROFILE, library=LIBRARY)
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            assert self.writer is not None
            try:
                self.writer.finish()
            except BaseException as err:  # noqa: BLE001 - the partial file goes too
                self._output.__exit__(type(err), err, err.__traceback__)
                raise
        self._output.__exit__(exc_type, exc, tb)

    def schema_id(
        self, name: str, encoding: str = SCHEMA_ENCODING, data: bytes | None = None
    ) -> int:
        """Id of a schema, registered on first use.

        Parameters
        ----------
        name : str
            Schema name (``aeromag.*`` or ``foxglove.*``).
        encoding : str
            Schema encoding (``jsonschema``).
        data : bytes, optional
            Schema text; by default the one shipped in ``schemas/``.

        Returns
        -------
        int
        """
        data = schema_bytes(name) if data is None else data
        key = (name, encoding, data)
        if key not in self._schemas:
            assert self.writer is not None
            self._schemas[key] = self.writer.register_schema(
                name=name, encoding=encoding, data=data
            )
        return self._schemas[key]

    def channel(self, topic: str, schema_name: str) -> int:
        """Channel id of a JSON topic with one of our schemas (registered on first use)."""
        if topic not in self._channels:
            assert self.writer is not None
            sid = self.schema_id(schema_name)
            self._channels[topic] = self.writer.register_channel(
                topic=topic, message_encoding=MESSAGE_ENCODING, schema_id=sid
            )
        return self._channels[topic]

    def write(
        self,
        channel_id: int,
        log_time_ns: int,
        data: bytes,
        publish_time_ns: int | None = None,
        sequence: int | None = None,
    ) -> None:
        """Write one message.

        Parameters
        ----------
        channel_id : int
            From :meth:`channel`.
        log_time_ns : int
            Sample time, ns since the Unix epoch (UTC).
        data : bytes
            The encoded payload.
        publish_time_ns : int, optional
            Defaults to ``log_time_ns``.
        sequence : int, optional
            Defaults to a per-channel counter.
        """
        assert self.writer is not None
        if sequence is None:
            sequence = self._sequence.get(channel_id, 0)
            self._sequence[channel_id] = sequence + 1
        self.writer.add_message(
            channel_id=channel_id,
            log_time=int(log_time_ns),
            data=data,
            publish_time=int(log_time_ns if publish_time_ns is None else publish_time_ns),
            sequence=sequence,
        )

    def metadata(self, name: str, data: dict[str, str]) -> None:
        """Write a Metadata record; values are stored as strings."""
        assert self.writer is not None
        self.writer.add_metadata(name=name, data={k: str(v) for k, v in data.items()})


class RowMessages(Sequence):
    """The messages of a large channel, made when read: ``(time_ns[i], payload(i))`` with
    ``timestamp`` ``{sec, nsec}`` added last, as :meth:`OutputChannel.add` does.

    A channel with a message per epoch (a compensated field over a 5 h flight: 180 000) held
    as a list of payload dicts took ~600 bytes a message; the writer encodes these one by one
    instead, each dict gone once its bytes are in the chunk.
    """

    def __init__(self, time_ns: np.ndarray, payload: Callable[[int], dict[str, Any]]):
        self.time_ns = np.asarray(time_ns, np.int64)
        self.payload = payload

    def __len__(self) -> int:
        return int(self.time_ns.size)

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self[k] for k in range(*i.indices(len(self)))]
        t = int(self.time_ns[i])
        p = self.payload(i if i >= 0 else i + len(self))
        p.setdefault("timestamp", stamp(t))
        return t, p


class ColumnMessages(RowMessages):
    """The messages of a large channel as columns: message ``i``'s payload is ``{name:
    column[i]}`` in ``columns`` order (a column is an array, one value per message, or one
    value for all), with ``timestamp`` last.

    The writer encodes a block of these at once (:func:`encode_rows`): numbers formatted by
    one ``orjson`` call per column and block, each message joined from its parts, the same
    bytes as encoding each payload (float arrays: NaN and infinities become ``null``, as a
    payload's ``None`` or non-finite float does).
    """

    def __init__(self, time_ns: np.ndarray, columns: dict[str, Any]):
        self.columns = columns
        arrays = {k: v for k, v in columns.items() if isinstance(v, np.ndarray)}

        def value(k: str, i: int) -> Any:
            v = arrays[k][i]
            return v.item() if isinstance(v, np.generic) else v

        def payload(i: int) -> dict[str, Any]:
            return {k: (value(k, i) if k in arrays else v) for k, v in columns.items()}

        super().__init__(time_ns, payload)


def _column_bytes(values: np.ndarray) -> list[bytes]:
    """Each value's JSON bytes as ``orjson`` writes it in a payload (numbers by one call;
    strings, one call per distinct value)."""
    if values.dtype.kind in "fiu":  # as float(value), int(value): float64, int64
        values = values.astype(np.float64 if values.dtype.kind == "f" else np.int64, copy=False)
        return orjson.dumps(values, option=orjson.OPT_SERIALIZE_NUMPY)[1:-1].split(b",")
    seen: dict[Any, bytes] = {}
    return [seen[v] if v in seen else seen.setdefault(v, orjson.dumps(v)) for v in values]


def encode_rows(columns: dict[str, Any], ix: np.ndarray, time_ns: np.ndarray) -> list[bytes]:
    """JSON bytes of the :class:`ColumnMessages` payloads ``ix`` (with ``timestamp`` of
    ``time_ns``, the same length): ``orjson.dumps`` of each payload, a block at a time."""
    from itertools import repeat

    if ix.size == 0:
        return []
    parts: list[Any] = []
    text = b"{"
    for name, col in columns.items():
        text += orjson.dumps(name) + b":"
        if isinstance(col, np.ndarray):
            parts += [repeat(text), _column_bytes(col[ix])]
            text = b","
        else:
            text += orjson.dumps(col, option=orjson.OPT_SERIALIZE_NUMPY) + b","
    sec, nsec = np.divmod(np.asarray(time_ns, np.int64), NS)
    parts += [repeat(text + b'"timestamp":{"sec":'), _column_bytes(sec)]
    parts += [repeat(b',"nsec":'), _column_bytes(nsec), repeat(b"}}")]
    return [b"".join(p) for p in zip(*parts, strict=False)]  # repeat() never ends


@dataclass
class OutputChannel:
    """A new channel for the output recording.

    ``messages`` are ``(log_time_ns, payload)`` pairs (a list, or :class:`RowMessages` made
    on demand); each payload carries the same instant as ``timestamp`` (added when absent).
    """

    topic: str
    schema_name: str
    messages: list[tuple[int, dict[str, Any]]] | RowMessages = field(default_factory=list)

    @classmethod
    def rows(
        cls,
        topic: str,
        schema_name: str,
        time_ns: np.ndarray,
        payload: Callable[[int], dict[str, Any]],
    ) -> OutputChannel:
        """A channel whose message ``i`` is ``payload(i)`` at ``time_ns[i]`` (ns), built when
        written (see :class:`RowMessages`)."""
        return cls(topic, schema_name, RowMessages(time_ns, payload))

    @classmethod
    def columns(
        cls, topic: str, schema_name: str, time_ns: np.ndarray, columns: dict[str, Any]
    ) -> OutputChannel:
        """A channel whose message ``i`` is ``{name: column[i]}`` at ``time_ns[i]`` (ns),
        encoded a block at a time when written (see :class:`ColumnMessages`)."""
        return cls(topic, schema_name, ColumnMessages(time_ns, columns))

    def log_times_ns(self) -> np.ndarray:
        """Log time of every message, ns (int64, in ``messages`` order)."""
        if isinstance(self.messages, RowMessages):
            return self.messages.time_ns
        return np.fromiter((t for t, _ in self.messages), np.int64, len(self.messages))

    def add(self, log_time_ns: int, payload: dict[str, Any]) -> None:
        """Append one message; adds ``timestamp`` ``{sec, nsec}`` to the payload when absent.

        Parameters
        ----------
        log_time_ns : int
            Sample time, ns since the Unix epoch (UTC).
        payload : dict
            The message, in the channel's schema.
        """
        payload.setdefault("timestamp", stamp(log_time_ns))
        assert isinstance(self.messages, list), "a RowMessages channel takes no add()"
        self.messages.append((int(log_time_ns), payload))


def _same_file(a: Path, b: Path) -> bool:
    try:
        return b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def write_with_new_channels(
    src: str | Path,
    dst: str | Path,
    channels: Iterable[OutputChannel],
    metadata: dict[str, dict[str, str]] | None = None,
) -> Path:
    """Copy every record of ``src`` unchanged into ``dst`` and add ``channels``.

    Input schemas and channels keep their ids; input messages, metadata and attachments are
    copied byte for byte (a damaged input contributes what :mod:`pipeline.io.scan` salvages).
    Messages of the input and of the new channels are merged in log-time order (ties: input
    first), so a viewer streams the file without seeking back. New topics must not already
    exist in the input. Written atomically.

    The input is read twice and its messages are never all in memory: an index pass (each
    message's channel, time and place) and, while writing, a pass that decompresses one chunk
    at a time (:func:`~pipeline.io.scan.scan_index`, :func:`~pipeline.io.scan.
    iter_message_records`).
    """
    from mcap.data_stream import ReadDataStream
    from mcap.records import Attachment, AttachmentIndex, Channel, Metadata, Schema

    from pipeline.io.bulk import BulkWriter, serialise
    from pipeline.io.scan import ScanError, scan_index

    src, dst = Path(src), Path(dst)
    if _same_file(src, dst) or src.resolve() == dst.resolve():
        raise AeromagError(
            "output path is the input file; the input is never overwritten", file=dst
        )
    channels = [c for c in channels if c.messages]
    try:
        # pass 1: everything but the messages' contents (their channels and times, file
        # order); pass 2 (:func:`_input_records`) streams the records while writing
        index = scan_index(src)
    except (ScanError, OSError) as exc:
        raise AeromagError(f"could not copy the input recording ({exc})", file=src) from None
    sc = index.scan
    clash = sorted({c.topic for c in sc.channels.values()} & {c.topic for c in channels})
    if clash:
        raise AeromagError(
            "the input already has this output channel; process the original recording instead",
            file=src,
            channel=clash[0],
        )

    def parse(record: bytes, cls):
        return cls.read(ReadDataStream(io.BytesIO(record[9:])))

    with atomic_output(dst) as stream:
        w = BulkWriter(stream)
        w.start(profile=PROFILE, library=LIBRARY)
        for sid, (name, enc, data) in sorted(sc.schemas.items()):
            w.add_schema(Schema(id=sid, name=name, encoding=enc, data=data))
        for cid, ch in sorted(sc.channels.items()):
            if ch.schema_id and ch.schema_id not in sc.schemas:
                continue  # its schema was lost with a damaged chunk
            w.add_channel(
                Channel(
                    id=cid,
                    topic=ch.topic,
                    message_encoding=ch.message_encoding,
                    metadata=ch.metadata,
                    schema_id=ch.schema_id,
                )
            )
        schema_ids = {(n, e, d): sid for sid, (n, e, d) in sc.schemas.items()}
        next_sid = max(sc.schemas, default=0) + 1
        next_cid = max(sc.channels, default=-1) + 1
        # every message, input first (grouped by channel id, file order within), then each
        # new channel: (source, channel, time); a stable sort by time merges them (input
        # first at equal times) and records are produced in that order, input ones read
        # from the file again, new ones encoded as they go into a chunk
        f_cid = np.asarray(index.cid, np.uint16)
        keep = np.isin(f_cid, np.fromiter(w.channels, np.int64, len(w.channels)))
        kept = np.flatnonzero(keep)
        # the kept input records grouped by channel id (file order within), as their ranks
        # among the kept ones in file order (what pass 2 yields)
        input_rank = np.argsort(f_cid[kept], kind="stable")
        grouped = kept[input_rank]  # file index
        cids: list[np.ndarray] = [f_cid[grouped]]
        times = [np.asarray(index.time_ns, np.uint64)[grouped].astype(np.int64)]
        n_input = grouped.size
        del f_cid, kept, grouped
        sources = []
        for c in channels:
            key = (c.schema_name, SCHEMA_ENCODING, schema_bytes(c.schema_name))
            if key not in schema_ids:
                schema_ids[key] = next_sid
                w.add_schema(Schema(id=next_sid, name=key[0], encoding=key[1], data=key[2]))
                next_sid += 1
            cid = next_cid
            next_cid += 1
            w.add_channel(
                Channel(
                    id=cid,
                    topic=c.topic,
                    message_encoding=MESSAGE_ENCODING,
                    metadata={},
                    schema_id=schema_ids[key],
                )
            )
            t_c = c.log_times_ns()
            rank = np.argsort(t_c, kind="stable")  # as sorted(messages, key=time)
            sources.append(_encoded(c.messages, rank, cid))
            cids.append(np.full(t_c.size, cid, np.uint16))
            times.append(t_c[rank])
        if n_input or sources:
            take, c_all, t_all = _merge_plan(input_rank, cids, times)
            records = _input_records(src, index, keep)
            try:
                w.add_messages(_merged(records, sources, take), c_all, t_all)
            finally:
                records.close()
        for rec in sc.metadata_records:
            w.add_metadata_record(rec, parse(rec, Metadata).name)
        for name, data in (metadata or {}).items():
            rec = serialise(Metadata(name=name, metadata={k: str(v) for k, v in data.items()}))
            w.add_metadata_record(rec, name)
        for rec in sc.attachment_records:
            att = parse(rec, Attachment)
            w.add_attachment_record(
                rec,
                AttachmentIndex(
                    offset=0,
                    length=0,
                    log_time=att.log_time,
                    create_time=att.create_time,
                    data_size=len(att.data),
                    name=att.name,
                    media_type=att.media_type,
                ),
            )
        w.finish()
    return dst


def _merge_plan(
    input_rank: np.ndarray, cids: list[np.ndarray], times: list[np.ndarray]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The output order of every message: the input's (``cids[0]``, ``times[0]``; their
    ranks in pass 2 ``input_rank``) and each new channel's (``cids[k + 1]``, ``times[k + 1]``,
    in time order) merged by a stable sort of the times (input first at equal times).

    Returns what each output position takes (an input record: its rank in pass 2, >= 0; the
    next message of new channel k: ~k) and the channel ids and times in output order. The
    lists are emptied as their arrays are merged (millions of messages at 5 h: each copy
    counts in the write stage's peak memory).
    """
    take = np.empty(sum(t.size for t in times), np.int32)
    take[: input_rank.size] = input_rank
    pos = input_rank.size
    for k, t in enumerate(times[1:]):
        take[pos : pos + t.size] = ~k
        pos += t.size
    c_all = np.concatenate(cids)
    cids.clear()
    t_all = np.concatenate(times)
    times.clear()
    order = np.argsort(t_all, kind="stable")
    return take[order], c_all[order], t_all[order]


def _encoded(messages, rank: np.ndarray, cid: int) -> Iterator[bytes]:
    """Message records of a new channel in time order (``rank``), sequence numbers 0, 1, ...

    A :class:`RowMessages` channel (up to a million messages at 5 h) is encoded here
    directly, its times taken a block at a time: the same records as :meth:`RowMessages.
    __getitem__` then :func:`~pipeline.io.bulk.message_record` make, without their calls."""
    from mcap.opcode import Opcode

    from pipeline.io.bulk import MESSAGE_HEAD, message_record

    if not isinstance(messages, RowMessages):
        for k, i in enumerate(rank.tolist()):
            t, p = messages[i]
            yield message_record(cid, k, t, t, encode(p))
        return
    payload, time_ns = messages.payload, messages.time_ns
    pack, dumps, opt = MESSAGE_HEAD.pack, orjson.dumps, orjson.OPT_SERIALIZE_NUMPY
    op = Opcode.MESSAGE
    block = 1 << 14
    for b in range(0, rank.size, block):
        ix = rank[b : b + block]
        if isinstance(messages, ColumnMessages):
            t_ix = time_ns[ix]
            rows = encode_rows(messages.columns, ix, t_ix)
            for k, t, data in zip(range(b, b + ix.size), t_ix.tolist(), rows, strict=True):
                yield pack(op, 22 + len(data), cid, k & 0xFFFFFFFF, t, t) + data
            continue
        for k, i, t in zip(range(b, b + ix.size), ix.tolist(), time_ns[ix].tolist(), strict=True):
            p = payload(i)
            if "timestamp" not in p:  # stamp(t), inline
                sec, nsec = divmod(t, NS)
                p["timestamp"] = {"sec": sec, "nsec": nsec}
            data = dumps(p, option=opt)
            yield pack(op, 22 + len(data), cid, k & 0xFFFFFFFF, t, t) + data


def _input_records(src: Path, index, keep: np.ndarray) -> Iterator[bytes]:
    """The message records of ``index`` (:func:`~pipeline.io.scan.scan_index`), read again in
    file order, those of ``keep`` (a mask over that index) only."""
    from pipeline.io.scan import ScanError, iter_message_records

    at = 0
    every = bool(keep.all())
    try:
        for batch in iter_message_records(src, index):
            if every:
                yield from batch
            else:
                mine = keep[at : at + len(batch)].tolist()
                yield from (r for r, k in zip(batch, mine, strict=True) if k)
            at += len(batch)
    except ScanError as exc:
        raise AeromagError(f"could not copy the input recording ({exc})", file=src) from None


def _merged(
    records: Iterator[bytes],
    sources: list[Iterator[bytes]],
    take: np.ndarray,
    block: int = 1 << 16,
) -> Iterator[bytes]:
    """Records in merged order: for ``take[j] >= 0`` the input record of that rank in
    ``records`` (read in file order), for ``take[j] < 0`` the next of ``sources[~take[j]]``
    (a stable time sort keeps each new channel's own order).

    An input record is read when its turn comes; those read past on the way (a file not in
    log-time order, or messages of equal times on different channels) wait in a dict until
    theirs: a file in log-time order holds a few, the worst case all of them."""
    nexts = [s.__next__ for s in sources]
    read = records.__next__
    waiting: dict[int, bytes] = {}
    pos = 0  # rank of the next record to read
    try:
        for b in range(0, take.size, block):
            for v in take[b : b + block].tolist():
                if v < 0:
                    yield nexts[~v]()
                elif v == pos:
                    pos += 1
                    yield read()
                elif v < pos:
                    yield waiting.pop(v)
                else:
                    while pos < v:
                        waiting[pos] = read()
                        pos += 1
                    pos += 1
                    yield read()
    except StopIteration:
        raise AeromagError("the input recording changed while it was copied") from None


def write_json_atomic(path: str | Path, obj: Any) -> Path:
    """Write a JSON document atomically (see :func:`atomic_output`)."""
    with atomic_output(path) as f:
        f.write(
            orjson.dumps(
                obj,
                option=orjson.OPT_INDENT_2 | orjson.OPT_SERIALIZE_NUMPY | orjson.OPT_NON_STR_KEYS,
            )
        )
    return Path(path)


def write_text_atomic(path: str | Path, text: str) -> Path:
    """Write a text file (UTF-8) atomically (see :func:`atomic_output`)."""
    with atomic_output(path) as f:
        f.write(text.encode("utf-8"))
    return Path(path)
