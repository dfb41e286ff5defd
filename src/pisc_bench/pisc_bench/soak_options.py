"""The soak's options (``pisc_soak``'s command line, checked) and the machine set-up
they ask for: busy loops beside the run (``--load``), SCHED_FIFO (``--realtime``)."""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from pisc_bench.soak_figures import START_AFTER_S

__all__ = ["ArgumentError", "SoakOptions", "check_realtime", "parse_args", "start_load",
           "stop_load"]

class ArgumentError(ValueError):
    """A refused command line; the message names the option and the rule."""


@dataclass(frozen=True)
class SoakOptions:
    duration_s: float = 600.0
    driver: bool = False
    faults: bool = False
    realtime: int = 0
    seed: int = 0
    out: Path | None = None
    load: int = 0  # busy loops beside the run, one per CPU


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="pisc_soak", description="A wall-clock soak of the graph: latency, cycles, "
        "CPU and memory per process, the machine's own timer beside it (docs/soak.md).")
    parser.add_argument("--duration", type=float, default=600.0,
                        help="run length [s], at least 15 (default 600)")
    parser.add_argument("--driver", action="store_true",
                        help="through the serial driver and the virtual rig on a pty")
    parser.add_argument("--faults", action="store_true",
                        help="with --driver: byte drops 1e-3, a 0.2 s silence each minute, "
                        "garbage bursts, seeded; recoveries and an outside observer")
    parser.add_argument("--realtime", type=int, default=0, metavar="P",
                        help="SCHED_FIFO priority of the graph (the rig gets P + 10); needs "
                        "CAP_SYS_NICE; 0 = normal scheduling")
    parser.add_argument("--load", type=int, default=0, metavar="N",
                        help="N busy loops beside the run, each held to one CPU (a loaded "
                        "machine; at most the CPUs this process may use); default 0")
    parser.add_argument("--seed", type=int, default=0, help="seed of the faults (default 0)")
    parser.add_argument("--out", type=Path,
                        help="new directory for the bag and report.json "
                        "(default bags/soak-<time>)")
    return parser


def parse_args(argv: Sequence[str]) -> SoakOptions:
    """The options, or :class:`ArgumentError` naming what is wrong (argparse's own
    errors exit 2 as usual)."""
    args = _parser().parse_args(list(argv))
    if not math.isfinite(args.duration) or args.duration < START_AFTER_S + 5.0:
        raise ArgumentError(f"--duration {args.duration:g}: must be a finite number of "
                            f"seconds >= {START_AFTER_S + 5.0:g} (memory is first read "
                            f"{START_AFTER_S:g} s into the run)")
    if args.faults and not args.driver:
        raise ArgumentError("--faults needs --driver: the faults are the virtual rig's "
                            "(byte drops, silences, garbage on the serial line)")
    if not 0 <= args.realtime <= 89:
        raise ArgumentError(f"--realtime {args.realtime}: must be a SCHED_FIFO priority "
                            "from 1 to 89 (the rig runs at P + 10), or 0 for none")
    if args.seed < 0:
        raise ArgumentError(f"--seed {args.seed}: must be >= 0")
    if args.out is not None and args.out.exists() and (
            not args.out.is_dir() or any(args.out.iterdir())):
        raise ArgumentError(f"--out {args.out}: exists and is not an empty directory; "
                            "not overwriting")
    cpus = len(os.sched_getaffinity(0))
    if not 0 <= args.load <= cpus:
        raise ArgumentError(f"--load {args.load}: must be 0 .. {cpus} (one busy loop per CPU "
                            "this process may use)")
    return SoakOptions(args.duration, args.driver, args.faults, args.realtime, args.seed,
                       args.out, args.load)


BUSY_LOOP = "while True:\n    pass\n"


def start_load(count: int) -> list[subprocess.Popen]:
    """``count`` busy loops, each held to one of this process's CPUs (SCHED_OTHER,
    whatever this process's policy)."""
    cpus = sorted(os.sched_getaffinity(0))[:count]

    def pinned(cpu: int) -> Callable[[], None]:
        def setup() -> None:  # pragma: no cover - runs in the child before exec
            os.sched_setaffinity(0, {cpu})
            if os.sched_getscheduler(0) != os.SCHED_OTHER:
                os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        return setup

    return [subprocess.Popen([sys.executable, "-c", BUSY_LOOP], preexec_fn=pinned(cpu),
                             stdin=subprocess.DEVNULL) for cpu in cpus]


def stop_load(loops: Sequence[subprocess.Popen]) -> None:
    for loop in loops:
        if loop.poll() is None:
            loop.kill()
        loop.wait()


def check_realtime(priority: int) -> str | None:
    """Why SCHED_FIFO at ``priority`` cannot be used here, or None (tried in a child)."""
    if not priority:
        return None
    probe = subprocess.run(
        [sys.executable, "-c", "import os, sys; os.sched_setscheduler(0, os.SCHED_FIFO, "
         f"os.sched_param({priority}))"], capture_output=True, text=True)
    if probe.returncode:
        return probe.stderr.strip().splitlines()[-1] if probe.stderr.strip() else "refused"
    return None

