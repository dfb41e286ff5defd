"""pisc_feasibility: can any controller swing up and hold the rigs of a distribution?
(docs/feasibility.md)

    pisc_feasibility --distribution thesis-rig --draws 100 --seed 1
    pisc_feasibility --draws 300 --catch-by 8 --hold-from 9 --run-s 12

For each draw (the same draws as ``pisc_robustness CONFIG --distribution D --seed S``):
the exact plant (its own m, l, I, M, motor and friction, its own start; no noise, no
latency) is searched for a voltage sequence that is caught by ``--catch-by`` seconds
(3.0) and held from ``--hold-from`` (6.0) to the end of a run of ``--run-s`` (10.0),
within the benchmark's rules (:mod:`pisc_analysis.feasibility`). Prints the fraction of
draws with a witness and its Clopper-Pearson 95 % interval, split by pivot friction
(fifths of its range) and by the search that found it, and every draw without one;
``--csv FILE`` writes one row a draw, after ``# key: value`` lines giving the rules, the
seed, the number of draws and the distribution's digest
(:mod:`pisc_analysis.witnesses`). A witness proves a draw feasible; a search that fails
proves nothing unless the energy bound or the comparison lemma's climb time says so
(column ``bound``; ``bound_least_time_s``). ``--multiple-shooting`` adds a last, slower
search.
"""

from __future__ import annotations

import argparse
import math
import shlex
import sys
import time
from pathlib import Path

PROG = "pisc_feasibility"
PIVOT = "friction.pivot_viscous_nms"
INITIAL = ("initial.x_m", "initial.x_dot_mps", "initial.theta_rad", "initial.theta_dot_radps")


def _indices(text: str) -> list[int]:
    try:
        values = [int(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: draw numbers separated by commas") from None
    if any(v < 0 for v in values):
        raise argparse.ArgumentTypeError(f"{text!r}: draw numbers are 0 or more")
    if len(set(values)) < len(values):
        raise argparse.ArgumentTypeError(f"{text!r}: a draw named twice")
    return values


def _limit(text: str) -> float:
    """A current limit in A, or 'none' (infinite: the voltage alone limits the current)."""
    if text == "none":
        return math.inf
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: a current in A or 'none'") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"{text!r}: the current limit must be positive")
    return value


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: a time in seconds") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"{text!r}: a positive, finite time in seconds")
    return value


def rule_problem(catch_by_s: float, hold_from_s: float, run_s: float) -> str | None:
    """What is wrong with the rules (``--catch-by``, ``--hold-from``, ``--run-s``), or
    None: caught by a time within the run, held from then or later to the run's end."""
    if catch_by_s >= run_s:
        return (f"--catch-by {catch_by_s:g}: not before the end of the run (--run-s "
                f"{run_s:g}): the catch must come within the run")
    if hold_from_s >= run_s:
        return (f"--hold-from {hold_from_s:g}: outside the run (--run-s {run_s:g}): the hold "
                "is checked from there to the run's end")
    if hold_from_s < catch_by_s:
        return (f"--hold-from {hold_from_s:g}: before --catch-by {catch_by_s:g}: the hold "
                "starts once the pendulum is caught")
    return None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", default="default", metavar="NAME|FILE",
                        help="configuration giving the nominal plant, the safe range, the "
                        "catch region and the limits (default: %(default)s)")
    parser.add_argument("--distribution", default="thesis-rig", metavar="NAME|FILE",
                        help="a shipped distribution or a distribution file "
                        "(default: %(default)s)")
    parser.add_argument("--draws", type=int, default=100, metavar="N",
                        help="draws (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=1, metavar="S",
                        help="seed of the draws and of each draw's search (default: "
                        "%(default)s)")
    parser.add_argument("--only", type=_indices, metavar="K,K,...",
                        help="search only these draws of the N (numbered from 0; a draw's "
                        "values depend on N, as in pisc_robustness)")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                        help="override a parameter of the configuration (repeatable), e.g. "
                        "safety.x_max_m=0.5 with track.max_m=0.51 for a longer track")
    parser.add_argument("--current-limit", type=_limit, default=None, metavar="A|none",
                        help="the current limit (default: the configuration's "
                        "current_loop.current_limit_a); 'none': the voltage alone limits it")
    parser.add_argument("--rounds", type=int, default=4, metavar="N",
                        help="rounds of the feedback search (default: %(default)s)")
    parser.add_argument("--restarts", type=int, default=1, metavar="N",
                        help="shooting restarts when feedback finds nothing (default: "
                        "%(default)s)")
    parser.add_argument("--multiple-shooting", action="store_true",
                        help="last, when the other searches find nothing: multiple shooting "
                        "with the catch deadline brought down by continuation from the best "
                        "feedback rollouts (slow: a minute or more a draw)")
    parser.add_argument("--catch-by", type=_seconds, default=3.0, metavar="S",
                        help="in the catch region for good from some t <= S (default: "
                        "%(default)s)")
    parser.add_argument("--hold-from", type=_seconds, default=6.0, metavar="S",
                        help="|theta| and |x| within the hold's bounds from S to the end "
                        "(default: %(default)s)")
    parser.add_argument("--run-s", type=_seconds, default=10.0, metavar="S",
                        help="the run's length (default: %(default)s)")
    parser.add_argument("--csv", type=Path, metavar="FILE",
                        help="write one row a draw, after '# key: value' lines with the "
                        "rules, the seed, the draws and the distribution's digest")
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parser.parse_args(argv)
    problem = rule_problem(args.catch_by, args.hold_from, args.run_s)
    if problem:
        parser.error(problem)
    for name in ("draws", "rounds"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} {getattr(args, name)}: at least 1")
    if args.restarts < 0:
        parser.error(f"--restarts {args.restarts}: 0 or more")
    if args.only and max(args.only) >= args.draws:
        parser.error(f"--only: draw {max(args.only)} is not among the {args.draws} draws "
                     "(0 .. N-1)")
    if args.csv is not None and not args.csv.parent.is_dir():
        parser.error(f"--csv {args.csv}: directory {args.csv.parent} does not exist")
    from pisc_robust.robustness_args import quiet_threads

    quiet_threads()

    import numpy as np

    from pisc_analysis.feasibility import clopper_pearson, exact_plant, make_rig
    from pisc_analysis.feasibility_search import find_witness
    from pisc_analysis.feasibility_shooting import Transcription
    from pisc_analysis.witnesses import write_witness_csv
    from pisc_robust.robustness import load_benchmark, witness_limits
    from pisc_msgs_py.config import ConfigError

    try:
        config, distribution, draws, base = load_benchmark(
            args.config, args.set, args.distribution, args.draws, args.seed)
    except ConfigError as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return 2
    try:
        limits = witness_limits(config, base, args.current_limit, args.catch_by,
                                args.hold_from, args.run_s)
    except ValueError as exc:
        print(f"{PROG}: the benchmark's rules: {exc}", file=sys.stderr)
        return 2
    pivot_range = distribution.range(PIVOT)
    lo, hi = (pivot_range.value_range if pivot_range is not None
              else (base.friction.pivot_viscous_nms,) * 2)
    indices = args.only if args.only else list(range(draws.n))
    print(f"distribution {distribution.name} (digest {distribution.digest}), "
          f"{len(indices)} of {draws.n} draws of seed {args.seed}")
    for item in args.set:
        print(f"  --set {item}")
    print(f"limits: |u| <= {limits.voltage_v} V, |i| <= "
          f"{'(voltage only)' if limits.current_a is None else f'{limits.current_a} A'}, "
          f"x in [{limits.x_min_m}, {limits.x_max_m}] m, in the catch region "
          f"(theta^2 + {limits.k_va} theta_dot^2 < {limits.delta_s}) for good by "
          f"{limits.catch_by_s} s, |theta| < {limits.hold_theta_rad} rad and |x| < "
          f"{limits.hold_x_m} m from {limits.hold_start_s} s to {limits.duration_s} s")
    meta = {"catch_by_s": limits.catch_by_s, "hold_from_s": limits.hold_start_s,
            "run_s": limits.duration_s, "seed": args.seed, "draws": draws.n,
            "searched": len(indices), "distribution": distribution.name,
            "distribution_digest": distribution.digest, "config": args.config,
            "set": " ".join(args.set), "only": ",".join(map(str, args.only or [])),
            "voltage_limit_v": limits.voltage_v,
            "current_limit_a": "none" if limits.current_a is None else limits.current_a,
            "x_min_m": limits.x_min_m, "x_max_m": limits.x_max_m,
            "hold_theta_rad": limits.hold_theta_rad, "hold_x_m": limits.hold_x_m,
            "rounds": args.rounds, "restarts": args.restarts,
            "multiple_shooting": args.multiple_shooting,
            "command": shlex.join([PROG, *argv])}
    rows = []
    start = time.perf_counter()
    for index in indices:
        values = draws.one(index)
        physical = {n: v for n, v in values.items() if n.split(".")[0] in
                    ("rig", "motor", "friction")}
        try:
            plant = exact_plant(base, physical)
        except ValueError as exc:
            print(f"{PROG}: draw {index}: {exc}", file=sys.stderr)
            return 2
        rig = make_rig(plant, *(values.get(n, getattr(config.initial, n.split(".")[1]))
                                for n in INITIAL))
        began = time.perf_counter()
        found = find_witness(rig, limits, np.random.default_rng([args.seed, index]),
                             rounds=args.rounds, restarts=args.restarts,
                             transcription=Transcription() if args.multiple_shooting else None)
        pivot = values.get(PIVOT, base.friction.pivot_viscous_nms)
        row = {"draw": index, "feasible": found.feasible, "how": found.how,
               "caught_at_s": found.verdict.caught_at_s if found.verdict else math.nan,
               "largest_x_m": found.verdict.largest_x_m if found.verdict else math.nan,
               "reason": found.verdict.reason if found.verdict and not found.feasible else "",
               "bound_needed_j": found.bound.needed_j,
               "bound_largest_gain_j": found.bound.largest_gain_j,
               "bound_least_time_s": found.bound.least_time_s,
               "bound_horizon_s": found.bound.horizon_s,
               "bound": found.bound.infeasible, "tried": found.tried,
               "transcribed_s": found.transcribed_s,
               "seconds": time.perf_counter() - began, **values}
        rows.append(row)
        met = ("" if math.isnan(found.transcribed_s) else
               f"multiple shooting met the deadline {found.transcribed_s:.3f} s, ")
        print(f"draw {index}: {'feasible' if found.feasible else found.how} "
              f"({found.how if found.feasible else row['reason']}), pivot {pivot:.2e} N m s, "
              f"R {values.get('motor.resistance_ohm', math.nan):.1f} ohm, {met}"
              f"{row['seconds']:.1f} s", flush=True)
        if args.csv is not None:
            write_witness_csv(args.csv, meta, rows)
    wall = time.perf_counter() - start
    print("\n".join(summary(rows, lo, hi, clopper_pearson)))
    print(f"wall time {wall:.0f} s")
    return 0


def summary(rows: list[dict], lo: float, hi: float, interval) -> list[str]:
    """The fraction feasible overall, by fifths of the pivot friction's range, by how."""
    def line(name: str, part: list[dict]) -> str:
        n = len(part)
        if n == 0:
            return f"{name}: no draws"
        wins = sum(r["feasible"] for r in part)
        a, b = interval(wins, n)
        return (f"{name}: {wins} of {n} = {100 * wins / n:.1f} % "
                f"(95 % interval {100 * a:.1f} .. {100 * b:.1f} %)")

    out = [line("witness found", rows)]
    edges = [lo + (hi - lo) * j / 5 for j in range(6)]
    for j in range(5):
        part = [r for r in rows if edges[j] <= r.get(PIVOT, lo) <= edges[j + 1]
                and (j == 4 or r.get(PIVOT, lo) < edges[j + 1])]
        out.append("  " + line(f"pivot friction {edges[j]:.1e} .. {edges[j + 1]:.1e} N m s",
                               part))
    hows = {}
    for r in rows:
        hows[r["how"]] = hows.get(r["how"], 0) + 1
    out.append("by search: " + ", ".join(f"{h} {n}" for h, n in sorted(hows.items())))
    proved = sum(r["bound"] for r in rows)
    out.append(f"proved infeasible by the energy bound or the climb time: {proved}")
    return out


if __name__ == "__main__":
    sys.exit(main())
