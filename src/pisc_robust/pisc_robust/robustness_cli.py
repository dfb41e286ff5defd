"""pisc_robustness: how often a configuration keeps rigs drawn from a distribution of
what is not known about the rig safe, catches them and catches them fast
(docs/robustness.md).

    pisc_robustness default --distribution thesis-rig --draws 10000 --seed 1

Prints the three tiers (safe, caught, fast) each with its 95 % interval and its failures
by kind, the fast tier over the draws a feasibility study found a witness for, the catch
time, the largest |x|, the hold's current set-point RMS, the wall time, and each tier's
worst draws with the command that reruns each through the ROS graph; writes
``DIR/success_by_parameter.png``. The same seed gives the same numbers.
"""

from __future__ import annotations

import argparse
import os
import sys
import textwrap
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from pisc_runs.verdict import Criteria, Outcomes
    from pisc_robust.uncertainty import Distribution, Draws

PROG = "pisc_robustness"
PLOT = "success_by_parameter.png"


def quiet_threads() -> None:
    """Let idle numba (OpenMP) threads sleep instead of spinning, unless the environment
    says otherwise; set before the plant's kernel starts its threads.

    With OpenMP's default active wait, the kernel's two threads ran a chunk of 1000
    draws in 15-38 s instead of 3 s when other processes shared the two cores (a
    thread spins at every period's barrier while its partner waits for a core);
    passive, 3.1 s (docs/robustness.md, "Scaling").
    """
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def add_run_arguments(parser: argparse.ArgumentParser, draws: int) -> None:
    """The arguments pisc_robustness and pisc_tune share."""
    parser.add_argument("config", metavar="CONFIG",
                        help="a configuration name (default, thesis) or a parameter file")
    parser.add_argument("--distribution", default="thesis-rig", metavar="NAME|FILE",
                        help="a shipped distribution or a distribution file "
                        "(default: %(default)s)")
    parser.add_argument("--draws", type=int, default=draws, metavar="N",
                        help="draws from the distribution (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=1, metavar="S",
                        help="seed of the draws and of the measurement noise "
                        "(default: %(default)s)")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                        help="override a parameter of the configuration (repeatable)")
    rules = parser.add_argument_group("the tiers' rules")
    rules.add_argument("--run-s", type=float, default=12.0, metavar="S",
                       help="length of each run (default: %(default)s)")
    rules.add_argument("--catch-by", type=float, default=8.0, metavar="S",
                       help="caught: caught for good by this time (default: %(default)s)")
    rules.add_argument("--hold-from", type=float, default=9.0, metavar="S",
                       help="caught: held from this time to the end (default: %(default)s)")
    rules.add_argument("--fast-by", type=float, default=3.0, metavar="S",
                       help="fast: caught for good by this time (default: %(default)s)")
    rules.add_argument("--fast-hold-from", type=float, default=6.0, metavar="S",
                       help="fast: held from this time to the end (default: %(default)s)")
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, metavar="N",
                       help="0: in this process, without Dask; N: a local Dask cluster of N "
                       "worker processes with one thread each (default: in this process up "
                       "to 4000 draws, else one worker per core)")
    where.add_argument("--scheduler", metavar="ADDRESS",
                       help="run on an existing Dask cluster (tcp://host:8786)")


# the most draws a run takes: each holds its parameters and outcomes in this process's
# memory (10^15 asked for 135 PiB, and ended in a traceback)
MAX_DRAWS = 10_000_000
MAX_SEED = 2**63 - 1  # numpy's seeds are non-negative integers


def check_run_arguments(parser: argparse.ArgumentParser, args: argparse.Namespace
                        ) -> Criteria:
    """Refuse what makes no sense, naming it; the tiers' rules as :class:`Criteria`."""
    from pisc_runs.verdict import Criteria

    from pisc_robust.cluster import check_scheduler

    if args.draws < 1:
        parser.error(f"--draws {args.draws}: at least 1")
    if args.draws > MAX_DRAWS:
        parser.error(f"--draws {args.draws}: at most {MAX_DRAWS:,} (each draw is held in "
                     "memory; run more as several seeds)")
    if not 0 <= args.seed <= MAX_SEED:
        parser.error(f"--seed {args.seed}: must be an integer 0 .. {MAX_SEED}")
    if args.workers is not None and args.workers < 0:
        parser.error(f"--workers {args.workers}: 0 (in this process) or more")
    if args.scheduler is not None:
        try:
            check_scheduler(args.scheduler)
        except ValueError as exc:
            parser.error(f"--scheduler {exc}")
    try:
        return Criteria(run_s=args.run_s, catch_by_s=args.catch_by,
                        hold_from_s=args.hold_from, fast_by_s=args.fast_by,
                        fast_hold_from_s=args.fast_hold_from)
    except ValueError as exc:
        parser.error(str(exc))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    add_run_arguments(parser, draws=10000)
    parser.add_argument("--out", type=Path, default=Path("robustness"), metavar="DIR",
                        help="directory of the plot (default: %(default)s)")
    parser.add_argument("--worst", type=int, default=5, metavar="K",
                        help="show each tier's K worst draws (default: %(default)s)")
    parser.add_argument("--witnesses", metavar="CSV|none",
                        help="a pisc_feasibility witness table (--csv) made with the fast "
                        "tier's rules: the fast tier is also measured over its draws that "
                        "have a witness (default: the table shipped for the distribution, "
                        "if any; none: not measured)")
    quiet_threads()
    args = parser.parse_args(argv)
    criteria = check_run_arguments(parser, args)
    if args.worst < 0:
        parser.error(f"--worst {args.worst}: 0 or more")

    from pisc_robust.cluster import chunk_runner, default_workers, describe_runner
    from pisc_sim.configuration import config_path
    from pisc_robust.robustness import CHUNK_DRAWS, evaluate, load_benchmark
    from pisc_control.supervisor import Supervisor
    from pisc_msgs_py.config import ConfigError, parse_overrides
    from pisc_msgs_py.progress import progress_bar

    try:
        config, distribution, draws, plant = load_benchmark(
            args.config, args.set, args.distribution, args.draws, args.seed)
        Supervisor(config.supervisor)  # the gain condition (3.29) and the catch design
        overrides = parse_overrides(args.set)  # (for the worst draws' commands)
    except ConfigError as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return 2
    chunks = -(-args.draws // CHUNK_DRAWS)
    workers = (default_workers(chunks) if args.workers is None and not args.scheduler
               else args.workers)
    print(f"configuration {args.config} ({config_path(args.config)})"
          + "".join(f"\n  --set {item}" for item in args.set))
    print(describe_distribution(distribution))
    print(f"draws {args.draws}, seed {args.seed}; the tiers:")
    print("\n".join(f"  {line}" for line in criteria.describe()))
    start = time.perf_counter()
    try:
        with progress_bar(chunks, "chunk") as bar, \
                chunk_runner(workers, args.scheduler, bar) as map_chunks:
            outcomes = evaluate(config, plant, draws, criteria, args.seed, map_chunks)
    except OSError as exc:  # the scheduler cannot be reached
        print(f"{PROG}: {args.scheduler}: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted; nothing written", file=sys.stderr)
        return 130
    wall = time.perf_counter() - start
    print("\n".join(report(outcomes, criteria)))
    try:
        table = witness_table(args.witnesses, distribution, criteria)
    except ValueError as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return 2
    if table is not None:
        path, meta, witnessed = table
        wit_draws = distribution.draw(meta["draws"], meta["seed"])
        with progress_bar(-(-wit_draws.n // CHUNK_DRAWS), "chunk") as bar, \
                chunk_runner(workers, args.scheduler, bar) as map_chunks:
            on_table = evaluate(config, plant, wit_draws, criteria, meta["seed"], map_chunks)
        print("\n".join(witnessed_report(on_table, witnessed, f"{path.name}: the "
                                          f"{meta['draws']} draws of seed {meta['seed']}")))
    print(f"wall time {wall:.1f} s ({describe_runner(workers, args.scheduler)}, {chunks} "
          f"chunk{'s' if chunks != 1 else ''}), "
          f"{args.draws * criteria.run_s / wall:.0f} simulated s per wall s")
    print("\n".join(worst(outcomes, criteria, draws, distribution, args.config, overrides,
                          args.worst)))
    args.out.mkdir(parents=True, exist_ok=True)
    plot = args.out / PLOT
    plot_success(plot, distribution, draws, outcomes, f"{args.config} on "
                 f"{distribution.name}, {args.draws} draws, seed {args.seed}")
    print(f"plot: {plot}")
    return 0


def describe_distribution(distribution: Distribution) -> str:
    lines = [f"distribution {distribution.name} (digest {distribution.digest})"
             + (f": {distribution.description}" if distribution.description else "")]
    lines += [f"  {name} = {value} (fixed)" for name, value in distribution.plant.items()]
    lines += [f"  {r.describe()}" for r in distribution.ranges]
    return "\n".join(lines)


def percentiles(values: np.ndarray, unit: str, digits: int = 3) -> str:
    if values.size == 0:
        return "none"
    p5, p50, p95 = np.percentile(values, [5, 50, 95])
    return (f"p5 {p5:.{digits}f}, p50 {p50:.{digits}f}, p95 {p95:.{digits}f}, max "
            f"{np.max(values):.{digits}f} {unit}")


def report(outcomes: Outcomes, criteria: Criteria) -> list[str]:
    """The summary lines (everything but the wall time and the worst draws)."""
    from pisc_robust.robustness import binomial_interval
    from pisc_runs.verdict import FAILURES, TIERS

    n = len(outcomes)
    lines = []
    for tier in TIERS:
        wins = int(np.sum(outcomes.passed(tier)))
        low, high = binomial_interval(wins, n)
        kinds = outcomes.kinds(criteria, tier)
        counts = [(int(np.sum(kinds == k)), name) for k, name in enumerate(FAILURES)]
        failures = ", ".join(f"{name} {count}" for count, name in counts if count)
        lines.append(f"{tier:6s} {wins} of {n} = {100 * wins / n:.2f} % (95 % interval "
                     f"{100 * low:.2f} .. {100 * high:.2f} %); failures: "
                     + (failures or "none"))
    caught = outcomes.caught_at_s[np.isfinite(outcomes.caught_at_s)]
    lines.append(f"catch time ({caught.size} caught for good): {percentiles(caught, 's', 2)}")
    lines.append(f"largest |x| (all draws): {percentiles(outcomes.largest_x_m, 'm')}")
    rms = outcomes.hold_setpoint_rms_a[outcomes.caught]
    lines.append(f"hold's current set-point RMS from {criteria.hold_from_s:g} s (caught): " + (
        "none" if rms.size == 0 else
        f"median {np.median(rms):.4f} A, p95 {np.percentile(rms, 95):.4f} A"))
    return lines


def witness_table(choice: str | None, distribution: Distribution, criteria: Criteria
                  ) -> tuple[Path, dict[str, Any], np.ndarray] | None:
    """The witness table to measure the fast tier over: (path, header, witnessed mask);
    None for ``none``, or by default when none is shipped for the distribution.

    A table must be of the distribution's draws (its digest) and made with the fast
    tier's rules (catch by, held from); ValueError names what differs."""
    from pisc_analysis.witnesses import read_witness_csv
    from pisc_msgs_py.config import package_dir

    if choice == "none":
        return None
    if choice is None:
        shipped = sorted((package_dir("pisc_robust", "distributions") / "witnesses")
                         .glob(f"{distribution.name}-*.csv"))
        for path in shipped:
            meta, _ = read_witness_csv(path)
            if (meta["distribution_digest"] == distribution.digest
                    and (meta["catch_by_s"], meta["hold_from_s"])
                    == (criteria.fast_by_s, criteria.fast_hold_from_s)):
                choice = str(path)
                break
        else:
            return None
    path = Path(choice)
    if not path.is_file():
        raise ValueError(f"--witnesses {choice}: no such file")
    meta, rows = read_witness_csv(path)
    if meta["distribution_digest"] != distribution.digest:
        raise ValueError(f"--witnesses {path}: its draws are of a distribution with digest "
                         f"{meta['distribution_digest']}, not {distribution.name}'s "
                         f"{distribution.digest}")
    rules = (meta["catch_by_s"], meta["hold_from_s"])
    if rules != (criteria.fast_by_s, criteria.fast_hold_from_s):
        raise ValueError(f"--witnesses {path}: made for a catch by {rules[0]:g} s held from "
                         f"{rules[1]:g} s, not the fast tier's {criteria.fast_by_s:g} s and "
                         f"{criteria.fast_hold_from_s:g} s")
    if meta["searched"] != meta["draws"]:
        raise ValueError(f"--witnesses {path}: searched {meta['searched']} of its "
                         f"{meta['draws']} draws; the fast tier is measured over all of them")
    witnessed = np.zeros(meta["draws"], dtype=bool)
    for row in rows:
        witnessed[row["draw"]] = row["feasible"]
    return path, meta, witnessed


def witnessed_report(outcomes: Outcomes, witnessed: np.ndarray, source: str) -> list[str]:
    """The fast tier over the draws a feasibility study found a witness for."""
    from pisc_robust.robustness import binomial_interval

    n = int(np.sum(witnessed))
    wins = int(np.sum(outcomes.fast & witnessed))
    if n == 0:
        return [f"fast over witnessed draws: {source} has no witness"]
    low, high = binomial_interval(wins, n)
    return [f"fast over the {n} witnessed of {len(outcomes)} draws ({source}): {wins} = "
            f"{100 * wins / n:.2f} % (95 % interval {100 * low:.2f} .. {100 * high:.2f} %); "
            f"safe {int(np.sum(outcomes.safe))} of {len(outcomes)}, fast over all "
            f"{int(np.sum(outcomes.fast))}"]


def worst(outcomes: Outcomes, criteria: Criteria, draws: Draws, distribution: Distribution,
          config: str, overrides: dict[str, Any], k: int) -> list[str]:
    """Each tier's ``k`` worst failures among the draws that pass the tiers before it,
    each with its values and the command that reruns it."""
    from pisc_robust.robustness import rerun_command
    from pisc_runs.verdict import TIERS

    lines = []
    below = np.ones(len(outcomes), dtype=bool)
    for tier in TIERS:
        badness = outcomes.badness(criteria, tier) * below
        order = [int(i) for i in np.argsort(-badness, kind="stable")[:k] if badness[i] > 0]
        below = below & outcomes.passed(tier)
        if not k:
            continue
        if not order:
            lines.append(f"worst draws, {tier}: no failure")
            continue
        lines.append(f"worst {len(order)} draws, {tier} (the graph draws its own "
                     "measurement noise):")
        for i in order:
            values = {name: float(f"{v:.6g}") for name, v in draws.one(i).items()}
            lines.append(f"  draw {i}: {outcomes.why(i, criteria, tier)}")
            lines += textwrap.wrap(", ".join(f"{name}={v:g}" for name, v in values.items()),
                                   width=100, initial_indent="    ", subsequent_indent="    ",
                                   break_on_hyphens=False)
            lines.append("    " + rerun_command(config, overrides, distribution.plant, values))
    return lines


def plot_success(path: Path, distribution: Distribution, draws: Draws, outcomes: Outcomes,
                 title: str) -> None:
    """Success rate in 10 bins of each varied parameter's value, one panel each."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FixedLocator, FuncFormatter, MaxNLocator, NullFormatter

    from pisc_robust.robustness import success_by_value
    from pisc_robust.uncertainty import unit_of

    from pisc_runs.verdict import TIERS

    ranges = distribution.ranges
    columns = 4
    rows = -(-len(ranges) // columns)
    fig, axes = plt.subplots(rows, columns, figsize=(3.3 * columns, 2.2 * rows + 0.9),
                             sharey=True, squeeze=False)
    rates = outcomes.rates()
    short = FuncFormatter(lambda v, _: f"{v:.3g}")
    for ax, r in zip(axes.flat, ranges, strict=False):
        log = r.kind == "factor"
        for color, tier in zip(("C2", "C0", "C1"), TIERS, strict=True):
            edges, rate, count = success_by_value(draws.values[r.name], outcomes.passed(tier),
                                                  log=log, span=r.value_range)
            percent = 100 * np.nan_to_num(rate)
            ax.stairs(percent, edges, color=color, lw=1.2, label=tier)
        if log:  # factor ranges: log axis, ticks at the ends and the nominal value
            ax.set_xscale("log")
            ax.xaxis.set_major_locator(FixedLocator([*r.value_range, r.nominal]))
            ax.xaxis.set_minor_formatter(NullFormatter())
        else:
            ax.xaxis.set_major_locator(MaxNLocator(4))
        ax.xaxis.set_major_formatter(short)
        ax.set_xlim(edges[0], edges[-1])
        unit = unit_of(r.name)
        ax.set_xlabel(r.name + (f" [{unit}]" if unit else ""), fontsize=8)
        ax.tick_params(labelsize=7)
        ax.set_ylim(0, 102)
        ax.set_yticks([0, 25, 50, 75, 100])
        ax.grid(alpha=0.3)
    axes.flat[0].legend(fontsize=7, loc="lower left")
    for ax in axes[:, 0]:
        ax.set_ylabel("draws passing [%]", fontsize=8)
    for ax in list(axes.flat)[len(ranges):]:
        ax.set_visible(False)
    overall = ", ".join(f"{tier} {100 * rates[tier]:.1f} %" for tier in TIERS)
    fig.suptitle(f"{title}\neach tier in 10 bins of each parameter's value; all draws: "
                 f"{overall}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
