"""Scenes: loading, refusal of bad ones, what each shipped scene does, determinism."""

import math
import textwrap

import numpy as np
import pytest
import yaml

from pisc_sim.closed_loop import simulate, simulate_batch
from pisc_sim.configuration import PLANT_READS
from pisc_sim.scene import DEFAULT_SCENE, load_scene, scene_names
from pisc_sim.scene_cli import main as scene_main
from pisc_msgs_py.config import ConfigError
from pisc_model.dynamics import wrap_to_upright
from pisc_plant.plant import Plant


def test_shipped_scenes():
    assert set(scene_names()) >= {"thesis-rig", "thesis-gains", "ideal-cart-pole",
                                  "conservative", "seed-000", "seed-001"}
    assert DEFAULT_SCENE == "thesis-rig"


@pytest.mark.parametrize("name,size", [("thesis-rig", 7), ("ideal-cart-pole", 4),
                                       ("conservative", 4), ("seed-001", 4)])
def test_a_scene_carries_only_the_state_its_models_need(name, size):
    assert Plant(load_scene(name).config.plant).size == size


def test_seed_rigs_are_the_seeds_parameters():
    rig = load_scene("seed-001").config.plant.rig
    assert (rig.cart_mass_kg, rig.pendulum_mass_kg, rig.pendulum_com_m,
            rig.pendulum_inertia_kgm2, rig.gravity_mps2) == (2.0, 0.1, 0.5, 0.0, 9.81)
    rig = load_scene("seed-000").config.plant.rig
    assert (rig.cart_mass_kg, rig.pendulum_mass_kg, rig.pendulum_com_m,
            rig.pendulum_inertia_kgm2, rig.gravity_mps2) == (1.0, 1.0, 1.0, 0.0, 9.8)


def test_seed_001_gains_from_its_poles_are_the_published_ones():
    """SPEC section 6: F = 74.698 theta + 16.587 theta_dot + 10.194 x + 9.1743 x_dot."""
    from pisc_control.supervisor import Supervisor

    k = Supervisor(load_scene("seed-001").config.supervisor).gain  # on x, x_dot, theta, theta_dot
    np.testing.assert_allclose(np.abs(k), [10.194, 9.1743, 74.698, 16.587], rtol=2e-4)


@pytest.mark.parametrize("name", ["seed-000", "seed-001", "ideal-cart-pole", "thesis-rig"])
def test_closed_loop_scenes_end_balanced(name):
    scene = load_scene(name)
    log = simulate(scene.config, scene.duration_s)
    late = log["t"] >= 6.0
    assert np.all(np.abs(wrap_to_upright(log["true_theta"][late])) < 0.05)
    assert np.all(np.abs(log["true_x"][late]) < 0.05)
    assert not np.any(log["mode"] == 2)  # no fault


def test_the_thesis_gains_scene_never_catches_in_simulation():
    """Why it is the playback test of pisc_integrators: 10 s of swing-up, no balancing
    on the open-loop-unstable upright."""
    scene = load_scene("thesis-gains")
    log = simulate(scene.config, scene.duration_s)
    assert np.all(log["mode"] == 0)
    assert np.max(np.abs(log["u"])) == pytest.approx(11.47, abs=0.01)


def test_same_scene_and_seed_give_bit_identical_runs_and_another_seed_does_not():
    noise = {"noise.seed": 7, "noise.x_std_m": 1e-3, "noise.theta_std_rad": 2e-3,
             "noise.current_std_a": 0.01}
    a = simulate(load_scene("thesis-rig", noise).config, 3.0).data
    b = simulate(load_scene("thesis-rig", noise).config, 3.0).data
    np.testing.assert_array_equal(a, b)
    c = simulate(load_scene("thesis-rig", {**noise, "noise.seed": 8}).config, 3.0).data
    assert not np.array_equal(a, c)


def test_batch_mode_runs_the_same_cores_as_one_rig():
    scene = load_scene("thesis-rig")
    starts = np.array([-0.05, 0.0, 0.05])
    outcome = simulate_batch(scene.config, starts, 10.0)
    for k, x0 in enumerate(starts):
        single = load_scene("thesis-rig", {"initial.x_m": float(x0)})
        log = simulate(single.config, 10.0)
        caught = log["t"][np.argmax(log["mode"] == 1)]
        assert outcome.caught_at_s[k] == pytest.approx(caught, abs=1e-9)
        assert outcome.x_max_m[k] == pytest.approx(max(float(x0), log["true_x"].max()), abs=1e-6)


def _write(tmp_path, body):
    path = tmp_path / "scene.yaml"
    path.write_text(textwrap.dedent(body))
    return str(path)


@pytest.mark.parametrize("body,match", [
    ("scene:\n  durationn_s: 3\n", r"scene.durationn_s: unknown key"),
    ("scene:\n  duration_s: -1\n", r"scene.duration_s = -1 must be a positive number"),
    ("scene:\n  controller: pid\n", r"scene.controller = 'pid' must be one of graph, none"),
    ("scene:\n  parameters: {rig: {cart_mass_kg: -0.4}}\n", r"rig.cart_mass_kg"),
    ("scene:\n  parameters: {models: {armature: ideal_force}}\n",
     r"models.current_loop = 'sampled_pi' does not go with models.armature"),
    ("scene:\n  parameters: {models: {armature: battery}}\n", r"models.armature"),
    ("nothing: here\n", r"one mapping under the key 'scene'"),
    ("scene:\n  record: /pisc/state\n", r"scene.record must be a list of topic names"),
    ("scene:\n  record: [/pisc/stat]\n",
     r"scene.record: /pisc/stat is not a topic of the graph \(topics: /pisc/joint_states"),
])
def test_bad_scenes_are_refused_naming_what_is_wrong(tmp_path, body, match):
    with pytest.raises(ConfigError, match=match):
        load_scene(_write(tmp_path, body))


def test_a_scene_says_what_pisc_graph_records(tmp_path):
    assert load_scene(DEFAULT_SCENE).record is None  # every topic
    scene = load_scene(_write(tmp_path, "scene:\n  record: [/pisc/state, /diagnostics]\n"))
    assert scene.record == ("/pisc/state", "/diagnostics")


def test_a_scenes_plant_block_sets_the_plant_only(tmp_path, capsys):
    """Model error in a scene: the plant: block is the simulated plant's, the controllers
    keep the configuration's model; pisc_scene params writes either file."""
    path = _write(tmp_path, """\
        scene:
          parameters: {initial: {x_m: 0.05}}
          plant: {motor: {resistance_ohm: 18.2}}
        """)
    scene = load_scene(path)
    assert scene.plant_overrides == {"motor.resistance_ohm": 18.2}
    assert scene.config.true_plant.motor.resistance_ohm == 18.2
    assert scene.config.simulated_plant is scene.config.true_plant
    assert scene.config.plant.motor.resistance_ohm == 14.0
    assert scene.config.initial.x_m == 0.05
    assert (scene.flat["motor.resistance_ohm"], scene.plant_flat["motor.resistance_ohm"]) == (
        14.0, 18.2)
    # overrides given to load_scene go after the block
    assert load_scene(path, plant_overrides={"motor.resistance_ohm": 20.0}).config.true_plant \
        .motor.resistance_ohm == 20.0
    assert load_scene(DEFAULT_SCENE).config.true_plant is None
    for plant, value in (([], "14.0"), (["--plant"], "18.2")):
        out = tmp_path / "p.yaml"
        assert scene_main(["params", path, "-o", str(out), *plant]) == 0
        assert f"resistance_ohm: {value}" in out.read_text()
    # the plant's file holds the plant's sections only, on a file and on standard output
    assert scene_main(["params", path, "--plant"]) == 0
    for text in (out.read_text(), capsys.readouterr().out):
        sections = set(yaml.safe_load(text)["/**"]["ros__parameters"])
        assert sections <= set(PLANT_READS) and {"rig", "motor", "initial"} <= sections
        assert "swing_up.law" in scene.flat and "swing_up" not in sections
    assert scene_main(["run", path, "--duration", "0.5"]) == 0
    assert "plant (model error): motor.resistance_ohm=18.2" in capsys.readouterr().out


@pytest.mark.parametrize("plant,match", [
    ("{motor: {nosuch: 1}}", r"motor.nosuch: unknown parameter"),
    ("{swing_up: {k_v: 1}}",
     r"scene.plant.swing_up.k_v: the plant does not read section 'swing_up'"),
    ("{motor: {resistance_ohm: -1}}", r"motor.resistance_ohm = -1.0 must be positive"),
    ("3", r"scene.plant must be a mapping of sections"),
])
def test_bad_plant_blocks_are_refused_naming_what_is_wrong(tmp_path, plant, match):
    with pytest.raises(ConfigError, match=match):
        load_scene(_write(tmp_path, f"scene:\n  plant: {plant}\n"))


def test_a_scene_whose_linearisation_is_uncontrollable_is_refused(tmp_path):
    path = _write(tmp_path, """\
        scene:
          parameters: {rig: {gravity_mps2: 0.0}}
        """)
    with pytest.raises(ConfigError, match=r"not controllable \(rank of the controllability"):
        load_scene(path)


def test_swing_up_gains_on_the_boundary_of_3_29_are_refused_and_just_inside_stay_finite(
        tmp_path):
    """Hard case: at k_v / k_e = 2 m g l a2 the denominator of (3.30) reaches zero at
    the hanging rest state; PISC refuses the gain set (saying (3.29)). Just inside the
    bound every state gives a finite force."""
    from pisc_control.swing_up import gain_condition, swing_up_force

    rig = load_scene("thesis-rig").config.plant.rig
    k_e = 0.5
    _, bound = gain_condition(rig, load_scene("thesis-rig").config.supervisor.swing_up)
    bound_kv = k_e * rig.a2 * 2.0 * rig.mgl
    path = _write(tmp_path, f"""\
        scene:
          configuration: lyapunov-tuned
          parameters: {{swing_up: {{law: lyapunov, k_v: {bound_kv!r}, k_e: {k_e},
                                    energy_target_j: 0.0}}}}
        """)
    with pytest.raises(ConfigError, match=r"\(3.29\)"):
        load_scene(path)
    inside = load_scene(path.replace("scene.yaml", "scene.yaml"),
                        {"swing_up.k_v": bound_kv * (1 + 1e-9)}).config.supervisor.swing_up
    rng = np.random.default_rng(0)
    theta = np.concatenate([[math.pi, -math.pi, 3 * math.pi], rng.uniform(-10, 10, 10000)])
    theta_dot = np.concatenate([[0.0, 0.0, 0.0], rng.uniform(-30, 30, 10000)])
    x = rng.uniform(-0.2, 0.1, theta.size)
    x_dot = rng.uniform(-2, 2, theta.size)
    f = swing_up_force(rig, inside, x, x_dot, theta, theta_dot, 0.0)
    assert np.all(np.isfinite(f))
    assert bound > 0


def test_pisc_scene_command(tmp_path, capsys):
    assert scene_main(["list"]) == 0
    assert "seed-001" in capsys.readouterr().out
    out = tmp_path / "p.yaml"
    assert scene_main(["params", "ideal-cart-pole", "-o", str(out)]) == 0
    text = out.read_text()
    assert "armature: ideal_force" in text and "ros__parameters" in text
    assert scene_main(["run", "conservative", "--duration", "5"]) == 0
    printed = capsys.readouterr().out
    drift = float(printed.split("largest |E - E0| / |E0| ")[1].split(";")[0])
    assert drift < 1e-9
    assert scene_main(["run", "no-such-scene"]) == 2
    assert "no such scene" in capsys.readouterr().err
