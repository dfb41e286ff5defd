"""Conversions between ROS messages and the typed values of :mod:`pisc_msgs_py.types`.

``*_to_msg`` build rclpy message objects; ``*_to_cdr`` write the same message as CDR
bytes (:mod:`pisc_msgs_py.cdr`), which a publisher sends without building an object (the
nodes' cycle). Both take their fields from one function per message, so they
cannot differ. ``*_from_msg`` read by attribute only, so they accept rclpy messages, the
objects rosbags decodes from a bag and the views :mod:`pisc_msgs_py.cdr` reads from raw
bytes. A message that does not have the agreed layout raises :class:`MessageError`
saying what is wrong.

:func:`fast_read` reads raw bytes straight into the typed value, for a message whose
shape (:mod:`pisc_msgs_py.cdr`, "Shapes met before") a converter has read whole before
(:func:`note_read`): the names and sequence lengths a converter checks are the shape's, so
what is left to check is that the values it reads are finite. It gives what
``from_msg(decode(data))`` gives, or None when that must run (test_cdr).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, NamedTuple

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import WrenchStamped
from sensor_msgs.msg import JointState

from pisc_msgs_py import cdr
from pisc_msgs_py.cdr import MessageError
from pisc_msgs_py.topics import JOINT_NAMES, MOTOR_JOINT, PENDULUM_ESTIMATE_JOINTS
from pisc_msgs_py.types import (
    CartForce,
    JointSample,
    Mode,
    ModeReport,
    MotorSample,
    PendulumEstimate,
    StateEstimate,
    TrueState,
)

__all__ = [
    "MessageError",
    "cart_force_from_msg",
    "cart_force_to_cdr",
    "cart_force_to_msg",
    "clock_to_cdr",
    "fast_read",
    "joint_sample_from_msg",
    "joint_sample_to_cdr",
    "joint_sample_to_msg",
    "mode_from_msg",
    "mode_to_msg",
    "motor_sample_from_msg",
    "motor_sample_to_cdr",
    "motor_sample_to_msg",
    "note_read",
    "pendulum_estimate_from_msg",
    "pendulum_estimate_to_cdr",
    "stamp_from_msg",
    "stamp_to_msg",
    "state_from_msg",
    "state_to_cdr",
    "state_to_msg",
    "true_state_from_msg",
    "true_state_to_cdr",
    "true_state_to_msg",
]

MODE_STATUS_NAME = "pisc/supervisor/mode"
_MODE_LEVEL = {Mode.SWING_UP: DiagnosticStatus.OK, Mode.CATCH: DiagnosticStatus.OK,
               Mode.FAULT: DiagnosticStatus.ERROR}


def stamp_to_msg(stamp_ns: int) -> Time:
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return Time(sec=sec, nanosec=nanosec)


def stamp_from_msg(stamp: Any) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def _finite(values: list[float], what: str) -> list[float]:
    for v in values:
        if not math.isfinite(v):
            raise MessageError(f"{what}: non-finite value in {values}")
    return values


def _joint_values(msg: Any, names: tuple[str, ...], field: str, what: str) -> list[float]:
    got = msg.name
    if got is not names and tuple(got) != names:
        raise MessageError(f"{what}: expected joints {list(names)}, got {list(got)}")
    values = list(map(float, getattr(msg, field)))
    if len(values) != len(names):
        raise MessageError(
            f"{what}: expected {len(names)} values in '{field}', got {len(values)}")
    return _finite(values, what)


# JointState fields: (stamp_ns, joint names, position, velocity, effort)
JointFields = tuple[int, tuple[str, ...], tuple[float, ...], tuple[float, ...],
                    tuple[float, ...]]


def _joint_state_msg(fields: JointFields) -> JointState:
    stamp_ns, names, position, velocity, effort = fields
    msg = JointState()
    msg.header.stamp = stamp_to_msg(stamp_ns)
    msg.name = list(names)
    msg.position = list(position)
    msg.velocity = list(velocity)
    msg.effort = list(effort)
    return msg


def _joint_sample_fields(sample: JointSample) -> JointFields:
    return (sample.stamp_ns, JOINT_NAMES, (float(sample.position_m), float(sample.angle_rad)),
            (), ())


def joint_sample_to_msg(sample: JointSample) -> JointState:
    return _joint_state_msg(_joint_sample_fields(sample))


def joint_sample_to_cdr(sample: JointSample) -> bytes:
    return cdr.joint_state(*_joint_sample_fields(sample))


def joint_sample_from_msg(msg: Any) -> JointSample:
    x, theta = _joint_values(msg, JOINT_NAMES, "position", "joint_states")
    return JointSample(stamp_from_msg(msg.header.stamp), x, theta)


def _motor_sample_fields(sample: MotorSample) -> JointFields:
    return sample.stamp_ns, (MOTOR_JOINT,), (), (), (float(sample.value),)


def motor_sample_to_msg(sample: MotorSample, frame_id: str = "") -> JointState:
    """``frame_id``: what the value is (the driver's ``/pisc/motor/voltage_sent`` says
    why each byte was written: ``answer``, ``hold`` or ``zero``)."""
    msg = _joint_state_msg(_motor_sample_fields(sample))
    msg.header.frame_id = frame_id
    return msg


def motor_sample_to_cdr(sample: MotorSample, frame_id: str = "") -> bytes:
    return cdr.joint_state(*_motor_sample_fields(sample), frame_id=frame_id)


def motor_sample_from_msg(msg: Any) -> MotorSample:
    (value,) = _joint_values(msg, (MOTOR_JOINT,), "effort", "motor")
    return MotorSample(stamp_from_msg(msg.header.stamp), value)


def _state_fields(state: StateEstimate) -> JointFields:
    return (state.stamp_ns, JOINT_NAMES, (float(state.position_m), float(state.angle_rad)),
            (float(state.velocity_mps), float(state.rate_radps)), ())


def state_to_msg(state: StateEstimate) -> JointState:
    return _joint_state_msg(_state_fields(state))


def state_to_cdr(state: StateEstimate) -> bytes:
    return cdr.joint_state(*_state_fields(state))


def state_from_msg(msg: Any) -> StateEstimate:
    x, theta = _joint_values(msg, JOINT_NAMES, "position", "state")
    x_dot, theta_dot = _joint_values(msg, JOINT_NAMES, "velocity", "state")
    return StateEstimate(stamp_from_msg(msg.header.stamp), x, x_dot, theta, theta_dot)


def _true_state_fields(state: TrueState) -> JointFields:
    return (state.stamp_ns, (*JOINT_NAMES, MOTOR_JOINT),
            (float(state.position_m), float(state.angle_rad), 0.0),
            (float(state.velocity_mps), float(state.rate_radps), 0.0),
            (0.0, 0.0, float(state.current_a)))


def true_state_to_msg(state: TrueState) -> JointState:
    return _joint_state_msg(_true_state_fields(state))


def true_state_to_cdr(state: TrueState) -> bytes:
    return cdr.joint_state(*_true_state_fields(state))


def true_state_from_msg(msg: Any) -> TrueState:
    names = (*JOINT_NAMES, MOTOR_JOINT)
    x, theta, _ = _joint_values(msg, names, "position", "true_state")
    x_dot, theta_dot, _ = _joint_values(msg, names, "velocity", "true_state")
    _, _, current = _joint_values(msg, names, "effort", "true_state")
    return TrueState(stamp_from_msg(msg.header.stamp), x, x_dot, theta, theta_dot, current)


def _pendulum_estimate_fields(e: PendulumEstimate) -> JointFields:
    return (e.stamp_ns, PENDULUM_ESTIMATE_JOINTS, (float(e.omega0_sq), float(e.pivot_loss)),
            (float(e.omega0_sq_std), float(e.pivot_loss_std)), ())


def pendulum_estimate_to_cdr(estimate: PendulumEstimate) -> bytes:
    return cdr.joint_state(*_pendulum_estimate_fields(estimate))


def pendulum_estimate_from_msg(msg: Any) -> PendulumEstimate:
    what = "pendulum_estimate"
    w2, beta = _joint_values(msg, PENDULUM_ESTIMATE_JOINTS, "position", what)
    w2_std, beta_std = _joint_values(msg, PENDULUM_ESTIMATE_JOINTS, "velocity", what)
    return PendulumEstimate(stamp_from_msg(msg.header.stamp), w2, beta, w2_std, beta_std)


CART_FRAME = "cart"  # the frame of the cart force


def cart_force_to_msg(force: CartForce) -> WrenchStamped:
    msg = WrenchStamped()
    msg.header.stamp = stamp_to_msg(force.stamp_ns)
    msg.header.frame_id = CART_FRAME
    msg.wrench.force.x = float(force.force_n)
    return msg


def cart_force_to_cdr(force: CartForce) -> bytes:
    return cdr.wrench_stamped(force.stamp_ns, CART_FRAME, (float(force.force_n), 0.0, 0.0))


def cart_force_from_msg(msg: Any) -> CartForce:
    (f,) = _finite([float(msg.wrench.force.x)], "cart_force")
    return CartForce(stamp_from_msg(msg.header.stamp), f)


def clock_to_cdr(stamp_ns: int) -> bytes:
    """``rosgraph_msgs/msg/Clock`` at ``stamp_ns`` as CDR bytes."""
    return cdr.clock(stamp_ns)


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


# -- raw bytes straight into values -------------------------------------------------------

class _Fast(NamedTuple):
    shape_of: Callable[[bytes], Any]  # cdr.*_shape
    # which values the converter checks are finite: (run, its first n, or None: all)
    finite: tuple[tuple[int, int | None], ...]
    build: Callable[..., Any]  # (stamp_ns, *runs) -> the converter's value


_FAST: dict[Callable[[Any], Any], _Fast] = {
    joint_sample_from_msg: _Fast(cdr.joint_state_shape, ((0, None),),
                                 lambda s, p, v, e: JointSample(s, p[0], p[1])),
    motor_sample_from_msg: _Fast(cdr.joint_state_shape, ((2, None),),
                                 lambda s, p, v, e: MotorSample(s, e[0])),
    state_from_msg: _Fast(cdr.joint_state_shape, ((0, None), (1, None)),
                          lambda s, p, v, e: StateEstimate(s, p[0], v[0], p[1], v[1])),
    true_state_from_msg: _Fast(cdr.joint_state_shape, ((0, None), (1, None), (2, None)),
                               lambda s, p, v, e: TrueState(s, p[0], v[0], p[1], v[1], e[2])),
    cart_force_from_msg: _Fast(cdr.wrench_stamped_shape, ((0, 1),),  # force.x alone
                               lambda s, w: CartForce(s, w[0])),
}


def fast_read(from_msg: Callable[[Any], Any], data: bytes) -> Any | None:
    """``from_msg`` of the message in ``data`` (raw CDR) if its shape is one ``from_msg``
    read whole before and every value it checks is finite; None otherwise: then
    ``from_msg(decode(data))`` gives the value or the error (and :func:`note_read`
    after it makes the next message of that shape fast)."""
    fast = _FAST.get(from_msg)
    if fast is None:
        return None
    shape = fast.shape_of(data)
    if shape is None or from_msg not in shape.read_by:
        return None
    runs = shape.doubles(data)
    for k, n in fast.finite:
        for v in runs[k][:n]:
            if not math.isfinite(v):
                return None
    return fast.build(shape.stamp_ns(data), *runs)


def note_read(from_msg: Callable[[Any], Any], data: bytes) -> None:
    """``from_msg`` read the message in ``data`` without error: the same shape holds the
    same names and sequence lengths, so :func:`fast_read` reads it from now on."""
    fast = _FAST.get(from_msg)
    if fast is not None:
        shape = fast.shape_of(data)
        if shape is not None:
            shape.read_by.add(from_msg)
