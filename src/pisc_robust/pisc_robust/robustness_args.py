"""The command line the robustness benchmark's commands share (``pisc_robustness``,
``pisc_tune``): the configuration, the distribution and its draws, the tiers' rules and
where to run (:func:`add_run_arguments`, checked by :func:`check_run_arguments`), and the
kernel's threads set to wait passively (:func:`quiet_threads`)."""

from __future__ import annotations

import argparse
import os
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from pisc_runs.verdict import Criteria

__all__ = ["MAX_DRAWS", "MAX_SEED", "add_run_arguments", "check_run_arguments",
           "quiet_threads"]


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
