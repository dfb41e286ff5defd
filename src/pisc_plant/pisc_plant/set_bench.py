"""Benchmark of plant sets (:func:`pisc_plant.plant_config.plant_set`): prints, asserts nothing.

10 000 rigs of the default plant (full armature, RC filters, end stops, exprk4 at two
steps a period) driven open loop for 400 periods (2 s), stepped by
:meth:`pisc_plant.plant.Plant.advance` in four ways: one configuration for all;
parameters of each rig's own (R, L, J_m, b_m, M, m, l, I drawn about the thesis rig);
one command latency a rig (each period advanced by the latency with the old voltage,
then by the rest with the new one); both. A fifth case draws the latencies anew every
period, so that the operator tables are computed at every call instead of being kept.
Run it with ``.venv/bin/python -c "from pisc_plant.set_bench import measure; measure()"``.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from pisc_msgs_py.progress import progress_bar
from pisc_plant.plant import Plant
from pisc_plant.plant_config import PlantConfig, plant_set

__all__ = ["measure"]


def _draws(rigs: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Parameters of a robustness study: each within +-20 % of the thesis rig's."""
    config = PlantConfig()
    names = ("motor.resistance_ohm", "motor.inductance_h", "motor.rotor_inertia_kgm2",
             "motor.viscous_friction_nms", "rig.cart_mass_kg", "rig.pendulum_mass_kg",
             "rig.pendulum_com_m", "rig.pendulum_inertia_kgm2")
    draws = {}
    for name in names:
        section, field = name.split(".")
        value = getattr(getattr(config, section), field)
        draws[name] = value * rng.uniform(0.8, 1.2, rigs)
    return draws


def _seconds(step: Callable[[np.ndarray, int], np.ndarray], y0: np.ndarray,
             periods: int) -> np.ndarray:
    """Wall and processor seconds (all threads') of ``periods`` periods."""
    y = y0
    start = np.array([time.perf_counter(), time.process_time()])
    for t in range(periods):
        y = step(y, t)
    return np.array([time.perf_counter(), time.process_time()]) - start


def measure(rigs: int = 10_000, periods: int = 400, repeats: int = 3) -> None:
    """Time the four ways (and the fifth) and print ns per rig and period: of the wall
    clock, and of processor time summed over numba's threads (which a machine's other
    work does not lengthen, as long as it leaves the caches alone)."""
    rng = np.random.default_rng(0)
    base = PlantConfig()
    period = base.loop.period_s
    uniform = Plant(base)
    per_rig = Plant(plant_set(base, _draws(rigs, rng)))
    y0 = uniform.initial_state(rng.uniform(-0.1, 0.1, rigs), 0.0, np.pi, 0.0)
    phase = rng.uniform(0.0, 2.0 * np.pi, rigs)
    times = np.arange(periods + 1) * period
    # a 3 Hz sine of 6 V, each rig at its own phase; the command of period t is u[t + 1]
    u = 6.0 * np.sin(2.0 * np.pi * 3.0 * times[:, None] + phase)
    delays = rng.uniform(0.0, 0.002, rigs)
    jitter = rng.uniform(0.0, 0.002, (periods + 1, rigs))

    def split(plant: Plant, latency: Callable[[int], np.ndarray]
              ) -> Callable[[np.ndarray, int], np.ndarray]:
        def step(y: np.ndarray, t: int) -> np.ndarray:
            d = latency(t)
            return plant.advance(plant.advance(y, u[t], d), u[t + 1], period - d)
        return step

    cases = {
        "uniform": lambda y, t: uniform.advance(y, u[t + 1], period),
        "per-rig parameters": lambda y, t: per_rig.advance(y, u[t + 1], period),
        "per-rig latency": split(uniform, lambda t: delays),
        "per-rig parameters and latency": split(per_rig, lambda t: delays),
        "per-rig latency, new every period": split(uniform, lambda t: jitter[t]),
    }
    print(f"pisc_plant.set_bench: {rigs} rigs x {periods} periods of {period * 1e3:g} ms, "
          f"{base.integrator.method} at {base.integrator.substeps} steps a period, best of "
          f"{repeats} runs taken in turn")
    # a bar of the timed runs on stderr when it is a terminal (one update between runs,
    # outside the timed spans)
    with progress_bar(len(cases) * (1 + repeats), "run", "set_bench") as bar:
        # the first period compiles the kernels unless numba's cache has them
        first = {}
        for name, step in cases.items():
            first[name] = _seconds(step, y0, 1)[0]
            bar(1)
        best = {name: np.full(2, np.inf) for name in cases}
        for _ in range(repeats):  # in turn, so that a machine's changing load meets them all
            for name, step in cases.items():
                best[name] = np.minimum(best[name], _seconds(step, y0, periods))
                bar(1)
    reference = best["uniform"]
    print(f"  {'':34s} {'wall':>8s} {'processor':>10s}   ns per rig and period")
    for name, seconds in best.items():
        wall, cpu = seconds / (rigs * periods) * 1e9
        ratio = seconds / reference
        print(f"  {name:34s} {wall:8.1f} {cpu:10.1f}   ({ratio[0]:4.2f} x, {ratio[1]:4.2f} x "
              f"uniform; first period {first[name]:.2f} s)")
