"""Cart-pole with pendulum inertia: equations of motion, energy, linearisation.

All functions are pure and broadcast over numpy arrays of any leading shape, so the
same code evaluates one rig in a node and thousands in a batch.

State convention (SPEC section 1): ``y = [x, x_dot, theta, theta_dot]``, theta = 0
upright, positive towards +x, theta = pi hanging down; the force f acts along +x.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from pisc_model.params import RigParams

__all__ = [
    "accelerations",
    "energy",
    "linearise_upright",
    "wrap_to_upright",
]


def accelerations(
    rig: RigParams,
    theta: ArrayLike,
    theta_dot: ArrayLike,
    force: ArrayLike,
    extra_cart_mass_kg: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Cart and pendulum accelerations.

    Parameters
    ----------
    rig
        Cart-pole parameters.
    theta, theta_dot
        Pendulum angle (rad, 0 upright) and rate (rad/s).
    force
        Force on the cart along +x (N).
    extra_cart_mass_kg
        Mass added to the cart row only, e.g. the motor's rotor inertia reflected to
        the cart, J_m / r^2. Zero gives the thesis model exactly.

    Returns
    -------
    x_ddot, theta_ddot

    Notes
    -----
    Implements (3.3) and (3.5) with ``a2`` replaced by ``a2 + extra_cart_mass_kg``:
    the extra mass enters the cart equation (2.31) only, and (3.5) follows from (3.3)
    and the pendulum equation (3.4), which it does not touch.
    """
    s = np.sin(theta)
    c = np.cos(theta)
    a1 = rig.a1
    a2 = rig.a2 + extra_cart_mass_kg
    ml = rig.ml
    g = rig.gravity_mps2
    theta_dot = np.asarray(theta_dot, dtype=float)
    force = np.asarray(force, dtype=float)
    den = a2 - a1 * c * c
    centripetal = ml * theta_dot * theta_dot * s
    x_ddot = (-a1 * g * s * c + centripetal + force) / den
    theta_ddot = (a1 * a2 * g * s - a1 * centripetal * c - a1 * force * c) / (ml * den)
    return x_ddot, theta_ddot


def energy(rig: RigParams, x_dot: ArrayLike, theta: ArrayLike, theta_dot: ArrayLike) -> np.ndarray:
    """Total energy of the cart-pole, zero upright at rest, -2 m g l hanging at rest.

    Notes
    -----
    Implements (2.54) with (2.12) and (2.14)::

        E = 1/2 (M+m) x_dot^2 + m l x_dot theta_dot cos(theta)
            + 1/2 (I + m l^2) theta_dot^2 + m g l (cos(theta) - 1)

    The kinetic part is a quadratic form with the positive definite inertia matrix
    (2.27), so E >= -2 m g l for any velocities, measured or true.
    """
    x_dot = np.asarray(x_dot, dtype=float)
    theta_dot = np.asarray(theta_dot, dtype=float)
    c = np.cos(theta)
    m = rig.pendulum_mass_kg
    l = rig.pendulum_com_m
    kinetic = (
        0.5 * rig.a2 * x_dot * x_dot
        + m * l * x_dot * theta_dot * c
        + 0.5 * (rig.pendulum_inertia_kgm2 + m * l * l) * theta_dot * theta_dot
    )
    return kinetic + rig.mgl * (c - 1.0)


def linearise_upright(rig: RigParams) -> tuple[np.ndarray, np.ndarray]:
    """A and B of the linearisation about the upright equilibrium.

    Notes
    -----
    Implements (3.41)-(3.42); for the thesis rig the nonzero entries are
    -a1 g/(a2-a1) = -0.16302, a1 a2 g/(m l (a2-a1)) = 86.469, 1/(a2-a1) = 2.1002 and
    -a1/(m l (a2-a1)) = -18.210 (thesis (6.3)).
    """
    a1, a2, ml, g = rig.a1, rig.a2, rig.ml, rig.gravity_mps2
    d = a2 - a1
    a = np.array(
        [
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, -a1 * g / d, 0.0],
            [0.0, 0.0, 0.0, 1.0],
            [0.0, 0.0, a1 * a2 * g / (ml * d), 0.0],
        ]
    )
    b = np.array([[0.0], [1.0 / d], [0.0], [-a1 / (ml * d)]])
    return a, b


def wrap_to_upright(theta: ArrayLike) -> np.ndarray:
    """Angle from the nearest upright equilibrium theta = 2 pi n, in [-pi, pi).

    The thesis program measures from 0 or 2 pi depending on theta < pi (appendix A.2);
    this is the same rule extended to any number of revolutions (SPEC section 3).
    """
    theta = np.asarray(theta, dtype=float)
    return theta - 2.0 * np.pi * np.floor(theta / (2.0 * np.pi) + 0.5)
