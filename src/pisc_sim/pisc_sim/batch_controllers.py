"""The controller cores of a batch, compiled: one pass over the rigs per cycle (numba).

:func:`pisc_sim.closed_loop.simulate_batch` runs the estimator, the supervisor and the
current loop of every rig each cycle. Their numpy cores (:mod:`pisc_control`) do that with
about a hundred array operations a cycle, each a pass over all the rigs; here one compiled
loop over the rigs, split between the cores (``prange``), does the same arithmetic for one
rig at a time. The operations are the numpy cores', in their order and grouping, with
the constants the cores compute in Python computed the same way in :class:`BatchControllers`,
so every rig gets the same bits as from the numpy cores (and from the nodes, which run
those cores on one rig): numba compiles without ``fastmath``, so no multiply-add is fused
and nothing is reassociated, and ``math.sin``/``math.cos`` are the C library's, which are
numpy's own for float64 on this machine (``test_batch_controllers`` compares the two over
closed-loop runs and over hostile inputs: NaN, infinities, the safe range's edges).

Implements, per rig: the differences (4.7), (4.9) over N periods with the optional
low-pass (:func:`pisc_control.estimator.estimator_update`); the switching rule (4.1) with
its hysteresis and energy band, the swing-up laws (3.30) and ``energy_pump``, the catch
(3.46) with its settling reference, the start-up target and the faults
(:meth:`pisc_control.supervisor.Supervisor.update`); the set-point (4.2) and the PI loop
(3.47) with the fault's safe state (:func:`pisc_control.current_loop.current_loop_cycle`).
Experiments (``experiment.kind``) are not compiled: :func:`supported` says so and the
batch then runs the numpy cores.
"""

from __future__ import annotations

import math
import time

import numba
import numpy as np

from pisc_control.estimator import EstimatorState
from pisc_control.supervisor import FAULT_NONE, FAULT_NOT_FINITE, FAULT_OUT_OF_RANGE
from pisc_msgs_py.types import Mode
from pisc_sim.configuration import GraphConfig

__all__ = ["BatchControllers", "supported"]

SWING_UP, CATCH, FAULT = Mode.SWING_UP.code, Mode.CATCH.code, Mode.FAULT.code
TWO_PI = 2.0 * np.pi  # wrap_to_upright's constant, as numpy forms it

# The constants' places in the parameter array (each as the numpy core computes it).
(P_EST_A, P_EST_B, P_X_MIN, P_X_MAX, P_MIDDLE, P_STARTUP_D, P_SWING_TARGET, P_K_VA,
 P_DELTA_S, P_DELTA_EXIT, P_BAND, P_INERTIA_HALF, P_MGL, P_K1, P_K2, P_K3, P_K4,
 P_CATCH_TARGET, P_SETTLE_STEP, P_SIN_A1, P_A2, P_A1G, P_ML, P_KE_HALF_A2, P_HALF_J,
 P_M_L, P_SU_KV, P_SU_KX, P_SU_KDELTA, P_SU_KE, P_E_REF, P_PUMP_ACCEL_NEG, P_PUMP_GAIN,
 P_TWO_MGL, P_OMEGA0, P_TRACK_KX, P_TRACK_KV, P_BRAKE, P_TWO_BRAKE, P_GUARD_LOW,
 P_GUARD_HIGH, P_FORCE_PER_AMP, P_I_LIMIT, P_VM, P_KII_TS, P_RESET, P_K_PI,
 N_P) = range(48)

LAW_LYAPUNOV, LAW_ENERGY_PUMP = 0, 1

_jit = numba.njit(cache=True, error_model="numpy", inline="always")


@_jit
def _clip(v, lo, hi):
    """np.clip for one value (NaN passes through, as numpy's does)."""
    if v < lo:
        return lo
    if v > hi:
        return hi
    return v


@_jit
def _wrap(theta):
    """:func:`pisc_model.dynamics.wrap_to_upright`."""
    return theta - TWO_PI * math.floor(theta / TWO_PI + 0.5)


@_jit
def _swing_up_force(p, x, x_dot, theta, theta_dot, target):
    """:func:`pisc_control.swing_up.swing_up_force` (3.30) with the energy (2.54)."""
    s = math.sin(theta)
    c = math.cos(theta)
    den_mass = p[P_A2] - p[P_SIN_A1] * c * c
    kinetic = (p[P_KE_HALF_A2] * x_dot * x_dot + p[P_M_L] * x_dot * theta_dot * c
               + p[P_HALF_J] * theta_dot * theta_dot)
    e = (kinetic + p[P_MGL] * (c - 1.0)) - p[P_E_REF]
    numerator = p[P_SU_KV] * s * (p[P_A1G] * c - p[P_ML] * theta_dot * theta_dot) - (
        den_mass * (p[P_SU_KX] * (x - target) + p[P_SU_KDELTA] * x_dot))
    return numerator / (p[P_SU_KV] + den_mass * p[P_SU_KE] * e)


@_jit
def _energy_pump_force(p, guard, x, x_dot, theta, theta_dot, target):
    """:func:`pisc_control.swing_up.energy_pump_force`."""
    s = math.sin(theta)
    c = math.cos(theta)
    e_p = p[P_INERTIA_HALF] * theta_dot * theta_dot + p[P_MGL] * (c - 1.0)
    error = (p[P_E_REF] - e_p) / p[P_TWO_MGL]
    pump = p[P_PUMP_ACCEL_NEG] * _clip(p[P_PUMP_GAIN] * error * theta_dot * c / p[P_OMEGA0],
                                       -1.0, 1.0)
    a = pump - p[P_TRACK_KX] * (x - target) - p[P_TRACK_KV] * x_dot
    if guard:
        stop = x + x_dot * abs(x_dot) / p[P_TWO_BRAKE]
        if stop > p[P_GUARD_HIGH] and x_dot > 0.0:
            a = -p[P_BRAKE]
        elif stop < p[P_GUARD_LOW] and x_dot < 0.0:
            a = p[P_BRAKE]
    a1 = p[P_SIN_A1]
    return (p[P_A2] - a1 * c * c) * a + p[P_A1G] * s * c - p[P_ML] * theta_dot * theta_dot * s


@_jit
def _rig(r, p, law, guard, settle, first, est_first, span, oldest, write, filtered,
         x, theta, current, x_hist, theta_hist, v_x, v_theta, mode, fault, caught,
         startup_target, reference, integral, force_out, setpoint_out, voltage_out):
    """One cycle of rig r: estimator, supervisor, current loop; state in place."""
    xr, thr = x[r], theta[r]
    # estimator (4.7), (4.9)
    if est_first:
        x_dot = 0.0
        theta_dot = 0.0
    else:
        x_dot = (xr - x_hist[r, oldest]) / span
        theta_dot = (thr - theta_hist[r, oldest]) / span
        if filtered:
            x_dot = p[P_EST_A] * v_x[r] + p[P_EST_B] * x_dot
            theta_dot = p[P_EST_A] * v_theta[r] + p[P_EST_B] * theta_dot
    x_hist[r, write] = xr
    theta_hist[r, write] = thr
    v_x[r] = x_dot
    v_theta[r] = theta_dot

    # supervisor
    if first:
        old_mode = SWING_UP
        old_fault = FAULT_NONE
        was_caught = False
        if p[P_STARTUP_D] > 0.0:
            direction = -1.0 if xr >= p[P_MIDDLE] else 1.0
            startup_target[r] = xr + direction * p[P_STARTUP_D]
        else:
            startup_target[r] = p[P_SWING_TARGET]
    else:
        old_mode = mode[r]
        old_fault = fault[r]
        was_caught = caught[r]
    finite = (math.isfinite(xr) and math.isfinite(x_dot) and math.isfinite(thr)
              and math.isfinite(theta_dot))
    in_range = xr >= p[P_X_MIN] and xr <= p[P_X_MAX]
    if old_fault != FAULT_NONE:
        new_fault = old_fault
    elif not finite:
        new_fault = FAULT_NOT_FINITE
    elif not in_range:
        new_fault = FAULT_OUT_OF_RANGE
    else:
        new_fault = FAULT_NONE
    th = _wrap(thr)
    criterion = th * th + p[P_K_VA] * theta_dot * theta_dot
    catching = old_mode == CATCH
    inside = criterion < (p[P_DELTA_EXIT] if catching else p[P_DELTA_S])
    if p[P_BAND] > 0.0:
        e_p = p[P_INERTIA_HALF] * theta_dot * theta_dot + p[P_MGL] * (math.cos(thr) - 1.0)
        inside = inside and (catching or abs(e_p) < p[P_BAND])
    new_mode = CATCH if inside else SWING_UP
    if new_fault != FAULT_NONE:
        new_mode = FAULT
    now_caught = was_caught or new_mode == CATCH
    target = p[P_SWING_TARGET] if now_caught else startup_target[r]
    if law == LAW_ENERGY_PUMP:
        f_swing = _energy_pump_force(p, guard, xr, x_dot, thr, theta_dot, target)
    else:
        f_swing = _swing_up_force(p, xr, x_dot, thr, theta_dot, target)
    if settle:
        previous = xr if first else reference[r]
        ref = xr if (new_mode == CATCH and old_mode != CATCH) else previous
        if new_mode == CATCH:
            ref = ref + _clip(p[P_CATCH_TARGET] - ref, -p[P_SETTLE_STEP], p[P_SETTLE_STEP])
    else:
        ref = p[P_CATCH_TARGET]
    f_catch = -(p[P_K1] * (xr - ref) + p[P_K2] * x_dot + p[P_K3] * _wrap(thr)
                + p[P_K4] * theta_dot)
    if new_mode == CATCH:
        force = f_catch
    elif new_mode == SWING_UP:
        force = f_swing
    else:
        force = 0.0
    if not math.isfinite(force):
        force = 0.0
    mode[r] = new_mode
    fault[r] = new_fault
    caught[r] = now_caught
    reference[r] = ref

    # current loop (4.2), (3.47)
    i_d = _clip(force / p[P_FORCE_PER_AMP], -p[P_I_LIMIT], p[P_I_LIMIT])
    e = i_d - current[r]
    vm = p[P_VM]
    old = integral[r]
    if old < vm and old > -vm:
        new = old + p[P_KII_TS] * e
    elif old >= vm:
        new = p[P_RESET]
    else:
        new = -p[P_RESET]
    voltage = _clip(p[P_K_PI] * e + new, -vm, vm)
    if new_mode == FAULT:
        integral[r] = 0.0
        setpoint_out[r] = 0.0
        voltage_out[r] = 0.0
    else:
        integral[r] = new
        setpoint_out[r] = i_d
        voltage_out[r] = voltage
    force_out[r] = force


@numba.njit(cache=True, error_model="numpy", parallel=True)
def _cycle(p, law, guard, settle, first, est_first, span, oldest, write, filtered,
           x, theta, current, x_hist, theta_hist, v_x, v_theta, mode, fault, caught,
           startup_target, reference, integral, force_out, setpoint_out, voltage_out):
    for r in numba.prange(x.shape[0]):
        _rig(r, p, law, guard, settle, first, est_first, span, oldest, write, filtered,
             x, theta, current, x_hist, theta_hist, v_x, v_theta, mode, fault, caught,
             startup_target, reference, integral, force_out, setpoint_out, voltage_out)


def supported(config: GraphConfig) -> bool:
    """Whether the compiled cores cover this configuration (all but experiments)."""
    return config.supervisor.experiment.kind == "none"


class BatchControllers:
    """The controllers of ``rigs`` rigs, stepped a cycle at a time by the compiled pass.

    ``estimator`` is the estimator's state before the first cycle (a primed previous
    sample, :func:`pisc_sim.closed_loop.simulate_batch`), flat arrays of ``rigs``
    values; the default is none (the first sample gives zero velocity). The catch gain is
    the supervisor's (:class:`pisc_control.supervisor.Supervisor`).
    """

    def __init__(self, config: GraphConfig, gain: np.ndarray, rigs: int,
                 estimator: EstimatorState | None = None) -> None:
        if not supported(config):
            raise ValueError(f"experiment.kind = {config.supervisor.experiment.kind!r}: "
                             "experiments run on the numpy cores, not the compiled ones")
        c = config.supervisor
        rig, su, sw, est = c.rig, c.swing_up, c.switching, config.estimator
        period = config.loop.period_s
        motor, loop = config.plant.motor, config.current_loop
        p = np.zeros(N_P)
        if est.velocity_filter_hz > 0.0:
            a = math.exp(-2.0 * math.pi * est.velocity_filter_hz * period)
            p[P_EST_A], p[P_EST_B] = a, 1.0 - a
        p[P_X_MIN], p[P_X_MAX] = c.safety.x_min_m, c.safety.x_max_m
        p[P_MIDDLE] = 0.5 * (c.safety.x_min_m + c.safety.x_max_m)
        p[P_STARTUP_D] = c.startup.distance_m
        p[P_SWING_TARGET] = su.target_m
        p[P_K_VA], p[P_DELTA_S], p[P_DELTA_EXIT] = sw.k_va, sw.delta_s, sw.delta_exit
        p[P_BAND] = sw.energy_band_j
        inertia = rig.pendulum_inertia_kgm2 + rig.ml * rig.pendulum_com_m
        p[P_INERTIA_HALF] = 0.5 * inertia
        p[P_MGL] = rig.mgl
        p[P_K1], p[P_K2], p[P_K3], p[P_K4] = (float(k) for k in gain)
        p[P_CATCH_TARGET] = c.catch.target_m
        p[P_SETTLE_STEP] = c.catch.settle_rate_mps * c.loop.period_s
        p[P_SIN_A1], p[P_A2] = rig.a1, rig.a2
        p[P_A1G] = rig.a1 * rig.gravity_mps2
        p[P_ML] = rig.ml
        m, l = rig.pendulum_mass_kg, rig.pendulum_com_m
        p[P_KE_HALF_A2] = 0.5 * rig.a2
        p[P_HALF_J] = 0.5 * (rig.pendulum_inertia_kgm2 + m * l * l)
        p[P_M_L] = m * l
        p[P_SU_KV], p[P_SU_KX], p[P_SU_KDELTA], p[P_SU_KE] = su.k_v, su.k_x, su.k_delta, su.k_e
        p[P_E_REF] = su.energy_target_j
        p[P_PUMP_ACCEL_NEG] = -su.pump_accel_mps2
        p[P_PUMP_GAIN] = su.pump_gain
        p[P_TWO_MGL] = 2.0 * rig.mgl
        p[P_OMEGA0] = np.sqrt(rig.mgl / inertia)
        p[P_TRACK_KX], p[P_TRACK_KV] = su.track_k_x, su.track_k_v
        p[P_BRAKE] = su.guard_accel_mps2
        p[P_TWO_BRAKE] = 2.0 * su.guard_accel_mps2
        p[P_GUARD_LOW] = c.safety.x_min_m + su.guard_margin_m
        p[P_GUARD_HIGH] = c.safety.x_max_m - su.guard_margin_m
        p[P_FORCE_PER_AMP] = motor.force_per_amp
        p[P_I_LIMIT] = loop.current_limit_a
        p[P_VM] = loop.voltage_limit_v
        p[P_KII_TS] = loop.k_ii * period
        p[P_RESET] = loop.integral_reset_fraction * loop.voltage_limit_v
        p[P_K_PI] = loop.k_pi
        self._p = p
        self._law = LAW_ENERGY_PUMP if su.law == "energy_pump" else LAW_LYAPUNOV
        self._guard = su.law == "energy_pump" and su.guard_accel_mps2 > 0.0
        self._settle = c.catch.settle_rate_mps != 0.0
        self._filtered = est.velocity_filter_hz > 0.0
        self._period = period
        self._n = est.difference_periods
        self._x_hist = np.zeros((rigs, self._n))
        self._theta_hist = np.zeros((rigs, self._n))
        self._v_x = np.zeros(rigs)
        self._v_theta = np.zeros(rigs)
        self._seen = 0  # samples the estimator holds (the same for every rig)
        if estimator is not None and estimator.x_m is not None:
            if estimator.x_past:
                raise ValueError("a primed estimator holds one previous sample")
            self._x_hist[:, 0] = np.broadcast_to(estimator.x_m, (rigs,))
            self._theta_hist[:, 0] = np.broadcast_to(estimator.theta_rad, (rigs,))
            self._v_x[:] = np.broadcast_to(estimator.x_dot_mps, (rigs,))
            self._v_theta[:] = np.broadcast_to(estimator.theta_dot_radps, (rigs,))
            self._seen = 1
        self._cycles = 0
        self._mode = np.full(rigs, SWING_UP, dtype=np.int64)
        self._fault = np.full(rigs, FAULT_NONE, dtype=np.int64)
        self._caught = np.zeros(rigs, dtype=np.bool_)
        self._startup_target = np.zeros(rigs)
        self._reference = np.zeros(rigs)
        self._integral = np.zeros(rigs)

    def step(self, x: np.ndarray, theta: np.ndarray, current: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """One cycle for flat arrays of measurements: (force, mode code, i_d, voltage)."""
        x, theta, current = (np.ascontiguousarray(v, dtype=float) for v in (x, theta, current))
        rigs = self._v_x.shape[0]
        if not x.shape == theta.shape == current.shape == (rigs,):
            raise ValueError(f"measurements of shape {x.shape}, {theta.shape}, "
                             f"{current.shape}: want ({rigs},) each")
        n = min(self._seen, self._n)  # samples in the difference's window
        span = self._period if n <= 1 else n * self._period
        oldest = (self._seen - n) % self._n
        write = self._seen % self._n
        force, setpoint, voltage = np.empty(rigs), np.empty(rigs), np.empty(rigs)
        _cycle(self._p, self._law, self._guard, self._settle, self._cycles == 0,
               self._seen == 0, span, oldest, write,
               self._filtered, x, theta, current, self._x_hist, self._theta_hist, self._v_x,
               self._v_theta, self._mode, self._fault, self._caught, self._startup_target,
               self._reference, self._integral, force, setpoint, voltage)
        self._seen += 1
        self._cycles += 1
        return force, self._mode.copy(), setpoint, voltage


def warm_up() -> float:
    """Compile (or load from numba's cache) the compiled pass; seconds taken."""
    from pisc_sim.scene import load_scene

    start = time.perf_counter()
    config = load_scene("thesis-rig").config
    controllers = BatchControllers(config, np.zeros(4), 2)
    controllers.step(np.zeros(2), np.zeros(2), np.zeros(2))
    return time.perf_counter() - start


if __name__ == "__main__":  # python -m pisc_sim.batch_controllers: ./pisc test warms it
    print(f"pisc_sim.batch_controllers: the compiled batch controllers ready in "
          f"{warm_up():.1f} s", flush=True)
