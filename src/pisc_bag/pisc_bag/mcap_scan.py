"""One walk of an MCAP file's records, a block at a time: how the indexer
(:mod:`pisc_bag.bag_index`, finishing and repairing a bag) and the column reader
(:mod:`pisc_bag.bag_columns`, the summary's and analysis's fast path) read a bag.

The file is read in blocks of :data:`BLOCK_BYTES` and walked record by record by opcode
and length (MCAP specification, "Records"); a record that does not fit in a block is
read whole. Messages are taken at the top level (a stream, as the recorder writes it) and
inside chunks (an indexed file: an uncompressed chunk's messages are read where they lie
in the block, a compressed chunk is opened by the ``mcap`` library; every chunk's CRC is
checked). The walk stops taking records at the first one that
is incomplete or corrupt (a message shorter than its fixed fields, a schema, channel or
chunk that does not parse, a chunk whose CRC is wrong) and at the data end or footer
(:attr:`RecordScan.stopped` says which); it goes on reading only the framing, to give the
offset after the last whole record (what repair reports as dropped) and to count the
summary's records. A message whose channel has no channel record before it (MCAP
requires one) cannot be read and is dropped (:attr:`RecordScan.unknown` counts them).

The messages come in :class:`Batch`es: a buffer (a block of the file, or a compressed
chunk's records) and, as numpy columns, where each message record starts in it, its
size, log time, channel and publish time, so that their callers handle a block's
messages at once (the messages of a block's uncompressed chunks in one batch: the column
reader's cost is per batch as much as per message).

Memory: one block and one chunk, whatever the length of the file.
"""

from __future__ import annotations

import io
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["BLOCK_BYTES", "MCAP_MAGIC", "MESSAGE_HEAD", "Batch", "NotMcap", "RecordScan",
           "concat", "message_batch"]  # and the opcodes, OP_*

MCAP_MAGIC = b"\x89MCAP0\r\n"
BLOCK_BYTES = 4 * 1024 * 1024  # the file is read this much at a time

# MCAP record opcodes (MCAP specification, "Records")
OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL = 0x01, 0x02, 0x03, 0x04
OP_MESSAGE, OP_CHUNK, OP_MESSAGE_INDEX, OP_CHUNK_INDEX = 0x05, 0x06, 0x07, 0x08
OP_ATTACHMENT_INDEX = 0x0A
OP_STATISTICS, OP_METADATA_INDEX, OP_SUMMARY_OFFSET, OP_DATA_END = 0x0B, 0x0D, 0x0E, 0x0F
# the records the walk counts (RecordScan's tallies) besides taking messages
_TALLIED = frozenset((OP_SCHEMA, OP_CHANNEL, OP_CHUNK, OP_MESSAGE_INDEX, OP_CHUNK_INDEX,
                      OP_STATISTICS, OP_DATA_END, OP_FOOTER))
RECORD = struct.Struct("<BQ")  # opcode, length
MESSAGE_FIXED = 2 + 4 + 8 + 8  # channel id, sequence, log time, publish time
MESSAGE_HEAD = 9 + MESSAGE_FIXED  # a message record up to its data
_CHUNK_HEAD = struct.Struct("<QQQII")  # start, end, uncompressed size and CRC, compression length


class NotMcap(ValueError):
    """The file does not start with the MCAP magic."""


@dataclass
class Batch:
    """Message records in ``data``, with the fields the ordering and indexes need (and
    the publish times, which the column reader reads; None in a batch :meth:`take`
    made)."""

    data: bytes | memoryview  # a block of the file, a chunk's records, or a copy
    starts: np.ndarray  # int64: where each record starts (its opcode) in data
    sizes: np.ndarray  # int64: each record's size, opcode and length included
    log: np.ndarray  # uint64 log times
    channel: np.ndarray  # uint16 channel ids
    in_chunk: bool = False  # the messages of a chunk record
    publish: np.ndarray | None = None  # int64 publish times

    def __len__(self) -> int:
        return len(self.starts)

    def take(self, index: np.ndarray) -> Batch:
        """The messages at ``index``, in that order, copied into a compact buffer (a
        slice for each run of records that lie one after the other)."""
        starts, sizes = self.starts[index], self.sizes[index]
        ends = starts + sizes
        cut = np.flatnonzero(starts[1:] != ends[:-1]) + 1
        first = np.concatenate(([0], cut)).astype(np.int64)
        last = np.concatenate((cut, [len(starts)])).astype(np.int64) - 1
        view = memoryview(self.data)
        data = b"".join([view[a:b] for a, b in zip(starts[first].tolist(),
                                                   ends[last].tolist(), strict=True)]) \
            if len(starts) else b""
        return Batch(data, np.cumsum(sizes) - sizes, sizes, self.log[index],
                     self.channel[index])


def message_batch(data: bytes, starts: list[int]) -> Batch:
    """The messages whose records start at ``starts`` in ``data``."""
    at = np.asarray(starts, dtype=np.int64)
    if not len(at):
        return Batch(data, at, at, np.zeros(0, np.uint64), np.zeros(0, np.uint16),
                     publish=at)
    whole = np.frombuffer(data, dtype=np.uint8)
    heads = np.lib.stride_tricks.sliding_window_view(whole, MESSAGE_HEAD)[at]  # a copy

    def field(offset: int, dtype: str) -> np.ndarray:  # one field of every head, a view
        return np.ndarray((len(at),), dtype, heads, offset, (MESSAGE_HEAD,))

    return Batch(data, at, field(1, "<u8").astype(np.int64) + 9,
                 field(15, "<u8").astype(np.uint64), field(9, "<u2").astype(np.uint16),
                 publish=field(23, "<u8").astype(np.int64))


def concat(parts: list[Batch]) -> Batch:
    """One batch of several, their buffers joined."""
    if len(parts) == 1:
        return parts[0]
    shift = np.cumsum([0] + [len(p.data) for p in parts[:-1]])
    return _joined(b"".join(p.data for p in parts),
                   [replace(p, starts=p.starts + s) for p, s in zip(parts, shift, strict=True)])


def _joined(data: bytes | memoryview, parts: list[Batch], in_chunk: bool = False) -> Batch:
    """The messages of ``parts``, whose starts are in ``data``, as one batch."""
    publish = (None if any(p.publish is None for p in parts)
               else np.concatenate([p.publish for p in parts]))
    return Batch(data, np.concatenate([p.starts for p in parts]),
                 np.concatenate([p.sizes for p in parts]),
                 np.concatenate([p.log for p in parts]),
                 np.concatenate([p.channel for p in parts]), in_chunk, publish)


class RecordScan:
    """The records of an MCAP file, walked in blocks (see the module).

    :meth:`batches` yields the messages in file order; the schemas and channels found on
    the way are in :attr:`schemas` and :attr:`channels` (the ``mcap`` library's records,
    by id, in file order) and, until a writer takes them, in :attr:`new_definitions`.
    """

    def __init__(self, path: Path, block_bytes: int | None = None) -> None:
        self.path = Path(path)
        self.block_bytes = block_bytes or BLOCK_BYTES
        self.schemas: dict[int, Any] = {}
        self.channels: dict[int, Any] = {}
        self.new_definitions: list[Any] = []
        self.size = 0
        self.whole_bytes = 0  # offset after the last whole record
        # why records stopped being taken before the end: "" at the data end or footer,
        # else the record that stopped them; None while they are taken
        self.stopped: str | None = None
        # tallies for index_counts: messages dropped for want of a channel, chunk
        # records, message index entries, chunk indexes, the last statistics' message
        # count, a footer seen, and what makes the tallies unsure
        self.unknown = self.chunk_records = self.indexed = self.chunk_indexes = 0
        self.statistics: int | None = None
        self.footer = False
        self.unsure: str | None = None

    def batches(self) -> Iterator[Batch]:
        with self.path.open("rb") as stream:
            stream.seek(0, io.SEEK_END)
            self.size = stream.tell()
            stream.seek(0)
            if stream.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
                raise NotMcap("not an MCAP file (it does not start with the MCAP magic)")
            buf_at = self.whole_bytes = len(MCAP_MAGIC)  # file offset of buf[0]
            buf = b""
            need = 0
            while buf_at + len(buf) < self.size:
                buf += stream.read(max(self.block_bytes, need))
                pos, need, found = self._walk(buf, buf_at)
                for batch in found:
                    if len(batch):
                        yield batch
                self.whole_bytes = buf_at + pos
                if need < 0:  # a record runs past the end of the file
                    return
                buf, buf_at = buf[pos:], buf_at + pos

    def _walk(self, buf: bytes, buf_at: int) -> tuple[int, int, list[Batch]]:
        """The whole records of ``buf``: (end of the last, bytes the next one needs, or -1
        when it runs past the end of the file; the batches of messages found)."""
        found: list[Batch] = []
        starts: list[int] = []
        unpack = RECORD.unpack_from
        pos, end = 0, len(buf)
        live = self.stopped is None
        while pos + 9 <= end:
            op, length = unpack(buf, pos)
            nxt = pos + 9 + length
            if nxt > end:
                return pos, (nxt - pos if buf_at + nxt <= self.size else -1), \
                    self._close_batch(buf, starts, found)
            if op in _TALLIED:
                self._tally(op, buf, pos + 9, nxt, live)
            if live:
                if op == OP_MESSAGE:
                    if length >= MESSAGE_FIXED:
                        starts.append(pos)
                    else:
                        live = self._stop("a message record shorter than its fields")
                elif op == OP_SCHEMA or op == OP_CHANNEL:
                    # the messages before it are checked against the channels before it
                    self._close_batch(buf, starts, found)
                    starts = []
                    live = self._definition(op, buf[pos + 9:nxt])
                elif op == OP_CHUNK:
                    self._close_batch(buf, starts, found)
                    starts = []
                    inner = self._chunk(buf, pos + 9, nxt)
                    if inner is not None:
                        _add(found, inner, True)
                    live = self.stopped is None
                elif op == OP_DATA_END or op == OP_FOOTER:
                    live = self._stop("")
            pos = nxt
        return pos, 9, self._close_batch(buf, starts, found)

    def _tally(self, op: int, buf: bytes, body: int, end: int, live: bool) -> None:
        from mcap.data_stream import ReadDataStream
        from mcap.records import Channel, Schema, Statistics

        try:
            if op == OP_CHUNK:
                self.chunk_records += 1
            elif op == OP_MESSAGE_INDEX:
                self.indexed += struct.unpack_from("<I", buf, body + 2)[0] // 16
            elif op == OP_CHUNK_INDEX:
                self.chunk_indexes += 1
            elif op == OP_STATISTICS:
                stream = ReadDataStream(io.BytesIO(buf[body:end]))
                self.statistics = Statistics.read(stream).message_count
            elif op == OP_DATA_END:
                if struct.unpack_from("<I", buf, body)[0]:
                    self.unsure = "a data section CRC"  # the reader checks it
            elif op == OP_FOOTER:
                self.footer = True
            elif not live:  # a schema or channel of the summary
                (Schema if op == OP_SCHEMA else Channel).read(
                    ReadDataStream(io.BytesIO(buf[body:end])))
        except Exception as exc:  # noqa: BLE001 - a record that does not parse
            self.unsure = f"{type(exc).__name__}: {exc}"

    def _stop(self, why: str) -> bool:
        if self.stopped is None:
            self.stopped = why
        return False

    def _close_batch(self, buf: bytes, starts: list[int], found: list[Batch],
                     in_chunk: bool = False) -> list[Batch]:
        if starts:
            _add(found, self._known(message_batch(buf, starts)), in_chunk)
        return found

    def _known(self, batch: Batch) -> Batch:
        """Without the messages of channels that have no channel record (yet)."""
        known = np.isin(batch.channel, np.fromiter(self.channels, dtype=np.uint16,
                                                   count=len(self.channels)))
        if known.all():
            return batch
        self.unknown += int(np.count_nonzero(~known))
        return Batch(batch.data, batch.starts[known], batch.sizes[known], batch.log[known],
                     batch.channel[known], publish=batch.publish[known])

    def _definition(self, op: int, body: bytes) -> bool:
        from mcap.data_stream import ReadDataStream
        from mcap.records import Channel, Schema

        try:
            stream = ReadDataStream(io.BytesIO(body))
            record = (Schema if op == OP_SCHEMA else Channel).read(stream)
            if stream.count > len(body):
                raise ValueError("runs past its record")
        except Exception:  # noqa: BLE001 - a record that does not parse ends the data
            return self._stop(f"a {'schema' if op == OP_SCHEMA else 'channel'} record that "
                              "does not parse")
        (self.schemas if op == OP_SCHEMA else self.channels)[record.id] = record
        self.new_definitions.append(record)
        return True

    def _chunk(self, buf: bytes, body: int, end: int) -> Batch | None:
        """The messages of the chunk record ``buf[body:end]`` (its schemas and channels
        taken), or None when it holds none, does not parse or its CRC is wrong (none of
        its records are taken then: :attr:`stopped` says so). An uncompressed chunk's
        messages are read where they lie in ``buf`` (the batch's data is ``buf``); a
        compressed one is opened by the mcap library."""
        try:
            start, stop, size, crc, n = _CHUNK_HEAD.unpack_from(buf, body)
            at = body + _CHUNK_HEAD.size + n
            (length,) = struct.unpack_from("<Q", buf, at)
            compression = bytes(buf[at - n:at]).decode()
            at += 8
            if at + length > end:
                raise ValueError("the chunk's records run past it")
            if compression:
                data = _decompressed(compression, buf[at:at + length], start, stop, size, crc)
                first, last = 0, len(data)
            else:  # read where they lie
                data, first, last = buf, at, at + length
                # the check the mcap library makes of a chunk's uncompressed records
                if crc and zlib.crc32(memoryview(buf)[first:last]) != crc:
                    raise ValueError("the chunk's CRC is wrong")
            starts, definitions = _chunk_records(data, first, last)
        except Exception:  # noqa: BLE001 - whatever the chunk's decoding raises
            self._stop("a chunk that does not parse")
            return None
        batches: list[Batch] = []
        taken = 0  # messages before the definition at hand
        for k, op, pos, nxt in definitions:
            self._close_batch(data, starts[taken:k], batches, True)
            taken = k
            if not self._definition(op, bytes(data[pos + 9:nxt])):
                taken = len(starts)  # nothing after a definition that does not parse
                break
        self._close_batch(data, starts[taken:], batches, True)
        if not batches:
            return None
        return batches[0] if len(batches) == 1 else concat(batches)


def _add(found: list[Batch], batch: Batch, in_chunk: bool) -> None:
    """``batch`` after ``found``'s: joined to the last one when they share a buffer (the
    messages of a block's uncompressed chunks, one after the other), so that a block's
    messages come in one batch, whatever its chunks."""
    batch.in_chunk = in_chunk
    last = found[-1] if found else None
    if last is None or last.data is not batch.data or last.in_chunk != in_chunk:
        found.append(batch)
        return
    found[-1] = _joined(last.data, [last, batch], in_chunk)


def _decompressed(compression: str, data: bytes, start: int, stop: int, size: int,
                  crc: int) -> bytes:
    """A compressed chunk's records, decompressed and their CRC checked by the mcap
    library."""
    from mcap.records import Chunk
    from mcap.stream_reader import get_chunk_data_stream

    stream, size = get_chunk_data_stream(Chunk(
        compression=compression, data=data, message_end_time=stop, message_start_time=start,
        uncompressed_crc=crc, uncompressed_size=size), validate_crc=True)
    return stream.read(size)


def _chunk_records(data: bytes, pos: int,
                   end: int) -> tuple[list[int], list[tuple[int, int, int, int]]]:
    """Where the message records of a chunk's records ``data[pos:end]`` start, and its
    schemas and channels as (messages before it, opcode, start, end); ValueError when a
    record runs past the chunk or a message is shorter than its fixed fields."""
    starts: list[int] = []
    definitions: list[tuple[int, int, int, int]] = []
    unpack, append = RECORD.unpack_from, starts.append
    message, schema, channel = OP_MESSAGE, OP_SCHEMA, OP_CHANNEL
    while pos < end:  # (a record cut by the chunk's end fails to unpack, or ends past it)
        op, length = unpack(data, pos)
        if op == message:
            append(pos)
        elif op == schema or op == channel:
            definitions.append((len(starts), op, pos, pos + 9 + length))
        pos += 9 + length
    if pos != end:
        raise ValueError("a record runs past its chunk")
    if starts:  # every message record holds its fixed fields (all at once)
        at = np.asarray(starts, dtype=np.int64) + 1
        lengths = np.lib.stride_tricks.sliding_window_view(
            np.frombuffer(data, dtype=np.uint8), 8)[at].copy().view("<u8")
        if int(lengths.min()) < MESSAGE_FIXED or int(at[-1]) + 8 + MESSAGE_FIXED > end:
            raise ValueError("a message record shorter than its fields")
    return starts, definitions
