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


LATE = """distribution:
  description: latencies past half a period and past the period, a few unknowns
  parameters:
    actuator.command_delay_s: {uniform: [0.0, 0.007]}
    motor.resistance_ohm: {relative: 0.3}
    rig.pendulum_mass_kg: {relative: 0.2}
    noise.x_std_m: {uniform: [0.0, 0.00043]}
"""


@pytest.fixture(scope="module")
def late(tmp_path_factory) -> str:
    """A distribution whose latencies cut a period into parts of one and two substeps
    in either part, or miss the period (the command then takes effect at the next)."""
    path = tmp_path_factory.mktemp("late") / "late.yaml"
    path.write_text(LATE)
    return str(path)


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


@pytest.mark.parametrize("distribution, task, current, seed", [
    (None, "swing_up", False, 11), ("thesis-rig", "swing_up", False, 11),
    ("thesis-rig", "swing_up", True, 11), ("thesis-rig", "catch", False, 11),
    ("late", "swing_up", False, 0), ("late", "swing_up", True, 4)])
def test_controllers_as_policy_give_the_closed_loops_voltages_bit_for_bit(
        distribution, task, current, seed, late):
    if distribution == "late":
        distribution = late
    env = PiscEnv(task, distribution=distribution, episode_s=4.0,
                  action="current" if current else "voltage")
    rig, rows = run_policy(env, seed, 800, current)
    if distribution == late:  # seed 0: past half a period; seed 4: past the period
        period = env.task.period_s
        assert period / 2 < rig["actuator.command_delay_s"] < period or seed != 0
        assert rig["actuator.command_delay_s"] > period or seed != 4
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
    """The configuration's controllers swing up and hold (whatever laws it names); every
    step's reward is r = (1 + cos theta)/2 - w_x (x - x_mid)^2 - w_u (u / u_max)^2 of the
    true state after it and the voltage commanded, computed here from the info."""
    env = PiscEnv("swing_up", episode_s=10.0, x_weight=7.0, voltage_weight=0.03)
    obs, _ = env.reset(seed=0)
    controllers = Controllers(env.task.config)
    low, high = env.task.config.supervisor.safety.x_min_m, env.task.config.supervisor.safety.x_max_m
    u_max = env.task.config.simulated_plant.actuator.full_scale_v
    rewards, expected = [], []
    while True:
        out = controllers.step(*(float(v) for v in obs[:3]))
        obs, reward, terminated, truncated, info = env.step(np.array([out.voltage]))
        x, _, theta, _, _ = info["true_state"]
        rewards.append(reward)
        expected.append((1.0 + np.cos(theta)) / 2.0 - 7.0 * (x - (low + high) / 2.0) ** 2
                        - 0.03 * (info["voltage_v"] / u_max) ** 2)
        if terminated or truncated:
            break
    assert truncated and not terminated and len(rewards) == 2000
    assert abs(np.cos(theta) - 1.0) < 1e-3  # held upright
    np.testing.assert_allclose(rewards, expected, rtol=0, atol=1e-12)
    assert rewards[0] < 0.01 < 0.9 < rewards[-1]  # hanging at the start, upright at the end


def _random_actions(n: int, steps: int, limit: float) -> np.ndarray:
    return np.random.default_rng(5).uniform(-limit, limit, (steps, n))


@pytest.mark.parametrize("n, picked, distribution, action", [
    (5, range(5), "thesis-rig", "voltage"), (300, (0, 17, 256, 299), "thesis-rig", "voltage"),
    (40, range(0, 40, 3), "late", "current")])
def test_the_vector_environment_is_n_single_ones(n, picked, distribution, action, late):
    options = dict(task="catch", distribution=late if distribution == "late" else distribution,
                   episode_s=0.15, velocities=True, fall_rad=0.35, action=action,
                   start="rest")  # at rest, some of them fall within the episode
    vector = PiscVectorEnv(n, **options)
    actions = _random_actions(n, 70, vector.single_action_space.high[0])
    obs, infos = vector.reset(seed=100)
    got = [(obs, None, None, None)]
    for a in actions:
        o, r, te, tr, _ = vector.step(a)
        got.append((o, r, te, tr))
    # rigs fell and were reset, and others reached the episode's end
    assert any(te.any() for _, _, te, _ in got[1:]) and any(tr.any() for *_, tr in got[1:])
    if distribution == "late":  # parts of one and of two substeps, and commands too late
        latency = infos["rig"]["actuator.command_delay_s"] / vector.task.period_s
        assert latency.min() < 0.5 < latency.max() and (latency > 1.0).any()
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


def test_an_action_that_is_not_finite_is_refused_naming_it():
    env = PiscEnv("catch")
    env.reset(seed=0)
    with pytest.raises(ValueError, match="action nan \\(rig 0 of 1\\)"):
        env.step(np.array([np.nan]))
    vector = PiscVectorEnv(4, task="catch")
    vector.reset(seed=0)
    with pytest.raises(ValueError, match="action inf \\(rig 2 of 4\\)"):
        vector.step(np.array([0.0, 1.0, np.inf, 2.0]))


def test_an_unknown_task_is_refused():
    with pytest.raises(ConfigError, match="task = 'balance': unknown"):
        PiscEnv("balance")
