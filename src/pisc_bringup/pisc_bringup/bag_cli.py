"""pisc_bag: repair, play, regression-replay and analyse PISC bags.

    pisc_bag repair BAG                       finish a bag whose recorder was killed
    pisc_bag play BAG [--rate R] [--loop]      publish its topics on /clock sim time
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
import importlib
import sys
from collections.abc import Callable

from pisc_bag.bag import BagError
from pisc_msgs_py.config import ConfigError

__all__ = ["main"]

# subcommand -> module with add_arguments(parser) and run(args) -> int
SUBCOMMANDS = {
    "repair": ("pisc_bag.repair_cmd", "finish a bag whose recorder was killed"),
    "play": ("pisc_runs.play_cmd", "publish a bag's topics on /clock simulated time"),
    "replay": ("pisc_bringup.replay_cmd", "recompute every controller output of a bag and "
                                      "compare, stamp by stamp"),
    "analyse": ("pisc_runs.analyse_cmd", "metrics, plots like the thesis's Figs. 6.3-6.8 and "
                                         "the CSV log of a bag"),
    "animate": ("pisc_runs.animate_cmd", "the run drawn as the rig (cart, pendulum, track, "
                                        "mode, force, time) to a GIF or an MP4"),
}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = argparse.ArgumentParser(prog="pisc_bag", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    # only the chosen subcommand's module is imported: `analyse` need not load rclpy
    # (play, replay) nor matplotlib's animation writers (animate)
    chosen = next((a for a in argv if not a.startswith("-")), None)
    runners: dict[str, Callable[[argparse.Namespace], int]] = {}
    for name, (module_name, help_text) in SUBCOMMANDS.items():
        sub_parser = sub.add_parser(name, help=help_text, description=help_text)
        if name == chosen:
            module = importlib.import_module(module_name)
            module.add_arguments(sub_parser)
            runners[name] = module.run
    args = parser.parse_args(argv)
    graph = sys.modules.get("pisc_bringup.graph")  # loaded by the commands that run one
    errors = (BagError,) if graph is None else (BagError, graph.GraphError)
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
