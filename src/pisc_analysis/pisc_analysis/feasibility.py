"""Can any controller swing a given rig up and hold it? The problem and its check.

The feasibility study (docs/feasibility.md) asks it of one plant known exactly (its true
m, l, I, M, motor and friction, its initial state, no noise, no latency): is there a
voltage sequence, one value per control period (zero-order hold, the plant's own input),
that brings the pendulum from its initial state into the catch region by ``catch_by_s``
and holds it there, within the robustness benchmark's rules (:class:`Limits`): the cart
inside the safe range at every sample, |u| within the bridge's voltage, |i| within the
current loop's limit at every sample, from ``hold_start_s`` |theta| and |x| within the
hold's bounds.

This module holds the problem: the rules (:class:`Limits`), the exactly known rig
(:class:`Rig`, :func:`exact_plant`, :func:`make_rig`), its simulation on the compiled
plant (:func:`rollout`) and the check of a voltage sequence against every rule
(:func:`check` for a batch, :func:`verify` re-simulated alone), with
:func:`clopper_pearson` for the study's rates. The searches for a witness are
:mod:`pisc_analysis.feasibility_search` (with :mod:`~pisc_analysis.feasibility_feedback`
and :mod:`~pisc_analysis.feasibility_shooting`), the necessary conditions that prove a
rig infeasible :mod:`pisc_analysis.feasibility_bound`.

The searches use the plant with ideal sensors, no sensor filters and an unquantised
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
from pisc_plant.plant import Plant
from pisc_plant.plant_config import PlantConfig

__all__ = ["Limits", "Rig", "Verdict", "cart_friction", "check", "clopper_pearson",
           "exact_plant", "make_rig", "pendulum_energy", "pivot_friction", "rollout", "samples",
           "verify", "wrap"]

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


def cart_friction(rig: Rig, x_dot: np.ndarray) -> np.ndarray:
    """The cart's friction force the motor must overcome (kernel: b_m/r^2, b_c, F_c)."""
    f = rig.config.friction
    m = rig.config.motor
    coulomb = (f.cart_coulomb_n * np.tanh(x_dot / f.coulomb_velocity_mps)
               if rig.config.models.friction == "coulomb" else 0.0)
    viscous = (f.cart_viscous_ns_per_m if rig.config.models.friction != "none" else 0.0)
    return (m.reflected_damping_ns_per_m + viscous) * x_dot + coulomb


def pivot_friction(rig: Rig) -> float:
    """The pivot's viscous friction b_p the model uses (0 without friction)."""
    return (rig.config.friction.pivot_viscous_nms
            if rig.config.models.friction != "none" else 0.0)



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


def clopper_pearson(successes: int, n: int, level: float = 0.95) -> tuple[float, float]:
    """Clopper-Pearson (exact) interval of a success probability."""
    from scipy.stats import beta

    if n < 1 or not 0 <= successes <= n:
        raise ValueError(f"{successes} successes of {n}: need 0 <= successes <= n, n >= 1")
    tail = (1.0 - level) / 2.0
    low = 0.0 if successes == 0 else float(beta.ppf(tail, successes, n - successes + 1))
    high = 1.0 if successes == n else float(beta.ppf(1.0 - tail, successes + 1, n - successes))
    return low, high
