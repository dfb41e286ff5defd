"""PISC's rig as a Gymnasium environment: one rig, a 5 ms step, the motor and the sensors.

``gymnasium.make("pisc/SwingUp-v0")`` and ``gymnasium.make("pisc/Catch-v0")`` (after
``import pisc_gym``) build :class:`PiscEnv`; its keywords are :func:`pisc_gym.task.
make_task`'s (``scene``, ``distribution``, ``action``, ``velocities``, ``episode_s``,
``start_angle_rad``, ``start``, ``fall_rad``, ``x_weight``, ``voltage_weight``).

Action (held for one period, applied each rig's latency after the sample, as the PIC
applies a command byte): ``action="voltage"`` the armature voltage [V], in
[-u_max, u_max], through the H-bridge's saturation and 7-bit quantisation;
``action="current"`` the current set-point i_d [A] (4.2), saturated to the current
limit, through PISC's own PI current loop (3.47) on the measured current.

Observation: what the rig's sensors give, decoded as the host decodes them: the cart
position [m] (IR sensor, 10-bit ADC), the pendulum angle [rad] (encoder, 4000 counts a
turn, pi hanging, not wrapped), the armature current [A] (ACS712, 10-bit ADC); with
``velocities=True`` also the estimator's differences x_dot, theta_dot ((4.7), (4.9)
over the configuration's N periods, low-passed as configured).

``info``: ``true_state`` (x, x_dot, theta, theta_dot, i), ``voltage_v`` (the voltage
commanded this step), ``setpoint_a`` (with a current action); at a reset ``rig``, the
rig drawn as plant overrides (:meth:`pisc_gym.task.RigDraw.as_overrides`: the same rig
in ``pisc_graph --plant-set`` or :func:`pisc_sim.closed_loop.simulate`).
Reward, termination and truncation: :mod:`pisc_gym.task`.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from pisc_gym.rigs import Rigs
from pisc_gym.task import Task, make_task

__all__ = ["PiscEnv", "spaces_of"]


def spaces_of(task: Task) -> tuple[spaces.Box, spaces.Box]:
    """(observation space, action space) of one rig of ``task``."""
    size = 5 if task.velocities else 3
    observation = spaces.Box(-np.inf, np.inf, (size,), dtype=np.float64)
    limit = task.voltage_limit_v if task.action == "voltage" else task.current_limit_a
    action = spaces.Box(-limit, limit, (1,), dtype=np.float64)
    return observation, action


class PiscEnv(gym.Env):
    """One PISC rig (:class:`pisc_gym.rigs.Rigs` of one), a Gymnasium environment."""

    metadata: dict[str, Any] = {"render_modes": []}

    def __init__(self, task: str = "swing_up", render_mode: str | None = None,
                 **options: Any) -> None:
        if render_mode is not None:
            raise ValueError(f"render_mode = {render_mode!r}: PISC's environments do not "
                             "render (watch a run with pisc_graph --foxglove)")
        self.task = make_task(task, **options)
        self.observation_space, self.action_space = spaces_of(self.task)
        self._rigs = Rigs(self.task, 1)
        self._started = False

    @property
    def rigs(self) -> Rigs:
        """The rig (its state, constants and latest sample)."""
        return self._rigs

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None
              ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        if options:
            raise ValueError(f"reset options {sorted(options)}: none are known")
        draws = self.task.draw_many([self.np_random])
        self._rigs.reset([0], draws)
        self._rigs.observe()
        self._started = True
        return self._rigs.observation()[0], {"true_state": self._rigs.true_state()[0],
                                             "rig": draws[0].as_overrides()}

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if not self._started:
            raise RuntimeError("step before reset: call reset() first")
        rigs = self._rigs
        reward, terminated, truncated = rigs.step(np.asarray(action, dtype=float).reshape(1))
        info: dict[str, Any] = {"true_state": rigs.true_state()[0],
                                "voltage_v": float(rigs.voltage[0])}
        if self.task.action == "current":
            info["setpoint_a"] = float(rigs.setpoint[0])
        return (rigs.observation()[0], float(reward[0]), bool(terminated[0]),
                bool(truncated[0]), info)
