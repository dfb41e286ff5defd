"""Message converters: exact round trips, refusal of malformed messages."""

import math

import pytest
from diagnostic_msgs.msg import DiagnosticStatus
from sensor_msgs.msg import JointState

from pisc_msgs_py.convert import (
    MessageError,
    cart_force_from_msg,
    cart_force_to_msg,
    joint_sample_from_msg,
    joint_sample_to_msg,
    mode_from_msg,
    mode_to_msg,
    motor_sample_from_msg,
    motor_sample_to_msg,
    state_from_msg,
    state_to_msg,
    true_state_from_msg,
    true_state_to_msg,
)
from pisc_msgs_py.types import (
    CartForce,
    JointSample,
    Mode,
    ModeReport,
    MotorSample,
    StateEstimate,
    TrueState,
)

STAMP = 1_795_000_000_123_456_789


@pytest.mark.parametrize("value,to_msg,from_msg", [
    (JointSample(STAMP, -0.123456789012345, math.pi + 1e-9), joint_sample_to_msg,
     joint_sample_from_msg),
    (MotorSample(STAMP, 0.1 + 0.2), motor_sample_to_msg, motor_sample_from_msg),
    (StateEstimate(STAMP, 0.01, -0.2, 3.0, 11.5), state_to_msg, state_from_msg),
    (CartForce(STAMP, -1.7917), cart_force_to_msg, cart_force_from_msg),
    (ModeReport(STAMP, Mode.FAULT, "cart outside"), mode_to_msg, mode_from_msg),
    (TrueState(STAMP, 0.1, 0.2, 0.3, 0.4, 0.5), true_state_to_msg, true_state_from_msg),
])
def test_round_trip_is_exact(value, to_msg, from_msg):
    assert from_msg(to_msg(value)) == value


def test_stamp_splits_into_sec_and_nanosec():
    msg = joint_sample_to_msg(JointSample(STAMP, 0.0, 0.0))
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1_795_000_000, 123_456_789)


def test_fault_mode_is_an_error_status():
    assert mode_to_msg(ModeReport(0, Mode.FAULT)).status[0].level == DiagnosticStatus.ERROR
    assert mode_to_msg(ModeReport(0, Mode.CATCH)).status[0].level == DiagnosticStatus.OK


@pytest.mark.parametrize("names,positions,message", [
    (["pendulum", "cart"], [0.0, 0.0], r"expected joints \['cart', 'pendulum'\]"),
    (["cart", "pendulum"], [0.0], "expected 2 values in 'position', got 1"),
    (["cart", "pendulum"], [0.0, float("nan")], "non-finite"),
])
def test_malformed_joint_states_are_refused(names, positions, message):
    msg = JointState(name=names, position=positions)
    with pytest.raises(MessageError, match=message):
        joint_sample_from_msg(msg)


def test_unknown_mode_is_refused():
    msg = mode_to_msg(ModeReport(0, Mode.CATCH))
    msg.status[0].message = "dancing"
    with pytest.raises(MessageError, match="unknown mode 'dancing'"):
        mode_from_msg(msg)
