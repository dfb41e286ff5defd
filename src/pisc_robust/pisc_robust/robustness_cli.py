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
import sys
import time
from pathlib import Path

from pisc_robust.robustness_args import add_run_arguments, check_run_arguments, quiet_threads
from pisc_robust.robustness_report import (
    describe_distribution,
    plot_success,
    report,
    witness_table,
    witnessed_report,
    worst,
)

PROG = "pisc_robustness"
PLOT = "success_by_parameter.png"


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

    from pisc_robust.cluster import chunk_runner, describe_runner, workers_for
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
    workers = workers_for(chunks, args.workers, args.scheduler)
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


if __name__ == "__main__":
    raise SystemExit(main())
