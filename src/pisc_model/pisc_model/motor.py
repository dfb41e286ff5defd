"""Brushed DC motor on the cart's wheels: armature circuit and force at the cart.

Pure functions that broadcast over numpy arrays. The shaft angle is phi = x / r
(wheels on the motor shaft), so phi_dot = x_dot / r.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from pisc_model.params import MotorParams

__all__ = ["armature_current_rate", "cart_force", "quasi_static_current"]


def armature_current_rate(
    motor: MotorParams, current_a: ArrayLike, voltage_v: ArrayLike, cart_velocity_mps: ArrayLike
) -> np.ndarray:
    """di/dt of the armature.

    Notes
    -----
    Implements (2.81), ``L di/dt = u - R i - k_e phi_dot`` with phi_dot = x_dot / r.
    """
    back_emf = motor.back_emf_v_s_per_rad * np.asarray(cart_velocity_mps) / motor.wheel_radius_m
    return (np.asarray(voltage_v) - motor.resistance_ohm * np.asarray(current_a) - back_emf) / (
        motor.inductance_h
    )


def quasi_static_current(
    motor: MotorParams, voltage_v: ArrayLike, cart_velocity_mps: ArrayLike
) -> np.ndarray:
    """Armature current once the electrical transient has died out (L di/dt = 0 in (2.81))."""
    back_emf = motor.back_emf_v_s_per_rad * np.asarray(cart_velocity_mps) / motor.wheel_radius_m
    return (np.asarray(voltage_v) - back_emf) / motor.resistance_ohm


def cart_force(
    motor: MotorParams, current_a: ArrayLike, cart_velocity_mps: ArrayLike
) -> np.ndarray:
    """Force the motor puts on the cart, less its own viscous friction.

    Notes
    -----
    Torque k_m i (2.82) through the wheel radius gives f = k_m i / r (4.2); the rotor's
    viscous friction b_m phi_dot appears at the cart as b_m x_dot / r^2. The rotor
    inertia is not a force: it is added to the cart's mass (see
    :func:`pisc_model.dynamics.accelerations`).
    """
    return motor.force_per_amp * np.asarray(current_a) - motor.reflected_damping_ns_per_m * (
        np.asarray(cart_velocity_mps)
    )
