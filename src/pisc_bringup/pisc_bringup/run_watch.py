"""What the graph runner watches while the graph runs: the voltages that say how far the
run is (:class:`Progress`; with separate processes through :class:`VoltageTap`), the
recorder's death (:class:`RecorderWatch`), a node process's death and the plant naming
the stage that stopped (:class:`DeathWatch`), the messages the nodes of this process
publish (:func:`count_publications`) and the recorder's acknowledgement of them
(:func:`wait_acknowledged`).
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import rclpy.duration
from rclpy.node import Node
from rclpy.qos import HistoryPolicy
from rclpy.serialization import serialize_message
from rclpy.task import Future

from pisc_bag.recorder_node import header_stamp_ns
from pisc_bringup.children import ExitAlarm, exit_description
from pisc_msgs_py.base_node import message_class, qos_profile, raw_subscription
from pisc_msgs_py.topics import DIAGNOSTICS, VOLTAGE

__all__ = ["DEATH_GRACE_S", "DeathWatch", "Progress", "RecorderWatch", "VoltageTap",
           "count_publications", "wait_acknowledged"]


class Progress:
    """Watches the recorder's voltage stamps for the end of the run."""

    def __init__(self, duration_s: float) -> None:
        self.duration_ns = round(duration_s * 1e9)
        self.first_ns: int | None = None
        self.last_ns: int | None = None
        self.first_wall: float | None = None  # time.monotonic() at the first voltage
        self.first_cpu: float | None = None  # time.process_time() then
        self.loop_s: float | None = None  # wall time from the first voltage to the last
        self.loop_cpu_s: float | None = None  # and this process's CPU time
        self.done = threading.Event()
        self.future = Future()  # for an executor spinning until the end

    def __call__(self, topic: str, data: bytes, wall_s: float | None = None) -> None:
        """A message of ``topic`` (the voltage counts) seen at ``wall_s`` (default: now,
        ``time.monotonic()``; the same clock for every call of a run)."""
        if topic != VOLTAGE.name:
            return
        stamp = header_stamp_ns(data)
        if stamp is None:
            return
        if wall_s is None:
            wall_s = time.monotonic()
        if self.first_ns is None:
            self.first_ns = stamp
            self.first_wall = wall_s
            self.first_cpu = time.process_time()
        self.last_ns = stamp
        if stamp - self.first_ns >= self.duration_ns and not self.done.is_set():
            self.loop_s = wall_s - self.first_wall
            self.loop_cpu_s = time.process_time() - self.first_cpu
            self.done.set()
            self.future.set_result(stamp)

    def end(self) -> None:
        """End the spin now, before the duration (the run stops)."""
        if not self.future.done():
            self.future.set_result(None)

    def run_time(self, at_ns: int | None) -> str:
        """The run's time at the voltage stamped ``at_ns``, as ``at t = S s``."""
        if self.first_ns is None or at_ns is None:
            return "before the first cycle"
        return f"at t = {(at_ns - self.first_ns) * 1e-9:.3f} s"


class VoltageTap:
    """With separate processes: the voltages the runner follows (:class:`Progress`),
    taken on its timer, a period of wall time apart, instead of a callback for each.
    Each voltage woke the runner's process, about 10 % of a core of the two the graph's
    six processes share in a lockstep run (docs/figures.md); now DDS keeps them (the
    newest 1,000: no writer ever waits for this reader) until :meth:`drain`. The first
    and the last voltage's times are their publishers' (``source_timestamp``), so the
    loop's wall time does not depend on when the timer ran."""

    DEPTH = 1000

    def __init__(self, node: Node, progress: Progress) -> None:
        qos = qos_profile(VOLTAGE.qos)
        qos.history, qos.depth = HistoryPolicy.KEEP_LAST, self.DEPTH
        self._handle = raw_subscription(node, VOLTAGE, qos)
        self._type = message_class(VOLTAGE.type)
        self._progress = progress

    def drain(self) -> None:
        while (taken := self._handle.take_message(self._type, True)) is not None:
            data, info = taken
            self._progress(VOLTAGE.name, data, info["source_timestamp"] * 1e-9)

    def destroy(self) -> None:
        self._handle.destroy_when_not_in_use()


class RecorderWatch:
    """Notices that pisc_record died, at once (:class:`ExitAlarm`; with separate
    processes at the next period, on the runner's timer, :class:`VoltageTap`),
    in lockstep and on the wall clock alike, says so at once and ends the spin (the run
    stops; a driver is stopped, which commands 0 V)."""

    def __init__(self, recorder: subprocess.Popen, progress: Progress) -> None:
        self.recorder = recorder
        self.progress = progress
        self.died_at_ns: int | None = None  # the last voltage stamp when it was noticed
        self.returncode: int | None = None

    def check(self) -> None:
        if self.returncode is not None or self.recorder.poll() is None:
            return
        self.returncode = self.recorder.returncode
        self.died_at_ns = self.progress.last_ns
        print(f"pisc_graph: pisc_record {exit_description(self.returncode)} "
              f"{self.run_time()}; stopping the run", file=sys.stderr, flush=True)
        self.progress.end()

    def run_time(self) -> str:
        return self.progress.run_time(self.died_at_ns)


def count_publications(nodes: Sequence[Node],
                       on_voltage: Callable[[bytes], None] | None = None) -> dict[str, int]:
    """Count every message the nodes publish, per topic, from now on (a live dict), and
    hand each voltage command to ``on_voltage`` as it is published (its CDR bytes)."""
    counts: dict[str, int] = {}
    for node in nodes:
        for publisher in node.publishers:
            name = publisher.topic_name
            if name == "/rosout" or name == "/parameter_events":
                continue
            counts.setdefault(name, 0)
            tap = on_voltage if name == VOLTAGE.name else None

            def counted(msg: Any, _publish: Callable[[Any], None] = publisher.publish,
                        _name: str = name, _tap: Callable[[bytes], None] | None = tap) -> None:
                _publish(msg)
                counts[_name] += 1
                if _tap is not None:
                    _tap(msg if isinstance(msg, bytes) else serialize_message(msg))

            publisher.publish = counted  # type: ignore[method-assign]
    return counts


def wait_acknowledged(nodes: Sequence[Node], timeout_s: float) -> bool:
    """Wait until every reliable subscriber (the recorder) acknowledged what was sent.

    In lockstep the graph runs faster than real time and the recorder may trail it by
    seconds; the wait lasts until it has caught up or ``timeout_s`` has passed in all.
    """
    deadline = time.monotonic() + timeout_s
    acked = True
    for node in nodes:
        for publisher in node.publishers:
            left = max(0.0, deadline - time.monotonic())
            acked &= publisher.wait_for_all_acked(rclpy.duration.Duration(seconds=left))
    return acked


# After a node process died: the longest the run waits for the plant (or the driver) to
# name the stage that stopped, on /diagnostics
DEATH_GRACE_S = 2.0


class DeathWatch:
    """End the run once a node process has died and the plant (or the driver) has named
    on /diagnostics the stage that stopped (its watchdog: 0 V from the third sample left
    unanswered, the stage named once it has fallen 8 samples behind; 55 ms on an idle
    machine), or :data:`DEATH_GRACE_S` after the death. (Until 2026-12-03 the run ended
    0.2 s after the death: under the test suite's own load a plant stopped then had said
    nothing, in the bag or to an outside subscriber, 1 of about 20 kills.)"""

    def __init__(self, watcher: Node, children: Sequence[subprocess.Popen],
                 progress: Progress) -> None:
        self.children, self.progress = children, progress
        self.died_at: float | None = None
        self.named_at: float | None = None  # when a status naming a stage last came
        watcher.create_subscription(message_class(DIAGNOSTICS.type), DIAGNOSTICS.name,
                                    self._on_diagnostics, qos_profile(DIAGNOSTICS.qos))
        # after a death, a look every 20 ms for the naming; nothing before it
        self._timer = watcher.create_timer(0.02, self.check)
        self._timer.cancel()
        self.alarm = ExitAlarm(watcher, children, self._on_exit)

    def _on_exit(self) -> None:
        self.check()
        if self.died_at is not None and self._timer.is_canceled():
            self._timer.reset()

    def _on_diagnostics(self, msg: Any) -> None:
        if any(kv.key == "silent" for s in msg.status for kv in s.values):
            self.named_at = time.monotonic()

    def check(self) -> None:
        now = time.monotonic()
        if self.died_at is None:
            if not any(c.poll() is not None for c in self.children):
                return
            self.died_at = now
        # a naming may come before this timer sees the death (it looks every 20 ms); one
        # from before the kill is older than that. 50 ms more: the recorder has it too
        named = self.named_at is not None and self.named_at > self.died_at - 0.1
        if (named and now - self.named_at > 0.05) or now - self.died_at > DEATH_GRACE_S:
            self.progress.end()


