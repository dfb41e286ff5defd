"""pisc_commission_bench: the commissioning on rigs it was not told about
(docs/commissioning.md, "The hidden-rig benchmark").

    pisc_commission_bench --rigs 10 --seed 1 [--out DIR] [--starts 5] [--realtime 40]
                          [--trials 40] [--draws 400] [--verify-draws 2000] [--lockstep]

Draws rigs from ``thesis-rig`` (the seed's draws in order): each rig's masses, lengths,
motor, friction and sensors' noise (not its start or latency: on the wall clock the
latency is the machine's). A draw is kept only if a 3 s witness exists for it
(:func:`pisc_analysis.feasibility_search.find_witness`, as ``pisc_feasibility`` searches: some
voltage sequence catches it by 3 s from hanging at rest in the middle and holds it, the
fast tier). Each kept rig becomes a plant file (the plant's sections only) and is
commissioned through ``pisc_virtual_rig`` on the wall clock with its sensors' noise, as on
the rig (``--lockstep``: in lockstep instead), its M, m and l given as measured
(``--set``, rounded to 1 g, 0.1 g and 1 mm); then ``--starts`` swing-ups through the graph
on its virtual rig from random starts (x0 within 0.08 m, theta within 0.05 rad of hanging,
at rest), with the tuned file and, from the same starts, with the default configuration,
each judged by the fast tier: caught for good by 3 s and held from 6 s to the end of 12 s,
never outside the safe range. Prints each rig's figures as it goes and the totals; every
rig's directory (stages, report, bags) is kept under ``--out``.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

PROG = "pisc_commission_bench"
#: What a hidden rig takes from its draw (the rest: the default configuration's)
DRAWN = ("rig.", "motor.", "friction.", "noise.")
#: How finely M, m and l are measured on the rig (rounded to these many decimals, SI)
MEASURED = {"rig.cart_mass_kg": 3, "rig.pendulum_mass_kg": 4, "rig.pendulum_com_m": 3}


def hidden_rigs(n: int, seed: int, say=print) -> list[tuple[int, dict[str, float]]]:
    """The first ``n`` draws of ``thesis-rig`` (seed ``seed``, up to 20 n candidates)
    that have a 3 s witness: (draw number, the draw's plant values)."""
    import numpy as np

    from pisc_analysis.feasibility import exact_plant, make_rig
    from pisc_analysis.feasibility_search import find_witness
    from pisc_robust.robustness import load_benchmark, witness_limits
    from pisc_runs.verdict import Criteria

    candidates = 20 * n
    config, _, draws, base = load_benchmark("default", [], "thesis-rig", candidates, seed)
    criteria = Criteria()  # the fast tier: caught for good by 3 s, held from 6 s to 12 s
    limits = witness_limits(config, base, None, criteria.fast_by_s, criteria.fast_hold_from_s,
                            criteria.run_s)
    kept = []
    for k in range(candidates):
        values = draws.one(k)
        physical = {name: v for name, v in values.items() if name.startswith(DRAWN[:3])}
        rig = make_rig(exact_plant(base, physical), 0.0, 0.0, math.pi, 0.0)
        found = find_witness(rig, limits, np.random.default_rng([seed, k]))
        say(f"draw {k}: {'a 3 s witness' if found.feasible else 'no witness: ' + found.how}")
        if found.feasible:
            kept.append((k, {name: v for name, v in values.items()
                             if name.startswith(DRAWN)}))
            if len(kept) == n:
                break
    return kept


def plant_file(values: dict[str, float], seed: int, path: Path) -> None:
    """The hidden rig's parameter file: the default's plant sections with the draw's
    values, Coulomb friction, its noise seeded."""
    from pisc_msgs_py.config import load_params_file
    from pisc_sim.configuration import config_path, params_file_text, plant_only

    flat = plant_only(load_params_file(config_path("default")))
    flat.update({"models.friction": "coulomb", "noise.seed": seed,
                 **{k: float(v) for k, v in values.items()}})
    path.write_text(f"# hidden rig: draw of thesis-rig, seed {seed}\n" + params_file_text(flat))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    parser.add_argument("--rigs", type=int, default=10, metavar="N")
    parser.add_argument("--seed", type=int, default=1, metavar="S",
                        help="of the rigs' draws (and of their starts)")
    parser.add_argument("--out", type=Path, default=Path("commission-bench"), metavar="DIR")
    parser.add_argument("--starts", type=int, default=5, metavar="N")
    parser.add_argument("--trials", type=int, default=40, metavar="N")
    parser.add_argument("--draws", type=int, default=400, metavar="N")
    parser.add_argument("--verify-draws", type=int, default=2000, metavar="N")
    parser.add_argument("--realtime", type=int, default=0, metavar="PRIORITY",
                        help="SCHED_FIFO priority of the graph runs (the virtual rig's: +10)")
    parser.add_argument("--lockstep", action="store_true",
                        help="rehearse in lockstep instead of through the virtual rig")
    args = parser.parse_args(argv)
    for name in ("rigs", "starts", "trials", "draws", "verify_draws"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} {getattr(args, name)}: at least 1")
    if args.seed < 0:
        parser.error(f"--seed {args.seed}: 0 or more")
    from pisc_robust.robustness_args import quiet_threads

    quiet_threads()
    from pisc_robust import commission as cm

    claim = None
    if "ROS_DOMAIN_ID" not in os.environ:
        from pisc_msgs_py.processes import DomainClaim

        claim = DomainClaim()
        os.environ["ROS_DOMAIN_ID"] = str(claim.domain_id)
    args.out.mkdir(parents=True, exist_ok=True)
    print(f"{PROG}: {args.rigs} rigs of thesis-rig, seed {args.seed}, each with a 3 s witness; "
          f"{'lockstep' if args.lockstep else 'pisc_virtual_rig on the wall clock'}",
          flush=True)
    rows = []
    try:
        rigs = hidden_rigs(args.rigs, args.seed, lambda text: print(f"  {text}", flush=True))
        for k, (draw, values) in enumerate(rigs):
            where = args.out / f"rig-{draw:03d}"
            where.mkdir(exist_ok=True)
            hidden = where / "hidden.yaml"
            plant_file(values, args.seed * 1000 + draw, hidden)
            measured = {name: round(values[name], digits) for name, digits in MEASURED.items()}
            rig = cm.Rig("lockstep" if args.lockstep else "virtual", plant=str(hidden),
                         realtime=args.realtime)
            plan = cm.Plan(where / "commissioning", rig, overrides=measured,
                           trials=args.trials, draws=args.draws,
                           verify_draws=args.verify_draws, seed=args.seed)
            log = (where / "commissioning.log").open("a")
            began = time.monotonic()
            try:
                cm.commission(plan, say=lambda text: print(text, file=log, flush=True),
                              command=f"{PROG} rig {draw}")
            except cm.CommissionError as exc:
                print(f"rig {draw}: commissioning failed: {exc}", flush=True)
                rows.append((draw, math.nan, None, None))
                continue
            finally:
                log.close()
            wall = time.monotonic() - began
            starts = cm.draw_starts(args.starts, args.seed + draw, plan.start_x_m,
                                    plan.start_theta_rad)
            runs = {}
            for label, config in (("tuned", str(plan.directory / "tuned.yaml")),
                                  ("default", "default")):
                runs[label] = cm.swing_ups(rig, config, starts, where / f"swing-ups-{label}",
                                           os.environ, say=lambda text: None)
            rows.append((draw, wall, runs["tuned"], runs["default"]))
            print(f"rig {draw} ({k + 1}/{len(rigs)}): commissioned in {wall / 60:.1f} min; "
                  + "; ".join(f"{label}: {sum(r.passed for r in runs[label])} of "
                              f"{len(starts)} fast, {sum(r.safe for r in runs[label])} safe"
                              for label in ("tuned", "default")), flush=True)
    finally:
        if claim is not None:
            claim.release()
    print("\n".join(summary(rows, args.starts)))
    return 0


def summary(rows: list, starts: int) -> list[str]:
    done = [r for r in rows if r[2] is not None]
    lines = [f"rigs commissioned: {len(done)} of {len(rows)}"]
    for index, label in ((2, "tuned"), (3, "default")):
        runs = [s for r in done for s in r[index]]
        lines.append(f"{label}: {sum(s.passed for s in runs)} of {len(runs)} swing-ups caught "
                     f"for good by 3 s and held (the fast tier); {sum(s.safe for s in runs)} "
                     "never outside the safe range")
    walls = [r[1] for r in done]
    if walls:
        lines.append(f"commissioning wall time: median {sorted(walls)[len(walls) // 2] / 60:.1f}"
                     f" min, largest {max(walls) / 60:.1f} min")
    return lines


if __name__ == "__main__":
    sys.exit(main())
