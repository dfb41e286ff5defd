"""Typed values that cross node boundaries, independent of any message library.

Stamps are integer nanoseconds (ROS time: wall or simulated), so a stamp survives a
round trip through a message or a bag exactly and can key a control cycle.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

__all__ = [
    "CartForce",
    "JointSample",
    "Mode",
    "ModeReport",
    "MotorSample",
    "StateEstimate",
    "TrueState",
]


class Mode(StrEnum):
    """What the supervisor is doing (its code is the batch cores' integer mode)."""

    SWING_UP = "swing_up"
    CATCH = "catch"
    FAULT = "fault"

    @property
    def code(self) -> int:
        return _MODE_CODES[self]

    @classmethod
    def from_code(cls, code: int) -> Mode:
        return _CODE_MODES[int(code)]


_MODE_CODES = {Mode.SWING_UP: 0, Mode.CATCH: 1, Mode.FAULT: 2}
_CODE_MODES = {v: k for k, v in _MODE_CODES.items()}


@dataclass(frozen=True)
class JointSample:
    """Measured cart position and pendulum angle of one sample."""

    stamp_ns: int
    position_m: float
    angle_rad: float


@dataclass(frozen=True)
class MotorSample:
    """One armature quantity of one cycle: current (A) or voltage (V), by topic."""

    stamp_ns: int
    value: float


@dataclass(frozen=True)
class StateEstimate:
    stamp_ns: int
    position_m: float
    velocity_mps: float
    angle_rad: float
    rate_radps: float


@dataclass(frozen=True)
class PendulumEstimate:
    """The supervisor's online estimates of its pendulum and their standard deviations."""

    stamp_ns: int
    omega0_sq: float  # omega_0^2 = m g l / J [1/s^2]
    pivot_loss: float  # b / J [1/s]
    omega0_sq_std: float
    pivot_loss_std: float


@dataclass(frozen=True)
class CartForce:
    stamp_ns: int
    force_n: float


@dataclass(frozen=True)
class ModeReport:
    stamp_ns: int
    mode: Mode
    reason: str = ""


@dataclass(frozen=True)
class TrueState:
    """The simulator's state at a sample (not measurable on the rig)."""

    stamp_ns: int
    position_m: float
    velocity_mps: float
    angle_rad: float
    rate_radps: float
    current_a: float
