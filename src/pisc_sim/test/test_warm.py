"""What set-up compiles: ``./pisc run`` needs the default configuration's kernel layout
for one rig and nothing else; ``./pisc test`` every layout, and the default's with Coulomb
friction."""

import ast
import re
from pathlib import Path

import pytest

from pisc_sim.configuration import load_graph_config
from pisc_plant import kernel_jit
from pisc_plant.kernel_jit import SOURCES
from pisc_plant.plant import Plant
from pisc_plant.plant_config import PlantConfig
from pisc_plant.warm import LAYOUTS, layout_models, steps


def test_run_scope_compiles_the_default_configurations_layout_for_one_rig():
    config, _ = load_graph_config("default", {})
    default = Plant(config.plant).layout
    assert Plant(PlantConfig(models=layout_models(*LAYOUTS[0]))).layout == default
    assert [what for what, _ in steps("run")] == ["full + RC filters: one rig"]


def test_all_scope_covers_seven_distinct_layouts_with_every_entry_point():
    """The six layouts (armature x filters) and the default's with Coulomb friction, the
    one identification and the robustness reruns use."""
    layouts = {Plant(PlantConfig(models=layout_models(*spec))).layout for spec in LAYOUTS}
    assert len(layouts) == 7
    assert sum(layout.coulomb for layout in layouts) == 1
    coulomb = Plant(PlantConfig(models=layout_models("full", True, True)))
    assert coulomb.layout.coulomb and coulomb.config.models.friction == "coulomb"
    names = [what for what, _ in steps("all")]
    assert len(names) == 21 and sum(n.endswith("parallel batch") for n in names) == 7


def test_unknown_scope_is_refused():
    with pytest.raises(ValueError, match="one of run, all"):
        list(steps("everything"))


def _pisc_kernel_sources() -> tuple[str, ...]:
    text = (Path(__file__).resolve().parents[3] / "pisc").read_text()
    found = re.search(r"^KERNEL_SOURCES=\(([^)]*)\)", text, re.MULTILINE)
    assert found, "./pisc defines no KERNEL_SOURCES=(...)"
    return tuple(found.group(1).split())


def test_pisc_removes_the_cache_of_the_kernels_sources_in_their_order():
    """./pisc removes stale cache entries file by file in the order of kernel_jit.SOURCES:
    the two lists must be the same."""
    assert _pisc_kernel_sources() == SOURCES


def test_each_kernel_source_comes_after_every_pisc_plant_module_it_imports():
    """A compiled function holds the code of what it calls from other files, and numba
    keys its cache on its own file: every module with compiled code is in SOURCES, after
    each pisc_plant module it imports (whose change makes its entries stale)."""
    package = Path(kernel_jit.__file__).parent
    order = {name: k for k, name in enumerate(SOURCES)}
    for path in sorted(package.glob("*.py")):
        tree = ast.parse(path.read_text())
        imported = {f"{node.module.rsplit('.', 1)[1]}.py" for node in ast.walk(tree)
                    if isinstance(node, ast.ImportFrom) and node.module
                    and node.module.startswith("pisc_plant.")}
        imported |= {f"{alias.name}.py" for node in ast.walk(tree)
                     if isinstance(node, ast.ImportFrom) and node.module == "pisc_plant"
                     for alias in node.names}
        if "kernel_jit.py" in imported:
            assert path.name in order, f"{path.name} compiles kernel code but is not in SOURCES"
        if path.name in order:
            for name in imported:
                assert name in order and order[name] < order[path.name], (
                    f"{path.name} imports {name}, which is not before it in SOURCES")
