"""Conversions between ROS messages and the typed values of :mod:`pisc_msgs_py.types`.

``*_to_msg`` build rclpy message objects. ``*_from_msg`` read by attribute only, so they
accept both rclpy messages and the objects rosbags decodes from a bag. A message that
does not have the agreed layout raises :class:`MessageError` saying what is wrong.
"""

from __future__ import annotations

import math
from typing import Any

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import WrenchStamped
from sensor_msgs.msg import JointState

from pisc_msgs_py.topics import JOINT_NAMES, MOTOR_JOINT
from pisc_msgs_py.types import (
    CartForce,
    JointSample,
    Mode,
    ModeReport,
    MotorSample,
    StateEstimate,
    TrueState,
)

__all__ = [
    "MessageError",
    "cart_force_from_msg",
    "cart_force_to_msg",
    "joint_sample_from_msg",
    "joint_sample_to_msg",
    "mode_from_msg",
    "mode_to_msg",
    "motor_sample_from_msg",
    "motor_sample_to_msg",
    "stamp_from_msg",
    "stamp_to_msg",
    "state_from_msg",
    "state_to_msg",
    "true_state_from_msg",
    "true_state_to_msg",
]

MODE_STATUS_NAME = "pisc/supervisor/mode"
_MODE_LEVEL = {Mode.SWING_UP: DiagnosticStatus.OK, Mode.CATCH: DiagnosticStatus.OK,
               Mode.FAULT: DiagnosticStatus.ERROR}


class MessageError(ValueError):
    """A message does not have the layout PISC agreed for its topic."""


def stamp_to_msg(stamp_ns: int) -> Time:
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return Time(sec=sec, nanosec=nanosec)


def stamp_from_msg(stamp: Any) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def _finite(values: list[float], what: str) -> list[float]:
    if not all(math.isfinite(v) for v in values):
        raise MessageError(f"{what}: non-finite value in {values}")
    return values


def _joint_values(msg: Any, names: tuple[str, ...], field: str, what: str) -> list[float]:
    got = tuple(msg.name)
    if got != names:
        raise MessageError(f"{what}: expected joints {list(names)}, got {list(got)}")
    values = [float(v) for v in getattr(msg, field)]
    if len(values) != len(names):
        raise MessageError(
            f"{what}: expected {len(names)} values in '{field}', got {len(values)}")
    return _finite(values, what)


def joint_sample_to_msg(sample: JointSample) -> JointState:
    msg = JointState()
    msg.header.stamp = stamp_to_msg(sample.stamp_ns)
    msg.name = list(JOINT_NAMES)
    msg.position = [float(sample.position_m), float(sample.angle_rad)]
    return msg


def joint_sample_from_msg(msg: Any) -> JointSample:
    x, theta = _joint_values(msg, JOINT_NAMES, "position", "joint_states")
    return JointSample(stamp_from_msg(msg.header.stamp), x, theta)


def motor_sample_to_msg(sample: MotorSample) -> JointState:
    msg = JointState()
    msg.header.stamp = stamp_to_msg(sample.stamp_ns)
    msg.name = [MOTOR_JOINT]
    msg.effort = [float(sample.value)]
    return msg


def motor_sample_from_msg(msg: Any) -> MotorSample:
    (value,) = _joint_values(msg, (MOTOR_JOINT,), "effort", "motor")
    return MotorSample(stamp_from_msg(msg.header.stamp), value)


def state_to_msg(state: StateEstimate) -> JointState:
    msg = JointState()
    msg.header.stamp = stamp_to_msg(state.stamp_ns)
    msg.name = list(JOINT_NAMES)
    msg.position = [float(state.position_m), float(state.angle_rad)]
    msg.velocity = [float(state.velocity_mps), float(state.rate_radps)]
    return msg


def state_from_msg(msg: Any) -> StateEstimate:
    x, theta = _joint_values(msg, JOINT_NAMES, "position", "state")
    x_dot, theta_dot = _joint_values(msg, JOINT_NAMES, "velocity", "state")
    return StateEstimate(stamp_from_msg(msg.header.stamp), x, x_dot, theta, theta_dot)


def true_state_to_msg(state: TrueState) -> JointState:
    msg = JointState()
    msg.header.stamp = stamp_to_msg(state.stamp_ns)
    msg.name = [*JOINT_NAMES, MOTOR_JOINT]
    msg.position = [float(state.position_m), float(state.angle_rad), 0.0]
    msg.velocity = [float(state.velocity_mps), float(state.rate_radps), 0.0]
    msg.effort = [0.0, 0.0, float(state.current_a)]
    return msg


def true_state_from_msg(msg: Any) -> TrueState:
    names = (*JOINT_NAMES, MOTOR_JOINT)
    x, theta, _ = _joint_values(msg, names, "position", "true_state")
    x_dot, theta_dot, _ = _joint_values(msg, names, "velocity", "true_state")
    _, _, current = _joint_values(msg, names, "effort", "true_state")
    return TrueState(stamp_from_msg(msg.header.stamp), x, x_dot, theta, theta_dot, current)


def cart_force_to_msg(force: CartForce) -> WrenchStamped:
    msg = WrenchStamped()
    msg.header.stamp = stamp_to_msg(force.stamp_ns)
    msg.header.frame_id = "cart"
    msg.wrench.force.x = float(force.force_n)
    return msg


def cart_force_from_msg(msg: Any) -> CartForce:
    (f,) = _finite([float(msg.wrench.force.x)], "cart_force")
    return CartForce(stamp_from_msg(msg.header.stamp), f)


def mode_to_msg(report: ModeReport) -> DiagnosticArray:
    msg = DiagnosticArray()
    msg.header.stamp = stamp_to_msg(report.stamp_ns)
    status = DiagnosticStatus()
    status.level = _MODE_LEVEL[report.mode]
    status.name = MODE_STATUS_NAME
    status.message = report.mode.value
    status.hardware_id = "pisc"
    status.values = [KeyValue(key="reason", value=report.reason)]
    msg.status = [status]
    return msg


def mode_from_msg(msg: Any) -> ModeReport:
    statuses = [s for s in msg.status if s.name == MODE_STATUS_NAME]
    if len(statuses) != 1:
        raise MessageError(f"mode: expected one status named {MODE_STATUS_NAME!r}")
    status = statuses[0]
    try:
        mode = Mode(status.message)
    except ValueError:
        raise MessageError(f"mode: unknown mode {status.message!r}") from None
    reason = next((kv.value for kv in status.values if kv.key == "reason"), "")
    return ModeReport(stamp_from_msg(msg.header.stamp), mode, reason)
