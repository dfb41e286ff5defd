"""The perfect-knowledge feedback search of the feasibility study: an energy pump and an
LQR hold on the true model, many gain sets at once as a batch of rigs.

:func:`feedback_rollouts` runs the closed loops (the force from (3.3), the voltage from
(4.2), (2.81)), :func:`hold_gain` designs the hold on the true plant,
:func:`feedback_search` is the cross-entropy search over the gains that
:func:`pisc_analysis.feasibility_search.find_witness` runs first; its rollouts
(:class:`Pool`) seed the shooting searches.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pisc_analysis.feasibility import (THETA, THETA_DOT, X, X_DOT, Limits, Rig, Verdict,
                                       cart_friction, check, pendulum_energy,
                                       pivot_friction, verify, wrap)

__all__ = ["Gains", "Pool", "feedback_rollouts", "feedback_search", "force_for_acceleration",
           "hold_from", "hold_gain", "voltage_for_force"]


def force_for_acceleration(rig: Rig, y: np.ndarray, accel: np.ndarray) -> np.ndarray:
    """The motor force that gives the cart acceleration ``accel``: (3.3) solved for f,
    with the pivot torque -b_p theta_dot and the cart friction added back."""
    s, c = np.sin(y[..., THETA]), np.cos(y[..., THETA])
    den = rig.a2 - rig.a1 * c * c
    torque = -pivot_friction(rig) * y[..., THETA_DOT]
    return (accel * den + rig.a1 * rig.mgl / rig.ml * s * c
            - rig.ml * y[..., THETA_DOT] ** 2 * s + rig.a1 * c * torque / rig.ml
            + cart_friction(rig, y[..., X_DOT]))


def voltage_for_force(rig: Rig, limits: Limits, y: np.ndarray,
                      force: np.ndarray) -> np.ndarray:
    """The voltage that makes the current k_m i / r = f within a period (4.2), (2.81):
    i_d within the current limit, u = R i_d + k_e x_dot / r within the bridge's."""
    m = rig.config.motor
    i_d = force / m.force_per_amp
    if limits.current_a is not None:
        i_d = np.clip(i_d, -limits.current_a, limits.current_a)
    # the armature settles within L/R (0.14 ms) of the 5 ms period: aim the mean current
    u = m.resistance_ohm * i_d + m.back_emf_v_s_per_rad / m.wheel_radius_m * y[..., X_DOT]
    return np.clip(u, -limits.voltage_v, limits.voltage_v)


def hold_gain(rig: Rig, weights: tuple[float, float, float, float] = (0.02, 0.3, 0.05, 0.5),
              force_n: float = 1.0) -> np.ndarray:
    """Discrete LQR gain K (4,) of the force f = -K z about upright at rest,
    z = [x, x_dot, theta, theta_dot] (the catch (3.46) designed on the true plant).

    The linearisation (3.41)-(3.42) with the rig's own a1, a2 (rotor included), the
    cart's viscous friction and the pivot's, held over one period (zero-order hold);
    Q = diag(1 / weights^2), R = 1 / force_n^2.
    """
    from scipy.linalg import expm, solve_discrete_are

    a1, a2, ml, g = rig.a1, rig.a2, rig.ml, rig.mgl / rig.ml
    den = a2 - a1
    b_cart = float(cart_friction(rig, np.array(1.0)) - cart_friction(rig, np.array(0.0)))
    if rig.config.models.friction == "coulomb":  # the regularised Coulomb slope is not physics
        f = rig.config.friction
        b_cart -= f.cart_coulomb_n * math.tanh(1.0 / f.coulomb_velocity_mps)
    bp = pivot_friction(rig)
    a = np.array([
        [0.0, 1.0, 0.0, 0.0],
        [0.0, -b_cart / den, -a1 * g / den, a1 * bp / (ml * den)],
        [0.0, 0.0, 0.0, 1.0],
        [0.0, a1 * b_cart / (ml * den), a1 * a2 * g / (ml * den), -a1 * a2 * bp / (ml * ml * den)],
    ])
    b = np.array([0.0, 1.0 / den, 0.0, -a1 / (ml * den)])
    h = rig.period_s
    block = np.zeros((5, 5))
    block[:4, :4] = a * h
    block[:4, 4] = b * h
    e = expm(block)
    ad, bd = e[:4, :4], e[:4, 4:5]
    q = np.diag(1.0 / np.square(weights))
    r = np.array([[1.0 / force_n**2]])
    p = solve_discrete_are(ad, bd, q, r)
    return np.linalg.solve(r + bd.T @ p @ bd, bd.T @ p @ ad)[0]


@dataclass(frozen=True)
class Gains:
    """Gain sets of the perfect-knowledge pump, one value a rollout (arrays (n,))."""

    accel_mps2: np.ndarray  # a_max of the pump
    pump: np.ndarray  # k_E, dimensionless
    energy_target_j: np.ndarray  # E_ref of E_p (above 0 makes up for pivot loss ahead)
    track_k_x: np.ndarray  # 1/s^2
    track_k_v: np.ndarray  # 1/s
    target_m: np.ndarray  # x*
    guard_accel_mps2: np.ndarray
    guard_margin_m: np.ndarray
    switch: np.ndarray  # the LQR takes over when theta^2 + k_va theta_dot^2 < switch

    @staticmethod
    def from_unit(u: np.ndarray, limits: Limits) -> Gains:
        """Gain sets from points of the unit cube, ``u`` (9, n), uniform (or log-uniform)
        over each gain's search range."""
        u = np.clip(u, 0.0, 1.0)
        return Gains(
            accel_mps2=1.0 + 3.5 * u[0],
            pump=np.exp(np.log(2.0) + (np.log(80.0) - np.log(2.0)) * u[1]),
            energy_target_j=10e-3 * u[2] ** 2,
            track_k_x=np.exp(np.log(1.0) + (np.log(30.0) - np.log(1.0)) * u[3]),
            track_k_v=0.2 + 4.0 * u[4],
            target_m=(0.5 * (limits.x_min_m + limits.x_max_m)) * u[5],
            guard_accel_mps2=1.2 + 2.8 * u[6],
            guard_margin_m=0.005 + 0.045 * u[7],
            switch=limits.delta_s * (0.1 + 0.9 * u[8]),
        )


def feedback_rollouts(rig: Rig, limits: Limits, gains: Gains, steps: int,
                      gain_k: np.ndarray | None = None, y0: np.ndarray | None = None
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Closed loops of the perfect-knowledge pump and LQR hold, one per gain set.

    Each period: the state (true, exact); in swing-up the cart acceleration
    a = a_pump + track term, a_pump = -a_max sat(k_E (E_ref - E_p) / (2 m g l) theta_dot
    cos(theta) / omega_0) (raises E_p, since dE_p/dt = -m l a theta_dot cos(theta)),
    braked by the track guard when the stopping distance x_dot^2 / (2 a_g) reaches the
    guard's limit; the force for it from (3.3), the voltage from (4.2), (2.81). Once
    theta^2 + k_va theta_dot^2 < switch the LQR hold (:func:`hold_gain`) takes over for
    good. Returns (voltages (n, steps), states (n, steps + 1, 5)).
    """
    k_gain = hold_gain(rig) if gain_k is None else gain_k
    n = len(gains.pump)
    y = np.array(np.broadcast_to(rig.y0 if y0 is None else y0, (n, 5)), dtype=float)
    states = np.empty((n, steps + 1, 5))
    states[:, 0] = y
    voltages = np.empty((n, steps))
    holding = np.zeros(n, dtype=bool)
    two_mgl = 2.0 * rig.mgl
    hi = limits.x_max_m - gains.guard_margin_m
    lo = limits.x_min_m + gains.guard_margin_m
    for k in range(steps):
        th = wrap(y[:, THETA])
        holding |= th**2 + limits.k_va * y[:, THETA_DOT] ** 2 < gains.switch
        energy = pendulum_energy(rig, y)
        pump = -gains.accel_mps2 * np.clip(
            gains.pump * (gains.energy_target_j - energy) / two_mgl * y[:, THETA_DOT]
            * np.cos(y[:, THETA]) / rig.omega0, -1.0, 1.0)
        accel = np.clip(pump - gains.track_k_x * (y[:, X] - gains.target_m)
                        - gains.track_k_v * y[:, X_DOT], -gains.accel_mps2, gains.accel_mps2)
        stop = y[:, X_DOT] * np.abs(y[:, X_DOT]) / (2.0 * gains.guard_accel_mps2)
        accel = np.where((y[:, X_DOT] > 0) & (y[:, X] + stop > hi), -gains.guard_accel_mps2,
                         accel)
        accel = np.where((y[:, X_DOT] < 0) & (y[:, X] + stop < lo), gains.guard_accel_mps2,
                         accel)
        force = force_for_acceleration(rig, y, accel)
        z = np.stack([y[:, X], y[:, X_DOT], th, y[:, THETA_DOT]], axis=-1)
        hold_force = -(z @ k_gain) + cart_friction(rig, y[:, X_DOT])
        force = np.where(holding, hold_force, force)
        u = voltage_for_force(rig, limits, y, force)
        voltages[:, k] = u
        y = rig.plant.advance(y, u, rig.period_s)
        states[:, k + 1] = y
    return voltages, states


def hold_from(rig: Rig, limits: Limits, y: np.ndarray, steps: int,
              gain_k: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The LQR hold alone from states ``y`` (n, 5): (voltages (n, steps), states)."""
    n = y.shape[0]
    always = Gains(*(np.full(n, v) for v in (1.0, 1.0, 0.0, 1.0, 1.0, 0.0, 1.0, 0.01,
                                             np.inf)))
    return feedback_rollouts(rig, limits, always, steps, gain_k, y0=y)


@dataclass(frozen=True)
class Pool:
    """The feedback search's rollouts (:func:`feedback_search`): voltages (n, steps),
    states (n, steps + 1, 5) and their badness (n,) (:func:`check`)."""

    voltages: np.ndarray
    states: np.ndarray
    badness: np.ndarray


def feedback_search(rig: Rig, limits: Limits, rng: np.random.Generator, rollouts: int = 48,
                    rounds: int = 4, k_gain: np.ndarray | None = None
                    ) -> tuple[np.ndarray | None, Verdict | None, Pool, int]:
    """The cross-entropy search over the pump's gains (the first stage of
    :func:`pisc_analysis.feasibility_search.find_witness`): ``rounds`` batches of
    ``rollouts`` gain sets, the first uniform, each next one around the best eighth so far
    with a spread that halves. Returns (the witness's voltages and verdict, or None, None;
    the pool of every rollout; candidates checked)."""
    period = rig.period_s
    steps = int(round(limits.duration_s / period))
    k_gain = hold_gain(rig) if k_gain is None else k_gain
    tried = 0
    pool_u, pool_v, pool_s, pool_b = [], [], [], []
    spread = 0.25
    for r in range(rounds):
        if r == 0:
            unit = rng.random((9, rollouts))
        else:
            ranked = np.argsort(np.concatenate(pool_b))
            elite = np.concatenate(pool_u, axis=1)[:, ranked[: max(2, rollouts // 8)]]
            pick = rng.integers(0, elite.shape[1], rollouts)
            unit = np.clip(elite[:, pick] + spread * rng.standard_normal((9, rollouts)), 0, 1)
            spread *= 0.5
        volts, states = feedback_rollouts(rig, limits, Gains.from_unit(unit, limits), steps,
                                          k_gain)
        ok, badness = check(limits, volts, states, period)
        pool_u.append(unit)
        pool_v.append(volts)
        pool_s.append(states)
        pool_b.append(badness)
        for j in np.flatnonzero(ok)[:2]:
            verdict = verify(rig, limits, volts[j])
            tried += 1
            if verdict.ok:
                return volts[j], verdict, Pool(np.concatenate(pool_v), np.concatenate(pool_s),
                                               np.concatenate(pool_b)), tried
    return None, None, Pool(np.concatenate(pool_v), np.concatenate(pool_s),
                            np.concatenate(pool_b)), tried

