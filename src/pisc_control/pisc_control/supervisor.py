"""The supervisor: swing-up, catch, the switching rule between them, and safety.

Each sample the supervisor decides the mode and the force on the cart:

* **catch** (3.46) while the switching criterion (4.1),
  ``theta^2 + k_va theta_dot^2``, with theta from the nearest upright, is below
  ``delta_s``; once catching it keeps catching until the criterion reaches
  ``delta_exit`` (``delta_exit = delta_s`` is the thesis's rule without hysteresis);
  with ``switching.energy_band_j`` > 0 a catch also needs the pendulum's own energy
  within the band of upright's, so that it can coast up; the catch's cart reference
  may settle from where the catch began (``catch.settle_rate_mps``);
* **swing_up** otherwise: (3.30), or the energy pump (``swing_up.law``,
  :func:`pisc_control.swing_up.energy_pump_force`);
* **fault** when the state is not finite or the cart leaves the safe range: the force
  is zero, the mode latches, and downstream the current loop commands zero volts.

With ``experiment.kind`` set (:mod:`pisc_control.excitation`) the supervisor runs an
identification experiment instead of swinging up and catching: the mode stays
``swing_up`` (its report's reason names the experiment), the force is the
experiment's, and the fault rules above still apply.

Start-up: (3.30) gives f = 0 for a pendulum hanging at rest with the cart at the
target, so a rig started there never moves; and from rest the thesis's own convergence
argument does not apply (it needs V(0) < k_e (2 m g l)^2 / 2, section 3.2, which a
pendulum hanging at rest never satisfies). With ``startup.distance_m = D > 0`` the
swing-up target starts at D from the first measured position, towards the middle of
the safe range, and stays there until the first catch. Pulling the cart over D is what
swings the pendulum up; because (3.30) does not depend on where the cart is, every
start then sees the same swing-up, whatever its position on the track.

The functions are pure and broadcast over arrays, so one call steps one rig in the
supervisor node or many in a batch.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike

from pisc_control.adaptation import AdaptationParams
from pisc_control.estimator import EstimatorParams
from pisc_control.catch import CatchParams, catch_force, catch_gain, governor_rows
from pisc_control.excitation import ExperimentParams, experiment_force
from pisc_control.swing_up import (
    SwingUpParams,
    check_gain_condition,
    energy_pump_force,
    pendulum_energy,
    swing_up_force,
)
from pisc_model.dynamics import wrap_to_upright
from pisc_model.params import LoopParams, MotorParams, RigParams, SensorParams
from pisc_msgs_py.config import ConfigError, nonnegative, param, positive
from pisc_msgs_py.types import Mode

__all__ = [
    "FAULT_NONE",
    "FAULT_NOT_FINITE",
    "FAULT_OUT_OF_RANGE",
    "SafetyParams",
    "StartupParams",
    "Supervisor",
    "SupervisorConfig",
    "SupervisorState",
    "SwitchingParams",
    "switching_criterion",
]

FAULT_NONE = 0
FAULT_NOT_FINITE = 1
FAULT_OUT_OF_RANGE = 2


@dataclass(frozen=True)
class SwitchingParams:
    """Switching rule (4.1); thesis values (Table 6.5) are k_va = 0.015, delta_s = 0.6."""

    k_va: float = param(0.015, "k_va, weight of theta_dot^2 in the criterion (4.1)", "s^2",
                        nonnegative)
    delta_s: float = param(0.6, "delta_s, catch when the criterion is below it (4.1)", "rad^2",
                           positive)
    delta_exit: float = param(0.6, "stop catching when the criterion reaches it "
                              "(hysteresis; = delta_s is the thesis's rule)", "rad^2", positive)
    energy_band_j: float = param(
        0.0, "catch only while the pendulum's own energy is within this of upright at rest "
        "(0 J), so that it can coast up; 0 = no energy condition, the thesis's rule", "J",
        nonnegative)

    def __post_init__(self) -> None:
        if self.delta_exit < self.delta_s:
            raise ConfigError(
                f"switching.delta_exit = {self.delta_exit} must not be below "
                f"switching.delta_s = {self.delta_s} (the catch would release at once)")


@dataclass(frozen=True)
class StartupParams:
    distance_m: float = param(
        0.0, "D: until the first catch the swing-up target is D from the first measured "
        "position, towards the middle of the safe range (0 = swing_up.target_m from the "
        "start, the thesis's behaviour)", "m", nonnegative)


@dataclass(frozen=True)
class SafetyParams:
    """Soft limits: outside them the supervisor faults and the motor gets zero volts."""

    x_min_m: float = param(-0.225, "lowest safe cart position", "m")
    x_max_m: float = param(0.125, "highest safe cart position", "m")

    def __post_init__(self) -> None:
        if not self.x_min_m < self.x_max_m:
            raise ConfigError(
                f"safety.x_min_m = {self.x_min_m} must be below safety.x_max_m = {self.x_max_m}")


@dataclass(frozen=True)
class SupervisorConfig:
    rig: RigParams = field(default_factory=RigParams)
    swing_up: SwingUpParams = field(default_factory=SwingUpParams)
    catch: CatchParams = field(default_factory=CatchParams)
    switching: SwitchingParams = field(default_factory=SwitchingParams)
    startup: StartupParams = field(default_factory=StartupParams)
    safety: SafetyParams = field(default_factory=SafetyParams)
    loop: LoopParams = field(default_factory=LoopParams)
    experiment: ExperimentParams = field(default_factory=ExperimentParams)
    motor: MotorParams = field(default_factory=MotorParams)
    adaptation: AdaptationParams = field(default_factory=AdaptationParams)
    # what lies between the rig and the supervisor, for the governor's prediction
    estimator: EstimatorParams = field(default_factory=EstimatorParams)
    sensors: SensorParams = field(default_factory=SensorParams)


@dataclass(frozen=True)
class SupervisorState:
    """Per-rig memory of the supervisor; ``None`` fields before the first sample."""

    mode: np.ndarray | None = None
    fault: np.ndarray | None = None
    startup_target_m: np.ndarray | None = None
    caught: np.ndarray | None = None  # has caught at least once
    catch_reference_m: np.ndarray | None = None  # the catch's cart reference (settling)
    sample: np.ndarray | None = None  # experiments: index of the sample (their clock)
    origin_m: np.ndarray | None = None  # experiments: the first measured position


def switching_criterion(k_va: float, theta: ArrayLike, theta_dot: ArrayLike) -> np.ndarray:
    """``theta^2 + k_va theta_dot^2`` with theta from the nearest upright (4.1)."""
    th = wrap_to_upright(theta)
    theta_dot = np.asarray(theta_dot, dtype=float)
    return th * th + k_va * theta_dot * theta_dot


class Supervisor:
    """A validated configuration with its catch gain; stateless apart from constants.

    Construction refuses a configuration that breaks (3.29) or whose linearisation is
    not controllable, with a :class:`ConfigError` naming the parameters.
    """

    def __init__(self, config: SupervisorConfig) -> None:
        check_gain_condition(config.rig, config.swing_up)
        self.config = config
        self.gain = catch_gain(config.rig, config.catch)
        c = config.catch
        #: the gain that balances once the catch has held (catch.hold_poles)
        self.hold_gain = (catch_gain(config.rig, replace(
            c, poles=tuple(c.hold_poles), poles_imag=(0.0,) * 4,
            recorded_gain=c.recorded_hold_gain)) if c.hold_poles else self.gain)
        margin = 2.0 * c.governor_margin_m
        if c.governor and not margin < config.safety.x_max_m - config.safety.x_min_m:
            raise ConfigError(
                f"catch.governor_margin_m = {c.governor_margin_m} leaves nothing of the safe "
                f"range [{config.safety.x_min_m}, {config.safety.x_max_m}] m")
        #: the governor's prediction (:func:`pisc_control.catch.governor_rows`); none
        #: without the governor
        self.governor_rows = (governor_rows(
            config.rig, self.gain, config.loop.period_s, c.governor_horizon_s,
            config.motor.force_per_amp, config.estimator.difference_periods,
            config.estimator.velocity_filter_hz, config.sensors.ir_filter_hz)
            if c.governor else np.zeros((0, 8)))
        if c.guard and (config.swing_up.law != "energy_pump"
                        or config.swing_up.guard_accel_mps2 <= 0.0):
            raise ConfigError("catch.guard: when it lets the catch go, the energy pump's track "
                              "guard brakes; it needs swing_up.law: energy_pump and "
                              "swing_up.guard_accel_mps2 > 0")
        if config.adaptation.enabled and config.swing_up.law != "energy_pump":
            raise ConfigError("adaptation.enabled: the online estimates serve the energy pump "
                              "(swing_up.law: energy_pump), not (3.30)")
        #: the configuration uses a law written only for one rig at a time
        #: (:mod:`pisc_control.scalar`: the governor, the catch's guard, the online
        #: estimates); :meth:`update` refuses it, :class:`pisc_control.scalar.
        #: ArraySupervisor` runs it over arrays, rig by rig
        self.by_rig = config.experiment.kind == "none" and (
            c.governor or c.guard or config.adaptation.enabled)

    def update(
        self,
        state: SupervisorState,
        x: ArrayLike,
        x_dot: ArrayLike,
        theta: ArrayLike,
        theta_dot: ArrayLike,
    ) -> tuple[SupervisorState, np.ndarray, np.ndarray]:
        """Decide the mode and force for one sample; returns (state, force, mode code)."""
        c = self.config
        x = np.asarray(x, dtype=float)
        x_dot = np.asarray(x_dot, dtype=float)
        theta = np.asarray(theta, dtype=float)
        theta_dot = np.asarray(theta_dot, dtype=float)
        shape = np.broadcast_shapes(x.shape, x_dot.shape, theta.shape, theta_dot.shape)
        if self.by_rig:
            raise ValueError("this configuration's laws are written for one rig at a time "
                             "(the governor, the catch's guard, the online estimates): "
                             "run them over arrays with pisc_control.scalar.ArraySupervisor")

        if state.mode is None:
            mode = np.full(shape, Mode.SWING_UP.code)
            fault = np.full(shape, FAULT_NONE)
            caught = np.zeros(shape, dtype=bool)
            middle = 0.5 * (c.safety.x_min_m + c.safety.x_max_m)
            direction = np.where(x >= middle, -1.0, 1.0)
            startup_target = np.where(c.startup.distance_m > 0.0,
                                      x + direction * c.startup.distance_m, c.swing_up.target_m)
        else:
            mode, fault, caught = state.mode, state.fault, state.caught
            startup_target = state.startup_target_m

        finite = np.isfinite(x) & np.isfinite(x_dot) & np.isfinite(theta) & np.isfinite(theta_dot)
        in_range = (x >= c.safety.x_min_m) & (x <= c.safety.x_max_m)
        new_fault = np.where(fault != FAULT_NONE, fault,
                             np.where(~finite, FAULT_NOT_FINITE,
                                      np.where(~in_range, FAULT_OUT_OF_RANGE, FAULT_NONE)))

        if c.experiment.kind != "none":
            return self._experiment(state, new_fault, startup_target, caught, x, x_dot, shape)

        criterion = switching_criterion(c.switching.k_va, theta, theta_dot)
        catching = mode == Mode.CATCH.code
        threshold = np.where(catching, c.switching.delta_exit, c.switching.delta_s)
        inside = criterion < threshold
        band = c.switching.energy_band_j
        if band > 0.0:
            coasting = np.abs(pendulum_energy(c.rig, theta, theta_dot)) < band
            inside &= catching | coasting
        new_mode = np.where(inside, Mode.CATCH.code, Mode.SWING_UP.code)
        new_mode = np.where(new_fault != FAULT_NONE, Mode.FAULT.code, new_mode)

        caught = caught | (new_mode == Mode.CATCH.code)
        target = np.where(caught, c.swing_up.target_m, startup_target)
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            if c.swing_up.law == "energy_pump":
                f_swing = energy_pump_force(c.rig, c.swing_up, x, x_dot, theta, theta_dot,
                                            target, (c.safety.x_min_m, c.safety.x_max_m))
            else:
                f_swing = swing_up_force(c.rig, c.swing_up, x, x_dot, theta, theta_dot, target)
            reference = self._catch_reference(state, mode, new_mode, x)
            f_catch = catch_force(self.gain, x, x_dot, theta, theta_dot, reference)
        force = np.where(new_mode == Mode.CATCH.code, f_catch,
                         np.where(new_mode == Mode.SWING_UP.code, f_swing, 0.0))
        # (3.29) keeps the swing-up denominator positive; a non-finite force can only come
        # from non-finite inputs, which fault above. Never pass one on.
        force = np.where(np.isfinite(force), force, 0.0)
        return (SupervisorState(new_mode, new_fault, startup_target, caught, reference), force,
                new_mode)

    def _experiment(self, state: SupervisorState, fault: np.ndarray, startup_target: np.ndarray,
                    caught: np.ndarray, x: np.ndarray, x_dot: np.ndarray, shape: tuple
                    ) -> tuple[SupervisorState, np.ndarray, np.ndarray]:
        """:meth:`update` during an experiment: its force, or none after a fault."""
        c = self.config
        sample = (np.zeros(shape, dtype=np.int64) if state.sample is None
                  else state.sample + 1)
        origin = np.broadcast_to(x, shape).copy() if state.origin_m is None else state.origin_m
        with np.errstate(invalid="ignore", over="ignore"):
            force = experiment_force(c.experiment, c.rig, (c.safety.x_min_m, c.safety.x_max_m),
                                     sample * c.loop.period_s, x, x_dot, origin)
        mode = np.where(fault != FAULT_NONE, Mode.FAULT.code, Mode.SWING_UP.code)
        force = np.where((mode == Mode.FAULT.code) | ~np.isfinite(force), 0.0, force)
        return (SupervisorState(mode, fault, startup_target, caught, state.catch_reference_m,
                                sample, origin), force, mode)

    def experiment_reason(self) -> str:
        """What the mode report says during an experiment ("" without one)."""
        e = self.config.experiment
        if e.kind == "none":
            return ""
        return f"experiment: {e.kind}" + (f" ({e.signal})" if e.kind == "excitation" else "")

    def _catch_reference(self, state: SupervisorState, mode: np.ndarray, new_mode: np.ndarray,
                         x: np.ndarray) -> np.ndarray:
        """The catch's cart reference: ``catch.target_m``, or with ``settle_rate_mps`` > 0
        the cart's position when the catch began, moved towards it by rate x Ts a sample."""
        c = self.config
        rate = c.catch.settle_rate_mps
        if rate == 0.0:
            return np.broadcast_to(np.asarray(c.catch.target_m, dtype=float), np.shape(x))
        previous = x if state.catch_reference_m is None else state.catch_reference_m
        entering = (new_mode == Mode.CATCH.code) & (mode != Mode.CATCH.code)
        reference = np.where(entering, x, previous)
        step = rate * c.loop.period_s
        return np.where(new_mode == Mode.CATCH.code,
                        reference + np.clip(c.catch.target_m - reference, -step, step), reference)

    def fault_reason(self, fault: int, x: float) -> str:
        c = self.config.safety
        if fault == FAULT_NOT_FINITE:
            return "non-finite state estimate"
        if fault == FAULT_OUT_OF_RANGE:
            return (f"cart at x = {x:.4f} m outside the safe range "
                    f"[{c.x_min_m}, {c.x_max_m}] m (safety.x_min_m, safety.x_max_m)")
        return ""
