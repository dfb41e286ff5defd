"""Playback of a reference bag on /clock simulated time."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState

from conftest import spin_until
from pisc_bag.bag import RawMessage, read_bag, read_bag_raw
from pisc_runs.play import play_bag, playback_plan
from pisc_bag.recorder_node import recording_qos
from pisc_msgs_py.convert import motor_sample_from_msg, stamp_from_msg
from pisc_msgs_py.base_node import message_class
from pisc_msgs_py.topics import CLOCK, GRAPH_TOPICS, VOLTAGE

SWINGUP = Path(__file__).resolve().parents[3] / "bags" / "default-swingup"


def stamped(sec: int, nanosec: int, tag: bytes) -> bytes:
    return b"\x00\x01\x00\x00" + sec.to_bytes(4, "little") + nanosec.to_bytes(4, "little") + tag


def test_plan_orders_by_header_stamp_keeps_recorded_order_within_one_and_drops_clock():
    messages = [
        RawMessage("/a", "t", 1, stamped(0, 5_000_000, b"a1")),
        RawMessage("/clock", "rosgraph_msgs/msg/Clock", 2, stamped(0, 0, b"")),
        RawMessage("/b", "t", 3, stamped(0, 0, b"b0")),
        RawMessage("/a", "t", 4, stamped(0, 0, b"a0")),
        RawMessage("/c", "t", 5, b"\x00\x01"),  # too short for a header: not played
    ]
    plan = playback_plan(messages)
    assert [(p.stamp_ns, p.topic, p.data[-2:]) for p in plan] == [
        (0, "/b", b"b0"), (0, "/a", b"a0"), (5_000_000, "/a", b"a1")]


@pytest.mark.integration
@pytest.mark.bag
def test_play_publishes_every_voltage_in_order_on_simulated_time(ros_context, domain_id):
    node = Node("listener", context=ros_context)
    voltages, clocks = [], []
    node.create_subscription(JointState, VOLTAGE.name,
                             lambda m: voltages.append(motor_sample_from_msg(m)),
                             recording_qos(VOLTAGE))
    # a reader of every other played topic too: play waits for one on each, and each
    # must receive every message
    plan = playback_plan(read_bag_raw(SWINGUP))
    played = {item.topic: item.type for item in plan if item.topic != VOLTAGE.name}
    received = dict.fromkeys(played, 0)
    topics = {t.name: t for t in GRAPH_TOPICS}

    def count(topic: str):
        def on_message(_: bytes) -> None:
            received[topic] += 1
        return on_message

    for topic, type_name in played.items():
        node.create_subscription(message_class(type_name), topic, count(topic),
                                 recording_qos(topics[topic]), raw=True)
    node.create_subscription(Clock, CLOCK.name, lambda m: clocks.append(stamp_from_msg(m.clock)),
                             recording_qos(CLOCK))
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    result = {}

    def play() -> None:
        started = time.monotonic()
        result["counts"] = play_bag(SWINGUP, rate=4.0, wait_subscribers_s=20.0,
                                    domain_id=domain_id)
        result["wall"] = time.monotonic() - started

    thread = threading.Thread(target=play)
    thread.start()
    try:
        assert spin_until(executor, lambda: "counts" in result and len(voltages) >= 2001
                          and sum(received.values()) + len(voltages) >= len(plan), 120.0)
        # /clock is another reader: its last message may still be queued behind the voltage
        spin_until(executor, lambda: clocks and clocks[-1] == 10_000_000_000, 5.0)
    finally:
        thread.join(60)
        node.destroy_node()
    recorded = [motor_sample_from_msg(m.message) for m in read_bag(SWINGUP, [VOLTAGE.name])]
    assert voltages == recorded  # same stamps, same values, same order
    assert result["counts"][VOLTAGE.name] == 2001 and result["counts"][CLOCK.name] == 2001
    assert received == {topic: result["counts"][topic] for topic in played}
    assert sum(received.values()) + len(voltages) == len(plan)
    assert result["wall"] >= 10.0 / 4.0  # paced: 10 s of run at 4x
    assert clocks == sorted(clocks) and clocks[-1] == 10_000_000_000
