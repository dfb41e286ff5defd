"""The PIC16F877A's firmware around a simulated plant, as SPEC section 4 and
docs/driver-protocol.md specify it: the frame of each sample, the command byte's
voltage, applied the moment it arrives, and the command watchdog.

Written on its own from SPEC section 4, not with the driver's codec: the tests check
that the two agree byte for byte. :mod:`pisc_plant.virtual_rig` runs it behind a
pseudo-terminal.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field

import numpy as np

from pisc_plant.plant import Plant

__all__ = ["DEFAULT_WATCHDOG_MS", "HEADER", "Firmware"]

HEADER = 0xAA
DEFAULT_WATCHDOG_MS = 50.0  # 10 periods; docs/driver-protocol.md says why


@dataclass
class Firmware:
    """The PIC's behaviour around a simulated plant; times are passed in (seconds).

    ``frame()`` is the 7 bytes of the current sample; ``receive(byte, t)`` applies a
    command byte at time ``t`` into the current period; ``advance()`` integrates the
    period with the voltage changing where the bytes arrived, then runs the period's
    timer tick: the command watchdog (``watchdog_s``, 0 = none) counts the ticks since the
    last byte and, at the first tick more than ``ceil(watchdog_s / period)`` of them
    after it, applies 0 V until the next byte. It is armed by the first byte (before it
    the duty is 0 anyway).
    """

    plant: Plant
    state: np.ndarray
    applied_v: float = 0.0
    time_s: float = 0.0
    watchdog_s: float = DEFAULT_WATCHDOG_MS * 1e-3
    silent_ticks: int = 0  # timer ticks since the last command byte
    armed: bool = False
    tripped: bool = False
    trips: int = 0
    last_byte_s: float | None = None  # firmware time of the last command byte
    trip_delay_s: float | None = None  # last trip: its time after the last byte
    # a hand on the rig (``--hold``): the state stays as it is until the first command
    # byte of a nonzero voltage, from which it moves; time and frames go on meanwhile
    held: bool = False
    released_s: float | None = None  # firmware time of that byte
    _changes: list[tuple[float, float]] = field(default_factory=list)
    # the sensors' noise (``noise.*``), drawn as the simulator's sampled plant draws it
    _noise: np.random.Generator | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.watchdog_s) and self.watchdog_s >= 0.0):
            raise ValueError(f"watchdog = {self.watchdog_s} s must be a finite number >= 0")
        noise = self.plant.config.noise
        self._noise = np.random.default_rng(noise.seed) if noise.any else None

    @property
    def watchdog_periods(self) -> int:
        """N: the watchdog trips at the (N+1)th tick without a byte (0 = no watchdog)."""
        if self.watchdog_s == 0.0:
            return 0
        return max(1, math.ceil(self.watchdog_s / self.plant.config.loop.period_s - 1e-9))

    def frame(self) -> bytes:
        """The frame of the state now: the sensors read with the voltage applied (the
        current of a quasi-static armature depends on it) and the parameter file's
        measurement noise (``noise.*``, one standard normal draw per sensor and frame
        from ``noise.seed``, as the simulator's plant node draws them)."""
        noise = None if self._noise is None else self._noise.standard_normal(3)
        ir, cur, count = self.plant.raw_measurement(self.state, self.applied_v, noise)
        count16 = ((int(count) + 0x8000) & 0xFFFF) - 0x8000  # the 16-bit counter register
        return struct.pack(">BHHh", HEADER, int(ir), int(cur), count16)

    def voltage(self, command: int) -> float:
        """PWM duty = magnitude << 1; duty 254 = full scale; bit 7 = negative."""
        a = self.plant.config.actuator
        duty = (command & 0x7F) << 1
        volts = a.full_scale_v * min(duty, 254) / 254
        return -volts if command & 0x80 else volts

    def receive(self, command: int, offset_s: float) -> None:
        """A command byte ``offset_s`` into the current period: applied from there (it
        also ends a watchdog trip) and the watchdog's count starts again."""
        self._changes.append((offset_s, self.voltage(command)))
        period = self.plant.config.loop.period_s
        self.last_byte_s = self.time_s + min(max(offset_s, 0.0), period)
        self.silent_ticks = 0
        self.armed = True
        self.tripped = False

    def advance(self) -> None:
        period = self.plant.config.loop.period_s
        t = 0.0
        if self.held:  # the state moves from the first nonzero byte on, or not at all
            release = next((o for o, volts in self._changes if volts != 0.0), None)
            if release is None:
                t = period
            else:
                t = min(max(release, 0.0), period)
                self.held = False
                self.released_s = self.time_s + t
        for offset, volts in self._changes:
            offset = min(max(offset, 0.0), period)
            if offset > t:
                self.state = self.plant.advance(self.state, self.applied_v, offset - t)
                t = offset
            self.applied_v = volts
        if period > t:
            self.state = self.plant.advance(self.state, self.applied_v, period - t)
        self._changes.clear()
        self.time_s += period
        self._tick()

    def _tick(self) -> None:
        """The timer tick at the end of a period: the command watchdog."""
        n = self.watchdog_periods
        if not n or not self.armed:
            return
        self.silent_ticks += 1
        if self.silent_ticks > n and not self.tripped:
            self.applied_v = 0.0
            self.tripped = True
            self.trips += 1
            self.trip_delay_s = self.time_s - self.last_byte_s
