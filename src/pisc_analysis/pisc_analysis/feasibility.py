"""Can any controller swing a given rig up and hold it? An upper bound (issue 13).

For one plant known exactly (its true m, l, I, M, motor and friction, its initial state,
no noise, no latency), :func:`find_witness` looks for a voltage sequence, one value per
control period (zero-order hold, the plant's own input), that brings the pendulum from
its initial state into the catch region by ``catch_by_s`` and holds it there, within
the robustness benchmark's rules (:class:`Limits`): the cart inside the safe range at
every sample, |u| within the bridge's voltage, |i| within the current loop's limit at
every sample, from ``hold_start_s`` |theta| and |x| within the hold's bounds.

Two searches, both on the compiled plant (:class:`pisc_plant.plant.Plant`):

1. **Perfect-knowledge feedback** (:func:`feedback_rollouts`): an energy pump on the
   true pendulum energy with a track guard, the force computed from the true model
   (3.3), (3.5), handed to a discrete LQR hold in the catch region; many random gain
   sets at once, as a batch of rigs.
2. **Direct shooting** (:func:`shoot`): the voltage piecewise constant over knots,
   ``scipy.optimize.least_squares`` on the terminal state (upright at rest) with the
   track and current limits as penalty residuals, started from the best feedback
   rollouts and from random pumps; the LQR hold takes over at the end of the horizon.

Every candidate is re-simulated from scratch as one voltage sequence and checked
(:func:`verify`); only a sequence that passes is a witness. A witness proves that the
rig can be swung up and held: the draw is *feasible*. A search that fails proves
nothing; :func:`energy_bound` gives a necessary condition that does (an energy budget),
and :class:`Search` says which of the two applies.

The search uses the plant with ideal sensors, no sensor filters and an unquantised
bridge (``actuator.command_levels = 0``): the 7-bit quantisation (90 mV steps) and the
sensors are what a real controller must live with, not what the physics allows.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from pisc_model.params import ActuatorParams, NoiseParams
from pisc_plant.plant import Plant, PlantConfig

__all__ = ["EnergyBound", "Gains", "Limits", "Rig", "Search", "Verdict", "check",
           "clopper_pearson", "energy_bound", "exact_plant", "feedback_rollouts",
           "find_witness", "hold_from", "hold_gain", "make_rig", "pendulum_energy", "rollout",
           "shoot", "verify", "wrap"]

X, X_DOT, THETA, THETA_DOT, CURRENT = range(5)


@dataclass(frozen=True)
class Limits:
    """What a successful run must respect (the robustness benchmark's rules, issue 13,
    and the actuator's limits). ``current_a`` None: the voltage alone limits the
    current (no current loop limit)."""

    voltage_v: float = 11.47
    current_a: float | None = 0.9
    x_min_m: float = -0.225
    x_max_m: float = 0.125
    catch_by_s: float = 3.0
    duration_s: float = 10.0
    hold_start_s: float = 6.0
    hold_theta_rad: float = 0.05
    hold_x_m: float = 0.02
    k_va: float = 0.0015  # the catch region (4.1): theta^2 + k_va theta_dot^2 < delta_s
    delta_s: float = 0.2363

    def __post_init__(self) -> None:
        checks = [
            (self.voltage_v > 0, f"voltage_v = {self.voltage_v}: must be positive"),
            (self.current_a is None or self.current_a > 0,
             f"current_a = {self.current_a}: must be positive (or None: no limit)"),
            (self.x_min_m < 0 < self.x_max_m,
             f"safe range [{self.x_min_m}, {self.x_max_m}] m must contain x = 0"),
            (0 < self.catch_by_s < self.hold_start_s < self.duration_s,
             f"times must satisfy 0 < catch_by_s ({self.catch_by_s}) < hold_start_s "
             f"({self.hold_start_s}) < duration_s ({self.duration_s})"),
            (self.hold_theta_rad > 0 and self.hold_x_m > 0,
             "hold_theta_rad and hold_x_m must be positive"),
            (self.k_va >= 0 and self.delta_s > 0, "k_va >= 0 and delta_s > 0 (4.1)"),
        ]
        for ok, message in checks:
            if not ok:
                raise ValueError(message)


@dataclass(frozen=True)
class Rig:
    """One exactly known plant and its start: the compiled plant and its constants."""

    plant: Plant
    y0: np.ndarray  # (5,) x, x_dot, theta, theta_dot, i

    @property
    def config(self) -> PlantConfig:
        return self.plant.config

    @property
    def period_s(self) -> float:
        return self.config.loop.period_s

    # the model's constants (thesis (3.1)-(3.6), (4.2)), as the kernel uses them
    @property
    def a1(self) -> float:
        return self.config.rig.a1

    @property
    def a2(self) -> float:
        """M + m plus the rotor reflected to the cart, J_m / r^2."""
        return self.config.rig.a2 + self.config.motor.reflected_mass_kg

    @property
    def ml(self) -> float:
        return self.config.rig.ml

    @property
    def mgl(self) -> float:
        return self.config.rig.mgl

    @property
    def inertia(self) -> float:
        """J = I + m l^2, the pendulum's inertia about the pivot."""
        r = self.config.rig
        return r.pendulum_inertia_kgm2 + r.ml * r.pendulum_com_m

    @property
    def omega0(self) -> float:
        """sqrt(m g l / J), the small-swing frequency of the pendulum (3.13)."""
        return math.sqrt(self.mgl / self.inertia)


def exact_plant(base: PlantConfig, values: Mapping[str, float] | None = None) -> PlantConfig:
    """``base`` with one rig's values (``rig.*``, ``motor.*``, ``friction.*``), a full
    armature, ideal sensors without filters, an unquantised bridge, no noise, no latency.

    Raises ValueError naming a parameter that is unknown or breaks its rule.
    """
    sections: dict[str, dict[str, float]] = {}
    for name, value in (values or {}).items():
        section, _, leaf = name.partition(".")
        if section not in ("rig", "motor", "friction"):
            raise ValueError(f"{name}: not a plant parameter of rig, motor or friction")
        known = {f.name: f for f in dataclasses.fields(getattr(base, section))}
        if leaf not in known:
            raise ValueError(f"{name}: unknown parameter (known in '{section}': "
                             f"{', '.join(known)})")
        problem = known[leaf].metadata["rule"](float(value))
        if problem:
            raise ValueError(f"{name} = {value}: {problem}")
        sections.setdefault(section, {})[leaf] = float(value)
    changes = {s: dataclasses.replace(getattr(base, s), **v) for s, v in sections.items()}
    models = dataclasses.replace(base.models, armature="full", current_loop="sampled_pi",
                                 sensors="ideal", sensor_filters=False)
    return dataclasses.replace(
        base, **changes, models=models, noise=NoiseParams(),
        actuator=ActuatorParams(full_scale_v=base.actuator.full_scale_v, command_levels=0,
                                command_delay_s=0.0))


def make_rig(config: PlantConfig, x_m: float, x_dot_mps: float, theta_rad: float,
             theta_dot_radps: float) -> Rig:
    """A :class:`Rig` of an :func:`exact_plant` configuration, starting at rest current."""
    plant = Plant(config)
    if plant.size != 5:
        raise ValueError("exact_plant's configuration expected (state x, x_dot, theta, "
                         f"theta_dot, i), got {', '.join(plant.state_names)}")
    return Rig(plant, plant.initial_state(x_m, x_dot_mps, theta_rad, theta_dot_radps))


# -- simulation ---------------------------------------------------------------------------

def rollout(rig: Rig, voltages: np.ndarray, y0: np.ndarray | None = None) -> np.ndarray:
    """States at every sample for voltage sequences held one period each.

    ``voltages`` (n, K) (or (K,)): n sequences of K periods; returns (n, K + 1, 5) (or
    (K + 1, 5)), the start first. The bridge saturates the voltage at its full scale.
    """
    u = np.atleast_2d(np.asarray(voltages, dtype=float))
    n, steps = u.shape
    y = np.array(np.broadcast_to(rig.y0 if y0 is None else y0, (n, 5)), dtype=float)
    out = np.empty((n, steps + 1, 5))
    out[:, 0] = y
    period = rig.period_s
    for k in range(steps):
        y = rig.plant.advance(y, u[:, k], period)
        out[:, k + 1] = y
    return out[0] if np.ndim(voltages) == 1 else out


def wrap(theta: np.ndarray) -> np.ndarray:
    """Angle from the nearest upright, in [-pi, pi)."""
    return (np.asarray(theta) + math.pi) % (2.0 * math.pi) - math.pi


def pendulum_energy(rig: Rig, y: np.ndarray) -> np.ndarray:
    """E_p = 1/2 J theta_dot^2 + m g l (cos theta - 1): the pendulum's energy in the
    cart's frame, 0 upright at rest, -2 m g l hanging at rest (the pendulum terms of
    (2.54)); dE_p/dt = -m l x_ddot theta_dot cos(theta) - b_p theta_dot^2."""
    return (0.5 * rig.inertia * y[..., THETA_DOT] ** 2
            + rig.mgl * (np.cos(y[..., THETA]) - 1.0))


def _friction(rig: Rig, x_dot: np.ndarray) -> np.ndarray:
    """The cart's friction force the motor must overcome (kernel: b_m/r^2, b_c, F_c)."""
    f = rig.config.friction
    m = rig.config.motor
    coulomb = (f.cart_coulomb_n * np.tanh(x_dot / f.coulomb_velocity_mps)
               if rig.config.models.friction == "coulomb" else 0.0)
    viscous = (f.cart_viscous_ns_per_m if rig.config.models.friction != "none" else 0.0)
    return (m.reflected_damping_ns_per_m + viscous) * x_dot + coulomb


def _pivot(rig: Rig) -> float:
    return (rig.config.friction.pivot_viscous_nms
            if rig.config.models.friction != "none" else 0.0)


def force_for_acceleration(rig: Rig, y: np.ndarray, accel: np.ndarray) -> np.ndarray:
    """The motor force that gives the cart acceleration ``accel``: (3.3) solved for f,
    with the pivot torque -b_p theta_dot and the cart friction added back."""
    s, c = np.sin(y[..., THETA]), np.cos(y[..., THETA])
    den = rig.a2 - rig.a1 * c * c
    torque = -_pivot(rig) * y[..., THETA_DOT]
    return (accel * den + rig.a1 * rig.mgl / rig.ml * s * c
            - rig.ml * y[..., THETA_DOT] ** 2 * s + rig.a1 * c * torque / rig.ml
            + _friction(rig, y[..., X_DOT]))


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
    b_cart = float(_friction(rig, np.array(1.0)) - _friction(rig, np.array(0.0)))
    if rig.config.models.friction == "coulomb":  # the regularised Coulomb slope is not physics
        f = rig.config.friction
        b_cart -= f.cart_coulomb_n * math.tanh(1.0 / f.coulomb_velocity_mps)
    bp = _pivot(rig)
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
        hold_force = -(z @ k_gain) + _friction(rig, y[:, X_DOT])
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


# -- the check -------------------------------------------------------------------------

@dataclass(frozen=True)
class Verdict:
    """One voltage sequence re-simulated and checked against :class:`Limits`."""

    ok: bool
    reason: str  # empty when ok
    caught_at_s: float  # start of the stay in the catch region that lasts; inf if none
    largest_x_m: float
    largest_current_a: float
    largest_voltage_v: float


def check(limits: Limits, voltages: np.ndarray, states: np.ndarray, period_s: float
          ) -> tuple[np.ndarray, np.ndarray]:
    """Every rule of :class:`Limits` at every sample, for a batch: ``voltages`` (n, K)
    and the states they gave (n, K + 1, 5). Returns (ok (n,), badness (n,)): badness is
    0 for a run that passes and grows with how far each rule is missed (the search
    ranks candidates by it)."""
    x = states[..., X]
    th = wrap(states[..., THETA])
    steps = voltages.shape[-1]
    t = np.arange(steps + 1) * period_s
    region = th**2 + limits.k_va * states[..., THETA_DOT] ** 2
    outside = region >= limits.delta_s
    # the stay that lasts starts at the sample after the last one outside the region
    start = np.where(outside.any(axis=-1),
                     steps + 1 - np.argmax(outside[..., ::-1], axis=-1), 0)
    caught = np.where(start > steps, np.inf, t[np.minimum(start, steps)])
    late = np.where(np.isinf(caught), limits.duration_s + np.min(region, axis=-1),
                    np.maximum(caught - limits.catch_by_s, 0.0))
    over = (np.max(np.maximum(x - limits.x_max_m, 0.0), axis=-1)
            + np.max(np.maximum(limits.x_min_m - x, 0.0), axis=-1))
    hold = t >= limits.hold_start_s - 1e-12
    hold_th = np.max(np.abs(th[..., hold]), axis=-1)
    hold_x = np.max(np.abs(x[..., hold]), axis=-1)
    excess = np.zeros(len(x))
    if limits.current_a is not None:
        excess = np.maximum(np.max(np.abs(states[..., CURRENT]), axis=-1)
                            - 1.02 * limits.current_a, 0.0)
    excess = excess + np.maximum(np.max(np.abs(voltages), axis=-1) - limits.voltage_v - 1e-9,
                                 0.0)
    ok = ((over == 0.0) & (late == 0.0) & (hold_th < limits.hold_theta_rad)
          & (hold_x < limits.hold_x_m) & (excess == 0.0))
    badness = (over / 0.01 + late + np.maximum(hold_th / limits.hold_theta_rad - 1.0, 0.0)
               + np.maximum(hold_x / limits.hold_x_m - 1.0, 0.0) + excess / 0.1)
    badness = np.where(ok, 0.0, np.maximum(badness, 1e-9))
    return ok, badness


def verify(rig: Rig, limits: Limits, voltages: np.ndarray) -> Verdict:
    """Re-simulate one voltage sequence (one value a period, ``duration_s`` long) from
    the rig's start and check every rule of :class:`Limits` at every sample."""
    period = rig.period_s
    steps = int(round(limits.duration_s / period))
    u = np.asarray(voltages, dtype=float)
    if u.shape != (steps,):
        raise ValueError(f"voltages: {steps} values expected (one a period over "
                         f"{limits.duration_s} s), got shape {u.shape}")
    states = rollout(rig, u)
    x = states[:, X]
    th = wrap(states[:, THETA])
    t = np.arange(steps + 1) * period
    largest_i = float(np.max(np.abs(states[:, CURRENT])))
    largest_u = float(np.max(np.abs(u)))
    region = th**2 + limits.k_va * states[:, THETA_DOT] ** 2 < limits.delta_s
    outside = np.flatnonzero(~region)
    if len(outside) == 0:
        caught = 0.0
    elif outside[-1] == steps:
        caught = math.inf
    else:
        caught = float(t[outside[-1] + 1])
    hold = t >= limits.hold_start_s - 1e-12
    reasons = []
    if np.any(x < limits.x_min_m) or np.any(x > limits.x_max_m):
        k = int(np.argmax((x < limits.x_min_m) | (x > limits.x_max_m)))
        reasons.append(f"cart left the safe range at {t[k]:.3f} s (x = {x[k]:+.4f} m)")
    if largest_u > limits.voltage_v + 1e-9:
        reasons.append(f"voltage {largest_u:.3f} V above {limits.voltage_v} V")
    if limits.current_a is not None and largest_i > limits.current_a * 1.02:
        reasons.append(f"current {largest_i:.3f} A above {limits.current_a} A")
    if caught > limits.catch_by_s:
        reasons.append("never in the catch region for good" if math.isinf(caught)
                       else f"in the catch region for good only from {caught:.3f} s")
    if np.max(np.abs(th[hold])) >= limits.hold_theta_rad:
        reasons.append(f"|theta| up to {np.max(np.abs(th[hold])):.3f} rad in the hold")
    if np.max(np.abs(x[hold])) >= limits.hold_x_m:
        reasons.append(f"|x| up to {np.max(np.abs(x[hold])):.3f} m in the hold")
    return Verdict(not reasons, "; ".join(reasons), caught, float(np.max(np.abs(x))),
                   largest_i, largest_u)


# -- direct shooting ---------------------------------------------------------------------

def _expand(knots: np.ndarray, per_knot: int) -> np.ndarray:
    return np.repeat(knots, per_knot, axis=-1)


def shoot(rig: Rig, limits: Limits, guess: np.ndarray, per_knot: int,
          margin_m: float = 0.003, max_nfev: int = 60) -> np.ndarray:
    """Direct shooting: knot voltages (piecewise constant over ``per_knot`` periods)
    from ``guess`` (K,) that bring the rig upright at rest at the horizon's end.

    ``scipy.optimize.least_squares`` (trust region reflective, the bridge's voltage as
    bounds) on the residuals: the terminal theta (from the nearest upright), theta_dot /
    omega_0, x_dot and x (weighted), and penalties for every sample's distance past the
    safe range less ``margin_m`` and past the current limit. The Jacobian by forward
    differences, all K + 1 rollouts in one batch on the compiled plant.
    """
    from scipy.optimize import least_squares

    limit_i = limits.current_a
    hi, lo = limits.x_max_m - margin_m, limits.x_min_m + margin_m
    w0 = rig.omega0

    def residuals(states: np.ndarray) -> np.ndarray:
        end = states[:, -1]
        terminal = np.stack([2.0 * wrap(end[:, THETA]), 2.0 * end[:, THETA_DOT] / w0,
                             1.0 * end[:, X_DOT], 0.5 * end[:, X]], axis=-1)
        x = states[:, 1:, X]
        track = 30.0 * (np.maximum(x - hi, 0.0) + np.maximum(lo - x, 0.0))
        parts = [terminal, track]
        if limit_i is not None:
            parts.append(3.0 * np.maximum(np.abs(states[:, 1:, CURRENT]) - limit_i, 0.0))
        return np.concatenate(parts, axis=-1)

    step = 1e-3  # V

    def fun(v: np.ndarray) -> np.ndarray:
        return residuals(rollout(rig, _expand(v[None, :], per_knot)))[0]

    def jac(v: np.ndarray) -> np.ndarray:
        # forward differences inward from the bounds
        signs = np.where(v + step > limits.voltage_v, -1.0, 1.0)
        batch = np.vstack([v, v + step * np.diag(signs)])
        r = residuals(rollout(rig, _expand(batch, per_knot)))
        return ((r[1:] - r[0]) / (step * signs[:, None])).T

    v0 = np.clip(np.asarray(guess, dtype=float), -limits.voltage_v + 1e-6,
                 limits.voltage_v - 1e-6)
    result = least_squares(fun, v0, jac=jac,
                           bounds=(-limits.voltage_v, limits.voltage_v), method="trf",
                           x_scale=1.0, max_nfev=max_nfev, xtol=1e-10, ftol=1e-10)
    return np.asarray(result.x)


# -- the bound ---------------------------------------------------------------------------

@dataclass(frozen=True)
class EnergyBound:
    """A necessary condition for reaching upright by ``horizon_s`` (see
    :func:`energy_bound`); ``infeasible`` proves that no input can."""

    needed_j: float  # -E_p(0): what the pendulum must gain
    largest_gain_j: float  # the most any input can add in the horizon, pivot loss paid
    accel_bound_mps2: float  # the largest cart acceleration any input can give
    horizon_s: float

    @property
    def infeasible(self) -> bool:
        return self.largest_gain_j < self.needed_j


def energy_bound(rig: Rig, limits: Limits, horizon_s: float | None = None) -> EnergyBound:
    """An energy budget that no input can beat.

    The pendulum's energy in the cart's frame E_p (:func:`pendulum_energy`) obeys
    dE_p/dt = -m l x_ddot theta_dot cos(theta) - b_p theta_dot^2. Upright at rest is
    E_p = 0; until E_p first reaches 0, |theta_dot| <= 2 omega_0, so by (3.3)
    |x_ddot| <= a_b = (f_max + F_c + m l (2 omega_0)^2 + a1 g / 2 + a1 b_p 2 omega_0 / (m l))
    / (a2 - a1), f_max = k_m i_max / r (4.2) with i_max the current limit (or the
    stall current u_max / R without one) and the cart's viscous friction taken at the
    no-load speed u_max r / k_e. With S = int theta_dot^2 dt and Cauchy-Schwarz,
    int |theta_dot| dt <= sqrt(T S), so the gain is at most
    max_S (m l a_b sqrt(T S) - b_p S) = (m l a_b)^2 T / (4 b_p) (unbounded without pivot
    friction). If that is below -E_p(0), no input reaches upright by T.
    """
    horizon = limits.catch_by_s if horizon_s is None else horizon_s
    m = rig.config.motor
    i_max = (limits.current_a if limits.current_a is not None
             else limits.voltage_v / m.resistance_ohm)
    no_load = limits.voltage_v * m.wheel_radius_m / m.back_emf_v_s_per_rad
    friction = float(abs(_friction(rig, np.array(no_load))))
    w = 2.0 * rig.omega0
    bp = _pivot(rig)
    f_bound = (m.force_per_amp * i_max + friction + rig.ml * w * w
               + rig.a1 * rig.mgl / rig.ml / 2.0 + rig.a1 * bp * w / rig.ml)
    accel = f_bound / (rig.a2 - rig.a1)
    needed = float(-pendulum_energy(rig, rig.y0))
    gain = math.inf if bp == 0.0 else (rig.ml * accel) ** 2 * horizon / (4.0 * bp)
    return EnergyBound(needed, gain, accel, horizon)


# -- the search --------------------------------------------------------------------------

@dataclass(frozen=True)
class Search:
    """What :func:`find_witness` found for one rig."""

    feasible: bool
    how: str  # 'feedback', 'shooting', 'bound' (proved infeasible) or 'not found'
    voltages: np.ndarray | None  # the witness, one value a period (None without one)
    verdict: Verdict | None  # the witness's check, or the best failed candidate's
    bound: EnergyBound
    tried: int  # candidates checked


def find_witness(rig: Rig, limits: Limits, rng: np.random.Generator, rollouts: int = 48,
                 rounds: int = 4, restarts: int = 2, knot_periods: int = 8,
                 max_nfev: int = 30) -> Search:
    """Search for a witness, stopping at the first.

    The energy bound first (:func:`energy_bound`). Then ``rounds`` batches of
    ``rollouts`` perfect-knowledge feedback gain sets (:func:`feedback_rollouts`): the
    first uniform over the gains' ranges, each next one drawn around the best eighth so
    far with a spread that halves (a cross-entropy search). If none passes, direct
    shooting (:func:`shoot`) from the ``restarts`` best rollouts, horizon at their
    closest approach to upright before ``catch_by_s`` (knots of ``knot_periods``
    periods), each handed to the LQR hold. A candidate counts only once :func:`verify`
    passes it, re-simulated alone.
    """
    bound = energy_bound(rig, limits)
    if bound.infeasible:
        return Search(False, "bound", None, None, bound, 0)
    period = rig.period_s
    steps = int(round(limits.duration_s / period))
    k_gain = hold_gain(rig)
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
        for j in np.flatnonzero(ok)[:2]:
            verdict = verify(rig, limits, volts[j])
            tried += 1
            if verdict.ok:
                return Search(True, "feedback", volts[j], verdict, bound, tried)
        pool_u.append(unit)
        pool_v.append(volts)
        pool_s.append(states)
        pool_b.append(badness)
    volts = np.concatenate(pool_v)
    states = np.concatenate(pool_s)
    badness = np.concatenate(pool_b)
    best = verify(rig, limits, volts[int(np.argmin(badness))])
    tried += 1
    last = int(round(limits.catch_by_s / period))
    region = wrap(states[:, : last + 1, THETA]) ** 2 + limits.k_va * states[:, : last + 1,
                                                                            THETA_DOT] ** 2
    for j in np.argsort(badness)[:restarts]:
        end = int(np.clip(np.argmin(region[j]) + 4, 2 * knot_periods, last))
        end -= end % knot_periods
        guess = volts[j, :end].reshape(-1, knot_periods).mean(axis=1)
        knots = shoot(rig, limits, guess, knot_periods, max_nfev=max_nfev)
        head = _expand(knots, knot_periods)
        y_end = rollout(rig, head)[-1]
        tail, _ = hold_from(rig, limits, y_end[None, :], steps - end, k_gain)
        candidate = np.concatenate([head, tail[0]])
        verdict = verify(rig, limits, candidate)
        tried += 1
        if verdict.ok:
            return Search(True, "shooting", candidate, verdict, bound, tried)
    return Search(False, "not found", None, best, bound, tried)


def clopper_pearson(successes: int, n: int, level: float = 0.95) -> tuple[float, float]:
    """Clopper-Pearson (exact) interval of a success probability."""
    from scipy.stats import beta

    if n < 1 or not 0 <= successes <= n:
        raise ValueError(f"{successes} successes of {n}: need 0 <= successes <= n, n >= 1")
    tail = (1.0 - level) / 2.0
    low = 0.0 if successes == 0 else float(beta.ppf(tail, successes, n - successes + 1))
    high = 1.0 if successes == n else float(beta.ppf(1.0 - tail, successes + 1, n - successes))
    return low, high
