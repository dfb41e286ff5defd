"""The control cycle's messages as CDR bytes, written and read without rclpy message objects.

rclpy publishes a message object by converting it to C and serialising it, and hands a
subscription's callback a new object built from the C message: a ``JointState`` is five
Python objects and three sequences each way. In the lockstep graph that was most of a
cycle: a probe publishing one JointState to a subscription in its process and
to a KEEP_ALL reader in another cost 104 us of CPU per message with objects and 37 us with
bytes written here and read raw (``/tmp`` probe, 2026-12-02, load 7-9; docs/figures.md).

So the nodes publish the bytes this module writes (``Publisher.publish`` takes ``bytes``)
and :meth:`pisc_msgs_py.base_node.PiscNode.subscription` reads the types it knows from
raw bytes into light views with the message's attribute paths (``msg.header.stamp.sec``,
``msg.name``, ``msg.position``, ``msg.wrench.force.x``...), which the converters of
:mod:`pisc_msgs_py.convert` read as they read a message object. The topics and their
standard types are unchanged: what goes on the wire is the CDR a ROS 2 node sends.

**The encoding** is plain CDR (OMG CDR as XCDR1, what rmw_fastrtps sends and rosbag2
records): a 4-byte encapsulation header (``00 01`` little-endian, options ``00 00``),
then the fields in order, each primitive aligned to its size counted from the end of the
header, padding zero; a string is its uint32 length with the terminating NUL, the bytes
and the NUL; a sequence is its uint32 count and its elements. Writing gives the bytes
Fast DDS puts on the wire for the same message (exact length, zero padding; a test
compares with the reference bags byte for byte). Reading takes little- and big-endian
CDR (``00 00``); anything else, or bytes that end inside a field, is a
:class:`MessageError`.

**Shapes met before.** The graph's messages of one kind differ only in their stamp and
their doubles: same frame, joint names, sequence lengths and padding. After reading a
message, the reader keeps its *shape* (every byte but the stamp's and the doubles', and
where the doubles are); a later message of the same length whose other bytes are those
is read by comparing them and unpacking its doubles, which gives the view the full reader
would build from those bytes (test_cdr: the same view or the same refusal, for every
message). Anything else goes through the full reader. At most :data:`SHAPES_KEPT` shapes
of messages up to :data:`SHAPE_MAX_BYTES` long are kept a type, so a stream of odd
messages costs no memory, only the full read.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

__all__ = ["DECODERS", "ENCAPSULATION", "Header", "JointStateView", "MessageError", "Stamp",
           "Vector3",
           "Wrench", "WrenchStampedView", "clock", "decode_joint_state",
           "decode_wrench_stamped", "joint_state", "joint_state_shape", "wrench_stamped",
           "wrench_stamped_shape"]

#: Encapsulation header of little-endian plain CDR (what this module writes).
ENCAPSULATION = b"\x00\x01\x00\x00"
_BASE = 4  # alignment counts from the end of the encapsulation header


class MessageError(ValueError):
    """A message does not have the layout PISC agreed for its topic (here, because its
    bytes are no CDR of its type; :mod:`pisc_msgs_py.convert` raises it for the rest
    and is where the nodes import it from)."""


def _padding(offset: int, size: int) -> int:
    return -(offset - _BASE) % size


class _Template:
    """A message's bytes with its stamp and doubles zero, and where they go.

    Built once per shape (type, frame, joint names, sequence lengths); :meth:`fill`
    copies it and writes one message's stamp and values.
    """

    def __init__(self) -> None:
        self.buf = bytearray(ENCAPSULATION)
        # (offset or None for an empty run, format) per run of doubles
        self.doubles: list[tuple[int | None, struct.Struct]] = []

    def _align(self, size: int) -> None:
        self.buf += bytes(_padding(len(self.buf), size))

    def uint32(self, value: int) -> None:
        self._align(4)
        self.buf += struct.pack("<I", value)

    def string(self, text: str) -> None:
        data = text.encode() + b"\x00"
        self.uint32(len(data))
        self.buf += data

    def header(self, frame_id: str) -> None:
        self.uint32(0)  # stamp.sec (int32), filled in
        self.uint32(0)  # stamp.nanosec
        self.string(frame_id)

    def double_run(self, count: int) -> None:
        """``count`` doubles in a row (values filled in), aligned to 8."""
        offset = None
        if count:
            self._align(8)
            offset = len(self.buf)
            self.buf += bytes(8 * count)
        self.doubles.append((offset, struct.Struct(f"<{count}d")))

    def sequence_of_doubles(self, count: int) -> None:
        self.uint32(count)
        self.double_run(count)

    def compile(self) -> _Template:
        """Once built: one format for the whole message, the bytes around the stamp and
        the doubles as strings of their own (:meth:`fill` packs it in one call)."""
        runs = [(o, fmt.size) for o, fmt in self.doubles if o is not None]
        fixed, at, fmt = [], 0, "<"
        for start, size, code in [(_BASE, 8, "iI")] + [(o, n, f"{n // 8}d") for o, n in runs]:
            fixed.append(bytes(self.buf[at:start]))
            fmt += f"{start - at}s{code}"
            at = start + size
        fixed.append(bytes(self.buf[at:]))
        self._pack = struct.Struct(fmt + f"{len(self.buf) - at}s").pack
        self._fixed = tuple(fixed)
        self._filled = tuple(i for i, (o, _) in enumerate(self.doubles) if o is not None)
        return self

    def fill(self, stamp_ns: int, *runs: Sequence[float]) -> bytes:
        """The message with this stamp and, in order, the values of each run."""
        fixed = self._fixed
        args = [fixed[0], *divmod(int(stamp_ns), 1_000_000_000)]
        for k, i in enumerate(self._filled, 1):
            args.append(fixed[k])
            args += runs[i]
        args.append(fixed[-1])
        return self._pack(*args)


def _joint_state_template(frame_id: str, names: tuple[str, ...], *counts: int) -> _Template:
    t = _Template()
    t.header(frame_id)
    t.uint32(len(names))
    for name in names:
        t.string(name)
    for count in counts:  # position, velocity, effort
        t.sequence_of_doubles(count)
    return t.compile()


def _wrench_stamped_template(frame_id: str) -> _Template:
    t = _Template()
    t.header(frame_id)
    t.double_run(6)  # force, torque
    return t.compile()


def _clock_template() -> _Template:
    t = _Template()
    t.uint32(0)  # clock.sec, filled in
    t.uint32(0)  # clock.nanosec
    return t.compile()


_joint_states: dict[tuple[Any, ...], _Template] = {}
_wrenches: dict[str, _Template] = {}
_CLOCK = _clock_template()


def joint_state(stamp_ns: int, names: tuple[str, ...], position: Sequence[float] = (),
                velocity: Sequence[float] = (), effort: Sequence[float] = (),
                frame_id: str = "") -> bytes:
    """A ``sensor_msgs/msg/JointState`` as CDR bytes (stamp in ns since the epoch)."""
    key = (frame_id, names, len(position), len(velocity), len(effort))
    template = _joint_states.get(key)
    if template is None:
        template = _joint_states[key] = _joint_state_template(*key)
    return template.fill(stamp_ns, position, velocity, effort)


def wrench_stamped(stamp_ns: int, frame_id: str, force: Sequence[float],
                   torque: Sequence[float] = (0.0, 0.0, 0.0)) -> bytes:
    """A ``geometry_msgs/msg/WrenchStamped`` as CDR bytes (force and torque: x, y, z)."""
    template = _wrenches.get(frame_id)
    if template is None:
        template = _wrenches[frame_id] = _wrench_stamped_template(frame_id)
    return template.fill(stamp_ns, (*force, *torque))


def clock(stamp_ns: int) -> bytes:
    """A ``rosgraph_msgs/msg/Clock`` as CDR bytes."""
    return _CLOCK.fill(stamp_ns)


# -- reading ----------------------------------------------------------------------------

class Stamp(NamedTuple):
    sec: int
    nanosec: int


class Header(NamedTuple):
    stamp: Stamp
    frame_id: str


class JointStateView(NamedTuple):
    """A ``sensor_msgs/msg/JointState`` read from CDR: every field, by its name."""
    header: Header
    name: tuple[str, ...]
    position: tuple[float, ...]
    velocity: tuple[float, ...]
    effort: tuple[float, ...]


class Vector3(NamedTuple):
    x: float
    y: float
    z: float


class Wrench(NamedTuple):
    force: Vector3
    torque: Vector3


class WrenchStampedView(NamedTuple):
    """A ``geometry_msgs/msg/WrenchStamped`` read from CDR: every field, by its name."""
    header: Header
    wrench: Wrench


class _Formats:
    """Precompiled unpackers of one byte order."""

    def __init__(self, order: str) -> None:
        self.uint32 = struct.Struct(order + "I").unpack_from
        self.stamp = struct.Struct(order + "iI").unpack_from
        self.order = order
        self.doubles = [struct.Struct(f"{order}{n}d").unpack_from for n in range(8)]

    def unpack_doubles(self, data: bytes, offset: int, n: int) -> tuple[float, ...]:
        if n < len(self.doubles):
            return self.doubles[n](data, offset)
        return struct.unpack_from(f"{self.order}{n}d", data, offset)


_FORMATS = {b"\x00\x01": _Formats("<"), b"\x00\x00": _Formats(">")}  # CDR_LE, CDR_BE


def _formats(data: bytes) -> _Formats:
    formats = _FORMATS.get(data[:2])
    if formats is None or len(data) < _BASE:
        raise ValueError(f"not plain CDR (encapsulation {bytes(data[:4]).hex() or 'none'})")
    return formats


def _string(data: bytes, offset: int, f: _Formats) -> tuple[str, int]:
    """The string at ``offset`` (aligned to 4 first) and the offset after it."""
    offset += -(offset - _BASE) % 4
    (length,) = f.uint32(data, offset)
    offset += 4
    end = offset + length
    if length == 0 or end > len(data) or data[end - 1] != 0:
        raise ValueError(f"a string of {length} bytes does not fit or is not terminated")
    return data[offset:end - 1].decode(), end


def _doubles(data: bytes, offset: int, f: _Formats) -> tuple[tuple[float, ...], int]:
    """The sequence of doubles at ``offset`` (its count aligned to 4) and the offset after."""
    offset += -(offset - _BASE) % 4
    (n,) = f.uint32(data, offset)
    offset += 4
    if not n:
        return (), offset
    offset += -(offset - _BASE) % 8
    if offset + 8 * n > len(data):
        raise ValueError(f"a sequence of {n} doubles does not fit in the message")
    return f.unpack_doubles(data, offset, n), offset + 8 * n


def _header(data: bytes, f: _Formats) -> tuple[Header, int]:
    frame_id, offset = _string(data, _BASE + 8, f)
    return Header(Stamp(*f.stamp(data, _BASE)), frame_id), offset


#: Shapes kept a message type, and the longest message whose shape is kept.
SHAPES_KEPT = 16
SHAPE_MAX_BYTES = 512


class _Shape(NamedTuple):
    """A message's bytes but its stamp's and its doubles': ``fixed`` are the (start,
    end, bytes) that must match, ``runs`` the (offset, unpack_from) of each run of
    doubles (None for an empty one), ``fields`` what the bytes give besides (frame,
    names); ``read_by`` the converters found to read this shape whole
    (:func:`pisc_msgs_py.convert.fast_read`)."""
    fixed: tuple[tuple[int, int, bytes], ...]
    stamp: Callable[[bytes, int], tuple[int, int]]
    runs: tuple[tuple[int, Callable[[bytes, int], tuple[float, ...]] | None], ...]
    fields: tuple[Any, ...]
    read_by: set[Any]

    def stamp_ns(self, data: bytes) -> int:
        sec, nanosec = self.stamp(data, _BASE)
        return sec * 1_000_000_000 + nanosec

    def doubles(self, data: bytes) -> tuple[tuple[float, ...], ...]:
        """Each run of doubles of ``data``, a message of this shape."""
        return tuple(read(data, offset) if read else () for offset, read in self.runs)


class _Shapes:
    """The shapes met so far of one message type, by message length."""

    def __init__(self) -> None:
        self._by_size: dict[int, list[_Shape]] = {}
        self._kept = 0

    def match(self, data: bytes) -> _Shape | None:
        for shape in self._by_size.get(len(data), ()):
            for start, end, fixed in shape.fixed:
                if data[start:end] != fixed:
                    break
            else:
                return shape
        return None

    def learn(self, data: bytes, f: _Formats, runs: Sequence[tuple[int, int]],
              fields: tuple[Any, ...]) -> None:
        """Keep the shape of ``data``, which the full reader read: ``runs`` are the
        (offset, count) of its runs of doubles, in order."""
        if self._kept >= SHAPES_KEPT or len(data) > SHAPE_MAX_BYTES:
            return
        fixed, at = [], 0
        for start, end in [(_BASE, _BASE + 8)] + [(o, o + 8 * n) for o, n in runs if n]:
            if start > at:
                fixed.append((at, start, bytes(data[at:start])))
            at = end
        if at < len(data):
            fixed.append((at, len(data), bytes(data[at:])))
        self._by_size.setdefault(len(data), []).append(_Shape(
            tuple(fixed), f.stamp,
            tuple((o, f.doubles[n] if n < len(f.doubles) else
                   struct.Struct(f"{f.order}{n}d").unpack_from) if n else (o, None)
                  for o, n in runs),
            fields, set()))
        self._kept += 1


_JOINT_STATE_SHAPES = _Shapes()
_WRENCH_STAMPED_SHAPES = _Shapes()


def joint_state_shape(data: bytes) -> _Shape | None:
    """The kept shape of ``data``, a ``JointState``, or None (not met before, or not
    kept)."""
    return _JOINT_STATE_SHAPES.match(data)


def wrench_stamped_shape(data: bytes) -> _Shape | None:
    """The kept shape of ``data``, a ``WrenchStamped``, or None."""
    return _WRENCH_STAMPED_SHAPES.match(data)


def _joint_state(data: bytes) -> JointStateView:
    shape = _JOINT_STATE_SHAPES.match(data)
    if shape is not None:
        frame_id, names = shape.fields
        (p, read_p), (v, read_v), (e, read_e) = shape.runs
        return JointStateView(Header(Stamp(*shape.stamp(data, _BASE)), frame_id), names,
                              read_p(data, p) if read_p else (),
                              read_v(data, v) if read_v else (),
                              read_e(data, e) if read_e else ())
    f = _formats(data)
    header, offset = _header(data, f)
    offset += -(offset - _BASE) % 4
    (count,) = f.uint32(data, offset)
    offset += 4
    if 8 * count > len(data) - offset:  # each name takes 8 bytes at least
        raise ValueError(f"{count} joint names do not fit in the message")
    names = []
    for _ in range(count):
        name, offset = _string(data, offset, f)
        names.append(name)
    position, offset = _doubles(data, offset, f)
    p = offset - 8 * len(position)
    velocity, offset = _doubles(data, offset, f)
    v = offset - 8 * len(velocity)
    effort, offset = _doubles(data, offset, f)
    view = JointStateView(header, tuple(names), position, velocity, effort)
    _JOINT_STATE_SHAPES.learn(data, f, ((p, len(position)), (v, len(velocity)),
                                        (offset - 8 * len(effort), len(effort))),
                              (header.frame_id, view.name))
    return view


def _wrench_stamped(data: bytes) -> WrenchStampedView:
    shape = _WRENCH_STAMPED_SHAPES.match(data)
    if shape is None:
        f = _formats(data)
        header, offset = _header(data, f)
        offset += -(offset - _BASE) % 8
        x, y, z, tx, ty, tz = f.doubles[6](data, offset)
        _WRENCH_STAMPED_SHAPES.learn(data, f, ((offset, 6),), (header.frame_id,))
    else:
        (frame_id,), ((offset, read),) = shape.fields, shape.runs
        header = Header(Stamp(*shape.stamp(data, _BASE)), frame_id)
        x, y, z, tx, ty, tz = read(data, offset)
    return WrenchStampedView(header, Wrench(Vector3(x, y, z), Vector3(tx, ty, tz)))


def _decoding(what: str, read: Callable[[bytes], Any], data: bytes) -> Any:
    try:
        return read(data)
    except (struct.error, ValueError, UnicodeDecodeError) as exc:
        raise MessageError(f"{what}: malformed CDR ({exc})") from None


def decode_joint_state(data: bytes) -> JointStateView:
    """Read a ``sensor_msgs/msg/JointState``; :class:`MessageError` if malformed."""
    return _decoding("JointState", _joint_state, data)


def decode_wrench_stamped(data: bytes) -> WrenchStampedView:
    """Read a ``geometry_msgs/msg/WrenchStamped``; :class:`MessageError` if malformed."""
    return _decoding("WrenchStamped", _wrench_stamped, data)


#: The types a PISC node reads from raw bytes, by ROS type name.
DECODERS: dict[str, Callable[[bytes], Any]] = {
    "sensor_msgs/msg/JointState": decode_joint_state,
    "geometry_msgs/msg/WrenchStamped": decode_wrench_stamped,
}
