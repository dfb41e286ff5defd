"""``pisc_bag repair BAG``: finish a bag whose recorder was killed (see :func:`repair_bag`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from pisc_bag.bag_repair import repair_bag

__all__ = ["add_arguments", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bag", type=Path, help="bag directory holding one unfinished .mcap")


def run(args: argparse.Namespace) -> int:
    print(repair_bag(args.bag).format())
    return 0
