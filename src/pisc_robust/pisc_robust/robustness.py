"""How often a configuration swings up and holds rigs it was not tuned on.

:func:`evaluate` draws plants, starts and latencies from a
:class:`~pisc_robust.uncertainty.Distribution`, runs each draw through the pure closed
loop (:func:`pisc_sim.closed_loop.simulate_batch`: the controllers' cores with the
configuration's nominal model, each plant with its own parameters, on the compiled
kernel) and scores it against :class:`Criteria`.

Draws are cut into chunks of :data:`CHUNK_DRAWS`; a chunk's measurement noise comes from
a generator seeded by (seed, chunk index). A chunk's result depends on nothing else,
so the same seed gives the same numbers whether the chunks run in this process, on a
local Dask cluster or on a remote one (:mod:`pisc_robust.cluster`).
"""

from __future__ import annotations

import math
import shlex
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from pisc_sim.closed_loop import simulate_batch
from pisc_sim.configuration import SECTIONS, GraphConfig
from pisc_robust.uncertainty import LATENCY, Distribution, Draws
from pisc_runs.verdict import Criteria, Outcomes, judge
from pisc_msgs_py.config import from_flat, to_flat
from pisc_model.params import InitialParams
from pisc_plant.plant_config import PlantConfig, plant_set

__all__ = ["CHUNK_DRAWS", "base_plant", "load_benchmark", "binomial_interval", "evaluate",
           "evaluate_chunk", "prepare", "rerun_command", "success_by_value",
           "witness_limits"]

CHUNK_DRAWS = 1000
INITIAL = ("initial.x_m", "initial.x_dot_mps", "initial.theta_rad", "initial.theta_dot_radps")


def _chunk_seed(seed: int, chunk: int) -> int:
    return int(np.random.SeedSequence([seed, chunk]).generate_state(1)[0])


def evaluate_chunk(config: GraphConfig, base_plant: PlantConfig, draws: Draws,
                   criteria: Criteria, noise_seed: int) -> Outcomes:
    """Simulate one chunk of draws (a pure function of its arguments)."""
    n = draws.n
    values = draws.values
    physical = {k: v for k, v in values.items() if k not in INITIAL and k != LATENCY}
    plant = plant_set(base_plant, physical) if physical else base_plant
    i0 = config.initial
    start = [values.get(name, np.full(n, float(getattr(i0, name.split(".")[1]))))
             for name in INITIAL]
    delay = values.get(LATENCY, 0.0)
    out = simulate_batch(config, start[0], criteria.run_s, criteria.hold_from_s,
                         delay, x_dot0_mps=start[1], theta0_rad=start[2],
                         theta_dot0_radps=start[3], plant=plant, noise_seed=noise_seed,
                         hold_box=(criteria.theta_rad, criteria.x_m))
    safety = config.supervisor.safety
    left = (out.x_min_m < safety.x_min_m) | (out.x_max_m > safety.x_max_m)
    safe, caught, fast = judge(criteria, out.faulted, left, out.caught_at_s, out.unheld_at_s)
    largest = np.maximum(np.abs(out.x_min_m), np.abs(out.x_max_m))
    return Outcomes(safe, caught, fast, out.caught_at_s, out.first_catch_s,
                    largest, out.unheld_at_s, out.hold_theta_rad, out.hold_x_m,
                    out.hold_setpoint_rms_a, out.faulted, left)


MapChunks = Callable[[Callable[..., Outcomes], Sequence[tuple[Any, ...]]], list[Outcomes]]


def run_here(fn: Callable[..., Outcomes], tasks: Sequence[tuple[Any, ...]]) -> list[Outcomes]:
    """The chunks one after another in this process (``cluster.chunk_runner(0)`` does the
    same with a progress bar)."""
    return [fn(*task) for task in tasks]


def evaluate(config: GraphConfig, base_plant: PlantConfig, draws: Draws,
             criteria: Criteria = Criteria(), seed: int = 0,
             map_chunks: MapChunks | None = None) -> Outcomes:
    """Every draw, in chunks of :data:`CHUNK_DRAWS`; ``map_chunks(fn, tasks)`` runs the
    chunks (default: one after another in this process) and returns their results in
    order (:func:`pisc_robust.cluster.chunk_runner`)."""
    size = CHUNK_DRAWS
    tasks = [(config, base_plant, draws[lo:lo + size], criteria, _chunk_seed(seed, c))
             for c, lo in enumerate(range(0, draws.n, size))]
    runner = map_chunks or run_here
    return Outcomes.concatenate(runner(evaluate_chunk, tasks))


def base_plant(config: GraphConfig, distribution: Distribution) -> PlantConfig:
    """The plant the draws vary: the configuration's (or its true plant) with the
    distribution's fixed overrides applied (``initial`` aside: see :func:`prepare`)."""
    plant = config.simulated_plant
    sections = {}
    for name in sorted({k.split(".", 1)[0] for k in distribution.plant} - {"initial"}):
        flat = {**to_flat(getattr(plant, name), name), **distribution.plant}
        sections[name] = from_flat(SECTIONS[name], flat, name)
    return replace(plant, **sections)


def prepare(config: GraphConfig, distribution: Distribution) -> tuple[GraphConfig, PlantConfig]:
    """What :func:`evaluate` takes for ``distribution``: the configuration with the
    distribution's fixed initial state (``plant: {initial: ...}``), and :func:`base_plant`."""
    if any(k.startswith("initial.") for k in distribution.plant):
        flat = {**to_flat(config.initial, "initial"), **distribution.plant}
        config = replace(config, initial=from_flat(InitialParams, flat, "initial"))
    return config, base_plant(config, distribution)


def load_benchmark(config_name: str, overrides: Sequence[str], distribution_name: str,
                   n: int, seed: int) -> tuple[GraphConfig, Distribution, Draws, PlantConfig]:
    """What a study over a distribution starts from (pisc_robustness, pisc_feasibility):
    the configuration ``config_name`` with ``overrides`` (``NAME=VALUE``), the
    distribution read against it, its ``n`` draws from ``seed``, and :func:`prepare`'s
    configuration and base plant. :class:`ConfigError` names what is wrong."""
    from pisc_robust.uncertainty import load_distribution
    from pisc_msgs_py.config import parse_overrides
    from pisc_sim.configuration import load_graph_config

    config, _ = load_graph_config(config_name, parse_overrides(list(overrides)))
    distribution = load_distribution(distribution_name, config)
    draws = distribution.draw(n, seed)
    config, plant = prepare(config, distribution)
    return config, distribution, draws, plant


def success_by_value(values: np.ndarray, success: np.ndarray, bins: int = 10,
                     log: bool = False, span: tuple[float, float] | None = None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(bin edges, success rate, draws) in ``bins`` equal bins (equal in log for ``log``)
    over ``span`` (default: the values' smallest to largest); the rate is NaN in an empty
    bin."""
    lo, hi = span if span is not None else (float(np.min(values)), float(np.max(values)))
    if hi <= lo:
        hi = lo + (abs(lo) or 1.0) * 1e-9
    edges = np.geomspace(lo, hi, bins + 1) if log else np.linspace(lo, hi, bins + 1)
    which = np.clip(np.searchsorted(edges, values, side="right") - 1, 0, bins - 1)
    count = np.bincount(which, minlength=bins)
    wins = np.bincount(which, weights=success.astype(float), minlength=bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        rate = np.where(count > 0, wins / np.maximum(count, 1), np.nan)
    return edges, rate, count


def binomial_interval(successes: int, n: int, level: float = 0.95) -> tuple[float, float]:
    """Clopper-Pearson (exact) interval of a success probability."""
    from scipy.stats import beta

    tail = (1.0 - level) / 2.0
    low = 0.0 if successes == 0 else float(beta.ppf(tail, successes, n - successes + 1))
    high = 1.0 if successes == n else float(beta.ppf(1.0 - tail, successes + 1, n - successes))
    return low, high


def rerun_command(config_name: str, overrides: Mapping[str, Any],
                  fixed: Mapping[str, Any], draw: Mapping[str, float]) -> str:
    """The ``./pisc run`` command that reruns one draw through the ROS graph."""
    args = ["./pisc", "run", "--config", config_name]
    for name, value in overrides.items():
        args += ["--set", f"{name}={_yaml_value(value)}"]
    for name, value in {**fixed, **draw}.items():
        args += ["--plant-set", f"{name}={_yaml_value(value)}"]
    return shlex.join(args)


def _yaml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, (list, tuple)):
        return "[" + ",".join(_yaml_value(v) for v in value) + "]"
    return str(value)


def witness_limits(config: Any, base: Any, current_limit: float | None = None,
                   catch_by_s: float = 3.0, hold_from_s: float = 6.0,
                   run_s: float = 10.0) -> Any:
    """A witness's limits: the actuator's and the track's, the catch region (4.1) of the
    configuration, the hold box of the benchmark (:class:`~pisc_runs.verdict.Criteria`)
    and the rules given. ``current_limit`` None: the configuration's; inf: none (the
    voltage alone). :class:`ValueError` for rules that make no sense."""
    from pisc_analysis.feasibility import Limits

    criteria = Criteria()
    sup = config.supervisor
    return Limits(
        voltage_v=min(config.current_loop.voltage_limit_v, base.actuator.full_scale_v),
        current_a=(config.current_loop.current_limit_a if current_limit is None
                   else None if math.isinf(current_limit) else current_limit),
        x_min_m=sup.safety.x_min_m, x_max_m=sup.safety.x_max_m,
        catch_by_s=catch_by_s, duration_s=run_s, hold_start_s=hold_from_s,
        hold_theta_rad=criteria.theta_rad, hold_x_m=criteria.x_m, k_va=sup.switching.k_va,
        delta_s=sup.switching.delta_s)
