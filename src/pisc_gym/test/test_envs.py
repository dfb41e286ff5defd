"""The environments are PISC's rig: the controllers as a policy give the pure closed
loop's bits, a vector environment gives N single ones, Gymnasium's checker passes, a
seed gives the same episode, and bad input is refused by name."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import pisc_gym  # noqa: F401 (registers the environments)
from pisc_gym.env import PiscEnv
from pisc_gym.vector import PiscVectorEnv
from pisc_msgs_py.config import ConfigError
from pisc_sim.closed_loop import Controllers, simulate
from pisc_sim.scene import load_scene


def closed_loop_of(env: PiscEnv, rig: dict, seconds: float):
    """The pure closed loop (pisc_sim.closed_loop.simulate) of the rig ``env`` drew: the
    scene with the distribution's fixed plant and the rig's values as plant overrides."""
    task = env.task
    fixed = dict(task.distribution.plant) if task.distribution is not None else {}
    scene = load_scene(task.scene.name, plant_overrides={**fixed, **rig})
    return scene.config, simulate(scene.config, seconds)


def run_policy(env: PiscEnv, seed: int, steps: int, current: bool):
    """PISC's controllers (estimator, supervisor, current loop: whatever laws the
    configuration names) as the policy; the voltages, samples and true states."""
    obs, info = env.reset(seed=seed)
    controllers = Controllers(env.task.config)
    rows = []
    for _ in range(steps):
        out = controllers.step(*(float(v) for v in obs[:3]))
        action = out.i_d if current else out.voltage
        obs_before = obs
        obs, _, terminated, truncated, step_info = env.step(np.array([action]))
        rows.append((*obs_before[:3], out.voltage, step_info["voltage_v"]))
        if terminated or truncated:
            break
    return info["rig"], np.array(rows)


@pytest.mark.parametrize("distribution, task, current", [
    (None, "swing_up", False), ("thesis-rig", "swing_up", False),
    ("thesis-rig", "swing_up", True), ("thesis-rig", "catch", False)])
def test_controllers_as_policy_give_the_closed_loops_voltages_bit_for_bit(distribution, task,
                                                                          current):
    env = PiscEnv(task, distribution=distribution, episode_s=4.0,
                  action="current" if current else "voltage")
    rig, rows = run_policy(env, 11, 800, current)
    config, log = closed_loop_of(env, rig, 4.0)
    n = len(rows)
    assert n > 400  # the episode ran (the cart stayed in the safe range)
    measured = np.column_stack([log["x"], log["theta"], log["i"]])[:n]
    np.testing.assert_array_equal(rows[:, :3], measured)  # the samples, bit for bit
    np.testing.assert_array_equal(rows[:, 3], log["u"][:n])  # the controllers' voltages
    np.testing.assert_array_equal(rows[:, 4], log["u"][:n])  # the env's voltage
    if distribution is not None:  # a randomised rig: the draw is not the nominal one
        assert rig["motor.resistance_ohm"] != config.plant.motor.resistance_ohm
        assert rig["noise.x_std_m"] > 0.0


def test_a_caught_pendulum_is_rewarded_and_the_episode_truncates():
    env = PiscEnv("swing_up", episode_s=10.0)
    obs, _ = env.reset(seed=0)
    controllers = Controllers(env.task.config)
    total, steps = 0.0, 0
    while True:
        out = controllers.step(*(float(v) for v in obs[:3]))
        obs, reward, terminated, truncated, info = env.step(np.array([out.voltage]))
        total += reward
        steps += 1
        if terminated or truncated:
            break
    assert truncated and not terminated and steps == 2000
    x, _, theta, _, _ = info["true_state"]
    assert abs(np.cos(theta) - 1.0) < 1e-3 and abs(x) < 0.02  # held upright at x* = 0
    # the reward's centre is the safe range's middle, -0.05 m, 5 cm from the controller's
    # x*: 1 - x_weight (x + 0.05)^2 = 1 - 10 * 0.05^2 = 0.975, less a little voltage
    assert reward == pytest.approx(1.0 - 10.0 * (x + 0.05) ** 2, abs=2e-3)
    assert reward > 0.97


def _random_actions(n: int, steps: int, limit: float) -> np.ndarray:
    return np.random.default_rng(5).uniform(-limit, limit, (steps, n))


@pytest.mark.parametrize("n, picked", [(5, range(5)), (300, (0, 17, 256, 299))])
def test_the_vector_environment_is_n_single_ones(n, picked):
    options = dict(task="catch", distribution="thesis-rig", episode_s=0.15, velocities=True,
                   fall_rad=0.35)
    vector = PiscVectorEnv(n, **options)
    actions = _random_actions(n, 70, 11.47)
    obs, infos = vector.reset(seed=100)
    got = [(obs, None, None, None)]
    for a in actions:
        o, r, te, tr, _ = vector.step(a)
        got.append((o, r, te, tr))
    # rigs fell and were reset, and others reached the episode's end
    assert any(te.any() for _, _, te, _ in got[1:]) and any(tr.any() for *_, tr in got[1:])
    for k in picked:
        env = PiscEnv(**options)
        o, info = env.reset(seed=100 + k)
        assert info["rig"] == {name: v[k] for name, v in infos["rig"].items()}
        np.testing.assert_array_equal(o, got[0][0][k])
        done = False
        for step, a in enumerate(actions, start=1):
            if done:
                o, _ = env.reset()
                r, te, tr = 0.0, False, False
            else:
                o, r, te, tr, _ = env.step(np.array([a[k]]))
            done = te or tr
            vo, vr, vte, vtr = got[step]
            np.testing.assert_array_equal(o, vo[k])
            assert (r, te, tr) == (vr[k], vte[k], vtr[k]), (k, step)


@pytest.mark.parametrize("env_id", ["pisc/SwingUp-v0", "pisc/Catch-v0"])
def test_gymnasiums_checker_passes(env_id):
    check_env(gym.make(env_id, distribution="thesis-rig").unwrapped, skip_render_check=True)
    check_env(gym.make(env_id, action="current", velocities=True).unwrapped,
              skip_render_check=True)


def test_make_vec_builds_the_vector_environment():
    vector = gym.make_vec("pisc/Catch-v0", num_envs=3, distribution="thesis-rig")
    assert isinstance(vector, PiscVectorEnv) and vector.num_envs == 3
    obs, _ = vector.reset(seed=0)
    assert obs.shape == (3, 3)


def test_a_seed_gives_the_same_episode_twice_and_another_seed_another():
    env = PiscEnv("swing_up", distribution="thesis-rig", velocities=True)
    actions = _random_actions(1, 300, 11.47)

    def episode(seed):
        obs, info = env.reset(seed=seed)
        out = [obs]
        for a in actions:
            obs, reward, _, _, step_info = env.step(a)
            out.append(np.concatenate([obs, [reward], step_info["true_state"]]))
        return info["rig"], np.concatenate(out)

    rig1, first = episode(3)
    rig2, second = episode(3)
    assert rig1 == rig2
    np.testing.assert_array_equal(first, second)
    rig3, third = episode(4)
    assert rig3 != rig1 and not np.array_equal(third, first)


@pytest.mark.parametrize("options, message", [
    ({"scene": "no-such-scene"}, "no-such-scene: no such scene"),
    ({"distribution": "no-such-rig"}, "no-such-rig: no such distribution"),
    ({"action": "torque"}, "action = 'torque': unknown"),
    ({"episode_s": -1.0}, "episode_s = -1.0"),
    ({"start_angle_rad": 4.0}, "start_angle_rad = 4.0"),
    ({"scene": "ideal-cart-pole"}, "ideal force source"),
    ({"wind": 3.0}, "wind"),
])
def test_bad_input_is_refused_naming_it(options, message):
    with pytest.raises((ConfigError, TypeError), match=message):
        PiscEnv("catch", **options)
    with pytest.raises((ConfigError, TypeError), match=message):
        gym.make_vec("pisc/Catch-v0", num_envs=2, **options)


def test_an_unknown_task_is_refused():
    with pytest.raises(ConfigError, match="task = 'balance': unknown"):
        PiscEnv("balance")
