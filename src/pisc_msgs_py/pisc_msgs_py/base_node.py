"""What every PISC node shares: typed parameters, topics by name, diagnostics, main().

A node lists the configuration sections it reads (``{"rig": RigParams, ...}``). For
each field the base class declares a ROS parameter with a descriptor (description,
unit) and builds the typed configuration through :func:`pisc_msgs_py.config.from_flat`,
so a bad value is refused with the parameter's name and the broken rule, at start-up and
on every later ``set_parameters``. A valid change is handed to ``on_config``.

**Names.** rclpy keeps a parameter that no node declares and says nothing; PISC refuses
it at start-up, naming it and the closest known name:

* a name aimed at this node (``-p NAME:=VALUE`` on its command line, or a section of a
  parameter file that names the node) must be one the node declares;
* a name every node is handed (a file's ``/**`` section, as the shipped configurations
  are written, or ``parameter_overrides`` from a runner that hands the whole
  configuration to each node) must be declared by this node when it is in one of this
  node's sections, and otherwise be in a section some PISC node reads
  (:data:`pisc_msgs_py.node_params.PISC_SECTIONS`): the node that reads it checks the
  rest (:func:`pisc_msgs_py.node_params.check_overrides`).

:func:`run_node` reads ``--ros-args`` before rclpy does
(:func:`pisc_msgs_py.node_params.parse_ros_arguments`), so a missing or broken
parameter file and a malformed ``-p`` are a one-line refusal, not an rcl traceback.

**Start.** Every node also reads ``start.*``
(:class:`pisc_msgs_py.node_params.StartParams`): before its first subscription it can
wait until its publishers have matched the readers a runner counts for them
(:meth:`PiscNode.await_subscribers`). A thread that destroys a node leaves SCHED_FIFO
first (:func:`leave_realtime`).

**Inputs answer to the graph alone.** Each input topic with a publisher in
``start.publishers`` (:data:`pisc_msgs_py.watchdog.GRAPH_PUBLISHERS` unless set; /clock
too, for a node on simulated time) is guarded (:class:`pisc_msgs_py.watchdog.InputGuard`):
the publisher of the node it names is pinned at the start, and while any other publisher
is matched on any input the node uses no input at all (so the control chain answers
nothing and the plant or the driver applies 0 V), and says so on /diagnostics naming the
publisher and the topic. A message stamped before 0 and a /clock that goes backwards are
refused and said (rclpy's own clock subscription raised on a negative time and ended the
node).

**Shell code said once.** :meth:`PiscNode.parse` turns a message into its core type or
says on ``/diagnostics`` why it was rejected; :meth:`PiscNode.diagnose` publishes a
status and logs an error, at most :class:`pisc_msgs_py.node_support.LogLimit`'s burst of
one kind a window; :meth:`PiscNode.routine_diagnostics` is the cadence of routine
statuses (:data:`DIAGNOSTIC_EVERY`); :class:`ResendCache` answers a sample a lockstep
plant sent again with the messages already published for it.
"""

from __future__ import annotations

import gc
import importlib
import os
import re
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.executors import ExternalShutdownException
from rclpy.experimental import EventsExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.type_support import check_is_valid_msg_type
from rosgraph_msgs.msg import Clock

from pisc_msgs_py import cdr
from pisc_msgs_py import config as cfg
from pisc_msgs_py.convert import (
    MessageError,
    fast_read,
    note_read,
    stamp_from_msg,
    stamp_to_msg,
)
from pisc_msgs_py.node_params import (
    Override,
    StartError,
    StartParams,
    await_entries,
    check_overrides,
    parse_ros_arguments,
)
from pisc_msgs_py.node_support import LogLimit, header_stamp_ns
from pisc_msgs_py.topics import CLOCK, DIAGNOSTICS, QosSpec, Topic
from pisc_msgs_py.watchdog import GRAPH_PUBLISHERS, InputGuard, parse_publishers

__all__ = ["DIAGNOSTIC_EVERY", "NewestStamps", "PiscNode", "ResendCache",
           "freeze_startup_objects", "leave_realtime", "message_class", "qos_profile",
           "raw_subscription", "run_node"]

OK = DiagnosticStatus.OK
WARN = DiagnosticStatus.WARN
ERROR = DiagnosticStatus.ERROR

#: Routine statuses on /diagnostics: the first item, then every this many (1 s at 5 ms).
DIAGNOSTIC_EVERY = 200


def qos_profile(spec: QosSpec) -> QoSProfile:
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=spec.depth,
        reliability=ReliabilityPolicy.RELIABLE if spec.reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=(DurabilityPolicy.TRANSIENT_LOCAL if spec.transient_local
                    else DurabilityPolicy.VOLATILE),
    )


def message_class(type_name: str) -> type:
    """'sensor_msgs/msg/JointState' -> the rclpy message class."""
    package, kind, name = type_name.split("/")
    return getattr(importlib.import_module(f"{package}.{kind}"), name)


def _ros_value(value: Any) -> Any:
    return list(value) if isinstance(value, tuple) else value


class ResendCache:
    """A stage's answer to the newest stamp, to publish again when that stamp comes again.

    A lockstep plant sends a sample again when no voltage answered it; every stage then
    answers the repeated stamp with the messages it already published (the same objects),
    without running its core a second time, so its state advances once per sample.
    """

    def __init__(self) -> None:
        self._stamp_ns: int | None = None
        self._sent: tuple[tuple[Any, Any], ...] = ()  # (publisher, message) pairs

    def resend(self, stamp_ns: int) -> bool:
        """If ``stamp_ns`` is the stamp last answered, publish that answer again and
        return True; otherwise publish nothing and return False."""
        if self._stamp_ns is None or stamp_ns != self._stamp_ns:
            return False
        for publisher, message in self._sent:
            publisher.publish(message)
        return True

    def publish(self, stamp_ns: int, *sent: tuple[Any, Any]) -> None:
        """Publish the answer to ``stamp_ns`` (``(publisher, message)`` pairs, in order)
        and keep it for :meth:`resend`."""
        self._stamp_ns = stamp_ns
        self._sent = sent
        for publisher, message in sent:
            publisher.publish(message)


def raw_subscription(node: Node, topic: Topic, qos: QoSProfile) -> Any:
    """A subscription of ``node`` to ``topic`` that no executor sees: in the ROS graph and
    matched like any other, its messages taken only when asked for
    (``handle.take_message(message_class(topic.type), True)``: ``(CDR bytes, message
    info)`` or None). Destroy it with ``destroy_when_not_in_use()``."""
    msg_type = message_class(topic.type)
    check_is_valid_msg_type(msg_type)  # loads the type support
    with node.handle:
        return _rclpy.Subscription(node.handle, msg_type, topic.name, qos.get_c_qos_profile())


class NewestStamps:
    """The header stamp of the newest message on each of some topics, taken when asked.

    The plant and the driver name the stage of the chain that stopped from the newest
    stamp out of each stage (after a watchdog trip, or a lockstep sample nobody
    answered). A subscription with a callback woke the node for every one of those
    messages, two a cycle, to keep a number read only then; in ``pisc_graph
    --processes`` each is a wake-up of the plant's process on a machine whose two cores
    the whole graph shares. These subscriptions are the node's (in the ROS graph and
    matched like any other) but no executor's: DDS keeps the newest message of each
    (KEEP_LAST 1) and :meth:`read` takes it. A message without a readable header leaves
    its topic's stamp as it was (the stage's own subscribers refuse it).
    """

    def __init__(self, node: Node, named: Sequence[tuple[str, Topic]]) -> None:
        self._readers = []
        for name, topic in named:
            qos = qos_profile(topic.qos)
            qos.history, qos.depth = HistoryPolicy.KEEP_LAST, 1
            self._readers.append((name, raw_subscription(node, topic, qos),
                                  message_class(topic.type), cdr.DECODERS[topic.type]))
        self._newest: dict[str, int] = {}

    def read(self) -> dict[str, int]:
        """Stage name -> stamp [ns] of the newest message taken so far (a stage that has
        published nothing is missing)."""
        for name, handle, msg_type, decode in self._readers:
            taken = handle.take_message(msg_type, True)
            if taken is None:
                continue
            try:
                self._newest[name] = stamp_from_msg(decode(taken[0]).header.stamp)
            except MessageError:
                continue
        return self._newest

    def destroy(self) -> None:
        for _, handle, _, _ in self._readers:
            handle.destroy_when_not_in_use()
        self._readers = []


class PiscNode(Node):
    """Base of the PISC nodes. Subclasses pass their sections and implement ``build``."""

    def __init__(
        self,
        node_name: str,
        sections: Mapping[str, type],
        *,
        parameter_overrides: list[Parameter] | None = None,
        command_line: Sequence[Override] = (),
        **kwargs: Any,
    ) -> None:
        """``command_line``: what :func:`parse_ros_arguments` read from this process's
        arguments (:func:`run_node` passes it); its names aimed at this node must be
        declared by it."""
        super().__init__(node_name, parameter_overrides=parameter_overrides, **kwargs)
        self._newest_stamps: list[NewestStamps] = []
        self._sections = {**dict(sections), "start": StartParams}
        self._inputs_opened = False
        for section, cls in self._sections.items():
            for name, default, unit, description in cfg.describe(cls, section):
                text = f"{description} [{unit}]" if unit else description
                self.declare_parameter(
                    name,
                    _ros_value(default),
                    ParameterDescriptor(description=text, dynamic_typing=True),
                )
        self._check_unknown_overrides(command_line)
        self._diagnostics = self.create_publisher(
            DiagnosticArray, DIAGNOSTICS.name, qos_profile(DIAGNOSTICS.qos))
        self._log_limit = LogLimit()
        # Refuses to start on a bad value: ConfigError propagates out of __init__.
        flat = self.flat_parameters()
        self.config = self.build(flat)
        self._start_params = self.section(flat, "start")
        self._pinned_publishers = {**GRAPH_PUBLISHERS,
                                   **parse_publishers(self._start_params.publishers)}
        self._input_guards: list[InputGuard] = []
        self._clock_ns = -1  # the newest /clock taken (simulated time)
        if getattr(self._time_source, "_clock_sub", None) is not None:
            self._guard_clock()
        self.add_on_set_parameters_callback(self._validate_change)
        self.add_post_set_parameters_callback(self._apply_change)

    # -- configuration ---------------------------------------------------------------

    def build(self, flat: Mapping[str, Any]) -> Any:
        """Typed configuration from dotted parameters; raise ConfigError if invalid."""
        raise NotImplementedError

    def on_config(self, config: Any) -> None:
        """A validated parameter change; the default keeps the new configuration."""
        self.config = config

    def section(self, flat: Mapping[str, Any], name: str) -> Any:
        return cfg.from_flat(self._sections[name], flat, name)

    def flat_parameters(self) -> dict[str, Any]:
        names = [n for s, c in self._sections.items() for n, *_ in cfg.describe(c, s)]
        return {p.name: p.value for p in self.get_parameters(names)}

    def _check_unknown_overrides(self, command_line: Sequence[Override]) -> None:
        """Refuse a name this node would ignore (module docstring, "Names")."""
        # rclpy keeps every value given to this node in _parameter_overrides
        check_overrides(self.get_name(), self.get_fully_qualified_name(),
                        list(self._parameters), self._sections, command_line,
                        getattr(self, "_parameter_overrides", {}) or {})

    def _validate_change(self, params: list[Parameter]) -> SetParametersResult:
        flat = self.flat_parameters()
        flat.update({p.name: p.value for p in params})
        try:
            self.section(flat, "start")  # checked; it matters only at the start
            self._pending = self.build(flat)
        except cfg.ConfigError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _apply_change(self, params: list[Parameter]) -> None:
        self.on_config(self._pending)

    # -- topics and diagnostics -------------------------------------------------------

    def publisher(self, topic: Topic) -> Any:
        return self.create_publisher(message_class(topic.type), topic.name, qos_profile(topic.qos))

    def subscription(self, topic: Topic, callback: Callable[..., None],
                     read: Callable[[Any], Any] | None = None, what: str = "",
                     level: int = ERROR, guarded: bool = True) -> Any:
        """Subscribe ``callback`` to ``topic``. A type :mod:`pisc_msgs_py.cdr` reads is
        taken raw and handed over as a view with the message's fields (no rclpy message
        object is built); bytes it cannot read are refused on /diagnostics
        (``rejected TOPIC: ...``) and the callback is not called.

        With ``read`` (a ``*_from_msg`` of :mod:`pisc_msgs_py.convert`) the callback
        gets the typed value instead; a message it refuses is said as :meth:`parse`
        says it (``rejected WHAT: ...`` at ``level``) and the callback is not called.
        A message of a shape ``read`` read before goes from its bytes to the value
        without a view (:func:`pisc_msgs_py.convert.fast_read`).

        The node's first subscription waits for ``start.await_subscribers``
        (:meth:`await_subscribers`): a node creates its publishers first, so that what it
        publishes in answer to its inputs reaches every reader it was told of."""
        if not self._inputs_opened:
            self._inputs_opened = True
            self.await_subscribers()
        owners = self._pinned_publishers.get(topic.name) if guarded else None
        guard = None if owners is None else self._guard(topic.name, owners)
        decode = cdr.DECODERS.get(topic.type)

        def hand_over(msg: Any, data: bytes | None = None) -> None:
            """``msg`` to the callback, or the value ``read`` makes of it (refused on
            /diagnostics); ``data``, its bytes, shape the next read's fast path."""
            if read is None:
                callback(msg)
                return
            value = self.parse(msg, read, what, level)
            if value is not None:
                if data is not None:
                    note_read(read, data)
                callback(value)

        if decode is None:
            def on_msg(msg: Any) -> None:
                header = getattr(msg, "header", None)
                stamp = None if header is None else stamp_from_msg(header.stamp)
                if self._admit(topic, guard, stamp):
                    hand_over(msg)

            sub = self.create_subscription(
                message_class(topic.type), topic.name, on_msg, qos_profile(topic.qos))
        else:
            def on_bytes(data: bytes) -> None:
                if not self._admit(topic, guard, header_stamp_ns(data)):
                    return
                if read is not None:
                    value = fast_read(read, data)
                    if value is not None:
                        callback(value)
                        return
                try:
                    msg = decode(data)
                except MessageError as exc:
                    self.diagnose(ERROR, f"rejected {topic.name}: {exc}")
                    return
                hand_over(msg, data)

            sub = self.create_subscription(message_class(topic.type), topic.name, on_bytes,
                                           qos_profile(topic.qos), raw=True)
        if guard is not None:
            guard.subscription = sub
        return sub

    # -- inputs that answer to the graph alone ------------------------------------------

    def _guard(self, topic: str, owners: Sequence[str]) -> InputGuard:
        levels = {0: OK, 1: WARN, 2: ERROR}
        guard = InputGuard(self, topic, owners, self.get_name(),
                           lambda level, message, **values: self.diagnose(
                               levels[level], message, **values))
        self._input_guards.append(guard)
        return guard

    def _admit(self, topic: Topic, guard: InputGuard | None, stamp_ns: int | None) -> bool:
        """Whether a message just taken on ``topic`` may be used: stamped at or after 0,
        its topic's publisher the pinned one (``guard``), and no other input of the node
        contested (module docstring, "Inputs answer to the graph alone")."""
        if stamp_ns is not None and stamp_ns < 0:
            self.diagnose(ERROR, f"rejected {topic.name}: stamp {stamp_ns * 1e-9:.9f} s is "
                          "before 0", topic=topic.name)
            return False
        if not self._input_guards:
            return True
        ok = guard.admits(stamp_ns) if guard is not None else True
        for other in self._input_guards:
            if other is not guard:
                other.check()
        return ok and not self.inputs_contested()

    def inputs_contested(self) -> bool:
        """Whether another publisher than the pinned one is on any input of the node."""
        return any(g.pin.intruders for g in self._input_guards)

    def _guard_clock(self) -> None:
        """Replace rclpy's /clock subscription (``use_sim_time``) by one that refuses a
        negative or backwards time and answers to the pinned publisher of /clock alone."""
        source = self._time_source
        qos = source._clock_sub.qos_profile
        self.destroy_subscription(source._clock_sub)
        owners = self._pinned_publishers.get(CLOCK.name)
        guard = None if owners is None else self._guard(CLOCK.name, owners)

        def on_clock(msg: Any) -> None:
            stamp = stamp_from_msg(msg.clock)
            if not self._admit(CLOCK, guard, stamp):
                return
            if stamp < self._clock_ns:
                self.diagnose(ERROR, f"rejected {CLOCK.name}: {stamp * 1e-9:.9f} s goes back "
                              f"from {self._clock_ns * 1e-9:.9f} s; the clock stays there",
                              topic=CLOCK.name)
                return
            self._clock_ns = stamp
            source.clock_callback(msg)

        source._clock_sub = self.create_subscription(Clock, CLOCK.name, on_clock, qos)
        if guard is not None:
            guard.subscription = source._clock_sub

    def await_subscribers(self) -> None:
        """Return once each publication ``start.await_subscribers`` names has matched its
        count of subscribers (DDS matches in its own threads: nothing is spun); raise
        :class:`StartError` after ``start.await_timeout_s``, or ConfigError for a topic
        this node does not publish."""
        if not self._start_params.await_subscribers:
            return
        wanted = await_entries(self._start_params.await_subscribers)
        mine = {p.topic_name: p for p in self.publishers}
        for topic, _ in wanted:
            if topic not in mine:
                raise cfg.ConfigError(
                    f"start.await_subscribers: {topic} is not published by node "
                    f"'{self.get_name()}' (it publishes {', '.join(sorted(mine))})")
        timeout_s = self._start_params.await_timeout_s
        deadline = time.monotonic() + timeout_s
        while True:
            have = {topic: mine[topic].get_subscription_count() for topic, _ in wanted}
            short = [(topic, have[topic], count) for topic, count in wanted
                     if have[topic] < count]
            if not short:
                return
            if time.monotonic() >= deadline:
                raise StartError(
                    f"node '{self.get_name()}': within {timeout_s:g} s (start.await_timeout_s) "
                    + "; ".join(f"{topic} matched {have} of the {count} subscribers of "
                                "start.await_subscribers" for topic, have, count in short))
            time.sleep(0.005)

    def newest_stamps(self, named: Sequence[tuple[str, Topic]]) -> NewestStamps:
        """The newest stamp of each ``(name, topic)``, read when asked
        (:class:`NewestStamps`); destroyed with the node."""
        stamps = NewestStamps(self, named)
        self._newest_stamps.append(stamps)
        return stamps

    def destroy_node(self) -> None:
        for stamps in self._newest_stamps:
            stamps.destroy()
        self._newest_stamps.clear()
        super().destroy_node()

    @staticmethod
    def routine_diagnostics(count: int) -> bool:
        """Whether the ``count``-th item (1 for the first) gets a routine status: the
        first, then every :data:`DIAGNOSTIC_EVERY`-th."""
        return (count - 1) % DIAGNOSTIC_EVERY == 0

    def parse(self, msg: Any, from_msg: Callable[[Any], Any], what: str,
              level: int = ERROR) -> Any:
        """``from_msg(msg)``, or None after saying on /diagnostics why the message was
        rejected (``rejected WHAT: reason`` at ``level``)."""
        try:
            return from_msg(msg)
        except MessageError as exc:
            self.diagnose(level, f"rejected {what}: {exc}")
            return None

    def diagnose(self, level: int, message: str, stamp_ns: int | None = None,
                 **values: Any) -> None:
        """Publish this node's status on /diagnostics (and log errors)."""
        msg = DiagnosticArray()
        msg.header.stamp = (stamp_to_msg(stamp_ns) if stamp_ns is not None
                            else self.get_clock().now().to_msg())
        status = DiagnosticStatus()
        status.level = level
        status.name = f"pisc/{self.get_name()}"
        status.hardware_id = "pisc"
        status.message = message
        status.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
        msg.status = [status]
        self._diagnostics.publish(msg)
        if level == ERROR:
            log, held_back = self._log_limit.admit(message, time.monotonic())
            if held_back:
                self.get_logger().error(held_back)
            if log:
                self.get_logger().error(message)


def freeze_startup_objects() -> None:
    """Exempt what exists now (the imports: rclpy, numpy, numba, scipy; the nodes) from
    the garbage collector's later passes, before a node spins. The messages of every
    cycle trigger collections, and a full one walks the whole heap: one took 641 ms in
    the middle of a 10 s lockstep run in one process (2,001 cycles of 1.8-2.7 ms).
    Cycles made later are still collected."""
    gc.freeze()


def _shutting_down(wait_s: float = 0.5) -> bool:
    """Whether rclpy's context goes down within ``wait_s`` (a signal is being handled)."""
    deadline = time.monotonic() + wait_s
    while rclpy.ok():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def leave_realtime() -> None:
    """The calling thread gives up SCHED_FIFO (or SCHED_RR) for SCHED_OTHER, before it
    destroys nodes. Fast DDS 2.14 waits without sleeping in ``destroy_participant`` for a
    discovery callback in flight (its issue 6513; seen here at 100 % of a core, docs/
    limitations.md); the callback runs in a receive thread of the same priority, and at
    SCHED_FIFO two such waits on the two cores leave it, and every other thread of that
    priority, no turn. On 2026-12-05 two controller processes of a ``--realtime 40`` run
    each held a core so, with Fast DDS's flow-controller thread, for 18 minutes, and
    pisc_graph, at the same priority, never ran to kill them (their stacks were not taken).
    The other threads keep their policy."""
    if not hasattr(os, "sched_getscheduler"):
        return
    if os.sched_getscheduler(0) in (os.SCHED_FIFO, os.SCHED_RR):
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


def run_node(factory: Callable[[], Node], args: list[str] | None = None) -> int:
    """Run one node on an EventsExecutor until shutdown; the shape of ros2/demos' talker.

    A node that refuses its parameters prints why and the process exits with status 2,
    as does a command line rcl cannot read (one line, no traceback).
    """
    try:
        command_line = parse_ros_arguments(sys.argv if args is None else args)
    except cfg.ConfigError as exc:
        print(f"refusing to start: {exc}", file=sys.stderr)
        return 2
    try:
        rclpy.init(args=args)
    except Exception as exc:  # rclpy's RCLError: whatever rcl refuses that we did not
        if type(exc).__name__ != "RCLError":
            raise
        # drop rcl's source locations (", at /project/src/...c:271")
        print("refusing to start: " + re.sub(r", at \S+:\d+", "", str(exc)), file=sys.stderr)
        return 2
    node = None
    try:
        node = factory(command_line=command_line)
        executor = EventsExecutor()
        executor.add_node(node)
        freeze_startup_objects()
        # EventsExecutor.spin() stays in C++ and Python never sees SIGINT or SIGTERM;
        # spinning in slices returns to the interpreter at least every 0.1 s.
        while rclpy.ok():
            try:
                executor.spin_once(timeout_sec=0.1)
            except Exception:
                if not _shutting_down():
                    raise
                # a callback that ran while shutting down could not publish, or the
                # executor woke on the signal's guard condition before the context was
                # down (measured once on SIGINT: pybind11 "Unable to convert call
                # argument"): that is the shutdown, not a fault

    except cfg.ConfigError as exc:
        print(f"refusing to start: invalid parameter: {exc}", file=sys.stderr)
        return 2
    except StartError as exc:
        print(f"not started: {exc}", file=sys.stderr)
        return 1
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        leave_realtime()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0
