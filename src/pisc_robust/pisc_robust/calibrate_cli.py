"""pisc_calibrate: the rigs of a distribution that reproduce the thesis's experiment
(SMC-ABC on the batch closed loop, :mod:`pisc_robust.calibrate`;
docs/thesis-experiment.md).

    pisc_calibrate --experiment thesis-6.6 --distribution thesis-rig --seed 1

Prints the experiment, the prior, each generation (its tolerance factor, the draws
simulated, the acceptance rate with its 95 % interval, the sample size and its effective
size) and each parameter's posterior (weighted median, 90 % interval, against its prior
range); writes to ``--out`` (default ``calibration/``) the posterior's histograms
(``posterior.png``), its particles with their weights and events (``posterior.csv``), a
distribution file of the posterior (``thesis-calibrated.yaml``: its rigs, resampled by
weight, drawn jointly, with the prior's uneven starts) and the calibrated nominal plant
(``thesis-calibrated-plant.yaml``: the particle that reproduces the experiment under the
most other noise draws, at its start). ``--epsilons 1`` is rejection ABC. The same seed
gives the same numbers. Exit status 0 with a complete posterior, 1 when the budget ran
out first, 2 on bad input.
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from pisc_robust.calibrate import Calibration, Generation

PROG = "pisc_calibrate"
PLOT = "posterior.png"
DISTRIBUTION = "thesis-calibrated.yaml"
PLANT = "thesis-calibrated-plant.yaml"
#: other noise draws each accepted rig is run with, to pick the nominal one
NOISE_SEEDS = 16


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    parser.add_argument("--experiment", default="thesis-6.6", metavar="NAME|FILE",
                        help="a shipped experiment or an experiment file (default: "
                        "%(default)s)")
    parser.add_argument("--distribution", default="thesis-rig", metavar="NAME|FILE",
                        help="the prior: a shipped distribution or a distribution file "
                        "(default: %(default)s)")
    parser.add_argument("--particles", type=int, default=100, metavar="N",
                        help="posterior sample size (default: %(default)s)")
    parser.add_argument("--epsilons", default="4,2,1", metavar="E,E,...",
                        help="the generations' tolerance factors, decreasing to 1 "
                        "(default: %(default)s; 1: rejection ABC)")
    parser.add_argument("--budget", type=int, default=600_000, metavar="N",
                        help="most draws simulated in all (default: %(default)s)")
    parser.add_argument("--batch", type=int, default=2000, metavar="N",
                        help="draws simulated at a time; the numbers depend on it "
                        "(default: %(default)s)")
    parser.add_argument("--seed", type=int, default=1, metavar="S",
                        help="seed of the draws and the noise (default: %(default)s)")
    parser.add_argument("--noises", type=int, default=NOISE_SEEDS, metavar="K",
                        help="other noise draws each accepted rig is run with to pick the "
                        "nominal plant (default: %(default)s)")
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, metavar="N",
                       help="0: in this process, without Dask; N: a local Dask cluster of N "
                       "workers (default: one per core from 5 chunks on)")
    where.add_argument("--scheduler", metavar="ADDRESS",
                       help="an existing Dask scheduler (tcp://host:8786)")
    parser.add_argument("--out", type=Path, default=Path("calibration"), metavar="DIR",
                        help="directory of the plot, the CSV and the two files "
                        "(default: %(default)s)")
    args = parser.parse_args(argv)
    if args.particles < 2 or min(args.noises, args.budget, args.batch) < 1:
        parser.error("--particles takes 2 or more, --noises, --budget and --batch a "
                     "positive number")
    try:
        args.epsilons = [float(e) for e in args.epsilons.split(",")]
    except ValueError:
        parser.error(f"--epsilons {args.epsilons}: numbers separated by commas")
    if (args.epsilons != sorted(args.epsilons, reverse=True) or args.epsilons[-1] != 1.0
            or len(set(args.epsilons)) != len(args.epsilons)):
        parser.error(f"--epsilons {args.epsilons}: decreasing, ending at 1 (the thesis's "
                     "tolerances)")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    from pisc_robust.robustness_args import quiet_threads

    quiet_threads()
    from pisc_robust.calibrate import (
        CHUNK_DRAWS,
        calibrate,
        experiment_prior,
        nominal_index,
        pass_rates,
    )
    from pisc_robust.cluster import chunk_runner, core_count, describe_runner
    from pisc_robust.experiment import load_experiment
    from pisc_robust.robustness import binomial_interval, prepare
    from pisc_robust.uncertainty import load_distribution
    from pisc_msgs_py.config import ConfigError
    from pisc_sim.configuration import load_graph_config

    try:
        experiment = load_experiment(args.experiment)
        config, flat = load_graph_config(experiment.configuration)
        distribution = load_distribution(args.distribution, config)
        config, base = prepare(config, distribution)
        prior = experiment_prior(distribution, config, experiment)
        args.out.mkdir(parents=True, exist_ok=True)
    except (ConfigError, OSError) as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return 2
    workers = args.workers
    if workers is None and args.scheduler is None:  # a worker a chunk of a batch, a core each
        chunks = -(-args.batch // CHUNK_DRAWS)
        workers = min(core_count(), chunks) if core_count() > 1 and chunks > 1 else 0
    print(f"experiment {experiment.name}: {experiment.description}")
    for event in experiment.events:
        print(f"  {event.describe()}")
    print(f"configuration {experiment.configuration}; prior {distribution.name} (digest "
          f"{distribution.digest}) with the experiment's start")
    print(*(f"  {r.describe()}" for r in prior.ranges), sep="\n")
    print(f"SMC-ABC: {args.particles} particles a generation, tolerance factors "
          f"{', '.join(f'{e:g}' for e in args.epsilons)}, seed {args.seed}, budget "
          f"{args.budget} draws; {describe_runner(workers, args.scheduler)}")
    start = time.perf_counter()

    def report(g: Generation) -> None:
        low, high = binomial_interval(g.accepted, g.simulated)
        print(f"  generation at {g.epsilon:g} x tolerance: {g.simulated} draws simulated, "
              f"{g.accepted} within it, acceptance rate {100 * g.rate:.3f} % (95 % interval "
              f"{100 * low:.3f} .. {100 * high:.3f} %); sample size {g.particles.n}, "
              f"effective {g.effective_size:.0f}; {time.perf_counter() - start:.0f} s",
              flush=True)

    with chunk_runner(workers, args.scheduler) as map_chunks:
        result = calibrate(config, base, prior, experiment, args.particles, args.seed,
                           args.epsilons, args.budget, map_chunks, args.batch, report)
        print(f"{result.simulated} draws simulated in {time.perf_counter() - start:.0f} s")
        print(*format_posterior(result), sep="\n")
        write_csv(args.out / "posterior.csv", result)
        if not result.complete:
            print(f"the budget ran out before {args.particles} particles at the thesis's "
                  f"tolerances: no distribution or plant file (docs/thesis-experiment.md)")
            return 1
        plot_posterior(args.out / PLOT, result)
        post = result.posterior
        rates = pass_rates(config, base, post, experiment, args.noises, args.seed + 1,
                           map_chunks)
    k = nominal_index(result, rates)
    print(f"under {args.noises} other noise draws each, the posterior's rigs reproduce the "
          f"experiment {100 * float(np.sum(rates * result.final.weights)):.1f} % of the time "
          f"(weighted; median rig {100 * float(np.median(rates)):.0f} %); the nominal rig: "
          f"particle {k}, {100 * rates[k]:.0f} %")
    from pisc_robust.calibrate_files import write_distribution, write_plant

    write_distribution(args.out / DISTRIBUTION, result, distribution)
    seed, tried = write_plant(args.out / PLANT, result, k, flat, distribution, config)
    print(f"nominal plant: noise seed {seed}, the first from 0 whose one-rig run reproduces "
          "the experiment" if seed is not None else
          f"nominal plant: no noise seed of 0 .. {tried - 1} gives a one-rig run that "
          "reproduces the experiment (the file has seed 0)")
    print(f"wrote {args.out / PLOT}, {args.out / 'posterior.csv'}, "
          f"{args.out / DISTRIBUTION}, {args.out / PLANT}")
    return 0


def format_posterior(result: Calibration) -> list[str]:
    from pisc_robust.uncertainty import unit_of

    lines = ["posterior (weighted median, 90 % interval) against the prior's range:"]
    for r, median, p5, p95 in result.summary():
        unit = unit_of(r.name)
        lo, hi = r.value_range
        lines.append(f"  {r.name:32s} {median:11.4g}  [{p5:10.4g}, {p95:10.4g}]   prior "
                     f"[{lo:.4g}, {hi:.4g}]{' ' + unit if unit else ''}")
    return lines


def write_csv(path: Path, result: Calibration) -> None:
    g = result.final
    names = list(g.particles.values)
    with path.open("w", newline="") as stream:
        out = csv.writer(stream)
        out.writerow(["particle", "weight", *names, *g.measured])
        for j in range(g.particles.n):
            out.writerow([j, repr(float(g.weights[j])),
                          *(repr(float(g.particles.values[n][j])) for n in names),
                          *(repr(float(v[j])) for v in g.measured.values())])


def plot_posterior(path: Path, result: Calibration) -> None:
    """One panel a parameter: the posterior's histogram over the prior's range, its
    median and 90 % interval; the prior's density dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from matplotlib.ticker import FixedLocator, FuncFormatter, MaxNLocator, NullFormatter

    from pisc_robust.uncertainty import unit_of

    short = FuncFormatter(lambda v, _: f"{v:.3g}")
    rows = result.summary()
    post = result.posterior
    columns = 4
    lines = -(-len(rows) // columns)
    fig, axes = plt.subplots(lines, columns, figsize=(3.3 * columns, 2.2 * lines + 0.8),
                             squeeze=False)
    for ax, (r, median, p5, p95) in zip(axes.flat, rows, strict=False):
        lo, hi = r.value_range
        log = r.kind == "factor"
        edges = np.geomspace(lo, hi, 16) if log else np.linspace(lo, hi, 16)
        values = post.values[r.name]
        ax.hist(values, bins=edges, weights=result.final.weights, color="C0", alpha=0.6)
        expected = (np.diff(np.log(edges)) / math.log(hi / lo) if log
                    else np.diff(edges) / (hi - lo))
        ax.stairs(expected, edges, color="k", ls="--", lw=0.8)
        for q, style in ((median, "-"), (p5, ":"), (p95, ":")):
            ax.axvline(q, color="C3", ls=style, lw=1.0)
        if log:  # ticks at the ends and the nominal value, as pisc_robustness draws them
            ax.set_xscale("log")
            ax.xaxis.set_major_locator(FixedLocator([lo, hi, r.nominal]))
            ax.xaxis.set_minor_formatter(NullFormatter())
        else:
            ax.xaxis.set_major_locator(MaxNLocator(4))
        ax.xaxis.set_major_formatter(short)
        ax.set_xlim(lo, hi)
        unit = unit_of(r.name)
        ax.set_xlabel(r.name + (f" [{unit}]" if unit else ""), fontsize=8)
        ax.tick_params(labelsize=7)
    for ax in axes[:, 0]:
        ax.set_ylabel("weight", fontsize=8)
    for ax in list(axes.flat)[len(rows):]:
        ax.set_visible(False)
    fig.suptitle(f"{result.experiment.name}: posterior of {post.n} particles (SMC-ABC, "
                 f"{result.simulated} draws simulated; {result.prior.name}, seed "
                 f"{result.seed}); weight per bin; red: median and 90 % interval; dashed: "
                 "the prior", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
