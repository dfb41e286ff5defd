"""pisc_commission: from a rig the controllers do not know to a configuration tuned for it,
in one command (docs/commissioning.md).

    pisc_commission --driver /dev/ttyUSB0 --set rig.cart_mass_kg=0.47 ...   # the rig
    pisc_commission --plant-config hidden.yaml --check 5                    # rehearsal

Records an excitation and a free swing, identifies the rig from both, writes the rig's
distribution (the identification's intervals widened, the noise and latency as measured,
the masses within their tolerance, the starts it will meet), tunes the controllers on it
(pisc_tune's library), verifies the result on fresh draws by the benchmark's tiers and
writes DIR/report.md and DIR/tuned.yaml, every input named in its header. Each stage is
kept in DIR: the same command resumes where the last run stopped. On the rig it tells the
operator what to do before each run and waits for Enter, and ends by offering the
swing-up with the tuned file; rehearsed, ``--check N`` swings the plant up N times
through the graph from random starts.

Exit status: 0 commissioned (and, with --check, every swing-up caught by the fast tier);
1 a stage failed (a run faulted, a fit failed) or a --check swing-up was not caught;
2 bad input, or a stage kept in DIR made with other options; 130 interrupted (rerun to
resume).
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
from pathlib import Path

PROG = "pisc_commission"


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    rig = p.add_argument_group("the rig (one of)")
    rig.add_argument("--driver", metavar="PORT",
                     help="the rig on this serial port (or a pisc_virtual_rig's device)")
    rig.add_argument("--plant-config", metavar="FILE",
                     help="rehearse on this plant parameter file, in lockstep")
    rig.add_argument("--virtual-rig", action="store_true",
                     help="with --plant-config: through pisc_virtual_rig and the driver, on "
                     "the wall clock, as on the rig")
    p.add_argument("--dir", type=Path, default=Path("commissioning"), metavar="DIR",
                   help="where the stages are kept (default: %(default)s)")
    p.add_argument("--config", default="default", metavar="NAME|FILE",
                   help="the configuration the controllers start from (default: %(default)s)")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="the rig as measured, e.g. rig.cart_mass_kg=0.471 (repeatable)")
    p.add_argument("--space", metavar="NAME|FILE",
                   help="pisc_tune's search space (default: the shipped one for the "
                   "configuration's law and settings)")
    d = p.add_argument_group("the rig's distribution")
    d.add_argument("--widen", type=float, default=3.0, metavar="F",
                   help="the identification's 95 %% intervals widened by F (default 3)")
    d.add_argument("--noise-span", type=float, default=0.5, metavar="F",
                   help="each measured noise x (1 -+ F) (default 0.5)")
    d.add_argument("--mass-tolerance", type=float, default=0.01, metavar="F",
                   help="M and m as weighed, relative (default 0.01)")
    d.add_argument("--length-tolerance", type=float, default=0.02, metavar="F",
                   help="l as measured, relative (default 0.02)")
    d.add_argument("--start-x", type=float, default=0.08, metavar="M",
                   help="starts: the cart within +-M of the middle (default 0.08)")
    d.add_argument("--start-theta", type=float, default=0.05, metavar="RAD",
                   help="starts: the pendulum within +-RAD of hanging (default 0.05)")
    d.add_argument("--prior", default="thesis-rig", metavar="NAME|FILE",
                   help="the ranges of what nothing pins down (default: %(default)s)")
    t = p.add_argument_group("tuning and verification")
    t.add_argument("--trials", type=int, default=40, metavar="N")
    t.add_argument("--draws", type=int, default=400, metavar="N", help="draws per trial")
    t.add_argument("--verify-draws", type=int, default=2000, metavar="N")
    t.add_argument("--seed", type=int, default=1, metavar="S",
                   help="of the tuning's draws; the verification's: S + 1000")
    t.add_argument("--sampler", choices=("tpe", "cmaes"), default="tpe")
    t.add_argument("--aim", choices=("fast", "safe"), default="fast",
                   help="what the tuning puts first (pisc_tune --aim; default: fast, the "
                   "draws caught by 3 s and held, each of them safe)")
    where = t.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, metavar="N")
    where.add_argument("--scheduler", metavar="ADDRESS")
    r = p.add_argument_group("the runs")
    r.add_argument("--excitation-s", type=float, default=60.0, metavar="S")
    r.add_argument("--swing-s", type=float, default=20.0, metavar="S")
    r.add_argument("--realtime", type=int, default=0, metavar="PRIORITY",
                   help="SCHED_FIFO priority of the graph runs on the wall clock (0: none)")
    r.add_argument("--check", type=int, default=0, metavar="N",
                   help="rehearsal: N swing-ups through the graph with the tuned file from "
                   "random starts at the end")
    return p


def _operator(text: str) -> None:
    """Show the operator what to do at the rig; wait for Enter."""
    if not sys.stdin.isatty():
        raise EOFError
    print(f"\n>>> {text}", flush=True)
    input(">>> Enter when ready, Ctrl-C to stop: ")


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    from pisc_robust import commission as cm
    from pisc_msgs_py.config import ConfigError, parse_overrides

    if args.virtual_rig and not args.plant_config:
        parser.error("--virtual-rig needs --plant-config FILE (the plant it simulates)")
    if args.check < 0:
        parser.error(f"--check {args.check}: 0 or more")
    if args.check and args.driver:
        parser.error("--check swings up a rehearsal's plant; on the rig the command offers "
                     "the swing-up at its end")
    if args.scheduler:
        from pisc_robust.cluster import check_scheduler

        try:
            check_scheduler(args.scheduler)
        except ValueError as exc:
            parser.error(f"--scheduler {exc}")
    from pisc_robust.robustness_args import quiet_threads

    quiet_threads()
    command = shlex.join([PROG, *(sys.argv[1:] if argv is None else argv)])
    try:
        kind = ("driver" if args.driver else "virtual" if args.virtual_rig else "lockstep")
        rig = cm.Rig(kind, args.driver, args.plant_config, args.realtime)
        plan = cm.Plan(
            args.dir, rig, config=args.config, overrides=parse_overrides(args.set),
            space=args.space, widen=args.widen, noise_span=args.noise_span,
            mass_tolerance=args.mass_tolerance, length_tolerance=args.length_tolerance,
            start_x_m=args.start_x, start_theta_rad=args.start_theta, trials=args.trials,
            draws=args.draws, verify_draws=args.verify_draws, seed=args.seed,
            sampler=args.sampler, aim=args.aim, excitation_s=args.excitation_s,
            swing_s=args.swing_s, prior=args.prior, workers=args.workers,
            scheduler=args.scheduler)
        _check_inputs(plan)
    except ConfigError as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return 2
    claim = None
    if "ROS_DOMAIN_ID" not in os.environ:  # the runs' graphs hear no other on this machine
        from pisc_msgs_py.processes import DomainClaim

        claim = DomainClaim()
        os.environ["ROS_DOMAIN_ID"] = str(claim.domain_id)
    stage = "?"

    def hook(name: str, event: str) -> None:
        nonlocal stage
        stage = name

    try:
        cm.commission(plan, say=lambda text: print(text, flush=True),
                      operator=_operator if rig.operated else None, hook=hook,
                      command=command)
        stage = "the swing-ups"
        return _finish(plan, args.check)
    except KeyboardInterrupt:
        print(f"\n{PROG}: interrupted in stage {stage}; what is done is kept in {plan.directory}:"
              " rerun the same command to resume", file=sys.stderr)
        return 130
    except EOFError:
        print(f"{PROG}: the rig needs an operator at a terminal to answer (standard input "
              "is not one); nothing more done", file=sys.stderr)
        return 2
    except cm.StageMismatch as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return 2
    except ConfigError as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return 2
    except cm.CommissionError as exc:
        print(f"{PROG}: stage {stage}: {exc}", file=sys.stderr)
        return 1
    finally:
        if claim is not None:
            claim.release()


def _check_inputs(plan) -> None:
    """What can be refused before any run: the configuration with the --set values, the
    search space against it, the prior."""
    from pisc_robust.tune_space import load_space
    from pisc_robust.uncertainty import load_distribution
    from pisc_control.supervisor import Supervisor
    from pisc_sim.configuration import load_graph_config, load_run_config

    config, flat = load_graph_config(plan.config, plan.overrides)
    Supervisor(config.supervisor)  # the gain condition (3.29) and the catch design
    if plan.space is not None:
        load_space(plan.space, flat)
    load_distribution(plan.prior, config)
    if plan.rig.plant is not None:
        load_run_config(plan.config, plan.overrides, plant=plan.rig.plant)


def _finish(plan, check: int) -> int:
    from pisc_robust import commission as cm

    tuned = plan.directory / "tuned.yaml"
    print(f"commissioned: {tuned} (report: {plan.directory / 'report.md'})")
    if plan.rig.operated:
        if not sys.stdin.isatty():
            return 0
        answer = input(f">>> Swing up with {tuned} now? Put the cart near the middle, the "
                       "pendulum hanging still, and keep clear. [y/N] ")
        if answer.strip().lower() not in ("y", "yes"):
            print(f"not now: ./pisc run --config {tuned} --driver {plan.rig.port} runs it")
            return 0
        runs = cm.swing_ups(plan.rig, str(tuned), [(0.0, 3.141592653589793)],
                            plan.directory / "swing-ups", os.environ, duration_s=20.0)
        return 0 if runs[0].passed else 1
    if not check:
        return 0
    starts = cm.draw_starts(check, plan.seed, plan.start_x_m, plan.start_theta_rad)
    print(f"{check} swing-ups through the graph with {tuned}, judged by the fast tier:")
    runs = cm.swing_ups(plan.rig, str(tuned), starts, plan.directory / "swing-ups",
                        os.environ)
    caught = sum(r.passed for r in runs)
    print(f"caught by the fast tier: {caught} of {check}; safe: {sum(r.safe for r in runs)}")
    with (plan.directory / "report.md").open("a") as report:
        report.write(f"\n## Swing-ups through the graph\n\n{caught} of {check} caught by the "
                     "fast tier (caught for good by 3 s, held from 6 s to the end of 12 s):\n\n"
                     + "".join(f"- x0 {r.x0_m:+.3f} m, theta0 {r.theta0_rad:.3f} rad: "
                               f"{r.verdict.strip()}\n" for r in runs))
    return 0 if caught == check else 1


if __name__ == "__main__":
    raise SystemExit(main())
