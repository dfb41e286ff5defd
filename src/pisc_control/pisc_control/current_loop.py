"""Force to current, and the PI current loop that drives the motor, thesis 3.4 and 4.1."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from pisc_msgs_py.config import in_range, nonnegative, param, positive
from pisc_model.params import MotorParams

__all__ = [
    "CurrentLoopParams",
    "CurrentLoopState",
    "current_loop_cycle",
    "current_loop_update",
    "current_setpoint",
]


@dataclass(frozen=True)
class CurrentLoopParams:
    """PI gains (Table 6.2) and the limits of the C++ program."""

    k_pi: float = param(2.9, "k_pi, proportional gain of (3.47)", "V/A", nonnegative)
    k_ii: float = param(1800.0, "k_ii, integral gain of (3.47)", "V/(A s)", nonnegative)
    current_limit_a: float = param(0.9, "saturation of the desired current i_d (IM)", "A",
                                   positive)
    voltage_limit_v: float = param(11.47, "saturation of the voltage and the integral (VM)",
                                   "V", positive)
    integral_reset_fraction: float = param(
        0.95, "anti-windup: the integral is reset to this fraction of the limit when it "
        "reaches it", "", in_range(0.0, 1.0))


@dataclass(frozen=True)
class CurrentLoopState:
    integral_v: np.ndarray = np.float64(0.0)  # noqa: RUF009 - immutable numpy scalar


def current_setpoint(
    motor: MotorParams, params: CurrentLoopParams, force_n: ArrayLike
) -> np.ndarray:
    """Desired current ``i_d = f r / k_m`` (4.2), saturated to +-``current_limit_a``."""
    i_d = np.asarray(force_n, dtype=float) / motor.force_per_amp
    return np.clip(i_d, -params.current_limit_a, params.current_limit_a)


def current_loop_update(
    params: CurrentLoopParams,
    period_s: float,
    state: CurrentLoopState,
    current_setpoint_a: ArrayLike,
    current_a: ArrayLike,
) -> tuple[CurrentLoopState, np.ndarray]:
    """One sample of the PI current loop; returns the new state and the voltage.

    Notes
    -----
    Implements (3.47), ``u = k_pi e + k_ii integral(e)``, e = i_d - i, exactly as the
    thesis C++ program (appendix A.2) samples it: while the integral lies strictly
    inside +-VM it accumulates ``k_ii Ts e`` before the output is formed; once it has
    reached the limit it is reset to +-0.95 VM without accumulating; the output
    ``k_pi e + integral`` is saturated to +-VM.
    """
    e = np.asarray(current_setpoint_a, dtype=float) - np.asarray(current_a, dtype=float)
    vm = params.voltage_limit_v
    integral = np.asarray(state.integral_v, dtype=float)
    inside = (integral < vm) & (integral > -vm)
    reset = params.integral_reset_fraction * vm
    integral = np.where(
        inside, integral + params.k_ii * period_s * e, np.where(integral >= vm, reset, -reset)
    )
    voltage = np.clip(params.k_pi * e + integral, -vm, vm)
    return CurrentLoopState(integral), voltage


def current_loop_cycle(
    motor: MotorParams,
    params: CurrentLoopParams,
    period_s: float,
    state: CurrentLoopState,
    force_n: ArrayLike,
    current_a: ArrayLike,
    fault: ArrayLike = False,
) -> tuple[CurrentLoopState, np.ndarray, np.ndarray]:
    """One cycle of the current loop as the graph runs it, with its fault handling.

    Returns the new state, the current set-point ``i_d`` and the voltage. The current
    loop node, the pure closed loop and the batch simulation all call this.

    Notes
    -----
    The set-point of the force is (4.2) (:func:`current_setpoint`), the voltage that of
    the PI loop (3.47) (:func:`current_loop_update`). Where ``fault`` holds (the
    supervisor's mode is ``fault``; one flag, or one per rig) the answer is the safe
    state: 0 A, 0 V, and the integral cleared, so that none is left to kick when the
    fault clears.
    """
    fault = np.asarray(fault, dtype=bool)
    i_d = current_setpoint(motor, params, force_n)
    new_state, voltage = current_loop_update(params, period_s, state, i_d, current_a)
    return (CurrentLoopState(np.where(fault, 0.0, new_state.integral_v)),
            np.where(fault, 0.0, i_d), np.where(fault, 0.0, voltage))
