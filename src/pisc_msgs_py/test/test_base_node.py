"""What every node shares: the resend cache, the diagnostics cadence, parse-then-diagnose."""

from __future__ import annotations

import pytest
from sensor_msgs.msg import JointState

from pisc_msgs_py.base_node import DIAGNOSTIC_EVERY, ERROR, WARN, PiscNode, ResendCache
from pisc_msgs_py.convert import joint_sample_from_msg, joint_sample_to_msg
from pisc_msgs_py.types import JointSample


class Recorder:
    """A publisher that keeps what it was given."""

    def __init__(self) -> None:
        self.sent: list[object] = []

    def publish(self, msg: object) -> None:
        self.sent.append(msg)


def test_the_resend_cache_answers_the_last_stamp_again_with_the_same_messages_only():
    force, voltage = Recorder(), Recorder()
    cache = ResendCache()
    assert not cache.resend(0)  # nothing answered yet, not even stamp 0
    first, second = object(), object()
    cache.publish(5_000_000, (force, first), (voltage, second))
    assert force.sent == [first] and voltage.sent == [second]
    assert not cache.resend(10_000_000)  # another stamp: no answer, nothing sent
    assert not cache.resend(4_999_999)
    assert force.sent == [first] and voltage.sent == [second]
    assert cache.resend(5_000_000)
    assert cache.resend(5_000_000)
    assert len(force.sent) == 3 and all(m is first for m in force.sent)
    assert len(voltage.sent) == 3 and all(m is second for m in voltage.sent)
    newer = object()
    cache.publish(10_000_000, (force, newer))
    assert not cache.resend(5_000_000)  # only the newest answer is kept
    assert cache.resend(10_000_000)
    assert force.sent[-2:] == [newer, newer] and len(voltage.sent) == 3


def test_routine_diagnostics_fire_on_the_samples_they_fired_on_before():
    # the controllers and the driver counted items from 1 (count % 200 == 1), the plant
    # its sample index from 0 (index % 200 == 0), which it now passes as index + 1
    assert DIAGNOSTIC_EVERY == 200
    for count in range(0, 3 * DIAGNOSTIC_EVERY + 2):
        assert PiscNode.routine_diagnostics(count) == (count % 200 == 1), count
        assert PiscNode.routine_diagnostics(count + 1) == (count % 200 == 0), count


def test_the_cadence_is_the_first_item_then_every_200th():
    fired = [n for n in range(1, 1001) if PiscNode.routine_diagnostics(n)]
    assert fired == [1, 201, 401, 601, 801]


class Diagnosed:
    """Stands in for a node's ``diagnose`` (PiscNode.parse only calls that)."""

    def __init__(self) -> None:
        self.statuses: list[tuple[int, str]] = []

    def diagnose(self, level: int, message: str, stamp_ns: int | None = None,
                 **values: object) -> None:
        self.statuses.append((level, message))


def test_parse_returns_the_value_of_a_good_message_and_says_nothing():
    node = Diagnosed()
    sample = JointSample(5_000_000, 0.05, 3.0)
    assert PiscNode.parse(node, joint_sample_to_msg(sample), joint_sample_from_msg,
                          "joint_states") == sample
    assert node.statuses == []


@pytest.mark.parametrize("level", [ERROR, WARN], ids=["error", "warn"])
def test_parse_diagnoses_a_malformed_message_with_the_text_the_nodes_said_before(level):
    node = Diagnosed()
    msg = JointState(name=["cart", "pendulum"], position=[0.0])
    assert PiscNode.parse(node, msg, joint_sample_from_msg, "joint_states", level) is None
    # "rejected WHAT: " and the converter's own message, which names the topic again
    assert node.statuses == [(level, "rejected joint_states: joint_states: expected 2 values "
                                     "in 'position', got 1")]


def test_parse_lets_other_errors_through():
    def broken(msg: object) -> object:
        raise KeyError("a bug, not a bad message")

    with pytest.raises(KeyError):
        PiscNode.parse(Diagnosed(), JointState(), broken, "joint_states")


def test_errors_of_one_kind_are_logged_a_burst_a_window_and_the_rest_counted():
    from pisc_msgs_py.node_support import LogLimit

    limit = LogLimit(burst=2, window_s=10.0)
    trip = "command watchdog: no command answered samples 1 .. 3: 0 V from sample 3"
    assert limit.admit(trip, 100.0) == (True, None)
    assert limit.admit("device silent: no frame for 20.0 ms", 100.1) == (True, None)
    assert limit.admit(trip, 101.0) == (True, None)
    assert limit.admit(trip, 102.0) == (False, None)  # the third in the window
    assert limit.admit(trip, 109.9) == (False, None)
    assert limit.admit("device silent: again", 105.0) == (True, None)  # its own kind
    # the next one after the window is logged, with what was held back
    assert limit.admit(trip, 110.0) == (True, "2 more 'command watchdog' error(s) not "
                                              "logged (2 are logged per 10 s; all are on "
                                              "/diagnostics)")
    assert limit.admit(trip, 125.0) == (True, None)  # nothing was held back since
    with pytest.raises(ValueError, match=r"burst 0 must be >= 1 and window 1.0 s > 0"):
        LogLimit(burst=0, window_s=1.0)
