"""The command: pisc_gym_learn: learn a catch policy on randomised rigs with CMA-ES, through
the vector environment, and count its catches over fresh randomised starts
(:mod:`pisc_gym.learn`)."""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from pisc_gym import learn as learning
from pisc_gym.learn import SCALE, episodes, learn, plot

__all__ = ["main"]


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="pisc_gym_learn", description=learning.__doc__.split("\n\n")[0])
    parser.add_argument("--generations", type=int, default=40)
    parser.add_argument("--population", type=int, default=16)
    parser.add_argument("--starts", type=int, default=32, help="episodes a candidate")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--evaluate", type=int, default=1000,
                        help="new randomised starts the learnt policy is counted on")
    parser.add_argument("--start", choices=("arriving", "rest"), default="arriving",
                        help="the catch's starts (pisc_gym.task): arriving as the swing-up "
                             "hands the pendulum over (default), or at rest")
    parser.add_argument("--figure", type=Path, help="write the learning curve (PNG) here")
    args = parser.parse_args(argv)
    for name in ("generations", "population", "starts", "evaluate"):
        if getattr(args, name) < (2 if name == "population" else 1):
            parser.error(f"--{name} {getattr(args, name)}: too small")
    from pisc_robust.robustness import binomial_interval

    started = time.perf_counter()
    gains, history = learn(args.generations, args.population, args.starts, args.seed,
                           start=args.start)
    learnt = time.perf_counter() - started
    # the evaluation's seeds lie past every seed the generations used
    _, caught = episodes(np.repeat(gains[None, :], args.evaluate, axis=0), 2**31 + args.seed,
                         start=args.start)
    low, high = binomial_interval(int(caught.sum()), args.evaluate)
    rate = float(caught.mean())
    k = gains / SCALE
    print(f"learnt in {learnt:.0f} s: i_d = {k[0]:.4g} (x - x_mid) + {k[1]:.4g} x_dot + "
          f"{k[2]:.4g} theta + {k[3]:.4g} theta_dot [A]")
    print(f"caught {int(caught.sum())} of {args.evaluate} new randomised starts: "
          f"{100 * rate:.1f} % (95 % interval {100 * low:.1f}-{100 * high:.1f} %)")
    if args.figure is not None:
        plot(history, rate, args.evaluate, args.figure, args.start)
        print(f"figure: {args.figure}")
    return 0 if rate >= 0.95 else 1


if __name__ == "__main__":
    raise SystemExit(main())
