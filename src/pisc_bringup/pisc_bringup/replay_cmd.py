"""pisc_bag replay: the command around :mod:`pisc_runs.replay` (through the cores) and
:mod:`pisc_bringup.replay_node` (through the nodes over topics); kept apart from both so
that neither imports the other back."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from pisc_bag.bag import BagError
from pisc_bag.run_files import PARAMS_FILE
from pisc_runs.replay import replay_bag
from pisc_msgs_py.config import parse_overrides

__all__ = ["add_arguments", "run"]


def add_arguments(parser: Any) -> None:
    """``pisc_bag replay`` options."""
    parser.add_argument("bag", type=Path, help="bag directory")
    parser.add_argument("--nodes", action="store_true",
                        help="through the estimator, supervisor and current-loop nodes over "
                             "topics (default: through their cores)")
    parser.add_argument("--config", help="configuration to replay with (default: the bag's "
                                         f"{PARAMS_FILE}); a name or a parameter file")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                        help="change a parameter, e.g. --set swing_up.k_x=6.3")
    parser.add_argument("--tolerance", type=float, default=0.0,
                        help="largest accepted |recorded - recomputed| (default 0: same bits)")
    parser.add_argument("--domain-id", type=int, help="ROS domain id for --nodes")
    parser.add_argument("--executor", choices=("events", "single", "multi"), default="events",
                        help="executor of the nodes for --nodes (default: events, as "
                             "pisc_graph runs them)")


def run(args: Any) -> int:
    """Replay, print the report; 0 reproduced, 1 mismatch."""
    overrides = parse_overrides(args.set)
    if args.tolerance < 0 or not math.isfinite(args.tolerance):
        raise BagError(f"--tolerance {args.tolerance}: expected a finite value >= 0")
    if args.nodes:
        from pisc_bringup.replay_node import replay_nodes

        report = replay_nodes(args.bag, args.config, overrides, args.tolerance, args.domain_id,
                              executor_name=args.executor)
    else:
        report = replay_bag(args.bag, args.config, overrides, args.tolerance)
    print(report.format())
    return 0 if report.reproduced else 1
