"""pisc_integrators: the plant's integrators and SciPy's, speed against error.

Two problems, each from a scene:

1. Open-loop playback (``--scene``, default ``thesis-gains``): the full-fidelity plant
   driven by the voltages of a recorded 10 s swing-up, each held over its 5 ms period;
   the voltages come from ``--bag`` (``/pisc/motor/voltage``) or, without one, from the
   scene's closed loop simulated here. Every method is restarted at each sample.
   Reference: ``solve_ivp`` DOP853 at rtol 1e-13, checked against the plant's
   exponential integrator at 64 steps per period.
2. The conservative scene (``--conservative``, default ``conservative``): f = 0 over the
   scene's duration (600 s); error against DOP853 at rtol 1e-13 and the drift of the
   energy (2.54), with python-control's ``input_output_response`` beside SciPy.

Prints one table per problem (wall time, error, energy drift, right-hand-side
evaluations), the comparison the README quotes (the scene's own integrator against the
fastest ``solve_ivp`` setting as accurate), and writes a log-log work-precision plot.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from pisc_sim.closed_loop import simulate
from pisc_sim.scene import Scene, load_scene
from pisc_msgs_py.config import ConfigError
from pisc_plant import work_precision as wp
from pisc_plant.plant import Plant

RTOLS = (1e-3, 1e-5, 1e-7, 1e-9)
REFERENCE_RTOL = 1e-13


def _commands(scene: Scene, bag: Path | None, duration_s: float) -> np.ndarray:
    period = scene.config.loop.period_s
    n = int(round(duration_s / period))
    if bag is None:
        log = simulate(scene.config, duration_s)
        return np.asarray(log["u"][:n])
    from pisc_bag.bag import read_bag
    from pisc_msgs_py.convert import motor_sample_from_msg
    from pisc_msgs_py.topics import VOLTAGE

    samples = sorted((motor_sample_from_msg(m.message) for m in read_bag(bag, [VOLTAGE.name])),
                     key=lambda s: s.stamp_ns)
    if len(samples) < n:
        raise ConfigError(f"{bag}: {len(samples)} voltage commands, {n} needed for "
                          f"{duration_s} s")
    return np.array([s.value for s in samples[:n]])


def _row(result: wp.Result, reference: np.ndarray, drift: float | None) -> str:
    drift_text = f"{drift:9.1e}" if drift is not None else "        -"
    return (f"{result.method:32s} {result.setting:17s} {result.wall_s * 1e3:10.1f} "
            f"{result.error(reference):9.1e} {drift_text} {result.rhs_evaluations:10d}")


HEADER = (f"{'method':32s} {'setting':17s} {'wall [ms]':>10s} {'error':>9s} "
          f"{'drift':>9s} {'rhs evals':>10s}")


def _scipy_grid(quick: bool) -> list[tuple[str, float]]:
    rtols = RTOLS[::2] if quick else RTOLS
    return [(m, r) for m in wp.SCIPY_METHODS for r in rtols]


def _control_rtols(quick: bool) -> tuple[float, ...]:
    return RTOLS[1::2] if quick else RTOLS


def runs(scene: Scene, quick: bool, conservative: bool) -> int:
    """How many integrations :func:`playback_table` (``conservative`` False) or
    :func:`conservative_table` makes for ``scene``: the reference (and the playback's
    check), then one per row."""
    own = sum(len(counts) for _, counts in wp.methods_for(scene.config.plant))
    if conservative:
        return 1 + own + len(_control_rtols(quick))
    return 2 + own + len(_scipy_grid(quick))


def _nothing(n: int) -> None:
    pass


def playback_table(scene: Scene, commands: np.ndarray, quick: bool, out,
                   done: Callable[[int], None] = _nothing) -> list[wp.Result]:
    """The open-loop playback's table on ``out``; ``done(1)`` after each integration."""
    period = scene.config.loop.period_s
    i0 = scene.config.initial
    default = Plant(scene.config.plant)
    y0 = default.initial_state(i0.x_m, i0.x_dot_mps, i0.theta_rad, i0.theta_dot_radps)
    print(f"playback: scene {scene.name}, {len(commands)} voltages held {period * 1e3:g} ms, "
          f"state {', '.join(default.state_names)}", file=out, flush=True)
    reference = wp.playback_scipy(default, y0, commands, period, "DOP853", REFERENCE_RTOL,
                                  REFERENCE_RTOL * 1e-3)
    done(1)
    check = wp.playback(wp.with_integrator(scene.config.plant, "exprk4", 64), y0, commands,
                        period)
    done(1)
    print(f"reference: solve_ivp DOP853 rtol {REFERENCE_RTOL:.0e} ({reference.wall_s:.1f} s); "
          f"exprk4 at 64 steps/period differs from it by "
          f"{check.error(reference.states):.1e}", file=out, flush=True)
    print(HEADER, file=out)
    results = []
    for method, counts in wp.methods_for(scene.config.plant):
        for n in counts:
            r = wp.playback(wp.with_integrator(scene.config.plant, method, n), y0, commands,
                            period)
            results.append(r)
            done(1)
            print(_row(r, reference.states, None), file=out, flush=True)
    for method, rtol in _scipy_grid(quick):
        r = wp.playback_scipy(default, y0, commands, period, method, rtol, rtol * 1e-3)
        results.append(r)
        done(1)
        print(_row(r, reference.states, None), file=out, flush=True)
    own = default.config.integrator
    mine = next(r for r in results if r.method == own.method
                and r.setting == f"{own.substeps} steps/period")
    mine_error = mine.error(reference.states)
    rivals = [r for r in results if r.method.startswith("solve_ivp")
              and r.error(reference.states) <= mine_error]
    print(f"\nscene integrator {own.method}, {own.substeps} steps/period: error "
          f"{mine_error:.1e} in {mine.wall_s * 1e3:.1f} ms", file=out)
    if rivals:
        best = min(rivals, key=lambda r: r.wall_s)
        print(f"fastest solve_ivp as accurate: {best.method} {best.setting}, error "
              f"{best.error(reference.states):.1e} in {best.wall_s * 1e3:.1f} ms: "
              f"{best.wall_s / mine.wall_s:.0f}x slower", file=out, flush=True)
    else:
        print("no solve_ivp setting measured here is as accurate", file=out, flush=True)
    return [reference, *results]


def conservative_table(scene: Scene, quick: bool, out,
                       done: Callable[[int], None] = _nothing) -> list[wp.Result]:
    """The conservative scene's table on ``out``; ``done(1)`` after each integration."""
    period = scene.config.loop.period_s
    plant = Plant(scene.config.plant)
    i0 = scene.config.initial
    y0 = plant.initial_state(i0.x_m, i0.x_dot_mps, i0.theta_rad, i0.theta_dot_radps)
    n = int(round(scene.duration_s / period))
    zeros = np.zeros(n)
    print(f"\nconservative: scene {scene.name}, f = 0 for {scene.duration_s:g} s, samples every "
          f"{period * 1e3:g} ms", file=out, flush=True)
    reference = wp.playback_control(plant, y0, scene.duration_s, period, REFERENCE_RTOL,
                                    REFERENCE_RTOL * 1e-3)
    done(1)
    print(f"reference: input_output_response DOP853 rtol {REFERENCE_RTOL:.0e} "
          f"({reference.wall_s:.1f} s), energy drift "
          f"{wp.energy_drift(plant, reference.states):.1e}", file=out)
    print(HEADER, file=out)
    results = []
    for method, counts in wp.methods_for(scene.config.plant):
        for k in counts:
            r = wp.playback(wp.with_integrator(scene.config.plant, method, k), y0, zeros, period)
            results.append(r)
            done(1)
            print(_row(r, reference.states, wp.energy_drift(plant, r.states)), file=out,
                  flush=True)
    for rtol in _control_rtols(quick):
        r = wp.playback_control(plant, y0, scene.duration_s, period, rtol, rtol * 1e-3)
        results.append(r)
        done(1)
        print(_row(r, reference.states, wp.energy_drift(plant, r.states)), file=out, flush=True)
    own = scene.config.plant.integrator
    mine = next(r for r in results if r.method == own.method
                and r.setting == f"{own.substeps} steps/period")
    print(f"\nscene integrator {own.method}, {own.substeps} steps/period: energy drift "
          f"{wp.energy_drift(plant, mine.states):.1e} over {scene.duration_s:g} s", file=out,
          flush=True)
    return [reference, *results]


def plot(panels: list[tuple[str, list[wp.Result]]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(panels), figsize=(6.5 * len(panels), 5), squeeze=False)
    for ax, (title, results) in zip(axes[0], panels, strict=True):
        reference = results[0].states
        families: dict[str, list[wp.Result]] = {}
        for r in results[1:]:
            families.setdefault(r.method, []).append(r)
        for method, rs in families.items():
            rs = sorted(rs, key=lambda r: r.wall_s)
            errors = [max(r.error(reference), 1e-16) for r in rs]
            ax.loglog([r.wall_s for r in rs], errors, "o-", label=method)
        ax.set_xlabel("wall time [s]")
        ax.set_ylabel("largest state error at the samples")
        ax.set_title(title)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="pisc_integrators",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", default="thesis-gains",
                        help="scene of the open-loop playback (default: thesis-gains)")
    parser.add_argument("--bag", type=Path, help="take the voltages from this bag")
    parser.add_argument("--duration", type=float, default=10.0,
                        help="playback length [s] (default 10)")
    parser.add_argument("--conservative", default="conservative",
                        help="conservative scene (default: conservative); 'none' to skip")
    parser.add_argument("--conservative-duration", type=float,
                        help="length of the conservative run [s] (default: the scene's)")
    parser.add_argument("--png", type=Path, default=Path("work-precision.png"),
                        help="where to write the plot (default: work-precision.png)")
    parser.add_argument("--quick", action="store_true",
                        help="fewer SciPy tolerances (for tests)")
    args = parser.parse_args(argv)
    for name, value in (("--duration", args.duration),
                        ("--conservative-duration", args.conservative_duration)):
        if value is not None and not (math.isfinite(value) and value >= 0.01):
            parser.error(f"{name} {value}: must be at least one period (0.01 s)")
    from pisc_msgs_py.progress import progress_bar

    start = time.perf_counter()
    try:
        scene = load_scene(args.scene)
        conservative = None
        if args.conservative != "none":
            conservative = load_scene(args.conservative)
            if args.conservative_duration is not None:
                conservative = dataclasses.replace(conservative,
                                                   duration_s=args.conservative_duration)
        commands = _commands(scene, args.bag, args.duration)
        total = runs(scene, args.quick, False) + (
            runs(conservative, args.quick, True) if conservative is not None else 0)
        with progress_bar(total, "run", "integrators") as bar:
            out = bar.above(sys.stdout)
            panels = [(f"playback: {scene.name}",
                       playback_table(scene, commands, args.quick, out, bar))]
            if conservative is not None:
                panels.append((f"conservative: {conservative.name}",
                               conservative_table(conservative, args.quick, out, bar)))
    except ConfigError as exc:
        print(f"pisc_integrators: {exc}", file=sys.stderr)
        return 2
    plot(panels, args.png)
    print(f"\nplot: {args.png}; {time.perf_counter() - start:.0f} s in all")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
