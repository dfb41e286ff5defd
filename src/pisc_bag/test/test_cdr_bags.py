"""The nodes' CDR bytes (pisc_msgs_py.cdr) against what DDS recorded in the reference bags.

The nodes publish the bytes :mod:`pisc_msgs_py.cdr` writes instead of rclpy message
objects. Every message of every reference bag, read into its typed value and
written again, gives the recorded bytes exactly: the bags a run records now are the bags
it recorded before, byte for byte, and replay reads them as it read those.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from pisc_bag.bag import read_bag_raw
from pisc_msgs_py import cdr
from pisc_msgs_py.convert import (
    cart_force_from_msg,
    cart_force_to_cdr,
    clock_to_cdr,
    joint_sample_from_msg,
    joint_sample_to_cdr,
    motor_sample_from_msg,
    motor_sample_to_cdr,
    stamp_from_msg,
    state_from_msg,
    state_to_cdr,
    true_state_from_msg,
    true_state_to_cdr,
)
from pisc_msgs_py.topics import (
    CART_FORCE,
    CLOCK,
    CURRENT_SETPOINT,
    JOINT_STATES,
    MOTOR_CURRENT,
    SIM_STATE,
    STATE,
    VOLTAGE,
)

pytestmark = pytest.mark.bag

BAGS = Path(__file__).resolve().parents[3] / "bags"
REFERENCE_BAGS = ("default-swingup", "lyapunov-swingup", "thesis-gains", "driver-swingup")


def _clock(data: bytes) -> bytes:
    return clock_to_cdr(stamp_from_msg(cdr.Stamp(
        int.from_bytes(data[4:8], "little", signed=True), int.from_bytes(data[8:12], "little"))))


# topic -> bytes written again from what the recorded bytes hold
AGAIN = {
    JOINT_STATES.name: lambda d: joint_sample_to_cdr(
        joint_sample_from_msg(cdr.decode_joint_state(d))),
    MOTOR_CURRENT.name: lambda d: motor_sample_to_cdr(
        motor_sample_from_msg(cdr.decode_joint_state(d))),
    CURRENT_SETPOINT.name: lambda d: motor_sample_to_cdr(
        motor_sample_from_msg(cdr.decode_joint_state(d))),
    VOLTAGE.name: lambda d: motor_sample_to_cdr(motor_sample_from_msg(cdr.decode_joint_state(d))),
    STATE.name: lambda d: state_to_cdr(state_from_msg(cdr.decode_joint_state(d))),
    SIM_STATE.name: lambda d: true_state_to_cdr(true_state_from_msg(cdr.decode_joint_state(d))),
    CART_FORCE.name: lambda d: cart_force_to_cdr(
        cart_force_from_msg(cdr.decode_wrench_stamped(d))),
    CLOCK.name: _clock,
}


@pytest.mark.parametrize("bag", REFERENCE_BAGS)
def test_every_cycle_message_of_a_reference_bag_is_written_again_byte_for_byte(bag):
    counts = dict.fromkeys(AGAIN, 0)
    for message in read_bag_raw(BAGS / bag, list(AGAIN)):
        data = bytes(message.data)
        assert AGAIN[message.topic](data) == data, (message.topic, data.hex())
        counts[message.topic] += 1
    # the driver's bag has no simulated state and no /clock; every other topic is there
    missing = {t for t, n in counts.items() if n == 0}
    assert missing == ({SIM_STATE.name, CLOCK.name} if bag == "driver-swingup" else set())
    assert min(n for t, n in counts.items() if n and t != CLOCK.name) > 1000
    assert counts[CLOCK.name] in (0, 201, 2001)  # every 10th sample, every one, or none
