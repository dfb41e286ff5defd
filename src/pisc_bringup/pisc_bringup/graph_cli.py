"""Run the PISC graph against the simulator, record it, and summarise the run.

``pisc_graph`` runs :func:`pisc_bringup.graph.run_graph`, whose module says how a run goes.

    pisc_graph [--config default|thesis|FILE] [--x0 M] [--duration S]
               [--clock lockstep|wall] [--processes] [--executor events|single|multi]
               [--driver PORT] [--realtime PRIORITY] [--bag DIR] [--set NAME=VALUE ...]
               [--plant-config default|thesis|FILE] [--plant-set NAME=VALUE ...]
               [--markers] [--launch FILE] [--tier safe|caught|fast]

Exit status: 0 when the run passes the tier ``--tier`` names (default ``caught``: caught
for good by 8 s and held from 9 s to the end), 1 when it does not, 2 bad configuration or
the graph did not run; an experiment run (``experiment.kind``) exits 0 when it ran
without a fault, 1 when it faulted. A publisher of another node on a topic of the graph
stops the run with 3, SIGINT or SIGTERM with 130 or 143, a serial port that went away and
did not come back within ``--port-retry`` seconds with 4
(:mod:`pisc_bringup.run_guard`).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Any

from pisc_bag.bag import BagError
from pisc_bringup.dds import dds_environment
from pisc_bringup.graph import GraphError, RecorderDied, RunOptions, RunResult, run_graph
from pisc_bringup.run_guard import RunStopped
from pisc_bringup.run_start import EXECUTORS, MAX_DOMAIN_ID, plant_description
from pisc_msgs_py.config import ConfigError, parse_overrides

__all__ = ["main"]


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="pisc_graph", description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", default="default",
                        help="named configuration (default, thesis) or a parameter file")
    parser.add_argument("--x0", type=float, help="initial cart position [m]")
    parser.add_argument("--scene", help="a scene (pisc_scene list): its configuration, "
                        "overrides and duration; --config is then ignored")
    parser.add_argument("--duration", type=float,
                        help="run length [s] (default: the scene's, else 10)")
    parser.add_argument("--clock", choices=("lockstep", "wall"),
                        help="lockstep (default) or wall; --driver runs on the wall clock")
    parser.add_argument("--driver", metavar="PORT",
                        help="run the serial driver on PORT (the rig, or the device "
                        "pisc_virtual_rig prints) instead of the simulated plant")
    parser.add_argument("--processes", action="store_true",
                        help="one process per node through the console entry points")
    parser.add_argument("--executor", choices=sorted(EXECUTORS), default="events",
                        help="executor of the nodes in one process (default: events)")
    parser.add_argument("--realtime", type=int, default=0, metavar="PRIORITY",
                        help="SCHED_FIFO priority 1-99 for the graph and its processes "
                        "(needs CAP_SYS_NICE; 0 = normal scheduling)")
    parser.add_argument("--bag", type=Path,
                        help="bag directory (default ./bags/run-<config>-<clock>-x0_<x0>-<time>)")
    parser.add_argument("--domain-id", type=int,
                        help=f"ROS domain id 0-{MAX_DOMAIN_ID} (default: environment)")
    parser.add_argument("--port-retry", type=float, default=3.0, metavar="S",
                        help="with --driver: how long a serial port that went away may "
                        "take to come back before the run ends, exit status 4 (default: "
                        "%(default)s)")
    parser.add_argument("--record", action="append", metavar="TOPIC",
                        help="record this topic (repeatable; default: the scene's list, else "
                        "every topic); the run's own topics are always recorded")
    parser.add_argument("--launch", metavar="FILE",
                        help="the launch file declaring the graph (default: the package's "
                        "sim.launch.xml, or rig.launch.xml with --driver)")
    parser.add_argument("--markers", action="store_true",
                        help="also run the markers node (the rig on /pisc/markers for RViz "
                        "and Foxglove, docs/markers.md) and record its topic")
    parser.add_argument("--foxglove", type=int, nargs="?", const=8765, metavar="PORT",
                        help="serve the run live to Foxglove on ws://127.0.0.1:PORT "
                        "(default 8765; docs/foxglove.md)")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                        help="override a parameter, e.g. --set swing_up.k_v=0.1")
    parser.add_argument("--plant-config", metavar="CONFIG",
                        help="model error: the plant's own configuration (a name or a "
                        "parameter file; default: the controllers')")
    parser.add_argument("--plant-set", action="append", default=[], metavar="NAME=VALUE",
                        help="model error: override a parameter of the plant only (after "
                        "--set), e.g. --plant-set motor.resistance_ohm=18.2")
    parser.add_argument("--tier", choices=("safe", "caught", "fast"), default="caught",
                        help="the benchmark's tier whose verdict is the result and the exit "
                        "status (default: %(default)s: caught for good by 8 s, held from 9 s)")
    return parser


def _options(args: argparse.Namespace, parser: argparse.ArgumentParser) -> RunOptions | int:
    """The run's options from the command line (and the scene it names), or the exit
    status of a command line that cannot run."""
    try:
        overrides = parse_overrides(args.set)
    except ConfigError as exc:
        parser.error(str(exc))
    plant_overrides: dict[str, Any] = {}
    for item in args.plant_set:
        try:
            plant_overrides.update(parse_overrides([item]))
        except ConfigError:
            parser.error(f"--plant-set {item!r}: expected NAME=VALUE")
    if args.x0 is not None:
        overrides["initial.x_m"] = args.x0
    config, duration = args.config, args.duration
    record = tuple(args.record) if args.record else None
    if args.scene is not None:
        from pisc_sim.scene import load_scene

        try:
            scene = load_scene(args.scene, overrides, plant_overrides)
        except ConfigError as exc:
            print(f"pisc_graph: invalid scene: {exc}", file=sys.stderr)
            return 2
        if not scene.closed_loop:
            print(f"pisc_graph: scene {scene.name} has no controller (controller: "
                  f"{scene.controller}); run it with pisc_scene run", file=sys.stderr)
            return 2
        # the scene's plant: block, then --plant-set
        config, overrides = scene.configuration, scene.overrides
        plant_overrides = scene.plant_overrides
        duration = duration if duration is not None else scene.duration_s
        record = record if record is not None else scene.record
    clock = args.clock or ("wall" if args.driver else "lockstep")
    if args.realtime:
        try:
            # threads and processes started from here on inherit the policy
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.realtime))
        except (OSError, AttributeError) as exc:
            print(f"pisc_graph: --realtime {args.realtime}: cannot use SCHED_FIFO ({exc})",
                  file=sys.stderr)
            return 2
    return RunOptions(config=config, overrides=overrides,
                      duration_s=duration if duration is not None else 10.0,
                      clock=clock, processes=args.processes,
                      executor=args.executor, bag_dir=args.bag,
                      domain_id=args.domain_id, driver_port=args.driver, record=record,
                      plant_config=args.plant_config, plant_overrides=plant_overrides,
                      markers=args.markers, launch=args.launch,
                      port_retry_s=args.port_retry, foxglove_port=args.foxglove)


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    # this process's nodes and every process it starts discover on this machine only and
    # use PISC's Fast DDS profile, unless the environment says otherwise (docs/safety.md,
    # docs/architecture.md); before this process's first DDS participant, which reads it
    dds_environment(os.environ)
    options = _options(args, parser)
    if isinstance(options, int):
        return options
    try:
        result = run_graph(options)
    except ConfigError as exc:
        print(f"pisc_graph: invalid configuration: {exc}", file=sys.stderr)
        return 2
    except RecorderDied as exc:
        if exc.summary is not None:
            print(f"bag: {exc.bag_dir} (what was recorded before pisc_record died)")
            print(exc.summary.format(args.tier))
        print("\n".join(f"pisc_graph: {line}" for line in str(exc).splitlines()),
              file=sys.stderr)
        return 2
    except RunStopped as exc:
        if exc.summary is not None:
            print(f"bag: {exc.bag_dir}")
            print(exc.summary.format(args.tier))
        first, *rest = str(exc).splitlines()
        print(f"{'stopped':<23}{first}")
        print("\n".join(f"pisc_graph: {line}" for line in [first, *rest]), file=sys.stderr)
        return exc.status
    except (GraphError, BagError) as exc:
        print(f"pisc_graph: {exc}", file=sys.stderr)
        return 2
    return _report(options, result, args.tier)


def _report(options: RunOptions, result: RunResult, tier: str) -> int:
    """Print the run and its summary; the exit status of its verdict."""
    names = {"events": "EventsExecutor", "single": "SingleThreadedExecutor",
             "multi": "MultiThreadedExecutor"}
    mode = ("separate processes" if options.processes
            else f"one process, {names[options.executor]}")
    against = "" if options.driver_port is None else f", serial driver on {options.driver_port}"
    x0 = options.initial_x_m
    plant = plant_description(options)
    print(f"PISC run: config {options.config}, {options.clock} clock, {mode}{against}, "
          f"x0 = {'from file' if x0 == 'file' else x0}"
          f"{'' if plant is None else f'; plant: {plant}'}")
    if result.processes:
        print(f"entry points: {', '.join(result.processes)}")
    loop = ("" if result.loop_s is None else
            f"; the loop: {options.duration_s:g} s in {result.loop_s:.2f} s")
    print(f"bag: {result.bag_dir} ({sum(result.recorded.values())} messages, "
          f"{result.wall_s:.1f} s wall{loop})")
    print(result.summary.format(tier, result.experiment))
    if result.experiment != "none":  # nothing is to be caught: the run must not fault
        return 1 if result.summary.faults else 0
    return 0 if result.summary.passed[tier] else 1



if __name__ == "__main__":
    raise SystemExit(main())
