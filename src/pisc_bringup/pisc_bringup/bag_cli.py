"""pisc_bag: repair, play, regression-replay and analyse PISC bags.

    pisc_bag repair BAG                       finish a bag whose recorder was killed
    pisc_bag play BAG [--rate R]              publish its topics on /clock sim time
    pisc_bag replay BAG [--nodes] [--set NAME=VALUE ...] [--tolerance T]
                                              recompute every controller output, compare
    pisc_bag analyse BAG [--out DIR] [--overlay BAG2]
                                              metrics, PNG plots and the thesis CSV
    pisc_bag animate BAG [--out FILE.gif|FILE.mp4] [--overlay BAG2]
                                              the run drawn as the rig, frame by frame

Exit status: 0 success (replay: every output reproduced), 1 replay mismatch, 2 a bag
that cannot be read or bad arguments; errors name the file and what is wrong.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from types import ModuleType

from pisc_bag.bag import BagError
from pisc_msgs_py.config import ConfigError

__all__ = ["main"]

# Each subcommand's module (add_arguments(parser), run(args) -> int), imported only when
# that subcommand is chosen: `analyse` need not load rclpy (play, replay) nor matplotlib's
# animation writers (animate). The imports are written out, not named by strings, so that
# the package-boundary test sees them.
def _repair() -> ModuleType:
    from pisc_bag import repair_cmd
    return repair_cmd


def _play() -> ModuleType:
    from pisc_runs import play_cmd
    return play_cmd


def _replay() -> ModuleType:
    from pisc_bringup import replay_cmd
    return replay_cmd


def _analyse() -> ModuleType:
    from pisc_runs import analyse_cmd
    return analyse_cmd


def _animate() -> ModuleType:
    from pisc_runs import animate_cmd
    return animate_cmd


# subcommand -> (its module, imported when chosen; its help)
SUBCOMMANDS: dict[str, tuple[Callable[[], ModuleType], str]] = {
    "repair": (_repair, "finish a bag whose recorder was killed"),
    "play": (_play, "publish a bag's topics on /clock simulated time"),
    "replay": (_replay, "recompute every controller output of a bag and compare, stamp by "
                        "stamp"),
    "analyse": (_analyse, "metrics, plots like the thesis's Figs. 6.3-6.8 and the CSV log of "
                          "a bag"),
    "animate": (_animate, "the run drawn as the rig (cart, pendulum, track, mode, force, "
                          "time) to a GIF or an MP4"),
}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = argparse.ArgumentParser(prog="pisc_bag", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    chosen = next((a for a in argv if not a.startswith("-")), None)
    runners: dict[str, Callable[[argparse.Namespace], int]] = {}
    for name, (load, help_text) in SUBCOMMANDS.items():
        sub_parser = sub.add_parser(name, help=help_text, description=help_text)
        if name == chosen:
            module = load()
            module.add_arguments(sub_parser)
            runners[name] = module.run
    args = parser.parse_args(argv)
    # loaded by the commands that run nodes (replay --nodes)
    start = sys.modules.get("pisc_bringup.run_start")
    errors = (BagError,) if start is None else (BagError, start.GraphError)
    try:
        return runners[args.command](args)
    except errors as exc:
        print(f"pisc_bag {args.command}: {exc}", file=sys.stderr)
        return 2
    except ConfigError as exc:
        print(f"pisc_bag {args.command}: invalid configuration: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # output piped into e.g. head, which stopped reading
        sys.stderr.close()
        return 1


if __name__ == "__main__":
    raise SystemExit(main())
