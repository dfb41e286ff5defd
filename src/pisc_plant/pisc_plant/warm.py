"""Compile the plant's numba kernel into its cache, as much as a command needs, saying so.

    python -m pisc_plant.warm_cli [run|all]

``run`` (what ``./pisc run`` needs): the entry points of the layout the default scene
uses (full armature, sampled PI loop, quantised sensors with their RC filters, exprk4)
for one rig, the way the plant node and the virtual rig call them. ``all`` (before the
test suite): every layout, and the default's with Coulomb friction (its own entry
points, :mod:`pisc_plant.kernel_batch`), for one rig, for rows and for the parallel batch.
The entry points of plant sets (a model per rig: the robustness and identification work)
are not among them and compile on first use (``test_plant_set.py`` took 59 s in the
first suite run of 2026-12-04, ``all`` already warm).

numba compiles an entry point the first time it is called and caches it on disk
(``cache=True``, :mod:`pisc_plant.kernel_jit`), so what is not compiled here is compiled
on first use, once, by whatever uses it. Compiling ahead matters for two reasons: a plant
node that compiles at start-up misses the graph's start, and processes started in
parallel (tests) would each compile the same entry point. Each step prints one line with
its time, so set-up never sits silent.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator

import numpy as np

from pisc_model.params import ModelParams

__all__ = ["LAYOUTS", "SCOPES", "layout_models", "steps", "warm_up"]

SCOPES = ("run", "all")
# (armature, filters, Coulomb friction); the last, the default scene's with Coulomb
# friction, is what identification and the robustness reruns use
LAYOUTS = (("full", True, False), ("full", False, False), ("quasi_static", True, False),
           ("quasi_static", False, False), ("ideal_force", True, False),
           ("ideal_force", False, False), ("full", True, True))


def layout_models(armature: str, filters: bool, coulomb: bool = False) -> ModelParams:
    """The plant models of one kernel layout (the first of :data:`LAYOUTS` is the default
    scene's)."""
    return ModelParams(armature=armature,
                       current_loop="ideal" if armature == "ideal_force" else "sampled_pi",
                       sensors="quantised" if filters else "ideal", sensor_filters=filters,
                       friction="coulomb" if coulomb else "none")


def steps(scope: str) -> Iterator[tuple[str, Callable[[], None]]]:
    """(what, compile it) for each step of ``scope``."""
    if scope not in SCOPES:
        raise ValueError(f"scope {scope!r}: one of {', '.join(SCOPES)}")
    from pisc_plant.kernel_batch import CHUNK
    from pisc_plant.plant import Plant
    from pisc_plant.plant_config import IntegratorParams, PlantConfig

    layouts = LAYOUTS[:1] if scope == "run" else LAYOUTS
    for armature, filters, coulomb in layouts:
        models = layout_models(armature, filters, coulomb)
        name = (f"{armature}{' + RC filters' if filters else ''}"
                f"{' + Coulomb friction' if coulomb else ''}")

        def plant(models: ModelParams = models) -> Plant:
            return Plant(PlantConfig(models=models, integrator=IntegratorParams("exprk4", 2)))

        def one(plant: Callable[[], Plant] = plant) -> None:
            p = plant()
            y = p.initial_state(0.0)
            p.advance(y, 1.0, 0.005)
            p.derivative(y, 0.0)
            p.end_stops(y)

        yield f"{name}: one rig", one
        if scope == "all":
            def rows(plant: Callable[[], Plant] = plant) -> None:
                p = plant()
                p.advance(p.initial_state(np.zeros(2)), np.zeros(2), 0.005)

            def batch(plant: Callable[[], Plant] = plant) -> None:
                p = plant()
                many = CHUNK + 1  # above one chunk: the parallel entry point
                p.advance(p.initial_state(np.zeros(many)), np.zeros(many), 0.005)

            yield f"{name}: rows", rows
            yield f"{name}: parallel batch", batch


def warm_up(scope: str = "all", say: Callable[[str], None] | None = None) -> float:
    """Compile (or load from the cache) the entry points of ``scope``; seconds in all.

    ``say`` receives text, not lines: each step's name and number before it compiles
    (``"  kernel full + RC filters: one rig (1/3) ..."``), so that a terminal shows what
    the minutes of a first compile are spent on, then its seconds and the line's end
    (``" 41.2 s\\n"``)."""
    start = time.perf_counter()
    todo = list(steps(scope))
    for number, (what, compile_it) in enumerate(todo, 1):
        if say is not None:
            say(f"  kernel {what} ({number}/{len(todo)}) ...")
        began = time.perf_counter()
        compile_it()
        if say is not None:
            say(f" {time.perf_counter() - began:.1f} s\n")
    return time.perf_counter() - start
