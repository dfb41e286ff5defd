"""One rig's controllers on Python floats: the numpy cores' arithmetic, one value at a time.

The numpy cores (:mod:`pisc_control.estimator`, :mod:`pisc_control.supervisor`,
:mod:`pisc_control.current_loop`) broadcast over arrays; on one rig, as a node runs
them each cycle, numpy's cost per call is most of their time (the supervisor's update
took 19 % of a one-process lockstep cycle's py-spy samples, 2026-12-03). The functions
here do the same operations in the same order and grouping on floats, with the
constants the cores form in Python formed the same way (:func:`supervisor_constants` and
its kin), so they give the cores' bits: IEEE arithmetic is the same on a float and on
an array element, numpy's float64 ``sin`` and ``cos`` are the C library's, which ``math``
calls, and where ``math`` raises (an infinite angle, the floor of NaN) the helpers give
numpy's NaN instead (``pisc_sim/test/test_batch_controllers.py`` compares them with the
cores over closed-loop runs, hostile inputs and parameter changes). They are also the
source the batch compiles (:mod:`pisc_sim.batch_controllers`): plain functions of
floats, ints and tuples, calling nothing but ``math`` and each other.
:class:`OneRigEstimator`, :class:`OneRigSupervisor` and :class:`OneRigCurrentLoop` hold
one rig's state for the nodes and :class:`pisc_sim.closed_loop.Controllers`.

Implements the differences (4.7), (4.9) over N periods with the optional low-pass; the
switching rule (4.1) with hysteresis and energy band, the swing-up laws (3.30) and
``energy_pump``, the catch (3.46) with its settling reference, the start-up target and
the faults; the set-point (4.2) and the PI loop (3.47) with the fault's safe state.
Experiments (``experiment.kind``) are not here: they run on the numpy cores.
"""

from __future__ import annotations

import math

import numpy as np

from pisc_control.adaptation import (
    adaptation_constants,
    adaptation_estimates,
    adaptation_init,
    adaptation_size,
    adaptation_std,
    adaptation_step,
)
from pisc_control.current_loop import CurrentLoopParams
from pisc_control.estimator import EstimatorParams
from pisc_control.supervisor import (
    FAULT_NONE,
    FAULT_NOT_FINITE,
    FAULT_OUT_OF_RANGE,
    Supervisor,
    SupervisorState,
)
from pisc_model.params import MotorParams
from pisc_msgs_py.types import Mode

__all__ = ["ArraySupervisor", "LAW_ENERGY_PUMP", "LAW_LYAPUNOV", "OneRigCurrentLoop", "OneRigEstimator",
           "OneRigSupervisor", "current_loop_constants",
           "current_loop_step", "estimator_constants", "estimator_step", "governor_interval",
           "governor_rows", "supervisor_constants", "supervisor_step"]

SWING_UP, CATCH, FAULT = Mode.SWING_UP.code, Mode.CATCH.code, Mode.FAULT.code
TWO_PI = 2.0 * np.pi  # wrap_to_upright's constant, as numpy forms it
LAW_LYAPUNOV, LAW_ENERGY_PUMP = 0, 1

# places in the supervisor's constants (each formed as the numpy core forms it)
(S_X_MIN, S_X_MAX, S_MIDDLE, S_STARTUP_D, S_SWING_TARGET, S_K_VA, S_DELTA_S, S_DELTA_EXIT,
 S_BAND, S_INERTIA_HALF, S_MGL, S_K1, S_K2, S_K3, S_K4, S_CATCH_TARGET, S_SETTLE_STEP,
 S_A1, S_A2, S_A1G, S_ML, S_HALF_A2, S_HALF_J, S_M_L, S_KV, S_KX, S_KDELTA, S_KE, S_E_REF,
 S_PUMP_ACCEL_NEG, S_PUMP_GAIN, S_TWO_MGL, S_OMEGA0, S_TRACK_KX, S_TRACK_KV, S_BRAKE,
 S_TWO_BRAKE, S_GUARD_LOW, S_GUARD_HIGH, S_LAW, S_GUARD, S_SETTLE, S_GOV, S_GOV_X_LO,
 S_GOV_X_HI, S_GOV_I, S_CATCH_GUARD, S_ADAPT, S_LOSS_GAIN, S_QUIET, S_CG_TWO_BRAKE, S_CG_LOW,
 S_CG_HIGH, S_CG_LEAD, S_H1, S_H2, S_H3, S_H4, S_HOLD_AFTER, S_HOLD_BLEND, N_S) = range(61)
# places in the current loop's constants
C_FORCE_PER_AMP, C_I_LIMIT, C_VM, C_KII_TS, C_RESET, C_K_PI, N_C = range(7)


def estimator_constants(params: EstimatorParams, period_s: float) -> tuple[float, float]:
    """(a, 1 - a) of the low-pass, a = exp(-2 pi fc Ts); (0, 0) without one."""
    if params.velocity_filter_hz > 0.0:
        a = math.exp(-2.0 * math.pi * params.velocity_filter_hz * period_s)
        return a, 1.0 - a
    return 0.0, 0.0


def estimator_step(a: float, b: float, span: float, x: float, theta: float,
                   oldest_x: float, oldest_theta: float, v_x: float, v_theta: float
                   ) -> tuple[float, float]:
    """(x_dot, theta_dot) from this sample and the window's oldest, (4.7), (4.9), over
    ``span``; low-passed with the previous estimates (v_x, v_theta) when a > 0
    (:func:`pisc_control.estimator.estimator_update`; the first sample, which has no
    window, gives 0, 0 without calling this)."""
    x_dot = (x - oldest_x) / span
    theta_dot = (theta - oldest_theta) / span
    if a > 0.0:
        x_dot = a * v_x + b * x_dot
        theta_dot = a * v_theta + b * theta_dot
    return x_dot, theta_dot


def supervisor_constants(supervisor: Supervisor) -> tuple[float, ...]:
    """The supervisor's constants, formed as its numpy core forms them (experiments: no)."""
    c = supervisor.config
    if c.experiment.kind != "none":
        raise ValueError(f"experiment.kind = {c.experiment.kind!r}: experiments run on the "
                         "numpy cores")
    rig, su, sw = c.rig, c.swing_up, c.switching
    inertia = rig.pendulum_inertia_kgm2 + rig.ml * rig.pendulum_com_m
    m, l = rig.pendulum_mass_kg, rig.pendulum_com_m
    k1, k2, k3, k4 = supervisor.gain
    s = [0.0] * N_S
    s[S_X_MIN], s[S_X_MAX] = c.safety.x_min_m, c.safety.x_max_m
    s[S_MIDDLE] = 0.5 * (c.safety.x_min_m + c.safety.x_max_m)
    s[S_STARTUP_D] = c.startup.distance_m
    s[S_SWING_TARGET] = su.target_m
    s[S_K_VA], s[S_DELTA_S], s[S_DELTA_EXIT] = sw.k_va, sw.delta_s, sw.delta_exit
    s[S_BAND] = sw.energy_band_j
    s[S_INERTIA_HALF] = 0.5 * inertia
    s[S_MGL] = rig.mgl
    s[S_K1], s[S_K2], s[S_K3], s[S_K4] = float(k1), float(k2), float(k3), float(k4)
    s[S_CATCH_TARGET] = c.catch.target_m
    s[S_SETTLE_STEP] = c.catch.settle_rate_mps * c.loop.period_s
    s[S_A1], s[S_A2] = rig.a1, rig.a2
    s[S_A1G] = rig.a1 * rig.gravity_mps2
    s[S_ML] = rig.ml
    s[S_HALF_A2] = 0.5 * rig.a2
    s[S_HALF_J] = 0.5 * (rig.pendulum_inertia_kgm2 + m * l * l)
    s[S_M_L] = m * l
    s[S_KV], s[S_KX], s[S_KDELTA], s[S_KE] = su.k_v, su.k_x, su.k_delta, su.k_e
    s[S_E_REF] = su.energy_target_j
    s[S_PUMP_ACCEL_NEG] = -su.pump_accel_mps2
    s[S_PUMP_GAIN] = su.pump_gain
    s[S_TWO_MGL] = 2.0 * rig.mgl
    s[S_OMEGA0] = float(np.sqrt(rig.mgl / inertia))
    s[S_TRACK_KX], s[S_TRACK_KV] = su.track_k_x, su.track_k_v
    s[S_BRAKE] = su.guard_accel_mps2
    s[S_TWO_BRAKE] = 2.0 * su.guard_accel_mps2
    s[S_GUARD_LOW] = c.safety.x_min_m + su.guard_margin_m
    s[S_GUARD_HIGH] = c.safety.x_max_m - su.guard_margin_m
    pump = su.law == "energy_pump"
    s[S_LAW] = float(LAW_ENERGY_PUMP if pump else LAW_LYAPUNOV)
    s[S_GUARD] = 1.0 if pump and su.guard_accel_mps2 > 0.0 else 0.0
    s[S_SETTLE] = 1.0 if c.catch.settle_rate_mps != 0.0 else 0.0
    s[S_GOV] = 1.0 if c.catch.governor else 0.0
    s[S_GOV_X_LO] = c.safety.x_min_m + c.catch.governor_margin_m
    s[S_GOV_X_HI] = c.safety.x_max_m - c.catch.governor_margin_m
    s[S_GOV_I] = c.catch.governor_current_a
    s[S_CATCH_GUARD] = 1.0 if c.catch.guard and s[S_GUARD] > 0.0 else 0.0
    s[S_ADAPT] = 1.0 if c.adaptation.enabled else 0.0
    s[S_LOSS_GAIN] = su.loss_gain
    s[S_QUIET] = su.track_quiet
    s[S_CG_TWO_BRAKE] = 2.0 * c.catch.guard_accel_mps2
    s[S_CG_LOW] = c.safety.x_min_m + c.catch.guard_margin_m
    s[S_CG_HIGH] = c.safety.x_max_m - c.catch.guard_margin_m
    s[S_CG_LEAD] = c.catch.guard_lead_s
    h1, h2, h3, h4 = supervisor.hold_gain
    s[S_H1], s[S_H2], s[S_H3], s[S_H4] = float(h1), float(h2), float(h3), float(h4)
    s[S_HOLD_AFTER] = c.catch.hold_after_s / c.loop.period_s if c.catch.hold_poles else -1.0
    s[S_HOLD_BLEND] = c.catch.hold_blend_s / c.loop.period_s
    return tuple(s)


def governor_rows(supervisor: Supervisor) -> list[tuple[float, ...]]:
    """The governor's prediction rows (:attr:`Supervisor.governor_rows`) as tuples of
    floats, which Python indexes faster than an array's elements."""
    return [tuple(float(v) for v in row) for row in supervisor.governor_rows]


def _clip(v: float, lo: float, hi: float) -> float:
    """np.clip of one value (NaN passes through, as numpy's does)."""
    if v < lo:
        return lo
    if v > hi:
        return hi
    return v


def _floor(v: float) -> float:
    """np.floor of one value: NaN and the infinities pass through (``math.floor`` raises
    on them) and so do values too large to have a fraction (2^52 and up), which compiled
    code would otherwise overflow into a 64-bit integer."""
    if v != v or abs(v) >= 4503599627370496.0:
        return v
    return float(math.floor(v))


def _sin(v: float) -> float:
    """np.sin of one value: NaN for the infinities (``math.sin`` raises on them)."""
    return v - v if math.isinf(v) else math.sin(v)


def _cos(v: float) -> float:
    """np.cos of one value: NaN for the infinities (``math.cos`` raises on them)."""
    return v - v if math.isinf(v) else math.cos(v)


def _wrap(theta: float) -> float:
    """:func:`pisc_model.dynamics.wrap_to_upright`."""
    return theta - TWO_PI * _floor(theta / TWO_PI + 0.5)


def _lyapunov_force(s: tuple[float, ...], x: float, x_dot: float, sn: float, c: float,
                    theta_dot: float, target: float) -> float:
    """:func:`pisc_control.swing_up.swing_up_force` (3.30), with the energy (2.54); ``sn``,
    ``c``: the sine and cosine of the angle."""
    den_mass = s[S_A2] - s[S_A1] * c * c
    kinetic = (s[S_HALF_A2] * x_dot * x_dot + s[S_M_L] * x_dot * theta_dot * c
               + s[S_HALF_J] * theta_dot * theta_dot)
    e = (kinetic + s[S_MGL] * (c - 1.0)) - s[S_E_REF]
    numerator = s[S_KV] * sn * (s[S_A1G] * c - s[S_ML] * theta_dot * theta_dot) - (
        den_mass * (s[S_KX] * (x - target) + s[S_KDELTA] * x_dot))
    return numerator / (s[S_KV] + den_mass * s[S_KE] * e)


def _pendulum_energy(s: tuple[float, ...], c: float, theta_dot: float, w2: float) -> float:
    """The pendulum's own energy (the pendulum terms of (2.54)): with the model's J, or with
    the online estimate ``w2`` of omega_0^2 = m g l / J (m g l (theta_dot^2 / (2
    omega_0^2) + cos(theta) - 1))."""
    if s[S_ADAPT] > 0.0:
        return s[S_MGL] * (theta_dot * theta_dot / (2.0 * w2) + (c - 1.0))
    return s[S_INERTIA_HALF] * theta_dot * theta_dot + s[S_MGL] * (c - 1.0)


def _energy_pump_force(s: tuple[float, ...], x: float, x_dot: float, sn: float, c: float,
                       theta_dot: float, target: float,
                       pendulum: tuple[float, float, float, float, float],
                       stalled: bool = False) -> float:
    """:func:`pisc_control.swing_up.energy_pump_force`; ``sn``, ``c``: the sine and cosine
    of the angle. ``pendulum``: (cos, rate, angle from upright) of the instant the energy
    is read at, and the online estimates omega_0^2 and beta = b / J. With the estimates,
    the energy is the estimated pendulum's, read one period late from a central
    difference, the pump acts on that instant's rate and angle, and the energy's target
    makes up for the pivot's loss still ahead on the way up, 4 b omega_0 (1 - |cos(th /
    2)|) (the loss int b theta_dot dtheta along the separatrix, theta_dot = 2 omega_0
    sin(th / 2)), times ``swing_up.loss_gain``. ``stalled``: no pump, the track's terms
    and its guard only."""
    e_c, e_rate, th, w2, beta = pendulum
    if s[S_ADAPT] > 0.0:
        e_p = _pendulum_energy(s, e_c, e_rate, w2)
        omega0 = math.sqrt(w2)
        loss = s[S_LOSS_GAIN] * s[S_MGL] * 4.0 * beta / omega0 * (1.0 - abs(_cos(0.5 * th)))
        error = (s[S_E_REF] + loss - e_p) / s[S_TWO_MGL]
        pump = s[S_PUMP_ACCEL_NEG] * _clip(s[S_PUMP_GAIN] * error * e_rate * e_c / omega0,
                                           -1.0, 1.0)
    else:
        e_p = _pendulum_energy(s, c, theta_dot, w2)
        error = (s[S_E_REF] - e_p) / s[S_TWO_MGL]
        pump = s[S_PUMP_ACCEL_NEG] * _clip(
            s[S_PUMP_GAIN] * error * theta_dot * c / s[S_OMEGA0], -1.0, 1.0)
    if stalled:
        pump = 0.0
    if s[S_QUIET] > 0.0:
        # the track's pull weighs less where it would change the pendulum's energy most
        # (dE_p/dt = -m l a theta_dot cos(theta))
        swing = s[S_QUIET] * theta_dot * c / s[S_OMEGA0]
        a = pump - (s[S_TRACK_KX] * (x - target) + s[S_TRACK_KV] * x_dot) / (1.0 + swing * swing)
    else:
        a = pump - s[S_TRACK_KX] * (x - target) - s[S_TRACK_KV] * x_dot
    if s[S_GUARD] > 0.0:
        stop = x + x_dot * abs(x_dot) / s[S_TWO_BRAKE]
        if stop > s[S_GUARD_HIGH] and x_dot > 0.0:
            a = -s[S_BRAKE]
        elif stop < s[S_GUARD_LOW] and x_dot < 0.0:
            a = s[S_BRAKE]
    a1 = s[S_A1]
    return (s[S_A2] - a1 * c * c) * a + s[S_A1G] * sn * c - s[S_ML] * theta_dot * theta_dot * sn


def _narrow(lo: float, hi: float, a: float, b: float, low: float, high: float
            ) -> tuple[float, float]:
    """[lo, hi] narrowed to the r with low <= a + b r <= high (empty: lo > hi)."""
    if b > 1e-12:
        lo = max(lo, (low - a) / b)
        hi = min(hi, (high - a) / b)
    elif b < -1e-12:
        lo = max(lo, (high - a) / b)
        hi = min(hi, (low - a) / b)
    elif not (a >= low and a <= high):
        lo, hi = math.inf, -math.inf
    return lo, hi


def governor_interval(s: tuple[float, ...], rows, x: float, x_dot: float, th: float,
                      theta_dot: float) -> tuple[float, float]:
    """(lo, hi): the catch's cart references r for which the linear closed loop's
    prediction from this state (:func:`pisc_control.catch.governor_rows`: row j gives the
    cart ``r + P_j . w`` and the set-point ``Q_j . w``, ``w = [x - r, x_dot, th,
    theta_dot]``) keeps the cart in [S_GOV_X_LO, S_GOV_X_HI] and the set-point within
    +-S_GOV_I at every row; lo > hi when no reference does."""
    lo, hi = -math.inf, math.inf
    x_lo, x_hi, i_max = s[S_GOV_X_LO], s[S_GOV_X_HI], s[S_GOV_I]
    for j in range(len(rows)):
        row = rows[j]
        moved = row[0] * x + row[1] * x_dot + row[2] * th + row[3] * theta_dot
        lo, hi = _narrow(lo, hi, moved, 1.0 - row[0], x_lo, x_hi)
        current = row[4] * x + row[5] * x_dot + row[6] * th + row[7] * theta_dot
        lo, hi = _narrow(lo, hi, current, -row[4], -i_max, i_max)
    return lo, hi


def supervisor_step(s: tuple[float, ...], rows,
                    pendulum: tuple[float, float, float, float, bool], first: bool, x: float, x_dot: float, theta: float,
                    theta_dot: float, mode: int, fault: int, caught: bool,
                    startup_target: float, reference: float
                    ) -> tuple[float, int, int, bool, float, float]:
    """One sample of :meth:`pisc_control.supervisor.Supervisor.update` for one rig.

    ``first``: the first sample (the state's mode, fault, caught, start-up target and
    reference are then ignored). Returns (force, mode, fault, caught, start-up target,
    catch reference), the last five the state for the next sample.
    """
    if first:
        mode = SWING_UP
        fault = FAULT_NONE
        caught = False
        if s[S_STARTUP_D] > 0.0:
            direction = -1.0 if x >= s[S_MIDDLE] else 1.0
            startup_target = x + direction * s[S_STARTUP_D]
        else:
            startup_target = s[S_SWING_TARGET]
    finite = (math.isfinite(x) and math.isfinite(x_dot) and math.isfinite(theta)
              and math.isfinite(theta_dot))
    if fault != FAULT_NONE:
        new_fault = fault
    elif not finite:
        new_fault = FAULT_NOT_FINITE
    elif not (x >= s[S_X_MIN] and x <= s[S_X_MAX]):
        new_fault = FAULT_OUT_OF_RANGE
    else:
        new_fault = FAULT_NONE
    th = _wrap(theta)
    sn = _sin(theta)  # taken once: the band and the swing-up law use them
    c = _cos(theta)
    w2, beta, middle, rate, stalled, held = pendulum
    if s[S_ADAPT] > 0.0:  # the energy from the angle and rate of one instant
        e_c = _cos(middle)
        e_rate = rate
        e_th = _wrap(middle)
    else:
        e_c, e_rate, e_th = c, theta_dot, th
    criterion = th * th + s[S_K_VA] * theta_dot * theta_dot
    catching = mode == CATCH
    inside = criterion < (s[S_DELTA_EXIT] if catching else s[S_DELTA_S])
    if s[S_BAND] > 0.0:
        e_p = _pendulum_energy(s, e_c, e_rate, w2)
        inside = inside and (catching or abs(e_p) < s[S_BAND])
    if inside and s[S_CATCH_GUARD] > 0.0:
        stop = x + x_dot * (s[S_CG_LEAD] + abs(x_dot) / s[S_CG_TWO_BRAKE])
        if (stop > s[S_CG_HIGH] and x_dot > 0.0) or (stop < s[S_CG_LOW] and x_dot < 0.0):
            inside = False  # the cart would not stop inside the guard's limits: brake
    # the hold's gain, blended in after hold_after_s in the catch (none: -1)
    blend = 0.0
    if s[S_HOLD_AFTER] >= 0.0 and catching:
        blend = _clip((held - s[S_HOLD_AFTER]) / s[S_HOLD_BLEND], 0.0, 1.0)
    governed = s[S_GOV] > 0.0 and inside and blend == 0.0
    lo = hi = 0.0
    if governed:
        lo, hi = governor_interval(s, rows, x, x_dot, th, theta_dot)
        if not catching and not lo <= hi:
            inside = False  # no reference keeps this catch in the track: do not start it
    new_mode = CATCH if inside else SWING_UP
    if new_fault != FAULT_NONE:
        new_mode = FAULT
    now_caught = caught or new_mode == CATCH
    target = s[S_SWING_TARGET] if now_caught else startup_target
    if s[S_LAW] == LAW_ENERGY_PUMP:
        f_swing = _energy_pump_force(s, x, x_dot, sn, c, theta_dot, target,
                                     (e_c, e_rate, e_th, w2, beta), stalled)
    else:
        f_swing = _lyapunov_force(s, x, x_dot, sn, c, theta_dot, target)
    if s[S_SETTLE] > 0.0:
        ref = x if first or (new_mode == CATCH and mode != CATCH) else reference
        if new_mode == CATCH:
            ref = ref + _clip(s[S_CATCH_TARGET] - ref, -s[S_SETTLE_STEP], s[S_SETTLE_STEP])
    else:
        ref = s[S_CATCH_TARGET]
    if governed and new_mode == CATCH and lo <= hi:
        ref = _clip(ref, lo, hi)
    if blend > 0.0:
        k1 = s[S_K1] + blend * (s[S_H1] - s[S_K1])
        k2 = s[S_K2] + blend * (s[S_H2] - s[S_K2])
        k3 = s[S_K3] + blend * (s[S_H3] - s[S_K3])
        k4 = s[S_K4] + blend * (s[S_H4] - s[S_K4])
        f_catch = -(k1 * (x - ref) + k2 * x_dot + k3 * th + k4 * theta_dot)
    else:
        f_catch = -(s[S_K1] * (x - ref) + s[S_K2] * x_dot + s[S_K3] * th + s[S_K4] * theta_dot)
    if new_mode == CATCH:
        force = f_catch
    elif new_mode == SWING_UP:
        force = f_swing
    else:
        force = 0.0
    if not math.isfinite(force):
        force = 0.0
    return force, new_mode, new_fault, now_caught, startup_target, ref


def current_loop_constants(motor: MotorParams, params: CurrentLoopParams,
                           period_s: float) -> tuple[float, ...]:
    """The current loop's constants, formed as its numpy core forms them."""
    c = [0.0] * N_C
    c[C_FORCE_PER_AMP] = motor.force_per_amp
    c[C_I_LIMIT] = params.current_limit_a
    c[C_VM] = params.voltage_limit_v
    c[C_KII_TS] = params.k_ii * period_s
    c[C_RESET] = params.integral_reset_fraction * params.voltage_limit_v
    c[C_K_PI] = params.k_pi
    return tuple(c)


def current_loop_step(c: tuple[float, ...], fault: bool, force: float, current: float,
                      integral: float) -> tuple[float, float, float]:
    """:func:`pisc_control.current_loop.current_loop_cycle` for one rig: (i_d, voltage,
    integral); 0, 0 and a cleared integral in ``fault``."""
    i_d = _clip(force / c[C_FORCE_PER_AMP], -c[C_I_LIMIT], c[C_I_LIMIT])
    e = i_d - current
    vm = c[C_VM]
    if integral < vm and integral > -vm:
        new = integral + c[C_KII_TS] * e
    elif integral >= vm:
        new = c[C_RESET]
    else:
        new = -c[C_RESET]
    voltage = _clip(c[C_K_PI] * e + new, -vm, vm)
    if fault:
        return 0.0, 0.0, 0.0
    return i_d, voltage, new


class OneRigEstimator:
    """The estimator of one rig, as its node runs it: the window of previous samples,
    the previous estimates, and :func:`estimator_step`."""

    def __init__(self, params: EstimatorParams, period_s: float) -> None:
        self._window: list[tuple[float, float]] = []  # previous samples, oldest first
        self._previous = (0.0, 0.0)
        self.configure(params, period_s)

    def configure(self, params: EstimatorParams, period_s: float) -> None:
        """New parameters; the window shrinks or grows to the new N over the next samples,
        as the numpy core's does."""
        self._a, self._b = estimator_constants(params, period_s)
        self._period = period_s
        self._n = params.difference_periods

    def step(self, x: float, theta: float) -> tuple[float, float]:
        """(x_dot, theta_dot) at this sample; (0, 0) at the first."""
        window = self._window
        if window:
            n = len(window)
            span = self._period if n == 1 else n * self._period
            oldest_x, oldest_theta = window[0]
            x_dot, theta_dot = estimator_step(self._a, self._b, span, x, theta, oldest_x,
                                              oldest_theta, *self._previous)
        else:
            x_dot = theta_dot = 0.0
        window.append((x, theta))
        del window[:-self._n]
        self._previous = (x_dot, theta_dot)
        return x_dot, theta_dot


class OneRigSupervisor:
    """The supervisor of one rig, as its node runs it: :func:`supervisor_step` on floats,
    or during an experiment the numpy core (:meth:`Supervisor.update`)."""

    def __init__(self, supervisor: Supervisor) -> None:
        # (mode, fault, caught, start-up target, catch reference); None before a sample
        self._state: tuple[int, int, bool, float, float] | None = None
        self._numpy_state = SupervisorState()
        self.stalled = False  # the swing-up has given up (adaptation.stall_s)
        self.configure(supervisor)

    def configure(self, supervisor: Supervisor) -> None:
        """New parameters; the state carries over (also into and out of an experiment), and
        so do the online estimates unless their parameters changed."""
        previous = getattr(self, "supervisor", None)
        self.supervisor = supervisor
        c = supervisor.config
        scalar = c.experiment.kind == "none"
        self._constants = supervisor_constants(supervisor) if scalar else None
        self._rows = governor_rows(supervisor) if scalar else []
        self._adapt = adaptation_constants(c.adaptation, c.rig, c.loop.period_s)
        if previous is None or (previous.config.adaptation, previous.config.rig) != (
                c.adaptation, c.rig):
            self._adapt_state = [0.0] * adaptation_size(c.adaptation)
            adaptation_init(c.adaptation, c.rig, self._adapt_state)
        self.estimates = adaptation_estimates(self._adapt_state)
        if scalar and self._numpy_state.mode is not None:
            n = self._numpy_state
            ref = n.catch_reference_m
            self._state = (int(n.mode), int(n.fault), bool(n.caught), float(n.startup_target_m),
                           0.0 if ref is None else float(ref))
            self._numpy_state = SupervisorState()
        elif not scalar and self._state is not None:
            mode, fault, caught, target, ref = self._state
            self._numpy_state = SupervisorState(np.int64(mode), np.int64(fault),
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
            self._numpy_state.caught is not None and self._numpy_state.caught)

    @property
    def reference(self) -> float:
        """The catch's cart reference (0 before the first sample)."""
        return float(self._state[4]) if self._state is not None else 0.0

    @property
    def fault(self) -> int:
        """The fault code (``FAULT_NONE`` before the first sample)."""
        if self._state is not None:
            return self._state[1]
        n = self._numpy_state.fault
        return FAULT_NONE if n is None else int(n)

    def step(self, x: float, x_dot: float, theta: float, theta_dot: float) -> tuple[float, int]:
        """(force, mode code) for this sample."""
        if self._constants is None:
            self._numpy_state, force, code = self.supervisor.update(
                self._numpy_state, x, x_dot, theta, theta_dot)
            return float(force), int(code)
        state = self._state
        pendulum = adaptation_step(self._adapt, self._adapt_state, x, theta,
                                   state is None or state[0] != CATCH)
        self.estimates = pendulum[:2]
        self.stalled = pendulum[4]
        if state is None:
            force, *new = supervisor_step(self._constants, self._rows, pendulum, True, x,
                                          x_dot, theta, theta_dot, SWING_UP, FAULT_NONE,
                                          False, 0.0, 0.0)
        else:
            force, *new = supervisor_step(self._constants, self._rows, pendulum, False, x,
                                          x_dot, theta, theta_dot, *state)
        self._state = tuple(new)  # type: ignore[assignment]
        return force, new[0]


class ArraySupervisor:
    """:meth:`Supervisor.update` over arrays for any configuration: the numpy core's, or
    for one whose laws are written for one rig at a time (:attr:`Supervisor.by_rig`) a
    :class:`OneRigSupervisor` per rig. The state it returns holds the mode, fault, caught
    and reference arrays; the one-rig supervisors keep the rest themselves, so a state is
    good for one next call only."""

    def __init__(self, supervisor: Supervisor) -> None:
        self.supervisor = supervisor
        self._rigs: list[OneRigSupervisor] | None = None

    def update(self, state: SupervisorState, x, x_dot, theta, theta_dot
               ) -> tuple[SupervisorState, np.ndarray, np.ndarray]:
        if not self.supervisor.by_rig:
            return self.supervisor.update(state, x, x_dot, theta, theta_dot)
        values = [np.asarray(v, dtype=float) for v in (x, x_dot, theta, theta_dot)]
        shape = np.broadcast_shapes(*(v.shape for v in values))
        flat = [np.broadcast_to(v, shape).reshape(-1) for v in values]
        size = flat[0].size
        if state.mode is None or self._rigs is None:
            self._rigs = [OneRigSupervisor(self.supervisor) for _ in range(size)]
        force = np.empty(size)
        mode = np.empty(size, dtype=np.int64)
        for r, rig in enumerate(self._rigs):
            force[r], mode[r] = rig.step(*(float(v[r]) for v in flat))
        fault = np.array([rig.fault for rig in self._rigs], dtype=np.int64)
        caught = np.array([rig.caught for rig in self._rigs], dtype=bool)
        reference = np.array([rig.reference for rig in self._rigs])
        new = SupervisorState(mode.reshape(shape), fault.reshape(shape), np.zeros(shape),
                              caught.reshape(shape), reference.reshape(shape))
        return new, force.reshape(shape), mode.reshape(shape)


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
