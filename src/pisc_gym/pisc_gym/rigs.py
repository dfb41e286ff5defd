"""N rigs stepped together: the plant's compiled kernel, the sensors, the latency, the
estimator and the current loop, each rig with its own constants, reset one at a time.

:class:`Rigs` is what both environments run: the single environment is one rig of it,
the vector environment N. A step is the graph's cycle after the controllers: the
command answering the last sample takes effect each rig's latency into the period (the
input held before it until then, as :class:`pisc_plant.sampled.SampledPlant` does),
the plant integrates to the next sample, and the sensors measure it.

The rigs are a plant set (:func:`pisc_plant.plant.plant_set`): every rig has its own
column of the kernel's constants (:func:`pisc_plant.plant.pack_constants`) and its own
operator tables for its steps, in the kernel's blocks (:func:`pisc_plant.kernel.lanes`);
a reset writes the new rig's column and recomputes the tables of the blocks whose rigs
changed, so a vector environment that resets a few rigs a step does not redo the rest.
The kernel gives a rig of a set the same bits as a plant of its own, and each rig takes
the substeps a plant of its own would take for its durations (rigs whose numbers
differ step in separate calls), so a rig here gives the pure closed loop's bits.

Measurement noise: each rig has its own generator, seeded by its draw
(:attr:`pisc_gym.task.RigDraw.noise_seed`), three standard normal values a sample as
:class:`~pisc_plant.sampled.SampledPlant` draws them, taken in blocks of up to
:data:`NOISE_BLOCK` samples (the same stream).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from pisc_control import scalar
from pisc_gym import compiled
from pisc_gym.task import RigDraw, Task
from pisc_model.dynamics import wrap_to_upright
from pisc_plant import kernel, layout
from pisc_plant.plant import Plant, pack_constants, plant_set

__all__ = ["NOISE_BLOCK", "Rigs"]

#: samples of noise drawn at once per rig (fewer for many rigs: at most ~32 MB in all)
NOISE_BLOCK = 256


class Rigs:
    """``n`` rigs of a :class:`~pisc_gym.task.Task`; arrays are per rig, first axis."""

    def __init__(self, task: Task, n: int) -> None:
        if n < 1:
            raise ValueError(f"num_envs = {n}: at least one rig")
        self.task = task
        self.n = n
        base = task.plant
        self.plant = Plant(base)  # the uniform plant: layout, start states, kernels
        lay = self.plant.layout
        self._kernels = kernel.for_layout(lay)
        self._stops = lay.end_stops
        self._method = layout.METHODS.index(base.integrator.method)
        self._nominal = self.plant.nominal_substep_s
        self.period_s = base.loop.period_s
        p0 = pack_constants(base)
        self.constants = np.repeat(p0[:, None], n, axis=1)  # (N_CONSTANTS, n)
        self._lanes = kernel.lanes(self.constants)
        self._full = base.models.has_current_state
        self._rates = np.zeros(n)
        if self._full:
            kernel.armature_rates(self.constants, self._rates)
        filters = base.models.sensor_filters
        self._w = (p0[layout.P_WIR] if filters else 0.0, p0[layout.P_WCUR] if filters else 0.0,
                   p0[layout.P_WCUR] / p0[layout.P_CURSCALE])
        # operator tables by (part, substeps); the durations' groups of the two parts of a
        # period (None: to be made); the blocks whose rigs were reset since the last step
        self._tables: dict[tuple[int, int], np.ndarray] = {}
        self._parts: tuple[dict[int, np.ndarray], dict[int, np.ndarray]] | None = None
        self._stale: set[int] = set()
        self.latency_s = np.full(n, base.actuator.command_delay_s)
        self.y = np.ascontiguousarray(self.plant.initial_state(np.zeros(n)))
        self.applied = np.zeros(n)  # the input held, through the actuator
        self.steps = np.zeros(n, dtype=np.int64)
        # sensors and noise
        models = base.models
        self._sensors = (compiled.SENSORS_IDEAL if models.sensors == "ideal"
                         else compiled.SENSORS_QUANTISED)
        self._armature = lay.armature
        self._sensor_m, self._ir_table = compiled.sensor_constants(base.sensors)
        self.noise_std = np.zeros((n, 3))
        self.noisy = np.zeros(n, dtype=np.bool_)
        self._generators: list[np.random.Generator | None] = [None] * n
        self._block = int(min(NOISE_BLOCK, max(16, 1_400_000 // n)))
        self._noise = np.zeros((n, self._block, 3))
        self._noise_at = np.zeros(n, dtype=np.int64)
        self.measured = np.zeros((n, 3))  # x, theta, i of the last sample
        self.true_current = np.zeros(n)
        # the estimator's differences (4.7), (4.9)
        est = task.config.estimator
        self._est_a, self._est_b = scalar.estimator_constants(est, self.period_s)
        self._est_n = est.difference_periods
        self._seen = np.zeros(n, dtype=np.int64)
        self._x_hist = np.zeros((n, self._est_n))
        self._theta_hist = np.zeros((n, self._est_n))
        self._v = np.zeros((2, n))
        self.velocity = np.zeros((n, 2))
        # the current loop (3.47) for a set-point action: k_m / r = 1 makes i_d the action
        c = list(scalar.current_loop_constants(base.motor, task.config.current_loop,
                                               self.period_s))
        c[scalar.C_FORCE_PER_AMP] = 1.0
        self._loop_constants = tuple(c)
        self.integral = np.zeros(n)
        self.voltage = np.zeros(n)  # the voltage commanded at the last step
        self.setpoint = np.zeros(n)  # the set-point of the last step (current action)

    # -- resets --------------------------------------------------------------------------

    def reset(self, rigs: Sequence[int] | np.ndarray, draws: Sequence[RigDraw]) -> None:
        """Put new rigs ``draws`` in the places ``rigs``, at their starts, with nothing
        held, the estimator and the current loop cleared; then :meth:`observe`."""
        idx = np.asarray(rigs, dtype=np.int64)
        m = len(idx)
        if m == 0:
            return
        names = self.task.physical_names
        if names:
            values = {name: np.array([d.physical[name] for d in draws]) for name in names}
            columns = pack_constants(plant_set(self.task.plant, values))
        else:
            columns = np.repeat(pack_constants(self.task.plant)[:, None], m, axis=1)
        self.constants[:, idx] = columns
        blocks = self._lanes.reshape(self._lanes.shape[0], layout.N_CONSTANTS, kernel.BLOCK)
        blocks[idx // kernel.BLOCK, :, idx % kernel.BLOCK] = columns.T
        if self._full:
            rates = np.zeros(m)
            kernel.armature_rates(np.ascontiguousarray(columns), rates)
            self._rates[idx] = rates
        latency = np.array([d.latency_s for d in draws], dtype=float)
        if not np.array_equal(latency, self.latency_s[idx]):
            self.latency_s[idx] = latency
            self._parts = None
        self._stale.update((idx // kernel.BLOCK).tolist())
        std = np.array([d.noise_std for d in draws], dtype=float).reshape(m, 3)
        self.noise_std[idx] = std
        self.noisy[idx] = (std > 0.0).any(axis=1)
        for k, d in zip(idx.tolist(), draws):
            if self.noisy[k]:
                generator = np.random.default_rng(d.noise_seed)
                generator.standard_normal(out=self._noise[k])
                self._generators[k] = generator
            else:
                self._generators[k] = None
            self._noise_at[k] = 0
        start = np.array([d.start for d in draws], dtype=float).reshape(m, 4)
        self.y[idx] = self.plant.initial_state(*start.T)
        self.applied[idx] = 0.0
        self.steps[idx] = 0
        self._seen[idx] = 0
        self._v[:, idx] = 0.0
        self.integral[idx] = 0.0
        self.voltage[idx] = 0.0
        self.setpoint[idx] = 0.0

    # -- stepping ------------------------------------------------------------------------

    def command(self, action: np.ndarray) -> np.ndarray:
        """The plant's input for each rig's action (the task's ``action``): the voltage
        commanded (kept in :attr:`voltage`) and what the plant gets for it."""
        action = np.asarray(action, dtype=float).reshape(self.n)
        plant = self.task.plant
        if self.task.action == "voltage":
            self.voltage[:] = action
            return plant.actuator.apply(action)
        limit = self.task.current_limit_a
        if plant.models.force_input:  # an ideal force source: the set-point's force (4.2)
            self.setpoint[:] = np.clip(action, -limit, limit)
            self.voltage[:] = 0.0
            return self.constants[layout.P_KF] * self.setpoint
        self.setpoint[:] = np.clip(action, -limit, limit)
        current = np.ascontiguousarray(self.measured[:, 2])
        compiled.current_loop(self._loop_constants, np.ascontiguousarray(action, dtype=float),
                              current, self.integral, self.voltage)
        return plant.actuator.apply(self.voltage)

    def advance(self, applied: np.ndarray) -> None:
        """One period: the held input until each rig's latency, then ``applied``."""
        if self._parts is None:
            period = self.period_s
            late = self.latency_s >= period  # the command misses the period
            self._parts = (self._groups(np.where(late, period, self.latency_s)),
                           self._groups(np.where(late, 0.0, period - self.latency_s)))
        stale, self._stale = self._stale, set()
        for part, inputs in enumerate((self.applied, applied)):
            groups = self._parts[part]
            for key in [k for k in self._tables if k[0] == part and k[1] not in groups]:
                del self._tables[key]
            for count, steps in groups.items():
                tables = self._operator_tables(part, count, steps, stale)
                inputs = np.ascontiguousarray(inputs, dtype=float)
                if self.n <= kernel.CHUNK:
                    self._kernels.advance_set(self.y, inputs, 0, self.n, self._lanes,
                                              self._stops, self._method, count, steps, tables)
                else:
                    self._kernels.advance_set_many(self.y, inputs, self._lanes, self._stops,
                                                   self._method, count, steps, tables)
        self.applied = np.array(applied, dtype=float)
        self.steps += 1

    def _groups(self, durations: np.ndarray) -> dict[int, np.ndarray]:
        """Substeps -> each rig's step (0 for the rigs that take another number): the
        substeps a plant of its own takes for each rig's duration (Plant.advance)."""
        substeps = np.maximum(1, np.ceil(durations / self._nominal - 1e-9)).astype(np.int64)
        groups = {}
        for count in np.unique(substeps).tolist():
            steps = np.where(substeps == count, durations / count, 0.0)
            if steps.any():
                groups[count] = steps
        return groups

    def _operator_tables(self, part: int, count: int, steps: np.ndarray,
                         stale: set[int]) -> np.ndarray:
        """The exponential scheme's operators of every rig for its step, in the kernel's
        blocks (:meth:`pisc_plant.plant.Plant.rig_coefficients`), made again only for
        the blocks ``stale`` (whose rigs were reset since the last step)."""
        blocks = self._lanes.shape[0]
        if self._method != layout.EXPRK4:
            return np.empty((blocks, 0))
        key = (part, count)
        tables = self._tables.get(key)
        if tables is None:
            tables = self._tables[key] = np.empty((blocks, kernel.N_TABLE * kernel.BLOCK))
            changed = np.arange(blocks)
        elif stale:
            changed = np.array(sorted(stale))
        else:
            return tables
        lanes = (changed[:, None] * kernel.BLOCK + np.arange(kernel.BLOCK)).ravel()
        inside = lanes < self.n
        rates = np.zeros(len(lanes))
        rates[inside] = self._rates[lanes[inside]]
        rig_steps = np.zeros(len(lanes))
        rig_steps[inside] = steps[lanes[inside]]
        part_tables = np.empty((len(changed), kernel.N_TABLE * kernel.BLOCK))
        kernel.exp_tables(*self._w, rates, rig_steps, part_tables)
        tables[changed] = part_tables
        return tables

    # -- sampling ------------------------------------------------------------------------

    def observe(self) -> None:
        """Every rig's sample: :attr:`measured`, :attr:`true_current` and (with the
        task's ``velocities``) the estimator's :attr:`velocity`."""
        compiled.measure(self.y, self.applied, self._sensors, self._armature,
                         self.plant.layout.current_index, self.plant.layout.ir_index,
                         self.plant.layout.current_sensor_index,
                         self.constants[layout.P_KER], self.constants[layout.P_R],
                         self.constants[layout.P_KF], self.noisy, self.noise_std, self._noise,
                         self._noise_at, self._sensor_m, self._ir_table, self.measured,
                         self.true_current)
        for k in np.flatnonzero(self._noise_at >= self._block).tolist():
            self._generators[k].standard_normal(out=self._noise[k])  # type: ignore[union-attr]
            self._noise_at[k] = 0
        if self.task.velocities:
            compiled.estimate(np.ascontiguousarray(self.measured[:, 0]),
                              np.ascontiguousarray(self.measured[:, 1]), self._est_a,
                              self._est_b, self.period_s, self._est_n, self._seen,
                              self._x_hist, self._theta_hist, self._v[0], self._v[1],
                              self.velocity)

    def observation(self) -> np.ndarray:
        """(n, 3) or with velocities (n, 5): x, theta, i as measured (x_dot, theta_dot)."""
        if self.task.velocities:
            return np.concatenate([self.measured, self.velocity], axis=1)
        return self.measured.copy()

    def true_state(self) -> np.ndarray:
        """(n, 5): x, x_dot, theta, theta_dot, i (true)."""
        return np.concatenate([self.y[:, :4], self.true_current[:, None]], axis=1)

    def outcome(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(reward, terminated, truncated) of the last step (:mod:`pisc_gym.task`)."""
        task = self.task
        x = self.y[:, 0]
        off = x - task.middle_m
        theta = self.y[:, 2]
        if task.plant.models.force_input:
            share = self.setpoint / task.current_limit_a
        else:
            share = self.voltage / task.voltage_limit_v
        with np.errstate(invalid="ignore", over="ignore"):
            reward = (0.5 * (1.0 + np.cos(theta)) - task.x_weight * off * off
                      - task.voltage_weight * share * share)
            low, high = task.safe_range
            terminated = ~((x >= low) & (x <= high)) | ~np.isfinite(self.y).all(axis=1)
            if math.isfinite(task.fall_rad):
                terminated |= ~(np.abs(wrap_to_upright(theta)) <= task.fall_rad)
        reward = np.where(np.isfinite(reward), reward, 0.0)
        truncated = self.steps >= task.episode_steps
        return reward, terminated, truncated
