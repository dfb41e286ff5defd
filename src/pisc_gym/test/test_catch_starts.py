"""The catch task's starts: arriving as the swing-up hands the pendulum over (pendulum
energy 0, moving towards upright) or at rest; and the linear programme that says which
starts any input can catch (pisc_gym.catchable)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from pisc_analysis.feasibility import exact_plant
from pisc_gym import catchable
from pisc_gym.env import PiscEnv
from pisc_gym.learn import environment
from pisc_model.dynamics import energy
from pisc_msgs_py.config import ConfigError
from pisc_plant.plant import Plant


def test_an_arriving_start_has_the_energy_of_upright_at_rest_and_moves_towards_it():
    env = PiscEnv("catch", distribution="thesis-rig")
    signs = set()
    for seed in range(6):
        _, info = env.reset(seed=seed)
        x, x_dot, theta, theta_dot, _ = info["true_state"]
        rig = info["rig"]
        params = dataclasses.replace(
            env.task.plant.rig, pendulum_mass_kg=rig["rig.pendulum_mass_kg"],
            pendulum_com_m=rig["rig.pendulum_com_m"],
            pendulum_inertia_kgm2=rig["rig.pendulum_inertia_kgm2"])
        # (2.54) with the cart at rest: zero is upright at rest
        assert abs(float(energy(params, 0.0, theta, theta_dot))) < 1e-15
        assert 0.0 < abs(theta) <= 0.3 and theta * theta_dot < 0.0  # towards upright
        assert (x, x_dot) == (env.task.middle_m, 0.0)
        signs.add(np.sign(theta))
    assert signs == {-1.0, 1.0}


def test_a_rest_start_is_at_rest_and_an_unknown_start_is_refused():
    env = PiscEnv("catch", distribution="thesis-rig", start="rest")
    _, info = env.reset(seed=0)
    assert info["true_state"][3] == 0.0 and 0.0 < abs(info["true_state"][2]) <= 0.3
    # the same rig and angle as the arriving start of the same seed
    _, arriving = PiscEnv("catch", distribution="thesis-rig").reset(seed=0)
    assert arriving["true_state"][2] == info["true_state"][2]
    with pytest.raises(ConfigError, match="start = 'falling': unknown"):
        PiscEnv("catch", start="falling")


def _linear_model(task):
    return catchable.linearise(Plant(exact_plant(task.plant, {"friction.cart_coulomb_n": 0.0})),
                               task.period_s)


@pytest.fixture(scope="module")
def nominal():
    env, _, _ = environment(1, 0, action="voltage", start="rest")
    task = env.task
    ad, bd = _linear_model(task)
    return task, ad, bd


def test_the_linear_model_has_the_pendulums_unstable_pole(nominal):
    task, ad, _ = nominal
    # thesis (6.3): open-loop poles +-9.2989 rad/s for the rig without motor or friction;
    # the motor's back EMF and the frictions move the unstable one a little
    fastest = math.log(max(abs(np.linalg.eigvals(ad)))) / task.period_s
    assert 9.0 < fastest < 9.6


def test_a_small_tilt_has_a_plan_and_it_keeps_every_rule_in_the_linear_model(nominal):
    task, ad, bd = nominal
    steps, hold_from = task.episode_steps, task.episode_steps - 200
    y0 = np.array([task.middle_m, 0.0, 0.1, 0.0, 0.0])
    p = catchable.plan(ad, bd, y0, steps, hold_from, task.safe_range, task.voltage_limit_v,
                       task.current_limit_a)
    assert p.keeps_track
    y = [y0]
    for u in p.voltages:  # the plan's voltages through the model, independently of HiGHS
        y.append(ad @ y[-1] + bd * u)
    y = np.array(y)
    low, high = task.safe_range
    assert np.all(y[:, 0] >= low - 1e-9) and np.all(y[:, 0] <= high + 1e-9)
    assert np.max(np.abs(y[hold_from:, 2])) <= 0.05 + 1e-9
    assert np.max(np.abs(y[:, 4])) <= task.current_limit_a + 1e-9
    assert np.max(np.abs(p.voltages)) <= task.voltage_limit_v + 1e-9


def test_a_tilt_past_what_the_stalled_motor_can_hold_has_no_plan(nominal):
    task, ad, bd = nominal
    motor, rig = task.plant.motor, task.plant.rig
    # at rest the motor gives at most k_m / r * u_max / R (4.2), (2.81); the pendulum
    # falls unless the cart's acceleration reaches g tan(theta), a = f / (M + m + J_m/r^2)
    force = motor.force_per_amp * task.voltage_limit_v / motor.resistance_ohm
    reach = math.atan(force / ((rig.a2 + motor.reflected_mass_kg) * rig.gravity_mps2))
    assert 0.3 < reach < 0.36
    y0 = np.array([task.middle_m, 0.0, reach + 0.03, 0.0, 0.0])
    p = catchable.plan(ad, bd, y0, task.episode_steps, task.episode_steps - 200,
                       task.safe_range, task.voltage_limit_v, task.current_limit_a)
    assert not p.keeps_track


def test_the_plans_flown_through_the_environment_catch_the_small_tilts():
    env, obs, info, plans, gains = catchable.plans("rest", 4, 7)
    caught = catchable.fly(env, obs, info, plans, gains)
    small = np.abs(info["true_state"][:, 2]) < 0.15
    assert small.any() and caught[small].all()
