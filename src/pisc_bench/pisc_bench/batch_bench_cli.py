"""pisc_batch_bench: how many simulated seconds per wall second the batch mode reaches.

Runs a scene's closed loop (default: the thesis rig at full fidelity, its own
integrator) for many rigs at once through :func:`pisc_sim.closed_loop.simulate_batch`
(the controllers compiled, :mod:`pisc_sim.batch_controllers`, and the plant's compiled
kernel, each over the rigs in parallel) and prints the rate, with the plant's share
measured apart and the same run with the laws applied rig by rig in Python over the
arrays (the array path; the same bits) for comparison.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from pisc_sim.closed_loop import simulate_batch
from pisc_sim.scene import DEFAULT_SCENE, load_scene
from pisc_msgs_py.config import ConfigError, parse_overrides
from pisc_plant.plant import Plant


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="pisc_batch_bench",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", default=DEFAULT_SCENE)
    parser.add_argument("--rigs", type=int, default=10000)
    parser.add_argument("--duration", type=float, default=2.0, help="simulated seconds")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    parser.add_argument("--json", type=Path, metavar="FILE",
                        help="also write the figures to FILE (for pisc_bench)")
    args = parser.parse_args(argv)
    if args.rigs < 1:
        parser.error(f"--rigs {args.rigs}: must be at least 1")
    if not (math.isfinite(args.duration) and args.duration > 0):
        parser.error(f"--duration {args.duration}: must be a positive number of seconds")
    try:
        scene = load_scene(args.scene, parse_overrides(args.set))
    except ConfigError as exc:
        print(f"pisc_batch_bench: {exc}", file=sys.stderr)
        return 2
    import numba

    cfg = scene.config
    integ = cfg.plant.integrator
    starts = np.linspace(-0.1, 0.1, args.rigs)
    for controllers in ("compiled", "numpy"):  # compile or load every path this size takes
        simulate_batch(cfg, starts, 0.01, controllers=controllers)
    from pisc_msgs_py.progress import progress_bar

    # a bar of the cycles on stderr when it is a terminal (one call a cycle, all rigs)
    with progress_bar(0, "cycle", "batch") as bar:
        start = time.perf_counter()
        outcome = simulate_batch(cfg, starts, args.duration,
                                 hold_start_s=min(6.0, args.duration),
                                 progress=lambda k, n: bar.to(k, n))
        wall = time.perf_counter() - start
    start = time.perf_counter()
    simulate_batch(cfg, starts, args.duration, hold_start_s=min(6.0, args.duration),
                   controllers="numpy")
    numpy_wall = time.perf_counter() - start
    periods = int(round(args.duration / cfg.loop.period_s)) + 1
    plant = Plant(cfg.plant)
    y = plant.initial_state(starts)
    u = np.zeros(args.rigs)
    plant.advance(y, u, cfg.loop.period_s)
    start = time.perf_counter()
    for _ in range(50):
        y = plant.advance(y, u, cfg.loop.period_s)
    plant_wall = (time.perf_counter() - start) / 50
    sim_seconds = args.rigs * args.duration
    caught = np.isfinite(outcome.caught_at_s)
    f = {"scene": scene.name, "rigs": args.rigs, "duration_s": args.duration,
         "threads": numba.get_num_threads(), "sim_s_per_s": sim_seconds / wall,
         "ns_per_rig_period": wall / periods / args.rigs * 1e9,
         "numpy_sim_s_per_s": sim_seconds / numpy_wall,
         "plant_ns_per_rig_period": plant_wall / args.rigs * 1e9,
         "plant_sim_s_per_s": cfg.loop.period_s * args.rigs / plant_wall,
         "caught": int(caught.sum())}
    print(f"scene {scene.name}, {args.rigs} rigs x {args.duration:g} s, integrator "
          f"{integ.method} {integ.substeps} steps/period, {f['threads']} threads")
    print(f"closed loop: {wall:.2f} s wall, {f['sim_s_per_s']:.0f} simulated s per wall s, "
          f"{f['ns_per_rig_period']:.0f} ns per rig and period")
    print(f"closed loop, numpy controller cores: {numpy_wall:.2f} s wall, "
          f"{f['numpy_sim_s_per_s']:.0f} simulated s per wall s "
          f"(compiled {numpy_wall / wall:.2f}x as fast)")
    print(f"plant alone: {f['plant_ns_per_rig_period']:.0f} ns per rig and period "
          f"({f['plant_sim_s_per_s']:.0f} simulated s per wall s)")
    print(f"caught by the end: {f['caught']} of {args.rigs}")
    if args.json is not None:
        args.json.write_text(json.dumps(f) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
