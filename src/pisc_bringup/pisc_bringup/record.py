"""pisc_record: record graph topics to a rosbag2 MCAP bag until SIGINT or SIGTERM.

    pisc_record --bag DIR [--topic NAME ...]

A process of its own, so recording competes with the control loop for nothing but a
CPU core. On SIGINT or SIGTERM it writes what it has queued, finishes the bag
(summary, footer, metadata.yaml) and prints the message count of every topic.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor

from pisc_bringup.bag import BagError, BagWriter
from pisc_bringup.recorder_node import RecorderNode
from pisc_msgs_py.topics import GRAPH_TOPICS

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="pisc_record", description=__doc__.split("\n\n")[0])
    parser.add_argument("--bag", type=Path, required=True, help="new bag directory")
    parser.add_argument("--topic", action="append", default=[],
                        help="topic to record (default: every topic of the graph)")
    args, ros_args = parser.parse_known_args(argv)
    known = {t.name: t for t in GRAPH_TOPICS}
    unknown = [t for t in args.topic if t not in known]
    if unknown:
        print(f"pisc_record: unknown topic {unknown[0]} (graph topics: {', '.join(known)})",
              file=sys.stderr)
        return 2
    topics = [known[t] for t in args.topic] or list(GRAPH_TOPICS)
    try:
        writer = BagWriter(args.bag, topics)
    except BagError as exc:
        print(f"pisc_record: {exc}", file=sys.stderr)
        return 2
    rclpy.init(args=[sys.argv[0], *ros_args])
    node = RecorderNode(writer, topics)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        while rclpy.ok():
            try:
                executor.spin_once(timeout_sec=0.1)
            except Exception:
                if rclpy.ok():
                    raise
                # interrupted by the shutdown itself (e.g. its wait set): not a failure
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.close()
        node.destroy_node()
        rclpy.try_shutdown()
    for name, count in writer.counts.items():
        print(f"{name} {count}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
