"""The command: ``pisc_virtual_rig``: the simulated rig behind a pseudo-terminal, acting as
its PIC16F877A (:mod:`pisc_plant.virtual_rig`)."""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import sys
from typing import Any

from pisc_msgs_py.config import ConfigError, parse_overrides
from pisc_plant.firmware import DEFAULT_WATCHDOG_MS, Firmware
from pisc_plant.plant import Plant
from pisc_plant.rig_faults import RigFaults
from pisc_plant import virtual_rig
from pisc_plant.virtual_rig import Rig, load_plant

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="pisc_virtual_rig",
                                     description=virtual_rig.__doc__.split("\n\n")[0])
    parser.add_argument("--params-file", help="ROS 2 parameter file (plant sections and "
                        "initial.*), e.g. pisc_bringup's config/default.yaml")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    parser.add_argument("--x0", type=float, help="initial cart position [m]")
    parser.add_argument("--drop-rate", type=float, default=0.0)
    parser.add_argument("--flip-rate", type=float, default=0.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--log", help="CSV of the true state each period")
    parser.add_argument("--realtime", type=int, default=0, metavar="PRIORITY",
                        help="run under SCHED_FIFO at this priority (1-99) so that a loaded "
                        "machine does not delay frames, as the PIC's timer never does; "
                        "needs CAP_SYS_NICE (0 = normal scheduling)")
    parser.add_argument("--no-control", action="store_true",
                        help="do not read JSON requests from standard input")
    parser.add_argument("--watchdog-ms", type=float, default=DEFAULT_WATCHDOG_MS,
                        metavar="MS",
                        help="command watchdog: no command byte for this long applies 0 V "
                        "until the next byte (checked at each 5 ms tick, so 0 V comes "
                        "within one period after it); 0 = none, the thesis's firmware "
                        f"(default {DEFAULT_WATCHDOG_MS:g} ms: 10 periods)")
    parser.add_argument("--hold", action="store_true",
                        help="hold the cart and pendulum at the initial state, as a hand "
                        "would, until the first command byte of a nonzero voltage lets go: "
                        "a run started at a state (near upright, to be caught) starts there "
                        "however long the graph takes to come up; frames are sent meanwhile")
    args = parser.parse_args(argv)
    try:
        if not (math.isfinite(args.watchdog_ms) and 0.0 <= args.watchdog_ms <= 60_000.0):
            raise ValueError(f"--watchdog-ms {args.watchdog_ms:g} must lie in [0, 60000] ms "
                             "(0 = no watchdog)")
        overrides = parse_overrides(args.set)
        if args.x0 is not None:
            overrides["initial.x_m"] = args.x0
        config, initial = load_plant(args.params_file, overrides)
        faults = RigFaults()
        faults.update({"drop_rate": args.drop_rate, "flip_rate": args.flip_rate}, 0.0)
    except (ConfigError, ValueError) as exc:
        print(f"pisc_virtual_rig: {exc}", file=sys.stderr)
        return 2
    if args.realtime:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.realtime))
        except (OSError, AttributeError) as exc:
            print(f"pisc_virtual_rig: --realtime {args.realtime}: cannot use SCHED_FIFO "
                  f"({exc}); running with normal scheduling", file=sys.stderr)
    plant = Plant(config)
    state = plant.initial_state(initial.x_m, initial.x_dot_mps, initial.theta_rad,
                                initial.theta_dot_radps)
    # a large buffer: a flush that waits for the disk must not delay a frame
    log = open(args.log, "w", buffering=1 << 20) if args.log else None  # noqa: SIM115
    if log is not None:
        log.write("t_s,monotonic_s,unix_s,x,x_dot,theta,theta_dot,i,applied_v\n")
    rig = Rig(Firmware(plant, state, watchdog_s=args.watchdog_ms * 1e-3, held=args.hold),
              faults, args.seed, log)

    def stop(signum: int, frame: Any) -> None:
        rig.running = False

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    print(f"device {rig.device}", flush=True)
    try:
        rig.run(None if args.no_control else sys.stdin.fileno(), sys.stdout)
    finally:
        print(json.dumps(rig.status()), flush=True)
        rig.close()
        if log is not None:
            log.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
