"""The two files a calibration writes: the posterior as a distribution file, and the
calibrated nominal plant as a plant parameter file (``--plant-config``).

The distribution keeps the accepted rigs together (its ``joint`` block: each draw takes
one accepted rig with all its values, so what the experiment says about combinations of
parameters is kept) and the prior's uneven starts (its independent ``initial.*`` ranges):
``pisc_robustness`` and ``pisc_tune`` take it as they take ``thesis-rig``. The cart's start
of the experiment is not a property of the rig and is left out.

The nominal plant is one accepted rig, at the experiment's start, with a noise seed for
which the one-rig closed loop (:func:`pisc_sim.closed_loop.simulate`, which a lockstep
graph reproduces bit for bit) reproduces the experiment.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml

from pisc_robust.calibrate import X0, experiment_config
from pisc_robust.experiment import judge, measure, traces_from_log
from pisc_robust.uncertainty import Distribution
from pisc_sim.configuration import PLANT_READS, GraphConfig, load_run_config, params_file_text

if TYPE_CHECKING:
    from pisc_robust.calibrate import Calibration

__all__ = ["reproduces", "write_distribution", "write_plant"]

#: noise seeds tried, from 0, for the nominal plant's single run
SEEDS_TRIED = 32


def _nested(flat: Mapping[str, Any]) -> dict[str, Any]:
    tree: dict[str, Any] = {}
    for name, value in flat.items():
        section, _, leaf = name.partition(".")
        tree.setdefault(section, {})[leaf] = value
    return tree


def _provenance(result: Calibration) -> str:
    epsilons = ",".join(f"{g.epsilon:g}" for g in result.generations)
    return (f"# Written by pisc_calibrate --experiment {result.experiment.name} "
            f"--distribution {result.prior.name} --particles {result.particles} "
            f"--epsilons {epsilons} --seed {result.seed}\n# (prior digest "
            f"{result.prior.digest}; {result.simulated} draws simulated; "
            "docs/thesis-experiment.md).\n")


def write_distribution(path: Path, result: Calibration, prior: Distribution) -> None:
    """The posterior's rigs resampled by weight (``joint``), the prior's starts and fixed
    plant overrides."""
    post = result.resampled(result.posterior.n)
    names = [n for n in post.values if n != X0]
    starts = {r.name: {r.kind: [float(r.low), float(r.high)]} for r in prior.ranges
              if r.name.startswith("initial.")}
    rows = [[float(f"{post.values[n][j]:.9g}") for n in names] for j in range(post.n)]
    body = {"distribution": {
        "description": f"the rigs of {prior.name} that reproduce {result.experiment.name} "
                       f"(SMC-ABC posterior, {post.n} rows), with {prior.name}'s starts",
        "plant": _nested(prior.plant),
        "parameters": starts,
        "joint": {"names": names, "rows": rows},
    }}
    text = yaml.safe_dump(body, sort_keys=False, default_flow_style=None, width=100)
    path.write_text(_provenance(result) + text)


def reproduces(config_name: str, plant_file: Path, result: Calibration) -> bool:
    """Whether the one-rig closed loop of ``config_name`` on ``plant_file`` meets the
    experiment."""
    from pisc_sim.closed_loop import simulate

    config, _, _ = load_run_config(config_name, plant=str(plant_file))
    log = simulate(config, result.experiment.duration_s)
    current = config.current_loop
    traces = traces_from_log(log, current.voltage_limit_v, current.current_limit_a,
                             config.loop.period_s)
    return bool(judge(result.experiment, measure(traces))[0])


def write_plant(path: Path, result: Calibration, index: int, flat: Mapping[str, Any],
                prior: Distribution, config: GraphConfig) -> tuple[int | None, int]:
    """Accepted draw ``index`` as a plant file at the experiment's start; returns the noise
    seed written (the first from 0 whose single run reproduces the experiment, None if
    none of :data:`SEEDS_TRIED` does) and the seeds tried."""
    post = result.posterior
    plant = {k: v for k, v in flat.items() if k.split(".", 1)[0] in PLANT_READS}
    plant.update(prior.plant)
    plant.update({n: float(f"{post.values[n][index]:.9g}") for n in post.values})
    start = experiment_config(config, result.experiment).initial
    plant.update({f"initial.{k}": float(getattr(start, k)) for k in
                  ("x_dot_mps", "theta_rad", "theta_dot_radps")})
    header = (_provenance(result)
              + f"# The calibrated nominal plant: particle {index} of the posterior, at "
              "the experiment's start.\n# ./pisc run --config "
              f"{result.experiment.configuration} --plant-config {path.stem} (shipped in "
              "src/pisc_sim/config/)\n")
    for seed in range(SEEDS_TRIED):
        plant["noise.seed"] = seed
        path.write_text(header + params_file_text(plant))
        if reproduces(result.experiment.configuration, path, result):
            return seed, seed + 1
    plant["noise.seed"] = 0
    path.write_text(header + params_file_text(plant))
    return None, SEEDS_TRIED
