"""The whole graph's typed configuration, read from one ROS 2 parameter file.

Each node reads its own sections of the same file; this module reads them all at once
for the pure closed-loop simulation, the summary and the tests, through the same
:func:`pisc_msgs_py.config.from_flat` the nodes use, so both agree on every value.

**Model error.** The plant (simulator or virtual rig) may run with other physical
parameters than the controllers assume: a parameter file of its own (``plant``) and
overrides of its own (``plant_overrides``, only in the sections the plant reads,
:data:`PLANT_READS`). The controllers keep theirs. :attr:`GraphConfig.true_plant` then
holds the plant that is simulated, and :attr:`GraphConfig.plant` stays the model the
controllers were designed on; ``initial`` is the plant's.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import yaml

from pisc_control.catch import CatchParams
from pisc_control.adaptation import AdaptationParams
from pisc_control.current_loop import CurrentLoopParams
from pisc_control.estimator import EstimatorParams
from pisc_control.excitation import ExperimentParams
from pisc_control.supervisor import (
    SafetyParams,
    StartupParams,
    SupervisorConfig,
    SwitchingParams,
)
from pisc_control.swing_up import SwingUpParams
from pisc_msgs_py.config import ConfigError, find_file, from_flat, load_params_file, package_dir
from pisc_model.params import InitialParams, LoopParams, check_models_use
from pisc_plant.plant_config import PLANT_SECTIONS, PlantConfig

__all__ = ["CONFIG_DIR", "PLANT_READS", "GraphConfig", "check_plant_overrides", "config_path",
           "load_graph_config", "load_run_config", "params_file_text", "plant_only",
           "write_params_file"]

CONFIG_DIR = package_dir("pisc_sim", "config")  # the named configurations

SECTIONS: dict[str, type] = {
    **PLANT_SECTIONS, "initial": InitialParams, "estimator": EstimatorParams,
    "swing_up": SwingUpParams, "catch": CatchParams, "switching": SwitchingParams,
    "startup": StartupParams, "safety": SafetyParams, "current_loop": CurrentLoopParams,
    "experiment": ExperimentParams, "adaptation": AdaptationParams,
}


#: The sections the plant (simulator, virtual rig) reads: the only ones a plant override
#: may set.
PLANT_READS = ("rig", "motor", "sensors", "actuator", "track", "loop", "integrator", "models",
               "friction", "noise", "initial")


@dataclass(frozen=True)
class GraphConfig:
    plant: PlantConfig  # the model the controllers assume (and the plant, without model error)
    initial: InitialParams
    estimator: EstimatorParams
    supervisor: SupervisorConfig
    current_loop: CurrentLoopParams
    # the plant that is simulated when it differs from the model (model error)
    true_plant: PlantConfig | None = None

    @property
    def loop(self) -> LoopParams:
        return self.plant.loop

    @property
    def simulated_plant(self) -> PlantConfig:
        """The plant a simulation runs: :attr:`true_plant`, else the model."""
        return self.plant if self.true_plant is None else self.true_plant


def config_path(name_or_path: str) -> Path:
    """A configuration by name (``default``, ``thesis``) or a path to a parameter file."""
    return find_file(name_or_path, CONFIG_DIR, "configuration",
                     lambda: sorted(p.stem for p in CONFIG_DIR.glob("*.yaml")))


def _sections(flat: Mapping[str, Any]) -> dict[str, Any]:
    unknown = sorted(k for k in flat if k.split(".", 1)[0] not in SECTIONS)
    if unknown:
        raise ConfigError(f"{unknown[0]}: unknown parameter section "
                          f"(known: {', '.join(SECTIONS)})")
    sections = {name: from_flat(cls, flat, name) for name, cls in SECTIONS.items()}
    # a value the selected sub-models leave out is refused, not silently ignored
    check_models_use(dict(flat))
    return sections


def _plant_config(s: Mapping[str, Any]) -> PlantConfig:
    return PlantConfig(rig=s["rig"], motor=s["motor"], sensors=s["sensors"],
                       actuator=s["actuator"], track=s["track"], loop=s["loop"],
                       integrator=s["integrator"], models=s["models"], friction=s["friction"],
                       noise=s["noise"])


def check_plant_overrides(overrides: Mapping[str, Any], what: str = "--plant-set") -> None:
    """Refuse a plant override in a section the plant does not read, naming it."""
    for name in overrides:
        section = name.split(".", 1)[0]
        if section not in PLANT_READS:
            raise ConfigError(
                f"{what} {name}: the plant does not read section '{section}' (it reads "
                f"{', '.join(PLANT_READS)}); the controllers' parameters are set with --set")


def load_graph_config(
    name_or_path: str, overrides: Mapping[str, Any] | None = None
) -> tuple[GraphConfig, dict[str, Any]]:
    """Typed configuration and the flat parameters (file values plus ``overrides``)."""
    flat = load_params_file(config_path(name_or_path))
    flat.update(overrides or {})
    s = _sections(flat)
    config = GraphConfig(
        plant=_plant_config(s),
        initial=s["initial"],
        estimator=s["estimator"],
        supervisor=SupervisorConfig(rig=s["rig"], swing_up=s["swing_up"], catch=s["catch"],
                                    switching=s["switching"], startup=s["startup"],
                                    safety=s["safety"], loop=s["loop"],
                                    experiment=s["experiment"], motor=s["motor"],
                                    adaptation=s["adaptation"], estimator=s["estimator"],
                                    sensors=s["sensors"]),
        current_loop=s["current_loop"],
    )
    return config, flat


def load_run_config(
    name_or_path: str,
    overrides: Mapping[str, Any] | None = None,
    plant: str | None = None,
    plant_overrides: Mapping[str, Any] | None = None,
) -> tuple[GraphConfig, dict[str, Any], dict[str, Any]]:
    """A run's configuration with model error: (config, controllers' flat, plant's flat).

    The controllers read ``name_or_path`` with ``overrides``. The plant reads ``plant``
    (a configuration name or parameter file; default: the controllers' file) with the
    same ``overrides`` and then ``plant_overrides``, which may only set the sections the
    plant reads. Without ``plant`` and ``plant_overrides`` both flats are the same and
    :attr:`GraphConfig.true_plant` is None. Raises :class:`ConfigError` naming the
    parameter; the plant and the controllers must share the sample period.
    """
    config, flat = load_graph_config(name_or_path, overrides)
    if plant is None and not plant_overrides:
        return config, flat, dict(flat)
    check_plant_overrides(plant_overrides or {})
    plant_flat = load_params_file(config_path(plant)) if plant is not None else dict(flat)
    plant_flat.update(overrides or {})
    plant_flat.update(plant_overrides or {})
    what = f"plant ({plant})" if plant is not None else "plant"
    try:
        s = _sections(plant_flat)
    except ConfigError as exc:
        raise ConfigError(f"{what}: {exc}") from None
    true_plant = _plant_config(s)
    if true_plant.loop.period_s != config.loop.period_s:
        raise ConfigError(
            f"{what}: loop.period_s = {true_plant.loop.period_s} differs from the "
            f"controllers' {config.loop.period_s}: the plant is sampled at the control period")
    config = replace(config, initial=s["initial"], true_plant=true_plant)
    return config, flat, plant_flat


def plant_only(flat: Mapping[str, Any]) -> dict[str, Any]:
    """The parameters of the sections the plant reads (:data:`PLANT_READS`): what a file
    written for the plant alone holds."""
    return {k: v for k, v in flat.items() if k.split(".", 1)[0] in PLANT_READS}


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
