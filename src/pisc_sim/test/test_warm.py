"""What set-up compiles: ``./pisc run`` needs the default configuration's kernel layout
for one rig and nothing else; ``./pisc test`` every layout, and the default's with Coulomb
friction."""

import pytest

from pisc_sim.configuration import load_graph_config
from pisc_plant.plant import Plant, PlantConfig
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
