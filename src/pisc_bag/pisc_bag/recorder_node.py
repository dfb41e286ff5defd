"""Recorder node: every graph topic, raw, into a rosbag2 MCAP bag, as soon as it arrives.

The recorder runs in a process of its own (:mod:`pisc_bag.record_cli`), so nothing it
does delays the control loop's callbacks; what it must do is keep up, because whatever
it has not yet written when it is killed is lost. So it does not go through an
executor: :meth:`RecorderNode.take` waits on one wait set for any of its subscriptions,
then takes every message that has arrived on every subscription (the serialized CDR
bytes with the DDS message info, no decoding), writes them in the order they were
received (the DDS reception time is each message's log time) and hands them to the
operating system with one flush. A message is thus on its way to the disk about a wait
set's wake-up after DDS received it, and a slow disk delays only the recorder: DDS
keeps what arrives meanwhile.

Subscriptions keep all history (``KEEP_ALL``) with the topic's reliability and
durability, so the recorder never drops what it has taken. A reliable publisher keeps
its last 100 messages (the topic's depth) until the recorder has acknowledged them: a
recorder that falls further behind, or has not yet matched a publisher that already
matched it, loses the older ones. :mod:`pisc_bag.record_cli` reports when it has matched
every publisher (``--ready-file``); the runner starts the graph after that.

A recorder that falls more than 100 messages behind loses the oldest, and a lockstep
graph makes ~1,800 samples a second: with a recorder short of the CPU for more than
55 ms, a bag missed 338 of its 2001 cycles (CI, stop 20). So with ``progress`` (the
recorded topics the graph publishes every sample) the recorder publishes, on
``/pisc/recorder/progress`` (:data:`pisc_msgs_py.topics.RECORDER_PROGRESS`), the oldest
of the newest stamps it has written of each of them, after every ``progress_every``
samples' worth of their messages and when it wakes to nothing; the lockstep plant does
not run more than ``simulation.recorder_lag_samples`` ahead of it. Woken to nothing, it
says the same stamp again every ``resay_after_s``: the stamp that releases a held plant
is then not a single message (the plant's subscription keeps only the newest), so the
run cannot stand still on one that did not reach the plant (in full-suite runs of
2026-12-03 a plant stayed held after a 3 s stop of the recorder until the test's 120 s
timeout, twice; not seen in 8 runs of that test alone beside a CPU hog on 2026-12-04, so
which side lost what is not known). Each topic counts: a
reliable reader delivers a publisher's messages in order, so a message lost on the way
holds back the later ones of its topic until it is sent again, while the others go on
(before 2026-12-03 the voltage alone was followed: a recorder stopped for 3 s then lost
13 and 6 messages of /clock in 2 of 8 one-process runs, and with Fast DDS's data sharing
turned off 1 of /pisc/cart_force in 1 of 6).

**Foreign publishers are marked.** Given the publishers each topic has in the run
(:meth:`RecorderNode.expect_publishers`, ``pisc_record --expect``), the recorder looks at
how many it has matched on each topic it takes messages of; while a topic has more, it
records what arrives as ever, and writes into the bag a status on
``/pisc/recorder/foreign`` (:data:`pisc_msgs_py.topics.FOREIGN`) naming the topic and
its publishers when that starts, and one when it ends with the count of the messages
taken meanwhile (no message says who sent it: all of them are contested).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.qos import HistoryPolicy
from rclpy.serialization import serialize_message

from pisc_bag.bag import BagWriter, header_stamp_ns
from pisc_msgs_py.base_node import message_class, qos_profile
from pisc_msgs_py.convert import clock_to_cdr
from pisc_msgs_py.convert import stamp_to_msg
from pisc_msgs_py.topics import FOREIGN, RECORDER_PROGRESS, Topic

__all__ = ["RecorderNode", "header_stamp_ns", "recording_qos"]

UNNAMED = "a publisher the ROS graph does not name yet"


def recording_qos(topic: Topic) -> Any:
    """The topic's QoS with all history kept: the recorder never drops a sample it got."""
    profile = qos_profile(topic.qos)
    profile.history = HistoryPolicy.KEEP_ALL
    return profile


def _unused(*_: Any) -> None:  # pragma: no cover - messages are taken by RecorderNode.take
    pass


class RecorderNode(Node):
    """Record ``topics`` into ``writer``; ``on_message(topic, data)`` observes arrivals."""

    def __init__(
        self,
        writer: BagWriter,
        topics: Sequence[Topic],
        on_message: Callable[[str, bytes], None] | None = None,
        progress: Sequence[str] = (),
        progress_every: int = 5,
        resay_after_s: float = 1.0,
        **kwargs: Any,
    ) -> None:
        kwargs.setdefault("start_parameter_services", False)
        super().__init__("recorder", **kwargs)
        self._writer = writer
        self._on_message = on_message
        if isinstance(progress, str):
            raise TypeError("progress: a sequence of topic names, not one name")
        for name in progress:
            if name not in {t.name for t in topics}:
                raise ValueError(f"progress: {name} is not a recorded topic")
        if progress_every < 1:
            raise ValueError(f"progress_every = {progress_every}: must be >= 1")
        if not resay_after_s > 0:
            raise ValueError(f"resay_after_s = {resay_after_s}: must be > 0")
        # newest stamp written of each ``progress`` topic
        self._newest_ns: dict[str, int] = dict.fromkeys(progress, -1)
        self._progress_every = progress_every * len(self._newest_ns)
        self._progress_pub = (self.create_publisher(
            message_class(RECORDER_PROGRESS.type), RECORDER_PROGRESS.name,
            qos_profile(RECORDER_PROGRESS.qos)) if progress else None)
        self._said_ns = -1
        self._said_at = 0.0  # time.monotonic() when it was last said
        self._resay_after_s = resay_after_s
        self._unsaid = 0  # messages of ``progress`` written since it was last said
        self.received: dict[str, int] = {t.name: 0 for t in topics}
        self._subs = {
            t.name: self.create_subscription(
                message_class(t.type), t.name, _unused, recording_qos(t), raw=True)
            for t in topics
        }
        self._takes = [(name, sub.handle, sub.msg_type) for name, sub in self._subs.items()]
        self._wait_set = _rclpy.WaitSet(len(self._takes), 0, 0, 0, 0, 0, self.context.handle)
        self._expected: dict[str, int] = {}  # publishers of each topic in the run
        self._own: frozenset[str] = frozenset()  # the run's node names
        # topic -> [messages taken while contested, the publishers marked]
        self._contested: dict[str, list[Any]] = {}
        self._matched: dict[str, int] = {}  # publishers matched when last looked
        self.foreign: list[str] = []  # "TOPIC: publishers" marked in the bag

    def expect_publishers(self, counts: dict[str, int], own: Sequence[str] = ()) -> None:
        """The run's publishers of each recorded topic (a count), and the names of its
        nodes (``own``, not named as foreign): from now on more on a topic are marked in
        the bag (module docstring)."""
        self._expected = {t: n for t, n in counts.items() if t in self._subs}
        self._own = frozenset(own)

    def _others(self, topic: str, matched: int) -> str:
        """The publishers on ``topic`` not of the run's nodes, as the graph names them
        ('' for none: then only more matched than the run has is one, unnamed).

        A publisher the graph does not name yet counts only by the count: discovery lists
        an endpoint before its node's name (the run's own, for 20-80 ms as a node starts)
        and keeps it a moment after the name has gone (as a node ends), so unnamed it is
        foreign only when more are matched than the run has."""
        names = set()
        for i in self.get_publishers_info_by_topic(topic):
            if (i.node_name in self._own or not self._own  # (no names: by the count alone)
                    or i.node_name.startswith("_NODE_NAME_UNKNOWN")):
                continue
            names.add(f"{i.node_namespace.rstrip('/')}/{i.node_name}")
        if not names and matched > self._expected[topic]:
            names.add(UNNAMED)
        return ", ".join(sorted(names))

    def take(self, timeout_s: float) -> int:
        """Wait up to ``timeout_s`` for a message, then take and write every message that
        has arrived; returns how many."""
        wait_set = self._wait_set
        wait_set.clear_entities()
        for _, handle, _ in self._takes:
            wait_set.add_subscription(handle)
        wait_set.wait(round(timeout_s * 1e9))
        batch = []
        for name, handle, msg_type in self._takes:
            while (taken := handle.take_message(msg_type, True)) is not None:
                data, info = taken
                batch.append((info["received_timestamp"], name, data, info["source_timestamp"]))
        if not batch:
            self._say_progress(idle=True)
            return 0
        batch.sort(key=lambda item: item[0])
        if self._expected:
            self._mark_foreign(batch)
        for log_time, name, data, publish_time in batch:
            self._writer.write(name, data, log_time, publish_time, flush=False)
            self.received[name] += 1
        self._writer.flush()
        if self._newest_ns:
            self._note_progress(batch)
        if self._on_message is not None:
            for _, name, data, _ in batch:
                self._on_message(name, data)
        return len(batch)

    def _note_progress(self, batch: list[tuple[int, str, bytes, int]]) -> None:
        """Note the stamps of what ``batch`` (written and flushed) holds of the progress
        topics; say the progress after every ``progress_every`` samples' worth of them."""
        newest = self._newest_ns
        for _, name, data, _ in batch:
            if name in newest:
                stamp = header_stamp_ns(data)
                if stamp is not None:
                    newest[name] = max(newest[name], stamp)
                    self._unsaid += 1
        if self._unsaid >= self._progress_every:
            self._say_progress()

    def _say_progress(self, idle: bool = False) -> None:
        """Publish the oldest of the newest stamps written of each progress topic, once
        every one has been written and when it has moved; ``idle`` (woken to nothing):
        also the same stamp again when it was last said ``resay_after_s`` ago."""
        if not self._newest_ns:
            return
        self._unsaid = 0
        oldest = min(self._newest_ns.values())
        now = time.monotonic()
        if oldest > self._said_ns or (
                idle and self._said_ns >= 0 and now - self._said_at >= self._resay_after_s):
            self._progress_pub.publish(clock_to_cdr(oldest))
            self._said_ns, self._said_at = oldest, now

    def _mark_foreign(self, batch: list[tuple[int, str, bytes, int]]) -> None:
        """Mark in the bag a topic of ``batch`` that has more publishers than the run's,
        and the end of that (module docstring)."""
        counts: dict[str, int] = {}
        for log_time, name, _, _ in batch:
            counts[name] = counts.get(name, 0) + 1
        for name, count in counts.items():
            expected = self._expected.get(name)
            if expected is None:
                continue
            matched = self._subs[name].get_publisher_count()
            first_log = next(item[0] for item in batch if item[1] == name)
            # the graph is asked only when the count moved or while the topic is contested
            who = (self._others(name, matched)
                   if matched != self._matched.get(name) or name in self._contested else "")
            self._matched[name] = matched
            if who:
                state = self._contested.setdefault(name, [0, None])
                if state[1] is None or state[1] == UNNAMED:  # (named once the graph can)
                    if who != state[1]:
                        state[1] = who
                        self._mark(first_log, name, who, matched,
                                   f": the messages of {name} from here on are contested")
                state[0] += count
            elif name in self._contested:
                taken = self._contested.pop(name)[0]
                self._write_mark(first_log, 0, f"{name} has the run's publishers alone again "
                                 f"({taken} messages taken while it had more)", topic=name,
                                 contested_messages=taken)

    def _mark(self, log_time: int, name: str, who: str, matched: int, rest: str) -> None:
        self.foreign.append(f"{name}: {who}")
        self._write_mark(log_time, 2, f"another publisher on {name}: {who} ({matched} "
                         f"matched, the run has {self._expected[name]}){rest}", topic=name,
                         publishers=who)

    def _write_mark(self, log_time: int, level: int, message: str, **values: Any) -> None:
        if FOREIGN.name not in self._writer.counts:
            self._writer.add_topic(FOREIGN)
        msg = DiagnosticArray()
        msg.header.stamp = stamp_to_msg(log_time)
        status = DiagnosticStatus(level=bytes([level]), name="pisc/recorder",
                                  hardware_id="pisc", message=message)
        status.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
        msg.status = [status]
        self._writer.write(FOREIGN.name, serialize_message(msg), log_time, log_time,
                           flush=False)

    def close_marks(self, told: Sequence[tuple[str, str]] = ()) -> None:
        """Before the bag is finished: a topic still contested gets its count, and one
        with another publisher of which nothing came since is marked too (a run stopped
        as that publisher appeared), as is each (topic, publishers) the runner ``told``
        of (it may have seen a publisher this process has not yet discovered)."""
        found = [(name, self._others(name, self._subs[name].get_publisher_count()))
                 for name in self._expected]
        for name, who in [*found, *told]:
            if name not in self._subs or not who or f"{name}: {who}" in self.foreign:
                continue
            marked = self._contested.get(name)
            if marked is None or (marked[1] == UNNAMED and who != UNNAMED):
                self._contested[name] = [0 if marked is None else marked[0], who]
                self._mark(time.time_ns(), name, who,
                           self._subs[name].get_publisher_count(), "")
        for name, (taken, who) in list(self._contested.items()):
            self._write_mark(time.time_ns(), 2, f"{name} still had another publisher when "
                             f"the recording ended ({taken} messages taken while it had "
                             "more)", topic=name, contested_messages=taken, publishers=who)

    def publisher_count(self, topic: str) -> int:
        """Publishers this recorder's subscription of ``topic`` has matched."""
        return self._subs[topic].get_publisher_count()

    @property
    def total_received(self) -> int:
        return sum(self.received.values())

    def close(self) -> None:
        """Finish the bag (indexed, in log-time order, with its metadata)."""
        self._writer.close()
