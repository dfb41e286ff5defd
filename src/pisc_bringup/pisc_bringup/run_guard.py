"""How a pisc_graph run ends when it is not by its duration: a foreign publisher, a
signal, a serial port that went away (docs/safety.md, "Every end is a clean end").

* :func:`pin_publishers`: every node of the graph told which node publishes each of its
  inputs (``start.publishers``), as the launch file names them: each node pins those
  publishers at the start and uses nothing from any other
  (:class:`pisc_msgs_py.watchdog.InputGuard`).
* :class:`RunGuard`: the runner's own watch, on its timer and on /diagnostics: any
  publisher on a topic of the graph that is not the graph's (the runner pins them as the
  nodes do, /clock and /diagnostics included) ends the run at once (0 V: the plant or the
  driver is stopped first), named; so do SIGINT and SIGTERM (:class:`Interrupt`), and a
  serial port the driver says is gone and that has not come back within
  ``port_retry_s`` (nor before the run's duration is over).
* :class:`RunStopped`: what ended the run, with the exit status pisc_graph gives it
  (:data:`EXIT_FOREIGN`, :data:`EXIT_PORT_LOST`, 128 + the signal's number).
"""

from __future__ import annotations

import signal
import sys
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import replace
from pathlib import Path
from typing import Any

from pisc_msgs_py.base_node import message_class, qos_profile
from pisc_msgs_py.topics import CLOCK, DIAGNOSTICS, RECORDER_PROGRESS, Topic
from pisc_msgs_py.watchdog import PublisherPin, format_publishers, listed_publishers

__all__ = ["EXIT_FOREIGN", "EXIT_PORT_LOST", "Interrupt", "RunGuard", "RunStopped",
           "expected_publishers_of", "pin_publishers"]

EXIT_FOREIGN = 3  # another publisher than the graph's was on a topic of the graph
EXIT_PORT_LOST = 4  # the serial port went away and did not come back in time
GUARD_PERIOD_S = 0.05  # how often the runner looks at the graph's topics and for a signal


class RunStopped(RuntimeError):
    """The run was ended before its duration, by ``cause`` (the message says what and
    when); the bag was finished, ``summary`` is what it holds (None: nothing to
    summarise), ``status`` the exit status."""

    def __init__(self, message: str, status: int, bag_dir: Path, summary: Any = None) -> None:
        super().__init__(message)
        self.status, self.bag_dir, self.summary = status, bag_dir, summary


def expected_publishers_of(graph: Any, topics: Iterable[Topic], lockstep: bool,
                           ) -> dict[str, tuple[str, ...]]:
    """The node(s) of ``graph`` that publish each of ``topics`` (every node on
    /diagnostics; the plant on /clock in lockstep, nobody on the wall clock); a topic
    with none has an empty tuple: any publisher on it is foreign."""
    out = {}
    for topic in topics:
        names = tuple(n.name for n in graph.nodes if topic in n.publishes)
        if topic is CLOCK and not lockstep:
            names = ()
        out[topic.name] = names
    return out


def pin_publishers(graph: Any, recorder: str, lockstep: bool) -> Any:
    """``graph`` with ``start.publishers`` set on every node: the node that publishes
    each topic it reads (and /clock on simulated time, the run's recorder's progress
    for the lockstep plant), by the launch file's names."""
    topics = {t for n in graph.nodes for t in n.publishes}
    owners = expected_publishers_of(graph, topics, lockstep)

    def pinned(node: Any) -> Any:
        mine = {t.name: owners[t.name] for t in node.subscribes if owners.get(t.name)}
        if lockstep and node is not graph.source and owners.get(CLOCK.name):
            mine[CLOCK.name] = owners[CLOCK.name]
        if lockstep and node is graph.source:
            mine[RECORDER_PROGRESS.name] = (recorder,)
        if not mine:
            return node
        return replace(node, parameters={**node.parameters,
                                         "start.publishers": format_publishers(mine)})

    return replace(graph, source=pinned(graph.source),
                   controllers=tuple(pinned(n) for n in graph.controllers),
                   observers=tuple(pinned(n) for n in graph.observers))


class Interrupt:
    """SIGINT and SIGTERM, noted: :attr:`signum` is the first one. While :attr:`armed`
    (the run is starting: waits in plain Python) a signal raises :class:`KeyboardInterrupt`
    at once; while the executor spins the runner's timer looks at :attr:`signum` (a
    handler must not touch the executor's future: it may run inside it)."""

    def __init__(self) -> None:
        self.signum: int | None = None
        self.at: float | None = None  # time.monotonic() of the first signal
        self.armed = False
        self._previous: dict[int, Any] = {}

    def install(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return  # (signals reach the main thread only; a caller there handles them)
        for signum in (signal.SIGINT, signal.SIGTERM):
            self._previous[signum] = signal.signal(signum, self._handle)

    def restore(self) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        self._previous.clear()

    def _handle(self, signum: int, _frame: Any) -> None:
        if self.signum is None:
            self.signum, self.at = signum, time.monotonic()
        if self.armed:
            self.armed = False
            raise KeyboardInterrupt

    @property
    def name(self) -> str:
        return signal.Signals(self.signum).name if self.signum else ""


class RunGuard:
    """The runner's watch over the graph (module docstring): ``end()`` is called once
    the run must stop; :attr:`foreign` names what was found, :attr:`port_lost` the port
    that did not come back."""

    def __init__(self, watcher: Any, graph: Any, topics: Iterable[Topic], lockstep: bool,
                 interrupt: Interrupt, end: Callable[[], None], run_time: Callable[[], str],
                 port_retry_s: float = 3.0, duration_s: float = 0.0,
                 first_wall: Callable[[], float | None] = lambda: None) -> None:
        self.watcher, self.interrupt, self._end, self._run_time = (
            watcher, interrupt, end, run_time)
        self.port_retry_s, self.duration_s, self._first_wall = (
            port_retry_s, duration_s, first_wall)
        names = [t for t in topics]
        if DIAGNOSTICS not in names:
            names.append(DIAGNOSTICS)
        if CLOCK not in names:
            names.append(CLOCK)
        owners = expected_publishers_of(graph, names, lockstep)
        self._pins = {name: (PublisherPin(o) if o else None) for name, o in owners.items()}
        self._counts = dict.fromkeys(owners, -1)
        self.foreign: list[str] = []  # "TOPIC: NODE (...)" for each one found
        self.port_lost: str | None = None  # the port that did not come back
        self._lost: tuple[str, float] | None = None  # (port, time.monotonic()) while gone
        self.ended = False
        watcher.create_subscription(message_class(DIAGNOSTICS.type), DIAGNOSTICS.name,
                                    self._on_diagnostics, qos_profile(DIAGNOSTICS.qos))
        watcher.create_timer(GUARD_PERIOD_S, self.check)

    def _say(self, text: str) -> None:
        print(f"pisc_graph: {text}", file=sys.stderr, flush=True)

    def _stop(self) -> None:
        if not self.ended:
            self.ended = True
            self._end()

    def _found(self, topic: str, who: str, said_by: str = "") -> None:
        entry = f"{topic}: {who}"
        if entry in self.foreign:
            return
        self.foreign.append(entry)
        by = f" (named by {said_by})" if said_by else ""
        self._say(f"another publisher on {topic}: {who}{by} {self._run_time()}; only the "
                  "graph's own publishers may be on its topics: the run is stopped (0 V)")
        self._stop()

    def check(self) -> None:
        """The timer: a signal, the topics' publishers, a port gone for too long."""
        if self.interrupt.signum is not None and not self.ended:
            self._say(f"{self.interrupt.name}: stopping the run {self._run_time()} (0 V first)")
            self._stop()
        for topic, pin in self._pins.items():
            count = self.watcher.count_publishers(topic)
            if count == self._counts[topic] and (pin is None or not (pin.intruders
                                                                    or pin.pending)):
                continue
            self._counts[topic] = count
            listed = listed_publishers(self.watcher, topic)
            if pin is None:
                who = [e.fully_qualified for e in listed]
            else:
                pin.look(count, listed)
                who = [i for i in pin.intruders if i not in PublisherPin.PLACEHOLDERS]
            if who:
                self._found(topic, ", ".join(who))
        if self._lost is not None and not self.ended:
            port, since = self._lost
            limit = since + self.port_retry_s
            first = self._first_wall()
            if first is not None and self.duration_s:
                limit = min(limit, max(since, first + self.duration_s))
            if time.monotonic() >= limit:
                self.port_lost = port
                self._say(f"{port} did not come back within {time.monotonic() - since:.1f} s "
                          f"(--port-retry {self.port_retry_s:g}): the run is stopped")
                self._stop()

    def tell(self, path: Path) -> None:
        """Write what was found for the recorder (``pisc_record --marks-file``): it may
        not have discovered a publisher the runner saw before the run stopped."""
        if self.foreign:
            path.write_text("".join(f"{entry.replace(': ', chr(9), 1)}\n"
                                    for entry in self.foreign))

    def _on_diagnostics(self, msg: Any) -> None:
        for status in msg.status:
            level = status.level[0] if isinstance(status.level, bytes) else int(status.level)
            values = {kv.key: kv.value for kv in status.values}
            node = "/" + status.name.partition("/")[2]
            intruders = values.get("intruders", "")
            named = [i for i in intruders.split(", ")
                     if i and i not in PublisherPin.PLACEHOLDERS]
            if level == 2 and named and "topic" in values:
                self._found(values["topic"], ", ".join(named), node)
            if level == 2 and named and "topic" not in values:  # the command topic
                self._found(_command_topic(status.message), ", ".join(named), node)
            if values.get("link") == "lost" and self._lost is None:
                self._lost = (values.get("port", "?"), time.monotonic())
                self._say(f"{values.get('port')} went away {self._run_time()}: the rig "
                          "cannot be sent 0 V (its firmware's watchdog zeroes the motor); "
                          f"retrying for up to {self.port_retry_s:g} s")
            elif values.get("link") == "reopened" and self._lost is not None:
                self._say(f"{values.get('port')} is back after "
                          f"{time.monotonic() - self._lost[1]:.1f} s")
                self._lost = None


def _command_topic(message: str) -> str:
    """The topic of a plant's or driver's ``another publisher on TOPIC: ...``."""
    head = message.partition(":")[0]
    return head.rpartition(" ")[2] or "the command topic"
