"""A salvaging, bounded, fast scan of an MCAP file's records.

Why hand-written: the official reader (``mcap.reader``) stops at the first damaged record — a
truncated file, a chunk whose CRC does not match, a chunk declaring an absurd size — and loses
everything after it; it also builds one Python object per message. Post-flight processing needs
the opposite on both counts: every intact chunk of a damaged recording, with the loss reported as
time ranges, and the payloads of each channel as plain lists to decode column-wise. The format
itself is simple (https://mcap.dev/spec): magic, then records ``opcode u8 | length u64 | body``;
a Chunk's body holds compressed Schema/Channel/Message records. This module walks those records
on a read-only memory map and never trusts a declared size beyond the file and a fixed limit.
"""

from __future__ import annotations

import mmap
import struct
import zlib
from array import array
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from pipeline.io.series import Loss

MAGIC = b"\x89MCAP0\r\n"
OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 0x02, 0x03, 0x04, 0x05, 0x06
OP_ATTACHMENT, OP_METADATA, OP_DATA_END = 0x09, 0x0C, 0x0F

# A chunk larger than this is refused rather than decompressed: recorders write chunks of a few
# MB; a declared size beyond this is damage or hostility, and believing it could exhaust memory.
MAX_CHUNK_BYTES = 256 * 1024 * 1024
# the file map's pages are given back every this many bytes walked (see :func:`release`)
RELEASE_BYTES = 8 * 1024 * 1024

_U16, _U32, _U64 = struct.Struct("<H"), struct.Struct("<I"), struct.Struct("<Q")
_CHUNK_HEAD = struct.Struct("<QQQI")  # start, end, uncompressed size, uncompressed crc
_MSG_HEAD = struct.Struct("<H4xQ")  # channel id, (sequence), log time


class ScanError(Exception):
    """The file cannot be scanned at all (not MCAP, or nothing before the damage)."""


@dataclass
class ChannelData:
    """One MCAP channel as scanned: topic, schema id, message encoding, channel metadata, and the
    log time (ns) and payload of each message (its whole record with ``whole_records``).
    """

    topic: str
    schema_id: int
    message_encoding: str
    metadata: dict[str, str] = field(default_factory=dict)
    # log times (u64): an array of 8 bytes a message, not a list of 40-byte Python ints
    log_time_ns: array = field(default_factory=lambda: array("Q"))
    data: list[bytes] = field(default_factory=list)  # payloads, or whole records (see scan)


@dataclass
class Scan:
    """What a scan found: schemas, channels with their messages, and what was lost."""

    schemas: dict[int, tuple[str, str, bytes]] = field(default_factory=dict)  # name, enc, data
    channels: dict[int, ChannelData] = field(default_factory=dict)
    losses: list[Loss] = field(default_factory=list)
    footer_seen: bool = False
    summary_seen: bool = False  # records after Data End (the index section)
    chunks: int = 0
    orphan_messages: int = 0  # on a channel whose Channel record was lost
    metadata_records: list[bytes] = field(default_factory=list)  # whole records, file order
    attachment_records: list[bytes] = field(default_factory=list)

    def schema_of(self, ch: ChannelData) -> tuple[str, str]:
        """Schema name and encoding of a channel (empty strings when its Schema record was lost).

        Parameters
        ----------
        ch : ChannelData

        Returns
        -------
        tuple of (str, str)
        """
        name, enc, _ = self.schemas.get(ch.schema_id, ("", "", b""))
        return name, enc


@dataclass
class MessageIndex:
    """Where the messages of a recording are (:func:`scan_index`), one entry a message on a
    known channel, in file order.

    Attributes
    ----------
    scan : Scan
        Schemas, channels (no messages in them), metadata, attachments, losses.
    cid : array of uint16
        Channel id.
    time_ns : array of uint64
        Log time, ns since the Unix epoch.
    start, end : array of uint64
        The whole record's byte span in its chunk's decompressed content (in the file for a
        message outside chunks).
    segments : list of (int, int, int)
        Per intact chunk (and run of messages outside chunks): the chunk body's byte span
        in the file (-1, -1 outside chunks) and the index of its first message.
    """

    scan: Scan
    cid: array = field(default_factory=lambda: array("H"))
    time_ns: array = field(default_factory=lambda: array("Q"))
    start: array = field(default_factory=lambda: array("Q"))
    end: array = field(default_factory=lambda: array("Q"))
    segments: list[tuple[int, int, int]] = field(default_factory=list)


def _string(buf, pos: int, end: int) -> tuple[str, int]:
    n = _U32.unpack_from(buf, pos)[0]
    pos += 4
    if pos + n > end:
        raise ValueError("string runs past its record")
    return bytes(buf[pos : pos + n]).decode("utf-8"), pos + n


def _string_map(buf, pos: int, end: int) -> dict[str, str]:
    n = _U32.unpack_from(buf, pos)[0]
    pos += 4
    stop = pos + n
    if stop > end:
        raise ValueError("map runs past its record")
    out = {}
    while pos < stop:
        k, pos = _string(buf, pos, stop)
        v, pos = _string(buf, pos, stop)
        out[k] = v
    return out


def _decompress(compression: str, data, usize: int) -> bytes:
    if compression == "":
        return bytes(data)
    if compression == "zstd":
        import zstandard

        size = zstandard.frame_content_size(data)
        if size > usize:  # the frame claims more than the chunk header: do not believe either
            raise ValueError(f"zstd frame declares {size} bytes, chunk header {usize}")
        return zstandard.ZstdDecompressor().decompress(data, max_output_size=usize)
    if compression == "lz4":
        import lz4.frame

        return lz4.frame.LZ4FrameDecompressor().decompress(bytes(data), max_length=usize)
    raise ValueError(f"unsupported compression {compression!r}")


class _Scanner:
    """The record walk. ``mode`` says what each message on a known channel leaves:
    ``payload`` (its payload, per channel), ``record`` (its whole record, per channel) or
    ``index`` (its channel id, log time and place, in file order: see :class:`MessageIndex`).
    """

    def __init__(self, buf, wanted: set[str] | None, mode: str = "payload"):
        self.buf = buf
        self.wanted = wanted
        self.mode = mode
        self.whole = mode == "record"
        self.out = Scan()
        self._sinks: dict[int, tuple] = {}  # channel id -> (append time, append payload)
        self._after_data_end = False
        self._kept = 0  # the file map's pages before this offset were given back
        self.index = MessageIndex(self.out) if mode == "index" else None

    def _sink(self, cid: int, ch: ChannelData) -> tuple:
        """(append log time, append payload or record) for the messages of channel ``cid``
        (index mode: the rest is appended in :meth:`records`)."""
        if self.index is not None:
            return self.index.time_ns.append, None
        return ch.log_time_ns.append, ch.data.append

    # -- records shared by the top level and chunks ------------------------------------------
    def record(self, buf, op: int, pos: int, end: int) -> None:
        """A Channel or Schema record (messages take the hot path in :meth:`records`)."""
        if op == OP_CHANNEL:
            cid = _U16.unpack_from(buf, pos)[0]
            sid = _U16.unpack_from(buf, pos + 2)[0]
            topic, p = _string(buf, pos + 4, end)
            enc, p = _string(buf, p, end)
            meta = _string_map(buf, p, end)
            if cid not in self.out.channels:
                ch = self.out.channels[cid] = ChannelData(topic, sid, enc, meta)
                if self.wanted is None or topic in self.wanted:
                    self._sinks[cid] = self._sink(cid, ch)
        elif op == OP_SCHEMA:
            sid = _U16.unpack_from(buf, pos)[0]
            name, p = _string(buf, pos + 2, end)
            enc, p = _string(buf, p, end)
            n = _U32.unpack_from(buf, p)[0]
            if p + 4 + n > end:
                raise ValueError("schema data runs past its record")
            self.out.schemas.setdefault(sid, (name, enc, bytes(buf[p + 4 : p + 4 + n])))

    def chunk(self, pos: int, end: int) -> None:
        buf = self.buf
        start, stop, usize, crc = _CHUNK_HEAD.unpack_from(buf, pos)
        loss = Loss(pos - 9, "", start, stop, end - pos + 9)
        try:
            compression, p = _string(buf, pos + 28, end)
            dlen = _U64.unpack_from(buf, p)[0]
            if p + 8 + dlen > end:
                raise ValueError("chunk data runs past its record")
            if usize > MAX_CHUNK_BYTES:
                loss.reason = (
                    f"chunk declares {usize} uncompressed bytes (limit {MAX_CHUNK_BYTES}): skipped"
                )
                self.out.losses.append(loss)
                return
            data = _decompress(compression, memoryview(buf)[p + 8 : p + 8 + dlen], usize)
        except Exception as exc:  # noqa: BLE001 - any damage to one chunk loses that chunk only
            loss.reason = f"chunk unreadable ({type(exc).__name__}: {exc})"
            self.out.losses.append(loss)
            return
        if len(data) != usize:
            loss.reason = f"chunk decompresses to {len(data)} bytes, header says {usize}"
            self.out.losses.append(loss)
            return
        if crc != 0 and zlib.crc32(data) != crc:
            loss.reason = "chunk CRC mismatch (corrupt data)"
            self.out.losses.append(loss)
            return
        self.out.chunks += 1
        if self.index is not None:
            self.index.segments.append((pos, end, len(self.index.cid)))
        self.records(data, 0, len(data), inner=True, base=pos)

    def records(self, buf, pos: int, size: int, *, inner: bool, base: int = 0) -> None:
        """Walk the records of ``buf[pos:size]`` (a chunk's content when ``inner``)."""
        u64 = _U64.unpack_from
        head = _MSG_HEAD.unpack_from
        sinks = self._sinks
        whole = self.whole
        ix = self.index
        if ix is not None:
            add_cid, add_start, add_end = ix.cid.append, ix.start.append, ix.end.append
        while pos < size:
            if pos + 9 > size:
                self._truncated(pos, size, inner, base)
                return
            op = buf[pos]
            end = pos + 9 + u64(buf, pos + 1)[0]
            if end > size:
                self._truncated(pos, size, inner, base)
                return
            if op == OP_MESSAGE:
                # the hot path, inlined: one message record (header: channel id, sequence,
                # log time, publish time = 22 bytes)
                if end - pos < 31:
                    self.out.losses.append(
                        Loss(
                            base + pos,
                            "malformed record (message shorter than its header)",
                            bytes_lost=end - pos,
                        )
                    )
                else:
                    cid, lt = head(buf, pos + 9)
                    sink = sinks.get(cid)
                    if sink is None:
                        pass
                    elif ix is None:
                        sink[0](lt)
                        sink[1](buf[pos:end] if whole else buf[pos + 31 : end])
                    else:
                        if not inner and (not ix.segments or ix.segments[-1][0] >= 0):
                            ix.segments.append((-1, -1, len(ix.cid)))  # outside chunks
                        sink[0](lt)
                        add_cid(cid)
                        add_start(pos)
                        add_end(end)
                    if sink is None and cid not in self.out.channels:
                        self.out.orphan_messages += 1
                pos = end
                continue
            body = pos + 9
            try:
                if op == OP_CHUNK and not inner:
                    self.chunk(body, end)
                elif op in (OP_CHANNEL, OP_SCHEMA):
                    self.record(buf, op, body, end)
                elif op == OP_FOOTER and not inner:
                    self.out.footer_seen = True
                    return
                elif op == OP_DATA_END and not inner:
                    self._after_data_end = True
                elif op == OP_METADATA and not inner and not self._after_data_end:
                    self.out.metadata_records.append(bytes(buf[pos:end]))
                elif op == OP_ATTACHMENT and not inner and not self._after_data_end:
                    self.out.attachment_records.append(bytes(buf[pos:end]))
                if self._after_data_end and op != OP_DATA_END and not inner:
                    self.out.summary_seen = True
            except (struct.error, ValueError, UnicodeDecodeError) as exc:
                self.out.losses.append(
                    Loss(
                        base + pos,
                        f"malformed record (opcode {op:#04x}: {exc})",
                        bytes_lost=end - pos,
                    )
                )
            pos = end
            if not inner and pos - self._kept >= RELEASE_BYTES:
                self._kept = release(buf, self._kept, pos)

    def _truncated(self, pos: int, size: int, inner: bool, base: int) -> None:
        if inner:
            self.out.losses.append(
                Loss(base, "chunk content ends inside a record", bytes_lost=size - pos)
            )
        else:
            self.out.losses.append(
                Loss(pos, "file truncated: the last record is incomplete", bytes_lost=size - pos)
            )


def release(buf, start: int, stop: int) -> int:
    """Give back the resident pages of the file map ``buf`` between ``start`` and ``stop``
    (rounded down to a page) once they are read, so that walking a large file does not add
    its size to the process's resident memory (pages mapped from a file count in it, and
    in its peak, as long as they stay mapped); they are read again from the file if touched.
    Returns the new start. Anything but a memory map is left alone."""
    stop -= stop % mmap.PAGESIZE
    if isinstance(buf, mmap.mmap) and stop > start and hasattr(mmap, "MADV_DONTNEED"):
        buf.madvise(mmap.MADV_DONTNEED, start, stop - start)
        return stop
    return start


def _close_map(mm: mmap.mmap) -> None:
    """Close the file map. A view into it that only a reference cycle still holds (freed at
    the next garbage collection) makes ``close`` raise BufferError: seen once as "internal
    error: BufferError: cannot close exported pointers exist" on a Dask worker during archive
    reprocessing, a valid file quarantined. Collect and retry; if a view is still alive the
    map closes itself when the last one goes."""
    try:
        mm.close()
    except BufferError:
        import gc

        gc.collect()
        try:
            mm.close()
        except BufferError:
            pass


@contextmanager
def _mapped(path: Path) -> Iterator[tuple[mmap.mmap, int]]:
    """The file memory-mapped read-only, with its size, once its magic is checked."""
    with path.open("rb") as f:
        size = path.stat().st_size
        if size == 0:
            raise ScanError("empty file (0 bytes), not an MCAP recording")
        head = f.read(len(MAGIC))
        if head != MAGIC:
            raise ScanError(
                f"not a readable MCAP recording (starts with {head[:8]!r}, not the MCAP magic)"
            )
        mm = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        try:
            yield mm, size
        finally:
            _close_map(mm)


def _finish(out: Scan, size: int) -> Scan:
    if not out.footer_seen and not any("truncated" in x.reason for x in out.losses):
        out.losses.append(Loss(size, "no footer: the recording was not closed (summary lost)"))
    return out


def scan_mcap(
    path: str | Path, topics: set[str] | None = None, *, whole_records: bool = False
) -> Scan:
    """Read every intact record of an MCAP file, salvaging around damage.

    Parameters
    ----------
    path
        The file (opened read-only, memory-mapped).
    topics
        Keep the messages of these topics only (default: all).
    whole_records
        Keep each message as its whole serialised record (opcode, length, header, payload),
        to copy it byte for byte, instead of its payload.

    Raises
    ------
    ScanError
        Empty file or no MCAP magic.
    """
    sc, size = _walk(path, topics, "record" if whole_records else "payload")
    return _finish(sc.out, size)


def scan_index(path: str | Path) -> MessageIndex:
    """:func:`scan_mcap` without the messages' contents: schemas, channels (their ``data``
    and ``log_time_ns`` left empty), metadata and attachment records and losses in
    ``.scan``, and the channel id, log time and place of every message on a known channel,
    in file order.

    With :func:`iter_message_records` (the same messages, same order, as whole records) a
    large recording is copied without holding its messages in memory.

    Raises
    ------
    ScanError
        Empty file or no MCAP magic.
    """
    sc, size = _walk(path, None, "index")
    _finish(sc.out, size)
    return sc.index


def _walk(path: str | Path, topics, mode: str) -> tuple[_Scanner, int]:
    """Every top-level record of the file at ``path`` through a :class:`_Scanner` in
    ``mode`` (payload, record or index); the scanner and the file size (bytes)."""
    with _mapped(Path(path)) as (mm, size):
        sc = _Scanner(mm, topics, mode)
        sc.records(mm, len(MAGIC), size, inner=False)
    return sc, size


def iter_message_records(path: str | Path, index: MessageIndex) -> Iterator[list[bytes]]:
    """The whole serialised record of every message ``index`` (:func:`scan_index` of the
    same file) lists, in its order: a list per chunk (or per run of messages outside chunks).
    Only the current chunk is held (and the file map, until the iterator ends or is closed).

    Raises
    ------
    ScanError
        The file is not the one indexed any more (a chunk no longer decompresses to what it
        did).
    """
    path = Path(path)
    bounds = [s[2] for s in index.segments[1:]] + [len(index.cid)]
    kept = 0
    with _mapped(path) as (mm, _):
        for (pos, end, i0), i1 in zip(index.segments, bounds, strict=True):
            if i1 == i0:
                continue
            data = mm if pos < 0 else _chunk_content(mm, pos, end)
            batch = [
                data[a:b]
                for a, b in zip(index.start[i0:i1].tolist(), index.end[i0:i1].tolist(), strict=True)
            ]
            kept = release(mm, kept, end if pos >= 0 else index.end[i1 - 1])
            yield batch


def _chunk_content(buf, pos: int, end: int) -> bytes:
    """The decompressed content of the Chunk record whose body spans ``buf[pos:end]`` (one
    the scan found intact)."""
    _, _, usize, crc = _CHUNK_HEAD.unpack_from(buf, pos)
    try:
        compression, p = _string(buf, pos + 28, end)
        dlen = _U64.unpack_from(buf, p)[0]
        data = _decompress(compression, memoryview(buf)[p + 8 : p + 8 + dlen], usize)
    except Exception as exc:  # noqa: BLE001
        raise ScanError(f"a chunk at byte {pos - 9} changed since it was read ({exc})") from None
    if len(data) != usize or (crc != 0 and zlib.crc32(data) != crc):
        raise ScanError(f"a chunk at byte {pos - 9} changed since it was read")
    return data
