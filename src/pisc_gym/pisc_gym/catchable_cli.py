"""The command: pisc_gym_catchable: which of the catch task's starts can be caught at all?
(:mod:`pisc_gym.catchable`)."""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence

import numpy as np

from pisc_gym import catchable
from pisc_gym.catchable import fly, plans

__all__ = ["main"]


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="pisc_gym_catchable",
                                     description=catchable.__doc__.split("\n\n")[0])
    parser.add_argument("--start", choices=("arriving", "rest"), default="arriving",
                        help="the catch task's starts (pisc_gym.task)")
    parser.add_argument("--starts", type=int, default=300)
    parser.add_argument("--seed", type=int, default=2**31,
                        help="the vector environment's seed (default: pisc_gym_learn's "
                             "evaluation)")
    args = parser.parse_args(argv)
    if args.starts < 1:
        parser.error(f"--starts {args.starts}: too small")
    from pisc_robust.robustness import binomial_interval

    started = time.perf_counter()
    env, obs, info, found, gains = plans(args.start, args.starts, args.seed, report=True)
    caught = fly(env, obs, info, found, gains)
    keeps = np.array([best.keeps_track for best, _ in found])
    slack = np.array([best.slack_m for best, _ in found])
    angle = np.abs(info["true_state"][:, 2])
    n = args.starts

    def share(count: int) -> str:
        low, high = binomial_interval(count, n)
        return (f"{count} of {n}, {100 * count / n:.1f} % (95 % interval {100 * low:.1f}-"
                f"{100 * high:.1f} %)")

    print(f"starts {args.start!r}, seed {args.seed}, {time.perf_counter() - started:.0f} s")
    print(f"a plan within the track (linear model): {share(int(keeps.sum()))}")
    print(f"caught by the plan flown through the environment: {share(int(caught.sum()))}")
    print("by |theta_0| [rad]: starts; with a plan; caught flown; the best plan past the "
          "track (its largest slack); no plan at all")
    edges = np.linspace(0.0, env.task.start_angle_rad, 7)
    for low, high in zip(edges[:-1], edges[1:]):
        m = (angle >= low) & (angle < high + (1e-12 if high == edges[-1] else 0.0))
        past = m & np.isfinite(slack) & ~keeps
        worst = f", up to {1000 * slack[past].max():.1f} mm" if past.any() else ""
        print(f"  {low:.2f}-{high:.2f}: {int(m.sum()):4d}; {int(keeps[m].sum()):4d}; "
              f"{int(caught[m].sum()):4d}; {int(past.sum()):3d}{worst}; "
              f"{int((~np.isfinite(slack[m])).sum()):3d}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
