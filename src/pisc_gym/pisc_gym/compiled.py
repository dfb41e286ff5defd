"""The environments' per-step work over all rigs, compiled (numba): the sensors, the
estimator's differences and the current loop, each rig with its own constants.

Each function is one pass over the rigs, so a vector environment of ten thousand rigs
costs a few passes a step besides the plant's kernel. The arithmetic is the one the
rest of PISC does, operation for operation, so a rig here gives the same bits as the
pure closed loop (:func:`pisc_sim.closed_loop.simulate`):

* :func:`measure` is :meth:`pisc_plant.plant.Plant.measurement_one` (quantised sensors
  behind their RC filters: the noise at the ADC's input, the 10-bit codes, the encoder
  count, the host's conversions with the IR curve (4.8) of every code from numpy) or
  :meth:`~pisc_plant.plant.Plant.measurement` with ideal sensors, with one noise
  standard deviation a rig (a plant set's ``noise.*_std_*``);
* :func:`estimate` runs :func:`pisc_control.scalar.estimator_step`, the differences
  (4.7), (4.9) over N periods with the optional low-pass, on each rig's own window;
* :func:`current_loop` runs :func:`pisc_control.scalar.current_loop_step`, the PI loop
  (3.47), for a set-point given as the action.

The control laws are not copied here: the estimator's and the current loop's steps are
compiled from :mod:`pisc_control.scalar`'s source, as :mod:`pisc_sim.batch_controllers`
compiles them (importing it registers the helpers they call).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from pisc_control import scalar
from pisc_plant.layout import ARM_FORCE, ARM_FULL
from pisc_sim import batch_controllers  # noqa: F401 (registers scalar's helpers for numba)

__all__ = ["SENSORS_IDEAL", "SENSORS_QUANTISED", "current_loop", "estimate", "measure"]

SENSORS_QUANTISED, SENSORS_IDEAL = 0, 1

_estimator_step = numba.njit(scalar.estimator_step, error_model="numpy", inline="always")
_current_loop_step = numba.njit(scalar.current_loop_step, error_model="numpy",
                                inline="always")

# places in measure's sensor constants
(M_LSB, M_LOW, M_TOP, M_IR_ORIGIN, M_IR_EXPONENT, M_CURRENT_SCALE, M_CURRENT_OFFSET,
 M_ENCODER_ZERO, M_RAD_PER_COUNT, N_M) = range(10)


def sensor_constants(sensors) -> tuple[np.ndarray, np.ndarray]:
    """:func:`measure`'s constants of :class:`pisc_model.params.SensorParams`, and the
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


#: rigs a thread measures at a time (fewer rigs are measured in the caller's thread)
CHUNK = 1024


@numba.njit(cache=True, error_model="numpy", parallel=True)
def _measure_many(y, applied, kind, armature, ii, vir, vcur, ker, resistance, force_per_amp,
                  noisy, std, noise, noise_at, m, ir_table, out, true_current):
    rigs = y.shape[0]
    for c in numba.prange((rigs + CHUNK - 1) // CHUNK):
        _measure_rows(y, applied, kind, armature, ii, vir, vcur, ker, resistance,
                      force_per_amp, noisy, std, noise, noise_at, m, ir_table, out,
                      true_current, c * CHUNK, min(rigs, (c + 1) * CHUNK))


def measure(y, applied, kind, armature, ii, vir, vcur, ker, resistance, force_per_amp,
            noisy, std, noise, noise_at, m, ir_table, out, true_current):
    """Every rig's measurement of its state ``y`` (rigs, size) into ``out`` (rigs, 3):
    x [m], theta [rad], i [A]; the true armature current into ``true_current``.

    ``applied``: the input held at the sample, through the actuator (it sets the current
    of a quasi-static armature, (2.81) with L di/dt = 0, and of an ideal force source,
    (4.2)); ``ker``, ``resistance``, ``force_per_amp``: each rig's k_e / r, R and
    k_m / r. ``noisy[r]``: rig r draws noise, its three standard normal values
    ``noise[r, noise_at[r]]`` (a block of its stream; ``noise_at[r]`` then moves on),
    scaled by ``std[r]``. A state that is not finite reads NaN.
    """
    args = (y, applied, kind, armature, ii, vir, vcur, ker, resistance, force_per_amp, noisy,
            std, noise, noise_at, m, ir_table, out, true_current)
    if y.shape[0] > CHUNK:
        _measure_many(*args)
    else:
        _measure_rows(*args, 0, y.shape[0])


@numba.njit(cache=True, error_model="numpy")
def _measure_rows(y, applied, kind, armature, ii, vir, vcur, ker, resistance, force_per_amp,
                  noisy, std, noise, noise_at, m, ir_table, out, true_current, lo, hi):
    """:func:`measure` of rigs lo..hi."""
    lsb, low, top = m[M_LSB], m[M_LOW], m[M_TOP]
    for r in range(lo, hi):
        draws = noise[r, noise_at[r]]
        if noisy[r]:
            noise_at[r] += 1
        if armature == ARM_FULL:
            current = y[r, ii]
        elif armature == ARM_FORCE:
            current = applied[r] / force_per_amp[r]
        else:
            current = (applied[r] - ker[r] * y[r, 1]) / resistance[r]
        true_current[r] = current
        theta = y[r, 2]
        if kind == SENSORS_IDEAL:  # Plant._noisy
            x = y[r, 0]
            if noisy[r]:
                x = x + std[r, 0] * draws[0]
                theta = theta + std[r, 1] * draws[1]
                current = current + std[r, 2] * draws[2]
            out[r, 0], out[r, 1], out[r, 2] = x, theta, current
            continue
        v_ir = y[r, vir]
        v_cur = y[r, vcur]
        if noisy[r]:  # Plant.measurement_one: the noise at the ADC's input
            theta = theta + std[r, 1] * draws[1]
            distance = max(m[M_IR_ORIGIN] - y[r, 0], 1e-3)
            v_ir = v_ir + v_ir / (m[M_IR_EXPONENT] * distance) * std[r, 0] * draws[0]
            v_cur = v_cur + std[r, 2] * draws[2] / m[M_CURRENT_SCALE]
        turns = (theta - m[M_ENCODER_ZERO]) / m[M_RAD_PER_COUNT] + 0.5
        if not (math.isfinite(v_ir) and math.isfinite(v_cur) and abs(turns) < 2.0 ** 62):
            out[r, 0] = out[r, 1] = out[r, 2] = np.nan
            continue
        ir_code = min(max(np.floor((v_ir - low) / lsb), 0.0), top)  # sensors.adc_code
        cur_code = min(max(np.floor((v_cur - low) / lsb), 0.0), top)
        out[r, 0] = ir_table[int(ir_code)]
        out[r, 1] = np.floor(turns) * m[M_RAD_PER_COUNT] + m[M_ENCODER_ZERO]
        out[r, 2] = m[M_CURRENT_SCALE] * (cur_code * lsb + low) - m[M_CURRENT_OFFSET]


@numba.njit(cache=True, error_model="numpy")
def estimate(x, theta, a, b, period, n, seen, x_hist, theta_hist, v_x, v_theta, out):
    """Every rig's (x_dot, theta_dot) at this sample into ``out`` (rigs, 2): (0, 0) at
    a rig's first sample, else the difference over the window of its last ``n``
    samples (``x_hist``, ``theta_hist`` (rigs, n), a ring written at ``seen[r] % n``),
    low-passed with the previous estimate when a > 0, as
    :class:`pisc_control.scalar.OneRigEstimator` steps it."""
    for r in range(x.shape[0]):
        s = seen[r]
        if s == 0:
            x_dot = 0.0
            theta_dot = 0.0
        else:
            k = min(s, n)  # samples in the window
            span = period if k <= 1 else k * period
            oldest = (s - k) % n
            x_dot, theta_dot = _estimator_step(a, b, span, x[r], theta[r], x_hist[r, oldest],
                                               theta_hist[r, oldest], v_x[r], v_theta[r])
        x_hist[r, s % n] = x[r]
        theta_hist[r, s % n] = theta[r]
        seen[r] = s + 1
        v_x[r] = x_dot
        v_theta[r] = theta_dot
        out[r, 0] = x_dot
        out[r, 1] = theta_dot


@numba.njit(cache=True, error_model="numpy")
def current_loop(c, setpoint, current, integral, voltage):
    """The PI loop (3.47) of every rig for the set-points ``setpoint`` (A) and the
    measured currents: the voltages into ``voltage``, the integrals updated in place.
    ``c``: :func:`pisc_control.scalar.current_loop_constants` with k_m / r = 1, so that
    the set-point (4.2) is the action itself, saturated to the current limit."""
    for r in range(setpoint.shape[0]):
        _, voltage[r], integral[r] = _current_loop_step(c, False, setpoint[r], current[r],
                                                        integral[r])
