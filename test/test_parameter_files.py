"""Parameter files that cannot lie: a value in a part of the plant that the selected
sub-models leave out (friction values with ``models.friction: none``, an RC filter's
corner with the filters off, L with a quasi-static armature) is refused with its name
wherever a plant's parameters are read: a configuration, a run's plant file and
``--plant-set``, a scene, the virtual rig, a distribution (the plant node: test_nodes).
A value equal to its default changes nothing and passes; every shipped file passes."""

from __future__ import annotations

import textwrap

import pytest

from pisc_bringup.graph_cli import main as graph_main
from pisc_robust.uncertainty import distribution_names, load_distribution
from pisc_model.params import unused_by_models
from pisc_msgs_py.config import ConfigError
from pisc_plant.virtual_rig import load_plant
from pisc_plant.virtual_rig_cli import main as rig_main
from pisc_sim.configuration import CONFIG_DIR, load_graph_config, load_run_config
from pisc_sim.scene import load_scene, scene_names

PIVOT = "friction.pivot_viscous_nms = 4e-05 is not used: models.friction is 'none' (no " \
        "friction besides the motor's b_m); set models.friction: coulomb (or viscous, " \
        "without the Coulomb term) to use it, or leave it out"


def params(tmp_path, body: str, name: str = "plant.yaml"):
    path = tmp_path / name
    path.write_text("/**:\n  ros__parameters:\n" + textwrap.indent(textwrap.dedent(body), "    "))
    return path


@pytest.mark.parametrize("flat, named", [
    ({"friction.pivot_viscous_nms": 4e-5}, ["friction.pivot_viscous_nms = 4e-05"]),
    ({"models.friction": "viscous", "friction.cart_coulomb_n": 0.05,
      "friction.cart_viscous_ns_per_m": 0.3},
     ["friction.cart_coulomb_n = 0.05 is not used: models.friction is 'viscous'"]),
    ({"models.sensor_filters": False, "sensors.ir_filter_hz": 20.0,
      "sensors.current_filter_hz": 72.0},
     ["sensors.ir_filter_hz = 20.0 is not used: models.sensor_filters is false"]),
    ({"models.armature": "quasi_static", "motor.inductance_h": 0.01},
     ["motor.inductance_h = 0.01 is not used: models.armature is 'quasi_static'"]),
    ({"models.armature": "ideal_force", "models.current_loop": "ideal",
      "motor.resistance_ohm": 20.0, "motor.rotor_inertia_kgm2": 2e-6},
     ["motor.resistance_ohm = 20.0 is not used: models.armature is 'ideal_force'"]),
])
def test_each_value_the_models_leave_out_is_named_and_defaults_are_not(flat, named):
    found = unused_by_models(flat)
    assert len(found) == len(named), found  # (the defaults: 72 Hz, 2e-6, no coulomb...)
    for text, start in zip(found, named, strict=True):
        assert text.startswith(start), text


def test_a_configuration_file_and_a_run_plant_file_refuse_it(tmp_path):
    lying = params(tmp_path, "friction: {pivot_viscous_nms: 4.0e-5}\n")
    with pytest.raises(ConfigError) as caught:
        load_graph_config(str(lying))
    assert str(caught.value) == PIVOT
    with pytest.raises(ConfigError, match="^plant \\(.*plant.yaml\\): friction.pivot_visc"):
        load_run_config("default", plant=str(lying))
    with pytest.raises(ConfigError, match="^plant: friction.cart_coulomb_n = 0.05 is not"):
        load_run_config("default", plant_overrides={"friction.cart_coulomb_n": 0.05})
    honest = params(tmp_path, "models: {friction: coulomb}\nfriction: {pivot_viscous_nms: "
                    "4.0e-5}\n", "honest.yaml")
    run, _, _ = load_run_config("default", plant=str(honest))
    assert run.true_plant.friction.pivot_viscous_nms == 4e-5


def test_pisc_graph_refuses_the_run_before_it_starts(tmp_path, capsys):
    lying = params(tmp_path, "friction: {cart_coulomb_n: 0.05}\n")
    assert graph_main(["--plant-config", str(lying), "--bag", str(tmp_path / "bag")]) == 2
    err = capsys.readouterr().err
    assert "invalid configuration: plant (" in err and "friction.cart_coulomb_n = 0.05 is " \
        "not used" in err
    assert not (tmp_path / "bag").exists()


def test_the_virtual_rig_refuses_it(tmp_path, capsys):
    with pytest.raises(ConfigError, match="sensors.current_filter_hz = 50.0 is not used"):
        load_plant(None, {"models.sensor_filters": False, "sensors.current_filter_hz": 50.0})
    lying = params(tmp_path, "friction: {pivot_viscous_nms: 4.0e-5}\n")
    assert rig_main(["--params-file", str(lying)]) == 2
    assert f"pisc_virtual_rig: {PIVOT}" in capsys.readouterr().err


def test_a_scene_refuses_it(tmp_path):
    path = tmp_path / "scene.yaml"
    path.write_text("scene:\n  plant: {friction: {pivot_viscous_nms: 4.0e-5}}\n")
    with pytest.raises(ConfigError, match="friction.pivot_viscous_nms = 4e-05 is not used"):
        load_scene(str(path))


@pytest.mark.parametrize("body, message, honest", [
    ("{plant: {friction: {cart_coulomb_n: 0.05}}, parameters: {R}}",
     "distribution.plant: friction.cart_coulomb_n = 0.05 is not used",
     "{plant: {models: {friction: coulomb}, friction: {cart_coulomb_n: 0.05}}, "
     "parameters: {R}}"),
    ("{parameters: {friction.cart_coulomb_n: {uniform: [0.0, 0.1]}}}",
     "distribution.parameters: friction.cart_coulomb_n = 0.1 (varied) is not used: "
     "models.friction is 'none'",
     "{plant: {models: {friction: coulomb}}, parameters: {friction.cart_coulomb_n: "
     "{uniform: [0.0, 0.1]}}}"),
    ("{plant: {models: {friction: viscous}}, parameters: {friction.cart_coulomb_n: "
     "{uniform: [0.0, 0.1]}}}",
     "friction.cart_coulomb_n = 0.1 (varied) is not used: models.friction is 'viscous'",
     "{plant: {models: {friction: viscous}}, parameters: {friction.cart_viscous_ns_per_m: "
     "{uniform: [0.0, 0.1]}}}"),
])
def test_a_distribution_refuses_a_fixed_or_varied_value_the_plant_ignores(tmp_path, body,
                                                                          message, honest):
    config = load_graph_config("default")[0]
    path = tmp_path / "d.yaml"
    body, honest = (text.replace("{R}", "{motor.resistance_ohm: {relative: 0.1}}")
                    for text in (body, honest))
    path.write_text(f"distribution: {body}\n")
    with pytest.raises(ConfigError) as caught:
        load_distribution(str(path), config)
    assert message in str(caught.value)
    path.write_text(f"distribution: {honest}\n")
    load_distribution(str(path), config)  # the same value, with the model that reads it


def test_every_shipped_configuration_scene_and_distribution_passes():
    for config in sorted(p.stem for p in CONFIG_DIR.glob("*.yaml")):
        graph, _ = load_graph_config(config)
        for name in distribution_names():
            load_distribution(name, graph)
    for name in scene_names():
        load_scene(name)
