"""Current-loop node: force and measured current in, current setpoint and voltage out."""

from __future__ import annotations

from typing import Any

from pisc_control.current_loop import (
    CurrentLoopParams,
    CurrentLoopState,
    current_loop_update,
    current_setpoint,
)
from pisc_msgs_py.base_node import ERROR, OK, PiscNode, run_node
from pisc_msgs_py.convert import (
    MessageError,
    cart_force_from_msg,
    mode_from_msg,
    motor_sample_from_msg,
    motor_sample_to_msg,
)
from pisc_msgs_py.sync import StampPairer
from pisc_msgs_py.topics import CART_FORCE, CURRENT_SETPOINT, MODE, MOTOR_CURRENT, VOLTAGE
from pisc_msgs_py.types import CartForce, Mode, MotorSample
from pisc_model.params import LoopParams, MotorParams

DIAGNOSTIC_EVERY = 200


class CurrentLoopNode(PiscNode):
    def __init__(self, **kwargs: Any) -> None:
        super().__init__(
            "current_loop",
            {"loop": LoopParams, "motor": MotorParams, "current_loop": CurrentLoopParams},
            **kwargs,
        )
        self._state = CurrentLoopState()
        self._pairs: StampPairer[CartForce, MotorSample] = StampPairer()
        self._fault = ""
        self._cycles = 0
        self._last: tuple[int, Any, Any] | None = None  # (stamp, setpoint, voltage) sent
        self._setpoint_pub = self.publisher(CURRENT_SETPOINT)
        self._voltage_pub = self.publisher(VOLTAGE)
        self._subs = [
            self.subscription(CART_FORCE, self._on_force),
            self.subscription(MOTOR_CURRENT, self._on_current),
            self.subscription(MODE, self._on_mode),
        ]

    def build(self, flat: dict[str, Any]) -> tuple[LoopParams, MotorParams, CurrentLoopParams]:
        return (self.section(flat, "loop"), self.section(flat, "motor"),
                self.section(flat, "current_loop"))

    def _on_force(self, msg: Any) -> None:
        try:
            force = cart_force_from_msg(msg)
        except MessageError as exc:
            self.diagnose(ERROR, f"rejected cart_force: {exc}")
            return
        if self._resend(force.stamp_ns):
            return
        pair = self._pairs.add_first(force.stamp_ns, force)
        if pair:
            self._cycle(*pair)

    def _on_current(self, msg: Any) -> None:
        try:
            current = motor_sample_from_msg(msg)
        except MessageError as exc:
            self.diagnose(ERROR, f"rejected motor current: {exc}")
            return
        if self._resend(current.stamp_ns):
            return
        pair = self._pairs.add_second(current.stamp_ns, current)
        if pair:
            self._cycle(*pair)

    def _on_mode(self, msg: Any) -> None:
        try:
            report = mode_from_msg(msg)
        except MessageError as exc:
            self.diagnose(ERROR, f"rejected mode: {exc}")
            return
        self._fault = (report.reason or "supervisor fault") if report.mode is Mode.FAULT else ""
        if self._fault:
            self.diagnose(ERROR, f"supervisor fault ({self._fault}): commanding 0 V",
                          report.stamp_ns)

    def _resend(self, stamp_ns: int) -> bool:
        """A cycle already answered (a resent sample): send the same answer again."""
        if self._last is None or self._last[0] != stamp_ns:
            return False
        self._setpoint_pub.publish(self._last[1])
        self._voltage_pub.publish(self._last[2])
        return True

    def _cycle(self, force: CartForce, current: MotorSample) -> None:
        loop, motor, params = self.config
        if self._fault:
            # Safe state: no voltage, and no integral left to kick when the fault clears.
            self._state = CurrentLoopState()
            i_d, voltage = 0.0, 0.0
        else:
            i_d = float(current_setpoint(motor, params, force.force_n))
            self._state, u = current_loop_update(params, loop.period_s, self._state, i_d,
                                                 current.value)
            voltage = float(u)
        setpoint_msg = motor_sample_to_msg(MotorSample(force.stamp_ns, i_d))
        voltage_msg = motor_sample_to_msg(MotorSample(force.stamp_ns, voltage))
        self._last = (force.stamp_ns, setpoint_msg, voltage_msg)
        self._setpoint_pub.publish(setpoint_msg)
        self._voltage_pub.publish(voltage_msg)
        self._cycles += 1
        if self._cycles % DIAGNOSTIC_EVERY == 1 and not self._fault:
            self.diagnose(OK, "regulating current", force.stamp_ns, cycles=self._cycles,
                          unmatched_dropped=self._pairs.dropped)


def main(args: list[str] | None = None) -> int:
    return run_node(CurrentLoopNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
