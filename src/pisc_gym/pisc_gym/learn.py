"""pisc_gym_learn: learn a catch policy on randomised rigs with CMA-ES, through the vector
environment, and count its catches over fresh randomised starts.

    pisc_gym_learn [--generations 40] [--population 16] [--starts 32] [--seed 0]
                   [--evaluate 1000] [--start arriving|rest] [--figure FILE]

The task is ``pisc/Catch-v0`` on ``thesis-rig`` rigs (each start a new rig: motor,
masses, friction, noise and latency drawn from the distribution), the pendulum within
0.3 rad of upright as the swing-up hands it over (``--start arriving``, the task's
default: energy 0, moving towards upright) or at rest (``--start rest``, of which no
input catches a fifth to a quarter: :mod:`pisc_gym.catchable`), the action the current
set-point through PISC's PI current loop, the observation the sensors' x, theta, i and
the estimator's differences.

The policy is linear in what it observes, ``i_d = g . (x - x_mid, x_dot, theta_wrapped,
theta_dot)`` (x_mid the middle of the safe range, theta wrapped to the nearest upright,
:func:`pisc_model.dynamics.wrap_to_upright`): four numbers, learnt from zero (on the
features over :data:`SCALE`). Each generation of CMA-ES (the ``cmaes`` package,
Hansen's CMA-ES with its default step-size adaptation) asks for ``--population``
candidates; every candidate runs ``--starts`` episodes, all of them in
one vector environment (each rig its candidate's gains), and is scored by its mean
return (:mod:`pisc_gym.task`'s reward). The generation's mean is the policy.

A start is caught when its episode (3 s) is not terminated (the cart stays in the safe
range, the pendulum within pi / 2 of upright) and the true angle stays within 0.05 rad
of upright over its last second. The learnt policy is evaluated on ``--evaluate`` new
starts (seeds no generation used) and the command prints the share caught with its
Clopper-Pearson 95 % interval. docs/gym.md has the figures.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["CAUGHT_RAD", "environment", "episodes", "features", "learn", "run"]

CAUGHT_RAD = 0.05  # |theta| over the episode's last second, for a catch
HOLD_S = 1.0
OPTIONS = {"distribution": "thesis-rig", "action": "current", "velocities": True}
#: the features' scales (m, m/s, rad, rad/s): the policy's gains act on z / SCALE, so that
#: CMA-ES starts from one step size for all four
SCALE = np.array([0.1, 0.5, 0.3, 3.0])


def run(env, obs: np.ndarray, info: dict, policy) -> tuple[np.ndarray, np.ndarray]:
    """One episode of each rig of a vector environment ``env`` just reset (its first
    observation and infos ``obs``, ``info``), the action ``policy(k, obs, info)`` at step
    k: (returns, caught). A rig is caught when its episode is not terminated and its
    true angle stays within :data:`CAUGHT_RAD` of upright over the last :data:`HOLD_S`."""
    from pisc_model.dynamics import wrap_to_upright

    n = env.num_envs
    steps = env.task.episode_steps
    hold_from = steps - int(round(HOLD_S / env.task.period_s))
    returns = np.zeros(n)
    live = np.ones(n, dtype=bool)  # in its first episode
    held = np.ones(n, dtype=bool)
    for k in range(steps):
        obs, reward, terminated, truncated, info = env.step(policy(k, obs, info))
        returns += np.where(live, reward, 0.0)
        if k + 1 >= hold_from:
            angle = np.abs(wrap_to_upright(info["true_state"][:, 2]))
            held &= ~live | (angle < CAUGHT_RAD)
        held &= ~(live & terminated)
        live &= ~(terminated | truncated)
    return returns, held & ~live


def environment(n: int, seed: int, **options):
    """A vector environment of ``n`` catch rigs (:data:`OPTIONS`, then ``options``),
    reset with ``seed``: (env, observation, infos)."""
    from pisc_gym.vector import PiscVectorEnv

    env = PiscVectorEnv(n, task="catch", **{**OPTIONS, **options})
    return (env, *env.reset(seed=seed))


def features(obs: np.ndarray, middle_m: float) -> np.ndarray:
    """The policy's features (rigs, 4): x - x_mid, x_dot, theta wrapped to the nearest
    upright, theta_dot, from the sensors and the estimator's differences."""
    from pisc_model.dynamics import wrap_to_upright

    return np.column_stack([obs[:, 0] - middle_m, obs[:, 3], wrap_to_upright(obs[:, 1]),
                            obs[:, 4]])


def episodes(gains: np.ndarray, seed: int, **options) -> tuple[np.ndarray, np.ndarray]:
    """One episode of each row of ``gains`` (rigs, 4) on its own randomised rig (vector
    environment seeded ``seed``): (returns, caught)."""
    env, obs, info = environment(len(gains), seed, **options)
    middle = env.task.middle_m
    return run(env, obs, info,
               lambda k, obs, info: np.sum(gains * features(obs, middle) / SCALE, axis=1))


def learn(generations: int, population: int, starts: int, seed: int,
          report: bool = True, start: str = "arriving"
          ) -> tuple[np.ndarray, list[tuple[float, float, float]]]:
    """CMA-ES from zero gains: the final mean and, per generation, (best, mean) return of
    the candidates and the mean's return."""
    from cmaes import CMA

    optimizer = CMA(mean=np.zeros(4), sigma=1.0, population_size=population, seed=seed)
    history = []
    for g in range(generations):
        candidates = np.array([optimizer.ask() for _ in range(optimizer.population_size)])
        rows = np.repeat(np.vstack([candidates, optimizer.mean]), starts, axis=0)
        returns, _ = episodes(rows, seed * 1_000_003 + g * (population + 1) * starts,
                              start=start)
        scores = returns.reshape(population + 1, starts).mean(axis=1)
        optimizer.tell([(c, -s) for c, s in zip(candidates, scores[:-1])])
        history.append((float(scores[:-1].max()), float(scores[:-1].mean()),
                        float(scores[-1])))
        if report:
            print(f"generation {g + 1:3d}: best {history[-1][0]:7.1f}, mean "
                  f"{history[-1][1]:7.1f}, policy {history[-1][2]:7.1f} (of "
                  f"{len(rows)} episodes)", flush=True)
    return optimizer.mean.copy(), history


def plot(history: list[tuple[float, float, float]], rate: float, n: int, path: Path,
         start: str = "arriving") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    h = np.array(history)
    fig, ax = plt.subplots(figsize=(7, 3.6), dpi=110)
    gens = np.arange(1, len(h) + 1)
    ax.plot(gens, h[:, 0], label="best candidate")
    ax.plot(gens, h[:, 1], label="candidates' mean")
    ax.plot(gens, h[:, 2], label="the policy (CMA-ES mean)", linewidth=2)
    ax.set_xlabel("generation")
    ax.set_ylabel("mean return of its episodes")
    ax.set_title(f"CMA-ES, pisc/Catch-v0 on thesis-rig rigs, {start} starts: "
                 f"{100 * rate:.1f} % of {n} new starts caught", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
