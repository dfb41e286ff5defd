"""pisc_tune: search the controllers' parameters over a distribution, safe first, then
the catches (the benchmark's tiers: a caught draw counts one, a fast draw two), with
Optuna, and write the best as a parameter file (docs/robustness.md).

    pisc_tune default --trials 40 --draws 400 --seed 1 --out tuned.yaml

Every trial scores a candidate on the same draws (the seed's). The study is kept in
``--storage`` (default: an SQLite file beside ``--out``); the same command resumes it,
and a storage that holds another tuning (distribution, draws, seed, space) is refused.
Interrupted (Ctrl-C), it says how many trials the study keeps and exits 130; the same
command resumes from there. ``--space`` defaults to the shipped space for the
configuration's settings (:func:`pisc_robust.tune_space.space_for`).
"""

from __future__ import annotations

import argparse
import datetime
import shlex
import sys
from pathlib import Path

PROG = "pisc_tune"


def main(argv: list[str] | None = None) -> int:
    from pisc_robust.robustness_args import (
        add_run_arguments,
        check_run_arguments,
        quiet_threads,
    )

    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    add_run_arguments(parser, draws=400)
    parser.add_argument("--space", metavar="FILE",
                        help="the search space: a shipped name or a file (default: the "
                        "shipped space for the configuration's law and settings)")
    parser.add_argument("--trials", type=int, default=40, metavar="N",
                        help="complete trials the study should hold (default: %(default)s)")
    parser.add_argument("--sampler", choices=("tpe", "cmaes"), default="tpe",
                        help="Optuna's sampler, seeded by --seed (default: %(default)s)")
    parser.add_argument("--aim", choices=("safe", "fast"), default="safe",
                        help="what the score puts first: safe (then the catches), or fast "
                        "(the draws caught by the fast tier, each safe; then the safe ones) "
                        "(default: %(default)s)")
    parser.add_argument("--storage", metavar="URL",
                        help="Optuna storage (default: sqlite:///<--out without .yaml>.db)")
    parser.add_argument("--nominal-starts", type=int, default=0, metavar="N",
                        help="N starts at rest, x0 evenly in [-0.1, 0.1] m, on the "
                        "configuration's own plant, must all be fast; each one that is not "
                        "costs as much as 1/N of half the draws' catches (default: none)")
    parser.add_argument("--hold-rms", type=float, default=0.0, metavar="A",
                        help="with --nominal-starts: a start whose set-point RMS from "
                        "--fast-hold-from on is over this is not fast (default: no limit)")
    parser.add_argument("--out", type=Path, default=Path("tuned.yaml"), metavar="FILE",
                        help="the tuned parameter file (default: %(default)s)")
    quiet_threads()
    args = parser.parse_args(argv)
    criteria = check_run_arguments(parser, args)
    if args.trials < 1:
        parser.error(f"--trials {args.trials}: at least 1")
    command = shlex.join([PROG, *(sys.argv[1:] if argv is None else argv)])

    from pisc_robust.cluster import chunk_runner, describe_runner, workers_for
    from pisc_sim.configuration import load_graph_config
    from pisc_robust.robustness import CHUNK_DRAWS
    from pisc_robust.robustness_report import describe_distribution
    from pisc_robust.tune import Tuning, provenance, trials_kept, tune, tuned_file_text
    from pisc_robust.tune_space import load_space, space_for
    from pisc_robust.uncertainty import load_distribution
    from pisc_control.supervisor import Supervisor
    from pisc_msgs_py.config import ConfigError, parse_overrides
    from pisc_msgs_py.progress import progress_bar

    storage = args.storage or f"sqlite:///{args.out.with_suffix('.db')}"
    try:
        overrides = parse_overrides(args.set)
        config, flat = load_graph_config(args.config, overrides)
        Supervisor(config.supervisor)  # the gain condition (3.29) and the catch design
        distribution = load_distribution(args.distribution, config)
        space = load_space(args.space or space_for(flat), flat)
        tuning = Tuning(args.config, overrides, distribution, space, args.draws, args.seed,
                        args.sampler, criteria, args.nominal_starts, args.hold_rms,
                        args.aim)
    except ConfigError as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return 2
    chunks = -(-args.draws // CHUNK_DRAWS)
    workers = workers_for(chunks, args.workers, args.scheduler)
    print(f"configuration {args.config}; " + describe_distribution(distribution))
    print(f"space {space.name} (digest {space.digest})"
          + "".join(f"\n  {d.describe()}" for d in space.dimensions))
    print(f"{args.trials} trials x {args.draws} draws (seed {args.seed}, the same draws for "
          f"every trial), sampler {args.sampler}, {describe_runner(workers, args.scheduler)}; "
          f"study in {storage}")
    args.out.parent.mkdir(parents=True, exist_ok=True)  # and the default storage's
    try:
        with progress_bar(args.trials, "trial", "best -") as bar, \
                chunk_runner(workers, args.scheduler) as map_chunks:

            def progress(done: int, best: dict[str, float]) -> None:
                bar.to(done)
                bar.describe("best " + "/".join(f"{100 * best.get(t, 0.0):.1f}"
                                                for t in ("safe", "caught", "fast")) + " %")

            result = tune(tuning, args.trials, storage, map_chunks, progress)
    except ConfigError as exc:  # includes a storage of another tuning
        print(f"{PROG}: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # the scheduler cannot be reached
        print(f"{PROG}: {args.scheduler}: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"\n{PROG}: interrupted; {trials_kept(tuning, storage)} trials kept in "
              f"{storage}, rerun the same command to resume", file=sys.stderr)
        return 130
    date = datetime.date.today().isoformat()
    print("\n".join(provenance(result, tuning, command, date, storage)))
    args.out.write_text(tuned_file_text(result, tuning, command, date, storage))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
