"""N PISC rigs as one Gymnasium vector environment, stepped by one call of the kernel.

``gymnasium.make_vec("pisc/SwingUp-v0", num_envs=N)`` (after ``import pisc_gym``) builds
:class:`PiscVectorEnv`, which takes :class:`pisc_gym.env.PiscEnv`'s keywords. Its rigs
are :class:`pisc_gym.rigs.Rigs` of N: every step is one compiled pass over all of
them (command, plant, outcome, sensors), not N Python steps.

Each sub-environment is the single environment: with ``reset(seed=s)`` sub-environment
k is seeded with ``s + k``, as Gymnasium's :class:`~gymnasium.vector.SyncVectorEnv`
seeds its copies, and draws its rigs from its own generator, so that it gives the bits
of ``PiscEnv`` reset with ``seed=s + k`` (tested). Autoreset is Gymnasium's
``NEXT_STEP`` mode: the step after a sub-environment terminated or was truncated
resets it (its action is ignored, its reward is 0) and returns its first observation.

``infos``: ``true_state`` (N, 5) and ``voltage_v`` (N,) every step (with Gymnasium's
``_name`` masks); at :meth:`reset`, ``rig``: each parameter drawn, (N,) a name.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from pisc_gym.env import spaces_of
from pisc_gym.rigs import Rigs
from pisc_gym.task import make_task

__all__ = ["PiscVectorEnv"]


class PiscVectorEnv(VectorEnv):
    """``num_envs`` PISC rigs stepped together."""

    metadata: dict[str, Any] = {"render_modes": [], "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(self, num_envs: int = 1, task: str = "swing_up",
                 render_mode: str | None = None, **options: Any) -> None:
        if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
            raise ValueError(f"num_envs = {num_envs!r}: a positive whole number")
        if render_mode is not None:
            raise ValueError(f"render_mode = {render_mode!r}: PISC's environments do not "
                             "render (watch a run with pisc_graph --foxglove)")
        self.task = make_task(task, **options)
        self.num_envs = num_envs
        self.render_mode = None
        self.single_observation_space, self.single_action_space = spaces_of(self.task)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self._rigs = Rigs(self.task, num_envs)
        self._generators: list[np.random.Generator | None] = [None] * num_envs
        self._done = np.zeros(num_envs, dtype=np.bool_)
        self._started = False

    @property
    def rigs(self) -> Rigs:
        """The rigs (their state, constants and latest samples)."""
        return self._rigs

    def _seeds(self, seed: int | list[int | None] | None) -> list[int | None]:
        n = self.num_envs
        if seed is None:
            return [None] * n
        if isinstance(seed, (int, np.integer)) and not isinstance(seed, bool):
            return [int(seed) + k for k in range(n)]
        seeds = list(seed)
        if len(seeds) != n:
            raise ValueError(f"{len(seeds)} seeds for {n} sub-environments")
        return seeds

    def reset(self, *, seed: int | list[int | None] | None = None,
              options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        if options:
            raise ValueError(f"reset options {sorted(options)}: none are known")
        seeds = self._seeds(seed)
        super().reset(seed=seeds[0])
        for k, s in enumerate(seeds):
            if s is not None or self._generators[k] is None:
                self._generators[k] = seeding.np_random(s)[0]
        draws = self.task.draw_many(self._generators)  # type: ignore[arg-type]
        rigs = self._rigs
        rigs.reset(np.arange(self.num_envs), draws)
        rigs.observe()
        self._done[:] = False
        self._started = True
        ones = np.ones(self.num_envs, dtype=np.bool_)
        return rigs.observation(), {"true_state": rigs.true_state(), "_true_state": ones,
                                    "rig": draws.as_overrides(), "_rig": ones}

    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                          dict[str, Any]]:
        if not self._started:
            raise RuntimeError("step before reset: call reset() first")
        rigs = self._rigs
        n = self.num_envs
        actions = np.asarray(actions, dtype=float)
        if actions.size != n:
            raise ValueError(f"actions of shape {actions.shape}: one a sub-environment, "
                             f"({n}, 1) or ({n},)")
        # the sub-environments that ended at the last step start anew (NEXT_STEP): reset
        # before the step, which leaves them at their start, their outcome 0
        done = np.flatnonzero(self._done)
        if len(done):
            rigs.reset(done, self.task.draw_many([self._generators[k]  # type: ignore[misc]
                                                  for k in done.tolist()]))
        reward, terminated, truncated = rigs.step(actions.reshape(n), self._done)
        self._done = terminated | truncated
        ones = np.ones(n, dtype=np.bool_)
        infos = {"true_state": rigs.true_state(), "_true_state": ones,
                 "voltage_v": rigs.voltage.copy(), "_voltage_v": ones}
        return rigs.observation(), reward, terminated, truncated, infos
