"""Recorder node: every graph topic, raw, into a rosbag2 MCAP bag, off the control path.

Subscriptions take the serialized CDR bytes (no decoding) together with the DDS message
info, and hand them to a writer thread through a queue, so a slow disk never delays a
callback of the control loop. rclpy's EventsExecutor cannot deliver message info, so
this node runs on its own SingleThreadedExecutor (see :mod:`pisc_bringup.graph`).

Subscriptions keep all history (``KEEP_ALL``) with the topic's reliability and
durability, so the recorder never drops what it has taken. A reliable publisher keeps
its last 100 messages (the topic's depth) until the recorder has acknowledged them: a
recorder that falls further behind, or has not yet matched a publisher that already
matched it, loses the older ones. :mod:`pisc_bringup.record` reports when it has matched
every publisher (``--ready-file``); the runner starts the graph after that.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Sequence
from typing import Any

from rclpy.node import Node
from rclpy.qos import HistoryPolicy

from pisc_bringup.bag import BagWriter, header_stamp_ns
from pisc_msgs_py.base_node import message_class, qos_profile
from pisc_msgs_py.topics import Topic

__all__ = ["RecorderNode", "header_stamp_ns", "recording_qos"]

_STOP = object()


def recording_qos(topic: Topic) -> Any:
    """The topic's QoS with all history kept: the recorder never drops a sample it got."""
    profile = qos_profile(topic.qos)
    profile.history = HistoryPolicy.KEEP_ALL
    return profile


class RecorderNode(Node):
    """Record ``topics`` into ``writer``; ``on_message(topic, data)`` observes arrivals."""

    def __init__(
        self,
        writer: BagWriter,
        topics: Sequence[Topic],
        on_message: Callable[[str, bytes], None] | None = None,
        **kwargs: Any,
    ) -> None:
        super().__init__("recorder", **kwargs)
        self._writer = writer
        self._on_message = on_message
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self.received: dict[str, int] = {t.name: 0 for t in topics}
        self._subs = {
            t.name: self.create_subscription(
                message_class(t.type), t.name, self._callback(t.name), recording_qos(t),
                raw=True)
            for t in topics
        }
        self._thread = threading.Thread(target=self._write_loop, name="bag-writer", daemon=True)
        self._thread.start()

    def _callback(self, topic: str) -> Callable[[bytes, dict], None]:
        def callback(data: bytes, info: dict) -> None:
            self.received[topic] += 1
            self._queue.put((topic, data, info["received_timestamp"], info["source_timestamp"]))
            if self._on_message is not None:
                self._on_message(topic, data)

        return callback

    def _write_loop(self) -> None:
        while True:
            item = self._queue.get()
            if item is _STOP:
                return
            self._writer.write(*item)

    def publisher_count(self, topic: str) -> int:
        """Publishers this recorder's subscription of ``topic`` has matched."""
        return self._subs[topic].get_publisher_count()

    @property
    def total_received(self) -> int:
        return sum(self.received.values())

    def close(self) -> None:
        """Write what is queued, then finish the bag."""
        self._queue.put(_STOP)
        self._thread.join()
        self._writer.close()
