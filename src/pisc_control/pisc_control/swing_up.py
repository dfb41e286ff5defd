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

The laws are written on floats, one rig at a time (:func:`lyapunov_force`,
:func:`energy_pump_force`, :func:`pendulum_energy`, with the constants of
:func:`swing_up_constants`): the supervisor (:func:`pisc_control.supervisor.
supervisor_step`) calls them in the node and in the compiled batch, and
:func:`swing_up_force` applies them to arrays of states.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from pisc_control.floatmath import clip, cos, sin
from pisc_msgs_py.config import ConfigError, finite, nonnegative, one_of, param, positive
from pisc_model.params import RigParams

__all__ = ["LAWS", "SwingUpParams", "check_gain_condition", "energy_pump_force",
           "gain_condition", "lyapunov_force", "pendulum_energy", "rig_pendulum_energy",
           "swing_up_constants", "swing_up_force"]

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


# places in the swing-up's constants (swing_up_constants)
(W_INERTIA_HALF, W_MGL, W_A1, W_A2, W_A1G, W_ML, W_HALF_A2, W_HALF_J, W_M_L, W_KV, W_KX,
 W_KDELTA, W_KE, W_E_REF, W_PUMP_ACCEL_NEG, W_PUMP_GAIN, W_TWO_MGL, W_OMEGA0, W_TRACK_KX,
 W_TRACK_KV, W_BRAKE, W_TWO_BRAKE, W_GUARD_LOW, W_GUARD_HIGH, W_GUARD, W_LOSS_GAIN, W_QUIET,
 W_ADAPT, N_W) = range(29)


def swing_up_constants(rig: RigParams, gains: SwingUpParams,
                       limits_m: tuple[float, float] = (-math.inf, math.inf),
                       adaptive: bool = False) -> tuple[float, ...]:
    """The constants of the laws below (places ``W_*``) for the model ``rig``, the safe
    range ``limits_m`` (the track guard's) and whether the online estimates
    (:mod:`pisc_control.adaptation`) replace the model's omega_0^2."""
    inertia = rig.pendulum_inertia_kgm2 + rig.ml * rig.pendulum_com_m
    m, l = rig.pendulum_mass_kg, rig.pendulum_com_m
    w = [0.0] * N_W
    w[W_INERTIA_HALF] = 0.5 * inertia
    w[W_MGL] = rig.mgl
    w[W_A1], w[W_A2] = rig.a1, rig.a2
    w[W_A1G] = rig.a1 * rig.gravity_mps2
    w[W_ML] = rig.ml
    w[W_HALF_A2] = 0.5 * rig.a2
    w[W_HALF_J] = 0.5 * (rig.pendulum_inertia_kgm2 + m * l * l)
    w[W_M_L] = m * l
    w[W_KV], w[W_KX], w[W_KDELTA], w[W_KE] = gains.k_v, gains.k_x, gains.k_delta, gains.k_e
    w[W_E_REF] = gains.energy_target_j
    w[W_PUMP_ACCEL_NEG] = -gains.pump_accel_mps2
    w[W_PUMP_GAIN] = gains.pump_gain
    w[W_TWO_MGL] = 2.0 * rig.mgl
    w[W_OMEGA0] = float(np.sqrt(rig.mgl / inertia))
    w[W_TRACK_KX], w[W_TRACK_KV] = gains.track_k_x, gains.track_k_v
    w[W_BRAKE] = gains.guard_accel_mps2
    w[W_TWO_BRAKE] = 2.0 * gains.guard_accel_mps2
    w[W_GUARD_LOW] = limits_m[0] + gains.guard_margin_m
    w[W_GUARD_HIGH] = limits_m[1] - gains.guard_margin_m
    pump = gains.law == "energy_pump"
    w[W_GUARD] = 1.0 if pump and gains.guard_accel_mps2 > 0.0 else 0.0
    w[W_LOSS_GAIN] = gains.loss_gain
    w[W_QUIET] = gains.track_quiet
    w[W_ADAPT] = 1.0 if adaptive else 0.0
    return tuple(w)


def lyapunov_force(w: tuple[float, ...], x: float, x_dot: float, sn: float, c: float,
                   theta_dot: float, target: float) -> float:
    """Cart force that drives the energy to ``E_ref`` and the cart to the target x*;
    ``sn``, ``c``: the sine and cosine of the angle; ``w``: :func:`swing_up_constants`.
    No branch: it also runs on arrays.

    Notes
    -----
    Implements (3.30)::

        f = (k_v sin(theta) (a1 g cos(theta) - m l theta_dot^2)
             - (a2 - a1 cos^2) (k_x (x - x*) + k_delta x_dot))
            / (k_v + (a2 - a1 cos^2) k_e (E - E_ref))

    with E from (2.54). With E_ref = 0 this is the thesis's law; the Lyapunov function
    (2.52) with (E - E_ref)^2 gives the same derivation because dE/dt = x_dot f (2.57)
    does not depend on E_ref. Under (3.29) the denominator is positive for every state,
    because E >= -2 m g l for any velocities (see :func:`pisc_model.dynamics.energy`)
    and a2 - a1 cos^2 <= a2.
    """
    den_mass = w[W_A2] - w[W_A1] * c * c
    kinetic = (w[W_HALF_A2] * x_dot * x_dot + w[W_M_L] * x_dot * theta_dot * c
               + w[W_HALF_J] * theta_dot * theta_dot)
    e = (kinetic + w[W_MGL] * (c - 1.0)) - w[W_E_REF]
    numerator = w[W_KV] * sn * (w[W_A1G] * c - w[W_ML] * theta_dot * theta_dot) - (
        den_mass * (w[W_KX] * (x - target) + w[W_KDELTA] * x_dot))
    return numerator / (w[W_KV] + den_mass * w[W_KE] * e)


def pendulum_energy(w: tuple[float, ...], c: float, theta_dot: float, w2: float) -> float:
    """The pendulum's own energy, zero upright at rest, -2 m g l hanging at rest; ``c``:
    the cosine of the angle. No branch on the values: it also runs on arrays.

    Notes
    -----
    The pendulum terms of (2.54): ``1/2 (I + m l^2) theta_dot^2 + m g l (cos(theta) -
    1)``; with the online estimate ``w2`` of omega_0^2 = m g l / J (``W_ADAPT``) m g l
    (theta_dot^2 / (2 omega_0^2) + cos(theta) - 1).
    """
    if w[W_ADAPT] > 0.0:
        return w[W_MGL] * (theta_dot * theta_dot / (2.0 * w2) + (c - 1.0))
    return w[W_INERTIA_HALF] * theta_dot * theta_dot + w[W_MGL] * (c - 1.0)


def energy_pump_force(w: tuple[float, ...], x: float, x_dot: float, sn: float, c: float,
                      theta_dot: float, target: float,
                      pendulum: tuple[float, float, float, float, float],
                      stalled: bool = False) -> float:
    """Cart force of the ``energy_pump`` law; ``sn``, ``c``: the sine and cosine of the
    angle; ``w``: :func:`swing_up_constants`.

    ``pendulum``: (cos, rate, angle from upright) of the instant the energy is read at,
    and the online estimates omega_0^2 and beta = b / J. With the estimates
    (``W_ADAPT``), the energy is the estimated pendulum's, read one period late from a
    central difference, the pump acts on that instant's rate and angle, and the energy's
    target makes up for the pivot's loss still ahead on the way up, 4 b omega_0 (1 -
    |cos(th / 2)|) (the loss int b theta_dot dtheta along the separatrix, theta_dot = 2
    omega_0 sin(th / 2)), times ``swing_up.loss_gain``. ``stalled``: no pump, the track's
    terms and its guard only.

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
    by the acceleration the motor can give; the others hold the cart near x*. With
    ``track_quiet`` = kappa > 0 the track's terms are divided by 1 + (kappa theta_dot
    cos(theta) / omega_0)^2. The track guard (``guard_accel_mps2`` = a_b > 0) keeps the
    cart inside the safe range narrowed by ``guard_margin_m``: where the cart, braked at
    a_b, would stop beyond it (``x + x_dot |x_dot| / (2 a_b)``), a becomes the braking
    -a_b sign(x_dot). The force that gives a follows from (3.3): ``f = (a2 - a1 cos^2) a
    + a1 g sin cos - m l theta_dot^2 sin``.
    """
    e_c, e_rate, th, w2, beta = pendulum
    if w[W_ADAPT] > 0.0:
        e_p = pendulum_energy(w, e_c, e_rate, w2)
        omega0 = math.sqrt(w2)
        loss = w[W_LOSS_GAIN] * w[W_MGL] * 4.0 * beta / omega0 * (1.0 - abs(cos(0.5 * th)))
        error = (w[W_E_REF] + loss - e_p) / w[W_TWO_MGL]
        pump = w[W_PUMP_ACCEL_NEG] * clip(w[W_PUMP_GAIN] * error * e_rate * e_c / omega0,
                                          -1.0, 1.0)
    else:
        e_p = pendulum_energy(w, c, theta_dot, w2)
        error = (w[W_E_REF] - e_p) / w[W_TWO_MGL]
        pump = w[W_PUMP_ACCEL_NEG] * clip(
            w[W_PUMP_GAIN] * error * theta_dot * c / w[W_OMEGA0], -1.0, 1.0)
    if stalled:
        pump = 0.0
    if w[W_QUIET] > 0.0:
        # the track's pull weighs less where it would change the pendulum's energy most
        # (dE_p/dt = -m l a theta_dot cos(theta))
        swing = w[W_QUIET] * theta_dot * c / w[W_OMEGA0]
        a = pump - (w[W_TRACK_KX] * (x - target) + w[W_TRACK_KV] * x_dot) / (1.0 + swing * swing)
    else:
        a = pump - w[W_TRACK_KX] * (x - target) - w[W_TRACK_KV] * x_dot
    if w[W_GUARD] > 0.0:
        stop = x + x_dot * abs(x_dot) / w[W_TWO_BRAKE]
        if stop > w[W_GUARD_HIGH] and x_dot > 0.0:
            a = -w[W_BRAKE]
        elif stop < w[W_GUARD_LOW] and x_dot < 0.0:
            a = w[W_BRAKE]
    a1 = w[W_A1]
    return (w[W_A2] - a1 * c * c) * a + w[W_A1G] * sn * c - w[W_ML] * theta_dot * theta_dot * sn


# -- over arrays of states: the laws above element by element ---------------------------

def swing_up_force(
    rig: RigParams,
    gains: SwingUpParams,
    x: ArrayLike,
    x_dot: ArrayLike,
    theta: ArrayLike,
    theta_dot: ArrayLike,
    target_m: ArrayLike | None = None,
    limits_m: tuple[float, float] = (-math.inf, math.inf),
) -> np.ndarray:
    """The swing-up force of ``gains.law`` (:func:`lyapunov_force` or
    :func:`energy_pump_force`, with the model's pendulum) over arrays of states; x* =
    ``target_m`` (default ``gains.target_m``), the track guard's safe range
    ``limits_m``."""
    w = swing_up_constants(rig, gains, limits_m)
    target = gains.target_m if target_m is None else target_m
    if gains.law == "energy_pump":
        def one(x, x_dot, theta, theta_dot, target):
            return energy_pump_force(w, x, x_dot, sin(theta), cos(theta), theta_dot, target,
                                     (0.0, 0.0, 0.0, 0.0, 0.0))
    else:
        def one(x, x_dot, theta, theta_dot, target):
            return lyapunov_force(w, x, x_dot, sin(theta), cos(theta), theta_dot, target)
    return np.vectorize(one, otypes=[float])(x, x_dot, theta, theta_dot, target)


def rig_pendulum_energy(rig: RigParams, theta: ArrayLike, theta_dot: ArrayLike
                        ) -> np.ndarray:
    """:func:`pendulum_energy` of the model's pendulum over arrays of angles and rates."""
    w = swing_up_constants(rig, SwingUpParams())
    return np.vectorize(lambda th, rate: pendulum_energy(w, cos(th), rate, 0.0),
                        otypes=[float])(theta, theta_dot)
