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

The law is :func:`supervisor_step`, one sample of one rig on floats, with the swing-up
laws (:mod:`pisc_control.swing_up`) and the catch's (:mod:`pisc_control.catch`) it
calls: the supervisor node runs it through :class:`OneRigSupervisor`, the compiled batch
compiles it (:mod:`pisc_sim.batch_controllers`), and :meth:`Supervisor.update` runs it
over arrays of rigs, one rig after another.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike

from pisc_control.adaptation import (
    AdaptationParams,
    adaptation_constants,
    adaptation_estimates,
    adaptation_init,
    adaptation_size,
    adaptation_std,
    adaptation_step,
)
from pisc_control.catch import (
    K_GOV,
    CatchParams,
    catch_constants,
    catch_gain,
    catch_reference,
    governor_interval,
    governor_rows,
    guard_lets_go,
    held_catch_force,
    hold_blend,
)
from pisc_control.estimator import EstimatorParams
from pisc_control.excitation import ExperimentParams, experiment_force
from pisc_control.floatmath import cos, sin, wrap
from pisc_control.swing_up import (
    SwingUpParams,
    check_gain_condition,
    energy_pump_force,
    lyapunov_force,
    pendulum_energy,
    swing_up_constants,
)
from pisc_model.params import LoopParams, MotorParams, RigParams, SensorParams
from pisc_msgs_py.config import ConfigError, nonnegative, param, positive
from pisc_msgs_py.types import Mode

__all__ = [
    "FAULT_NONE",
    "FAULT_NOT_FINITE",
    "FAULT_OUT_OF_RANGE",
    "OneRigSupervisor",
    "SafetyParams",
    "StartupParams",
    "Supervisor",
    "SupervisorConfig",
    "SupervisorState",
    "SwitchingParams",
    "fault_code",
    "startup_target",
    "supervisor_constants",
    "supervisor_step",
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
    """Per-rig memory of :meth:`Supervisor.update`; ``None`` fields before the first
    sample."""

    mode: np.ndarray | None = None
    fault: np.ndarray | None = None
    startup_target_m: np.ndarray | None = None
    caught: np.ndarray | None = None  # has caught at least once
    catch_reference_m: np.ndarray | None = None  # the catch's cart reference (settling)
    sample: np.ndarray | None = None  # experiments: index of the sample (their clock)
    origin_m: np.ndarray | None = None  # experiments: the first measured position
    # the online estimates' state (:mod:`pisc_control.adaptation`), one row per rig
    adaptation: np.ndarray | None = None


def switching_criterion(k_va: float, th: float, theta_dot: float) -> float:
    """``theta^2 + k_va theta_dot^2`` (4.1), ``th`` the angle from the nearest upright
    (:func:`pisc_control.floatmath.wrap`, or over arrays
    :func:`pisc_model.dynamics.wrap_to_upright`). No branch: it also runs on arrays."""
    return th * th + k_va * theta_dot * theta_dot


# places in the supervisor's own constants (supervisor_constants)
(S_X_MIN, S_X_MAX, S_MIDDLE, S_STARTUP_D, S_SWING_TARGET, S_K_VA, S_DELTA_S, S_DELTA_EXIT,
 S_BAND, S_LAW, S_ADAPT, N_S) = range(12)
LAW_LYAPUNOV, LAW_ENERGY_PUMP = 0, 1
SWING_UP, CATCH, FAULT = Mode.SWING_UP.code, Mode.CATCH.code, Mode.FAULT.code


def supervisor_constants(config: SupervisorConfig) -> tuple[float, ...]:
    """The constants of :func:`supervisor_step` of its own (places ``S_*``)."""
    c = config
    s = [0.0] * N_S
    s[S_X_MIN], s[S_X_MAX] = c.safety.x_min_m, c.safety.x_max_m
    s[S_MIDDLE] = 0.5 * (c.safety.x_min_m + c.safety.x_max_m)
    s[S_STARTUP_D] = c.startup.distance_m
    s[S_SWING_TARGET] = c.swing_up.target_m
    sw = c.switching
    s[S_K_VA], s[S_DELTA_S], s[S_DELTA_EXIT] = sw.k_va, sw.delta_s, sw.delta_exit
    s[S_BAND] = sw.energy_band_j
    s[S_LAW] = float(LAW_ENERGY_PUMP if c.swing_up.law == "energy_pump" else LAW_LYAPUNOV)
    s[S_ADAPT] = 1.0 if c.adaptation.enabled else 0.0
    return tuple(s)


def startup_target(s: tuple[float, ...], x: float) -> float:
    """The swing-up's target until the first catch, from the first measured position
    ``x``: ``startup.distance_m`` from it towards the middle of the safe range, or
    without a distance ``swing_up.target_m``."""
    if s[S_STARTUP_D] > 0.0:
        direction = -1.0 if x >= s[S_MIDDLE] else 1.0
        return x + direction * s[S_STARTUP_D]
    return s[S_SWING_TARGET]


def fault_code(s: tuple[float, ...], fault: int, x: float, x_dot: float, theta: float,
               theta_dot: float) -> int:
    """The fault after this sample: a fault latches; else a state that is not finite,
    or a cart outside the safe range, faults."""
    if fault != FAULT_NONE:
        return fault
    if not (math.isfinite(x) and math.isfinite(x_dot) and math.isfinite(theta)
            and math.isfinite(theta_dot)):
        return FAULT_NOT_FINITE
    if not (x >= s[S_X_MIN] and x <= s[S_X_MAX]):
        return FAULT_OUT_OF_RANGE
    return FAULT_NONE


def supervisor_step(s: tuple[float, ...], w: tuple[float, ...], k: tuple[float, ...], rows,
                    pendulum: tuple[float, float, float, float, bool, float], first: bool,
                    x: float, x_dot: float, theta: float, theta_dot: float, mode: int,
                    fault: int, caught: bool, target0: float, reference: float
                    ) -> tuple[float, int, int, bool, float, float]:
    """One sample of the supervisor for one rig: (force, mode, fault, caught, start-up
    target, catch reference), the last five the state for the next sample.

    ``s``, ``w``, ``k``: the constants of :func:`supervisor_constants`,
    :func:`pisc_control.swing_up.swing_up_constants` and
    :func:`pisc_control.catch.catch_constants`; ``rows``: the governor's prediction
    (:func:`pisc_control.catch.governor_rows`); ``pendulum``: what
    :func:`pisc_control.adaptation.adaptation_step` gave for this sample. ``first``: the
    first sample (the state's mode, fault, caught, start-up target and reference are
    then ignored).

    The catch (3.46) while the criterion (4.1) is below ``delta_s``, or once catching
    below ``delta_exit`` (with the energy band, the catch's guard and the governor's
    conditions to start one); the swing-up law otherwise; no force in a fault.
    """
    if first:
        mode = SWING_UP
        fault = FAULT_NONE
        caught = False
        target0 = startup_target(s, x)
    new_fault = fault_code(s, fault, x, x_dot, theta, theta_dot)
    th = wrap(theta)
    c = cos(theta)
    w2, beta, middle, rate, stalled, held = pendulum
    if s[S_ADAPT] > 0.0:  # the energy from the angle and rate of one instant
        e_c = cos(middle)
        e_rate = rate
        e_th = wrap(middle)
    else:
        e_c, e_rate, e_th = c, theta_dot, th
    catching = mode == CATCH
    criterion = switching_criterion(s[S_K_VA], th, theta_dot)
    inside = criterion < (s[S_DELTA_EXIT] if catching else s[S_DELTA_S])
    if s[S_BAND] > 0.0:
        inside = inside and (catching or abs(pendulum_energy(w, e_c, e_rate, w2)) < s[S_BAND])
    if inside and guard_lets_go(k, x, x_dot):
        inside = False  # the cart would not stop inside the guard's limits: brake
    blend = hold_blend(k, held) if catching else 0.0
    lo, hi = math.inf, -math.inf  # no governor's interval
    if k[K_GOV] > 0.0 and inside and blend == 0.0:
        lo, hi = governor_interval(k, rows, x, x_dot, th, theta_dot)
        if not catching and not lo <= hi:
            inside = False  # no reference keeps this catch in the track: do not start it
    new_mode = CATCH if inside else SWING_UP
    if new_fault != FAULT_NONE:
        new_mode = FAULT
    now_caught = caught or new_mode == CATCH
    entering = first or (new_mode == CATCH and not catching)
    ref = catch_reference(k, entering, new_mode == CATCH, x, reference,
                          lo if new_mode == CATCH else math.inf,
                          hi if new_mode == CATCH else -math.inf)
    if new_mode == CATCH:
        force = held_catch_force(k, blend, x, x_dot, th, theta_dot, ref)
    elif new_mode == SWING_UP:
        target = s[S_SWING_TARGET] if now_caught else target0
        sn = sin(theta)
        if s[S_LAW] == LAW_ENERGY_PUMP:
            force = energy_pump_force(w, x, x_dot, sn, c, theta_dot, target,
                                      (e_c, e_rate, e_th, w2, beta), stalled)
        else:
            force = lyapunov_force(w, x, x_dot, sn, c, theta_dot, target)
    else:
        force = 0.0
    # (3.29) keeps the swing-up denominator positive; a non-finite force can only come
    # from non-finite inputs, which fault. Never pass one on.
    if not math.isfinite(force):
        force = 0.0
    return force, new_mode, new_fault, now_caught, target0, ref


class Supervisor:
    """A validated configuration with its catch gain and the laws' constants.

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
        limits = (config.safety.x_min_m, config.safety.x_max_m)
        su = config.swing_up
        #: the constants of :func:`supervisor_step`: its own, the swing-up's, the catch's
        self.constants = (
            supervisor_constants(config),
            swing_up_constants(config.rig, su, limits, config.adaptation.enabled),
            catch_constants(self.gain, self.hold_gain, c, limits, config.loop.period_s,
                            su.law == "energy_pump" and su.guard_accel_mps2 > 0.0))
        #: the governor's rows as tuples of floats, which Python indexes faster than an
        #: array's elements
        self.rows = [tuple(float(v) for v in row) for row in self.governor_rows]
        #: the online estimates' constants (:func:`pisc_control.adaptation.
        #: adaptation_constants`)
        self.adaptation = adaptation_constants(config.adaptation, config.rig,
                                               config.loop.period_s)

    def update(
        self,
        state: SupervisorState,
        x: ArrayLike,
        x_dot: ArrayLike,
        theta: ArrayLike,
        theta_dot: ArrayLike,
    ) -> tuple[SupervisorState, np.ndarray, np.ndarray]:
        """Decide the mode and force for one sample of arrays of rigs (any shape; the
        state's arrays are flat): :func:`supervisor_step` rig after rig, or during an
        experiment its force. Returns (state, force, mode code)."""
        values = [np.asarray(v, dtype=float) for v in (x, x_dot, theta, theta_dot)]
        shape = np.broadcast_shapes(*(v.shape for v in values), *(
            np.shape(v) for v in (state.mode, state.fault, state.caught,
                                  state.startup_target_m, state.catch_reference_m)
            if v is not None))
        x, x_dot, theta, theta_dot = (np.broadcast_to(v, shape).reshape(-1) for v in values)
        rigs = x.size
        first = state.mode is None
        s, w, k = self.constants
        if first:
            mode = np.full(rigs, SWING_UP, dtype=np.int64)
            fault = np.full(rigs, FAULT_NONE, dtype=np.int64)
            caught = np.zeros(rigs, dtype=bool)
            target = np.array([startup_target(s, v) for v in x.tolist()])
        else:
            mode, fault, caught, target = (
                np.broadcast_to(v, shape).reshape(-1).copy()
                for v in (state.mode, state.fault, state.caught, state.startup_target_m))
        if self.config.experiment.kind != "none":
            return self._experiment(state, shape, first, fault, target, caught, x, x_dot,
                                    theta, theta_dot)
        reference = (x.copy() if state.catch_reference_m is None else
                     np.broadcast_to(state.catch_reference_m, shape).reshape(-1).copy())
        a = self.config.adaptation
        if state.adaptation is None:
            adapt = np.zeros((rigs, adaptation_size(a)))
            for row in adapt:
                adaptation_init(a, self.config.rig, row)
        else:
            adapt = state.adaptation.copy()
        force = np.empty(rigs)
        # one rig after another: the law is written for one rig (the nodes'), and the
        # compiled batch runs it over many (pisc_sim.batch_controllers)
        for r in range(rigs):
            row = adapt[r].tolist()
            pendulum = adaptation_step(self.adaptation, row, float(x[r]), float(theta[r]),
                                       first or mode[r] != CATCH)
            adapt[r] = row
            force[r], mode[r], fault[r], caught[r], target[r], reference[r] = supervisor_step(
                s, w, k, self.rows, pendulum, first, float(x[r]), float(x_dot[r]),
                float(theta[r]), float(theta_dot[r]), int(mode[r]), int(fault[r]),
                bool(caught[r]), float(target[r]), float(reference[r]))
        new = SupervisorState(mode.reshape(shape), fault.reshape(shape), target.reshape(shape),
                              caught.reshape(shape), reference.reshape(shape),
                              adaptation=adapt)
        return new, force.reshape(shape), mode.reshape(shape)

    def _experiment(self, state: SupervisorState, shape: tuple, first: bool,
                    fault: np.ndarray, target: np.ndarray, caught: np.ndarray, x: np.ndarray,
                    x_dot: np.ndarray, theta: np.ndarray, theta_dot: np.ndarray
                    ) -> tuple[SupervisorState, np.ndarray, np.ndarray]:
        """:meth:`update` during an experiment: its force, or none after a fault."""
        c = self.config
        s = self.constants[0]
        fault = np.array([fault_code(s, int(f), *v) for f, *v in zip(
            fault.tolist(), x.tolist(), x_dot.tolist(), theta.tolist(), theta_dot.tolist())],
            dtype=np.int64).reshape(shape)
        x, x_dot = x.reshape(shape), x_dot.reshape(shape)
        sample = (np.zeros(shape, dtype=np.int64) if state.sample is None
                  else state.sample + 1)
        origin = x.copy() if state.origin_m is None else state.origin_m
        with np.errstate(invalid="ignore", over="ignore"):
            force = experiment_force(c.experiment, c.rig, (c.safety.x_min_m, c.safety.x_max_m),
                                     sample * c.loop.period_s, x, x_dot, origin)
        mode = np.where(fault != FAULT_NONE, FAULT, SWING_UP)
        force = np.where((mode == FAULT) | ~np.isfinite(force), 0.0, force)
        return (SupervisorState(mode, fault, target.reshape(shape), caught.reshape(shape),
                                state.catch_reference_m, sample, origin), force, mode)

    def experiment_reason(self) -> str:
        """What the mode report says during an experiment ("" without one)."""
        e = self.config.experiment
        if e.kind == "none":
            return ""
        return f"experiment: {e.kind}" + (f" ({e.signal})" if e.kind == "excitation" else "")

    def fault_reason(self, fault: int, x: float) -> str:
        c = self.config.safety
        if fault == FAULT_NOT_FINITE:
            return "non-finite state estimate"
        if fault == FAULT_OUT_OF_RANGE:
            return (f"cart at x = {x:.4f} m outside the safe range "
                    f"[{c.x_min_m}, {c.x_max_m}] m (safety.x_min_m, safety.x_max_m)")
        return ""


class OneRigSupervisor:
    """The supervisor of one rig, as its node runs it: :func:`supervisor_step` on floats
    with the online estimates' state, or during an experiment :meth:`Supervisor.update`."""

    def __init__(self, supervisor: Supervisor) -> None:
        # (mode, fault, caught, start-up target, catch reference); None before a sample
        self._state: tuple[int, int, bool, float, float] | None = None
        self._array_state = SupervisorState()
        self.stalled = False  # the swing-up has given up (adaptation.stall_s)
        self.configure(supervisor)

    def configure(self, supervisor: Supervisor) -> None:
        """New parameters; the state carries over (also into and out of an experiment), and
        so do the online estimates unless their parameters changed."""
        previous = getattr(self, "supervisor", None)
        self.supervisor = supervisor
        c = supervisor.config
        self._law = c.experiment.kind == "none"
        self._s, self._w, self._k = supervisor.constants
        self._rows = supervisor.rows
        self._adapt = supervisor.adaptation
        if previous is None or (previous.config.adaptation, previous.config.rig) != (
                c.adaptation, c.rig):
            self._adapt_state = [0.0] * adaptation_size(c.adaptation)
            adaptation_init(c.adaptation, c.rig, self._adapt_state)
        self.estimates = adaptation_estimates(self._adapt_state)
        if self._law and self._array_state.mode is not None:
            n = self._array_state
            ref = n.catch_reference_m
            self._state = (int(n.mode), int(n.fault), bool(n.caught), float(n.startup_target_m),
                           0.0 if ref is None else float(ref))
            self._array_state = SupervisorState()
        elif not self._law and self._state is not None:
            mode, fault, caught, target, ref = self._state
            self._array_state = SupervisorState(np.int64(mode), np.int64(fault),
                                                np.float64(target), np.bool_(caught),
                                                np.float64(ref))
            self._state = None

    def estimates_std(self) -> tuple[float, float]:
        """The standard deviations of :attr:`estimates` (omega_0^2, beta)."""
        return adaptation_std(self._adapt_state)

    @property
    def caught(self) -> bool:
        """Whether the rig has been caught at least once."""
        return bool(self._state[2]) if self._state is not None else bool(
            self._array_state.caught is not None and self._array_state.caught)

    @property
    def reference(self) -> float:
        """The catch's cart reference (0 before the first sample)."""
        return float(self._state[4]) if self._state is not None else 0.0

    @property
    def fault(self) -> int:
        """The fault code (``FAULT_NONE`` before the first sample)."""
        if self._state is not None:
            return self._state[1]
        n = self._array_state.fault
        return FAULT_NONE if n is None else int(n)

    def step(self, x: float, x_dot: float, theta: float, theta_dot: float) -> tuple[float, int]:
        """(force, mode code) for this sample."""
        if not self._law:
            self._array_state, force, code = self.supervisor.update(
                self._array_state, x, x_dot, theta, theta_dot)
            return float(force), int(code)
        state = self._state
        pendulum = adaptation_step(self._adapt, self._adapt_state, x, theta,
                                   state is None or state[0] != CATCH)
        self.estimates = pendulum[:2]
        self.stalled = pendulum[4]
        if state is None:
            out = supervisor_step(self._s, self._w, self._k, self._rows, pendulum, True, x,
                                  x_dot, theta, theta_dot, SWING_UP, FAULT_NONE, False, 0.0,
                                  0.0)
        else:
            out = supervisor_step(self._s, self._w, self._k, self._rows, pendulum, False, x,
                                  x_dot, theta, theta_dot, *state)
        self._state = out[1:]
        return out[0], out[1]
