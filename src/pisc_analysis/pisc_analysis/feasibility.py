"""Can any controller swing a given rig up and hold it? An upper bound (docs/feasibility.md).

For one plant known exactly (its true m, l, I, M, motor and friction, its initial state,
no noise, no latency), :func:`find_witness` looks for a voltage sequence, one value per
control period (zero-order hold, the plant's own input), that brings the pendulum from
its initial state into the catch region by ``catch_by_s`` and holds it there, within
the robustness benchmark's rules (:class:`Limits`): the cart inside the safe range at
every sample, |u| within the bridge's voltage, |i| within the current loop's limit at
every sample, from ``hold_start_s`` |theta| and |x| within the hold's bounds.

Three searches, all on the compiled plant (:class:`pisc_plant.plant.Plant`):

1. **Perfect-knowledge feedback** (:func:`feedback_rollouts`): an energy pump on the
   true pendulum energy with a track guard, the force computed from the true model
   (3.3), (3.5), handed to a discrete LQR hold in the catch region; many random gain
   sets at once, as a batch of rigs.
2. **Direct shooting** (:func:`shoot`): the voltage piecewise constant over knots,
   ``scipy.optimize.least_squares`` on the terminal state (upright at rest) with the
   track and current limits as penalty residuals, started from the best feedback
   rollouts and from random pumps; the LQR hold takes over at the end of the horizon.
3. **Multiple shooting** (:func:`transcribe`, optional): the catch deadline brought
   down by continuation from the best feedback rollouts, 5 ms knots, 0.2 s segments.

Every candidate is re-simulated from scratch as one voltage sequence and checked
(:func:`verify`); only a sequence that passes is a witness. A witness proves that the
rig can be swung up and held: the draw is *feasible*. A search that fails proves
nothing; :func:`energy_bound` gives necessary conditions that do (an energy budget and
the comparison lemma's :func:`climb_time` to the catch region's energy), and
:class:`Search` says which applies.

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

__all__ = ["EnergyBound", "Gains", "Limits", "Pool", "Rig", "Search", "Transcribed",
           "Transcription", "Verdict", "accel_bound", "check", "climb_time", "clopper_pearson",
           "energy_bound", "exact_plant", "feedback_rollouts", "feedback_search",
           "find_witness", "hold_from", "hold_gain", "make_rig", "pendulum_energy",
           "region_energy", "rollout", "samples", "shoot", "transcribe", "verify", "wrap"]

X, X_DOT, THETA, THETA_DOT, CURRENT = range(5)


@dataclass(frozen=True)
class Limits:
    """What a successful run must respect (the robustness benchmark's rules and the
    actuator's limits): a run of ``duration_s``, in the catch region for good from some
    t <= ``catch_by_s``, held from ``hold_start_s`` to its end. ``current_a`` None: the
    voltage alone limits the current (no current loop limit)."""

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
        for name in ("voltage_v", "x_min_m", "x_max_m", "catch_by_s", "duration_s",
                     "hold_start_s", "hold_theta_rad", "hold_x_m", "k_va", "delta_s"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"{name} = {getattr(self, name)}: must be finite")
        checks = [
            (self.voltage_v > 0, f"voltage_v = {self.voltage_v}: must be positive"),
            (self.current_a is None or self.current_a > 0,
             f"current_a = {self.current_a}: must be positive (or None: no limit)"),
            (self.x_min_m < 0 < self.x_max_m,
             f"safe range [{self.x_min_m}, {self.x_max_m}] m must contain x = 0"),
            (0 < self.catch_by_s <= self.hold_start_s < self.duration_s,
             f"times must satisfy 0 < catch_by_s ({self.catch_by_s}) <= hold_start_s "
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

def samples(seconds: float, period_s: float) -> int:
    """The last sample at or before ``seconds`` (a deadline between two samples is met
    only by the earlier one)."""
    return int(math.floor(seconds / period_s + 1e-9))


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
                    np.where(caught > limits.catch_by_s + 1e-9, caught - limits.catch_by_s,
                             0.0))
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
    if caught > limits.catch_by_s + 1e-9:
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


# -- multiple shooting -------------------------------------------------------------------

@dataclass(frozen=True)
class Transcription:
    """The settings of :func:`transcribe` (multiple shooting, the catch deadline by
    continuation)."""

    knot_periods: int = 1  # the voltage piecewise constant over knots of 1 period (5 ms)
    segment_periods: int = 40  # a shooting segment: 0.2 s
    tail_s: float = 0.6  # the catch region kept this long past the deadline, then the hold
    deadline_step_s: float = 0.04  # the continuation's first step of the catch deadline
    first_deadline_after_s: float = 0.5  # the latest deadline it starts from, past catch_by_s
    guesses: int = 2  # the best feedback rollouts it starts from
    max_nfev: int = 40  # least-squares evaluations per deadline
    track_margin_m: float = 0.0005
    region_margin: float = 0.002  # below delta_s of (4.1)
    current_margin: float = 0.99  # of the current limit
    tolerance: float = 1e-3  # the largest residual (scaled) that counts as met


@dataclass(frozen=True)
class Transcribed:
    """What :func:`transcribe` found: a witness (or None), its check, the earliest
    deadline met with a zero residual (inf if none), candidates checked."""

    voltages: np.ndarray | None
    verdict: Verdict | None
    earliest_s: float
    tried: int


# scales of the shooting nodes' states x, x_dot, theta, theta_dot, i (the unknowns are
# the states over these)
_NODE_SCALE = np.array([0.01, 0.1, 0.02, 0.2, 0.05])


class _Shooting:
    """Residuals and their Jacobian of one multiple-shooting problem: the voltage
    piecewise constant over knots of ``knot_periods``, the horizon cut into segments of
    ``segment_periods``, the unknowns the knot voltages and the state at the start of
    every segment but the first (scaled by :data:`_NODE_SCALE`). A residual block per
    segment: three hinges per sample (the safe range less a margin; the current limit;
    from the deadline sample on, the catch region (4.1) less a margin), then the
    continuity defect to the next node (5), or, for the last segment, the hand-over
    hinges (4): near upright, slow, the cart near the middle, where the LQR hold takes
    over. A zero residual is a voltage sequence meeting every rule up to the horizon."""

    def __init__(self, rig: Rig, limits: Limits, settings: Transcription, horizon: int,
                 deadline: int) -> None:
        self.rig, self.limits, self.s = rig, limits, settings
        self.kp, self.seg = settings.knot_periods, settings.segment_periods
        self.nseg = horizon // self.seg
        self.kps = self.seg // self.kp
        self.nknots = self.nseg * self.kps
        self.horizon, self.deadline = horizon, deadline
        self.hi = limits.x_max_m - settings.track_margin_m
        self.lo = limits.x_min_m + settings.track_margin_m
        self.i_max = (math.inf if limits.current_a is None
                      else settings.current_margin * limits.current_a)
        self.region = limits.delta_s - settings.region_margin
        self.block = 3 * self.seg + 5

    def split(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        knots = z[: self.nknots].reshape(self.nseg, self.kps)
        nodes = z[self.nknots:].reshape(self.nseg - 1, 5) * _NODE_SCALE
        return knots, np.vstack([self.rig.y0[None, :], nodes])

    def segments(self, starts: np.ndarray, knots: np.ndarray) -> np.ndarray:
        # batches of at most 256 rigs: the kernel's single-thread path (kernel.CHUNK),
        # several times faster per rig than its threaded one on a shared 2-core machine
        volts = _expand(knots, self.kp)
        return np.concatenate([rollout(self.rig, volts[a: a + 256], y0=starts[a: a + 256])
                               for a in range(0, len(starts), 256)])

    def _blocks(self, traj: np.ndarray, seg_index: np.ndarray, following: np.ndarray
                ) -> np.ndarray:
        """Residual blocks (B, block) of segment trajectories (B, seg + 1, 5) that are
        segments ``seg_index`` (B,), the next node ``following`` (B, 5)."""
        y = traj[:, 1:]
        k = seg_index[:, None] * self.seg + np.arange(1, self.seg + 1)[None, :]
        x = y[..., X]
        track = (np.maximum(x - self.hi, 0.0) + np.maximum(self.lo - x, 0.0)) / 0.005
        current = np.maximum(np.abs(y[..., CURRENT]) - self.i_max, 0.0) / 0.02
        reach = wrap(y[..., THETA]) ** 2 + self.limits.k_va * y[..., THETA_DOT] ** 2
        region = np.where(k >= self.deadline, np.maximum(reach - self.region, 0.0) / 0.02, 0.0)
        end = traj[:, -1]
        defect = (end - following) / _NODE_SCALE
        last = seg_index == self.nseg - 1
        handover = np.stack([
            np.maximum(np.abs(wrap(end[:, THETA])) - 0.05, 0.0) / 0.01,
            np.maximum(np.abs(end[:, THETA_DOT]) - 0.3, 0.0) / 0.1,
            np.maximum(np.abs(end[:, X_DOT]) - 0.15, 0.0) / 0.05,
            np.maximum(np.abs(end[:, X]) - 0.06, 0.0) / 0.01,
            np.zeros(len(end))], axis=-1)
        tail = np.where(last[:, None], handover, defect)
        return np.concatenate([track, current, region, tail], axis=-1)

    def residuals(self, z: np.ndarray) -> np.ndarray:
        knots, starts = self.split(z)
        traj = self.segments(starts, knots)
        index = np.arange(self.nseg)
        following = np.vstack([starts[1:], np.zeros((1, 5))])
        return self._blocks(traj, index, following).ravel()

    def jacobian(self, z: np.ndarray) -> np.ndarray:
        """Forward differences, every segment's perturbations in one batch: a segment's
        residuals depend on its knots and its start only (and its defect on the next
        node, with derivative -1 in the scaled unknowns)."""
        knots, starts = self.split(z)
        u_max = self.limits.voltage_v
        step_u, step_s = 1e-4, 1e-6
        per = 1 + self.kps + 5
        b_knots = np.repeat(knots, per, axis=0).reshape(self.nseg, per, self.kps)
        b_starts = np.repeat(starts, per, axis=0).reshape(self.nseg, per, 5)
        signs = np.where(knots + step_u > u_max, -1.0, 1.0)  # inward from the bound
        for a in range(self.kps):
            b_knots[:, 1 + a, a] += step_u * signs[:, a]
        for a in range(5):
            b_starts[:, 1 + self.kps + a, a] += step_s * _NODE_SCALE[a]
        index = np.repeat(np.arange(self.nseg), per)
        following = np.repeat(np.vstack([starts[1:], np.zeros((1, 5))]), per, axis=0)
        traj = self.segments(b_starts.reshape(-1, 5), b_knots.reshape(-1, self.kps))
        r = self._blocks(traj, index, following).reshape(self.nseg, per, self.block)
        base = r[:, 0]
        jac = np.zeros((self.nseg, self.block, len(z)))
        for j in range(self.nseg):
            cols = slice(j * self.kps, (j + 1) * self.kps)
            jac[j, :, cols] = ((r[j, 1: 1 + self.kps] - base[j]) / (step_u * signs[j][:, None])).T
            if j > 0:
                c0 = self.nknots + 5 * (j - 1)
                jac[j, :, c0: c0 + 5] = ((r[j, 1 + self.kps:] - base[j]) / step_s).T
            if j < self.nseg - 1:
                c1 = self.nknots + 5 * j
                jac[j, 3 * self.seg + np.arange(5), c1 + np.arange(5)] = -1.0
        from scipy.sparse import csr_matrix

        return csr_matrix(jac.reshape(self.nseg * self.block, len(z)))

    def unknowns(self, voltages: np.ndarray, states: np.ndarray) -> np.ndarray:
        """The unknowns of a trajectory: knot means of ``voltages`` (>= horizon values)
        and ``states`` (>= horizon + 1 samples) at the segments' starts."""
        knots = voltages[: self.horizon].reshape(-1, self.kp).mean(axis=1)
        nodes = states[self.seg: self.horizon: self.seg] / _NODE_SCALE
        return np.concatenate([knots, nodes.ravel()])

    def solve(self, z0: np.ndarray, max_nfev: int) -> tuple[np.ndarray, float]:
        from scipy.optimize import least_squares

        u_max = self.limits.voltage_v
        lower = np.full(len(z0), -np.inf)
        upper = np.full(len(z0), np.inf)
        lower[: self.nknots], upper[: self.nknots] = -u_max, u_max
        z0 = np.clip(z0, lower + 1e-9, upper - 1e-9)
        result = least_squares(self.residuals, z0, jac=self.jacobian, bounds=(lower, upper),
                               method="trf", tr_solver="lsmr", max_nfev=max_nfev,
                               tr_options={"atol": 1e-10, "btol": 1e-10}, x_scale="jac",
                               xtol=1e-12, ftol=1e-12, gtol=1e-12)
        return np.asarray(result.x), float(np.max(np.abs(result.fun), initial=0.0))


def transcribe(rig: Rig, limits: Limits, pool: Pool, settings: Transcription | None = None,
               k_gain: np.ndarray | None = None) -> Transcribed:
    """Multiple shooting with the catch deadline as the continuation parameter.

    The rule "in the catch region (4.1) for good from some t <= catch_by_s" is the same
    as "in it at every sample from catch_by_s on": the deadline. From each of the
    ``guesses`` best rollouts of the feedback search (``pool``), whose stay in the region
    begins late (at t_c), the deadline starts at min(t_c, ``catch_by_s`` +
    ``first_deadline_after_s``; a budget: a local method seldom moves a catch by
    seconds) and comes down by ``deadline_step_s`` to ``catch_by_s``; at each deadline
    d, ``scipy.optimize.least_squares`` (trust region reflective, the bridge's voltage
    as bounds) drives the residuals of :class:`_Shooting` over the horizon d +
    ``tail_s`` to zero (at most ``tolerance``), warm-started from the last deadline met
    (nodes included). A deadline not met is tried again half as far below the last one
    met, down to one period; then it stops. Met at ``catch_by_s``, the knots are
    re-simulated alone from the start, handed to the LQR hold (:func:`hold_from`) and
    checked (:func:`verify`)."""
    s = settings or Transcription()
    if s.segment_periods % s.knot_periods:
        raise ValueError(f"segment_periods ({s.segment_periods}) must be a multiple of "
                         f"knot_periods ({s.knot_periods})")
    period = rig.period_s
    steps = int(round(limits.duration_s / period))
    k_gain = hold_gain(rig) if k_gain is None else k_gain
    target = samples(limits.catch_by_s, period)
    step = max(1, int(round(s.deadline_step_s / period)))
    outside = (wrap(pool.states[..., THETA]) ** 2
               + limits.k_va * pool.states[..., THETA_DOT] ** 2 >= limits.delta_s)
    start = np.where(outside.any(axis=-1), steps + 1 - np.argmax(outside[..., ::-1], axis=-1), 0)
    earliest, tried = math.inf, 0
    best_verdict = None
    for j in np.argsort(pool.badness)[: s.guesses]:
        d = min(int(start[j]), target + int(round(s.first_deadline_after_s / period)))
        d = target + step * math.ceil(max(d - target, 0) / step)
        voltages, states = pool.voltages[j], pool.states[j]
        met, stride = math.inf, step
        while d >= target:
            horizon = s.segment_periods * math.ceil((d + s.tail_s / period)
                                                    / s.segment_periods)
            if horizon >= steps:
                break
            problem = _Shooting(rig, limits, s, horizon, d)
            z, worst = problem.solve(problem.unknowns(voltages, states), s.max_nfev)
            if worst > s.tolerance:
                # not met: a smaller step from the last deadline met, down to one period
                if stride == 1 or math.isinf(met):
                    break
                d += stride
                stride = max(1, stride // 2)
                d -= stride
                continue
            met = d * period
            # the next deadline starts from this solution: its voltages and the states of
            # its segments re-simulated from its nodes
            knots, starts = problem.split(z)
            seg_states = problem.segments(starts, knots)
            states = np.concatenate([seg_states[:, :-1].reshape(-1, 5), seg_states[-1:, -1]])
            voltages = _expand(knots.ravel(), problem.kp)
            if d == target:
                break
            d = max(target, d - stride)
        earliest = min(earliest, met)
        if not met <= limits.catch_by_s + period / 2:
            continue
        y = rollout(rig, voltages)
        tail, _ = hold_from(rig, limits, y[-1][None, :], steps - len(voltages), k_gain)
        candidate = np.concatenate([voltages, tail[0]])
        verdict = verify(rig, limits, candidate)
        tried += 1
        if verdict.ok:
            return Transcribed(candidate, verdict, met, tried)
        best_verdict = verdict
    return Transcribed(None, best_verdict, earliest, tried)


# -- the bound ---------------------------------------------------------------------------

@dataclass(frozen=True)
class EnergyBound:
    """A necessary condition for entering the catch region by ``horizon_s`` (see
    :func:`energy_bound`); ``infeasible`` proves that no input can."""

    needed_j: float  # E* - E_p(0): what the pendulum must gain to enter the region
    largest_gain_j: float  # the most any input can add in the horizon, pivot loss paid
    accel_bound_mps2: float  # the largest cart acceleration any input can give
    horizon_s: float
    least_time_s: float = 0.0  # :func:`climb_time`: no input enters the region sooner

    @property
    def infeasible(self) -> bool:
        return self.largest_gain_j < self.needed_j or self.least_time_s > self.horizon_s


def region_energy(rig: Rig, limits: Limits) -> float:
    """E*: the least pendulum energy E_p inside the catch region (4.1), theta^2 + k_va
    theta_dot^2 < delta_s; at theta_dot = 0, |theta| = sqrt(delta_s): m g l (cos
    sqrt(delta_s) - 1). The pendulum enters the region with E_p > E*."""
    return rig.mgl * (math.cos(min(math.sqrt(limits.delta_s), math.pi)) - 1.0)


def accel_bound(rig: Rig, limits: Limits) -> float:
    """a_b: the largest |x_ddot| any input can give while |theta_dot| <= 2 omega_0 (3.3):
    (f_max + cart friction at the no-load speed + m l (2 omega_0)^2 + a1 g / 2
    + a1 b_p 2 omega_0 / (m l)) / (a2 - a1), f_max = k_m i_max / r (4.2) with i_max the
    current limit and the check's 2 % tolerance (or the stall current u_max / R without
    a limit)."""
    m = rig.config.motor
    i_max = (1.02 * limits.current_a if limits.current_a is not None
             else limits.voltage_v / m.resistance_ohm)
    no_load = limits.voltage_v * m.wheel_radius_m / m.back_emf_v_s_per_rad
    friction = float(abs(_friction(rig, np.array(no_load))))
    w = 2.0 * rig.omega0
    f_bound = (m.force_per_amp * i_max + friction + rig.ml * w * w
               + rig.a1 * rig.mgl / rig.ml / 2.0 + rig.a1 * _pivot(rig) * w / rig.ml)
    return f_bound / (rig.a2 - rig.a1)


def energy_bound(rig: Rig, limits: Limits, horizon_s: float | None = None) -> EnergyBound:
    """An energy budget that no input can beat.

    The pendulum's energy in the cart's frame E_p (:func:`pendulum_energy`) obeys
    dE_p/dt = -m l x_ddot theta_dot cos(theta) - b_p theta_dot^2. To be in the catch
    region the pendulum needs E_p > E* (:func:`region_energy`, < 0); until E_p first
    reaches E*, |theta_dot| <= 2 omega_0, so |x_ddot| <= a_b (:func:`accel_bound`).
    With S = int theta_dot^2 dt and Cauchy-Schwarz, int |theta_dot| dt <= sqrt(T S), so
    the gain is at most max_S (m l a_b sqrt(T S) - b_p S) = (m l a_b)^2 T / (4 b_p)
    (unbounded without pivot friction). If that is below E* - E_p(0), no input enters
    the catch region by T. The comparison lemma (:func:`climb_time`, ``least_time_s``)
    is a second, sharper test: no input enters it sooner than that.
    """
    horizon = limits.catch_by_s if horizon_s is None else horizon_s
    bp = _pivot(rig)
    accel = accel_bound(rig, limits)
    needed = float(region_energy(rig, limits) - pendulum_energy(rig, rig.y0))
    gain = math.inf if bp == 0.0 else (rig.ml * accel) ** 2 * horizon / (4.0 * bp)
    return EnergyBound(needed, gain, accel, horizon, climb_time(rig, limits))


def climb_time(rig: Rig, limits: Limits, cells: int = 400, phases: int = 2000) -> float:
    """A lower bound on the time any input needs to bring E_p from E_p(0) to E*
    (:func:`region_energy`): the comparison lemma on dE_p/dt <= G(E_p).

    With c = cos(theta) and theta_dot^2 = w^2(E, c) = 2 (E + m g l (1 - c)) / J at
    energy E (the pendulum terms of (2.54)), dE_p/dt = -m l x_ddot theta_dot c - b_p
    theta_dot^2 <= G(E) = max_c (m l a_b w |c| - b_p w^2) over the phases c with
    w^2 >= 0, a_b of :func:`accel_bound` (valid while E_p < E*). E* - E_p(0) is cut into
    ``cells`` equal cells of energy; the phase range [-1, 1] into ``phases`` cells, on
    each of which w is largest at the lower c and at the cell's upper energy, w^2
    smallest at the upper c and the lower energy: that upper-bounds G over the energy
    cell (G_k), every step an inequality. Crossing energy cell k upward takes at least
    dE / G_k (E_p rises at most at G_k while in it, and must rise by dE there), so the
    sum over the cells bounds the time. Returns 0 if E_p(0) >= E*.
    """
    start = float(pendulum_energy(rig, rig.y0))
    target = region_energy(rig, limits)
    if start >= target:
        return 0.0
    a_b, bp, ml, mgl, j = accel_bound(rig, limits), _pivot(rig), rig.ml, rig.mgl, rig.inertia
    edges = np.linspace(start, target, cells + 1)
    c = np.linspace(-1.0, 1.0, phases + 1)
    c_lo, c_hi = c[:-1], c[1:]
    c_abs = np.maximum(np.abs(c_lo), np.abs(c_hi))
    e_lo, e_hi = edges[:-1, None], edges[1:, None]
    w_top = np.sqrt(np.maximum(2.0 * (e_hi + mgl * (1.0 - c_lo)) / j, 0.0))
    w2_low = np.maximum(2.0 * (e_lo + mgl * (1.0 - c_hi)) / j, 0.0)
    reachable = 2.0 * (e_hi + mgl * (1.0 - c_lo)) >= 0.0
    g = np.max(np.where(reachable, ml * a_b * w_top * c_abs - bp * w2_low, -np.inf), axis=1)
    return float(np.sum(np.diff(edges) / np.maximum(g, 1e-300)))


# -- the search --------------------------------------------------------------------------

@dataclass(frozen=True)
class Search:
    """What :func:`find_witness` found for one rig."""

    feasible: bool
    how: str  # 'feedback', 'shooting', 'multiple shooting',
    # 'bound' (proved infeasible) or 'not found'
    voltages: np.ndarray | None  # the witness, one value a period (None without one)
    verdict: Verdict | None  # the witness's check, or the best failed candidate's
    bound: EnergyBound
    tried: int  # candidates checked
    # the earliest catch deadline multiple shooting met (its residual zero), inf if none;
    # NaN when it did not run
    transcribed_s: float = math.nan


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
    """The cross-entropy search over the pump's gains (:func:`find_witness`'s first
    stage): ``rounds`` batches of ``rollouts`` gain sets, the first uniform, each next
    one around the best eighth so far with a spread that halves. Returns (the witness's
    voltages and verdict, or None, None; the pool of every rollout; candidates checked)."""
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


def find_witness(rig: Rig, limits: Limits, rng: np.random.Generator, rollouts: int = 48,
                 rounds: int = 4, restarts: int = 2, knot_periods: int = 8,
                 max_nfev: int = 30, transcription: Transcription | None = None) -> Search:
    """Search for a witness, stopping at the first.

    The energy bound first (:func:`energy_bound`). Then ``rounds`` batches of
    ``rollouts`` perfect-knowledge feedback gain sets (:func:`feedback_search`). If none
    passes, direct shooting (:func:`shoot`) from the ``restarts`` best rollouts, horizon
    at their closest approach to upright before ``catch_by_s`` (knots of
    ``knot_periods`` periods), each handed to the LQR hold. With ``transcription``,
    last, multiple shooting with the catch deadline brought down by continuation
    (:func:`transcribe`) from the best rollouts. A candidate counts only once
    :func:`verify` passes it, re-simulated alone.
    """
    bound = energy_bound(rig, limits)
    if bound.infeasible:
        return Search(False, "bound", None, None, bound, 0)
    period = rig.period_s
    steps = int(round(limits.duration_s / period))
    k_gain = hold_gain(rig)
    found, verdict, pool, tried = feedback_search(rig, limits, rng, rollouts, rounds, k_gain)
    if found is not None:
        return Search(True, "feedback", found, verdict, bound, tried)
    volts, states, badness = pool.voltages, pool.states, pool.badness
    best = verify(rig, limits, volts[int(np.argmin(badness))])
    tried += 1
    last = samples(limits.catch_by_s, period)
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
    if transcription is not None:
        result = transcribe(rig, limits, pool, transcription, k_gain)
        tried += result.tried
        if result.voltages is not None:
            return Search(True, "multiple shooting", result.voltages, result.verdict, bound,
                          tried, result.earliest_s)
        return Search(False, "not found", None, best, bound, tried, result.earliest_s)
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
