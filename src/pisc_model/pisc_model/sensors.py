"""Sensor models and calibrations of the rig (SPEC section 4).

Both directions live here so they cannot drift apart: the simulator and the virtual
rig encode the true state into raw device values (ADC codes, encoder counts) through
the inverse calibrations, and the plant node and the serial driver decode raw values
into SI units with exactly the conversions of the thesis's C++ program.

Raw values: ``ir_code`` and ``current_code`` are 10-bit ADC codes, ``count`` the
signed encoder count (0 at power-up, hanging down).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from pisc_model.params import SensorParams

__all__ = [
    "adc_code",
    "adc_voltage",
    "current_from_voltage",
    "current_sensor_voltage",
    "decode",
    "encoder_angle",
    "encoder_count",
    "ir_position",
    "ir_voltage",
]


def ir_voltage(s: SensorParams, position_m: ArrayLike) -> np.ndarray:
    """Output voltage of the Sharp GP2Y0A21 for a cart position (inverse of (4.8)).

    The cart-to-sensor distance is ``origin - x``; it is kept above 1 mm so a cart
    pushed through the sensor face (impossible on the rig) gives a finite reading.
    """
    distance = np.maximum(s.ir_origin_m - np.asarray(position_m, dtype=float), 1e-3)
    return (distance / s.ir_scale_m) ** (-1.0 / s.ir_exponent)


def ir_position(s: SensorParams, voltage_v: ArrayLike) -> np.ndarray:
    """Cart position from the IR voltage, ``x = -0.2451 V^-1.069 + 0.20`` (C++ program)."""
    return s.ir_origin_m - s.ir_scale_m * np.asarray(voltage_v, dtype=float) ** (-s.ir_exponent)


def current_sensor_voltage(s: SensorParams, current_a: ArrayLike) -> np.ndarray:
    """ACS712 output voltage for a current (inverse of ``i = 5 V - 12.555``)."""
    return (np.asarray(current_a, dtype=float) + s.current_offset_a) / s.current_scale_a_per_v


def current_from_voltage(s: SensorParams, voltage_v: ArrayLike) -> np.ndarray:
    """Motor current from the ACS712 voltage, ``i = 5.0 V - 12.555`` (C++ program)."""
    return s.current_scale_a_per_v * np.asarray(voltage_v, dtype=float) - s.current_offset_a


def adc_code(s: SensorParams, voltage_v: ArrayLike) -> np.ndarray:
    """10-bit code of a successive-approximation ADC between its references.

    Truncates like the PIC's converter and saturates at 0 and 2^bits - 1.
    """
    code = np.floor((np.asarray(voltage_v, dtype=float) - s.adc_ref_low_v) / s.adc_lsb_v)
    return np.clip(code, 0, s.adc_levels - 1).astype(np.int64)


def adc_voltage(s: SensorParams, code: ArrayLike) -> np.ndarray:
    """Voltage for a code, ``V = code * 2.514 / 1024 + 0.595`` (C++ program)."""
    return np.asarray(code, dtype=float) * s.adc_lsb_v + s.adc_ref_low_v


def encoder_count(s: SensorParams, angle_rad: ArrayLike) -> np.ndarray:
    """Quadrature count of the pendulum encoder, 0 at the power-up angle.

    The count changes by one each 2 pi / 4000 rad, with edges half a count either side
    of the power-up angle.
    """
    turns = (np.asarray(angle_rad, dtype=float) - s.encoder_zero_rad) / s.encoder_rad_per_count
    return np.floor(turns + 0.5).astype(np.int64)


def encoder_angle(s: SensorParams, count: ArrayLike) -> np.ndarray:
    """Pendulum angle from the count, ``theta = pi * count / 2000 + pi`` (C++ program)."""
    return np.asarray(count, dtype=float) * s.encoder_rad_per_count + s.encoder_zero_rad


def decode(
    s: SensorParams, ir_code: ArrayLike, current_code: ArrayLike, count: ArrayLike
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Raw device values to (x [m], theta [rad], i [A]), as the host program converts them."""
    x = ir_position(s, adc_voltage(s, ir_code))
    theta = encoder_angle(s, count)
    current = current_from_voltage(s, adc_voltage(s, current_code))
    return x, theta, current
