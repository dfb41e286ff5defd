"""Playback: publish a bag's topics on simulated time (``/clock``), at real speed or faster.

    pisc_bag play BAG [--rate R] [--topic NAME ...] [--wait-subscribers S]

Messages are played in the order of their header stamps (the control cycle's time;
within a cycle in the order they were recorded), the recorded CDR bytes unchanged, and
``/clock`` is published with each new stamp, so nodes started with
``use_sim_time:=true`` run on the recorded run's time. The bag's own ``/clock`` is not
replayed (playback owns the clock). ``--rate 2`` plays twice as fast as recorded,
``--rate 0`` as fast as the subscribers take it. E.g. play only the measurements and
run the controllers against them::

    pisc_bag play bags/default-swingup --topic /pisc/joint_states --topic /pisc/motor/current
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pisc_bag.bag import BagError, RawMessage, header_stamp_ns, read_bag_raw

__all__ = ["PlayItem", "play_bag", "playback_plan"]


@dataclass(frozen=True)
class PlayItem:
    stamp_ns: int
    topic: str
    type: str
    data: bytes


def playback_plan(messages: Iterable[RawMessage], clock_topic: str = "/clock") -> list[PlayItem]:
    """Messages with a header stamp, ordered by stamp (stable: recorded order within one)."""
    items = []
    for m in messages:
        if m.topic == clock_topic:
            continue
        stamp = header_stamp_ns(m.data)
        if stamp is None:
            continue
        items.append(PlayItem(stamp, m.topic, m.type, m.data))
    items.sort(key=lambda item: item.stamp_ns)
    return items


def play_bag(bag: str | Path, rate: float = 1.0, topics: Sequence[str] | None = None,
             wait_subscribers_s: float = 0.0, domain_id: int | None = None,
             foxglove_port: int | None = None) -> dict[str, int]:
    """Publish the bag; returns the messages published per topic (``/clock`` included).
    ``foxglove_port``: also serve each message to Foxglove as it is played
    (:class:`pisc_runs.foxglove_live.LiveServer`, the rig drawn from the bag's
    parameter file)."""
    import rclpy
    from rclpy.context import Context
    from rclpy.duration import Duration
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rosgraph_msgs.msg import Clock

    from pisc_msgs_py.base_node import message_class, qos_profile
    from pisc_msgs_py.convert import stamp_to_msg
    from pisc_msgs_py.topics import CLOCK, CONTROL_QOS, GRAPH_TOPICS

    if rate < 0:
        raise BagError(f"--rate {rate}: expected >= 0 (0: as fast as possible)")
    plan = playback_plan(read_bag_raw(bag, topics))
    if not plan:
        raise BagError(f"{bag}: no stamped message to play"
                       + (f" on {', '.join(topics)}" if topics else ""))
    qos = {t.name: t.qos for t in GRAPH_TOPICS}
    live = None
    if foxglove_port is not None:  # refused (a port in use) before anything is played
        from pisc_runs.foxglove_live import LiveServer
        from pisc_runs.foxglove_node import scene_of

        params = sorted(Path(bag).glob("*.yaml"))
        params = [p for p in params if p.name != "metadata.yaml"]
        if not params:
            raise BagError(f"{bag}: no parameter file to draw the rig from (--foxglove)")
        live = LiveServer(foxglove_port, scene_of(params[0]))
        print(f"serving ws://127.0.0.1:{live.port}", flush=True)
    context = Context()
    rclpy.init(context=context, domain_id=domain_id)
    node = Node("pisc_play", context=context)
    published = {CLOCK.name: 0}
    try:
        clock_pub = node.create_publisher(Clock, CLOCK.name, qos_profile(CLOCK.qos))
        publishers: dict[str, Any] = {}
        for item in plan:
            if item.topic not in publishers:
                publishers[item.topic] = node.create_publisher(
                    message_class(item.type), item.topic,
                    qos_profile(qos.get(item.topic, CONTROL_QOS)))
                published[item.topic] = 0
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        deadline = time.monotonic() + wait_subscribers_s
        while (time.monotonic() < deadline
               and not all(p.get_subscription_count() for p in publishers.values())):
            executor.spin_once(timeout_sec=0.01)
        start_wall = time.monotonic()
        first = plan[0].stamp_ns
        stamp = None
        for item in plan:
            if item.stamp_ns != stamp:
                stamp = item.stamp_ns
                if rate > 0:
                    due = start_wall + (stamp - first) * 1e-9 / rate
                    while (wait := due - time.monotonic()) > 0:
                        time.sleep(min(wait, 0.05))
                clock = Clock()
                clock.clock = stamp_to_msg(stamp)
                clock_pub.publish(clock)
                published[CLOCK.name] += 1
            publishers[item.topic].publish(item.data)
            published[item.topic] += 1
            if live is not None:
                live.publish(item.topic, item.data)
        for publisher in publishers.values():  # reliable subscribers get everything
            publisher.wait_for_all_acked(Duration(seconds=5.0))
    finally:
        node.destroy_node()
        context.try_shutdown()
        if live is not None:
            live.close()
    return published
