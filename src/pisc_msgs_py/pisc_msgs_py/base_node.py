"""What every PISC node shares: typed parameters, topics by name, diagnostics, main().

A node lists the configuration sections it reads (``{"rig": RigParams, ...}``). For
each field the base class declares a ROS parameter with a descriptor (description,
unit), checks that the parameter file does not set unknown names in those sections,
and builds the typed configuration through :func:`pisc_msgs_py.config.from_flat`, so
a bad value is refused with the parameter's name and the broken rule, at start-up and
on every later ``set_parameters``. A valid change is handed to ``on_config``.
"""

from __future__ import annotations

import importlib
import sys
import time
from collections.abc import Callable, Mapping
from typing import Any

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.executors import ExternalShutdownException
from rclpy.experimental import EventsExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from pisc_msgs_py import config as cfg
from pisc_msgs_py.convert import stamp_to_msg
from pisc_msgs_py.topics import DIAGNOSTICS, QosSpec, Topic

__all__ = ["PiscNode", "message_class", "qos_profile", "run_node"]

OK = DiagnosticStatus.OK
WARN = DiagnosticStatus.WARN
ERROR = DiagnosticStatus.ERROR


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


class PiscNode(Node):
    """Base of the PISC nodes. Subclasses pass their sections and implement ``build``."""

    def __init__(
        self,
        node_name: str,
        sections: Mapping[str, type],
        *,
        parameter_overrides: list[Parameter] | None = None,
        **kwargs: Any,
    ) -> None:
        super().__init__(node_name, parameter_overrides=parameter_overrides, **kwargs)
        self._sections = dict(sections)
        self._check_unknown_overrides()
        for section, cls in self._sections.items():
            for name, default, unit, description in cfg.describe(cls, section):
                text = f"{description} [{unit}]" if unit else description
                self.declare_parameter(
                    name,
                    _ros_value(default),
                    ParameterDescriptor(description=text, dynamic_typing=True),
                )
        self._diagnostics = self.create_publisher(
            DiagnosticArray, DIAGNOSTICS.name, qos_profile(DIAGNOSTICS.qos))
        # Refuses to start on a bad value: ConfigError propagates out of __init__.
        self.config = self.build(self.flat_parameters())
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

    def _check_unknown_overrides(self) -> None:
        # rclpy keeps the parameter file's values for this node in _parameter_overrides
        # and would silently ignore a misspelt name; refuse it instead.
        overrides = getattr(self, "_parameter_overrides", {}) or {}
        for section, cls in self._sections.items():
            cfg.check_names(cls, overrides, section)

    def _validate_change(self, params: list[Parameter]) -> SetParametersResult:
        flat = self.flat_parameters()
        flat.update({p.name: p.value for p in params})
        try:
            self._pending = self.build(flat)
        except cfg.ConfigError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _apply_change(self, params: list[Parameter]) -> None:
        self.on_config(self._pending)

    # -- topics and diagnostics -------------------------------------------------------

    def publisher(self, topic: Topic) -> Any:
        return self.create_publisher(message_class(topic.type), topic.name, qos_profile(topic.qos))

    def subscription(self, topic: Topic, callback: Callable[..., None]) -> Any:
        return self.create_subscription(
            message_class(topic.type), topic.name, callback, qos_profile(topic.qos))

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
            self.get_logger().error(message)


def _shutting_down(wait_s: float = 0.5) -> bool:
    """Whether rclpy's context goes down within ``wait_s`` (a signal is being handled)."""
    deadline = time.monotonic() + wait_s
    while rclpy.ok():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def run_node(factory: Callable[[], Node], args: list[str] | None = None) -> int:
    """Run one node on an EventsExecutor until shutdown; the shape of ros2/demos' talker.

    A node that refuses its parameters prints why and the process exits with status 2.
    """
    rclpy.init(args=args)
    node = None
    try:
        node = factory()
        executor = EventsExecutor()
        executor.add_node(node)
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
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0
