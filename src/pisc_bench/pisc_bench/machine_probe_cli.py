"""One bare timer loop, pinned to a CPU, writing how late it woke at each deadline
(:func:`pisc_bench.machine_probe.run_loop`; :class:`pisc_bench.machine_probe.Probes`
starts one per CPU beside a soak).

    python -m pisc_bench.machine_probe_cli --cpu N [--priority P] [--period 0.005] --out FILE

It says ``ready`` on standard output, runs until SIGTERM or SIGINT (or
``--max-duration``) and writes ``FILE`` (numpy ``.npz``: ``lateness_ns`` per deadline,
``start_unix_ns``, ``period_ns``, ``cpu``, ``priority``).
"""

from __future__ import annotations

import argparse
import math
import os
import signal
import sys
from pathlib import Path

import numpy as np

from pisc_bench.machine_probe import run_loop

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="machine_probe", description=__doc__.split("\n\n")[0])
    parser.add_argument("--cpu", type=int, required=True, help="the CPU to pin the loop to")
    parser.add_argument("--priority", type=int, default=0,
                        help="SCHED_FIFO priority, 0 = normal scheduling (default 0)")
    parser.add_argument("--period", type=float, default=0.005, help="[s] (default 0.005)")
    parser.add_argument("--max-duration", type=float, default=3600.0,
                        help="stop after this long [s] (default 3600)")
    parser.add_argument("--out", type=Path, required=True, help="the .npz file to write")
    args = parser.parse_args(argv)
    if not (math.isfinite(args.period) and 1e-4 <= args.period <= 1.0):
        parser.error(f"--period {args.period}: must be from 0.0001 to 1 s")
    if not (math.isfinite(args.max_duration) and args.max_duration > 0):
        parser.error(f"--max-duration {args.max_duration}: must be > 0 s")
    if not args.out.parent.is_dir():  # refused now, not after the whole run
        parser.error(f"--out {args.out}: {args.out.parent} is not a directory")
    try:
        os.sched_setaffinity(0, {args.cpu})
        if args.priority:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.priority))
    except (OSError, ValueError) as exc:
        print(f"machine_probe: CPU {args.cpu}, priority {args.priority}: {exc}",
              file=sys.stderr)
        return 2
    stop: list = []
    for signum in (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, lambda *_: stop.append(1))
    period_ns = round(args.period * 1e9)
    print("ready", flush=True)
    start_unix_ns, lateness = run_loop(period_ns, math.ceil(args.max_duration * 1e9 / period_ns),
                                       stop)
    tmp = args.out.with_name(args.out.name + ".tmp.npz")
    np.savez(tmp, lateness_ns=lateness, start_unix_ns=start_unix_ns, period_ns=period_ns,
             cpu=args.cpu, priority=args.priority)
    tmp.replace(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
