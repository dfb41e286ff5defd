"""What an environment is: a scene, a task, an action, what is observed, the reward, and
the rigs it draws (domain randomisation), checked before anything runs.

:class:`Task` reads a scene by name or path (:func:`pisc_sim.scene.load_scene`: the
plant models only what the scene needs, as the graph's plant does) and, optionally, a
distribution file (:func:`pisc_robust.uncertainty.load_distribution`: ``thesis-rig`` or
a path) around the scene's configuration. :meth:`Task.draw` takes one rig from a
generator: its physical parameters, command latency and noise levels from the
distribution (the scene's own without one), its start, and the seed of its measurement
noise. Every value comes from the generator in a fixed order, so a rig drawn by a
single environment and the same rig drawn inside a vector environment from the same
seed are the same rig.

Tasks:

``swing_up``
    Start where the distribution's ``initial.*`` put it (hanging, by default at rest);
    the episode lasts ``episode_s`` (default 10 s).
``catch``
    The cart at rest in the middle of the safe range, the pendulum within
    ``start_angle_rad`` (default 0.3 rad) of upright, uniformly, as ``start`` says:

    - ``arriving`` (default): as the swing-up hands it to the catch, moving towards
      upright with the energy the swing-up (3.30) drives it to, E_p = 0 (upright at rest,
      (2.54)'s pendulum terms): theta_dot = -sign(theta) sqrt(2 m g l (1 - cos theta)
      / (I + m l^2)) with the drawn rig's own m, l, I and g;
    - ``rest``: at rest (theta_dot = 0), a push to recover from. On ``thesis-rig`` rigs
      a fifth to a quarter of these starts (more than half of those past 0.2 rad) cannot be
      caught by any input within the track and the actuator's limits (docs/gym.md,
      "What the catch task allows").

    The episode lasts ``episode_s`` (default 3 s) and also ends when the pendulum falls
    past ``fall_rad`` (default pi / 2) from upright.

Reward (every step, of the true state after it and the voltage commanded for it)::

    r = (1 + cos theta) / 2 - w_x (x - x_mid)^2 - w_u (u / u_max)^2

with theta from upright (SPEC section 1), x in metres, x_mid the middle of the
supervisor's safe range (-0.05 m on the thesis rig, whose track is uneven about the IR
sensor's zero), u the armature voltage and u_max the actuator's full scale (with an
ideal force source, i_d / i_max instead); ``w_x`` = 10 1/m^2 and ``w_u`` = 0.01 by
default. An
episode terminates when the true cart position leaves the supervisor's safe range
(``safety.x_min_m`` .. ``safety.x_max_m``) or the state is no longer finite.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pisc_msgs_py.config import ConfigError

__all__ = ["ACTIONS", "STARTS", "TASKS", "RigDraw", "RigDraws", "Task", "make_task"]

TASKS = ("swing_up", "catch")
STARTS = ("arriving", "rest")  # the catch's starts (module docstring)
ACTIONS = ("voltage", "current")
INITIAL = ("initial.x_m", "initial.x_dot_mps", "initial.theta_rad", "initial.theta_dot_radps")
LATENCY = "actuator.command_delay_s"
NOISE = ("noise.x_std_m", "noise.theta_std_rad", "noise.current_std_a")
NOISE_SEED_RANGE = 2**31  # noise.seed lies in [0, 2^31 - 1]
#: the sections of a plant set a rig's constants come from (noise has its own arrays)
PHYSICAL = ("rig", "motor", "friction")


@dataclass(frozen=True)
class RigDraw:
    """One rig: its varied physical parameters (plant-set names), latency, noise standard
    deviations, start (x, x_dot, theta, theta_dot) and noise seed."""

    physical: dict[str, float]
    latency_s: float
    noise_std: tuple[float, float, float]
    start: tuple[float, float, float, float]
    noise_seed: int

    def as_overrides(self) -> dict[str, Any]:
        """The rig as plant overrides (``--plant-set NAME=VALUE``) of the scene: what
        :func:`pisc_sim.configuration.load_run_config` needs to simulate the same rig."""
        out: dict[str, Any] = dict(self.physical)
        out[LATENCY] = self.latency_s
        out.update(zip(NOISE, self.noise_std))
        out.update(zip(INITIAL, self.start))
        out["noise.seed"] = self.noise_seed
        return out


@dataclass(frozen=True)
class RigDraws:
    """Rigs drawn together (:meth:`Task.draw_many`): the fields of :class:`RigDraw`, one
    row a rig."""

    physical: dict[str, np.ndarray]  # (m,) a name
    latency_s: np.ndarray  # (m,)
    noise_std: np.ndarray  # (m, 3)
    start: np.ndarray  # (m, 4)
    noise_seed: np.ndarray  # (m,) int64

    def __len__(self) -> int:
        return len(self.latency_s)

    def __getitem__(self, k: int) -> RigDraw:
        return RigDraw({name: float(v[k]) for name, v in self.physical.items()},
                       float(self.latency_s[k]),
                       tuple(float(v) for v in self.noise_std[k]),  # type: ignore[arg-type]
                       tuple(float(v) for v in self.start[k]),  # type: ignore[arg-type]
                       int(self.noise_seed[k]))

    def as_overrides(self) -> dict[str, np.ndarray]:
        """:meth:`RigDraw.as_overrides` of every rig: (m,) a name."""
        out: dict[str, np.ndarray] = dict(self.physical)
        out[LATENCY] = self.latency_s
        out.update(zip(NOISE, self.noise_std.T))
        out.update(zip(INITIAL, self.start.T))
        out["noise.seed"] = self.noise_seed
        return out


@dataclass(frozen=True)
class Task:
    """A checked environment description; :func:`make_task` builds it from keywords."""

    task: str
    scene: Any  # pisc_sim.scene.Scene
    config: Any  # pisc_sim.configuration.GraphConfig, with the distribution's fixed initial
    plant: Any  # pisc_plant.plant_config.PlantConfig: the base plant the draws vary
    distribution: Any | None  # pisc_robust.uncertainty.Distribution
    action: str
    velocities: bool
    episode_steps: int
    start_angle_rad: float
    fall_rad: float
    x_weight: float
    voltage_weight: float
    physical_names: tuple[str, ...] = field(default=())
    start: str = "arriving"

    @property
    def period_s(self) -> float:
        return self.config.loop.period_s

    @property
    def safe_range(self) -> tuple[float, float]:
        s = self.config.supervisor.safety
        return s.x_min_m, s.x_max_m

    @property
    def middle_m(self) -> float:
        """The middle of the safe range."""
        low, high = self.safe_range
        return 0.5 * (low + high)

    @property
    def voltage_limit_v(self) -> float:
        return self.plant.actuator.full_scale_v

    @property
    def current_limit_a(self) -> float:
        return self.config.current_loop.current_limit_a

    def draw(self, rng: np.random.Generator) -> RigDraw:
        """One rig from ``rng`` (:meth:`draw_many` of one generator)."""
        return self.draw_many([rng])[0]

    def draw_many(self, generators: Sequence[np.random.Generator]) -> RigDraws:
        """One rig from each generator: the distribution's uniform draws (one per varied
        parameter, in the file's sorted order, as
        :meth:`pisc_robust.uncertainty.Distribution.draw` orders them), then the
        catch's start angle, then the noise seed. The values are computed for all rigs
        at once, each from its own uniform draws, with the same numbers as one at a
        time (numpy's elementwise functions do not depend on the array's length)."""
        m = len(generators)
        ranges = self.distribution.ranges if self.distribution is not None else ()
        u = np.empty((m, len(ranges)))
        angle = np.zeros(m)
        seed = np.empty(m, dtype=np.int64)
        catch = self.task == "catch"
        for k, rng in enumerate(generators):
            if ranges:
                u[k] = rng.random(len(ranges))
            if catch:
                angle[k] = rng.uniform(-self.start_angle_rad, self.start_angle_rad)
            seed[k] = rng.integers(NOISE_SEED_RANGE)
        values = {r.name: np.asarray(r.sample(np.ascontiguousarray(u[:, j])), dtype=float)
                  for j, r in enumerate(ranges)}
        i0 = self.config.initial
        if catch:
            start = np.zeros((m, 4))
            start[:, 0] = self.middle_m
            start[:, 2] = angle
            if self.start == "arriving":
                start[:, 3] = self._arriving_rate(angle, values)
        else:
            nominal = (i0.x_m, i0.x_dot_mps, i0.theta_rad, i0.theta_dot_radps)
            start = np.column_stack([values.get(name, np.full(m, v))
                                     for name, v in zip(INITIAL, nominal)])
        noise = self.plant.noise
        std = np.column_stack([values.get(name, np.full(m, float(getattr(
            noise, name.split(".")[1])))) for name in NOISE])
        latency = values.get(LATENCY, np.full(m, self.plant.actuator.command_delay_s))
        physical = {name: values[name] for name in self.physical_names}
        return RigDraws(physical, latency, std, start, seed)

    def _arriving_rate(self, angle: np.ndarray, values: dict[str, np.ndarray]) -> np.ndarray:
        """theta_dot towards upright at pendulum energy E_p = 0 (2.54): 1/2 J theta_dot^2
        = m g l (1 - cos theta), J = I + m l^2, each rig's own drawn m, l, I."""
        base = self.plant.rig
        m, l, inertia = (values.get(f"rig.{name}", np.full(len(angle), getattr(base, name)))
                         for name in ("pendulum_mass_kg", "pendulum_com_m",
                                      "pendulum_inertia_kgm2"))
        mgl = m * base.gravity_mps2 * l
        return -np.sign(angle) * np.sqrt(2.0 * mgl * (1.0 - np.cos(angle))
                                         / (inertia + m * l * l))


def _number(name: str, value: Any, low: float, high: float, low_open: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(
            value) or value > high or value < low or (low_open and value == low):
        bound = "(" if low_open else "["
        raise ConfigError(f"{name} = {value!r}: must be a number in {bound}{low:g}, {high:g}]")
    return float(value)


def make_task(task: str, scene: str = "thesis-rig", distribution: str | None = None,
              action: str = "voltage", velocities: bool = False,
              episode_s: float | None = None, start_angle_rad: float = 0.3,
              fall_rad: float | None = None, x_weight: float = 10.0,
              voltage_weight: float = 0.01, start: str = "arriving") -> Task:
    """Check and load an environment's description; :class:`ConfigError` names the bad
    value (an unknown scene, distribution, task or action, a number out of range)."""
    from pisc_robust.robustness import prepare
    from pisc_robust.uncertainty import load_distribution
    from pisc_sim.scene import load_scene

    if task not in TASKS:
        raise ConfigError(f"task = {task!r}: unknown (known: {', '.join(TASKS)})")
    if action not in ACTIONS:
        raise ConfigError(f"action = {action!r}: unknown (known: {', '.join(ACTIONS)}: the "
                          "armature voltage, or the current set-point through PISC's PI "
                          "current loop)")
    if start not in STARTS:
        raise ConfigError(f"start = {start!r}: unknown (known: {', '.join(STARTS)}: the "
                          "catch's pendulum arriving as the swing-up hands it over, or at "
                          "rest)")
    if not isinstance(velocities, bool):
        raise ConfigError(f"velocities = {velocities!r}: must be true or false")
    if not isinstance(scene, str):
        raise ConfigError(f"scene = {scene!r}: a scene's name or path")
    loaded = load_scene(scene)
    if not loaded.closed_loop:
        raise ConfigError(f"scene {loaded.name} has no controller (controller: "
                          f"{loaded.controller}): its configuration is not one to learn on")
    config = loaded.config
    dist = None
    if distribution is not None:
        if not isinstance(distribution, str):
            raise ConfigError(f"distribution = {distribution!r}: a distribution's name or "
                              "path")
        dist = load_distribution(distribution, config)
    if dist is not None:
        config, plant = prepare(config, dist)
    else:
        plant = config.simulated_plant
    models = plant.models
    if models.sensors == "quantised" and not models.sensor_filters:
        raise ConfigError(f"scene {loaded.name}: quantised sensors without their RC filters "
                          "(models.sensor_filters: false) are not modelled by pisc_gym")
    if models.force_input and action == "voltage":
        raise ConfigError(f"action = 'voltage': scene {loaded.name}'s plant is an ideal force "
                          "source (models.armature = ideal_force), driven by the current "
                          "set-point: use action = 'current'")
    if not config.supervisor.experiment.kind == "none":
        raise ConfigError(f"scene {loaded.name}: an identification experiment "
                          f"(experiment.kind = {config.supervisor.experiment.kind})")
    default_s = 3.0 if task == "catch" else 10.0
    seconds = _number("episode_s", default_s if episode_s is None else episode_s, 0.0, 3600.0,
                      True)
    steps = max(1, int(round(seconds / config.loop.period_s)))
    angle = _number("start_angle_rad", start_angle_rad, 0.0, math.pi)
    fall = math.inf if task == "swing_up" and fall_rad is None else _number(
        "fall_rad", math.pi / 2 if fall_rad is None else fall_rad, 0.0, math.pi, True)
    physical = ()
    if dist is not None:
        physical = tuple(r.name for r in dist.ranges
                         if r.name.split(".")[0] in PHYSICAL)
    return Task(task, loaded, config, plant, dist, action, velocities, steps, angle, fall,
                _number("x_weight", x_weight, 0.0, 1e6),
                _number("voltage_weight", voltage_weight, 0.0, 1e6), physical, start)

