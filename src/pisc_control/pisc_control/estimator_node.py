"""Estimator node: measured positions in, positions and velocities out, same stamp.

The velocities are differences over one period ((4.7), (4.9)), so a measurement is used
only when its stamp is the next one: later than the one before, and on simulated time
(lockstep) exactly one period later. Any other is refused and said on /diagnostics (a
stamp from another publisher, or one replayed out of order, would be differentiated as
if it were the next sample)."""

from __future__ import annotations

from typing import Any

from pisc_control.estimator import EstimatorParams, OneRigEstimator
from pisc_msgs_py.base_node import ERROR, OK, PiscNode, ResendCache, run_node
from pisc_msgs_py.convert import joint_sample_from_msg, state_to_cdr
from pisc_msgs_py.topics import JOINT_STATES, STATE
from pisc_msgs_py.types import JointSample, StateEstimate
from pisc_model.params import LoopParams


class EstimatorNode(PiscNode):
    def __init__(self, **kwargs: Any) -> None:
        super().__init__("estimator", {"loop": LoopParams, "estimator": EstimatorParams}, **kwargs)
        loop, params = self.config
        self._estimator = OneRigEstimator(params, loop.period_s)
        self._samples = 0
        self._last_ns: int | None = None  # stamp of the last measurement used
        self._answers = ResendCache()  # a resent sample: same answer, same state
        self._state_pub = self.publisher(STATE)
        self._sub = self.subscription(JOINT_STATES, self._on_joint_states,
                                      joint_sample_from_msg, "joint_states")

    def build(self, flat: dict[str, Any]) -> tuple[LoopParams, EstimatorParams]:
        return self.section(flat, "loop"), self.section(flat, "estimator")

    def on_config(self, config: tuple[LoopParams, EstimatorParams]) -> None:
        self.config = config
        loop, params = config
        self._estimator.configure(params, loop.period_s)

    def _on_joint_states(self, sample: JointSample) -> None:
        if self._answers.resend(sample.stamp_ns):
            return
        if not self._next_stamp(sample.stamp_ns):
            return
        x_dot, theta_dot = self._estimator.step(sample.position_m, sample.angle_rad)
        out = state_to_cdr(StateEstimate(
            sample.stamp_ns, sample.position_m, x_dot, sample.angle_rad, theta_dot))
        self._answers.publish(sample.stamp_ns, (self._state_pub, out))
        self._samples += 1
        if self.routine_diagnostics(self._samples):
            self.diagnose(OK, "estimating", sample.stamp_ns, samples=self._samples)


    def _next_stamp(self, stamp_ns: int) -> bool:
        """Whether ``stamp_ns`` is the next measurement's (module docstring); says why not."""
        last = self._last_ns
        if last is not None:
            period_ns = round(self.config[0].period_s * 1e9)
            lockstep = self.get_clock().ros_time_is_active
            if stamp_ns <= last or (lockstep and stamp_ns - last != period_ns):
                rule = (f"{last * 1e-9:.6f} s + {period_ns * 1e-6:g} ms" if lockstep
                        else f"later than {last * 1e-9:.6f} s")
                self.diagnose(ERROR, f"rejected joint_states: stamp {stamp_ns * 1e-9:.6f} s is "
                              f"not the next period's ({rule}); not used", stamp_ns,
                              topic="/pisc/joint_states", last_stamp_ns=last)
                return False
        self._last_ns = stamp_ns
        return True


def main(args: list[str] | None = None) -> int:
    return run_node(EstimatorNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
