"""The command: pisc_gym_bench: steps per second of PISC's vector environment beside
Gymnasium's CartPoleVectorEnv, at the same numbers of copies in the same run, and each
one's error against an accurate solution of its own equations (:mod:`pisc_gym.bench`)."""

from __future__ import annotations

import argparse
import os
from collections.abc import Sequence

from pisc_gym import bench
from pisc_gym.bench import GOAL, cartpole_error, cartpole_rate, pisc_error, pisc_rate

__all__ = ["main"]


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="pisc_gym_bench", description=bench.__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1, 100, 10000],
                        help="numbers of copies (default: 1 100 10000)")
    parser.add_argument("--seconds", type=float, default=3.0,
                        help="wall time each environment steps at each size (default 3)")
    parser.add_argument("--threads", type=int, help="numba threads (default: numba's, one a "
                        "core)")
    args = parser.parse_args(argv)
    if any(n < 1 for n in args.sizes) or not args.seconds > 0:
        parser.error("--sizes must be positive and --seconds above 0")
    import numba

    if args.threads is not None:
        if not 1 <= args.threads <= numba.config.NUMBA_NUM_THREADS:
            parser.error(f"--threads {args.threads}: 1 .. {numba.config.NUMBA_NUM_THREADS}")
        numba.set_num_threads(args.threads)
    print(f"pisc_gym_bench: {os.cpu_count()} CPUs, numba threads {numba.get_num_threads()}, "
          f"load average {os.getloadavg()[0]:.2f} at the start")
    print(f"{'N':>7} {'PISC rig-steps/s':>18} {'CartPole steps/s':>18} {'PISC / CartPole':>16}")
    figures = {}
    for n in args.sizes:
        pisc = pisc_rate(n, args.seconds)
        cart = cartpole_rate(n, args.seconds)
        figures[n] = pisc
        print(f"{n:>7} {pisc:>18,.0f} {cart:>18,.0f} {pisc / cart:>16.3f}", flush=True)
    print(f"load average {os.getloadavg()[0]:.2f} at the end")
    e_pisc, e_cart = pisc_error(), cartpole_error()
    print(f"error against solve_ivp (rtol 1e-12) over 1 s, largest |x, x_dot, theta, "
          f"theta_dot| difference: PISC {e_pisc:.2e}, CartPole {e_cart:.2e}")
    if 10000 in figures:
        met = figures[10000] >= GOAL
        print(f"goal >= {GOAL:,} rig-steps/s at N = 10,000: "
              f"{'met' if met else 'missed'} ({figures[10000]:,.0f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
