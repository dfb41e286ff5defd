"""Current-loop node: force and measured current in, current setpoint and voltage out."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from pisc_control.current_loop import CurrentLoopParams, OneRigCurrentLoop
from pisc_msgs_py.base_node import ERROR, OK, PiscNode, ResendCache, run_node
from pisc_msgs_py.convert import (
    cart_force_from_msg,
    mode_from_msg,
    motor_sample_from_msg,
    motor_sample_to_cdr,
)
from pisc_msgs_py.sync import StampPairer
from pisc_msgs_py.topics import CART_FORCE, CURRENT_SETPOINT, MODE, MOTOR_CURRENT, VOLTAGE
from pisc_msgs_py.types import CartForce, Mode, ModeReport, MotorSample
from pisc_model.params import LoopParams, MotorParams


class CurrentLoopNode(PiscNode):
    def __init__(self, **kwargs: Any) -> None:
        super().__init__(
            "current_loop",
            {"loop": LoopParams, "motor": MotorParams, "current_loop": CurrentLoopParams},
            **kwargs,
        )
        loop, motor, params = self.config
        self._loop = OneRigCurrentLoop(motor, params, loop.period_s)
        self._pairs: StampPairer[CartForce, MotorSample] = StampPairer()
        self._fault = ""
        self._cycles = 0
        self._answers = ResendCache()  # a cycle already answered: the same set-point and voltage
        self._setpoint_pub = self.publisher(CURRENT_SETPOINT)
        self._voltage_pub = self.publisher(VOLTAGE)
        self._subs = [
            self.subscription(CART_FORCE, self._on_force, cart_force_from_msg, "cart_force"),
            self.subscription(MOTOR_CURRENT, self._on_current, motor_sample_from_msg,
                              "motor current"),
            self.subscription(MODE, self._on_mode, mode_from_msg, "mode"),
        ]

    def build(self, flat: dict[str, Any]) -> tuple[LoopParams, MotorParams, CurrentLoopParams]:
        return (self.section(flat, "loop"), self.section(flat, "motor"),
                self.section(flat, "current_loop"))

    def on_config(self, config: tuple[LoopParams, MotorParams, CurrentLoopParams]) -> None:
        self.config = config
        loop, motor, params = config
        self._loop.configure(motor, params, loop.period_s)

    def _on_force(self, force: CartForce) -> None:
        self._pair(force, self._pairs.add_first)

    def _on_current(self, current: MotorSample) -> None:
        self._pair(current, self._pairs.add_second)

    def _pair(self, item: CartForce | MotorSample,
              add: Callable[[int, Any], tuple[CartForce, MotorSample] | None]) -> None:
        """One half of a cycle: a resent stamp gets its first answer again; the half
        that completes a pair runs the cycle."""
        if self._answers.resend(item.stamp_ns):
            return
        pair = add(item.stamp_ns, item)
        if pair:
            self._cycle(*pair)

    def _on_mode(self, report: ModeReport) -> None:
        self._fault = (report.reason or "supervisor fault") if report.mode is Mode.FAULT else ""
        if self._fault:
            self.diagnose(ERROR, f"supervisor fault ({self._fault}): commanding 0 V",
                          report.stamp_ns)

    def _cycle(self, force: CartForce, current: MotorSample) -> None:
        i_d, voltage = self._loop.step(force.force_n, current.value, bool(self._fault))
        self._answers.publish(
            force.stamp_ns,
            (self._setpoint_pub, motor_sample_to_cdr(MotorSample(force.stamp_ns, i_d))),
            (self._voltage_pub, motor_sample_to_cdr(MotorSample(force.stamp_ns, voltage))))
        self._cycles += 1
        if self.routine_diagnostics(self._cycles) and not self._fault:
            self.diagnose(OK, "regulating current", force.stamp_ns, cycles=self._cycles,
                          unmatched_dropped=self._pairs.dropped)


def main(args: list[str] | None = None) -> int:
    return run_node(CurrentLoopNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
