"""CDR bytes without message objects: what rclpy reads from them, what they read from rclpy,
big-endian senders, and refusal of bytes that are no such message."""

from __future__ import annotations

import math
import struct

import pytest
from geometry_msgs.msg import WrenchStamped
from rclpy.serialization import deserialize_message, serialize_message
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState

from pisc_msgs_py import cdr
from pisc_msgs_py.convert import (
    MessageError,
    cart_force_from_msg,
    cart_force_to_cdr,
    cart_force_to_msg,
    clock_to_cdr,
    joint_sample_from_msg,
    joint_sample_to_cdr,
    joint_sample_to_msg,
    motor_sample_from_msg,
    motor_sample_to_cdr,
    motor_sample_to_msg,
    state_from_msg,
    state_to_cdr,
    state_to_msg,
    true_state_from_msg,
    true_state_to_cdr,
    true_state_to_msg,
)
from pisc_msgs_py import convert
from pisc_msgs_py.types import CartForce, JointSample, MotorSample, StateEstimate, TrueState

STAMP = 1_795_000_000_123_456_789

CASES = [
    (JointSample(STAMP, -0.123456789012345, math.pi + 1e-9), joint_sample_to_msg,
     joint_sample_to_cdr, joint_sample_from_msg, cdr.decode_joint_state),
    (MotorSample(STAMP, 0.1 + 0.2), motor_sample_to_msg, motor_sample_to_cdr,
     motor_sample_from_msg, cdr.decode_joint_state),
    (StateEstimate(5_000_000, 0.05, -1e-300, 3.0, 7.5), state_to_msg, state_to_cdr,
     state_from_msg, cdr.decode_joint_state),
    (TrueState(0, 0.01, 0.02, 0.03, 0.04, -2.5), true_state_to_msg, true_state_to_cdr,
     true_state_from_msg, cdr.decode_joint_state),
    (CartForce(STAMP, -1.25e-3), cart_force_to_msg, cart_force_to_cdr, cart_force_from_msg,
     cdr.decode_wrench_stamped),
]
IDS = ["joint_sample", "motor_sample", "state", "true_state", "cart_force"]


@pytest.mark.parametrize("value,to_msg,to_cdr,from_msg,decode", CASES, ids=IDS)
def test_the_bytes_are_the_message_rclpy_builds(value, to_msg, to_cdr, from_msg, decode):
    """rclpy reads the bytes as the message ``*_to_msg`` builds, every field; the bytes
    rclpy writes for that message read back to the same value through the view."""
    msg = to_msg(value)
    assert deserialize_message(to_cdr(value), type(msg)) == msg
    assert from_msg(decode(serialize_message(msg))) == value
    assert from_msg(decode(to_cdr(value))) == value


@pytest.mark.parametrize("frame_id", ["answer", "hold", "zero", ""])
def test_a_motor_sample_with_a_frame_is_the_message_rclpy_builds(frame_id):
    """The driver's /pisc/motor/voltage_sent names why each byte was written in the
    header's frame; the string's length changes the padding before the effort. (Not
    compared byte for byte with ``serialize_message``: its padding bytes are whatever its
    buffer held before.)"""
    value = MotorSample(STAMP, -7.3125)
    msg = motor_sample_to_msg(value, frame_id)
    assert msg.header.frame_id == frame_id
    data = motor_sample_to_cdr(value, frame_id)
    assert deserialize_message(data, JointState) == msg
    assert cdr.decode_joint_state(data).header.frame_id == frame_id
    assert motor_sample_from_msg(cdr.decode_joint_state(data)) == value


def test_the_clock_is_the_message_rclpy_builds():
    msg = deserialize_message(clock_to_cdr(STAMP), Clock)
    assert (msg.clock.sec, msg.clock.nanosec) == (1_795_000_000, 123_456_789)


def test_a_view_has_every_field_of_its_message():
    msg = JointState(name=[f"joint_{k}" for k in range(11)],
                     position=[float(k) for k in range(11)], velocity=[0.5], effort=[])
    msg.header.frame_id = "base_link"
    msg.header.stamp.sec, msg.header.stamp.nanosec = -3, 7
    view = cdr.decode_joint_state(serialize_message(msg))
    assert view.header == cdr.Header(cdr.Stamp(-3, 7), "base_link")
    assert view.name == tuple(msg.name) and view.position == tuple(msg.position)
    assert view.velocity == (0.5,) and view.effort == ()
    wrench = WrenchStamped()
    wrench.wrench.force.y, wrench.wrench.torque.z = 2.0, -3.0
    view = cdr.decode_wrench_stamped(serialize_message(wrench))
    assert view.wrench.force == (0.0, 2.0, 0.0) and view.wrench.torque == (0.0, 0.0, -3.0)


def _big_endian_motor_sample(sec: int, nanosec: int, value: float) -> bytes:
    """CDR_BE by hand: header (stamp, frame ''), names ['motor'], position [], velocity
    [], effort [value], each field aligned from the end of the encapsulation header."""
    body = struct.pack(">iII", sec, nanosec, 1) + b"\x00" + bytes(3)  # frame_id '' + pad
    body += struct.pack(">II", 1, 6) + b"motor\x00" + bytes(2)  # one name + pad
    body += struct.pack(">III", 0, 0, 1) + bytes(4) + struct.pack(">d", value)
    return b"\x00\x00\x00\x00" + body


def test_big_endian_cdr_reads_as_little_endian_does():
    view = cdr.decode_joint_state(_big_endian_motor_sample(3, 5_000_000, -0.75))
    assert motor_sample_from_msg(view) == MotorSample(3_005_000_000, -0.75)


def test_bytes_that_are_no_such_message_are_refused_saying_why():
    good = state_to_cdr(StateEstimate(5_000_000, 0.05, 0.0, 3.0, 0.0))
    for cut in range(len(good)):  # every truncation, the empty message included
        with pytest.raises(MessageError, match=r"^JointState: malformed CDR \("):
            cdr.decode_joint_state(good[:cut])
    with pytest.raises(MessageError, match=r"not plain CDR \(encapsulation 00070000\)"):
        cdr.decode_joint_state(b"\x00\x07\x00\x00" + good[4:])  # XCDR2: not what ROS sends
    huge = good[:20] + struct.pack("<I", 1_000_000) + good[24:]  # a million joint names
    with pytest.raises(MessageError, match="1000000 joint names do not fit"):
        cdr.decode_joint_state(huge)
    with pytest.raises(MessageError, match=r"^WrenchStamped: malformed CDR"):
        # a motor sample is shorter than any WrenchStamped (CDR does not name its type:
        # a longer JointState would read as one)
        cdr.decode_wrench_stamped(motor_sample_to_cdr(MotorSample(0, 1.0)))


def test_non_finite_values_go_through_to_the_converters_which_refuse_them():
    data = motor_sample_to_cdr(MotorSample(0, math.nan))
    with pytest.raises(MessageError, match="non-finite"):
        motor_sample_from_msg(cdr.decode_joint_state(data))


# -- shapes met before: the same view or the same refusal as the full reader -----------------

def _full_read(decode, data, monkeypatch):
    """What the full reader makes of ``data`` (no shape kept): a view or the refusal."""
    with monkeypatch.context() as m:
        m.setattr(cdr, "_JOINT_STATE_SHAPES", cdr._Shapes())
        m.setattr(cdr, "_WRENCH_STAMPED_SHAPES", cdr._Shapes())
        return _outcome(decode, data)


def _outcome(decode, data):
    try:
        return decode(data)
    except MessageError as exc:
        return str(exc)


@pytest.mark.parametrize("value,to_msg,to_cdr,from_msg,decode", CASES, ids=IDS)
def test_a_shape_met_before_reads_every_byte_as_the_full_reader_does(
        value, to_msg, to_cdr, from_msg, decode, monkeypatch):
    """Once a message's shape is kept, every message of its length is read through it or
    the full reader: changing any one byte of the message (to each of three values) gives
    what the full reader gives, a view or the same refusal. A change in the stamp or a
    double is read through the shape; one anywhere else is not that shape."""
    data = to_cdr(value)
    monkeypatch.setattr(cdr, "_JOINT_STATE_SHAPES", cdr._Shapes())
    monkeypatch.setattr(cdr, "_WRENCH_STAMPED_SHAPES", cdr._Shapes())
    assert from_msg(decode(data)) == value  # the full reader, which keeps the shape
    shapes = cdr._WRENCH_STAMPED_SHAPES if decode is cdr.decode_wrench_stamped \
        else cdr._JOINT_STATE_SHAPES
    shape = shapes.match(data)
    assert shape is not None
    values = [run for run in _runs(decode(data)) if run]
    starts = [offset for offset, read in shape.runs if read is not None]
    varying = {*range(4, 12), *(k for start, run in zip(starts, values)
                                for k in range(start, start + 8 * len(run)))}
    assert len(varying) == 8 + 8 * sum(map(len, values))
    for at in range(len(data)):
        for byte in {0x00, 0x41, 0xFF, data[at] ^ 0x01} - {data[at]}:
            changed = data[:at] + bytes([byte]) + data[at + 1:]
            assert (shapes.match(changed) is shape) == (at in varying), at
            assert _outcome(decode, changed) == _full_read(decode, changed, monkeypatch), at


def _runs(view):
    if isinstance(view, cdr.WrenchStampedView):
        return [(*view.wrench.force, *view.wrench.torque)]
    return [view.position, view.velocity, view.effort]


def test_shapes_kept_are_bounded_and_odd_messages_still_read(monkeypatch):
    """A stream of messages of ever new shapes (frames of every length) keeps at most
    SHAPES_KEPT shapes, none of a message longer than SHAPE_MAX_BYTES, and every one of
    them still reads right through the full reader."""
    monkeypatch.setattr(cdr, "_JOINT_STATE_SHAPES", cdr._Shapes())
    for k in range(3 * cdr.SHAPES_KEPT):
        data = motor_sample_to_cdr(MotorSample(STAMP + k, float(k)), "f" * k)
        view = cdr.decode_joint_state(data)
        assert view.header.frame_id == "f" * k and view.effort == (float(k),)
    kept = cdr._JOINT_STATE_SHAPES._by_size
    assert sum(map(len, kept.values())) == cdr.SHAPES_KEPT
    monkeypatch.setattr(cdr, "_JOINT_STATE_SHAPES", cdr._Shapes())
    long = motor_sample_to_cdr(MotorSample(STAMP, 1.0), "x" * cdr.SHAPE_MAX_BYTES)
    assert cdr.decode_joint_state(long).effort == (1.0,)
    assert cdr._JOINT_STATE_SHAPES.match(long) is None


def test_a_big_endian_shape_reads_big_endian(monkeypatch):
    monkeypatch.setattr(cdr, "_JOINT_STATE_SHAPES", cdr._Shapes())
    cdr.decode_joint_state(_big_endian_motor_sample(3, 5_000_000, -0.75))  # keeps it
    view = cdr.decode_joint_state(_big_endian_motor_sample(-4, 999_999_999, 1e-300))
    assert motor_sample_from_msg(view) == MotorSample(-3_000_000_001, 1e-300)


def _converted(from_msg, decode, data):
    try:
        return from_msg(decode(data))
    except MessageError as exc:
        return str(exc)


@pytest.mark.parametrize("value,to_msg,to_cdr,from_msg,decode", CASES, ids=IDS)
def test_bytes_go_straight_to_the_value_only_as_the_converter_would_read_them(
        value, to_msg, to_cdr, from_msg, decode, monkeypatch):
    """fast_read gives nothing for a shape the converter has not read whole; once it
    has (note_read), it gives what the converter gives for every one-byte change of the
    message, or nothing (the node then reads it in full): never another value, and
    nothing where the converter refuses (a non-finite value, other names)."""
    monkeypatch.setattr(cdr, "_JOINT_STATE_SHAPES", cdr._Shapes())
    monkeypatch.setattr(cdr, "_WRENCH_STAMPED_SHAPES", cdr._Shapes())
    data = to_cdr(value)
    assert convert.fast_read(from_msg, data) is None  # shape not met
    assert from_msg(decode(data)) == value  # keeps the shape
    assert convert.fast_read(from_msg, data) is None  # not yet read whole by from_msg
    convert.note_read(from_msg, data)
    assert convert.fast_read(from_msg, data) == value
    fast = refused = 0
    for at in range(len(data)):
        for byte in {0x00, 0x7F, 0xFF, data[at] ^ 0x01} - {data[at]}:
            changed = data[:at] + bytes([byte]) + data[at + 1:]
            got = convert.fast_read(from_msg, changed)
            full = _converted(from_msg, decode, changed)
            if got is None:
                refused += isinstance(full, str)
            else:
                fast += 1
                assert got == full, at
    assert fast and refused  # both kinds were met


def test_a_converter_reads_fast_only_the_shapes_it_read_whole(monkeypatch):
    """The estimator's joint_states and the motor current share a type: a motor sample's
    shape read whole by motor_sample_from_msg is not one joint_sample_from_msg reads, and
    a JointState with other joint names is never read fast."""
    monkeypatch.setattr(cdr, "_JOINT_STATE_SHAPES", cdr._Shapes())
    current = motor_sample_to_cdr(MotorSample(STAMP, 0.5))
    motor_sample_from_msg(cdr.decode_joint_state(current))
    convert.note_read(motor_sample_from_msg, current)
    assert convert.fast_read(motor_sample_from_msg, current) == MotorSample(STAMP, 0.5)
    assert convert.fast_read(joint_sample_from_msg, current) is None
    other = cdr.joint_state(STAMP, ("x", "y"), (1.0, 2.0))
    with pytest.raises(MessageError, match="expected joints"):
        joint_sample_from_msg(cdr.decode_joint_state(other))
    assert convert.fast_read(joint_sample_from_msg, other) is None
