"""A PISC bag's numbers as columns, read in blocks: the fast path of summary and analysis.

``read_bag`` decodes every message into a rosbags object, one at a time in Python: about
20 us a message, and a 10-minute run holds 740,000 of them (issue 16: `pisc_bag analyse`
of such a bag took 52 s and 1.66 GB when every object was kept). The summary and the
analysis need only a few numbers per message: the header stamp, the publish time and the
joint values of each ``sensor_msgs/JointState``, and the rare mode reports. This module
reads those as numpy columns:

* the MCAP file is read in blocks of :data:`BLOCK_BYTES` (a record that does not fit is
  read whole), and its records are walked by their opcode and length (MCAP
  specification, "Records"): messages at the top level (a stream) or inside chunks
  (an indexed file; compressed chunks are opened with the mcap library's decompressors);
* the messages of a topic with the same length have the same layout when the publisher
  sends the same joint names (every PISC node does): the first one is decoded with
  rosbags to find where its stamp and values lie (CDR, XCDR1 little endian), and every
  message of that length whose other bytes equal the first one's is read at those
  offsets, the whole block at once with numpy. Any other message is decoded on its own.
  ``geometry_msgs/WrenchStamped`` (``/pisc/cart_force``, for replay) is read the same way:
  its ``force`` and ``torque`` as values of the "joints" x, y, z.

What comes out is what ``read_bag`` would give, per topic in file order: the header
stamps, the publish times and, for each of ``position``, ``velocity`` and ``effort``, the
values by joint. :func:`read_columns` refuses (:class:`FastPathRefused`) anything it would
have to guess at (a topic whose joint names change, a value that is not finite, a type
other than JointState on the numeric topics); the callers then take the message path,
whose errors name the message.

Memory: the columns only (about 140 bytes per control cycle for the topics the summary
reads) and one block; the file itself is never held.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pisc_bag.bag import TYPESTORE, BagError, bag_files

__all__ = ["BLOCK_BYTES", "FastPathRefused", "JointColumns", "read_columns"]

BLOCK_BYTES = 8 * 1024 * 1024
JOINT_STATE = "sensor_msgs/msg/JointState"
WRENCH_STAMPED = "geometry_msgs/msg/WrenchStamped"
FIELDS = ("position", "velocity", "effort")

# MCAP record opcodes (MCAP specification, "Records")
_SCHEMA, _CHANNEL, _MESSAGE, _CHUNK, _DATA_END = 0x03, 0x04, 0x05, 0x06, 0x0F
_RECORD = struct.Struct("<BQ")  # opcode, length
_MESSAGE_HEAD = 2 + 4 + 8 + 8  # channel id, sequence, log time, publish time
_CHUNK_HEAD = struct.Struct("<QQQI")  # start, end, uncompressed size, uncompressed crc


class FastPathRefused(Exception):
    """The columns cannot be read without guessing; read the bag message by message."""


@dataclass
class JointColumns:
    """The ``sensor_msgs/JointState`` messages of one topic, in file order (or its
    ``geometry_msgs/WrenchStamped``: ``force`` and ``torque`` of the joints x, y, z)."""

    names: tuple[str, ...]
    stamp_ns: np.ndarray  # int64, header stamps
    log_ns: np.ndarray  # int64
    publish_ns: np.ndarray  # int64
    values: dict[str, np.ndarray] = field(default_factory=dict)  # field -> (n, joints)

    def __len__(self) -> int:
        return len(self.stamp_ns)


@dataclass(frozen=True)
class _Layout:
    """Where a JointState of one length keeps its stamp and values."""

    names: tuple[str, ...]
    offsets: dict[str, int]  # field -> byte offset of its first double (fields present)
    fixed: np.ndarray  # bool mask of the bytes every such message shares
    reference: np.ndarray  # uint8: the shared bytes, from the first such message


def _align(pos: int, n: int) -> int:
    """CDR alignment, counted from the end of the 4-byte encapsulation header."""
    return 4 + -(-(pos - 4) // n) * n


def _joint_layout(data: bytes) -> _Layout:
    """The layout of one little-endian CDR JointState (header, name[], position[],
    velocity[], effort[]); FastPathRefused when it is not one."""
    if len(data) < 12 or data[:2] != b"\x00\x01":
        raise FastPathRefused("not little-endian plain CDR")
    fixed = np.ones(len(data), dtype=bool)
    fixed[4:12] = False  # stamp sec, nanosec
    pos = 12
    (n,) = struct.unpack_from("<I", data, pos)
    pos += 4 + n  # frame_id, with its terminating NUL
    pos = _align(pos, 4)
    (count,) = struct.unpack_from("<I", data, pos)
    pos += 4
    names = []
    for _ in range(count):
        pos = _align(pos, 4)
        (n,) = struct.unpack_from("<I", data, pos)
        names.append(data[pos + 4:pos + 3 + n].decode())
        pos += 4 + n
    offsets = {}
    for name in FIELDS:
        pos = _align(pos, 4)
        (count,) = struct.unpack_from("<I", data, pos)
        pos += 4
        if count:
            pos = _align(pos, 8)
            if count != len(names):
                raise FastPathRefused(f"{name}: {count} values for {len(names)} joints")
            offsets[name] = pos
            fixed[pos:pos + 8 * count] = False
            pos += 8 * count
    if pos != len(data):
        raise FastPathRefused("trailing bytes")
    # checked against rosbags' own decoding of the same bytes
    msg = TYPESTORE.deserialize_cdr(data, JOINT_STATE)
    if list(msg.name) != names or any(
            (len(getattr(msg, f)) != 0) != (f in offsets) for f in FIELDS):
        raise FastPathRefused("layout differs from rosbags' decoding")
    return _Layout(tuple(names), offsets, fixed,
                   np.frombuffer(data, dtype=np.uint8)[fixed].copy())


def _wrench_layout(data: bytes) -> _Layout:
    """The layout of one little-endian CDR WrenchStamped (header, force, torque: three
    doubles each); FastPathRefused when it is not one."""
    if len(data) < 12 or data[:2] != b"\x00\x01":
        raise FastPathRefused("not little-endian plain CDR")
    fixed = np.ones(len(data), dtype=bool)
    fixed[4:12] = False  # stamp sec, nanosec
    (n,) = struct.unpack_from("<I", data, 12)
    pos = _align(12 + 4 + n, 8)  # after frame_id, at the first double
    if pos + 48 != len(data):
        raise FastPathRefused("not a WrenchStamped's length")
    fixed[pos:pos + 48] = False
    values = np.frombuffer(data, dtype="<f8", count=6, offset=pos)
    # checked against rosbags' own decoding of the same bytes
    msg = TYPESTORE.deserialize_cdr(data, WRENCH_STAMPED)
    w = msg.wrench
    if values.tobytes() != np.array([w.force.x, w.force.y, w.force.z, w.torque.x, w.torque.y,
                                     w.torque.z], dtype="<f8").tobytes():
        raise FastPathRefused("layout differs from rosbags' decoding")
    return _Layout(("x", "y", "z"), {"force": pos, "torque": pos + 24}, fixed,
                   np.frombuffer(data, dtype=np.uint8)[fixed].copy())


#: the types read as columns, and how their layout is found
_LAYOUTS = {JOINT_STATE: _joint_layout, WRENCH_STAMPED: _wrench_layout}


class _Scan:
    """Walks an MCAP file's records block by block (see the module)."""

    def __init__(self, path: Path, block_bytes: int) -> None:
        self.path = path
        self.block_bytes = block_bytes
        self.schemas: dict[int, str] = {}  # id -> type name
        self.channels: dict[int, tuple[str, int]] = {}  # id -> (topic, schema id)

    def segments(self) -> Iterator[tuple[bytes, np.ndarray]]:
        """(buffer, int64 offsets of message bodies in it) in file order; a buffer is a
        block of the file or the contents of a compressed chunk."""
        with self.path.open("rb") as stream:
            buf = stream.read(self.block_bytes)
            if not buf.startswith(b"\x89MCAP0\r\n"):
                raise FastPathRefused(f"{self.path}: not an MCAP file")
            pos = 8
            while True:
                found: list[tuple[bytes, list[int]]] = []
                used, done, need = self._walk(buf, pos, len(buf), found)
                for data, offsets in found:
                    if offsets:
                        yield data, np.asarray(offsets, dtype=np.int64)
                if done:
                    return
                rest = buf[used:]
                more = stream.read(max(self.block_bytes, need - len(rest)))
                if not more:
                    if rest:
                        raise FastPathRefused(f"{self.path}: ends inside a record")
                    return
                buf, pos = rest + more, 0

    def _walk(self, buf: bytes, start: int, end: int,
              found: list[tuple[bytes, list[int]]], top: bool = True) -> tuple[int, bool, int]:
        """Append (buffer, message body offsets) to ``found`` for the records in
        ``buf[start:end]``; returns (end of the last whole record, the data section is
        over, bytes the next record needs)."""
        offsets: list[int] = []
        found.append((buf, offsets))
        unpack = _RECORD.unpack_from
        pos = start
        while pos + 9 <= end:
            op, length = unpack(buf, pos)
            body = pos + 9
            nxt = body + length
            if nxt > end:
                if not top:
                    raise FastPathRefused("a chunk's record runs past the chunk")
                return pos, False, nxt - pos
            if op == _MESSAGE:
                offsets.append(body)
            elif op == _CHUNK:
                data, inner = self._chunk(buf, body)
                if data is buf:
                    offsets.extend(inner)
                else:
                    found.append((data, inner))
                    offsets = []
                    found.append((buf, offsets))
            elif op == _SCHEMA:
                sid, n = struct.unpack_from("<HI", buf, body)
                self.schemas[sid] = bytes(buf[body + 6:body + 6 + n]).decode()
            elif op == _CHANNEL:
                cid, sid, n = struct.unpack_from("<HHI", buf, body)
                self.channels[cid] = (bytes(buf[body + 8:body + 8 + n]).decode(), sid)
            elif op == _DATA_END and top:
                return nxt, True, 0
            pos = nxt
        if pos != end and not top:
            raise FastPathRefused("a chunk ends inside a record")
        return pos, False, 9

    def _chunk(self, buf: bytes, body: int) -> tuple[bytes, list[int]]:
        """(buffer, message body offsets) of a chunk: ``buf`` itself when uncompressed."""
        pos = body + _CHUNK_HEAD.size
        (n,) = struct.unpack_from("<I", buf, pos)
        compression = bytes(buf[pos + 4:pos + 4 + n]).decode()
        pos += 4 + n
        (length,) = struct.unpack_from("<Q", buf, pos)
        pos += 8
        found: list[tuple[bytes, list[int]]] = []
        if compression == "":
            self._walk(buf, pos, pos + length, found, top=False)
            return buf, [o for _, offsets in found for o in offsets]
        from mcap.records import Chunk
        from mcap.stream_reader import get_chunk_data_stream

        start, end, size, crc = _CHUNK_HEAD.unpack_from(buf, body)
        try:
            stream, size = get_chunk_data_stream(
                Chunk(compression=compression, data=bytes(buf[pos:pos + length]),
                      message_end_time=end, message_start_time=start,
                      uncompressed_crc=crc, uncompressed_size=size), validate_crc=True)
            data = stream.read(size)
        except Exception as exc:  # noqa: BLE001 - whatever the decompressor raises
            raise FastPathRefused(f"chunk compression {compression!r}: {exc}") from None
        self._walk(data, 0, len(data), found, top=False)
        return data, [o for _, offsets in found for o in offsets]


def _gather(buf: bytes, starts: np.ndarray, length: int) -> np.ndarray:
    """(n, length) uint8: ``length`` bytes of ``buf`` from each of ``starts``: rows of a
    sliding-window view of the buffer, so numpy copies whole rows."""
    whole = np.frombuffer(buf, dtype=np.uint8)
    return np.lib.stride_tricks.sliding_window_view(whole, length)[starts]


@dataclass
class _TopicParts:
    stamp: list[np.ndarray] = field(default_factory=list)
    log: list[np.ndarray] = field(default_factory=list)
    publish: list[np.ndarray] = field(default_factory=list)
    values: dict[str, list[np.ndarray]] = field(default_factory=dict)
    names: tuple[str, ...] | None = None


def read_columns(bag: str | Path, joint_topics: Sequence[str],
                 other_topics: Sequence[str] = (),
                 block_bytes: int = BLOCK_BYTES) -> tuple[dict[str, JointColumns],
                                                          list[tuple[str, int, int, Any]]]:
    """The JointState (or WrenchStamped) topics ``joint_topics`` of ``bag`` as columns,
    and the messages of ``other_topics`` decoded, as (topic, log time, publish time,
    message) in file order.

    :class:`BagError` for a bag that cannot be read (as ``read_bag``);
    :class:`FastPathRefused` where the message path must decide.
    """
    parts = {t: _TopicParts() for t in joint_topics}
    others: list[tuple[str, int, int, Any]] = []
    layouts: dict[tuple[str, int], _Layout] = {}
    for path in bag_files(bag):
        scan = _Scan(path, block_bytes)
        try:
            for buf, bodies in scan.segments():
                _columns_of_block(scan, buf, bodies, parts, others, set(other_topics),
                                  layouts)
        except (FastPathRefused, BagError):
            raise
        except Exception as exc:  # noqa: BLE001 - a damaged file: the message path names it
            raise FastPathRefused(f"{path}: {type(exc).__name__}: {exc}") from None
    out = {}
    for topic, p in parts.items():
        def cat(arrays: list[np.ndarray]) -> np.ndarray:
            return np.concatenate(arrays) if arrays else np.zeros(0, dtype=np.int64)

        out[topic] = JointColumns(
            names=p.names or (),
            stamp_ns=cat(p.stamp), log_ns=cat(p.log), publish_ns=cat(p.publish),
            values={f: np.concatenate(v) for f, v in p.values.items()})
    return out, others


def _columns_of_block(scan: _Scan, buf: bytes, bodies: np.ndarray,
                      parts: dict[str, _TopicParts], others: list[tuple[str, int, int, Any]],
                      other_topics: set[str], layouts: dict[tuple[str, int], _Layout]) -> None:
    heads = _gather(buf, bodies, _MESSAGE_HEAD)
    channel = heads[:, 0:2].copy().view("<u2")[:, 0]
    log = heads[:, 6:14].copy().view("<u8")[:, 0].astype(np.int64)
    publish = heads[:, 14:22].copy().view("<u8")[:, 0].astype(np.int64)
    # each body's end: the record length sits 8 bytes before the body
    lengths = _gather(buf, bodies - 8, 8).view("<u8")[:, 0].astype(np.int64)
    starts = bodies + _MESSAGE_HEAD
    sizes = lengths - _MESSAGE_HEAD
    for cid in np.unique(channel):
        if int(cid) not in scan.channels:
            raise FastPathRefused(f"message on channel {cid}, which has no channel record")
        topic, sid = scan.channels[int(cid)]
        mine = channel == cid
        if topic in other_topics:
            type_name = scan.schemas.get(sid, "")
            for s, n, lt, pt in zip(starts[mine], sizes[mine], log[mine], publish[mine],
                                    strict=True):
                msg = TYPESTORE.deserialize_cdr(bytes(buf[s:s + n]), type_name)
                others.append((topic, int(lt), int(pt), msg))
            continue
        if topic not in parts:
            continue
        type_name = scan.schemas.get(sid)
        if type_name not in _LAYOUTS:
            raise FastPathRefused(f"{topic}: not {' or '.join(_LAYOUTS)}")
        _joint_block(topic, type_name, buf, starts[mine], sizes[mine], log[mine], publish[mine],
                     parts[topic], layouts)


def _joint_block(topic: str, type_name: str, buf: bytes, starts: np.ndarray, sizes: np.ndarray,
                 log: np.ndarray, publish: np.ndarray, part: _TopicParts,
                 layouts: dict[tuple[str, int], _Layout]) -> None:
    """Append one block's messages of a topic, kept in file order (one length at a time
    would reorder them: a topic whose messages differ in length is refused)."""
    size = int(sizes[0])
    if np.any(sizes != size):
        raise FastPathRefused(f"{topic}: messages of several lengths")
    layout = layouts.get((topic, size))
    if layout is None:
        layout = layouts[(topic, size)] = _LAYOUTS[type_name](
            bytes(buf[starts[0]:starts[0] + size]))
    if part.names is None:
        part.names = layout.names
    elif part.names != layout.names:
        raise FastPathRefused(f"{topic}: joint names change")
    rows = _gather(buf, starts, size)
    if not np.all(rows[:, layout.fixed] == layout.reference):
        raise FastPathRefused(f"{topic}: messages of one length differ in layout")
    stamps = rows[:, 4:12].copy()
    sec = stamps[:, 0:4].copy().view("<i4")[:, 0].astype(np.int64)
    nsec = stamps[:, 4:8].copy().view("<u4")[:, 0].astype(np.int64)
    part.stamp.append(sec * 1_000_000_000 + nsec)
    part.log.append(log)
    part.publish.append(publish)
    joints = len(layout.names)
    for name, offset in layout.offsets.items():
        values = rows[:, offset:offset + 8 * joints].copy().view("<f8")
        if not np.all(np.isfinite(values)):
            raise FastPathRefused(f"{topic}: a value that is not finite")
        part.values.setdefault(name, []).append(values)
    missing = set(part.values) ^ set(layout.offsets)
    if missing:
        raise FastPathRefused(f"{topic}: fields {sorted(missing)} come and go")
