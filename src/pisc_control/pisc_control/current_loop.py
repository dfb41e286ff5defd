"""Force to current, and the PI current loop that drives the motor, thesis 3.4 and 4.1.

The laws are :func:`current_setpoint_step` (4.2) and :func:`pi_step` (3.47), on floats,
and :func:`current_loop_step`, one cycle of both with the fault's safe state: the
current loop node runs it through :class:`OneRigCurrentLoop`, the compiled batch
(:mod:`pisc_sim.batch_controllers`) and the environments compile it, and
:func:`current_setpoint`, :func:`current_loop_update` and :func:`current_loop_cycle`
apply it to arrays of rigs element by element.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from pisc_control.floatmath import clip
from pisc_model.params import MotorParams
from pisc_msgs_py.config import in_range, nonnegative, param, positive

__all__ = [
    "C_FORCE_PER_AMP",
    "CurrentLoopParams",
    "CurrentLoopState",
    "OneRigCurrentLoop",
    "current_loop_constants",
    "current_loop_cycle",
    "current_loop_step",
    "current_loop_update",
    "current_setpoint",
    "current_setpoint_step",
    "pi_step",
]

# places in the current loop's constants
C_FORCE_PER_AMP, C_I_LIMIT, C_VM, C_KII_TS, C_RESET, C_K_PI, N_C = range(7)


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


def current_loop_constants(motor: MotorParams, params: CurrentLoopParams,
                           period_s: float) -> tuple[float, ...]:
    """The constants of :func:`current_loop_step` (places ``C_*``)."""
    c = [0.0] * N_C
    c[C_FORCE_PER_AMP] = motor.force_per_amp
    c[C_I_LIMIT] = params.current_limit_a
    c[C_VM] = params.voltage_limit_v
    c[C_KII_TS] = params.k_ii * period_s
    c[C_RESET] = params.integral_reset_fraction * params.voltage_limit_v
    c[C_K_PI] = params.k_pi
    return tuple(c)


def current_setpoint_step(c: tuple[float, ...], force: float) -> float:
    """Desired current ``i_d = f r / k_m`` (4.2), saturated to +-``current_limit_a``."""
    return clip(force / c[C_FORCE_PER_AMP], -c[C_I_LIMIT], c[C_I_LIMIT])


def pi_step(c: tuple[float, ...], i_d: float, current: float, integral: float
            ) -> tuple[float, float]:
    """One sample of the PI current loop: (voltage, new integral).

    Notes
    -----
    Implements (3.47), ``u = k_pi e + k_ii integral(e)``, e = i_d - i, exactly as the
    thesis C++ program (appendix A.2) samples it: while the integral lies strictly
    inside +-VM it accumulates ``k_ii Ts e`` before the output is formed; once it has
    reached the limit it is reset to +-0.95 VM without accumulating; the output
    ``k_pi e + integral`` is saturated to +-VM.
    """
    e = i_d - current
    vm = c[C_VM]
    if integral < vm and integral > -vm:
        new = integral + c[C_KII_TS] * e
    elif integral >= vm:
        new = c[C_RESET]
    else:
        new = -c[C_RESET]
    return clip(c[C_K_PI] * e + new, -vm, vm), new


def current_loop_step(c: tuple[float, ...], fault: bool, force: float, current: float,
                      integral: float) -> tuple[float, float, float]:
    """One cycle of the current loop as the graph runs it: (i_d, voltage, integral).

    The set-point (4.2) (:func:`current_setpoint_step`), then the PI loop (3.47)
    (:func:`pi_step`). In ``fault`` (the supervisor's mode is ``fault``) the answer is
    the safe state: 0 A, 0 V, and the integral cleared, so that none is left to kick
    when the fault clears.
    """
    i_d = current_setpoint_step(c, force)
    voltage, new = pi_step(c, i_d, current, integral)
    if fault:
        return 0.0, 0.0, 0.0
    return i_d, voltage, new


# -- over arrays of rigs: the laws above element by element -----------------------------

@dataclass(frozen=True)
class CurrentLoopState:
    integral_v: np.ndarray = np.float64(0.0)  # noqa: RUF009 - immutable numpy scalar


def current_setpoint(
    motor: MotorParams, params: CurrentLoopParams, force_n: ArrayLike
) -> np.ndarray:
    """:func:`current_setpoint_step` (4.2) over an array of forces."""
    c = current_loop_constants(motor, params, 0.0)
    return np.vectorize(lambda f: current_setpoint_step(c, f), otypes=[float])(force_n)


def current_loop_update(
    params: CurrentLoopParams,
    period_s: float,
    state: CurrentLoopState,
    current_setpoint_a: ArrayLike,
    current_a: ArrayLike,
) -> tuple[CurrentLoopState, np.ndarray]:
    """:func:`pi_step` (3.47) over arrays of rigs: the new state and the voltage."""
    c = current_loop_constants(MotorParams(), params, period_s)
    voltage, integral = np.vectorize(lambda i_d, i, integral: pi_step(c, i_d, i, integral),
                                     otypes=[float, float])(
        current_setpoint_a, current_a, state.integral_v)
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
    """:func:`current_loop_step` over arrays of rigs (``fault``: one flag, or one per
    rig): the new state, the current set-point ``i_d`` and the voltage."""
    c = current_loop_constants(motor, params, period_s)
    i_d, voltage, integral = np.vectorize(
        lambda f, i, integral, k: current_loop_step(c, bool(k), f, i, integral),
        otypes=[float, float, float])(force_n, current_a, state.integral_v, fault)
    return CurrentLoopState(integral), i_d, voltage


class OneRigCurrentLoop:
    """The current loop of one rig, as its node runs it: :func:`current_loop_step`."""

    def __init__(self, motor: MotorParams, params: CurrentLoopParams, period_s: float) -> None:
        self.integral_v = 0.0
        self.configure(motor, params, period_s)

    def configure(self, motor: MotorParams, params: CurrentLoopParams, period_s: float) -> None:
        self._constants = current_loop_constants(motor, params, period_s)

    def step(self, force: float, current: float, fault: bool) -> tuple[float, float]:
        """(i_d, voltage) for this cycle."""
        i_d, voltage, self.integral_v = current_loop_step(self._constants, fault, force,
                                                          current, self.integral_v)
        return i_d, voltage
