"""Regression replay through the real controller nodes, over topics.

The estimator, supervisor and current-loop nodes run in this process with the run's
parameters, as in ``pisc_graph``. A feeder node stands in for the plant: it publishes
the recorded sample k (``/pisc/joint_states`` and ``/pisc/motor/current``), waits for
the voltage stamped k, then publishes sample k+1, so the nodes see exactly the
recorded sequence. A collector records every output the nodes publish; the outputs
are then compared as :func:`pisc_runs.replay.compare` does for the cores.
"""

from __future__ import annotations

import importlib
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import rclpy
from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter

from pisc_bag.bag import bag_topics, read_bag
from pisc_runs.summary import foreign_in_bag
from pisc_sim.configuration import load_graph_config
from pisc_bringup.launch_graph import (
    GraphNode,
    controllers,
    expected_subscribers,
    ros_parameters,
)
from pisc_bringup.run_start import EXECUTORS, GraphError
from pisc_runs.replay import (
    COMPARED_TOPICS,
    Outputs,
    RecordedRun,
    ReplayReport,
    bag_config,
    compare,
    load_recorded,
)
from pisc_msgs_py.base_node import message_class, qos_profile
from pisc_msgs_py.convert import (
    cart_force_from_msg,
    joint_sample_to_msg,
    mode_from_msg,
    motor_sample_from_msg,
    motor_sample_to_msg,
    state_from_msg,
)
from pisc_msgs_py.topics import (
    CART_FORCE,
    CURRENT_SETPOINT,
    JOINT_STATES,
    MODE,
    MOTOR_CURRENT,
    STATE,
    VOLTAGE,
    Topic,
)
from pisc_msgs_py.types import JointSample, MotorSample
from pisc_msgs_py.watchdog import format_publishers

__all__ = ["ReplayFeeder", "replay_nodes"]


class ReplayFeeder(Node):
    """Publishes recorded samples one cycle at a time and collects the nodes' outputs."""

    def __init__(self, run: RecordedRun, **kwargs: Any) -> None:
        super().__init__("pisc_replay", **kwargs)
        self._run = run
        self.next_index = 0
        self.outputs: Outputs = {name: {} for name in COMPARED_TOPICS}
        self._joint_pub = self.create_publisher(
            message_class(JOINT_STATES.type), JOINT_STATES.name, qos_profile(JOINT_STATES.qos))
        self._current_pub = self.create_publisher(
            message_class(MOTOR_CURRENT.type), MOTOR_CURRENT.name,
            qos_profile(MOTOR_CURRENT.qos))
        self._subs = [
            self._collect(STATE, lambda m: ((s := state_from_msg(m)).stamp_ns,
                                            (s.velocity_mps, s.rate_radps))),
            self._collect(CART_FORCE, lambda m: ((s := cart_force_from_msg(m)).stamp_ns,
                                                 (s.force_n,))),
            self._collect(MODE, lambda m: ((s := mode_from_msg(m)).stamp_ns, (s.mode,))),
            self._collect(CURRENT_SETPOINT, lambda m: ((s := motor_sample_from_msg(m)).stamp_ns,
                                                       (s.value,))),
            self._collect(VOLTAGE, self._on_voltage),
        ]

    def _collect(self, topic: Topic, convert: Any) -> Any:
        table = self.outputs[topic.name]

        def callback(msg: Any) -> None:
            stamp, values = convert(msg)
            table.setdefault(stamp, values)

        return self.create_subscription(message_class(topic.type), topic.name, callback,
                                        qos_profile(topic.qos))

    def _on_voltage(self, msg: Any) -> tuple[int, tuple[float]]:
        sample = motor_sample_from_msg(msg)
        if (self.next_index < len(self._run.samples)
                and sample.stamp_ns == self._run.samples[self.next_index - 1][0]):
            self.publish_next()
        return sample.stamp_ns, (sample.value,)

    @property
    def done(self) -> bool:
        return (self.next_index >= len(self._run.samples)
                and self._run.samples[-1][0] in self.outputs[VOLTAGE.name])

    def publish_next(self) -> None:
        stamp, x, theta, current = self._run.samples[self.next_index]
        self.next_index += 1
        self._joint_pub.publish(joint_sample_to_msg(JointSample(stamp, x, theta)))
        self._current_pub.publish(motor_sample_to_msg(MotorSample(stamp, current)))

    def subscribers_matched(self) -> bool:
        return (self._joint_pub.get_subscription_count() >= 1
                and self._current_pub.get_subscription_count() >= 1)


def replay_nodes(bag: str | Path, config: str | None = None,
                 overrides: Mapping[str, Any] | None = None, tolerance: float = 0.0,
                 domain_id: int | None = None, timeout_s: float | None = None,
                 executor_name: str = "events") -> ReplayReport:
    """Regression replay of a bag through the controller nodes over topics.

    ``executor_name`` is as ``pisc_graph --executor``: 'events' (default, as the graph
    runs), 'single' or 'multi'.
    """
    if executor_name not in EXECUTORS:
        raise GraphError(f"executor {executor_name!r}: expected one of {', '.join(EXECUTORS)}")
    _, source = bag_config(bag, config, overrides)  # validates, names the source
    _, flat = load_graph_config(source, overrides)
    run = load_recorded(read_bag(bag), str(bag))
    # the run ends at the last recorded answer; later samples were never answered
    last = max(run.outputs[VOLTAGE.name])
    run = RecordedRun([s for s in run.samples if s[0] <= last], run.outputs, run.notes)
    timeout = timeout_s or 60.0 + 0.02 * len(run.samples)
    context = Context()
    rclpy.init(context=context, domain_id=domain_id)
    nodes: list[Node] = []
    feeder = None
    try:
        # the samples come from the feeder: its publishers are the pinned ones
        fed = format_publishers({JOINT_STATES.name: ("pisc_replay",),
                                 MOTOR_CURRENT.name: ("pisc_replay",)})
        params = [*ros_parameters(flat), Parameter("use_sim_time", value=False),
                  Parameter("start.publishers", value=fed)]
        specs = controllers()  # sim.launch.xml's, as pisc_graph starts them
        for spec in specs:
            cls = getattr(importlib.import_module(spec.module), spec.cls)
            nodes.append(cls(context=context, parameter_overrides=params))
        feeder = ReplayFeeder(run, context=context)
        # as pisc_graph runs them: one EventsExecutor, in this (the main) thread, which
        # handles messages in the order they arrive
        executor = EXECUTORS[executor_name](context=context)
        for node in [*nodes, feeder]:
            executor.add_node(node)
        _spin_until(executor, lambda: _connected(nodes, specs) and feeder.subscribers_matched(),
                    30.0, "the nodes to connect")
        feeder.publish_next()
        _spin_until(executor, lambda: feeder.done, timeout,
                    f"the nodes to answer {len(run.samples)} samples "
                    f"(answered {len(feeder.outputs[VOLTAGE.name])})")
        # a last mode change may still be on its way: let what is in flight arrive
        _spin_for(executor, 0.2)
    finally:
        # the feeder too: a node left undestroyed keeps its publishers in the domain after
        # the context's shutdown, and a second replay's controllers took them for a
        # publisher other than their own feeder
        for node in [*nodes, *([feeder] if feeder is not None else [])]:
            node.destroy_node()
        context.try_shutdown()
    report = compare(run, feeder.outputs, tolerance, str(bag), "nodes", bag_topics(bag))
    report.foreign.extend(foreign_in_bag(bag))
    changed = ", ".join(f"{k}={v}" for k, v in (overrides or {}).items())
    report.notes.append(f"configuration: {source}" + (f" with {changed}" if changed else ""))
    return report


def _connected(nodes: list[Node], specs: Sequence[GraphNode]) -> bool:
    """Every controller output reaches its subscribers among the controllers and the feeder."""
    for node in nodes:
        for publisher in node.publishers:
            topic = next((t for t in (STATE, CART_FORCE, MODE, CURRENT_SETPOINT, VOLTAGE)
                          if t.name == publisher.topic_name), None)
            if topic is None:
                continue
            if publisher.get_subscription_count() < expected_subscribers(topic, True, specs):
                return False
    return True


def _spin_for(executor: Any, seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        executor.spin_once(timeout_sec=0.01)


def _spin_until(executor: Any, predicate: Any, timeout_s: float,
                what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise GraphError(f"timed out after {timeout_s:.0f} s waiting for {what}")
        executor.spin_once(timeout_sec=0.05)

