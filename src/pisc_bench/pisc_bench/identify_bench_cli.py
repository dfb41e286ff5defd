"""The identification benchmark's command (:mod:`pisc_bench.identify_bench`).

    python -m pisc_bench.identify_bench_cli [--via driver|lockstep] [--draws 20] [--seed 1]
                                              [--duration S] [--set NAME=VALUE ...]
                                              [--truth NAME=VALUE ...] [--keep DIR]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

from pisc_bench.identify_bench import (
    FIT,
    Outcome,
    draw_truths,
    format_outcome,
    identify_one,
    judge,
    record_driver,
    record_lockstep,
    scene_experiment,
    summary,
)
from pisc_robust.identify_data import IdentifyError, read_recording
from pisc_sim.configuration import load_run_config
from pisc_msgs_py.config import ConfigError, parse_overrides

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    from pisc_robust.robustness_args import quiet_threads

    quiet_threads()
    parser = argparse.ArgumentParser(
        prog="identify_bench", description="Benchmark of pisc_identify: rigs drawn from a "
        "distribution, each identified from an excitation, against the truth")
    parser.add_argument("--via", choices=("driver", "lockstep"), default="driver")
    parser.add_argument("--draws", type=int, default=20)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--duration", type=float, default=None,
                        help="length of each run, s (default: the excitation scene's)")
    parser.add_argument("--distribution", default="thesis-rig")
    parser.add_argument("--fit", default=FIT)
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                        help="override the experiment's parameters (e.g. experiment.signal=prbs)")
    parser.add_argument("--truth", action="append", default=[], metavar="NAME=VALUE",
                        help="set a parameter of every draw's hidden plant (e.g. "
                        "noise.current_std_a=0: lockstep without the current's noise)")
    parser.add_argument("--keep", type=Path, metavar="DIR", help="keep the bags here; a bag "
                        "already there (draw-NNN of the same seed) is identified again "
                        "instead of recorded")
    args = parser.parse_args(argv)
    try:
        overrides = parse_overrides(args.set)
        try:
            fixed = parse_overrides(args.truth)
        except ConfigError as exc:  # (its text names --set)
            raise ConfigError(str(exc).replace("--set", "--truth", 1)) from None
        truths = [{**t, **fixed} for t in draw_truths(args.draws, args.seed, args.distribution,
                                                      args.via == "lockstep", noise=True)]
    except ConfigError as exc:
        print(f"identify_bench: {exc}", file=sys.stderr)
        return 2
    base, _, _ = load_run_config("default")
    duration = args.duration if args.duration is not None else scene_experiment()[1]
    claim = None
    if args.via == "driver" and "ROS_DOMAIN_ID" not in os.environ:
        # a ROS domain of its own: another graph on this machine (a test, a soak) must not
        # hear these runs, nor they it
        from pisc_msgs_py.processes import DomainClaim

        claim = DomainClaim()
        os.environ["ROS_DOMAIN_ID"] = str(claim.domain_id)
    outcomes = []
    with tempfile.TemporaryDirectory(prefix="identify-bench-") as tmp:
        where = args.keep or Path(tmp)
        where.mkdir(parents=True, exist_ok=True)
        for k, truth in enumerate(truths):
            outcome = Outcome(k, truth, None)
            try:
                if args.via == "lockstep":
                    recording = record_lockstep(truth, duration, overrides, args.seed + k)
                else:
                    bag = where / f"draw-{k:03d}"
                    # a draw recorded again (the machine did not keep time) is draw-NNN-A
                    kept = sorted(p for p in where.glob(f"draw-{k:03d}*")
                                  if (p / "metadata.yaml").exists()) if args.keep else []
                    bag = kept[-1] if kept else record_driver(truth, duration, overrides,
                                                              bag)
                    recording = read_recording(bag)
                outcome.result, outcome.wall_s = identify_one(recording, args.fit)
                judge(outcome, base.plant)
            except (IdentifyError, RuntimeError) as exc:
                outcome.error = str(exc)
            outcomes.append(outcome)
            print(format_outcome(outcome), flush=True)
    print(summary(outcomes))
    if claim is not None:
        claim.release()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
