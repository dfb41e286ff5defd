"""N rigs stepped together: the plant's compiled kernel, the sensors, the latency, the
estimator and the current loop, each rig with its own constants, reset a few at a time.

:class:`Rigs` is what both environments run: the single environment is one rig of it,
the vector environment N. A step (:meth:`Rigs.step`) is the graph's cycle after the
controllers, in one compiled pass over the rigs (:func:`pisc_gym.compiled.step`): the
command answering the last sample takes effect each rig's latency into the period (the
input held before it until then, as :class:`pisc_plant.sampled.SampledPlant` does),
the plant integrates to the next sample, the reward is taken and the sensors measure.

The rigs are a plant set (:func:`pisc_plant.plant_config.plant_set`): every rig has its own
column of the kernel's constants (:func:`pisc_plant.plant_config.pack_constants`) and its own
operator tables for its steps, in the kernel's blocks (:func:`pisc_plant.kernel_sets.lanes`).
Each rig takes, in each part of the period, the substeps a plant of its own takes for
that part's duration (:meth:`pisc_plant.plant.Plant.advance`); the rigs of one number of
substeps step together (a group), the others keep their state in that call. A reset
writes the new rigs' columns and computes their tables alone. The kernel gives a rig of
a set the same bits as a plant of its own, so a rig here gives the pure closed loop's
bits.

Measurement noise: each rig has its own generator, seeded by its draw
(:attr:`pisc_gym.task.RigDraw.noise_seed`), three standard normal values a sample as
:class:`~pisc_plant.sampled.SampledPlant` draws them, taken in blocks of up to
:data:`NOISE_BLOCK` samples (the same stream).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from pisc_control import current_loop, estimator
from pisc_gym import compiled
from pisc_gym.task import RigDraws, Task
from pisc_plant import kernel_sets, layout
from pisc_plant.plant import Plant
from pisc_plant.plant_config import pack_constants, plant_set

__all__ = ["NOISE_BLOCK", "Rigs"]

#: samples of noise drawn at once per rig (fewer for many rigs: at most ~64 MB in all)
NOISE_BLOCK = 512


class Rigs:
    """``n`` rigs of a :class:`~pisc_gym.task.Task`; arrays are per rig, first axis."""

    def __init__(self, task: Task, n: int) -> None:
        if n < 1:
            raise ValueError(f"num_envs = {n}: at least one rig")
        self.task = task
        self.n = n
        base = task.plant
        self.plant = Plant(base)  # the uniform plant: layout, start states
        lay = self.plant.layout
        self._layout = (lay.armature, lay.filters)
        self._stops = lay.end_stops
        self._method = layout.METHODS.index(base.integrator.method)
        self._nominal = self.plant.nominal_substep_s
        self.period_s = base.loop.period_s
        p0 = pack_constants(base)
        self.constants = np.repeat(p0[:, None], n, axis=1)  # (N_CONSTANTS, n)
        self._lanes = kernel_sets.lanes(self.constants)
        self._full = base.models.has_current_state
        self._rates = np.zeros(n)
        if self._full:
            kernel_sets.armature_rates(self.constants, self._rates)
        filters = base.models.sensor_filters
        self._w = (p0[layout.P_WIR] if filters else 0.0, p0[layout.P_WCUR] if filters else 0.0,
                   p0[layout.P_WCUR] / p0[layout.P_CURSCALE])
        self.latency_s = np.full(n, base.actuator.command_delay_s)
        # each part's substeps (0: no step) and step per rig, and its groups: (counts (G,),
        # steps (G, n), operator tables (G, blocks, N_TABLE * BLOCK))
        self._substeps = [np.zeros(n, dtype=np.int64), np.zeros(n, dtype=np.int64)]
        self._steps = [np.zeros(n), np.zeros(n)]
        self._groups = [self._no_groups(), self._no_groups()]
        self._set_parts(np.arange(n))
        self.y = np.ascontiguousarray(self.plant.initial_state(np.zeros(n)))
        self.applied = np.zeros(n)  # the input held, through the actuator
        self.steps = np.zeros(n, dtype=np.int64)
        # the action, and the task's constants for the compiled step
        models = base.models
        if task.action == "voltage":
            self._kind = compiled.ACTION_VOLTAGE
        else:
            self._kind = compiled.ACTION_FORCE if models.force_input else compiled.ACTION_CURRENT
        c = np.zeros(compiled.N_T)
        c[compiled.T_MIDDLE] = task.middle_m
        c[compiled.T_X_WEIGHT], c[compiled.T_VOLTAGE_WEIGHT] = task.x_weight, task.voltage_weight
        c[compiled.T_SHARE_LIMIT] = (task.current_limit_a if models.force_input
                                     else task.voltage_limit_v)
        c[compiled.T_LOW], c[compiled.T_HIGH] = task.safe_range
        c[compiled.T_FALL] = task.fall_rad
        c[compiled.T_CURRENT_LIMIT] = task.current_limit_a
        actuator = base.actuator
        c[compiled.T_FULL_SCALE] = actuator.full_scale_v
        c[compiled.T_LEVELS] = float(actuator.command_levels)
        c[compiled.T_STEP_V] = actuator.step_v
        self._task_constants = c
        # sensors and noise
        self._sensors = (compiled.SENSORS_IDEAL if models.sensors == "ideal"
                         else compiled.SENSORS_QUANTISED)
        self._indices = (lay.current_index, lay.ir_index, lay.current_sensor_index)
        self._sensor_m, self._ir_table = compiled.sensor_constants(base.sensors)
        self.noise_std = np.zeros((n, 3))
        self.noisy = np.zeros(n, dtype=np.bool_)
        self._generators: list[np.random.Generator | None] = [None] * n
        self._block = int(min(NOISE_BLOCK, max(16, 2_800_000 // n)))
        self._noise = np.zeros((n, self._block, 3))
        self._noise_at = np.zeros(n, dtype=np.int64)
        self.measured = np.zeros((n, 3))  # x, theta, i of the last sample
        self.true_current = np.zeros(n)
        # the estimator's differences (4.7), (4.9)
        est = task.config.estimator
        a, b = estimator.estimator_constants(est, self.period_s)
        self._est = np.array([a, b, self.period_s])
        self._est_n = est.difference_periods
        self._seen = np.zeros(n, dtype=np.int64)
        self._x_hist = np.zeros((n, self._est_n))
        self._theta_hist = np.zeros((n, self._est_n))
        self._v = np.zeros((2, n))
        self.velocity = np.zeros((n, 2))
        # the current loop (3.47) for a set-point action: k_m / r = 1 makes i_d the action
        c_loop = list(current_loop.current_loop_constants(base.motor, task.config.current_loop,
                                                          self.period_s))
        c_loop[current_loop.C_FORCE_PER_AMP] = 1.0
        self._loop_constants = tuple(c_loop)
        self.integral = np.zeros(n)
        self.voltage = np.zeros(n)  # the voltage commanded at the last step
        self.setpoint = np.zeros(n)  # the set-point of the last step (current action)
        self._not_done = np.zeros(n, dtype=np.bool_)
        self._obs = np.zeros((n, 5 if task.velocities else 3))
        self._true_state = np.zeros((n, 5))

    # -- the parts of a period -----------------------------------------------------------

    def _no_groups(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        width = kernel_sets.N_TABLE * kernel_sets.BLOCK if self._method == layout.EXPRK4 else 0
        blocks = self._lanes.shape[0]
        return (np.zeros(0, dtype=np.int64), np.zeros((0, self.n)),
                np.zeros((0, blocks, width)))

    def _set_parts(self, idx: np.ndarray) -> None:
        """The parts' substeps, steps and operator tables of rigs ``idx`` (new latencies
        or constants): each part's duration cut as :meth:`Plant.advance` cuts it."""
        period = self.period_s
        latency = self.latency_s[idx]
        late = latency >= period  # the command misses the period
        for part, durations in enumerate((np.where(late, period, latency),
                                          np.where(late, 0.0, period - latency))):
            count = np.maximum(1, np.ceil(durations / self._nominal - 1e-9)).astype(np.int64)
            count[durations == 0.0] = 0  # no step: the rig keeps its state
            self._substeps[part][idx] = count
            self._steps[part][idx] = np.where(count > 0, durations / np.maximum(count, 1), 0.0)
            self._regroup(part, idx)

    def _regroup(self, part: int, idx: np.ndarray) -> None:
        counts, steps, tables = self._groups[part]
        substeps = self._substeps[part]
        present = np.flatnonzero(np.bincount(substeps)[1:]) + 1
        if not np.array_equal(present, counts):  # a number of substeps came or went
            kept = {int(c): g for g, c in enumerate(counts)}
            new_steps = np.zeros((len(present), self.n))
            new_tables = np.zeros((len(present),) + tables.shape[1:])
            for g, c in enumerate(present.tolist()):
                if c in kept:
                    new_steps[g] = steps[kept[c]]
                    new_tables[g] = tables[kept[c]]
                else:  # a new group: its tables for every rig in it
                    members = np.flatnonzero(substeps == c)
                    new_steps[g, members] = self._steps[part][members]
                    self._tables_of(new_tables[g], members, self._steps[part][members])
            counts, steps, tables = present, new_steps, new_tables
            self._groups[part] = (counts, steps, tables)
        mine = substeps[idx]
        for g, c in enumerate(counts.tolist()):
            steps[g, idx] = np.where(mine == c, self._steps[part][idx], 0.0)
            members = idx[mine == c]
            if len(members):
                self._tables_of(tables[g], members, self._steps[part][members])

    def _tables_of(self, tables: np.ndarray, rigs: np.ndarray, steps: np.ndarray) -> None:
        """The exponential scheme's operators of ``rigs`` for their ``steps``
        (:func:`pisc_plant.kernel_sets.exp_tables`, the same numbers a plant of its own uses)
        into their lanes of ``tables`` (blocks, N_TABLE * BLOCK)."""
        if self._method != layout.EXPRK4:
            return
        m = len(rigs)
        block = kernel_sets.BLOCK
        out = np.empty((-(-m // block), kernel_sets.N_TABLE * block))
        kernel_sets.exp_tables(*self._w, np.ascontiguousarray(self._rates[rigs]),
                               np.ascontiguousarray(steps, dtype=float), out)
        j = np.arange(m)
        values = out.reshape(-1, kernel_sets.N_TABLE, block)[j // block, :, j % block]
        tables.reshape(-1, kernel_sets.N_TABLE, block)[rigs // block, :, rigs % block] = values

    # -- resets --------------------------------------------------------------------------

    def reset(self, rigs: Sequence[int] | np.ndarray, draws: RigDraws) -> None:
        """Put new rigs ``draws`` in the places ``rigs``, at their starts, with nothing
        held, the estimator and the current loop cleared (observe them with
        :meth:`observe`, or step them with :meth:`step` as ``done``)."""
        idx = np.asarray(rigs, dtype=np.int64)
        m = len(idx)
        if m == 0:
            return
        if self.task.physical_names:
            columns = pack_constants(plant_set(self.task.plant, draws.physical))
        else:
            columns = np.repeat(pack_constants(self.task.plant)[:, None], m, axis=1)
        self.constants[:, idx] = columns
        blocks = self._lanes.reshape(self._lanes.shape[0], layout.N_CONSTANTS, kernel_sets.BLOCK)
        blocks[idx // kernel_sets.BLOCK, :, idx % kernel_sets.BLOCK] = columns.T
        if self._full:
            rates = np.zeros(m)
            kernel_sets.armature_rates(np.ascontiguousarray(columns), rates)
            self._rates[idx] = rates
        self.latency_s[idx] = draws.latency_s
        self._set_parts(idx)
        self.noise_std[idx] = draws.noise_std
        self.noisy[idx] = (draws.noise_std > 0.0).any(axis=1)
        for k, seed, noisy in zip(idx.tolist(), draws.noise_seed.tolist(),
                                  self.noisy[idx].tolist()):
            if noisy:
                generator = np.random.default_rng(seed)
                generator.standard_normal(out=self._noise[k])
                self._generators[k] = generator
            else:
                self._generators[k] = None
        self._noise_at[idx] = 0
        self.y[idx] = self.plant.initial_state(*draws.start.T)
        for array in (self.applied, self.integral, self.voltage, self.setpoint):
            array[idx] = 0.0
        self.steps[idx] = 0
        self._seen[idx] = 0
        self._v[:, idx] = 0.0

    # -- stepping ------------------------------------------------------------------------

    def _sample_arguments(self, obs: np.ndarray, true_state: np.ndarray) -> tuple:
        ii, vir, vcur = self._indices
        return (self._sensors, ii, vir, vcur, self.constants, self.noisy, self.noise_std,
                self._noise, self._noise_at, self._sensor_m, self._ir_table, self.measured,
                self.true_current, self.task.velocities, self._est, self._est_n, self._seen,
                self._x_hist, self._theta_hist, self._v, self.velocity, obs, true_state)

    def _refill(self) -> None:
        for k in np.flatnonzero(self._noise_at >= self._block).tolist():
            self._generators[k].standard_normal(out=self._noise[k])  # type: ignore[union-attr]
            self._noise_at[k] = 0

    def observe(self) -> None:
        """Every rig's sample without a step (after a reset): :meth:`observation`,
        :meth:`true_state`."""
        obs, true_state = np.empty_like(self._obs), np.empty((self.n, 5))
        args = self._sample_arguments(obs, true_state)
        compiled.observe(self.y, self.applied, args[0], self._layout[0], *args[1:])
        self._obs, self._true_state = obs, true_state
        self._refill()

    def step(self, action: np.ndarray, done: np.ndarray | None = None
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One period of every rig for its ``action`` (the task's ``action``), except the
        rigs ``done`` (a mask: reset for this step, only observed): (reward, terminated,
        truncated) of the step, each rig's sample in :meth:`observation`,
        :meth:`true_state`, :attr:`voltage`."""
        action = np.ascontiguousarray(action, dtype=float).reshape(self.n)
        if not np.isfinite(action).all():
            k = int(np.flatnonzero(~np.isfinite(action))[0])
            raise ValueError(f"action {action[k]} (rig {k} of {self.n}): an action must be a "
                             "finite number")
        n = self.n
        reward = np.empty(n)
        terminated = np.empty(n, dtype=np.bool_)
        truncated = np.empty(n, dtype=np.bool_)
        obs, true_state = np.empty_like(self._obs), np.empty((n, 5))
        (counts1, hs1, tables1), (counts2, hs2, tables2) = self._groups
        compiled.step(*self._layout, self._not_done if done is None else done, action,
                      self._kind, self._task_constants, self._loop_constants, self.y,
                      self.applied, self._lanes, self._stops, self._method, counts1, hs1,
                      tables1, counts2, hs2, tables2, self.integral, self.voltage,
                      self.setpoint, self.steps, self.task.episode_steps, reward, terminated,
                      truncated, *self._sample_arguments(obs, true_state))
        self._obs, self._true_state = obs, true_state
        self._refill()
        return reward, terminated, truncated

    def observation(self) -> np.ndarray:
        """(n, 3) or with velocities (n, 5): x, theta, i as measured (x_dot, theta_dot)
        at the last sample (a new array each sample)."""
        return self._obs

    def true_state(self) -> np.ndarray:
        """(n, 5): x, x_dot, theta, theta_dot, i (true) at the last sample."""
        return self._true_state

