"""An MCAP file rewritten indexed and in log-time order, in bounded memory.

What :meth:`pisc_bag.bag.BagWriter.close` and :func:`pisc_bag.bag_repair.repair_bag`
use to finish a bag (before, a 10-minute bag was finished by reading every message into
memory, 12.5 s and +458 MB, through the mcap writer's 10 us a message).

**Reading**: :class:`pisc_bag.mcap_scan.RecordScan` walks the file in blocks and gives its
messages in batches (the whole records up to the first incomplete or corrupt one, without
the messages of a channel that has no channel record before them).

**Ordering**: the messages of a recording arrive almost in log-time order (the
recorder takes them from several DDS readers: the reference bags had inversions of up to
10 messages, 5.6 ms). Each block's messages join a pool of the ones held back; the pool
is sorted by log time, stably (a tie keeps the recorded order), and all but the newest
:data:`HOLD_MESSAGES` are written. A message older than the last one written (the
window's flush point) would have to go before it: the window is then given up, and the
file is sorted again by an external merge: each block's messages sorted into a run in a
temporary directory beside the bag, the runs merged (stable as well). Either way every
message is written, in the order a stable sort of the whole file by log time gives.

**Writing** (:class:`IndexedWriter`): the layout of the ``mcap`` library's writer, byte
for byte (for schema and channel ids as the recorder writes them, 1, 2, ...): the
header; the schemas then the channels at the start of the first chunk; messages in
uncompressed chunks closed when they pass :data:`CHUNK_SIZE`, each followed by its
message indexes (one per channel, in the order of the channel's first message in the
chunk); the data end; a summary with the schemas, channels, statistics and chunk
indexes, the summary offsets, and the footer with the summary's CRC. Message records are
copied as they were read; the indexes are built with numpy.

Memory: one block, the held messages and one chunk (about 15 MB), whatever the length
of the bag; the merge holds one buffer per run.
"""

from __future__ import annotations

import heapq
import struct
import tempfile
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np

from pisc_bag.mcap_scan import (
    MCAP_MAGIC,
    MESSAGE_HEAD,
    OP_ATTACHMENT_INDEX,
    OP_CHANNEL,
    OP_CHUNK,
    OP_CHUNK_INDEX,
    OP_FOOTER,
    OP_MESSAGE_INDEX,
    OP_METADATA_INDEX,
    OP_SCHEMA,
    OP_STATISTICS,
    Batch,
    NotMcap,
    RecordScan,
    concat,
    message_batch,
)

__all__ = ["CHUNK_SIZE", "HOLD_MESSAGES", "IndexCounts", "IndexedWriter", "Written",
           "index_counts", "write_sorted"]

CHUNK_SIZE = 768 * 1024  # libmcap's default chunk size, which rosbag2 writes with
HOLD_MESSAGES = 8192  # held back to be sorted with the next block's messages
MERGE_READ_BYTES = 256 * 1024  # each run's read buffer in the external merge
SCRATCH_PREFIX = ".pisc-sort-"  # the external merge's temporary directory, beside the bag

@dataclass
class Written:
    """What :func:`write_sorted` wrote."""

    schemas: dict[int, Any]  # as read, by id
    channels: dict[int, Any]
    counts: dict[int, int]  # messages per channel id, every channel (0: none)
    first_ns: int  # log time of the first message (0: none)
    last_ns: int
    whole_bytes: int  # the source's offset after its last whole record
    size: int  # the source's size
    merged: bool  # the window was given up for the external merge
    messages: int = field(init=False)

    def __post_init__(self) -> None:
        self.messages = sum(self.counts.values())


class IndexedWriter:
    """Writes an indexed MCAP file as the mcap library's ``Writer`` (uncompressed chunks,
    CRCs, the summary with every index) would, from message records in log-time order."""

    def __init__(self, out: IO[bytes], library: str, chunk_size: int = CHUNK_SIZE) -> None:
        from mcap.data_stream import RecordBuilder
        from mcap.records import Header

        self._out = out
        self._written = 0  # offsets in the file: it is written from its start
        self._chunk_size = chunk_size
        builder = RecordBuilder()
        Header("ros2", library).write(builder)
        self._write(MCAP_MAGIC + builder.end())
        self.schemas: dict[int, Any] = {}
        self.channels: dict[int, Any] = {}
        self.counts: dict[int, int] = {}  # channel id -> messages, in order of the first
        self.messages = 0
        self.first_ns = self.last_ns = 0
        self._chunk: list[bytes] = []  # the open chunk's records
        self._chunk_bytes = 0
        self._index: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # channel, log, at
        self._chunk_indexes: list[Any] = []

    @property
    def _pos(self) -> int:
        return self._written

    def _write(self, data: bytes) -> None:
        self._out.write(data)
        self._written += len(data)

    def define(self, records: list[Any]) -> None:
        """Schemas and channels not yet written, schemas first (as the mcap writer has
        them registered), into the open chunk."""
        from mcap.data_stream import RecordBuilder
        from mcap.records import Channel, Schema

        builder = RecordBuilder()
        for record in [r for r in records if isinstance(r, Schema)] + [
                r for r in records if isinstance(r, Channel)]:
            if isinstance(record, Schema) and record.id not in self.schemas:
                self.schemas[record.id] = record
                record.write(builder)
            elif isinstance(record, Channel) and record.id not in self.channels:
                if record.schema_id not in self.schemas:
                    record = Channel(record.id, record.topic, record.message_encoding, 0,
                                     record.metadata)
                self.channels[record.id] = record
                record.write(builder)
        data = builder.end()
        if data:
            self._chunk.append(data)
            self._chunk_bytes += len(data)
            if self._index and self._chunk_bytes > self._chunk_size:
                self._close_chunk()

    def add(self, batch: Batch) -> None:
        """The messages of ``batch``, in its order (log-time order, checked by the caller)."""
        n = len(batch)
        if not n:
            return
        starts, sizes = batch.starts, batch.sizes
        ends = np.cumsum(sizes)  # each message's end, counted over the batch
        view = memoryview(batch.data)
        contiguous = bool(np.all(starts[1:] == starts[:-1] + sizes[:-1]))
        i = 0
        while i < n:
            begun = int(ends[i - 1]) if i else 0
            # the chunk closes after the first message that takes it past the chunk size
            k = max(i, int(np.searchsorted(ends, self._chunk_size - self._chunk_bytes + begun,
                                           side="right")))
            j = min(k, n - 1)
            if contiguous:
                self._chunk.append(view[starts[i]:starts[i] + int(ends[j]) - begun])
            else:
                self._chunk.extend(view[s:s + m] for s, m in zip(
                    starts[i:j + 1].tolist(), sizes[i:j + 1].tolist(), strict=True))
            at = self._chunk_bytes + (ends[i:j + 1] - sizes[i:j + 1] - begun)
            self._index.append((batch.channel[i:j + 1], batch.log[i:j + 1],
                                at.astype(np.uint64)))
            self._chunk_bytes += int(ends[j]) - begun
            if k < n:
                self._close_chunk()
            i = j + 1
        ids, first, counts = np.unique(batch.channel, return_index=True, return_counts=True)
        for k in np.argsort(first).tolist():  # the statistics list channels as they come
            cid = int(ids[k])
            self.counts[cid] = self.counts.get(cid, 0) + int(counts[k])
        if not self.messages:
            self.first_ns = int(batch.log[0])
        self.messages += n
        self.last_ns = max(self.last_ns, int(batch.log[-1]))

    def _close_chunk(self) -> None:
        from mcap.records import ChunkIndex

        if not self._index:
            return
        data = b"".join(self._chunk)
        channel = np.concatenate([c for c, _, _ in self._index])
        log = np.concatenate([t for _, t, _ in self._index])
        at = np.concatenate([a for _, _, a in self._index])
        start = self._pos
        head = struct.pack("<BQQQQIIQ", OP_CHUNK, 8 + 8 + 8 + 4 + 4 + 8 + len(data),
                           int(log.min()), int(log.max()), len(data), zlib.crc32(data), 0,
                           len(data))
        self._write(head)
        self._write(data)
        index_start = self._pos
        ids, first = np.unique(channel, return_index=True)
        offsets = {}
        parts = []
        for cid in ids[np.argsort(first)].tolist():
            mine = channel == cid
            pairs = np.empty((int(mine.sum()), 2), dtype="<u8")
            pairs[:, 0] = log[mine]
            pairs[:, 1] = at[mine]
            offsets[cid] = index_start + sum(len(p) for p in parts)
            parts.append(struct.pack("<BQHI", OP_MESSAGE_INDEX, 2 + 4 + pairs.nbytes, cid,
                                     pairs.nbytes) + pairs.tobytes())
        indexes = b"".join(parts)
        self._write(indexes)
        self._chunk_indexes.append(ChunkIndex(
            message_start_time=int(log.min()), message_end_time=int(log.max()),
            chunk_start_offset=start, chunk_length=len(head) + len(data),
            message_index_offsets=offsets, message_index_length=len(indexes),
            compression="", compressed_size=len(data), uncompressed_size=len(data)))
        self._chunk, self._chunk_bytes, self._index = [], 0, []
        # a first chunk's schemas and channels are not repeated in the next one

    def finish(self) -> None:
        """The last chunk, the data end, the summary and the footer (as the mcap writer)."""
        from mcap.data_stream import RecordBuilder
        from mcap.records import DataEnd, Footer, Statistics, SummaryOffset

        self._close_chunk()
        builder = RecordBuilder()
        DataEnd(0).write(builder)
        self._write(builder.end())
        summary_start = self._pos
        summary = RecordBuilder()
        offsets = []

        def group(opcode: int, records: list[Any]) -> None:
            begin = summary.count
            for record in records:
                record.write(summary)
            offsets.append(SummaryOffset(group_opcode=opcode, group_start=summary_start + begin,
                                         group_length=summary.count - begin))

        group(OP_SCHEMA, list(self.schemas.values()))
        group(OP_CHANNEL, list(self.channels.values()))
        group(OP_STATISTICS, [Statistics(
            attachment_count=0, channel_count=len(self.channels),
            channel_message_counts=dict(self.counts), chunk_count=len(self._chunk_indexes),
            message_count=self.messages, message_end_time=self.last_ns,
            message_start_time=self.first_ns, metadata_count=0,
            schema_count=len(self.schemas))])
        group(OP_CHUNK_INDEX, self._chunk_indexes)
        group(OP_ATTACHMENT_INDEX, [])
        group(OP_METADATA_INDEX, [])
        offset_start = summary_start + summary.count
        for offset in offsets:
            offset.write(summary)
        data = summary.end()
        crc = zlib.crc32(struct.pack("<BQQQ", OP_FOOTER, 8 + 8 + 4, summary_start, offset_start),
                         zlib.crc32(data))
        self._write(data)
        Footer(summary_start=summary_start, summary_offset_start=offset_start,
               summary_crc=crc).write(builder)
        self._write(builder.end() + MCAP_MAGIC)


@dataclass(frozen=True)
class IndexCounts:
    """What :func:`pisc_bag.bag_repair.index_problems` checks, counted."""

    messages: int
    in_chunks: int
    indexed: int  # message index entries
    backwards: int  # messages whose log time is before the one before them
    chunks: int
    chunk_indexes: int
    statistics: int | None  # the statistics' message count, None without statistics


def index_counts(path: Path) -> IndexCounts | None:
    """:class:`IndexCounts` of a finished MCAP file, walked in blocks, or None when the
    walk cannot be sure of them (a record that does not parse, a message whose channel
    has no channel record, a CRC of the data section, anything after the footer): the
    mcap reader decides then."""
    scan = RecordScan(path)
    messages = in_chunks = backwards = 0
    last: int | None = None
    try:
        for batch in scan.batches():
            log = batch.log
            messages += len(log)
            in_chunks += len(log) if batch.in_chunk else 0
            backwards += int(np.count_nonzero(log[1:] < log[:-1]))
            backwards += last is not None and int(log[0]) < last
            last = int(log[-1])
    except NotMcap:
        return None
    if (scan.stopped != "" or scan.unknown or scan.unsure or not scan.footer
            or scan.whole_bytes != scan.size - len(MCAP_MAGIC)):
        return None
    with Path(path).open("rb") as stream:
        stream.seek(scan.size - len(MCAP_MAGIC))
        if stream.read() != MCAP_MAGIC:
            return None
    return IndexCounts(messages, in_chunks, scan.indexed, backwards, scan.chunk_records,
                       scan.chunk_indexes, scan.statistics)


class _OutOfWindow(Exception):
    """A message older than the window's flush point."""


def write_sorted(source: Path, out: IO[bytes], library: str, *,
                 hold: int | None = None, block_bytes: int | None = None,
                 scratch: Path | None = None) -> Written:
    """The schemas, channels and messages of ``source`` (see :class:`RecordScan`) written
    to ``out`` as an indexed MCAP file, the messages in log-time order (stable).

    ``hold``: messages held back in the window (default :data:`HOLD_MESSAGES`);
    ``scratch``: where the external merge keeps its runs (default: beside ``source``).
    ``out`` is written from its start. :class:`NotMcap` when ``source`` is not an MCAP
    file.
    """
    hold = HOLD_MESSAGES if hold is None else hold
    start = out.tell()
    if start:
        raise ValueError("write_sorted writes a file from its start")
    scan = RecordScan(source, block_bytes)
    writer = IndexedWriter(out, library)
    try:
        _window(scan, writer, hold)
        merged = False
    except _OutOfWindow:
        out.seek(start)
        out.truncate()
        scan = RecordScan(source, block_bytes)
        writer = IndexedWriter(out, library)
        _merge(scan, writer, scratch or source.parent)
        merged = True
    writer.finish()
    counts = {cid: writer.counts.get(cid, 0) for cid in writer.channels}
    return Written(scan.schemas, scan.channels, counts, writer.first_ns, writer.last_ns,
                   scan.whole_bytes, scan.size, merged)


def _window(scan: RecordScan, writer: IndexedWriter, hold: int) -> None:
    held: Batch | None = None
    flushed: int | None = None  # log time of the last message written
    for batch in scan.batches():
        if flushed is not None and len(batch) and int(batch.log.min()) < flushed:
            raise _OutOfWindow
        pool = batch if held is None else concat([held, batch])
        order = np.argsort(pool.log, kind="stable")
        cut = max(0, len(order) - hold)
        if cut:
            writer.define(scan.new_definitions)
            scan.new_definitions = []
            writer.add(pool.take(order[:cut]))
            flushed = int(pool.log[order[cut - 1]])
        held = pool.take(order[cut:])
    writer.define(scan.new_definitions)
    scan.new_definitions = []
    if held is not None:
        writer.add(held)


def _merge(scan: RecordScan, writer: IndexedWriter, beside: Path) -> None:
    """External merge: each block's messages sorted into a run file, the runs merged."""
    with tempfile.TemporaryDirectory(prefix=SCRATCH_PREFIX, dir=beside) as scratch:
        runs = []
        for k, batch in enumerate(scan.batches()):
            run = Path(scratch) / f"run{k:06d}"
            run.write_bytes(batch.take(np.argsort(batch.log, kind="stable")).data)
            runs.append(run)
        writer.define(scan.new_definitions)
        scan.new_definitions = []
        pending: list[bytes] = []
        # heapq.merge is stable: on equal log times the earlier run (recorded first) wins
        for _, record in heapq.merge(*(_run_records(r) for r in runs), key=lambda m: m[0]):
            pending.append(record)
            if len(pending) == 8192:
                writer.add(_records_batch(pending))
                pending = []
        writer.add(_records_batch(pending))


def _run_records(path: Path) -> Iterator[tuple[int, bytes]]:
    """(log time, message record) of a run file, read a buffer at a time."""
    with path.open("rb") as stream:
        buf = b""
        while True:
            more = stream.read(MERGE_READ_BYTES)
            buf += more
            pos = 0
            while pos + MESSAGE_HEAD <= len(buf):
                (length,) = struct.unpack_from("<Q", buf, pos + 1)
                nxt = pos + 9 + length
                if nxt > len(buf):
                    break
                yield struct.unpack_from("<Q", buf, pos + 15)[0], buf[pos:nxt]
                pos = nxt
            buf = buf[pos:]
            if not more:
                return


def _records_batch(records: list[bytes]) -> Batch:
    data = b"".join(records)
    sizes = np.fromiter((len(r) for r in records), dtype=np.int64, count=len(records))
    return message_batch(data, (np.cumsum(sizes) - sizes).tolist())
