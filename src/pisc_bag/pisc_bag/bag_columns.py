"""A PISC bag's numbers as columns, read in blocks: the fast path of summary and analysis.

``read_bag`` decodes every message into a rosbags object, one at a time in Python: about
20 us a message, and a 10-minute run holds 740,000 of them (`pisc_bag analyse` of such a
bag took 52 s and 1.66 GB when every object was kept). The summary and the
analysis need only a few numbers per message: the header stamp, the publish time and the
joint values of each ``sensor_msgs/JointState``, and the rare mode reports. This module
reads those as numpy columns:

* the MCAP file is walked a block at a time by :class:`pisc_bag.mcap_scan.RecordScan`, the
  walk the indexer reads with too: messages at the top level (a stream) or inside chunks
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
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pisc_bag.bag import TYPESTORE, BagError, bag_files
from pisc_bag.mcap_scan import MESSAGE_HEAD, Batch, RecordScan

__all__ = ["FastPathRefused", "JointColumns", "read_columns"]

JOINT_STATE = "sensor_msgs/msg/JointState"
WRENCH_STAMPED = "geometry_msgs/msg/WrenchStamped"
FIELDS = ("position", "velocity", "effort")


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
                 block_bytes: int | None = None) -> tuple[dict[str, JointColumns],
                                                          list[tuple[str, int, int, Any]]]:
    """The JointState (or WrenchStamped) topics ``joint_topics`` of ``bag`` as columns,
    and the messages of ``other_topics`` decoded, as (topic, log time, publish time,
    message) in file order; ``block_bytes``: the walk's block (default
    :data:`pisc_bag.mcap_scan.BLOCK_BYTES`).

    :class:`BagError` for a bag that cannot be read (as ``read_bag``);
    :class:`FastPathRefused` where the message path must decide.
    """
    parts = {t: _TopicParts() for t in joint_topics}
    others: list[tuple[str, int, int, Any]] = []
    layouts: dict[tuple[str, int], _Layout] = {}
    for path in bag_files(bag):
        scan = RecordScan(path, block_bytes)
        try:
            for batch in scan.batches():
                _columns_of_block(scan, batch, parts, others, set(other_topics), layouts)
        except (FastPathRefused, BagError):
            raise
        except Exception as exc:  # noqa: BLE001 - a damaged file: the message path names it
            raise FastPathRefused(f"{path}: {type(exc).__name__}: {exc}") from None
        _check_walk(scan)
    out = {}
    for topic, p in parts.items():
        def cat(arrays: list[np.ndarray]) -> np.ndarray:
            return np.concatenate(arrays) if arrays else np.zeros(0, dtype=np.int64)

        out[topic] = JointColumns(
            names=p.names or (),
            stamp_ns=cat(p.stamp), log_ns=cat(p.log), publish_ns=cat(p.publish),
            values={f: np.concatenate(v) for f, v in p.values.items()})
    return out, others


def _check_walk(scan: RecordScan) -> None:
    """FastPathRefused when the walk did not take every message of the file: a record
    that stopped it, a message of a channel without a channel record, a file that ends
    inside a record."""
    if scan.stopped:
        raise FastPathRefused(f"{scan.path}: {scan.stopped}")
    if scan.unknown:
        raise FastPathRefused(f"{scan.path}: {scan.unknown} messages on channels that have "
                              "no channel record")
    if scan.stopped is None and scan.whole_bytes != scan.size:
        raise FastPathRefused(f"{scan.path}: ends inside a record")


def _columns_of_block(scan: RecordScan, batch: Batch, parts: dict[str, _TopicParts],
                      others: list[tuple[str, int, int, Any]], other_topics: set[str],
                      layouts: dict[tuple[str, int], _Layout]) -> None:
    buf, channel = batch.data, batch.channel
    log = batch.log.astype(np.int64)
    publish = batch.publish
    starts = batch.starts + MESSAGE_HEAD  # each message's data
    sizes = batch.sizes - MESSAGE_HEAD
    for cid in np.unique(channel):
        topic, sid = scan.channels[int(cid)].topic, scan.channels[int(cid)].schema_id
        mine = channel == cid
        schema = scan.schemas.get(sid)
        type_name = schema.name if schema is not None else None
        if topic in other_topics:
            for s, n, lt, pt in zip(starts[mine], sizes[mine], log[mine], publish[mine],
                                    strict=True):
                msg = TYPESTORE.deserialize_cdr(bytes(buf[s:s + n]), type_name or "")
                others.append((topic, int(lt), int(pt), msg))
            continue
        if topic not in parts:
            continue
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
