"""Energy-based swing-up for a cart-pole with pendulum inertia, thesis section 3.2."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from pisc_msgs_py.config import ConfigError, finite, param, positive
from pisc_plant.dynamics import energy
from pisc_plant.params import RigParams

__all__ = ["SwingUpParams", "check_gain_condition", "gain_condition", "swing_up_force"]


@dataclass(frozen=True)
class SwingUpParams:
    """Gains of (3.30); the thesis's values (Table 6.4) are the defaults."""

    k_v: float = param(0.1, "k_v, weight of x_dot^2 in the Lyapunov function (2.52)", "", positive)
    k_x: float = param(55.5, "k_x, weight of (x - x*)^2 in (2.52)", "", positive)
    k_delta: float = param(1.55, "k_delta, damping of x_dot, V_dot = -k_delta x_dot^2 (3.31)",
                           "", positive)
    k_e: float = param(8.1, "k_e, weight of E^2 in (2.52)", "", positive)
    energy_target_j: float = param(
        0.0, "E_ref: drive E to this value instead of 0 (0 = the thesis's law); a small "
        "positive value makes up for the energy the cart's motion takes", "J", finite)
    target_m: float = param(0.0, "x*, where the swing-up holds the cart", "m", finite)


def gain_condition(rig: RigParams, gains: SwingUpParams) -> tuple[float, float]:
    """Both sides of (3.29): ``(k_v / k_e, a2 (2 m g l + E_ref))``; the first must be larger.

    With ``E_ref = 0`` the bound is the thesis's ``2 m g l a2``. With an energy target the
    same argument ((3.26)-(3.29), E - E_ref >= -2 m g l - E_ref) gives the larger bound.
    """
    return gains.k_v / gains.k_e, rig.a2 * max(2.0 * rig.mgl + gains.energy_target_j, 0.0)


def check_gain_condition(rig: RigParams, gains: SwingUpParams) -> None:
    """Refuse gains that break (3.29), under which (3.30) can divide by zero."""
    ratio, bound = gain_condition(rig, gains)
    if not ratio > bound:
        what = "2 m g l a2" if gains.energy_target_j == 0.0 else "a2 (2 m g l + E_ref)"
        raise ConfigError(
            f"swing_up.k_v / swing_up.k_e = {ratio:.6g} must exceed {what} = {bound:.6g} "
            "(thesis condition (3.29)); otherwise the swing-up law (3.30) can divide by zero. "
            "Raise swing_up.k_v or lower swing_up.k_e."
        )


def swing_up_force(
    rig: RigParams,
    gains: SwingUpParams,
    x: ArrayLike,
    x_dot: ArrayLike,
    theta: ArrayLike,
    theta_dot: ArrayLike,
    target_m: ArrayLike | None = None,
) -> np.ndarray:
    """Cart force that drives the energy to ``E_ref`` and the cart to the target.

    Notes
    -----
    Implements (3.30)::

        f = (k_v sin(theta) (a1 g cos(theta) - m l theta_dot^2)
             - (a2 - a1 cos^2) (k_x (x - x*) + k_delta x_dot))
            / (k_v + (a2 - a1 cos^2) k_e (E - E_ref))

    with E from (2.54) and x* = ``target_m`` (default ``gains.target_m``). With
    E_ref = 0 this is the thesis's law; the Lyapunov function (2.52) with (E - E_ref)^2
    gives the same derivation because dE/dt = x_dot f (2.57) does not depend on E_ref.
    Under (3.29) the denominator is positive for every state, because E >= -2 m g l
    for any velocities (see :func:`pisc_plant.dynamics.energy`) and
    a2 - a1 cos^2 <= a2.
    """
    if target_m is None:
        target_m = gains.target_m
    x = np.asarray(x, dtype=float)
    x_dot = np.asarray(x_dot, dtype=float)
    theta_dot = np.asarray(theta_dot, dtype=float)
    s = np.sin(theta)
    c = np.cos(theta)
    a1, a2 = rig.a1, rig.a2
    den_mass = a2 - a1 * c * c
    e = energy(rig, x_dot, theta, theta_dot) - gains.energy_target_j
    numerator = gains.k_v * s * (a1 * rig.gravity_mps2 * c - rig.ml * theta_dot * theta_dot) - (
        den_mass * (gains.k_x * (x - target_m) + gains.k_delta * x_dot)
    )
    return numerator / (gains.k_v + den_mass * gains.k_e * e)
