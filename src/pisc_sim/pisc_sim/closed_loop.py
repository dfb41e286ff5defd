"""The graph's control cycle without ROS: the same cores, in the same order.

One cycle, exactly as the nodes run it: the plant samples; the estimator
differentiates; the supervisor picks the mode and force; the current loop turns the
force into a current setpoint and a voltage; the plant holds that voltage for one
period. Values cross each "topic" as Python floats, as they do in messages, so a
lockstep run of the graph reproduces this simulation bit for bit.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from pisc_sim.configuration import GraphConfig
from pisc_control.current_loop import CurrentLoopState, OneRigCurrentLoop, current_loop_cycle
from pisc_control.estimator import EstimatorState, OneRigEstimator, estimator_update
from pisc_control.supervisor import OneRigSupervisor, Supervisor, SupervisorState
from pisc_msgs_py.types import Mode
from pisc_model.dynamics import wrap_to_upright
from pisc_plant.command import plant_command
from pisc_plant.plant import THETA, Plant, X
from pisc_plant.plant_config import PlantConfig
from pisc_plant.sampled import SampledPlant

__all__ = ["BatchOutcome", "Controllers", "CycleLog", "CycleOutputs", "simulate",
           "simulate_batch"]

COLUMNS = ("t", "x", "theta", "x_dot", "theta_dot", "i", "i_d", "u", "f", "mode",
           "true_x", "true_x_dot", "true_theta", "true_theta_dot", "true_i")


@dataclass(frozen=True)
class CycleLog:
    """One row per cycle; columns named in :data:`COLUMNS` (measured, then true state)."""

    data: np.ndarray

    def __getitem__(self, name: str) -> np.ndarray:
        return self.data[:, COLUMNS.index(name)]


@dataclass(frozen=True)
class CycleOutputs:
    """What the controllers answer to one sample, as the values their messages carry."""

    x_dot: float  # /pisc/state velocity of cart (4.7)
    theta_dot: float  # /pisc/state velocity of pendulum (4.9)
    force: float  # /pisc/cart_force
    mode: Mode  # /pisc/mode (published when it changes)
    i_d: float  # /pisc/motor/current_setpoint (4.2)
    voltage: float  # /pisc/motor/voltage (3.47)


class Controllers:
    """The estimator, supervisor and current-loop cores of one rig, in the graph's order.

    One :meth:`step` is one control cycle of the three controller nodes: backward
    differences (4.7), (4.9); the supervisor's mode (4.1) and force (3.30) or (3.46);
    the current setpoint (4.2) and the PI voltage (3.47), or 0 V with the integral
    cleared in ``fault``. Values leave each stage as Python floats, as they cross a
    topic, so the pure simulation, the nodes and a regression replay compute the same
    bits; each stage runs its law on floats, one rig, as its node does. Raises
    :class:`pisc_msgs_py.config.ConfigError` for an invalid configuration.
    """

    def __init__(self, config: GraphConfig) -> None:
        self.config = config
        self.supervisor = Supervisor(config.supervisor)
        period = config.loop.period_s
        self._estimator = OneRigEstimator(config.estimator, period)
        self._supervisor = OneRigSupervisor(self.supervisor)
        self._current_loop = OneRigCurrentLoop(config.plant.motor, config.current_loop, period)

    def step(self, position_m: float, angle_rad: float, current_a: float) -> CycleOutputs:
        x_dot, theta_dot = self._estimator.step(position_m, angle_rad)
        force, code = self._supervisor.step(position_m, x_dot, angle_rad, theta_dot)
        mode = Mode.from_code(code)
        i_d, voltage = self._current_loop.step(force, current_a, mode is Mode.FAULT)
        return CycleOutputs(x_dot, theta_dot, force, mode, i_d, voltage)

    def fault_reason(self, position_m: float) -> str:
        """Why the supervisor faulted (empty when it has not)."""
        return self.supervisor.fault_reason(self._supervisor.fault, position_m)


def simulate(config: GraphConfig, duration_s: float) -> CycleLog:
    """Run the closed loop from ``config.initial`` for ``duration_s`` (inclusive).

    The plant is ``config.simulated_plant`` (with model error, not the controllers'
    model), its command latency ``actuator.command_delay_s``.
    """
    plant = Plant(config.simulated_plant)
    i0 = config.initial
    sampled = SampledPlant(plant, plant.initial_state(i0.x_m, i0.x_dot_mps, i0.theta_rad,
                                                      i0.theta_dot_radps))
    controllers = Controllers(config)
    rows = []
    n = int(round(duration_s / config.loop.period_s)) + 1
    for _ in range(n):
        sample = sampled.sample()
        out = controllers.step(sample.position_m, sample.angle_rad, sample.current_a)
        rows.append((sampled.time_ns * 1e-9, sample.position_m, sample.angle_rad, out.x_dot,
                     out.theta_dot, sample.current_a, out.i_d, out.voltage, out.force,
                     out.mode.code, *sample.true_state))
        sampled.command(plant_command(plant.config, setpoint_a=out.i_d, voltage_v=out.voltage))
        sampled.advance()
    return CycleLog(np.array(rows))


@dataclass(frozen=True)
class BatchOutcome:
    """Per-rig outcome of :func:`simulate_batch` (true state, run time from 0)."""

    caught_at_s: np.ndarray  # start of the catch that lasts to the end; inf if none
    x_min_m: np.ndarray
    x_max_m: np.ndarray
    hold_theta_rad: np.ndarray  # largest |theta| from hold_start_s on
    hold_x_m: np.ndarray
    faulted: np.ndarray
    first_catch_s: np.ndarray | None = None  # first time in catch; inf if never
    # RMS of the current set-point i_d from hold_start_s on (the hold's chatter)
    hold_setpoint_rms_a: np.ndarray | None = None
    # the last sample time the true state was outside the hold box (-inf: never), so
    # that a rig is held from T to the end when this is below T
    unheld_at_s: np.ndarray | None = None


def simulate_batch(
    config: GraphConfig,
    x0_m: ArrayLike,
    duration_s: float,
    hold_start_s: float = 6.0,
    command_delay_s: ArrayLike = 0.0,
    *,
    x_dot0_mps: ArrayLike | None = None,
    theta0_rad: ArrayLike | None = None,
    theta_dot0_radps: ArrayLike | None = None,
    prime_estimator: bool = False,
    plant: PlantConfig | None = None,
    noise_seed: int | None = None,
    progress: Callable[[int, int], None] | None = None,
    controllers: str = "compiled",
    hold_box: tuple[float, float] = (0.05, 0.02),
) -> BatchOutcome:
    """The cycle of :func:`simulate` for many starting states at once.

    The same cores over arrays (one rig per element). ``command_delay_s`` (one value, or
    one per rig) applies each voltage that long after its sample, as a real-time
    graph's latency does, on top of the plant's ``actuator.command_delay_s``. Results
    agree with :func:`simulate` to rounding; they are not guaranteed bit for bit,
    because numpy may evaluate array and scalar expressions with different
    instructions.

    ``plant`` is the simulated plant (default ``config.simulated_plant``); a plant set
    (:func:`pisc_plant.plant_config.plant_set`) gives every rig its own physical parameters,
    while the controllers keep ``config``'s model. ``noise_seed`` replaces the plant's
    ``noise.seed`` (a batch draws one generator for all its rigs).

    The initial velocity, angle and rate default to ``config.initial``; given, they
    broadcast with ``x0_m`` (e.g. a grid over angle and rate for a region of
    attraction). ``prime_estimator`` gives the estimator a previous sample, the sensors'
    reading of the state one period earlier moving at the initial velocities, so that
    the first difference (4.7), (4.9) sees the initial rates instead of zero: a rig
    that was already moving. ``progress(k, n)`` is called after each of the n cycles.

    ``controllers``: ``"compiled"`` runs the measurement, the controllers and the
    outcomes' bookkeeping of every rig in one compiled pass a cycle
    (:mod:`pisc_sim.batch_controllers`, the same outcomes as the numpy path;
    experiments fall back to it), ``"numpy"`` runs the sensors' model over arrays and
    the same laws over the rigs in Python (:func:`~pisc_control.estimator.
    estimator_update`, :meth:`~pisc_control.supervisor.Supervisor.update`,
    :func:`~pisc_control.current_loop.current_loop_cycle`).

    ``hold_box`` (|theta| from upright [rad], |x| [m]): the outcome's ``unheld_at_s`` is
    the last sample time the true state lay outside it.
    """
    if controllers not in ("compiled", "numpy"):
        raise ValueError(f"controllers = {controllers!r}: 'compiled' or 'numpy'")
    plant_config = config.simulated_plant if plant is None else plant
    sim = Plant(plant_config)
    i0 = config.initial
    start = [np.asarray(v, dtype=float) for v in (
        x0_m,
        i0.x_dot_mps if x_dot0_mps is None else x_dot0_mps,
        i0.theta_rad if theta0_rad is None else theta0_rad,
        i0.theta_dot_radps if theta_dot0_radps is None else theta_dot0_radps)]
    shape = np.broadcast_shapes(*(v.shape for v in start))
    x0 = np.broadcast_to(start[0], shape).copy()
    y = sim.initial_state(x0, *start[1:])
    supervisor = Supervisor(config.supervisor)
    period = config.loop.period_s
    delay = np.asarray(command_delay_s, dtype=float) + plant_config.actuator.command_delay_s
    if np.any(~np.isfinite(delay)) or np.any(delay < 0.0) or np.any(delay >= period):
        raise ValueError(f"command delay must lie in [0, {period}) s (one period)")
    if delay.ndim:
        delay = np.broadcast_to(delay, shape).reshape(-1).copy()
    est_state = EstimatorState()
    if prime_estimator:
        earlier = sim.initial_state(x0 - start[1] * period, start[1],
                                    start[2] - start[3] * period, start[3])
        x_prev, theta_prev, _ = sim.measurement(earlier)
        est_state = EstimatorState(x_prev, theta_prev, np.broadcast_to(start[1], shape),
                                   np.broadcast_to(start[3], shape))
    sup_state = SupervisorState()
    cl_state = CurrentLoopState(np.zeros_like(x0))
    compiled = None
    if controllers == "compiled":
        # numba: imported where it is used, not by this module's one-rig users (replay)
        from pisc_sim import batch_controllers

        if batch_controllers.supported(config):
            compiled = batch_controllers.BatchControllers(
                config, supervisor, x0.size,
                EstimatorState(*(np.broadcast_to(v, shape).reshape(-1) for v in (
                    est_state.x_m, est_state.theta_rad, est_state.x_dot_mps,
                    est_state.theta_dot_radps))) if prime_estimator else None)
    applied = np.zeros_like(x0)
    caught_at = np.full(x0.shape, np.inf)
    first_catch = np.full(x0.shape, np.inf)
    x_min = x0.copy()
    x_max = x0.copy()
    hold_theta = np.zeros_like(x0)
    hold_x = np.zeros_like(x0)
    hold_i2 = np.zeros_like(x0)
    hold_cycles = 0
    unheld_at = np.full(x0.shape, -np.inf)
    faulted = np.zeros(x0.shape, dtype=bool)
    previous_mode = np.full(x0.shape, Mode.SWING_UP.code)
    noise = plant_config.noise
    seed = noise.seed if noise_seed is None else noise_seed
    rng = np.random.default_rng(seed) if noise.any else None
    cycles = int(round(duration_s / period)) + 1
    if compiled is not None:
        # the measurement, the controllers and the outcomes in the compiled pass; the
        # plant steps the rows in place with the input the pass put through the actuator
        # (a plant set or one delay a rig: Plant.advance with the commands)
        compiled.track(sim, x0.reshape(-1), hold_box)
        flat = np.array(y.reshape(-1, y.shape[-1]), dtype=float, order="C")
        applied = applied.reshape(-1)
        in_place = sim.rigs is None and not delay.ndim  # one duration, one rig's constants
        acting = applied  # through the actuator (zero volts act as zero)
        for k in range(cycles):
            t = k * period
            draws = None if rng is None else rng.standard_normal(x0.shape + (3,))
            hold = t >= hold_start_s
            hold_cycles += hold
            command, acts = compiled.cycle(flat, applied, None if draws is None else
                                           draws.reshape(-1, 3), t, hold)
            if in_place:
                if delay > 0.0:
                    sim.advance_in_place(flat, acting, float(delay))
                sim.advance_in_place(flat, acts, period - float(delay))
            elif delay.ndim:
                flat = sim.advance(flat, applied, delay)
                flat = sim.advance(flat, command, period - delay)
            elif delay > 0.0:
                flat = sim.advance(flat, applied, float(delay))
                flat = sim.advance(flat, command, period - float(delay))
            else:
                flat = sim.advance(flat, command, period)
            applied, acting = command, acts
            if progress is not None:
                progress(k + 1, cycles)
        book = {name: v.reshape(shape) for name, v in compiled.outcomes(flat).items()}
        caught_at, first_catch = book["caught_at"], book["first_catch"]
        faulted = book["faulted"]
        x_min, x_max, hold_theta = book["x_min"], book["x_max"], book["hold_theta"]
        hold_x, hold_i2 = book["hold_x"], book["hold_i2"]
        unheld_at = book["unheld_at"]
    else:  # the sensors' model over arrays, the laws rig by rig
        for k in range(cycles):
            t = k * period
            draws = None if rng is None else rng.standard_normal(x0.shape + (3,))
            x, theta, current = sim.measurement(y, applied, draws)
            est_state, x_dot, theta_dot = estimator_update(
                config.estimator, period, est_state, x, theta)
            sup_state, force, mode = supervisor.update(sup_state, x, x_dot, theta,
                                                       theta_dot)
            fault = mode == Mode.FAULT.code
            cl_state, i_d, voltage = current_loop_cycle(
                config.plant.motor, config.current_loop, period, cl_state, force, current,
                fault)
            faulted |= fault
            command = plant_command(plant_config, setpoint_a=i_d, voltage_v=voltage)
            catching = mode == Mode.CATCH.code
            entered = catching & (previous_mode != Mode.CATCH.code)
            caught_at = np.where(entered, t, np.where(catching, caught_at, np.inf))
            first_catch = np.where(catching & ~np.isfinite(first_catch), t, first_catch)
            previous_mode = mode
            off_upright = np.abs(wrap_to_upright(y[..., THETA]))
            unheld_at = np.where((off_upright < hold_box[0]) & (np.abs(y[..., X]) < hold_box[1]),
                                 unheld_at, t)
            if t >= hold_start_s:
                hold_theta = np.maximum(hold_theta, off_upright)
                hold_x = np.maximum(hold_x, np.abs(y[..., X]))
                hold_i2 += i_d ** 2
                hold_cycles += 1
            if delay.ndim:
                flat = y.reshape(-1, y.shape[-1])
                flat = sim.advance(flat, applied.reshape(-1), delay)
                y = sim.advance(flat, command.reshape(-1), period - delay).reshape(y.shape)
            elif delay > 0.0:
                y = sim.advance(y, applied, float(delay))
                y = sim.advance(y, command, period - float(delay))
            else:
                y = sim.advance(y, command, period)
            applied = command
            x_min = np.minimum(x_min, y[..., X])
            x_max = np.maximum(x_max, y[..., X])
            if progress is not None:
                progress(k + 1, cycles)
    rms = np.sqrt(hold_i2 / hold_cycles) if hold_cycles else np.full(x0.shape, np.nan)
    return BatchOutcome(caught_at, x_min, x_max, hold_theta, hold_x, faulted, first_catch, rms,
                        unheld_at)
