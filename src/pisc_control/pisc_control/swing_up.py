"""Energy-based swing-up for a cart-pole with pendulum inertia.

Two laws, chosen by ``swing_up.law``:

* ``lyapunov``: the thesis's law (3.30), section 3.2, from the Lyapunov function (2.52)
  over the total energy (2.54), the cart's velocity and its distance from x*;
* ``energy_pump``: the cart's acceleration pumps the pendulum's own energy towards a
  target, bounded, as in Astrom and Furuta ("Swinging up a pendulum by energy control",
  Automatica 36 (2000) 287-295), plus a spring and damper that keep the cart near x*;
  the force follows from the acceleration through (3.3). Each term has a physical
  scale (an acceleration the motor can give, a track stiffness), so the law does not
  need to be retuned when the rig's masses change, and it pumps from any state on.
""" 

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from pisc_msgs_py.config import ConfigError, finite, nonnegative, one_of, param, positive
from pisc_model.dynamics import energy
from pisc_model.params import RigParams

__all__ = ["LAWS", "SwingUpParams", "check_gain_condition", "energy_pump_force", "gain_condition",
           "pendulum_energy", "swing_up_force"]

LAWS = ("lyapunov", "energy_pump")


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
    law: str = param("lyapunov", "'lyapunov': (3.30), the thesis's law (k_v, k_x, k_delta, k_e); "
                     "'energy_pump': a bounded cart acceleration pumps the pendulum's energy "
                     "(pump_gain, pump_accel_mps2, track_k_x, track_k_v)", "", one_of(*LAWS))
    pump_gain: float = param(2.0, "energy_pump: k_E, gain on the energy error over 2 m g l "
                             "times theta_dot cos(theta) / omega_0", "", positive)
    pump_accel_mps2: float = param(2.0, "energy_pump: a_max, largest pumping acceleration of "
                                   "the cart", "m/s^2", positive)
    track_k_x: float = param(4.0, "energy_pump: the cart's pull towards x*, an acceleration "
                             "per metre", "1/s^2", nonnegative)
    track_k_v: float = param(3.0, "energy_pump: damping of the cart's velocity, an "
                             "acceleration per m/s", "1/s", nonnegative)
    guard_accel_mps2: float = param(
        0.0, "energy_pump: braking acceleration of the track guard: when the cart, braked at "
        "this rate, would stop beyond the guard's limits, it is braked at this rate (0 = no "
        "guard)", "m/s^2", nonnegative)
    track_quiet: float = param(
        0.0, "energy_pump: kappa; the track's pull (track_k_x, track_k_v) is divided by 1 + "
        "(kappa theta_dot cos(theta) / omega_0)^2, so that it works where it changes the "
        "pendulum's energy least (0 = always in full)", "", nonnegative)
    loss_gain: float = param(
        1.0, "energy_pump with adaptation.enabled: the energy target gains this times the "
        "pivot's loss still ahead on the way up, as estimated online", "", nonnegative)
    guard_margin_m: float = param(0.02, "energy_pump: the guard's limits lie this far inside "
                                  "the safe range (safety.x_min_m, safety.x_max_m)", "m",
                                  nonnegative)


def gain_condition(rig: RigParams, gains: SwingUpParams) -> tuple[float, float]:
    """Both sides of (3.29): ``(k_v / k_e, a2 (2 m g l + E_ref))``; the first must be larger.

    With ``E_ref = 0`` the bound is the thesis's ``2 m g l a2``. With an energy target the
    same argument ((3.26)-(3.29), E - E_ref >= -2 m g l - E_ref) gives the larger bound.
    """
    return gains.k_v / gains.k_e, rig.a2 * max(2.0 * rig.mgl + gains.energy_target_j, 0.0)


def check_gain_condition(rig: RigParams, gains: SwingUpParams) -> None:
    """Refuse gains that break (3.29), under which (3.30) can divide by zero (the
    ``energy_pump`` law divides by nothing that can vanish and has no condition)."""
    if gains.law != "lyapunov":
        return
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
    for any velocities (see :func:`pisc_model.dynamics.energy`) and
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


def pendulum_energy(rig: RigParams, theta: ArrayLike, theta_dot: ArrayLike) -> np.ndarray:
    """The pendulum's own energy, zero upright at rest, -2 m g l hanging at rest.

    Notes
    -----
    The pendulum terms of (2.54): ``1/2 (I + m l^2) theta_dot^2 + m g l (cos(theta) - 1)``.
    """
    theta_dot = np.asarray(theta_dot, dtype=float)
    inertia = rig.pendulum_inertia_kgm2 + rig.ml * rig.pendulum_com_m
    return 0.5 * inertia * theta_dot * theta_dot + rig.mgl * (np.cos(theta) - 1.0)


def energy_pump_force(
    rig: RigParams,
    gains: SwingUpParams,
    x: ArrayLike,
    x_dot: ArrayLike,
    theta: ArrayLike,
    theta_dot: ArrayLike,
    target_m: ArrayLike | None = None,
    limits_m: tuple[float, float] = (-np.inf, np.inf),
) -> np.ndarray:
    """Cart force of the ``energy_pump`` law.

    Notes
    -----
    With the cart's acceleration a as the input, the pendulum row of (2.26),
    ``J theta_ddot = m g l sin(theta) - m l a cos(theta)`` with ``J = I + m l^2``, gives
    ``dE_p/dt = -m l a theta_dot cos(theta)`` for the pendulum's energy E_p
    (:func:`pendulum_energy`). The law asks for

        a = -a_max sat(k_E (E_ref - E_p) / (2 m g l) theta_dot cos(theta) / omega_0)
            - k_x (x - x*) - k_v x_dot,

    ``sat`` clipping to [-1, 1] and ``omega_0 = sqrt(m g l / J)``: the first term
    makes dE_p/dt >= 0 below E_ref and <= 0 above it (Astrom and Furuta 2000), bounded
    by the acceleration the motor can give; the others hold the cart near x*. The track
    guard (``guard_accel_mps2`` = a_b > 0) keeps the cart inside ``limits_m`` narrowed
    by ``guard_margin_m``: where the cart, braked at a_b, would stop beyond them
    (``x + x_dot |x_dot| / (2 a_b)``), a becomes the braking -a_b sign(x_dot). The force
    that gives a follows from (3.3): ``f = (a2 - a1 cos^2) a + a1 g sin cos - m l
    theta_dot^2 sin``.
    """
    if target_m is None:
        target_m = gains.target_m
    x = np.asarray(x, dtype=float)
    x_dot = np.asarray(x_dot, dtype=float)
    theta_dot = np.asarray(theta_dot, dtype=float)
    s = np.sin(theta)
    c = np.cos(theta)
    mgl = rig.mgl
    inertia = rig.pendulum_inertia_kgm2 + rig.ml * rig.pendulum_com_m
    omega_0 = np.sqrt(mgl / inertia)
    e_p = 0.5 * inertia * theta_dot * theta_dot + mgl * (c - 1.0)
    error = (gains.energy_target_j - e_p) / (2.0 * mgl)
    pump = -gains.pump_accel_mps2 * np.clip(
        gains.pump_gain * error * theta_dot * c / omega_0, -1.0, 1.0)
    a = pump - gains.track_k_x * (x - target_m) - gains.track_k_v * x_dot
    if gains.guard_accel_mps2 > 0.0:
        brake = gains.guard_accel_mps2
        stop = x + x_dot * np.abs(x_dot) / (2.0 * brake)
        low, high = limits_m[0] + gains.guard_margin_m, limits_m[1] - gains.guard_margin_m
        a = np.where((stop > high) & (x_dot > 0.0), -brake,
                     np.where((stop < low) & (x_dot < 0.0), brake, a))
    a1 = rig.a1
    return ((rig.a2 - a1 * c * c) * a + a1 * rig.gravity_mps2 * s * c
            - rig.ml * theta_dot * theta_dot * s)
