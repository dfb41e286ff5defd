"""Scenes: what one simulation needs, in one YAML file.

A scene names a configuration (``default``, ``thesis`` or a parameter file) and
overrides any of its parameters, including the plant's sub-models (``models``), its
friction and measurement noise, the integrator and the initial state; it also says how
long to run, whether the controllers close the loop and what ``pisc_graph`` records::

    scene:
      description: the ideal force-driven cart-pole
      configuration: default
      duration_s: 10.0
      controller: graph           # 'graph': estimator, supervisor, current loop; 'none': zero input
      parameters:                 # sections as in a ROS 2 parameter file
        models: {armature: ideal_force, current_loop: ideal, sensors: ideal,
                 sensor_filters: false}
        initial: {x_m: 0.05}
      plant:                      # optional, model error: the plant only (sections it reads)
        motor: {resistance_ohm: 18.2}
      record: [/pisc/state]       # optional: besides the run's own topics; default: all

Scenes ship in ``pisc_sim/scenes``; :func:`load_scene` takes a name or a path. The
scene's flat parameters are what the controllers get, and :func:`write_scene_params`
writes them as a ROS 2 parameter file for ``ros2 run``. The ``plant:`` block goes on top
of them for the plant (simulator or virtual rig) alone, after ``parameters``
(:func:`pisc_sim.configuration.load_run_config`): ``scene.config.true_plant`` is then
the plant that is simulated, ``scene.plant_flat`` its parameters
(``write_scene_params(scene, path, plant=True)``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pisc_sim.configuration import (
    CONFIG_DIR,
    PLANT_READS,
    GraphConfig,
    load_run_config,
    plant_only,
    write_params_file,
)
from pisc_control.supervisor import Supervisor
from pisc_msgs_py.config import ConfigError, find_file, flatten, load_keyed_yaml
from pisc_msgs_py.topics import graph_topics_named

__all__ = ["DEFAULT_SCENE", "SCENE_DIR", "Scene", "load_scene", "scene_names", "scene_path"]

SCENE_DIR = CONFIG_DIR.parent / "scenes"  # share/pisc_sim/scenes beside config/
DEFAULT_SCENE = "thesis-rig"
CONTROLLERS = ("graph", "none")
KEYS = ("description", "configuration", "duration_s", "controller", "parameters", "plant",
        "record")


@dataclass(frozen=True)
class Scene:
    name: str
    description: str
    configuration: str
    duration_s: float
    controller: str
    overrides: dict[str, Any]  # flat parameter overrides of the configuration
    config: GraphConfig
    flat: dict[str, Any]  # the configuration's flat parameters with the overrides
    # topics pisc_graph records besides the run's own (pisc_bringup.launch_graph.RUN_TOPICS);
    # None: every topic
    record: tuple[str, ...] | None = None
    # model error: flat overrides of the plant only (the plant: block), applied after
    # ``overrides``; and the plant's flat parameters (``flat`` without model error)
    plant_overrides: dict[str, Any] = field(default_factory=dict)
    plant_flat: dict[str, Any] = field(default_factory=dict)

    @property
    def closed_loop(self) -> bool:
        return self.controller == "graph"


def scene_names() -> list[str]:
    return sorted(p.stem for p in SCENE_DIR.glob("*.yaml"))


def scene_path(name_or_path: str) -> Path:
    return find_file(name_or_path, SCENE_DIR, "scene", scene_names, (".yaml", ".yml"))


def load_scene(name_or_path: str, overrides: Mapping[str, Any] | None = None,
               plant_overrides: Mapping[str, Any] | None = None) -> Scene:
    """Read and check a scene; ``overrides`` (flat names) go on top of the scene's own
    parameters, ``plant_overrides`` on top of its ``plant:`` block.

    Raises :class:`ConfigError` naming the file and the offending key or parameter.
    """
    path = scene_path(name_or_path)
    body = load_keyed_yaml(path, "scene", KEYS, "scene")
    configuration = str(body.get("configuration", "default"))
    duration = body.get("duration_s", 10.0)
    if isinstance(duration, bool) or not isinstance(duration, (int, float)) or not (
            math.isfinite(duration) and duration > 0):
        raise ConfigError(f"{path}: scene.duration_s = {duration!r} must be a positive number")
    controller = body.get("controller", "graph")
    if controller not in CONTROLLERS:
        raise ConfigError(f"{path}: scene.controller = {controller!r} must be one of "
                          f"{', '.join(CONTROLLERS)}")
    record = body.get("record")
    if record is not None:
        if not isinstance(record, list) or not all(isinstance(t, str) for t in record):
            raise ConfigError(f"{path}: scene.record must be a list of topic names")
        try:
            graph_topics_named(record)
        except ConfigError as exc:
            raise ConfigError(f"{path}: scene.record: {exc}") from None
        record = tuple(record)
    parameters = body.get("parameters") or {}
    if not isinstance(parameters, Mapping):
        raise ConfigError(f"{path}: scene.parameters must be a mapping of sections")
    flat_overrides = flatten(parameters)
    flat_overrides.update(overrides or {})
    plant = body.get("plant") or {}
    if not isinstance(plant, Mapping):
        raise ConfigError(f"{path}: scene.plant must be a mapping of sections (the plant's "
                          "parameters, as in a parameter file)")
    plant_flat_overrides = flatten(plant)
    for name in plant_flat_overrides:
        section = name.split(".", 1)[0]
        if section not in PLANT_READS:
            raise ConfigError(
                f"{path}: scene.plant.{name}: the plant does not read section '{section}' "
                f"(it reads {', '.join(PLANT_READS)}); the controllers' parameters go "
                "under scene.parameters")
    plant_flat_overrides.update(plant_overrides or {})
    try:
        config, flat, plant_flat = load_run_config(configuration, flat_overrides,
                                                   plant_overrides=plant_flat_overrides)
        Supervisor(config.supervisor)  # refuses (3.29) and an uncontrollable linearisation
    except ConfigError as exc:
        raise ConfigError(f"scene {path.stem}: {exc}") from exc
    return Scene(path.stem, str(body.get("description", "")), configuration, float(duration),
                 controller, flat_overrides, config, flat, record, plant_flat_overrides,
                 plant_flat)


def write_scene_params(scene: Scene, path: Path, plant: bool = False) -> None:
    """The scene as a ROS 2 parameter file: the one the controllers read, or with
    ``plant`` the plant's (its ``plant:`` block on top, the sections the plant reads
    only)."""
    write_params_file(path, plant_only(scene.plant_flat) if plant else scene.flat)
