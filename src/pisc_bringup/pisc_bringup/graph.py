"""Run the PISC graph against the simulator, record it, and summarise the run.

    pisc_graph [--config default|thesis|FILE] [--x0 M] [--duration S]
               [--clock lockstep|wall] [--processes] [--executor events|single|multi]
               [--driver PORT] [--realtime PRIORITY] [--bag DIR] [--set NAME=VALUE ...]
               [--plant-config default|thesis|FILE] [--plant-set NAME=VALUE ...]
               [--markers] [--launch FILE] [--tier safe|caught|fast]

**The graph is the launch file's.** Which nodes run, with which executable, node name,
parameter files and parameters, is read from ``pisc_bringup/launch/sim.launch.xml``
(``rig.launch.xml`` with ``--driver``; ``--launch FILE`` names another) by
:mod:`pisc_bringup.launch_file`, with the arguments ``ros2 launch`` would take: the bag's
parameter files (``params``, ``plant_params``), ``clock``, ``use_sim_time``, ``duration``,
what the plant or the driver waits for (``min_subscribers``...: the run's recorder) and
``markers``. What a launch file does not say, the class of each executable and the topics
it reads and writes, is :data:`NODE_KINDS`. A file whose graph cannot run (an unknown
executable, no plant or two, a topic the loop reads that no node publishes) is refused,
naming the file and the node, before anything starts.

The recorder (``pisc_record``) always runs as a process of its own. By default the
plant, estimator, supervisor and current loop run in this process on one
``EventsExecutor`` (the measured choice, see README), each named and parametrised as
the launch file says; ``--processes`` starts each node as its own process through its
console entry point, with the file's parameter files and parameters, as ``ros2 launch``
would. ``--driver PORT`` puts the serial driver (``pisc_driver driver_node``) in the
plant's place, on the rig's port or on the pseudo-terminal of ``pisc_virtual_rig``,
against the wall clock, always in a process of its own (a crash of the controllers'
process leaves it to zero the motor). ``--realtime PRIORITY`` runs this
process and the processes it starts under SCHED_FIFO, as a control computer runs its loop: a
real device does not wait for a loaded machine (README, "Serial driver"). ``--scene``
takes a scene's configuration, overrides, duration and the topics it records
(:mod:`pisc_sim.scene`; ``--record`` replaces that list, and :data:`RUN_TOPICS` are
recorded whatever it says). ``--markers`` also runs the markers node (the rig drawn on
``/pisc/markers`` for RViz and Foxglove, docs/markers.md) and records its topic.

**Model error.** ``--plant-config`` and ``--plant-set`` (and a scene's ``plant:`` block)
give the simulated plant other physical parameters than the controllers assume
(:func:`pisc_sim.configuration.load_run_config`): the plant node gets the plant's
flat parameters, the controllers keep theirs. The bag holds both: ``pisc_params.yaml``
(the controllers', which replay and analysis read) and ``plant_params.yaml`` (what the
plant node got; written for every simulated run). With ``--driver`` the plant is the
device and the plant options are refused.

The plant starts publishing once its subscribers are matched (in one process, once
every controller's are too) and the recorder has matched every publisher (a recorder
that matches late gets only the last 100 messages); a lockstep sample that is lost
anyway is sent again; in lockstep the plant runs at most :data:`RECORDER_LAG_SAMPLES`
samples ahead of the newest sample the recorder has written, so a recorder short of the
CPU pauses the run instead of losing messages (docs/recording.md). With ``--processes
--clock wall`` the plant does not wait for the recorder. The run ends when the voltage
answering the sample at ``--duration`` has been received; the bag is closed, read back
and summarised, and judged by the robustness benchmark's rule (:mod:`pisc_runs.summary`:
each tier, safe, caught and fast, with its rule). Exit status: 0 when the run passes the
tier ``--tier`` names (default ``caught``: caught for good by 8 s and held from 9 s to
the end), 1 when it does not, 2 bad configuration or the graph did not run. An experiment
run (``experiment.kind``) gets no swing-up verdict: the summary says what the experiment
did, and it exits 0 when it ran without a fault, 1 when it faulted.

**Other ends** (:mod:`pisc_bringup.run_guard`): every node answers to the graph's own
publishers alone, and a publisher of any other node on a topic of the graph stops the
run (exit status 3); SIGINT or SIGTERM stop it (130, 143), a serial port that went
away and did not come back within ``--port-retry`` seconds too (4). Each time the
source is stopped first (0 V), then the other nodes, the bag is finished and its summary
printed with what ended the run.
"""

from __future__ import annotations

import argparse
import collections
import ctypes
import gc
import importlib
import math
import os
import select
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import rclpy
import rclpy.duration
from rclpy.context import Context
from rclpy.executors import MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.experimental import EventsExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import HistoryPolicy
from rclpy.serialization import serialize_message
from rclpy.signals import SignalHandlerOptions
from rclpy.task import Future

import yaml

from pisc_bag.bag import BagError, RepairReport, repair_bag
from pisc_bringup.dds import dds_environment
from pisc_bringup.launch_file import LaunchError, launch_path, read_launch
from pisc_sim.configuration import load_run_config, write_params_file
from pisc_bag.recorder_node import header_stamp_ns
from pisc_bringup.run_guard import (
    EXIT_FOREIGN,
    EXIT_PORT_LOST,
    Interrupt,
    RunGuard,
    RunStopped,
    pin_publishers,
)
from pisc_runs.summary import RunSummary, summarise_bag
from pisc_control.supervisor import Supervisor
from pisc_msgs_py.processes import console_command
from pisc_msgs_py.base_node import (
    freeze_startup_objects,
    leave_realtime,
    message_class,
    qos_profile,
    raw_subscription,
)
from pisc_msgs_py.config import ConfigError, load_params_file, parse_overrides
from pisc_msgs_py.topics import (
    CART_FORCE,
    CLOCK,
    CURRENT_SETPOINT,
    DIAGNOSTICS,
    GRAPH_TOPICS,
    JOINT_STATES,
    MARKERS,
    MODE,
    MOTOR_CURRENT,
    PENDULUM_ESTIMATE,
    SIM_STATE,
    STATE,
    VOLTAGE,
    VOLTAGE_SENT,
    Topic,
    graph_topics_named,
)

__all__ = ["CONTROLLERS_PARAMS", "Graph", "GraphNode", "NODE_KINDS", "NodeKind", "PLANT_PARAMS",
           "RUN_TOPICS", "RunOptions", "RunResult", "controllers", "main", "plant_description",
           "read_graph", "recorded_topics", "ros_parameters", "run_graph"]


@dataclass(frozen=True)
class NodeKind:
    """What a launch file does not say about a node, by its package and executable: the
    class pisc_graph instantiates in one process, the topics it reads and writes (for the
    recording and the start-up wait), and its part: ``source`` (the plant or the driver:
    the samples, started last), ``controller`` (the loop), ``observer`` (reads only)."""
    module: str
    cls: str
    subscribes: tuple[Topic, ...]
    publishes: tuple[Topic, ...]
    role: str


NODE_KINDS: dict[tuple[str, str], NodeKind] = {
    ("pisc_plant", "plant_node"): NodeKind(
        "pisc_plant.plant_node", "PlantNode", (VOLTAGE,),
        (JOINT_STATES, MOTOR_CURRENT, SIM_STATE, CLOCK, DIAGNOSTICS), "source"),
    ("pisc_driver", "driver_node"): NodeKind(
        "pisc_driver.driver_node", "DriverNode", (VOLTAGE,),
        (JOINT_STATES, MOTOR_CURRENT, VOLTAGE_SENT, DIAGNOSTICS), "source"),
    ("pisc_control", "estimator_node"): NodeKind(
        "pisc_control.estimator_node", "EstimatorNode", (JOINT_STATES,), (STATE, DIAGNOSTICS),
        "controller"),
    ("pisc_control", "supervisor_node"): NodeKind(
        "pisc_control.supervisor_node", "SupervisorNode", (STATE,),
        (CART_FORCE, MODE, PENDULUM_ESTIMATE, DIAGNOSTICS), "controller"),
    ("pisc_control", "current_loop_node"): NodeKind(
        "pisc_control.current_loop_node", "CurrentLoopNode",
        (CART_FORCE, MOTOR_CURRENT, MODE), (CURRENT_SETPOINT, VOLTAGE, DIAGNOSTICS),
        "controller"),
    # draws the rig for RViz and Foxglove (docs/markers.md), read by no other node
    ("pisc_runs", "markers_node"): NodeKind(
        "pisc_runs.markers_node", "MarkersNode", (SIM_STATE, JOINT_STATES, CART_FORCE, MODE),
        (MARKERS, DIAGNOSTICS), "observer"),
}
# the launch file's source node, by what runs the rig
SOURCES = {False: ("pisc_plant", "plant_node"), True: ("pisc_driver", "driver_node")}


@dataclass(frozen=True)
class GraphNode:
    """A node of the launch file: its name, executable and parameters as the file says,
    and its :class:`NodeKind`."""
    name: str
    package: str
    executable: str
    kind: NodeKind
    param_files: tuple[Path, ...] = ()
    parameters: dict[str, Any] = field(default_factory=dict)

    @property
    def module(self) -> str:
        return self.kind.module

    @property
    def cls(self) -> str:
        return self.kind.cls

    @property
    def subscribes(self) -> tuple[Topic, ...]:
        return self.kind.subscribes

    @property
    def publishes(self) -> tuple[Topic, ...]:
        return self.kind.publishes

    def flat(self) -> dict[str, Any]:
        """Its parameters as ``ros2 launch`` gives them: each file's ``/**`` section and
        its own, in order, then the ``<param name value>``s."""
        flat: dict[str, Any] = {}
        for file in self.param_files:
            flat.update(load_params_file(file, ("/**", self.name, f"/{self.name}")))
        flat.update(self.parameters)
        return flat

    def instantiate(self, context: Context) -> Node:
        """The node in this process, named as the file names it."""
        cls = getattr(importlib.import_module(self.module), self.cls)
        return cls(context=context, parameter_overrides=ros_parameters(self.flat()),
                   cli_args=["--ros-args", "-r", f"__node:={self.name}"])

    def command(self) -> list[str]:
        """The node as a process through its console entry point, as ``ros2 launch`` runs
        it: named as the file names it, with its parameter files and parameters."""
        args = [*console_command(self.executable, self.module), "--ros-args",
                "-r", f"__node:={self.name}"]
        for file in self.param_files:
            args += ["--params-file", str(file)]
        for name, value in self.parameters.items():
            text = str(value).lower() if isinstance(value, bool) else str(value)
            args += ["-p", f"{name}:={text}"]
        return args


@dataclass(frozen=True)
class Graph:
    """The nodes a launch file starts, by part; ``path`` is the file."""
    path: Path
    source: GraphNode
    controllers: tuple[GraphNode, ...]
    observers: tuple[GraphNode, ...]

    @property
    def nodes(self) -> tuple[GraphNode, ...]:
        return (*self.controllers, *self.observers, self.source)


def read_graph(launch: str | Path, args: dict[str, str] | None = None,
               driver: bool = False) -> Graph:
    """The graph a launch file (a path, or ``sim``/``rig``) declares, with ``args``.

    Refused with :class:`ConfigError` naming the file and the node: a node whose
    executable pisc_graph does not know, two nodes of one name, no source or two (the
    plant, or the driver when ``driver``), a topic two nodes publish, or a topic the loop
    reads that no node of the file publishes.
    """
    path = launch_path(str(launch))
    nodes = []
    for n in read_launch(path, args):
        kind = NODE_KINDS.get((n.package, n.executable))
        if kind is None:
            known = ", ".join(f"{p} {e}" for p, e in NODE_KINDS)
            raise LaunchError(f"{path}: node {n.name!r} ({n.package} {n.executable}): "
                              f"pisc_graph does not know this executable (known: {known})")
        nodes.append(GraphNode(n.name, n.package, n.executable, kind, n.param_files,
                               n.parameters))
    names = [n.name for n in nodes]
    twice = next((n for n in names if names.count(n) > 1), None)
    if twice is not None:
        raise LaunchError(f"{path}: two nodes are named {twice!r}: node names are unique")
    want = SOURCES[driver]
    sources = [n for n in nodes if n.kind.role == "source"]
    wrong = [n for n in sources if (n.package, n.executable) != want]
    if wrong:
        raise LaunchError(
            f"{path}: node {wrong[0].name!r} ({wrong[0].package} {wrong[0].executable}) in a "
            f"run {'through the serial driver' if driver else 'of the simulated plant'}, "
            f"whose source of samples is {' '.join(want)}")
    if len(sources) != 1:
        raise LaunchError(
            f"{path}: {'no' if not sources else 'more than one'} node runs {' '.join(want)} "
            f"({', '.join(n.name for n in sources) or 'nodes: ' + ', '.join(names)}): the "
            "graph has one source of samples")
    for topic in GRAPH_TOPICS + (MARKERS,):
        if topic is DIAGNOSTICS:
            continue
        writers = [n.name for n in nodes if topic in n.publishes]
        if len(writers) > 1:
            raise LaunchError(f"{path}: nodes {writers[0]!r} and {writers[1]!r} both publish "
                              f"{topic.name}: a topic of the graph has one publisher")
    for node in nodes:
        if node.kind.role == "observer":  # draws what there is
            continue
        for topic in node.subscribes:
            if not any(topic in n.publishes for n in nodes):
                raise LaunchError(f"{path}: no node publishes {topic.name}, which node "
                                  f"{node.name!r} ({node.package} {node.executable}) reads")
    return Graph(path, sources[0], tuple(n for n in nodes if n.kind.role == "controller"),
                 tuple(n for n in nodes if n.kind.role == "observer"))


def controllers(launch: str | Path = "sim") -> tuple[GraphNode, ...]:
    """The controller nodes the launch file declares (with its default arguments)."""
    return read_graph(launch).controllers


def __getattr__(name: str) -> Any:
    # CONTROLLERS: the controllers of sim.launch.xml, for importers of the former tuple
    # (replay_node); read from the launch file when asked for
    if name == "CONTROLLERS":
        return controllers()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


# The bag's parameter files: the controllers' (replay and analysis read it) and the plant's.
CONTROLLERS_PARAMS = "pisc_params.yaml"
PLANT_PARAMS = "plant_params.yaml"


# What a run records whatever is asked: the lockstep plant starts once a recorder of
# joint_states, the motor current, the true state and /clock is there, and the run's
# summary reads those and the current set-point, voltage and mode.
RUN_TOPICS = (JOINT_STATES, MOTOR_CURRENT, SIM_STATE, CLOCK, CURRENT_SETPOINT, VOLTAGE, MODE)


def recorded_topics(names: Sequence[str] | None) -> tuple[Topic, ...]:
    """The topics a run records: every graph topic (``names`` None), else ``names`` and
    :data:`RUN_TOPICS`, in the graph's order; :class:`ConfigError` for an unknown name."""
    if names is None:
        return tuple(GRAPH_TOPICS)
    try:
        return graph_topics_named([*names, *(t.name for t in RUN_TOPICS)])
    except ConfigError as exc:
        raise ConfigError(f"record: {exc}") from None


def expected_subscribers(topic: Topic, recording: bool, nodes: Sequence[GraphNode]) -> int:
    """Subscribers ``topic`` has among ``nodes`` (and the recorder)."""
    return sum(topic in n.subscribes for n in nodes) + (1 if recording else 0)


def _clock_subscribers(graph: Graph, processes: bool) -> int:
    """Subscribers of /clock the lockstep plant waits for: each controller's clock (rclpy
    subscribes a node with use_sim_time to /clock), the recorder, and, with separate
    processes, this runner, which subscribes once the recorder has matched every
    publisher (in one process nothing runs before the runner spins, after that)."""
    return len(graph.controllers) + 1 + (1 if processes else 0)


def expected_publishers(topic: Topic, nodes: Sequence[GraphNode], lockstep: bool) -> int:
    """Publishers ``topic`` has among ``nodes``; /clock has its publisher in lockstep only."""
    if topic is CLOCK and not lockstep:
        return 0
    return sum(topic in n.publishes for n in nodes)


@dataclass(frozen=True)
class RunOptions:
    config: str = "default"
    overrides: dict[str, Any] = field(default_factory=dict)
    duration_s: float = 10.0
    clock: str = "lockstep"
    processes: bool = False
    executor: str = "events"  # in one process: 'events', 'single' or 'multi'
    bag_dir: Path | None = None
    domain_id: int | None = None
    timeout_s: float | None = None  # wall-clock limit; default scales with duration
    driver_port: str | None = None  # run the serial driver on this port instead of the plant
    record: tuple[str, ...] | None = None  # topics to record (with RUN_TOPICS); None: all
    # model error: the plant's own configuration (None: the controllers') and overrides
    # applied to the plant only, after ``overrides`` (sections the plant reads)
    plant_config: str | None = None
    plant_overrides: dict[str, Any] = field(default_factory=dict)
    markers: bool = False  # also run the markers node and record /pisc/markers
    foxglove_port: int | None = None  # serve the run live to Foxglove on this port
    # the launch file declaring the graph (a path); None: sim.launch.xml, or
    # rig.launch.xml with driver_port
    launch: str | None = None
    # with driver_port: how long a port that went away may take to come back [s]
    port_retry_s: float = 3.0

    @property
    def initial_x_m(self) -> Any:
        """The plant's initial cart position as set on the command line, else 'file'."""
        return self.plant_overrides.get("initial.x_m", self.overrides.get("initial.x_m", "file"))


@dataclass(frozen=True)
class RunResult:
    bag_dir: Path
    summary: RunSummary
    recorded: dict[str, int]  # messages per topic, as pisc_record reported on closing
    wall_s: float
    processes: list[str]  # executables started with --processes
    # messages per topic the nodes of this process published (empty with --processes);
    # with --processes in lockstep, what the samples of the run make (expected_messages)
    published: dict[str, int] = field(default_factory=dict)
    experiment: str = "none"  # experiment.kind: an identification run, not a swing-up
    # wall time from the first voltage this runner saw (its nodes published it, or with
    # --processes it received it) to the one ending the run:
    # the loop itself, without start-up and finishing the bag (lockstep: its speed), and
    # the CPU time this process used meanwhile (all its threads; the nodes in one process)
    loop_s: float | None = None
    loop_cpu_s: float | None = None

    @property
    def missing(self) -> dict[str, int]:
        """Messages per recorded topic that were published and the bag does not hold:
        this process's nodes' own count against the recorder's, or with --processes in
        lockstep a message of each sample topic per sample (:func:`expected_messages`);
        empty for a --processes run on the wall clock, which nothing here counts."""
        return {topic: sent - self.recorded[topic] for topic, sent in self.published.items()
                if topic in self.recorded and self.recorded[topic] < sent}


EXECUTORS = {"events": EventsExecutor, "single": SingleThreadedExecutor,
             "multi": MultiThreadedExecutor}


class GraphError(RuntimeError):
    """The graph did not run to the end; the message says what happened."""


class RecorderDied(GraphError):
    """pisc_record died during the run: the run stopped there, and the bag was finished
    with what had been recorded (``repair``, None if that failed; ``summary`` of the
    recorded part, None if there is none)."""

    def __init__(self, message: str, bag_dir: Path, summary: RunSummary | None,
                 repair: RepairReport | None) -> None:
        super().__init__(message)
        self.bag_dir = bag_dir
        self.summary = summary
        self.repair = repair


def _default_bag_dir(options: RunOptions) -> Path:
    stamp = datetime.now(UTC).strftime("%Y%m%d-%H%M%S-%f")
    x0 = options.initial_x_m
    name = Path(options.config).stem
    return Path("bags") / f"run-{name}-{options.clock}-x0_{x0}-{stamp}"


def plant_description(options: RunOptions) -> str | None:
    """What the plant runs when it differs from the controllers' model, else None.

    E.g. ``default with motor.resistance_ohm=18.2`` or ``thesis``.
    """
    if options.plant_config is None and not options.plant_overrides:
        return None
    name = options.plant_config if options.plant_config is not None else options.config
    if not options.plant_overrides:
        return name
    return f"{name} with " + ", ".join(f"{k}={v}" for k, v in options.plant_overrides.items())


def ros_parameters(flat: dict[str, Any]) -> list[Parameter]:
    """Flat parameters as rclpy Parameters (tuples as lists), for a node's overrides."""
    return [Parameter(k, value=list(v) if isinstance(v, tuple) else v) for k, v in flat.items()]


class _Progress:
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


class _VoltageTap:
    """With separate processes: the voltages the runner follows (:class:`_Progress`),
    taken on its timer, a period of wall time apart, instead of a callback for each.
    Each voltage woke the runner's process, about 10 % of a core of the two the graph's
    six processes share in a lockstep run (docs/figures.md); now DDS keeps them (the
    newest 1,000: no writer ever waits for this reader) until :meth:`drain`. The first
    and the last voltage's times are their publishers' (``source_timestamp``), so the
    loop's wall time does not depend on when the timer ran."""

    DEPTH = 1000

    def __init__(self, node: Node, progress: _Progress) -> None:
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


# how often a runner without pidfds (:class:`_ExitAlarm`) looks at its children
EXIT_POLL_S = 0.05


class _ExitAlarm:
    """Runs ``on_exit`` in the executor's thread as soon as one of ``children`` has
    exited, and nothing while they run: a thread blocks on their pidfds (Linux 5.3) and
    hands ``on_exit`` to the executor (``create_task``, which an EventsExecutor takes
    from any thread) once one is readable. The runner had looked with timers, every
    50 ms at the recorder and every 20 ms at a driver's process: 70 wake-ups a second of
    its main thread and about 200 of rclpy's timer thread, in the process whose CPU is
    the controllers' (issue 16, docs/soak.md). ``on_exit`` finds which child it was
    itself (``Popen.poll``); it may run more than once. Where pidfds are missing it
    looks every :data:`EXIT_POLL_S` on a timer of ``node`` instead."""

    def __init__(self, node: Node, children: Sequence[subprocess.Popen],
                 on_exit: Callable[[], None]) -> None:
        self._on_exit = on_exit
        self._fds: list[int] = []
        self._thread: threading.Thread | None = None
        self._stop_r = self._stop_w = -1
        self._exited = False  # one was gone (reaped) before its pidfd could be opened
        try:
            for child in children:
                try:
                    self._fds.append(os.pidfd_open(child.pid))
                except ProcessLookupError:
                    self._exited = True
        except (AttributeError, OSError):  # no pidfd_open: look on a timer
            self.close()
            node.create_timer(EXIT_POLL_S, on_exit)
            return
        self._stop_r, self._stop_w = os.pipe()

    def start(self, executor: Any) -> None:
        """Watch from now on (an exit before this is seen at once)."""
        if self._stop_r < 0:
            return
        if self._exited:
            executor.create_task(self._on_exit)
        self._thread = threading.Thread(target=self._wait, args=(executor,), daemon=True,
                                        name="pisc_graph_exit_alarm")
        self._thread.start()

    def _wait(self, executor: Any) -> None:
        poller = select.poll()
        for fd in (*self._fds, self._stop_r):
            poller.register(fd, select.POLLIN)
        while True:
            ready = {fd for fd, _ in poller.poll()}
            if self._stop_r in ready:
                return
            for fd in ready:  # (an exited child's pidfd stays readable: once each)
                poller.unregister(fd)
            executor.create_task(self._on_exit)

    def close(self) -> None:
        """Stop watching (before the executor is shut down) and close the descriptors."""
        if self._stop_w >= 0:
            os.write(self._stop_w, b"x")
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        for fd in (*self._fds, self._stop_r, self._stop_w):
            if fd >= 0:
                os.close(fd)
        self._fds, self._stop_r, self._stop_w = [], -1, -1


class _RecorderWatch:
    """Notices that pisc_record died, at once (:class:`_ExitAlarm`; with separate
    processes at the next period, on the runner's timer, :class:`_VoltageTap`),
    in lockstep and on the wall clock alike, says so at once and ends the spin (the run
    stops; a driver is stopped, which commands 0 V)."""

    def __init__(self, recorder: subprocess.Popen, progress: _Progress) -> None:
        self.recorder = recorder
        self.progress = progress
        self.died_at_ns: int | None = None  # the last voltage stamp when it was noticed
        self.returncode: int | None = None

    def check(self) -> None:
        if self.returncode is not None or self.recorder.poll() is None:
            return
        self.returncode = self.recorder.returncode
        self.died_at_ns = self.progress.last_ns
        print(f"pisc_graph: pisc_record {_exit_description(self.returncode)} "
              f"{self.run_time()}; stopping the run", file=sys.stderr, flush=True)
        if not self.progress.future.done():
            self.progress.future.set_result(None)

    def run_time(self) -> str:
        first, last = self.progress.first_ns, self.died_at_ns
        if first is None or last is None:
            return "before the first cycle"
        return f"at t = {(last - first) * 1e-9:.3f} s"


def _exit_description(returncode: int) -> str:
    if returncode < 0:
        try:
            return f"was killed by {signal.Signals(-returncode).name}"
        except ValueError:
            return f"was killed by signal {-returncode}"
    return f"exited with status {returncode}"


def _recorder_died(what: str, bag_dir: Path, period_s: float,
                   recorder_error: str) -> RecorderDied:
    """Finish the bag of a run whose recorder died, as ``pisc_bag repair`` does."""
    lines = [what]
    if recorder_error:
        lines.append(f"pisc_record said: {recorder_error}")
    repair, summary = None, None
    try:
        repair = repair_bag(bag_dir)
    except BagError as exc:
        lines.append(f"`pisc_bag repair {bag_dir}` could not finish the bag: {exc}")
    else:
        lines.append(f"the bag was finished with what was recorded, as `pisc_bag repair "
                     f"{bag_dir}` does: {repair.recovered} messages"
                     + (f"; the recorder's file as found is kept as {repair.backup.name}"
                        if repair.backup is not None else ""))
        try:
            summary = summarise_bag(bag_dir, period_s)
        except BagError as exc:
            lines.append(f"no summary: {exc}")
    return RecorderDied("\n".join(lines), bag_dir, summary, repair)


def _count_publications(nodes: Sequence[Node],
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


def _wait_acknowledged(nodes: Sequence[Node], timeout_s: float) -> bool:
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


def _wait(predicate: Callable[[], bool], timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise GraphError(f"timed out after {timeout_s:.0f} s waiting for {what}")
        time.sleep(0.01)


LAUNCH_FILES = {False: "sim", True: "rig"}

# Lockstep: how many samples the plant may run ahead of the newest sample the recorder
# has written whole (simulation.recorder_lag_samples). With what the recorder reports
# every 5 samples (pisc_record --progress), at most 25 samples' messages (7-8 a sample)
# are on their way to it: well inside each publisher's history of 100 (CONTROL_QOS) and Fast
# DDS's shared-memory port of 512 messages. With 50, a recorder stopped for 1 s froze
# the whole --processes graph in 2 of 13 runs (the plant's timer did not run either):
# most likely a writer waiting for a reader whose port was full (docs/recording.md).
RECORDER_LAG_SAMPLES = 20
# Lockstep: the recorder lets messages gather this long after writing a batch (pisc_record
# --gather), so that it wakes about once a cycle, not for each of a cycle's 7-8 messages
# (docs/figures.md, "Fewer wake-ups a cycle"). Well inside what the plant lets it trail
# (RECORDER_LAG_SAMPLES).
RECORDER_GATHER_S = 0.001
# what a lockstep graph publishes once every sample: the recorder's progress is the
# oldest of the newest it has written of each (a topic whose message DDS sends again
# lags the others). Not /clock: it goes out with every simulation.clock_every-th sample
# only, and as a progress topic it held the plant back once clock_every neared the lag.
SAMPLE_TOPICS = (JOINT_STATES, MOTOR_CURRENT, SIM_STATE, STATE, CART_FORCE,
                 CURRENT_SETPOINT, VOLTAGE)


def expected_messages(duration_s: float, period_s: float,
                      recorded: Sequence[Topic]) -> dict[str, int]:
    """What a lockstep run of ``duration_s`` publishes on the recorded topics that go
    out with every sample (:data:`SAMPLE_TOPICS`): a message for each of the samples
    0 .. duration_s / period_s (a sample sent again is recorded twice, so a bag may hold
    more)."""
    samples = round(duration_s / period_s) + 1
    return {t.name: samples for t in SAMPLE_TOPICS if t in recorded}


def _write_params(directory: Path, flat: dict[str, Any],
                  plant_flat: dict[str, Any] | None) -> dict[str, Path]:
    """The run's parameter files in ``directory``: the controllers' and, for the simulated
    plant, the plant's (:data:`CONTROLLERS_PARAMS`, :data:`PLANT_PARAMS`)."""
    files = {"params": directory / CONTROLLERS_PARAMS}
    write_params_file(files["params"], flat)
    if plant_flat is not None:
        files["plant_params"] = directory / PLANT_PARAMS
        write_params_file(files["plant_params"], plant_flat)
    return files


def _launch_args(options: RunOptions, files: dict[str, Path],
                 run: dict[str, str] | None = None) -> dict[str, str]:
    """The arguments pisc_graph gives the launch file, as ``ros2 launch FILE name:=value``
    would: its parameter files, the clock, markers on request, and ``run`` (what the plant
    or the driver waits for, computed from the graph: :func:`_run_args`; placeholders
    before the graph is known)."""
    args = {name: str(path) for name, path in files.items()}
    args["markers"] = "true" if options.markers else "false"
    if options.driver_port is not None:
        args["port"] = options.driver_port
        args["min_subscribers"] = "0"
    else:
        args["clock"] = options.clock
        args["use_sim_time"] = "true" if options.clock == "lockstep" else "false"
        # the plant stops at the duration itself: a node process is stopped later
        args["duration"] = yaml.safe_dump(float(options.duration_s)).splitlines()[0]
        args.update(min_subscribers="1", min_true_state_subscribers="0",
                    min_clock_subscribers="0")
    args.update(run or {})
    return args


def _run_args(options: RunOptions, graph: Graph) -> dict[str, str]:
    """What the source waits for before its first sample, from the graph's nodes."""
    loop = [*graph.controllers, graph.source]
    if options.driver_port is not None:
        # the driver publishes no sample before the graph's readers, the recorder among
        # them, have matched both sample topics: the bag then holds every sample
        return {"min_subscribers": str(min(expected_subscribers(JOINT_STATES, True, loop),
                                           expected_subscribers(MOTOR_CURRENT, True, loop)))}
    run = {"min_subscribers": str(expected_subscribers(JOINT_STATES, True, loop)),
           "min_true_state_subscribers": "1",
           "min_clock_subscribers": str(_clock_subscribers(graph, options.processes)),
           "recorder_lag_samples": str(RECORDER_LAG_SAMPLES
                                       if options.clock == "lockstep" else 0)}
    if not options.processes:
        # before the plant's first sample run_graph has seen both ends of every match:
        # the controllers' readers are matched where they are created (one participant),
        # the recorder's when it writes its ready file; no settling time is needed
        run["start_settle"] = "0.0"
    return run


def _read_again(first: Graph, options: RunOptions, files: dict[str, Path],
                run: dict[str, str]) -> Graph:
    """The launch file read with the bag's parameter files and the run's arguments; it
    must start the nodes it started on the first reading."""
    graph = read_graph(first.path, _launch_args(options, files, run),
                       options.driver_port is not None)
    if [(n.name, n.executable) for n in graph.nodes] != [
            (n.name, n.executable) for n in first.nodes]:
        raise GraphError(f"{first.path}: starts other nodes with the run's arguments "
                         f"({', '.join(n.name for n in graph.nodes)}) than without "
                         f"({', '.join(n.name for n in first.nodes)})")
    return graph


def run_graph(options: RunOptions) -> RunResult:
    """Run, record and summarise; raises ConfigError, BagError or GraphError.

    Every configuration error is raised before the recorder starts, so a refused run
    leaves no bag directory behind.
    """
    if options.driver_port is not None and (
            options.plant_config is not None or options.plant_overrides):
        raise ConfigError(
            f"--driver {options.driver_port} with --plant-config/--plant-set "
            f"({plant_description(options)}): the plant is the device: start "
            "pisc_virtual_rig with its own parameter file")
    if not math.isfinite(options.duration_s) or options.duration_s <= 0.0:
        raise ConfigError(f"--duration {options.duration_s}: must be a finite number of "
                          "seconds > 0")
    if options.timeout_s is not None and not (math.isfinite(options.timeout_s)
                                              and options.timeout_s > 0.0):
        raise ConfigError(f"timeout_s = {options.timeout_s}: must be a finite number of "
                          "seconds > 0 (None: by the duration)")
    config, flat, plant_params = load_run_config(
        options.config, options.overrides, options.plant_config, options.plant_overrides)
    supervisor = Supervisor(config.supervisor)  # refuses (3.29), an uncontrollable model
    # the K this machine computes goes into the bag's parameter file, so that a replay on
    # a machine whose LAPACK rounds differently uses the same bits (catch.recorded_gain)
    flat = {**flat, "catch.recorded_gain": [float(k) for k in supervisor.gain]}
    if config.supervisor.catch.hold_poles:
        flat["catch.recorded_hold_gain"] = [float(k) for k in supervisor.hold_gain]
    track = config.simulated_plant.track
    if options.driver_port is None and not track.min_m <= config.initial.x_m <= track.max_m:
        raise ConfigError(f"initial.x_m = {config.initial.x_m} lies outside the track "
                          f"(track.min_m .. track.max_m = {track.min_m} .. {track.max_m} m)")
    port = options.driver_port
    if port is not None and not os.access(port, os.R_OK | os.W_OK):
        # refused here, before the recorder makes the bag directory
        problem = "not readable and writable" if os.path.exists(port) else "no such device"
        raise ConfigError(f"driver.port = {port}: {problem}")
    if options.domain_id is not None and not 0 <= options.domain_id <= MAX_DOMAIN_ID:
        raise ConfigError(f"--domain-id {options.domain_id}: must be 0 .. {MAX_DOMAIN_ID} "
                          "(Fast DDS's ports for a larger id are past 65535)")
    if not (math.isfinite(options.port_retry_s) and 0.0 < options.port_retry_s <= 3600.0):
        raise ConfigError(f"--port-retry {options.port_retry_s}: must be a number of seconds "
                          "> 0 and <= 3600")
    if options.clock not in ("lockstep", "wall"):
        raise ConfigError(f"--clock {options.clock!r}: expected 'lockstep' or 'wall'")
    if options.executor not in EXECUTORS:
        raise ConfigError(
            f"--executor {options.executor!r}: expected one of {', '.join(EXECUTORS)}")
    lockstep = options.clock == "lockstep"
    if options.driver_port is not None and lockstep:
        raise ConfigError("--driver runs against the wall clock (the device paces the "
                          "samples): use --clock wall")
    driver = options.driver_port is not None
    bag_dir = options.bag_dir or _default_bag_dir(options)
    if bag_dir.exists() and any(bag_dir.iterdir()):
        raise BagError(f"{bag_dir}: exists and is not empty; not overwriting a bag")
    # Which nodes run is the launch file's to say. Read it now, with the run's parameter
    # files in a scratch directory (a file it refuses leaves no bag), and again once they
    # are in the bag, with what the run computes from the graph (what the plant or the
    # driver waits for).
    with tempfile.TemporaryDirectory(prefix="pisc_graph-launch-") as scratch:
        files = _write_params(Path(scratch), flat, None if driver else plant_params)
        graph = read_graph(options.launch or LAUNCH_FILES[driver],
                           _launch_args(options, files), driver)
    run_args = _run_args(options, graph)
    source = graph.source
    recorded = recorded_topics(options.record) + tuple(
        t for n in graph.observers for t in n.publishes if t is not DIAGNOSTICS)
    timeout = options.timeout_s if options.timeout_s is not None else (
        60.0 + 20.0 * options.duration_s)
    # discovery stays on this machine unless the user asked for more (docs/safety.md);
    # PISC's Fast DDS profile unless the user gives one
    env = dds_environment(dict(os.environ))
    if options.domain_id is not None:
        env["ROS_DOMAIN_ID"] = str(options.domain_id)

    started = time.monotonic()
    # the recorder never runs under --realtime: it must not take the CPU from the loop
    topic_args = [] if options.record is None and not graph.observers else [
        arg for t in recorded for arg in ("--topic", t.name)]
    # the recorder announces in this file that it has matched every publisher of the run
    ready_dir = tempfile.TemporaryDirectory(prefix="pisc_graph-")
    ready = Path(ready_dir.name) / "recorder-ready"
    bridge = None
    if options.foxglove_port is not None:  # refused (a port in use) before the bag exists
        from pisc_runs import foxglove_node

        write_params_file(Path(ready_dir.name) / "foxglove.yaml", flat)
        bridge = _spawn(foxglove_node.command(options.foxglove_port,
                                              Path(ready_dir.name) / "foxglove.yaml"),
                        env, subprocess.PIPE)
        try:
            foxglove_node.wait_serving(bridge, options.foxglove_port,
                                       lambda: _stderr_of(bridge))
        except ConfigError:
            ready_dir.cleanup()
            raise
    publishers = list(graph.nodes)
    if lockstep and not driver:  # the plant waits on its progress (RECORDER_LAG_SAMPLES)
        topic_args += [arg for t in recorded if t in SAMPLE_TOPICS
                       and expected_publishers(t, publishers, lockstep)
                       for arg in ("--progress", t.name)]
        topic_args += ["--gather", str(RECORDER_GATHER_S)]
    marks = Path(ready_dir.name) / "foreign"  # the runner's word to the recorder (run_guard)
    topic_args += [*(arg for n in graph.nodes for arg in ("--own", n.name)),
                   "--marks-file", str(marks)]
    topic_args += ["--ready-file", str(ready), *(
        arg for t in recorded
        for arg in ("--expect", f"{t.name}={expected_publishers(t, publishers, lockstep)}"))]
    # the run's recorder by a name of its own: another subscriber on the domain (a
    # `ros2 topic echo`, another run's recorder) must not pass for it
    recorder_name = f"pisc_record_{os.getpid()}"
    recorder = _spawn([*console_command("pisc_record", "pisc_bag.record"),
                       "--bag", str(bag_dir),
                       *topic_args, "--ros-args", "-r", f"__node:={recorder_name}"], env,
                      subprocess.PIPE, batch_scheduling=True)
    children: list[subprocess.Popen] = []
    interrupt = Interrupt()  # SIGINT, SIGTERM: a clean end (run_guard)
    context = Context()
    rclpy.init(context=context, domain_id=options.domain_id,
               signal_handler_options=SignalHandlerOptions.NO)
    progress = _Progress(options.duration_s)
    watch = _RecorderWatch(recorder, progress)
    watcher = Node("pisc_graph", context=context)

    def end_run() -> None:
        if not progress.future.done():
            progress.future.set_result(None)

    def run_time() -> str:
        first, last = progress.first_ns, progress.last_ns
        if first is None or last is None:
            return "before the first cycle"
        return f"at t = {(last - first) * 1e-9:.3f} s"

    guard = RunGuard(watcher, graph, recorded, lockstep, interrupt, end_run, run_time,
                     options.port_retry_s, options.duration_s,
                     lambda: progress.first_wall if not options.processes else None)

    tap = _VoltageTap(watcher, progress) if options.processes else None
    alarms: list[_ExitAlarm] = []  # started once the executor is there
    if tap is None:
        # The current loop is in this process: its voltages are followed as it publishes
        # them (_count_publications), not through a subscription of the runner's, which
        # was one more delivery and callback each cycle; the recorder's exit is seen as
        # it happens, not looked for (a timer each period cost the process 2-4 % of a
        # core on the wall clock, docs/soak.md)
        alarms.append(_ExitAlarm(watcher, [recorder], watch.check))
    else:
        def on_period() -> None:
            tap.drain()
            watch.check()

        watcher.create_timer(config.loop.period_s, on_period)
    nodes: list[Node] = []
    executor: Any = None
    published: dict[str, int] = {}
    finished = False
    interrupt.install()
    try:
        interrupt.armed = True  # a signal from now until the spin raises KeyboardInterrupt
        if interrupt.signum is not None:
            raise KeyboardInterrupt
        _wait(lambda: _recorder_ready(watcher, recorder, recorded, recorder_name), 30.0,
              "pisc_record to subscribe")
        # a bag says what was simulated, model error or not (plant_params.yaml)
        files = _write_params(bag_dir, flat, None if driver else plant_params)
        graph = _read_again(graph, options, files, run_args)
        # each node's inputs answer to the publishers of the graph alone (run_guard)
        graph = pin_publishers(graph, recorder_name, lockstep)
        source = graph.source
        if options.processes:
            children = _start_processes(graph, watcher, env, recorded,
                                        source_waits=lockstep)
            for node in graph.observers:  # the lockstep plant starts once the recorder
                children.insert(0, _spawn(awaiting(node, (), recorded).command(),  # matched it
                                          env, subprocess.DEVNULL))
            # a node process that dies ends the run at once; the plant's watchdog has
            # zeroed the motor, and _stop below names the process
            alarms.append(_DeathWatch(watcher, children, progress).alarm)
            _wait(lambda: _recorder_matched(recorder, ready), 30.0,
                  "pisc_record to match every publisher")
            if lockstep:  # the plant's last awaited subscriber: it may start now
                watcher.create_subscription(message_class(CLOCK.type), CLOCK.name,
                                            lambda data: None, qos_profile(CLOCK.qos), raw=True)
            # the runner only watches here, but a SingleThreadedExecutor took 37 % of a
            # core doing it (two messages a cycle) from the nodes' two cores; the
            # EventsExecutor 11 % (docs/figures.md)
            executor = EXECUTORS[options.executor](context=context)
        else:
            for node in graph.controllers:
                nodes.append(node.instantiate(context))
            for node in graph.observers:  # before the plant, which stays last: it is
                nodes.append(node.instantiate(context))  # stopped first
            # DDS matches in its own threads: no spinning is needed to wait for it.
            _wait(lambda: _matched(nodes, recorded, graph.controllers), 30.0,
                  "the graph to connect")
            if driver:
                # the driver in a process of its own: a crash of this one (the
                # controllers') leaves it to zero the motor (docs/safety.md)
                children = [_spawn(source.command(), env, subprocess.DEVNULL)]
                alarms.append(_DeathWatch(watcher, children, progress).alarm)
            else:
                nodes.append(source.instantiate(context))
            # nothing is sent before the executor spins: by then the recorder takes it all
            _wait(lambda: _recorder_matched(recorder, ready), 30.0,
                  "pisc_record to match every publisher")
            # The executor spins in the main thread: an EventsExecutor spun from another
            # thread holds the interpreter lock and starves the rest of the process.
            executor = EXECUTORS[options.executor](context=context)
        if not options.processes:
            def on_voltage(data: bytes) -> None:
                progress(VOLTAGE.name, data)

            published = _count_publications(nodes, on_voltage)
        elif lockstep and not driver:
            published = expected_messages(options.duration_s, config.loop.period_s, recorded)
        else:
            published = {}
        # An EventsExecutor kept busy (a lockstep run in this process) does not return at
        # its timeout (test_graph.py): a timer ends the wait at the limit.
        deadline = time.monotonic() + timeout

        def at_the_limit() -> None:
            if time.monotonic() > deadline and not progress.future.done():
                progress.future.set_result(None)

        watcher.create_timer(min(1.0, timeout / 4), at_the_limit)
        for node in [*nodes, watcher]:
            executor.add_node(node)
        for alarm in alarms:
            alarm.start(executor)
        freeze_startup_objects()
        interrupt.armed = False  # while spinning, the guard's timer looks at the signal
        if interrupt.signum is None:
            executor.spin_until_future_complete(progress.future, timeout)
        finished = progress.done.is_set() and not guard.ended
        # the plant stops with the last sample; what is still in flight reaches the recorder
        if watch.returncode is None and not _wait_acknowledged(nodes,
                                                               30.0 + options.duration_s):
            print("pisc_graph: the recorder did not acknowledge every message within "
                  f"{30.0 + options.duration_s:.0f} s; the bag may miss the last ones",
                  file=sys.stderr)
    except KeyboardInterrupt:  # a signal while the run started (Interrupt): a clean end
        pass
    finally:
        interrupt.armed = False
        # what was frozen is garbage again once the run is over (a process that runs
        # graphs one after another, as the tests do, would otherwise keep every frozen
        # object, nodes left undestroyed in reference cycles with their DDS endpoints)
        gc.unfreeze()
        for alarm in alarms:  # (the children's exits below are the run's end, not news)
            alarm.close()
        # the plant first, so the controllers see no sample after their peers stopped
        failures = _stop_all(children)
        leave_realtime()  # before any node or participant is destroyed (base_node)
        if tap is not None:
            tap.destroy()
        # the executor lets go of the nodes' entities while they live (a RecorderDied's
        # traceback kept it alive past the context's shutdown, and freeing it then
        # crashed pisc_graph, SIGSEGV in EventHandler.__exit__, once on 2026-12-04)
        if executor is not None:
            executor.shutdown()
        for node in [*reversed(nodes), watcher]:  # the plant or driver first: 0 V
            node.destroy_node()
        context.try_shutdown()
        guard.tell(marks)  # before the recorder finishes the bag
        recorder_problem, recorder_output = _stop(recorder)
        if bridge is not None:
            _stop(bridge, hang_is_failure=False)
        ready_dir.cleanup()
        interrupt.restore()
    failed = [f for f in failures if f]
    said = "; ".join(x for x in [*failed, recorder_problem.partition(": ")[2].strip()] if x)
    if watch.returncode is not None:
        raise _recorder_died(
            f"pisc_record {_exit_description(watch.returncode)} {watch.run_time()} of the "
            f"run; the run was stopped there"
            f"{' and the rig left at 0 V' if driver else ''}",
            bag_dir, config.loop.period_s, said)
    stopped = _stopped_by(guard, interrupt, run_time(), bag_dir, config.loop.period_s,
                          recorder_problem)
    if stopped is not None:
        raise stopped
    if recorder_problem and finished and not failed:  # it died finishing the bag
        raise _recorder_died(
            f"pisc_record {_exit_description(recorder.returncode)} after the run, while "
            "finishing the bag", bag_dir, config.loop.period_s, said)
    if failed:
        raise GraphError("; ".join(failed))
    if recorder_problem:
        raise GraphError(f"pisc_record failed: {recorder_problem}")
    recorded = recorded_counts(recorder_output)
    if not finished:
        raise GraphError(not_finished(options.duration_s, timeout, progress.last_ns, recorded))
    wall = time.monotonic() - started
    summary = summarise_bag(bag_dir, config.loop.period_s)
    started_as = [Path(c.args[0]).name for c in children]
    result = RunResult(bag_dir, summary, recorded, wall, started_as, dict(published),
                       config.supervisor.experiment.kind, progress.loop_s, progress.loop_cpu_s)
    for topic, lost in result.missing.items():
        print(f"pisc_graph: the bag misses {lost} of the {published[topic]} messages "
              f"published on {topic}", file=sys.stderr)
    return result


# Fast DDS maps a domain to UDP ports 7400 + 250 * id + ...: past 232 they exceed 65535
MAX_DOMAIN_ID = 232


def _stopped_by(guard: RunGuard, interrupt: Interrupt, run_time: str, bag_dir: Path,
                period_s: float, recorder_problem: str) -> RunStopped | None:
    """What ended a run before its duration (:mod:`pisc_bringup.run_guard`), as the
    exception pisc_graph reports, with the summary of the bag (None: nothing ended it)."""
    if interrupt.signum is not None:
        what, status = (f"interrupted {run_time} by {interrupt.name}",
                        128 + interrupt.signum)
    elif guard.foreign:
        what, status = (f"another publisher than the graph's {run_time}: "
                        + "; ".join(guard.foreign), EXIT_FOREIGN)
    elif guard.port_lost is not None:
        what, status = (f"{guard.port_lost} went away and did not come back; the run "
                        f"ended {run_time}", EXIT_PORT_LOST)
    else:
        return None
    summary = None
    lines = [what]
    if recorder_problem:
        lines.append(f"pisc_record: {recorder_problem}")
    try:
        summary = summarise_bag(bag_dir, period_s)
        if guard.foreign:
            summary = replace(summary, foreign=[*summary.foreign, *(
                f for f in guard.foreign if f not in summary.foreign)])
    except BagError as exc:
        lines.append(f"no summary: {exc}")
    return RunStopped("\n".join(lines), status, bag_dir, summary)


def not_finished(duration_s: float, timeout_s: float, last_ns: int | None,
                 recorded: dict[str, int]) -> str:
    """Why a run ended without its last voltage: the newest voltage it saw and what the
    recorder wrote of each topic (a run that stood still waiting for the recorder shows
    the topic it lacked)."""
    wrote = (f"the recorder wrote {', '.join(f'{t} {n}' for t, n in recorded.items())}"
             if recorded else "the recorder said nothing of what it wrote")
    return (f"the run did not reach {duration_s} s within {timeout_s:g} s of wall time "
            f"(last voltage stamp: {last_ns}); {wrote}")


def recorded_counts(output: str) -> dict[str, int]:
    """What pisc_record said it wrote, from its standard output: one line ``TOPIC COUNT``
    for each topic. Other lines are Fast DDS's log, which writes there too (a profile it cannot
    read, say); before 2026-12-03 such a line ended the run with a ValueError."""
    counts = {}
    for line in output.splitlines():
        topic, _, count = line.rpartition(" ")
        if topic.startswith("/") and " " not in topic and count.isdigit():
            counts[topic] = int(count)
    return counts


# After a node process died: the longest the run waits for the plant (or the driver) to
# name the stage that stopped, on /diagnostics
DEATH_GRACE_S = 2.0


class _DeathWatch:
    """End the run once a node process has died and the plant (or the driver) has named
    on /diagnostics the stage that stopped (its watchdog: 0 V from the third sample left
    unanswered, the stage named once it has fallen 8 samples behind; 55 ms on an idle
    machine), or :data:`DEATH_GRACE_S` after the death. (Until 2026-12-03 the run ended
    0.2 s after the death: under the test suite's own load a plant stopped then had said
    nothing, in the bag or to an outside subscriber, 1 of about 20 kills.)"""

    def __init__(self, watcher: Node, children: Sequence[subprocess.Popen],
                 progress: _Progress) -> None:
        self.children, self.progress = children, progress
        self.died_at: float | None = None
        self.named_at: float | None = None  # when a status naming a stage last came
        watcher.create_subscription(message_class(DIAGNOSTICS.type), DIAGNOSTICS.name,
                                    self._on_diagnostics, qos_profile(DIAGNOSTICS.qos))
        # after a death, a look every 20 ms for the naming; nothing before it
        self._timer = watcher.create_timer(0.02, self.check)
        self._timer.cancel()
        self.alarm = _ExitAlarm(watcher, children, self._on_exit)

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
        if ((named and now - self.named_at > 0.05) or now - self.died_at > DEATH_GRACE_S) \
                and not self.progress.future.done():
            self.progress.future.set_result(None)


def _die_with_parent() -> None:  # pragma: no cover - runs in the child before exec
    """Linux: have the kernel send SIGTERM to this child if the runner dies."""
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG = 1
    except OSError:
        pass


def _batch_scheduling() -> None:  # pragma: no cover - runs in the child before exec
    """The recorder's scheduling, whatever the runner's (SCHED_FIFO with --realtime):
    SCHED_BATCH, the normal share of the CPU without preempting a thread it is woken by.
    At SCHED_OTHER its shared-memory receive thread, woken by each message, preempted the
    graph's main thread about six times a cycle on the wall clock (perf sched_switch,
    docs/soak.md); at SCHED_FIFO (inherited) it made the graph miss its periods
    (docs/driver.md)."""
    _die_with_parent()
    try:
        os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))
    except OSError:
        if os.sched_getscheduler(0) != os.SCHED_OTHER:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


STDERR_TAIL_LINES = 200  # of a child's standard error, kept for the message on its failure


def _spawn(args: list[str], env: dict[str, str], stdout: int,
           batch_scheduling: bool = False) -> subprocess.Popen:
    """Start a child; a thread reads its standard error as it comes and keeps the last
    :data:`STDERR_TAIL_LINES` lines. (Read only when stopping it, the pipe filled on a
    long run: 344 lines of the driver's faults in a 10-minute soak blocked its reader
    thread in ``write`` at 163 s, and the run never ended.)"""
    preexec = _batch_scheduling if batch_scheduling else _die_with_parent
    # a process group of its own: a terminal's Ctrl-C reaches the runner alone, which
    # stops the source first (0 V) and then the rest (run_guard)
    child = subprocess.Popen(args, env=env, stdout=stdout, stderr=subprocess.PIPE,
                             preexec_fn=preexec if sys.platform == "linux" else None,
                             process_group=0)
    tail: collections.deque[bytes] = collections.deque(maxlen=STDERR_TAIL_LINES)
    stream, child.stderr = child.stderr, None  # the thread's alone: communicate() skips it
    reader = threading.Thread(target=_drain, args=(stream, tail), daemon=True,
                              name=f"stderr of {Path(args[0]).name}")
    reader.start()
    child.pisc_stderr = (tail, reader)  # type: ignore[attr-defined]
    return child


def _drain(stream: Any, tail: collections.deque[bytes]) -> None:
    with stream:
        for line in iter(stream.readline, b""):
            tail.append(line)


def _stderr_of(child: subprocess.Popen) -> bytes:
    """What a child that has exited wrote on its standard error (the last lines)."""
    tail, reader = child.pisc_stderr  # type: ignore[attr-defined]
    reader.join(timeout=5.0)
    return b"".join(tail)


def _cpu_ticks(pid: int) -> int | None:
    """User + system clock ticks a process has used (Linux), None when unknown."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
        return int(fields[11]) + int(fields[12])
    except (OSError, ValueError, IndexError):
        return None


STOP_PATIENCE_S = 20.0  # a stopping child that uses no CPU for this long is killed
STOP_LIMIT_S = 600.0  # and one still busy after this long


def _stop(child: subprocess.Popen, signalled: bool = False,
          busy_limit_s: float | None = None, hang_is_failure: bool = True) -> tuple[str, str]:
    """SIGTERM a child (SIGINT may be ignored in background jobs; not again when
    ``signalled``) and wait for it: while it keeps using the CPU (a recorder finishing a
    long bag on a loaded machine), up to ``busy_limit_s`` (default :data:`STOP_LIMIT_S`);
    SIGKILL once it used none for :data:`STOP_PATIENCE_S`. A child killed so is a failure,
    or, unless ``hang_is_failure``, a warning on standard error (a node process whose
    work ended with the run).

    Returns (what went wrong or "", its standard output).
    """
    if not signalled and child.poll() is None:
        child.send_signal(signal.SIGTERM)
    limit_s = STOP_LIMIT_S if busy_limit_s is None else busy_limit_s
    started = time.monotonic()
    first = ticks = _cpu_ticks(child.pid)
    killed = False
    while True:
        try:
            out, _ = child.communicate(timeout=STOP_PATIENCE_S)
            break
        except subprocess.TimeoutExpired:
            now = _cpu_ticks(child.pid)
            if (ticks is None or now is None or now == ticks
                    or time.monotonic() - started > limit_s):
                child.kill()
                killed = True
                out, _ = child.communicate()
                break
            ticks = now
    output = out.decode(errors="replace") if out else ""
    if killed and not hang_is_failure:
        busy = ("" if first is None or ticks is None
                else f", {(ticks - first) / os.sysconf('SC_CLK_TCK'):.1f} CPU s meanwhile")
        print(f"pisc_graph: {Path(child.args[0]).name} had not exited "
              f"{time.monotonic() - started:.0f} s after SIGTERM{busy}; killed "
              "(docs/limitations.md: Fast DDS 2.14 can spin without end destroying a "
              "participant)", file=sys.stderr, flush=True)
        return "", output
    if child.returncode not in (0, -signal.SIGTERM):
        return (f"{Path(child.args[0]).name} exited with status {child.returncode}: "
                f"{_stderr_of(child).decode(errors='replace').strip()}"), output
    return "", output


def _stop_all(children: Sequence[subprocess.Popen]) -> list[str]:
    """Stop the run's node processes: the last (the plant or the driver) first, so that
    the controllers see no sample after their peers stopped, then the rest at once (one
    after another, each took 0.16-0.22 s to shut its node down here). Returns what went
    wrong with each, in the order stopped; a controller that has not exited
    :data:`STOP_PATIENCE_S` after SIGTERM is killed, with a warning, not a failure."""
    if not children:
        return []
    *rest, source = children
    failures = [_stop(source)[0]]
    for child in rest:
        if child.poll() is None:
            child.send_signal(signal.SIGTERM)
    # a controller has nothing to finish once the source stopped: one still running after
    # STOP_PATIENCE_S is hung, busy or not (a supervisor spun for minutes in Fast DDS's
    # participant teardown, 2026-12-04), and is killed with a warning
    return failures + [_stop(child, signalled=True, busy_limit_s=STOP_PATIENCE_S,
                             hang_is_failure=False)[0] for child in reversed(rest)]


def _check_recorder(recorder: subprocess.Popen) -> None:
    if recorder.poll() is not None:
        recorder.communicate()
        raise GraphError(f"pisc_record exited: "
                         f"{_stderr_of(recorder).decode(errors='replace').strip()}")


def _recorder_ready(watcher: Node, recorder: subprocess.Popen, recorded: Sequence[Topic],
                    name: str) -> bool:
    """The recorder runs and its own subscriptions (node ``name``) are seen on every
    recorded topic (before any node of the graph exists)."""
    _check_recorder(recorder)
    return all(any(info.node_name == name
                   for info in watcher.get_subscriptions_info_by_topic(t.name))
               for t in recorded)


def _recorder_matched(recorder: subprocess.Popen, ready: Path) -> bool:
    """The recorder has matched every publisher of the run (its ``--ready-file``)."""
    _check_recorder(recorder)
    return ready.exists()


def _matched(nodes: Sequence[Node], recorded: Sequence[Topic],
             controllers: Sequence[GraphNode]) -> bool:
    """Every controller publisher sees its subscribers among the controllers and recorder.

    The plant comes later and waits for its own edges (``simulation.min_subscribers``).
    """
    for node in nodes:
        for publisher in node.publishers:
            topic = next((t for t in GRAPH_TOPICS if t.name == publisher.topic_name), None)
            if topic is None or topic in (DIAGNOSTICS, CLOCK):
                continue
            expected = expected_subscribers(topic, topic in recorded, controllers)
            if publisher.get_subscription_count() < expected:
                return False
    return True


def awaiting(node: GraphNode, counted: Sequence[GraphNode],
             recorded: Sequence[Topic]) -> GraphNode:
    """``node`` with ``start.await_subscribers`` (:class:`pisc_msgs_py.base_node.StartParams`)
    for a process of its own: each of its publications but /diagnostics and /clock waits
    for its subscribers among ``counted``, the recorder when the topic is recorded, and,
    for the voltage, the runner's tap (:class:`_VoltageTap`)."""
    wanted = ",".join(
        f"{t.name}={expected_subscribers(t, t in recorded, counted) + (t is VOLTAGE)}"
        for t in node.publishes if t not in (DIAGNOSTICS, CLOCK))
    if not wanted:
        return node
    return replace(node, parameters={**node.parameters, "start.await_subscribers": wanted})


def _start_processes(graph: Graph, watcher: Node, env: dict[str, str],
                     recorded: Sequence[Topic] = GRAPH_TOPICS,
                     source_waits: bool = False) -> list[subprocess.Popen]:
    """Start the launch file's controllers, each as its own process, and wait until they
    are connected; then start its source (the plant or the driver), last in the list.

    With ``source_waits`` (the lockstep plant, which samples nothing until the runner
    subscribes to /clock, the last subscriber it waits for) the source starts with the
    controllers, so that it loads while they do (from the controllers' connection to the
    recorder's last match took 0.6-3.4 s before, 0.5-0.8 s after, two runs each here on
    2026-12-03); its own subscriptions are not counted as the controllers'."""
    # each waits, before it subscribes, until its publishers have matched the readers
    # counted here: the recorder's too, which DDS may match long after the recorder
    # matched them (docs/recording.md, "Late matches")
    counted = [*graph.controllers, *([graph.source] if source_waits else [])]
    children = [_spawn(awaiting(node, counted, recorded).command(), env, subprocess.DEVNULL)
                for node in graph.controllers]
    if source_waits:
        children.append(_spawn(graph.source.command(), env, subprocess.DEVNULL))

    def subscribers(topic: Topic) -> int:
        return sum(1 for info in watcher.get_subscriptions_info_by_topic(topic.name)
                   if info.node_name != graph.source.name)

    def connected() -> bool:
        for child in children:
            if child.poll() is not None:
                raise GraphError(_stop(child)[0] or f"{child.args[0]} exited")
        for node in graph.controllers:
            for topic in node.publishes:
                if topic is DIAGNOSTICS:
                    continue
                expected = (expected_subscribers(topic, topic in recorded, graph.controllers)
                            + (topic is VOLTAGE))
                if subscribers(topic) < expected:
                    return False
            if watcher.count_publishers(node.publishes[0].name) < 1:
                return False
        return True

    _wait(connected, 60.0, "the node processes to connect")
    if not source_waits:
        children.append(_spawn(graph.source.command(), env, subprocess.DEVNULL))
    return children


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="pisc_graph", description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", default="default",
                        help="named configuration (default, thesis) or a parameter file")
    parser.add_argument("--x0", type=float, help="initial cart position [m]")
    parser.add_argument("--scene", help="a scene (pisc_scene list): its configuration, "
                        "overrides and duration; --config is then ignored")
    parser.add_argument("--duration", type=float,
                        help="run length [s] (default: the scene's, else 10)")
    parser.add_argument("--clock", choices=("lockstep", "wall"),
                        help="lockstep (default) or wall; --driver runs on the wall clock")
    parser.add_argument("--driver", metavar="PORT",
                        help="run the serial driver on PORT (the rig, or the device "
                        "pisc_virtual_rig prints) instead of the simulated plant")
    parser.add_argument("--processes", action="store_true",
                        help="one process per node through the console entry points")
    parser.add_argument("--executor", choices=sorted(EXECUTORS), default="events",
                        help="executor of the nodes in one process (default: events)")
    parser.add_argument("--realtime", type=int, default=0, metavar="PRIORITY",
                        help="SCHED_FIFO priority 1-99 for the graph and its processes "
                        "(needs CAP_SYS_NICE; 0 = normal scheduling)")
    parser.add_argument("--bag", type=Path,
                        help="bag directory (default ./bags/run-<config>-<clock>-x0_<x0>-<time>)")
    parser.add_argument("--domain-id", type=int,
                        help=f"ROS domain id 0-{MAX_DOMAIN_ID} (default: environment)")
    parser.add_argument("--port-retry", type=float, default=3.0, metavar="S",
                        help="with --driver: how long a serial port that went away may "
                        "take to come back before the run ends, exit status 4 (default: "
                        "%(default)s)")
    parser.add_argument("--record", action="append", metavar="TOPIC",
                        help="record this topic (repeatable; default: the scene's list, else "
                        "every topic); the run's own topics are always recorded")
    parser.add_argument("--launch", metavar="FILE",
                        help="the launch file declaring the graph (default: the package's "
                        "sim.launch.xml, or rig.launch.xml with --driver)")
    parser.add_argument("--markers", action="store_true",
                        help="also run the markers node (the rig on /pisc/markers for RViz "
                        "and Foxglove, docs/markers.md) and record its topic")
    parser.add_argument("--foxglove", type=int, nargs="?", const=8765, metavar="PORT",
                        help="serve the run live to Foxglove on ws://127.0.0.1:PORT "
                        "(default 8765; docs/foxglove.md)")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                        help="override a parameter, e.g. --set swing_up.k_v=0.1")
    parser.add_argument("--plant-config", metavar="CONFIG",
                        help="model error: the plant's own configuration (a name or a "
                        "parameter file; default: the controllers')")
    parser.add_argument("--plant-set", action="append", default=[], metavar="NAME=VALUE",
                        help="model error: override a parameter of the plant only (after "
                        "--set), e.g. --plant-set motor.resistance_ohm=18.2")
    parser.add_argument("--tier", choices=("safe", "caught", "fast"), default="caught",
                        help="the benchmark's tier whose verdict is the result and the exit "
                        "status (default: %(default)s: caught for good by 8 s, held from 9 s)")
    args = parser.parse_args(argv)
    # this process's nodes and every process it starts discover on this machine only and
    # use PISC's Fast DDS profile, unless the environment says otherwise (docs/safety.md,
    # docs/architecture.md); before this process's first DDS participant, which reads it
    dds_environment(os.environ)
    try:
        overrides = parse_overrides(args.set)
    except ConfigError as exc:
        parser.error(str(exc))
    plant_overrides: dict[str, Any] = {}
    for item in args.plant_set:
        try:
            plant_overrides.update(parse_overrides([item]))
        except ConfigError:
            parser.error(f"--plant-set {item!r}: expected NAME=VALUE")
    if args.x0 is not None:
        overrides["initial.x_m"] = args.x0
    config, duration = args.config, args.duration
    record = tuple(args.record) if args.record else None
    if args.scene is not None:
        from pisc_sim.scene import load_scene

        try:
            scene = load_scene(args.scene, overrides, plant_overrides)
        except ConfigError as exc:
            print(f"pisc_graph: invalid scene: {exc}", file=sys.stderr)
            return 2
        if not scene.closed_loop:
            print(f"pisc_graph: scene {scene.name} has no controller (controller: "
                  f"{scene.controller}); run it with pisc_scene run", file=sys.stderr)
            return 2
        # the scene's plant: block, then --plant-set
        config, overrides = scene.configuration, scene.overrides
        plant_overrides = scene.plant_overrides
        duration = duration if duration is not None else scene.duration_s
        record = record if record is not None else scene.record
    clock = args.clock or ("wall" if args.driver else "lockstep")
    if args.realtime:
        try:
            # threads and processes started from here on inherit the policy
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.realtime))
        except (OSError, AttributeError) as exc:
            print(f"pisc_graph: --realtime {args.realtime}: cannot use SCHED_FIFO ({exc})",
                  file=sys.stderr)
            return 2
    options = RunOptions(config=config, overrides=overrides,
                         duration_s=duration if duration is not None else 10.0,
                         clock=clock, processes=args.processes,
                         executor=args.executor, bag_dir=args.bag,
                         domain_id=args.domain_id, driver_port=args.driver, record=record,
                         plant_config=args.plant_config, plant_overrides=plant_overrides,
                         markers=args.markers, launch=args.launch,
                         port_retry_s=args.port_retry, foxglove_port=args.foxglove)
    try:
        result = run_graph(options)
    except ConfigError as exc:
        print(f"pisc_graph: invalid configuration: {exc}", file=sys.stderr)
        return 2
    except RecorderDied as exc:
        if exc.summary is not None:
            print(f"bag: {exc.bag_dir} (what was recorded before pisc_record died)")
            print(exc.summary.format(args.tier))
        print("\n".join(f"pisc_graph: {line}" for line in str(exc).splitlines()),
              file=sys.stderr)
        return 2
    except RunStopped as exc:
        if exc.summary is not None:
            print(f"bag: {exc.bag_dir}")
            print(exc.summary.format(args.tier))
        first, *rest = str(exc).splitlines()
        print(f"{'stopped':<23}{first}")
        print("\n".join(f"pisc_graph: {line}" for line in [first, *rest]), file=sys.stderr)
        return exc.status
    except (GraphError, BagError) as exc:
        print(f"pisc_graph: {exc}", file=sys.stderr)
        return 2
    names = {"events": "EventsExecutor", "single": "SingleThreadedExecutor",
             "multi": "MultiThreadedExecutor"}
    mode = ("separate processes" if options.processes
            else f"one process, {names[options.executor]}")
    against = "" if options.driver_port is None else f", serial driver on {options.driver_port}"
    x0 = options.initial_x_m
    plant = plant_description(options)
    print(f"PISC run: config {options.config}, {options.clock} clock, {mode}{against}, "
          f"x0 = {'from file' if x0 == 'file' else x0}"
          f"{'' if plant is None else f'; plant: {plant}'}")
    if result.processes:
        print(f"entry points: {', '.join(result.processes)}")
    loop = ("" if result.loop_s is None else
            f"; the loop: {options.duration_s:g} s in {result.loop_s:.2f} s")
    print(f"bag: {result.bag_dir} ({sum(result.recorded.values())} messages, "
          f"{result.wall_s:.1f} s wall{loop})")
    print(result.summary.format(args.tier, result.experiment))
    if result.experiment != "none":  # nothing is to be caught: the run must not fault
        return 1 if result.summary.faults else 0
    return 0 if result.summary.passed[args.tier] else 1


if __name__ == "__main__":
    raise SystemExit(main())
