"""Which rigs of a distribution reproduce the thesis's experiment: approximate Bayesian
computation (ABC) on the batch closed loop.

The prior is a distribution of what is not known about the rig (``thesis-rig``) with the
experiment's start in place of its uneven starts: hanging at rest, the cart anywhere in
the experiment's range. Each draw is simulated under the experiment's configuration with
the sensors' noise and the command latency drawn as on the rig, and its events are
measured (:mod:`pisc_robust.experiment`). A draw whose every event lies within its
tolerance reproduces the experiment; those draws are samples of the posterior, the prior
restricted to the rigs (and noise) that reproduce it (ABC with a uniform kernel on the
thesis's tolerances, Beaumont 2010, Annu. Rev. Ecol. Evol. Syst. 41, eq. 2). About one
draw of thesis-rig in 10,000 does, so :func:`calibrate` gets there by sequential Monte
Carlo (SMC-ABC, Beaumont et al. 2009): generations at tolerances widened by a decreasing
factor, each drawn around the last; one generation at factor 1 is rejection ABC.

Each chunk of :data:`CHUNK_DRAWS` draws is a pure function of its draws and its noise
seed (seeded by (seed, generation, batch, chunk index), as :mod:`pisc_robust.robustness`
seeds its chunks), so the same seed gives the same posterior in this process or on a Dask
cluster (:mod:`pisc_robust.cluster`). A chunk runs in two stages: every rig until the latest
hand-over the experiment allows, then again to the end only the rigs whose swing-up met
the experiment (:func:`simulate_events`); each rig's run depends on its own values and
noise only, so the second stage repeats the first's cycles bit for bit.

Why not a library: ELFI (batch simulators, rejection and SMC-ABC) requires matplotlib
< 3.9 (the project pins 3.11), GPy and ipyparallel; pyabc simulates one particle a call
(here the compiled batch steps a thousand rigs a call) and brings redis, SQLAlchemy and
ipykernel. SMC-ABC over the batch is a hundred lines of numpy.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from pisc_robust.experiment import Experiment, Traces, judge, measure
from pisc_robust.uncertainty import LATENCY, Distribution, Draws, Range
from pisc_control.supervisor import Supervisor
from pisc_msgs_py.config import ConfigError
from pisc_plant.plant import Plant
from pisc_plant.plant_config import PlantConfig, plant_set
from pisc_sim.configuration import GraphConfig

__all__ = ["CHUNK_DRAWS", "Calibration", "Generation", "calibrate", "distance",
           "experiment_prior", "nominal_index", "pass_rates", "simulate_events",
           "simulate_traces", "to_unit"]

CHUNK_DRAWS = 1000
X0 = "initial.x_m"
SWING = ("oscillations", "hand_over_s")  # the events a run's first stage judges


def experiment_prior(distribution: Distribution, config: GraphConfig,
                     experiment: Experiment) -> Distribution:
    """``distribution`` with the experiment's start in place of its ``initial.*`` ranges:
    the cart's start uniform over the experiment's range, the rest fixed. A distribution
    with a joint block (a posterior already) is refused: the prior's ranges are
    independent."""
    if distribution.rows is not None:
        raise ConfigError(f"{distribution.name}: a distribution with a joint block cannot "
                          "be the prior (calibrate from independent ranges, e.g. thesis-rig)")
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


def _screen_s(experiment: Experiment, epsilon: float) -> float | None:
    """Until when a run must be simulated to judge its swing-up (None: to the end)."""
    hand_over = experiment.event("hand_over_s")
    if hand_over is None:
        return None
    return min(hand_over.value + epsilon * hand_over.tolerance, experiment.duration_s)


def simulate_events(config: GraphConfig, base: PlantConfig, values: Mapping[str, np.ndarray],
                    experiment: Experiment, noise_seed: int, epsilon: float = 1.0
                    ) -> dict[str, np.ndarray]:
    """The experiment's events measured on each draw (``values``: one array a varied
    parameter, ``initial.x_m`` among them); a pure function of its arguments.

    Stage one runs every rig until the latest hand-over the experiment allows (within
    ``epsilon`` tolerances) and judges the swing-up (``oscillations``, ``hand_over_s``);
    stage two runs those that met it to the end. The others keep stage one's values,
    their later events infinite."""
    x0 = np.asarray(values[X0], dtype=float)
    n = len(x0)
    delay = np.asarray(values.get(LATENCY, np.zeros(n)), dtype=float)
    physical = {k: np.asarray(v) for k, v in values.items() if k not in (X0, LATENCY)}
    period = config.loop.period_s
    cycles = int(round(experiment.duration_s / period)) + 1
    plant = plant_set(base, physical) if physical else base
    noise = (np.random.default_rng(noise_seed).standard_normal((cycles, n, 3))
             if plant.noise.any else None)
    screen = _screen_s(experiment, epsilon)
    if screen is None:
        return measure(simulate_traces(config, plant, x0, delay, cycles, noise))
    early = measure(simulate_traces(config, plant, x0, delay,
                                    int(math.floor(screen / period + 1e-9)) + 2, noise))
    go_on = np.ones(n, dtype=bool)
    for event in experiment.events:
        if event.name in SWING:
            go_on &= event.miss(early[event.name]) <= epsilon
    out = {name: v.copy() if name in SWING else np.full(n, np.inf)
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

#: draws simulated at a time: a generation proposes in batches of this many until it has
#: its particles (two chunks, one for each worker of a 2-core machine; a number of its own,
#: not the workers', so that the result does not depend on where it runs)
BATCH_DRAWS = 2 * CHUNK_DRAWS


def _run_here(fn: Callable[..., Any], tasks: Sequence[tuple[Any, ...]]) -> list[Any]:
    return [fn(*task) for task in tasks]


def distance(experiment: Experiment, measured: Mapping[str, np.ndarray]) -> np.ndarray:
    """Each draw's largest miss, in tolerances: max over events of |measured - value| /
    tolerance (a draw with distance <= 1 meets every event; inf if one is never seen)."""
    worst = np.zeros(len(next(iter(measured.values()))))
    for event in experiment.events:
        worst = np.maximum(worst, event.miss(measured[event.name]))
    return worst


def to_unit(r: Range, values: np.ndarray) -> np.ndarray:
    """The inverse of :meth:`Range.sample`: where ``values`` lie in [0, 1)."""
    v = np.asarray(values, dtype=float)
    if r.kind == "factor":
        lo, hi = math.log(r.low), math.log(r.high)
        return (np.log(v / r.nominal) - lo) / (hi - lo)
    if r.kind == "offset":
        q = v - r.nominal
    elif r.kind == "relative":
        q = v / r.nominal - 1.0
    else:
        q = v
    return (q - r.low) / (r.high - r.low) if r.high > r.low else np.zeros_like(v)


@dataclass(frozen=True)
class Generation:
    """One population of SMC-ABC: ``particles`` (each parameter's values) with their
    importance ``weights`` (summing to 1) and events, all within ``epsilon`` tolerances."""

    epsilon: float
    simulated: int  # draws simulated for this generation
    accepted: int  # of those, within epsilon (the first ``particles.n`` are kept)
    particles: Draws
    weights: np.ndarray
    measured: dict[str, np.ndarray]

    @property
    def rate(self) -> float:
        return self.accepted / self.simulated if self.simulated else 0.0

    @property
    def effective_size(self) -> float:
        """Kish's effective sample size of the weights, (sum w)^2 / sum w^2."""
        return float(1.0 / np.sum(self.weights ** 2)) if len(self.weights) else 0.0


@dataclass(frozen=True)
class Calibration:
    """The generations of a calibration; the last is the posterior (complete when it has
    the particles asked for at the experiment's tolerances, epsilon = 1)."""

    experiment: Experiment
    prior: Distribution
    generations: tuple[Generation, ...]
    particles: int
    seed: int

    @property
    def final(self) -> Generation:
        return self.generations[-1]

    @property
    def complete(self) -> bool:
        g = self.final
        return g.epsilon <= 1.0 and g.particles.n == self.particles

    @property
    def simulated(self) -> int:
        return sum(g.simulated for g in self.generations)

    @property
    def posterior(self) -> Draws:
        return self.final.particles

    def summary(self) -> list[tuple[Range, float, float, float]]:
        """(prior range, weighted median, 5th and 95th percentile) of each parameter in the
        last generation (NaN without particles)."""
        g = self.final
        rows = []
        for r in self.prior.ranges:
            v = g.particles.values[r.name]
            if not len(v):
                rows.append((r, math.nan, math.nan, math.nan))
                continue
            order = np.argsort(v, kind="stable")
            cum = np.cumsum(g.weights[order])
            q = [float(v[order][min(np.searchsorted(cum, p * cum[-1]), len(v) - 1)])
                 for p in (0.5, 0.05, 0.95)]
            rows.append((r, *q))
        return rows

    def resampled(self, n: int) -> Draws:
        """``n`` rows of the posterior by systematic resampling of its weights (seeded by
        the calibration's seed): equally weighted rigs for a distribution file."""
        g = self.final
        rng = np.random.default_rng([self.seed, 1 << 20])
        positions = (rng.random() + np.arange(n)) / n
        picked = np.minimum(np.searchsorted(np.cumsum(g.weights), positions), g.particles.n - 1)
        return g.particles[picked]


def _values(prior: Distribution, unit: np.ndarray) -> dict[str, np.ndarray]:
    return {r.name: r.sample(unit[:, j]) for j, r in enumerate(prior.ranges)}


def _simulate(config: GraphConfig, base: PlantConfig, values: Mapping[str, np.ndarray],
              experiment: Experiment, seed: list[int], map_chunks: MapChunks,
              epsilon: float = 1.0) -> dict[str, np.ndarray]:
    n = len(next(iter(values.values())))
    tasks = [(config, base, {k: v[lo:lo + CHUNK_DRAWS] for k, v in values.items()},
              experiment, int(np.random.SeedSequence([*seed, c]).generate_state(1)[0]),
              epsilon)
             for c, lo in enumerate(range(0, n, CHUNK_DRAWS))]
    parts = map_chunks(simulate_events, tasks)
    return {name: np.concatenate([p[name] for p in parts]) for name in parts[0]}


def calibrate(config: GraphConfig, base: PlantConfig, prior: Distribution,
              experiment: Experiment, particles: int, seed: int,
              epsilons: Sequence[float] = (1.0,), budget: int = 200_000,
              map_chunks: MapChunks | None = None, batch: int = BATCH_DRAWS,
              report: Callable[[Generation], None] | None = None) -> Calibration:
    """Sequential Monte Carlo ABC (Beaumont et al. 2009, "Adaptive approximate Bayesian
    computation", Biometrika 96, algorithm of section 2; Toni et al. 2009) on the batch.

    Generation t keeps ``particles`` draws whose distance (:func:`distance`) is at most
    ``epsilons[t]``; the first draws from the prior, each later one from its
    predecessor's particles moved by a Gaussian kernel of twice their weighted covariance
    (in each parameter's prior range mapped to [0, 1), where the prior is uniform), each
    weighted by prior / (the kernel's mixture density). ``epsilons = (1,)`` is rejection
    ABC. Draws are proposed ``batch`` at a time, seeded by (seed, generation, batch
    index), until a generation has its particles; it stops early, with the generation it
    has, once ``budget`` draws have been simulated in all. ``config`` is the
    experiment's configuration, ``base`` the plant the draws vary.
    """
    if any(r.kind == "joint" for r in prior.ranges):
        raise ValueError(f"{prior.name}: a prior of independent ranges (it has a joint "
                         "block)")
    if not epsilons or list(epsilons) != sorted(epsilons, reverse=True) or epsilons[-1] <= 0:
        raise ValueError(f"epsilons {list(epsilons)}: positive and decreasing")
    config = experiment_config(config, experiment)
    run = map_chunks or _run_here
    d = len(prior.ranges)
    generations: list[Generation] = []
    spent = 0
    for t, epsilon in enumerate(epsilons):
        kept_u: list[np.ndarray] = []
        kept_m: list[dict[str, np.ndarray]] = []
        simulated = accepted = 0
        b = 0
        while sum(len(u) for u in kept_u) < particles and spent < budget:
            rng = np.random.default_rng([seed, t, b])
            if t == 0:
                unit = rng.random((batch, d))
            else:
                unit = _propose(rng, previous_u, previous_w, cov, batch)
            measured = _simulate(config, base, _values(prior, unit), experiment, [seed, t, b],
                                 run, epsilon)
            ok = distance(experiment, measured) <= epsilon
            simulated += batch
            spent += batch
            accepted += int(ok.sum())
            kept_u.append(unit[ok])
            kept_m.append({k: v[ok] for k, v in measured.items()})
            b += 1
        unit = np.concatenate(kept_u)[:particles] if kept_u else np.zeros((0, d))
        measured = {k: np.concatenate([m[k] for m in kept_m])[:particles]
                    for k in (kept_m[0] if kept_m else {})}
        if t == 0 or not len(unit):
            weights = np.full(len(unit), 1.0 / max(len(unit), 1))
        else:
            weights = 1.0 / _mixture_density(unit, previous_u, previous_w, cov)
            weights /= weights.sum()
        values = _values(prior, unit)
        generation = Generation(epsilon, simulated, accepted, Draws(values, len(unit)),
                                weights, measured)
        generations.append(generation)
        if report is not None:
            report(generation)
        if len(unit) < particles:
            break
        previous_u, previous_w = unit, weights
        cov = 2.0 * np.atleast_2d(np.cov(unit, rowvar=False, aweights=weights))
    return Calibration(experiment, prior, tuple(generations), particles, seed)


def _propose(rng: np.random.Generator, u: np.ndarray, w: np.ndarray, cov: np.ndarray,
             n: int) -> np.ndarray:
    """``n`` draws of the kernel mixture inside the unit cube (outside, the prior is 0)."""
    chol = np.linalg.cholesky(cov + 1e-12 * np.eye(len(cov)))
    out = np.empty((0, u.shape[1]))
    while len(out) < n:
        parents = rng.choice(len(u), size=n, p=w)
        moved = u[parents] + rng.standard_normal((n, u.shape[1])) @ chol.T
        out = np.concatenate([out, moved[np.all((moved >= 0.0) & (moved < 1.0), axis=1)]])
    return out[:n]


def _mixture_density(x: np.ndarray, u: np.ndarray, w: np.ndarray, cov: np.ndarray
                     ) -> np.ndarray:
    """sum_j w_j N(x_i; u_j, cov) for each row of x (the normal's constant included)."""
    chol = np.linalg.cholesky(cov + 1e-12 * np.eye(len(cov)))
    solved = np.linalg.solve(chol, (x[:, None, :] - u[None, :, :]).reshape(-1, len(cov)).T)
    q = np.sum(solved ** 2, axis=0).reshape(len(x), len(u))
    log_norm = -0.5 * len(cov) * math.log(2 * math.pi) - np.sum(np.log(np.diag(chol)))
    return np.exp(log_norm - 0.5 * q) @ w


def pass_rates(config: GraphConfig, base: PlantConfig, rigs: Draws, experiment: Experiment,
               noises: int, seed: int, map_chunks: MapChunks | None = None) -> np.ndarray:
    """Each of ``rigs`` run again with ``noises`` other noise draws: the share that
    reproduce the experiment, one a rig."""
    config = experiment_config(config, experiment)
    repeated = rigs[np.repeat(np.arange(rigs.n), noises)]
    measured = _simulate(config, base, repeated.values, experiment, [seed, 1 << 30],
                         map_chunks or _run_here)
    return judge(experiment, measured).reshape(rigs.n, noises).mean(axis=1)


def nominal_index(calibration: Calibration, rates: np.ndarray) -> int:
    """The posterior particle that stands for it: the highest pass rate over other noise,
    and among those the nearest to the posterior's weighted medians (in each parameter's
    prior range mapped to [0, 1))."""
    post = calibration.posterior
    medians = {r.name: m for r, m, _, _ in calibration.summary()}
    distance2 = np.zeros(post.n)
    for r in calibration.prior.ranges:
        distance2 += (to_unit(r, post.values[r.name]) - to_unit(r, medians[r.name])) ** 2
    best = np.flatnonzero(rates == rates.max())
    return int(best[np.argmin(distance2[best])])
