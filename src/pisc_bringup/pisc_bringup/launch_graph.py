"""The graph a launch file declares, as pisc_graph runs it.

Which nodes run, with which executable, node name, parameter files and parameters, is
the launch file's to say (read by :mod:`pisc_bringup.launch_file`). What a launch file
does not say, the class of each executable, the topics it reads and writes and its part
in the loop, is :data:`NODE_KINDS`. :func:`read_graph` refuses a file whose graph cannot
run (an unknown executable, no source of samples or two, a topic the loop reads that no
node publishes), naming the file and the node, before anything starts. The counts of
publishers and subscribers each topic has in a graph are what the runner and the nodes
wait for before the first sample.
"""

from __future__ import annotations

import importlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter

from pisc_bringup.launch_file import LaunchError, launch_path, read_launch
from pisc_msgs_py.config import ConfigError, load_params_file
from pisc_msgs_py.processes import console_command
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

__all__ = ["NODE_KINDS", "RUN_TOPICS", "SOURCES", "Graph", "GraphNode", "NodeKind",
           "controllers", "expected_publishers", "expected_subscribers", "read_graph",
           "recorded_topics", "ros_parameters"]


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


def expected_publishers(topic: Topic, nodes: Sequence[GraphNode], lockstep: bool) -> int:
    """Publishers ``topic`` has among ``nodes``; /clock has its publisher in lockstep only."""
    if topic is CLOCK and not lockstep:
        return 0
    return sum(topic in n.publishes for n in nodes)


def ros_parameters(flat: dict[str, Any]) -> list[Parameter]:
    """Flat parameters as rclpy Parameters (tuples as lists), for a node's overrides."""
    return [Parameter(k, value=list(v) if isinstance(v, tuple) else v) for k, v in flat.items()]

