"""Which rigs of a distribution reproduce the thesis's experiment: rejection ABC on the
batch closed loop.

Approximate Bayesian computation by rejection (Pritchard et al. 1999; Beaumont 2010,
"Approximate Bayesian computation in evolution and ecology", Annu. Rev. Ecol. Evol. Syst.
41, eq. 2 with a uniform kernel): draw rigs from the prior (a distribution of what is not
known about the rig, ``thesis-rig``, with the experiment's start in place of its uneven
starts: hanging at rest, the cart anywhere in the experiment's range), simulate each
under the experiment's configuration with the sensors' noise and the command latency
drawn as on the rig, measure the experiment's events (:mod:`pisc_bringup.experiment`) and
keep the draws whose every event lies within its tolerance. The kept draws are samples of
the posterior: the prior restricted to the rigs (and noise) that reproduce the
experiment. The tolerances are the thesis's, so the posterior is exact for this kernel;
nothing is shrunk further.

Each chunk of :data:`CHUNK_DRAWS` draws is a pure function of its draws and its noise
seed (seeded by (seed, chunk index), as :mod:`pisc_bringup.robustness`), so the same seed
gives the same posterior in this process or on a Dask cluster
(:mod:`pisc_bringup.cluster`). A chunk runs in two stages: every rig until the latest
hand-over the experiment allows, then again to the end only the rigs whose swing-up met
the experiment (:func:`simulate_events`); each rig's run depends on its own values and
noise only, so the second stage repeats the first's cycles bit for bit.

Why not a library: ELFI (batch simulators, rejection and SMC-ABC) requires matplotlib
< 3.9, GPy and ipyparallel; pyabc simulates one particle a call (here the compiled batch
steps a thousand rigs a call) and brings redis, SQLAlchemy and ipykernel. Rejection on the
batch is a few lines of numpy.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from pisc_bringup.experiment import Experiment, Traces, judge, measure
from pisc_bringup.uncertainty import LATENCY, Distribution, Draws, Range
from pisc_control.supervisor import Supervisor
from pisc_plant.plant import Plant, PlantConfig, plant_set
from pisc_sim.configuration import GraphConfig

__all__ = ["CHUNK_DRAWS", "Calibration", "calibrate", "chunk_seed", "experiment_prior",
           "pass_rates", "simulate_events", "simulate_traces"]

CHUNK_DRAWS = 1000
X0 = "initial.x_m"
FIXED_START = ("initial.x_dot_mps", "initial.theta_rad", "initial.theta_dot_radps")


def chunk_seed(seed: int, chunk: int) -> int:
    return int(np.random.SeedSequence([seed, chunk]).generate_state(1)[0])


def experiment_prior(distribution: Distribution, config: GraphConfig,
                     experiment: Experiment) -> Distribution:
    """``distribution`` with the experiment's start in place of its ``initial.*`` ranges:
    the cart's start uniform over the experiment's range, the rest fixed."""
    low, high = experiment.x_range_m
    ranges = [r for r in distribution.ranges if not r.name.startswith("initial.")]
    ranges.append(Range(X0, "uniform", low, high, float(config.initial.x_m)))
    return replace(distribution, ranges=tuple(sorted(ranges, key=lambda r: r.name)))


def experiment_config(config: GraphConfig, experiment: Experiment) -> GraphConfig:
    """``config`` started as the experiment says (the cart's start aside)."""
    return replace(config, initial=replace(config.initial, **experiment.start))


def simulate_traces(config: GraphConfig, plant: PlantConfig, x0: np.ndarray,
                    delay_s: np.ndarray, cycles: int, noise: np.ndarray | None) -> Traces:
    """The batch closed loop of :func:`pisc_sim.closed_loop.simulate_batch` (the
    controllers' compiled pass, the plant's kernel, the sensors' numpy model), keeping
    each cycle's measured angle, mode, set-point and voltage.

    ``plant`` is one rig or a plant set of ``len(x0)`` rigs, started at ``x0`` with the
    rest of ``config.initial``; ``delay_s`` (one a rig) the command latency; ``noise``
    standard normal draws (cycles, rigs, 3), or None without noise.
    """
    from pisc_sim.batch_controllers import BatchControllers

    n = len(x0)
    sim = Plant(plant)
    i0 = config.initial
    y = sim.initial_state(x0, np.full(n, i0.x_dot_mps), np.full(n, i0.theta_rad),
                          np.full(n, i0.theta_dot_radps))
    flat = np.array(y.reshape(n, -1), dtype=float, order="C")
    controllers = BatchControllers(config, Supervisor(config.supervisor), n)
    period = config.loop.period_s
    delay = np.asarray(delay_s, dtype=float) + plant.actuator.command_delay_s
    if np.any(~np.isfinite(delay)) or np.any(delay < 0.0) or np.any(delay >= period):
        raise ValueError(f"command delay must lie in [0, {period}) s (one period)")
    delay = np.broadcast_to(delay, (n,)).copy()
    log = {k: np.empty((cycles, n)) for k in ("theta", "mode", "u", "i_d")}
    applied = np.zeros(n)
    for k in range(cycles):
        draws = None if noise is None else noise[k]
        x, theta, current = sim.measurement(flat, applied, draws)
        _, mode, i_d, voltage = controllers.step(np.broadcast_to(x, (n,)),
                                                 np.broadcast_to(theta, (n,)),
                                                 np.broadcast_to(current, (n,)))
        log["theta"][k], log["mode"][k], log["u"][k], log["i_d"][k] = theta, mode, voltage, i_d
        if np.any(delay > 0.0):
            flat = sim.advance(flat, applied, delay)
            flat = sim.advance(flat, voltage, period - delay)
        else:
            flat = sim.advance(flat, voltage, period)
        applied = voltage
    return Traces(period, log["theta"], log["mode"].astype(np.int64), log["u"], log["i_d"],
                  config.current_loop.voltage_limit_v, config.current_loop.current_limit_a)


def _screen_s(experiment: Experiment) -> float | None:
    """Until when a run must be simulated to judge its swing-up (None: to the end)."""
    hand_over = experiment.event("hand_over_s")
    if hand_over is None:
        return None
    return min(hand_over.value + hand_over.tolerance, experiment.duration_s)


def simulate_events(config: GraphConfig, base: PlantConfig, values: Mapping[str, np.ndarray],
                    experiment: Experiment, noise_seed: int) -> dict[str, np.ndarray]:
    """The experiment's events measured on each draw (``values``: one array a varied
    parameter, ``initial.x_m`` among them); a pure function of its arguments.

    Stage one runs every rig until the latest hand-over the experiment allows and judges
    the swing-up (``oscillations``, ``hand_over_s``); stage two runs those that met it
    to the end. The others keep stage one's values, their later events infinite."""
    x0 = np.asarray(values[X0], dtype=float)
    n = len(x0)
    delay = np.asarray(values.get(LATENCY, np.zeros(n)), dtype=float)
    physical = {k: np.asarray(v) for k, v in values.items() if k not in (X0, LATENCY)}
    period = config.loop.period_s
    cycles = int(round(experiment.duration_s / period)) + 1
    plant = plant_set(base, physical) if physical else base
    noise = (np.random.default_rng(noise_seed).standard_normal((cycles, n, 3))
             if Plant(plant).config.noise.any else None)
    screen = _screen_s(experiment)
    if screen is None:
        return measure(simulate_traces(config, plant, x0, delay, cycles, noise))
    early = measure(simulate_traces(config, plant, x0, delay,
                                    int(math.floor(screen / period + 1e-9)) + 2, noise))
    swing = [e for e in experiment.events if e.name in ("oscillations", "hand_over_s")]
    go_on = np.ones(n, dtype=bool)
    for event in swing:
        go_on &= event.passes(early[event.name])
    out = {name: np.where(name in ("oscillations", "hand_over_s"), v, np.inf)
           for name, v in early.items()}
    picked = np.flatnonzero(go_on)
    if picked.size:
        subset = {k: v[picked] for k, v in physical.items()}
        late = measure(simulate_traces(
            config, plant_set(base, subset) if subset else base, x0[picked],
            delay[picked], cycles, None if noise is None else noise[:, picked]))
        for name, v in late.items():
            out[name][picked] = v
    return out


MapChunks = Callable[[Callable[..., Any], Sequence[tuple[Any, ...]]], list[Any]]


def _run_here(fn: Callable[..., Any], tasks: Sequence[tuple[Any, ...]]) -> list[Any]:
    return [fn(*task) for task in tasks]


@dataclass(frozen=True)
class Calibration:
    """Every draw of the prior with its measured events, and which reproduce the
    experiment."""

    experiment: Experiment
    prior: Distribution
    draws: Draws
    measured: dict[str, np.ndarray]
    accepted: np.ndarray
    seed: int

    @property
    def rate(self) -> float:
        return float(np.mean(self.accepted))

    @property
    def posterior(self) -> Draws:
        return self.draws[np.flatnonzero(self.accepted)]

    def summary(self) -> list[tuple[Range, float, float, float]]:
        """(prior range, median, 5th and 95th percentile) of each parameter's posterior
        (NaN without an accepted draw)."""
        rows = []
        post = self.posterior
        for r in self.prior.ranges:
            v = post.values[r.name]
            if len(v):
                rows.append((r, *(float(q) for q in np.percentile(v, [50, 5, 95]))))
            else:
                rows.append((r, math.nan, math.nan, math.nan))
        return rows


def _chunks(config: GraphConfig, base: PlantConfig, draws: Draws, experiment: Experiment,
            seed: int) -> list[tuple[Any, ...]]:
    return [(config, base, draws[lo:lo + CHUNK_DRAWS].values, experiment, chunk_seed(seed, c))
            for c, lo in enumerate(range(0, draws.n, CHUNK_DRAWS))]


def calibrate(config: GraphConfig, base: PlantConfig, prior: Distribution,
              experiment: Experiment, n: int, seed: int,
              map_chunks: MapChunks | None = None) -> Calibration:
    """``n`` draws of ``prior`` from ``seed``, each simulated and judged; ``config`` is
    the experiment's configuration, ``base`` the plant the draws vary."""
    config = experiment_config(config, experiment)
    draws = prior.draw(n, seed)
    parts = (map_chunks or _run_here)(simulate_events,
                                      _chunks(config, base, draws, experiment, seed))
    measured = {name: np.concatenate([p[name] for p in parts]) for name in parts[0]}
    return Calibration(experiment, prior, draws, measured, judge(experiment, measured), seed)


def pass_rates(config: GraphConfig, base: PlantConfig, rigs: Draws, experiment: Experiment,
               noises: int, seed: int, map_chunks: MapChunks | None = None) -> np.ndarray:
    """Each of ``rigs`` run again with ``noises`` other noise draws: the share that
    reproduce the experiment, one a rig."""
    config = experiment_config(config, experiment)
    repeated = rigs[np.repeat(np.arange(rigs.n), noises)]
    parts = (map_chunks or _run_here)(simulate_events,
                                      _chunks(config, base, repeated, experiment, seed))
    measured = {name: np.concatenate([p[name] for p in parts]) for name in parts[0]}
    return judge(experiment, measured).reshape(rigs.n, noises).mean(axis=1)


def nominal_index(calibration: Calibration, rates: np.ndarray) -> int:
    """The posterior draw that stands for it: the highest pass rate over other noise,
    and among those the nearest to the posterior's medians (in each parameter's prior
    range as the unit; log for a ``factor`` range)."""
    post = calibration.posterior
    distance = np.zeros(post.n)
    for r in calibration.prior.ranges:
        v = post.values[r.name]
        lo, hi = r.value_range
        if r.kind == "factor":
            v, lo, hi = np.log(v), math.log(lo), math.log(hi)
        if hi > lo:
            distance += ((v - np.median(v)) / (hi - lo)) ** 2
    best = np.flatnonzero(rates == rates.max())
    return int(best[np.argmin(distance[best])])
