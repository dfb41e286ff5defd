"""The whole graph's typed configuration, read from one ROS 2 parameter file.

Each node reads its own sections of the same file; this module reads them all at once
for the pure closed-loop simulation, the summary and the tests, through the same
:func:`pisc_msgs_py.config.from_flat` the nodes use, so both agree on every value.
"""

from __future__ import annotations

import sys
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from pisc_control.catch import CatchParams
from pisc_control.current_loop import CurrentLoopParams
from pisc_control.estimator import EstimatorParams
from pisc_control.supervisor import (
    SafetyParams,
    StartupParams,
    SupervisorConfig,
    SwitchingParams,
)
from pisc_control.swing_up import SwingUpParams
from pisc_msgs_py.config import ConfigError, from_flat, load_params_file
from pisc_plant.params import (
    ActuatorParams,
    FrictionParams,
    InitialParams,
    LoopParams,
    ModelParams,
    MotorParams,
    NoiseParams,
    RigParams,
    SensorParams,
    TrackParams,
)
from pisc_plant.plant import IntegratorParams, PlantConfig

__all__ = ["CONFIG_DIR", "GraphConfig", "config_path", "load_graph_config", "params_file_text",
           "write_params_file"]

def _config_dir() -> Path:
    """Parameter files: the source tree, else the installed share directory."""
    source = Path(__file__).resolve().parent.parent / "config"
    if source.is_dir():
        return source  # a checkout, or an editable install
    try:
        from ament_index_python.packages import PackageNotFoundError, get_package_share_directory
        try:
            return Path(get_package_share_directory("pisc_bringup")) / "config"
        except PackageNotFoundError:
            pass
    except ImportError:
        pass
    return Path(sys.prefix) / "share" / "pisc_bringup" / "config"  # pip install


CONFIG_DIR = _config_dir()

SECTIONS: dict[str, type] = {
    "rig": RigParams, "motor": MotorParams, "sensors": SensorParams,
    "actuator": ActuatorParams, "track": TrackParams, "loop": LoopParams,
    "integrator": IntegratorParams, "models": ModelParams, "friction": FrictionParams,
    "noise": NoiseParams, "initial": InitialParams, "estimator": EstimatorParams,
    "swing_up": SwingUpParams, "catch": CatchParams, "switching": SwitchingParams,
    "startup": StartupParams, "safety": SafetyParams, "current_loop": CurrentLoopParams,
}


@dataclass(frozen=True)
class GraphConfig:
    plant: PlantConfig
    initial: InitialParams
    estimator: EstimatorParams
    supervisor: SupervisorConfig
    current_loop: CurrentLoopParams

    @property
    def loop(self) -> LoopParams:
        return self.plant.loop


def config_path(name_or_path: str) -> Path:
    """A configuration by name (``default``, ``thesis``) or a path to a parameter file."""
    candidate = CONFIG_DIR / f"{name_or_path}.yaml"
    if candidate.exists():
        return candidate
    path = Path(name_or_path)
    if path.exists():
        return path
    known = ", ".join(sorted(p.stem for p in CONFIG_DIR.glob("*.yaml")))
    raise ConfigError(f"{name_or_path}: no such configuration (named ones: {known}) or file")


def load_graph_config(
    name_or_path: str, overrides: Mapping[str, Any] | None = None
) -> tuple[GraphConfig, dict[str, Any]]:
    """Typed configuration and the flat parameters (file values plus ``overrides``)."""
    flat = load_params_file(config_path(name_or_path))
    flat.update(overrides or {})
    unknown = sorted(k for k in flat if k.split(".", 1)[0] not in SECTIONS)
    if unknown:
        raise ConfigError(f"{unknown[0]}: unknown parameter section "
                          f"(known: {', '.join(SECTIONS)})")
    s = {name: from_flat(cls, flat, name) for name, cls in SECTIONS.items()}
    config = GraphConfig(
        plant=PlantConfig(rig=s["rig"], motor=s["motor"], sensors=s["sensors"],
                          actuator=s["actuator"], track=s["track"], loop=s["loop"],
                          integrator=s["integrator"], models=s["models"],
                          friction=s["friction"], noise=s["noise"]),
        initial=s["initial"],
        estimator=s["estimator"],
        supervisor=SupervisorConfig(rig=s["rig"], swing_up=s["swing_up"], catch=s["catch"],
                                    switching=s["switching"], startup=s["startup"],
                                    safety=s["safety"]),
        current_loop=s["current_loop"],
    )
    return config, flat


def params_file_text(flat: Mapping[str, Any]) -> str:
    """Flat parameters as a ROS 2 parameter file every node reads (``/**``)."""
    tree: dict[str, Any] = {}
    for name, value in flat.items():
        node = tree
        *parents, leaf = name.split(".")
        for parent in parents:
            node = node.setdefault(parent, {})
        node[leaf] = list(value) if isinstance(value, tuple) else value
    return yaml.safe_dump({"/**": {"ros__parameters": tree}}, sort_keys=False)


def write_params_file(path: Path, flat: Mapping[str, Any]) -> None:
    path.write_text(params_file_text(flat))
