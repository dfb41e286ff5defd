"""The environments' step over all rigs, compiled (numba): one pass a step.

:func:`step` does for every rig what the graph's cycle does after the controllers, in
one loop over the rigs (split between the cores, ``prange``, for more than
:data:`pisc_plant.kernel_batch.CHUNK` rigs): the action into the plant's input (the
actuator's saturation and quantisation, or PISC's current loop), the plant over the
period in its two parts (the input held until the rig's latency, then the new one:
the plant kernel's block step, :func:`pisc_plant.kernel_sets.block_step`, each rig with its
own constants and operator tables), the reward, termination and truncation, the
sensors' measurement and the estimator's differences. :func:`observe` is the
measurement and the estimator alone (at a reset). The arithmetic is the one the rest
of PISC does, operation for operation, so a rig here gives the same bits as the pure
closed loop (:func:`pisc_sim.closed_loop.simulate`):

* the measurement (:func:`_sample_rows`) is :meth:`pisc_plant.plant.Plant.
  measurement_one` (quantised sensors behind their RC filters: the noise at the ADC's
  input, the 10-bit codes, the encoder count, the host's conversions with the IR curve
  (4.8) of every code from numpy) or :meth:`~pisc_plant.plant.Plant.measurement` with
  ideal sensors, with one noise standard deviation a rig (a plant set's
  ``noise.*_std_*``);
* the estimator runs :func:`pisc_control.estimator.estimator_step`, the differences (4.7),
  (4.9) over N periods with the optional low-pass, on each rig's own window;
* the current action runs :func:`pisc_control.current_loop.current_loop_step`, the PI loop
  (3.47), and the bridge :func:`pisc_sim.batch_controllers._actuator`
  (:meth:`pisc_model.params.ActuatorParams.apply`).

The control laws are not copied here: they are compiled from their modules' source,
as :mod:`pisc_sim.batch_controllers` compiles them (importing it registers the helpers
they call). numba's cache keys an entry on its own file's time stamp only, and the pass
holds the code of the kernel and its vector maths (:data:`pisc_plant.kernel_jit.SOURCES`),
the laws and the bridge: when one of those files is newer than the cache's index, the
index is removed here before numba reads it
(:func:`pisc_sim.batch_controllers.drop_stale_cache`) and the pass compiles anew.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from pisc_control import current_loop, estimator, floatmath
from pisc_plant import kernel_batch, kernel_jit, kernel_sets
from pisc_plant.layout import ARM_FORCE, ARM_FULL, ARM_QUASI_STATIC, P_KER, P_KF, P_R
from pisc_sim import batch_controllers  # registers the laws' helpers for numba

__all__ = ["ACTION_CURRENT", "ACTION_FORCE", "ACTION_VOLTAGE", "SENSORS_IDEAL",
           "SENSORS_QUANTISED", "observe", "sensor_constants", "step"]


batch_controllers.drop_stale_cache(__file__, "*", (*kernel_jit.source_paths(), batch_controllers,
                                                 *batch_controllers.LAW_MODULES))

SENSORS_QUANTISED, SENSORS_IDEAL = 0, 1
#: what an action is: the armature voltage; the current set-point through the PI loop;
#: the set-point of an ideal force source (its force k_m / r i_d, (4.2))
ACTION_VOLTAGE, ACTION_CURRENT, ACTION_FORCE = 0, 1, 2
# places in the task's constants (``task`` of :func:`step`)
(T_MIDDLE, T_X_WEIGHT, T_VOLTAGE_WEIGHT, T_SHARE_LIMIT, T_LOW, T_HIGH, T_FALL,
 T_CURRENT_LIMIT, T_FULL_SCALE, T_LEVELS, T_STEP_V, N_T) = range(12)

_estimator_step = numba.njit(estimator.estimator_step, error_model="numpy", inline="always")
_current_loop_step = numba.njit(current_loop.current_loop_step, error_model="numpy",
                                inline="always")
_wrap = numba.njit(floatmath.wrap, error_model="numpy", inline="always")
_clip = numba.njit(floatmath.clip, error_model="numpy", inline="always")
_actuator = batch_controllers._actuator
# the plant kernel's step of one block of a plant set (pisc_plant's entry points gather
# a block's states, step it and scatter them: here the step of a period, both its parts,
# the outcome and the measurement are one pass)
_lanes_set = kernel_sets.block_step
BLOCK = kernel_sets.BLOCK

# places in the measurement's sensor constants
(M_LSB, M_LOW, M_TOP, M_IR_ORIGIN, M_IR_EXPONENT, M_CURRENT_SCALE, M_CURRENT_OFFSET,
 M_ENCODER_ZERO, M_RAD_PER_COUNT, N_M) = range(10)


def sensor_constants(sensors) -> tuple[np.ndarray, np.ndarray]:
    """The measurement's constants of :class:`pisc_model.params.SensorParams`, and the
    host's IR position of every ADC code by numpy's power, as
    :func:`pisc_model.sensors.decode` takes it (the table the compiled batch uses)."""
    from pisc_model import sensors as sensor_model

    s = sensors
    m = np.zeros(N_M)
    m[M_LSB], m[M_LOW], m[M_TOP] = s.adc_lsb_v, s.adc_ref_low_v, s.adc_levels - 1
    m[M_IR_ORIGIN], m[M_IR_EXPONENT] = s.ir_origin_m, s.ir_exponent
    m[M_CURRENT_SCALE], m[M_CURRENT_OFFSET] = s.current_scale_a_per_v, s.current_offset_a
    m[M_ENCODER_ZERO], m[M_RAD_PER_COUNT] = s.encoder_zero_rad, s.encoder_rad_per_count
    table = sensor_model.ir_position(s, sensor_model.adc_voltage(s, np.arange(s.adc_levels)))
    return m, np.ascontiguousarray(table, dtype=float)


_jit = numba.njit(cache=True, error_model="numpy")
_inline = numba.njit(error_model="numpy", inline="always")


@_inline
def _sample_rows(lo, hi, y, applied, kind, armature, ii, vir, vcur, constants, noisy, std,
                 noise, noise_at, m, ir_table, measured, true_current, velocities, est, est_n,
                 seen, x_hist, theta_hist, v, velocity, obs, true_state):
    """Rigs lo..hi's sample: the measurement of each state ``y[r]`` into ``measured[r]``
    (x [m], theta [rad], i [A]), the true armature current into ``true_current[r]``, the
    estimator's differences into ``velocity[r]`` (with ``velocities``), the observation
    ``obs[r]`` and the true state ``true_state[r]`` (x, x_dot, theta, theta_dot, i).

    ``applied``: the input held at the sample, through the actuator (it sets the current
    of a quasi-static armature, (2.81) with L di/dt = 0, and of an ideal force source,
    (4.2)); ``constants`` (N_CONSTANTS, rigs): each rig's k_e / r, R and k_m / r.
    ``noisy[r]``: the rig draws noise, its three standard normal values
    ``noise[r, noise_at[r]]`` (a block of its stream; ``noise_at[r]`` then moves on),
    scaled by ``std[r]``. A state that is not finite reads NaN. The estimator: (0, 0) at
    a rig's first sample, else the difference over the window of its last ``est_n``
    samples (``x_hist``, ``theta_hist`` (rigs, est_n), a ring written at ``seen[r] %
    est_n``), low-passed with the previous estimate ``v[:, r]`` when est[0] > 0, as
    :class:`pisc_control.estimator.OneRigEstimator` steps it. (Each choice of the layout is
    a loop of its own: branches on it inside one loop made the pass ten times slower.)
    """
    if armature == ARM_FULL:
        for r in range(lo, hi):
            true_current[r] = y[r, ii]
    elif armature == ARM_FORCE:
        for r in range(lo, hi):
            true_current[r] = applied[r] / constants[P_KF, r]
    else:
        for r in range(lo, hi):
            true_current[r] = (applied[r] - constants[P_KER, r] * y[r, 1]) / constants[P_R, r]
    if kind == SENSORS_IDEAL:  # Plant._noisy
        for r in range(lo, hi):
            x = y[r, 0]
            theta = y[r, 2]
            current = true_current[r]
            if noisy[r]:
                d = noise_at[r]
                noise_at[r] = d + 1
                x = x + std[r, 0] * noise[r, d, 0]
                theta = theta + std[r, 1] * noise[r, d, 1]
                current = current + std[r, 2] * noise[r, d, 2]
            measured[r, 0] = x
            measured[r, 1] = theta
            measured[r, 2] = current
    else:
        lsb, low, top = m[M_LSB], m[M_LOW], m[M_TOP]
        for r in range(lo, hi):
            theta = y[r, 2]
            v_ir = y[r, vir]
            v_cur = y[r, vcur]
            if noisy[r]:  # Plant.measurement_one: the noise at the ADC's input
                d = noise_at[r]
                noise_at[r] = d + 1
                theta = theta + std[r, 1] * noise[r, d, 1]
                distance = max(m[M_IR_ORIGIN] - y[r, 0], 1e-3)
                v_ir = v_ir + v_ir / (m[M_IR_EXPONENT] * distance) * std[r, 0] * noise[r, d, 0]
                v_cur = v_cur + std[r, 2] * noise[r, d, 2] / m[M_CURRENT_SCALE]
            turns = (theta - m[M_ENCODER_ZERO]) / m[M_RAD_PER_COUNT] + 0.5
            if not (math.isfinite(v_ir) and math.isfinite(v_cur) and abs(turns) < 2.0 ** 62):
                measured[r, 0] = measured[r, 1] = measured[r, 2] = np.nan
                continue
            ir_code = min(max(np.floor((v_ir - low) / lsb), 0.0), top)  # sensors.adc_code
            cur_code = min(max(np.floor((v_cur - low) / lsb), 0.0), top)
            measured[r, 0] = ir_table[int(ir_code)]
            measured[r, 1] = np.floor(turns) * m[M_RAD_PER_COUNT] + m[M_ENCODER_ZERO]
            measured[r, 2] = m[M_CURRENT_SCALE] * (cur_code * lsb + low) - m[M_CURRENT_OFFSET]
    if velocities:
        a, b, period = est[0], est[1], est[2]
        for r in range(lo, hi):
            x = measured[r, 0]
            theta = measured[r, 1]
            s = seen[r]
            if s == 0:
                x_dot = 0.0
                theta_dot = 0.0
            else:
                k = min(s, est_n)  # samples in the window
                span = period if k <= 1 else k * period
                oldest = (s - k) % est_n
                x_dot, theta_dot = _estimator_step(a, b, span, x, theta, x_hist[r, oldest],
                                                   theta_hist[r, oldest], v[0, r], v[1, r])
            x_hist[r, s % est_n] = x
            theta_hist[r, s % est_n] = theta
            seen[r] = s + 1
            v[0, r] = x_dot
            v[1, r] = theta_dot
            velocity[r, 0] = x_dot
            velocity[r, 1] = theta_dot
            obs[r, 3] = x_dot
            obs[r, 4] = theta_dot
    for r in range(lo, hi):
        obs[r, 0] = measured[r, 0]
        obs[r, 1] = measured[r, 1]
        obs[r, 2] = measured[r, 2]
        for j in range(4):
            true_state[r, j] = y[r, j]
        true_state[r, 4] = true_current[r]


@_jit
def _observe_rows(lo, hi, y, applied, kind, armature, ii, vir, vcur, constants, noisy, std,
                  noise, noise_at, m, ir_table, measured, true_current, velocities, est,
                  est_n, seen, x_hist, theta_hist, v, velocity, obs, true_state):
    _sample_rows(lo, hi, y, applied, kind, armature, ii, vir, vcur, constants, noisy, std,
                 noise, noise_at, m, ir_table, measured, true_current, velocities, est, est_n,
                 seen, x_hist, theta_hist, v, velocity, obs, true_state)


def observe(*args) -> None:
    """Every rig's sample (:func:`_sample_rows`' arguments after ``hi``), without a step:
    a reset's first observation."""
    _observe_rows(0, args[0].shape[0], *args)


@_inline
def _command_rows(lo, hi, done, action, kind, task, loop, measured, integral, voltage,
                  setpoint, constants, new):
    """The input to the plant of rigs lo..hi not ``done`` for their actions (``kind``,
    ``ACTION_*``) into ``new[r - lo]``; the voltage commanded, the set-point and the
    current loop's integral kept."""
    full_scale, levels, step_v = task[T_FULL_SCALE], task[T_LEVELS], task[T_STEP_V]
    limit = task[T_CURRENT_LIMIT]
    if kind == ACTION_VOLTAGE:
        for r in range(lo, hi):
            if not done[r]:
                voltage[r] = action[r]
                new[r - lo] = _actuator(full_scale, levels, step_v, action[r])
    elif kind == ACTION_FORCE:
        for r in range(lo, hi):
            if not done[r]:
                setpoint[r] = _clip(action[r], -limit, limit)
                voltage[r] = 0.0
                new[r - lo] = constants[P_KF, r] * setpoint[r]
    else:
        for r in range(lo, hi):
            if not done[r]:
                setpoint[r] = _clip(action[r], -limit, limit)
                _, voltage[r], integral[r] = _current_loop_step(loop, False, action[r],
                                                                measured[r, 2], integral[r])
                new[r - lo] = _actuator(full_scale, levels, step_v, voltage[r])


@_inline
def _outcome_rows(lo, hi, done, y, kind, task, voltage, setpoint, applied, new, steps,
                  episode_steps, reward, terminated, truncated):
    """Rigs lo..hi's reward, termination and truncation after their step
    (:mod:`pisc_gym.task`), the input they now hold, their step count; 0 and False for
    the rigs ``done``."""
    commanded = setpoint if kind == ACTION_FORCE else voltage
    size = y.shape[1]
    middle, limit = task[T_MIDDLE], task[T_SHARE_LIMIT]
    w_x, w_u = task[T_X_WEIGHT], task[T_VOLTAGE_WEIGHT]
    low, high, fall = task[T_LOW], task[T_HIGH], task[T_FALL]
    falls = math.isfinite(fall)
    for r in range(lo, hi):
        if done[r]:
            reward[r] = 0.0
            terminated[r] = False
            truncated[r] = False
            continue
        applied[r] = new[r - lo]
        steps[r] += 1
        x = y[r, 0]
        off = x - middle
        theta = y[r, 2]
        share = commanded[r] / limit
        value = 0.5 * (1.0 + math.cos(theta)) - w_x * off * off - w_u * share * share
        reward[r] = value if math.isfinite(value) else 0.0
        finite = True
        for j in range(size):
            finite = finite and math.isfinite(y[r, j])
        out = not (x >= low and x <= high) or not finite
        if falls:
            out = out or not (abs(_wrap(theta)) <= fall)
        terminated[r] = out
        truncated[r] = steps[r] >= episode_steps


@_inline
def _part(cols, us, h, p, stops, tables, method, substeps, arm, filt):
    """The kernel's block step (:func:`pisc_plant.kernel_sets.block_step`) for the layout
    (arm, filt), each a constant of its own compilation there."""
    if arm == ARM_FULL:
        if filt:
            _lanes_set(cols, us, h, p, stops, tables, method, substeps, ARM_FULL, True, True)
        else:
            _lanes_set(cols, us, h, p, stops, tables, method, substeps, ARM_FULL, False, True)
    elif arm == ARM_QUASI_STATIC:
        if filt:
            _lanes_set(cols, us, h, p, stops, tables, method, substeps, ARM_QUASI_STATIC, True,
                       True)
        else:
            _lanes_set(cols, us, h, p, stops, tables, method, substeps, ARM_QUASI_STATIC,
                       False, True)
    elif filt:
        _lanes_set(cols, us, h, p, stops, tables, method, substeps, ARM_FORCE, True, True)
    else:
        _lanes_set(cols, us, h, p, stops, tables, method, substeps, ARM_FORCE, False, True)


@_jit
def _step_rows(lo, hi, arm, filt, done, action, kind, task, loop, y, applied, p, stops,
               method, counts1, hs1, tables1, counts2, hs2, tables2, integral, voltage,
               setpoint, steps, episode_steps, reward, terminated, truncated, sensors, ii,
               vir, vcur, constants, noisy, std, noise, noise_at, m, ir_table, measured,
               true_current, velocities, est, est_n, seen, x_hist, theta_hist, v, velocity,
               obs, true_state):
    """:func:`step` of rows lo..hi (lo a multiple of BLOCK), a block at a time."""
    cols = np.zeros(7 * BLOCK)
    new = np.zeros(BLOCK)
    h = np.zeros(BLOCK)
    for start in range(lo, hi, BLOCK):
        end = min(hi, start + BLOCK)
        rigs = end - start
        block = start // BLOCK
        _command_rows(start, end, done, action, kind, task, loop, measured, integral,
                      voltage, setpoint, constants, new)
        for k in range(rigs):
            r = start + k
            cols[k] = y[r, 0]
            cols[BLOCK + k] = y[r, 1]
            cols[2 * BLOCK + k] = y[r, 2]
            cols[3 * BLOCK + k] = y[r, 3]
            if ii >= 0:
                cols[4 * BLOCK + k] = y[r, ii]
            if vir >= 0:
                cols[5 * BLOCK + k] = y[r, vir]
                cols[6 * BLOCK + k] = y[r, vcur]
        # the held input up to each rig's latency, then the new one; a rig reset for this
        # step (done) keeps its start (its step 0 keeps its state)
        for g in range(counts1.shape[0]):
            for k in range(rigs):
                h[k] = 0.0 if done[start + k] else hs1[g, start + k]
            _part(cols, applied[start:end], h[:rigs], p[block], stops, tables1[g, block],
                  method, counts1[g], arm, filt)
        for g in range(counts2.shape[0]):
            for k in range(rigs):
                h[k] = 0.0 if done[start + k] else hs2[g, start + k]
            _part(cols, new[:rigs], h[:rigs], p[block], stops, tables2[g, block], method,
                  counts2[g], arm, filt)
        for k in range(rigs):
            r = start + k
            y[r, 0] = cols[k]
            y[r, 1] = cols[BLOCK + k]
            y[r, 2] = cols[2 * BLOCK + k]
            y[r, 3] = cols[3 * BLOCK + k]
            if ii >= 0:
                y[r, ii] = cols[4 * BLOCK + k]
            if vir >= 0:
                y[r, vir] = cols[5 * BLOCK + k]
                y[r, vcur] = cols[6 * BLOCK + k]
        _outcome_rows(start, end, done, y, kind, task, voltage, setpoint, applied, new, steps,
                      episode_steps, reward, terminated, truncated)
        _sample_rows(start, end, y, applied, sensors, arm, ii, vir, vcur, constants, noisy,
                     std, noise, noise_at, m, ir_table, measured, true_current, velocities,
                     est, est_n, seen, x_hist, theta_hist, v, velocity, obs, true_state)


@numba.njit(cache=True, error_model="numpy", parallel=True)
def _step_many(arm, filt, done, action, kind, task, loop, y, applied, p, stops, method,
               counts1, hs1, tables1, counts2, hs2, tables2, integral, voltage, setpoint,
               steps, episode_steps, reward, terminated, truncated, sensors, ii, vir, vcur,
               constants, noisy, std, noise, noise_at, m, ir_table, measured, true_current,
               velocities, est, est_n, seen, x_hist, theta_hist, v, velocity, obs,
               true_state):
    rigs = done.shape[0]
    for c in numba.prange((rigs + kernel_batch.CHUNK - 1) // kernel_batch.CHUNK):
        _step_rows(c * kernel_batch.CHUNK, min(rigs, (c + 1) * kernel_batch.CHUNK), arm, filt,
                   done, action, kind, task, loop, y, applied, p, stops, method, counts1, hs1,
                   tables1, counts2, hs2, tables2, integral, voltage, setpoint, steps,
                   episode_steps, reward, terminated, truncated, sensors, ii, vir, vcur,
                   constants, noisy, std, noise, noise_at, m, ir_table, measured,
                   true_current, velocities, est, est_n, seen, x_hist, theta_hist, v,
                   velocity, obs, true_state)


def step(arm: int, filt: bool, *args) -> None:
    """One period of every rig, in place: the action's input (``kind``, ``ACTION_*``),
    the plant over the period's two parts, the outcome, the sample.

    ``args``: ``done`` (rigs reset for this step: not stepped, their outcome 0, only
    sampled), ``action``, ``kind``, ``task`` (``T_*``), ``loop``
    (:func:`pisc_control.current_loop.current_loop_constants`), the state ``y`` (rigs, size),
    the input held ``applied``, the plant's constants in the kernel's blocks ``p``,
    ``stops``, ``method``; each part's substep counts (G,), steps (G, rigs) and
    operator tables (G, blocks, N_TABLE * BLOCK) (a rig steps in the group of its count,
    with step 0 in the others); the current loop's integral, the voltage and set-point
    commanded, the steps, the episode's length; the outcome's arrays; then the sample's
    (:func:`_sample_rows`). Chunks of :data:`pisc_plant.kernel_batch.CHUNK` rigs are shared
    between numba's threads.
    """
    if args[0].shape[0] > kernel_batch.CHUNK:
        _step_many(arm, filt, *args)
    else:
        _step_rows(0, args[0].shape[0], arm, filt, *args)
