"""Writing many messages into an MCAP file in one pass: chunks packed from whole record lists.

Why hand-written: ``mcap.writer.Writer.add_message`` builds and serialises Python objects for
every message and its index entry (~18 µs per message here), which made copying a 5 h flight's
two million records the slowest stage of the post-flight flow. Here message records arrive
already serialised — input records are copied byte for byte, new ones packed by
:func:`message_record` — and a chunk's message indexes are packed with numpy. Every other
record (header, schemas, channels, chunk, indexes, statistics, summary offsets, footer) is
serialised by the mcap package's own record classes, so the layout follows the specification
(https://mcap.dev/spec) exactly as the official writer does it: chunked, zstd, CRCs, full
summary with offsets.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Iterable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from itertools import islice
from typing import BinaryIO

import numpy as np
import zstandard
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    AttachmentIndex,
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

MAGIC = b"\x89MCAP0\r\n"
# a Message record's head: opcode, length, channel id, sequence, log time, publish time
MESSAGE_HEAD = struct.Struct("<BQHIQQ")


def message_record(
    channel_id: int, sequence: int, log_time_ns: int, publish_time_ns: int, data: bytes
) -> bytes:
    """One serialised Message record."""
    return (
        MESSAGE_HEAD.pack(
            Opcode.MESSAGE,
            22 + len(data),
            channel_id,
            sequence & 0xFFFFFFFF,
            log_time_ns,
            publish_time_ns,
        )
        + data
    )


def serialise(record) -> bytes:
    """Any mcap record object (Schema, Chunk, Footer, ...) as bytes, by its own writer."""
    b = RecordBuilder()
    record.write(b)
    return b.end()


class BulkWriter:
    """MCAP writer for pre-serialised message records in log-time order.

    Parameters
    ----------
    stream
        Binary output, positioned at 0.
    chunk_size
        Uncompressed bytes per chunk (the official writer's default, 1 MiB).
    """

    def __init__(self, stream: BinaryIO, chunk_size: int = 1 << 20, level: int = 3):
        self.stream = stream
        self.chunk_size = chunk_size
        self._zstd = zstandard.ZstdCompressor(level=level)
        # a chunk being compressed on the second thread (add_messages): its future and the
        # rest of what writing it needs
        self._pool: ThreadPoolExecutor | None = None
        self._pending: tuple[Future, np.ndarray, np.ndarray, np.ndarray] | None = None
        self._crc = 0
        self._pos = 0
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.chunk_indexes: list[ChunkIndex] = []
        self.metadata_indexes: list[MetadataIndex] = []
        self.attachment_indexes: list[AttachmentIndex] = []
        self.stats = Statistics(
            attachment_count=0,
            channel_count=0,
            channel_message_counts={},
            chunk_count=0,
            message_count=0,
            message_end_time=0,
            message_start_time=0,
            metadata_count=0,
            schema_count=0,
        )

    # -- low level ---------------------------------------------------------------------------
    def _write(self, data: bytes) -> int:
        """Append to the data section; returns the offset it was written at."""
        at = self._pos
        self.stream.write(data)
        self._crc = zlib.crc32(data, self._crc)
        self._pos += len(data)
        return at

    # -- records -----------------------------------------------------------------------------
    def start(self, profile: str = "", library: str = "") -> None:
        """Write the MCAP magic and the Header record.

        Parameters
        ----------
        profile : str
            MCAP profile (empty for aeromag's JSON channels).
        library : str
            Name and version of the writing library.
        """
        self._write(MAGIC)
        self._write(serialise(Header(profile=profile, library=library)))

    def add_schema(self, schema: Schema) -> None:
        """Register ``schema`` under its id and write its Schema record."""
        self.schemas[schema.id] = schema
        self._write(serialise(schema))

    def add_channel(self, channel: Channel) -> None:
        """Register ``channel`` under its id and write its Channel record."""
        self.channels[channel.id] = channel
        self._write(serialise(channel))

    def add_metadata_record(self, record: bytes, name: str) -> None:
        """A serialised Metadata record (opcode + length + body)."""
        at = self._write(record)
        self.metadata_indexes.append(MetadataIndex(offset=at, length=len(record), name=name))

    def add_attachment_record(self, record: bytes, index: AttachmentIndex) -> None:
        """Write a serialised Attachment record and index it.

        Parameters
        ----------
        record : bytes
            The whole record (opcode + length + body).
        index : AttachmentIndex
            Its index entry; ``offset`` and ``length`` are filled in here.
        """
        index.offset = self._write(record)
        index.length = len(record)
        self.attachment_indexes.append(index)

    def add_messages(
        self, records: Iterable[bytes], channel_id: np.ndarray, log_time_ns: np.ndarray
    ) -> None:
        """Message records in the order to write them (log time order), packed into chunks.

        ``records`` may be any iterable (a generator encoding them on the fly): they are
        consumed one chunk at a time, so only a chunk's worth is held here. ``channel_id`` and
        ``log_time_ns`` give each record's channel and log time, in the same order.
        """
        n = len(channel_id)
        if n == 0:
            return
        limit = self.chunk_size
        batch: list[bytes] = []  # the open chunk's records, from record ``start`` on
        size = start = 0

        def flush() -> None:
            end = start + len(batch)
            lens = np.fromiter(map(len, batch), np.int64, len(batch))
            self._chunk(
                batch, channel_id[start:end], log_time_ns[start:end], np.cumsum(lens) - lens
            )

        # records are taken a block at a time and a chunk's boundary found from their lengths'
        # running sum (a record joins while the chunk stays within ``limit``; one larger than a
        # chunk gets its own): the same chunks as a record-by-record loop, without its calls;
        # each chunk is compressed on a second thread while the next one is packed (zstd and
        # crc32 release the GIL); chunks are written in their order: the same bytes
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="mcap-chunk")
        try:
            it = iter(records)
            while part := list(islice(it, 1 << 13)):
                lens = np.fromiter(map(len, part), np.int64, len(part))
                j = 0
                while j < len(part):
                    fill = size + np.cumsum(lens[j:])
                    fit = int(np.searchsorted(fill, limit, side="right"))
                    if fit == 0 and not batch:
                        fit = 1
                    if fit:
                        batch.extend(part[j : j + fit])
                        size = int(fill[fit - 1])
                        j += fit
                    if j < len(part):  # the next record does not fit: close the chunk
                        flush()
                        start += len(batch)
                        batch, size = [], 0
            if start + len(batch) != n:
                raise ValueError(f"{start + len(batch)} records for {n} channel ids and times")
            flush()
        finally:
            try:
                self._write_pending()
            finally:
                self._pool.shutdown()
                self._pool = None
        counts = np.bincount(channel_id.astype(np.int64))
        for cid in np.flatnonzero(counts):
            self.stats.channel_message_counts[int(cid)] = self.stats.channel_message_counts.get(
                int(cid), 0
            ) + int(counts[cid])
        first, last = int(log_time_ns.min()), int(log_time_ns.max())
        if self.stats.message_count == 0:
            self.stats.message_start_time, self.stats.message_end_time = first, last
        else:
            self.stats.message_start_time = min(self.stats.message_start_time, first)
            self.stats.message_end_time = max(self.stats.message_end_time, last)
        self.stats.message_count += n

    def _chunk(
        self, records: Sequence[bytes], cids: np.ndarray, times: np.ndarray, offsets: np.ndarray
    ) -> None:
        """Compress a chunk of ``records`` on the pool's thread (:meth:`add_messages`) and
        write the one before it."""
        data = b"".join(records)
        job = self._pool.submit(self._compressed, data)
        self._write_pending()
        self._pending = (job, cids, times, offsets)

    def _compressed(self, data: bytes) -> tuple[bytes, int, int]:
        """(zstd bytes, crc32, size) of a chunk's content."""
        return self._zstd.compress(data), zlib.crc32(data), len(data)

    def _write_pending(self) -> None:
        """Write the chunk waiting for its compression, if any (and its message indexes)."""
        if self._pending is None:
            return
        job, cids, times, offsets = self._pending
        self._pending = None
        compressed, crc, usize = job.result()
        chunk = Chunk(
            compression="zstd",
            data=compressed,
            message_start_time=int(times.min()),
            message_end_time=int(times.max()),
            uncompressed_crc=crc,
            uncompressed_size=usize,
        )
        rec = serialise(chunk)
        at = self._write(rec)
        index = ChunkIndex(
            message_start_time=chunk.message_start_time,
            message_end_time=chunk.message_end_time,
            chunk_start_offset=at,
            chunk_length=len(rec),
            message_index_offsets={},
            message_index_length=0,
            compression="zstd",
            compressed_size=len(compressed),
            uncompressed_size=usize,
        )
        parts = []
        pos = self._pos
        for cid in np.unique(cids):
            sel = cids == cid
            pairs = np.empty((int(sel.sum()), 2), dtype="<u8")
            pairs[:, 0] = times[sel]
            pairs[:, 1] = offsets[sel]
            body = pairs.tobytes()
            # MessageIndex: opcode, length, channel id u16, records as u32-prefixed byte array
            part = (
                struct.pack("<BQHI", Opcode.MESSAGE_INDEX, 2 + 4 + len(body), int(cid), len(body))
                + body
            )
            index.message_index_offsets[int(cid)] = pos
            pos += len(part)
            parts.append(part)
        blob = b"".join(parts)
        self._write(blob)
        index.message_index_length = len(blob)
        self.chunk_indexes.append(index)
        self.stats.chunk_count += 1

    def finish(self) -> None:
        """Data End, the summary section (schemas, channels, statistics, indexes, offsets),
        the footer and the closing magic."""
        self._write(serialise(DataEnd(data_section_crc=self._crc)))
        summary_start = self._pos
        s = self.stats
        s.schema_count, s.channel_count = len(self.schemas), len(self.channels)
        s.metadata_count, s.attachment_count = (
            len(self.metadata_indexes),
            len(self.attachment_indexes),
        )
        for cid in self.channels:
            s.channel_message_counts.setdefault(cid, 0)
        groups = [
            (Opcode.SCHEMA, list(self.schemas.values())),
            (Opcode.CHANNEL, list(self.channels.values())),
            (Opcode.STATISTICS, [s]),
            (Opcode.CHUNK_INDEX, self.chunk_indexes),
            (Opcode.ATTACHMENT_INDEX, self.attachment_indexes),
            (Opcode.METADATA_INDEX, self.metadata_indexes),
        ]
        body: list[bytes] = []
        offsets: list[SummaryOffset] = []
        pos = summary_start
        for opcode, recs in groups:
            if not recs:
                continue
            blob = b"".join(serialise(r) for r in recs)
            offsets.append(
                SummaryOffset(group_opcode=opcode, group_start=pos, group_length=len(blob))
            )
            body.append(blob)
            pos += len(blob)
        summary_offset_start = pos
        body += [serialise(o) for o in offsets]
        summary = b"".join(body)
        crc = zlib.crc32(summary)
        crc = zlib.crc32(
            struct.pack("<BQQQ", Opcode.FOOTER, 20, summary_start, summary_offset_start), crc
        )
        self.stream.write(summary)
        self.stream.write(
            serialise(
                Footer(
                    summary_start=summary_start,
                    summary_offset_start=summary_offset_start,
                    summary_crc=crc,
                )
            )
        )
        self.stream.write(MAGIC)
