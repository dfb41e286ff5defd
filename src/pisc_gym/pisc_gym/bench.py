"""pisc_gym_bench: steps per second of PISC's vector environment beside Gymnasium's
CartPoleVectorEnv, at the same numbers of copies in the same run, and each one's error
against an accurate solution of its own equations.

    pisc_gym_bench [--sizes 1 100 10000] [--seconds 3] [--threads K]

Speed: ``pisc/SwingUp-v0``'s vector environment (the motor's armature, the quantised
sensors behind their filters, the command latency, rigs drawn from ``thesis-rig`` and
drawn again at every autoreset) with uniformly random armature voltages, against
``CartPoleVectorEnv`` (Gymnasium's own vectorised cart-pole: a force of +-10 N, Euler
steps of 20 ms, no motor, no sensors) with random pushes, each stepped for
``--seconds`` after a few warm-up steps: rig-steps per second (steps x copies) and the
ratio PISC / CartPole.

Error: one second of each environment's own dynamics from a pendulum 0.05 rad from
upright, driven open loop by a held input (PISC: 5 V sin(2 pi 2 t), CartPole: random
pushes), against ``scipy.integrate.solve_ivp`` restarted at every step with the input
held (Radau for PISC's stiff armature, DOP853 for CartPole; rtol = atol = 1e-12): the
largest difference of x, x_dot, theta, theta_dot at the steps. PISC's reference is
:func:`pisc_plant.work_precision.playback_scipy` on the plant's own right-hand side;
CartPole's is its step's equations (Barto, Sutton and Anderson 1983 as Gymnasium writes
them) integrated exactly. docs/gym.md has the figures.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

__all__ = ["cartpole_error", "pisc_error", "rate"]

GOAL = 2_000_000  # rig-steps a second at N = 10,000 (with the motor, sensors, randomised rigs)


def rate(step: Callable[[int], None], copies: int, seconds: float) -> float:
    """Steps x copies per second of ``step(k)`` over about ``seconds`` of wall time."""
    for k in range(5):
        step(k)
    done = 0
    start = time.perf_counter()
    while True:
        for k in range(10):
            step(done + k)
        done += 10
        elapsed = time.perf_counter() - start
        if elapsed >= seconds:
            return done * copies / elapsed


def pisc_rate(n: int, seconds: float) -> float:
    from pisc_gym.vector import PiscVectorEnv

    env = PiscVectorEnv(n, task="swing_up", distribution="thesis-rig")
    env.reset(seed=0)
    limit = env.task.voltage_limit_v
    actions = np.random.default_rng(1).uniform(-limit, limit, (64, n))
    return rate(lambda k: env.step(actions[k % 64]), n, seconds)


def cartpole_rate(n: int, seconds: float) -> float:
    from gymnasium.envs.classic_control.cartpole import CartPoleVectorEnv

    env = CartPoleVectorEnv(num_envs=n)
    env.reset(seed=0)
    actions = np.random.default_rng(1).integers(0, 2, (64, n))
    return rate(lambda k: env.step(actions[k % 64]), n, seconds)


def pisc_error(seconds: float = 1.0) -> float:
    """Largest |x, x_dot, theta, theta_dot| difference of PISC's environment (the
    nominal thesis rig) from the Radau reference over ``seconds``."""
    from pisc_gym.env import PiscEnv
    from pisc_plant.work_precision import playback_scipy

    env = PiscEnv("catch", episode_s=seconds + 1.0, start_angle_rad=0.05, fall_rad=np.pi)
    env.reset(seed=0)
    rigs = env.rigs
    y0 = rigs.y[0].copy()
    period = env.task.period_s
    n = int(round(seconds / period))
    commands = 5.0 * np.sin(2.0 * np.pi * 2.0 * period * np.arange(n))
    states = [y0[:4]]
    for u in commands:
        _, _, terminated, _, info = env.step(np.array([u]))
        if terminated:
            raise RuntimeError("the error run left the safe range")
        states.append(info["true_state"][:4])
    reference = playback_scipy(rigs.plant, y0, commands, period, "Radau", 1e-12, 1e-12)
    return float(np.max(np.abs(np.array(states) - reference.states[:, :4])))


def cartpole_error(seconds: float = 1.0) -> float:
    """Largest |x, x_dot, theta, theta_dot| difference of CartPoleVectorEnv's Euler
    steps from the DOP853 reference of the same equations over ``seconds``."""
    from gymnasium.envs.classic_control.cartpole import CartPoleVectorEnv
    from scipy.integrate import solve_ivp

    env = CartPoleVectorEnv(num_envs=1)
    env.reset(seed=0)
    start = np.array([0.0, 0.0, 0.05, 0.0])
    env.state = start.reshape(4, 1).copy()
    g, mp, length = env.gravity, env.masspole, env.length
    total, pml = env.total_mass, env.polemass_length

    def rhs(_t: float, s: np.ndarray, force: float) -> np.ndarray:
        _, x_dot, theta, theta_dot = s
        temp = (force + pml * theta_dot**2 * np.sin(theta)) / total
        theta_acc = (g * np.sin(theta) - np.cos(theta) * temp) / (
            length * (4.0 / 3.0 - mp * np.cos(theta) ** 2 / total))
        x_acc = temp - pml * theta_acc * np.cos(theta) / total
        return np.array([x_dot, x_acc, theta_dot, theta_acc])

    n = int(round(seconds / env.tau))
    pushes = np.random.default_rng(2).integers(0, 2, n)
    worst, y = 0.0, start
    for a in pushes:
        env.prev_done[:] = False  # the dynamics only: no reset past the angle limit
        env.step(np.array([a]))
        force = env.force_mag if a == 1 else -env.force_mag
        y = solve_ivp(rhs, (0.0, env.tau), y, method="DOP853", rtol=1e-12, atol=1e-12,
                      args=(force,)).y[:, -1]
        worst = max(worst, float(np.max(np.abs(env.state[:, 0] - y))))
    return worst
