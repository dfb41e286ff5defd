"""The soak's outside observer: a node of its own process, beside the run's graph.

    python -m pisc_bench.soak_observer_node OUT --domain-id N

``pisc_soak --driver --faults`` starts it (:func:`pisc_bench.soak_run.run`) and, after
the run, checks that the bag holds every message it received
(:func:`pisc_bench.soak_figures.observer_check`).
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
from pathlib import Path
from typing import Any

__all__ = ["main", "observe"]


def observe(out: Path, domain_id: int) -> int:
    """The outside observer (a process of its own): KEEP_ALL reliable subscriptions on
    the driver's topics; each received message's header stamp is kept (diagnostics: only
    the driver's, status ``pisc/driver``). On SIGTERM or SIGINT it writes them to ``out``
    as JSON. It says ``loaded`` on standard output once its node exists, subscribes when
    a line comes on standard input, and says ``ready``.

    It subscribes only once told: a reader there before the run's would count among the
    readers the driver waits for (``driver.min_subscribers``, a count), so that the
    driver could publish its first samples before the recorder had matched them (the
    bag then lacked what the observer got: 1 of 4 bench runs in a row, 2026-12-05)."""
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions

    from pisc_bag.bag import header_stamp_ns
    from pisc_msgs_py.base_node import message_class
    from pisc_msgs_py.topics import DIAGNOSTICS, JOINT_STATES, MOTOR_CURRENT

    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
    signal.signal(signal.SIGINT, lambda *_: stop.append(1))
    context = Context()
    rclpy.init(context=context, domain_id=domain_id,
               signal_handler_options=SignalHandlerOptions.NO)
    node = Node("pisc_soak_observer", context=context)
    qos = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.VOLATILE)
    stamps: dict[str, list[int]] = {JOINT_STATES.name: [], MOTOR_CURRENT.name: [],
                                    DIAGNOSTICS.name: []}

    def on_diagnostics(msg: Any) -> None:
        if any(s.name == "pisc/driver" for s in msg.status):
            stamps[DIAGNOSTICS.name].append(
                msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec)

    print("loaded", flush=True)
    sys.stdin.readline()
    for topic in (JOINT_STATES, MOTOR_CURRENT):
        node.create_subscription(
            message_class(topic.type), topic.name,
            lambda data, _k=stamps[topic.name]: _k.append(header_stamp_ns(data) or -1),
            qos, raw=True)
    node.create_subscription(message_class(DIAGNOSTICS.type), DIAGNOSTICS.name,
                             on_diagnostics, qos)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    print("ready", flush=True)
    try:
        while not stop:
            executor.spin_once(timeout_sec=0.1)
    finally:
        tmp = out.with_suffix(".tmp")
        tmp.write_text(json.dumps(stamps))
        tmp.replace(out)
        node.destroy_node()
        context.try_shutdown()
    return 0



def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="soak_observer_node",
                                     description="pisc_soak's outside observer")
    parser.add_argument("out", type=Path, help="the JSON file of the stamps received")
    parser.add_argument("--domain-id", type=int, default=0, help="the run's ROS domain")
    args = parser.parse_args(argv)
    return observe(args.out, args.domain_id)


if __name__ == "__main__":
    raise SystemExit(main())
