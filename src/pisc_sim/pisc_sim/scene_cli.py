"""pisc_scene: list scenes, write one as a ROS 2 parameter file, or run it without ROS.

    pisc_scene list                         the shipped scenes and what they model
    pisc_scene params NAME [-o FILE]        the scene's parameters for ros2 run --params-file
                      [--plant]             (the controllers'; --plant: the plant's, with
                                            the scene's plant: block, its sections only)
    pisc_scene run NAME [--set N=V] [--duration S]
                                            simulate the scene in this process (the pure
                                            closed loop, or open loop for controller: none)
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from pisc_sim.closed_loop import simulate
from pisc_sim.configuration import params_file_text, plant_only
from pisc_sim.scene import load_scene, scene_names, write_scene_params
from pisc_msgs_py.config import ConfigError, parse_overrides
from pisc_model.dynamics import energy, wrap_to_upright
from pisc_plant.plant import Plant


def _models(scene) -> str:
    m = scene.config.simulated_plant.models
    return (f"armature {m.armature}, current loop {m.current_loop}, sensors {m.sensors}"
            f"{' + filters' if m.sensor_filters else ''}, friction {m.friction}, "
            f"end stops {'on' if m.end_stops else 'off'}")


def run(scene, out) -> int:
    cfg = scene.config
    simulated = cfg.simulated_plant  # the scene's plant: block, if any (model error)
    plant = Plant(simulated)
    print(f"scene {scene.name}: {scene.description}", file=out)
    if scene.plant_overrides:
        print("plant (model error): " + ", ".join(
            f"{k}={v}" for k, v in scene.plant_overrides.items()), file=out)
    print(f"models: {_models(scene)}; state {', '.join(plant.state_names)}; integrator "
          f"{simulated.integrator.method}, {simulated.integrator.substeps} steps/period",
          file=out)
    start = time.perf_counter()
    if scene.closed_loop:
        log = simulate(cfg, scene.duration_s)
        wall = time.perf_counter() - start
        theta = np.abs(wrap_to_upright(log["true_theta"]))
        mode = log["mode"]
        catches = np.flatnonzero(np.diff(mode) != 0)
        print(f"{len(log.data)} cycles ({scene.duration_s:g} s) in {wall:.2f} s wall", file=out)
        print(f"mode changes {len(catches)}; final |theta| {theta[-1]:.4f} rad, "
              f"x {log['true_x'][-1]:+.4f} m; largest |x| {np.abs(log['true_x']).max():.4f} m",
              file=out)
        return 0
    i0 = cfg.initial
    y = plant.initial_state(i0.x_m, i0.x_dot_mps, i0.theta_rad, i0.theta_dot_radps)
    period = cfg.loop.period_s
    n = int(round(scene.duration_s / period))
    rig = simulated.rig
    e0 = float(energy(rig, y[1], y[2], y[3]))
    drift = 0.0
    for _ in range(n):
        y = plant.advance(y, 0.0, period)
        drift = max(drift, abs(float(energy(rig, y[1], y[2], y[3])) - e0))
    wall = time.perf_counter() - start
    print(f"open loop, zero input: {n} periods ({scene.duration_s:g} s) in {wall:.2f} s wall",
          file=out)
    print(f"energy (2.54) {e0:.6e} J; largest |E - E0| / |E0| {drift / abs(e0):.2e}; final "
          f"state {np.array2string(y, precision=5)}", file=out)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="pisc_scene", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("list", help="the shipped scenes")
    params = sub.add_parser("params", help="write a scene as a ROS 2 parameter file")
    params.add_argument("scene")
    params.add_argument("-o", "--output", type=Path, help="file (default: standard output)")
    params.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    params.add_argument("--plant", action="store_true",
                        help="the plant's parameters (with the scene's plant: block) instead "
                        "of the controllers'")
    run_p = sub.add_parser("run", help="simulate a scene in this process")
    run_p.add_argument("scene")
    run_p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    run_p.add_argument("--duration", type=float, help="run length [s] (default: the scene's)")
    args = parser.parse_args(argv)
    try:
        if args.command == "list":
            for name in scene_names():
                scene = load_scene(name)
                print(f"{name:18s} {scene.description}\n{'':18s} {_models(scene)}")
            return 0
        overrides = parse_overrides(args.set)
        if args.command == "run" and args.duration is not None:
            if not args.duration > 0:
                parser.error(f"--duration {args.duration}: must be positive")
        scene = load_scene(args.scene, overrides)
        if args.command == "params":
            if args.output is None:
                sys.stdout.write(params_file_text(plant_only(scene.plant_flat)
                                                  if args.plant else scene.flat))
            else:
                write_scene_params(scene, args.output, plant=args.plant)
            return 0
        if args.duration is not None:
            import dataclasses

            scene = dataclasses.replace(scene, duration_s=args.duration)
        return run(scene, sys.stdout)
    except ConfigError as exc:
        print(f"pisc_scene: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
