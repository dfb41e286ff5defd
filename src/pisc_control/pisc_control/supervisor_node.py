"""Supervisor node: state in, cart force out every cycle, mode out when it changes."""

from __future__ import annotations

from typing import Any

import numpy as np

from pisc_control.adaptation import AdaptationParams
from pisc_control.catch import CatchParams
from pisc_control.estimator import EstimatorParams
from pisc_control.excitation import ExperimentParams
from pisc_control.supervisor import (
    OneRigSupervisor,
    SafetyParams,
    StartupParams,
    Supervisor,
    SupervisorConfig,
    SwitchingParams,
)
from pisc_control.swing_up import SwingUpParams
from pisc_model.params import LoopParams, MotorParams, RigParams, SensorParams
from pisc_msgs_py.base_node import ERROR, OK, WARN, PiscNode, ResendCache, run_node
from pisc_msgs_py.convert import (
    cart_force_to_cdr,
    mode_to_msg,
    pendulum_estimate_to_cdr,
    state_from_msg,
)
from pisc_msgs_py.topics import CART_FORCE, MODE, PENDULUM_ESTIMATE, STATE
from pisc_msgs_py.types import CartForce, Mode, ModeReport, PendulumEstimate, StateEstimate

SECTIONS = {
    "rig": RigParams,
    "swing_up": SwingUpParams,
    "catch": CatchParams,
    "switching": SwitchingParams,
    "startup": StartupParams,
    "safety": SafetyParams,
    "loop": LoopParams,
    "experiment": ExperimentParams,
    "motor": MotorParams,
    "adaptation": AdaptationParams,
    "estimator": EstimatorParams,
    "sensors": SensorParams,
}


class SupervisorNode(PiscNode):
    def __init__(self, **kwargs: Any) -> None:
        super().__init__("supervisor", SECTIONS, **kwargs)
        self._supervisor = OneRigSupervisor(self.config)
        self._mode: Mode | None = None
        self._answers = ResendCache()  # a resent cycle: same force, same state
        self._force_pub = self.publisher(CART_FORCE)
        self._mode_pub = self.publisher(MODE)
        self._estimate_pub = self.publisher(PENDULUM_ESTIMATE)
        self._stall_said = False
        self._sub = self.subscription(STATE, self._on_state, state_from_msg, "state")
        self.get_logger().info(f"catch gain K = {np.array2string(self.config.gain, precision=5)}")

    def build(self, flat: dict[str, Any]) -> Supervisor:
        return Supervisor(SupervisorConfig(**{s: self.section(flat, s) for s in SECTIONS}))

    def on_config(self, config: Supervisor) -> None:
        self.config = config
        self._supervisor.configure(config)

    def _on_state(self, state: StateEstimate) -> None:
        if self._answers.resend(state.stamp_ns):
            return
        supervisor: Supervisor = self.config
        believed = self._supervisor.estimates
        force, code = self._supervisor.step(state.position_m, state.velocity_mps,
                                            state.angle_rad, state.rate_radps)
        if self._supervisor.stalled and not self._stall_said:
            self._stall_said = True
            self.diagnose(WARN, "swing-up stopped: the pendulum's energy has not risen for "
                          f"{supervisor.config.adaptation.stall_s:g} s and stays more than "
                          f"{1e3 * supervisor.config.adaptation.stall_below_j:g} mJ below "
                          "upright's (too much loss or too little force for this rig); the "
                          "cart is kept near x*", state.stamp_ns)
        if self._supervisor.estimates != believed:
            self._estimate_pub.publish(pendulum_estimate_to_cdr(PendulumEstimate(
                state.stamp_ns, *self._supervisor.estimates,
                *self._supervisor.estimates_std())))
        mode = Mode.from_code(code)
        if mode is not self._mode:
            # Announce a change before the force of the same cycle, so that the current
            # loop normally knows of a fault before it handles that cycle.
            reason = ""
            if mode is Mode.FAULT:
                reason = supervisor.fault_reason(self._supervisor.fault, state.position_m)
                self.diagnose(ERROR, f"fault: {reason}; force set to 0", state.stamp_ns)
            else:
                reason = supervisor.experiment_reason()
                self.diagnose(OK, mode.value + (f" ({reason})" if reason else ""),
                              state.stamp_ns)
            self._mode_pub.publish(mode_to_msg(ModeReport(state.stamp_ns, mode, reason)))
            self._mode = mode
        self._answers.publish(state.stamp_ns, (
            self._force_pub, cart_force_to_cdr(CartForce(state.stamp_ns, force))))


def main(args: list[str] | None = None) -> int:
    return run_node(SupervisorNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
