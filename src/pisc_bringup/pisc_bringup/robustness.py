"""How often a configuration swings up and holds rigs it was not tuned on.

:func:`evaluate` draws plants, starts and latencies from a
:class:`~pisc_bringup.uncertainty.Distribution`, runs each draw through the pure closed
loop (:func:`pisc_sim.closed_loop.simulate_batch`: the controllers' cores with the
configuration's nominal model, each plant with its own parameters, on the compiled
kernel) and scores it against :class:`Criteria`.

Draws are cut into chunks of :data:`CHUNK_DRAWS`; a chunk's measurement noise comes from
a generator seeded by (seed, chunk index). A chunk's result depends on nothing else,
so the same seed gives the same numbers whether the chunks run in this process, on a
local Dask cluster or on a remote one (:mod:`pisc_bringup.cluster`).
"""

from __future__ import annotations

import math
import shlex
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from pisc_sim.closed_loop import simulate_batch
from pisc_sim.configuration import SECTIONS, GraphConfig
from pisc_bringup.uncertainty import LATENCY, Distribution, Draws
from pisc_msgs_py.config import from_flat, to_flat
from pisc_model.params import InitialParams
from pisc_plant.plant_config import PlantConfig, plant_set

__all__ = ["CHUNK_DRAWS", "FAILURES", "TIERS", "Criteria", "Outcomes", "base_plant", "load_benchmark",
           "binomial_interval", "evaluate", "evaluate_chunk", "judge", "prepare", "rerun_command",
           "success_by_value"]

CHUNK_DRAWS = 1000
#: The benchmark's tiers, each within the one before it: a fast draw is caught, a caught
#: draw is safe.
TIERS = ("safe", "caught", "fast")
#: The kinds of failure, in the order :meth:`Outcomes.kinds` checks them. The first two
#: fail every tier; the others fail "caught" or "fast" by that tier's deadline and window.
FAILURES = ("cart left the safe range", "fault", "never caught", "caught, then lost",
            "caught for good too late", "not held")
INITIAL = ("initial.x_m", "initial.x_dot_mps", "initial.theta_rad", "initial.theta_dot_radps")


@dataclass(frozen=True)
class Criteria:
    """The benchmark's three tiers, judged on each draw's true state over a run of
    ``run_s``:

    * **safe**: the cart inside the safe range at every sample and no fault, over the
      whole run (on the rig, the cart never meets an end stop);
    * **caught**: safe, caught for good (in the catch that lasts to the end of the run)
      by ``catch_by_s``, and held, |theta| < ``theta_rad`` and |x| < ``x_m`` at every
      sample from ``hold_from_s`` to the end;
    * **fast**: the same with ``fast_by_s`` and ``fast_hold_from_s``.

    Each argument that makes no sense is refused with a :class:`ValueError` naming it
    (with its command-line option).
    """

    run_s: float = 12.0
    catch_by_s: float = 8.0
    hold_from_s: float = 9.0
    fast_by_s: float = 3.0
    fast_hold_from_s: float = 6.0
    theta_rad: float = 0.05
    x_m: float = 0.02

    def __post_init__(self) -> None:
        names = {"run_s": "--run-s", "catch_by_s": "--catch-by", "hold_from_s": "--hold-from",
                 "fast_by_s": "--fast-by", "fast_hold_from_s": "--fast-hold-from",
                 "theta_rad": "the hold's |theta|", "x_m": "the hold's |x|"}
        for name, option in names.items():
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                shown = f"{value:g}" if isinstance(value, float) else value
                raise ValueError(f"{option} {shown}: a positive number of "
                                 f"{'s' if name.endswith('_s') else 'rad' if 'theta' in name else 'm'}")
        for by, hold, tier in (("catch_by_s", "hold_from_s", "caught"),
                               ("fast_by_s", "fast_hold_from_s", "fast")):
            deadline, window = getattr(self, by), getattr(self, hold)
            if deadline > self.run_s:
                raise ValueError(f"{names[by]} {deadline:g} s is past {names['run_s']} "
                                 f"{self.run_s:g} s: the {tier} tier's catch could never "
                                 "be seen")
            if not window < self.run_s:
                raise ValueError(f"{names[hold]} {window:g} s is not inside the run "
                                 f"({names['run_s']} {self.run_s:g} s): the {tier} tier's "
                                 "hold window would be empty")
            if window < deadline:
                raise ValueError(f"{names[hold]} {window:g} s is before {names[by]} "
                                 f"{deadline:g} s: the {tier} tier would ask for a hold "
                                 "before its catch")
        if self.fast_by_s > self.catch_by_s or self.fast_hold_from_s > self.hold_from_s:
            raise ValueError(f"the fast tier ({names['fast_by_s']} {self.fast_by_s:g} s, "
                             f"{names['fast_hold_from_s']} {self.fast_hold_from_s:g} s) must "
                             f"be within the caught tier ({names['catch_by_s']} "
                             f"{self.catch_by_s:g} s, {names['hold_from_s']} "
                             f"{self.hold_from_s:g} s)")

    def rule(self, tier: str) -> tuple[float, float]:
        """(catch deadline, start of the hold window) of the tier "caught" or "fast"."""
        if tier == "caught":
            return self.catch_by_s, self.hold_from_s
        if tier == "fast":
            return self.fast_by_s, self.fast_hold_from_s
        raise ValueError(f"tier {tier!r}: 'caught' or 'fast'")

    def describe(self) -> list[str]:
        """The tiers' rules in words, a line each."""
        box = f"|theta| < {self.theta_rad:g} rad and |x| < {self.x_m:g} m"
        return [f"safe: inside the safe range at every sample, no fault, for the whole "
                f"{self.run_s:g} s run"]+ [
                f"{tier}: safe, caught for good by {by:g} s, held ({box}) from {hold:g} s "
                f"to {self.run_s:g} s" for tier, (by, hold) in
                (("caught", self.rule("caught")), ("fast", self.rule("fast")))]


@dataclass(frozen=True)
class Outcomes:
    """Per-draw results, in draw order; the tiers' verdicts as the criteria judged them."""

    safe: np.ndarray
    caught: np.ndarray
    fast: np.ndarray
    caught_at_s: np.ndarray  # start of the catch that lasts; inf if none
    first_catch_s: np.ndarray
    largest_x_m: np.ndarray  # largest |x| over the run (true state)
    unheld_at_s: np.ndarray  # the last sample outside the hold box; -inf if none
    hold_theta_rad: np.ndarray  # largest |theta| from the caught tier's hold window on
    hold_x_m: np.ndarray
    hold_setpoint_rms_a: np.ndarray
    faulted: np.ndarray
    left_range: np.ndarray  # the true cart position left the safe range

    @staticmethod
    def concatenate(parts: Sequence[Outcomes]) -> Outcomes:
        return Outcomes(*(np.concatenate([getattr(p, f) for p in parts])
                          for f in Outcomes.__dataclass_fields__))

    def __len__(self) -> int:
        return len(self.safe)

    def passed(self, tier: str) -> np.ndarray:
        """The draws that pass ``tier`` (one of :data:`TIERS`)."""
        if tier not in TIERS:
            raise ValueError(f"tier {tier!r}: one of {', '.join(TIERS)}")
        return getattr(self, tier)

    def rates(self) -> dict[str, float]:
        """Each tier's fraction of the draws."""
        return {tier: float(np.mean(self.passed(tier))) for tier in TIERS}

    def score(self, penalty: float = 0.0, safe_target: float = 1.0) -> float:
        """One number that orders configurations safe first: one more safe draw outweighs
        any number of catches, up to ``safe_target`` of the draws (beyond it, safety is
        met and the catches decide); then each caught draw counts one and each fast draw
        one more (a fast draw is caught), less ``penalty`` counted in the same draws. At
        most 1, when every draw is fast and there is no penalty."""
        n = len(self)
        safe, caught, fast = (int(np.sum(self.passed(t))) for t in TIERS)
        enough = math.ceil(safe_target * n - 1e-9)
        weight = 2.0 * n + 1.0
        return (min(safe, enough) * weight + caught + fast - penalty) / (
            enough * weight + 2.0 * n)

    def kinds(self, criteria: Criteria, tier: str = "fast") -> np.ndarray:
        """Each draw's failure of ``tier`` as an index into :data:`FAILURES`; -1 where it
        passes. A draw that both faulted and was never caught counts as a fault."""
        never = ~np.isfinite(self.caught_at_s)
        if tier == "safe":
            return np.select([self.safe, self.left_range], [-1, 0], 1)
        by, hold = criteria.rule(tier)
        return np.select(
            [self.passed(tier), self.left_range, self.faulted,
             never & ~np.isfinite(self.first_catch_s), never, self.caught_at_s > by],
            [-1, 0, 1, 2, 3, 4], 5)

    def why(self, k: int, criteria: Criteria, tier: str = "fast") -> str:
        """In words, why draw ``k`` failed ``tier`` (empty where it passed)."""
        kind = int(self.kinds(criteria, tier)[k])
        if kind < 0:
            return ""
        if kind == 0:
            return f"cart left the safe range (|x| up to {self.largest_x_m[k]:.3f} m)"
        if kind == 3:
            return f"caught at {self.first_catch_s[k]:.2f} s, lost"
        if kind == 4:
            return f"caught for good only at {self.caught_at_s[k]:.2f} s"
        if kind == 5:
            return f"not held: outside the hold box until {self.unheld_at_s[k]:.2f} s"
        return FAILURES[kind]

    def badness(self, criteria: Criteria, tier: str = "fast") -> np.ndarray:
        """A ranking of ``tier``'s failures, worst first when sorted in descending order;
        0 where the draw passes."""
        never = ~np.isfinite(self.caught_at_s)
        if tier == "safe":
            return (~self.safe) * (1.0 + self.largest_x_m)
        by, hold = criteria.rule(tier)
        late = np.where(never, 0.0, np.maximum(self.caught_at_s - by, 0.0))
        unheld = np.where(never, 0.0, np.maximum(self.unheld_at_s - hold, 0.0))
        return (~self.passed(tier)) * (4.0 * (self.faulted | self.left_range) + 2.0 * never
                                       + np.minimum(late, 1.0) + np.minimum(unheld, 1.0))


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


def judge(criteria: Criteria, faulted: np.ndarray, left_range: np.ndarray,
          caught_at_s: np.ndarray, unheld_at_s: np.ndarray
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The tiers' verdicts (safe, caught, fast) of runs, each by :class:`Criteria`'s rule:
    safe, no fault and never outside the safe range; caught and fast, safe, caught for good
    (``caught_at_s``, inf if never) by the tier's deadline and no sample outside the hold
    box (the last at ``unheld_at_s``, -inf if none) from its hold window on. The one rule
    of the benchmark, the graph's run summary and the commissioning's report."""
    safe = ~np.asarray(faulted, dtype=bool) & ~np.asarray(left_range, dtype=bool)

    def tier(name: str) -> np.ndarray:
        by, hold = criteria.rule(name)
        return safe & (np.asarray(caught_at_s) <= by) & (np.asarray(unheld_at_s) < hold)

    return safe, tier("caught"), tier("fast")


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
    order (:func:`pisc_bringup.cluster.chunk_runner`)."""
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
    from pisc_bringup.uncertainty import load_distribution
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
