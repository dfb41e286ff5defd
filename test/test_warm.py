"""What set-up compiles: ``./pisc run`` needs the default configuration's kernel layout
for one rig and nothing else; ``./pisc test`` every layout."""

import pytest

from pisc_sim.configuration import load_graph_config
from pisc_plant.plant import Plant, PlantConfig
from pisc_plant.warm import LAYOUTS, layout_models, steps


def test_run_scope_compiles_the_default_configurations_layout_for_one_rig():
    config, _ = load_graph_config("default", {})
    default = Plant(config.plant).layout
    assert Plant(PlantConfig(models=layout_models(*LAYOUTS[0]))).layout == default
    assert [what for what, _ in steps("run")] == ["full + RC filters: one rig"]


def test_all_scope_covers_six_distinct_layouts_with_every_entry_point():
    layouts = {Plant(PlantConfig(models=layout_models(*spec))).layout for spec in LAYOUTS}
    assert len(layouts) == 6
    names = [what for what, _ in steps("all")]
    assert len(names) == 18 and sum(n.endswith("parallel batch") for n in names) == 6


def test_unknown_scope_is_refused():
    with pytest.raises(ValueError, match="one of run, all"):
        list(steps("everything"))
