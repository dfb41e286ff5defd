"""The plant as the control graph sees it: a sample every period, a voltage in between.

:class:`SampledPlant` turns the continuous plant into the rig's sampled interface:
``sample()`` gives the measurement of the current sample (and the true state, for
analysis); ``command(voltage, delay_s)`` gives the voltage answering it, applied
``delay_s`` (plus the plant's simulated latency, ``actuator.command_delay_s``) into the
period as the PIC applies a command byte on arrival; ``advance()``
integrates to the next sample, holding the previous voltage until the new one applies.
It reads no clock: the node passes the delay it measured (wall clock) or zero
(lockstep), so the same object serves real-time runs, lockstep runs and batch tests.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pisc_plant.plant import THETA, THETA_DOT, X_DOT, Plant, X

__all__ = ["Sample", "SampledPlant"]


@dataclass(frozen=True)
class Sample:
    index: int
    position_m: float
    angle_rad: float
    current_a: float
    true_state: tuple[float, float, float, float, float]  # x, x_dot, theta, theta_dot, i


class SampledPlant:
    def __init__(self, plant: Plant, state: np.ndarray, start_ns: int = 0) -> None:
        if state.shape != (plant.size,):
            raise ValueError(f"expected the state of one rig, shape ({plant.size},), "
                             f"got {state.shape}")
        self.plant = plant
        self.state = state
        self.index = 0
        self.start_ns = start_ns
        self.period_s = plant.config.loop.period_s
        self.period_ns = plant.config.loop.period_ns
        self.applied_v = 0.0  # voltage held since the last command took effect
        self._next: tuple[float, float] | None = None  # (voltage, delay) for this period
        self._latency_s = plant.config.actuator.command_delay_s
        noise = plant.config.noise
        # same scene and seed, same draws: one generator per simulated rig
        self._rng = np.random.default_rng(noise.seed) if noise.any else None

    @property
    def time_ns(self) -> int:
        """Simulated time of the current sample."""
        return self.start_ns + self.index * self.period_ns

    def sample(self) -> Sample:
        noise = None if self._rng is None else self._rng.standard_normal(3)
        y = self.state
        x, theta, current = self.plant.measurement_one(y, self.applied_v, noise)
        true_current = self.plant.current(y, self.applied_v)
        return Sample(
            self.index, x, theta, current,
            (float(y[X]), float(y[X_DOT]), float(y[THETA]), float(y[THETA_DOT]),
             float(true_current)),
        )

    @property
    def answered(self) -> bool:
        """Whether a voltage has been given for the current period."""
        return self._next is not None

    def command(self, voltage_v: float, delay_s: float = 0.0) -> None:
        """The voltage answering the current sample, taking effect ``delay_s`` after it,
        plus the plant's simulated latency ``actuator.command_delay_s``.

        A delay of a period or more means the command missed this period; it then
        takes effect at the start of the next one.
        """
        voltage = float(voltage_v)
        if not math.isfinite(voltage):
            raise ValueError(f"voltage command {voltage_v} is not finite")
        self._next = (voltage, max(0.0, float(delay_s)) + self._latency_s)

    def advance(self) -> None:
        """Integrate to the next sample."""
        if self._next is None:
            self.state = self.plant.advance(self.state, self.applied_v, self.period_s)
        else:
            voltage, delay = self._next
            if delay >= self.period_s:
                self.state = self.plant.advance(self.state, self.applied_v, self.period_s)
            else:
                if delay > 0.0:
                    self.state = self.plant.advance(self.state, self.applied_v, delay)
                self.state = self.plant.advance(self.state, voltage, self.period_s - delay)
            self.applied_v = voltage
        self._next = None
        self.index += 1
