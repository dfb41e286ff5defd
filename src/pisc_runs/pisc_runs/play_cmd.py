"""``pisc_bag play BAG``: publish a bag's topics on simulated time (:mod:`pisc_runs.play`)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from pisc_runs.play import play_bag

__all__ = ["add_arguments", "run"]


def add_arguments(parser: Any) -> None:
    """``pisc_bag play`` options."""
    parser.add_argument("bag", type=Path, help="bag directory")
    parser.add_argument("--rate", type=float, default=1.0,
                        help="speed relative to the recording (default 1; 0: as fast as "
                             "possible)")
    parser.add_argument("--topic", action="append", default=None,
                        help="play only this topic (repeatable; default: all but /clock)")
    parser.add_argument("--wait-subscribers", type=float, default=2.0, metavar="S",
                        help="wait up to S seconds for a subscriber on every played topic")
    parser.add_argument("--domain-id", type=int, help="ROS domain id (default: environment)")
    parser.add_argument("--foxglove", type=int, nargs="?", const=8765, metavar="PORT",
                        help="also serve the played messages to Foxglove on "
                        "ws://127.0.0.1:PORT (default 8765; docs/foxglove.md)")


def run(args: Any) -> int:
    started = time.monotonic()
    counts = play_bag(args.bag, args.rate, args.topic, args.wait_subscribers, args.domain_id,
                      args.foxglove)
    print(f"played {args.bag} in {time.monotonic() - started:.1f} s of wall time:")
    for topic, count in counts.items():
        print(f"  {topic} {count}")
    return 0
