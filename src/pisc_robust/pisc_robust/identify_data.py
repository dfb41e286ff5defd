"""Identification's input: what can be fitted (:data:`UNKNOWNS`, :func:`parse_fit`) and
the recordings it is fitted to (:func:`read_recording`: a bag's measured samples, each with
the voltage that answered it and when that voltage reached the rig).

**Timing.** Each voltage acts from the time it reached the rig: in a run on the wall
clock (the driver and a rig, or its virtual rig) that is the cycle's own latency from
the rig's tick, plus a constant the fit can estimate (``delay``). The bag gives the
latency from the sample's stamp to the voltage: to the driver's write of the byte
(``/pisc/motor/voltage_sent``; bags before 2026-12-03 have only the controllers'
publication of ``/pisc/motor/voltage``, earlier than the write by the callback's wait),
and from the rig's tick to the stamp, the read's delay, which :func:`rig_ticks`
estimates from the stamps. The voltage is the byte's: a sample the driver did not answer
(its answer came too late) or in whose period it wrote 0 V of its own is left out; one
that reached the rig after the next tick acts from there, in the next period. Measured
against the virtual rig's own record of each byte's arrival (a 60 s run, 2026-12-03):
the voltages' publication explained the arrival times with a correlation of 0.45-0.57
(another run), the writes 0.81 (0.27 ms robust spread), the writes with the reads'
delays 0.93 (0.13 ms), and 0.95 (0.11 ms) once the virtual rig timed its periods from
its timer's ticks (docs/identification.md, "Timing"). In a lockstep simulation the
latency is ``delay`` alone (the plant's ``actuator.command_delay_s``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pisc_bag.bag import BagError, bag_topics, read_bag
from pisc_bag.run_files import PARAMS_FILE
from pisc_msgs_py.config import ConfigError
from pisc_msgs_py.convert import MessageError, joint_sample_from_msg, motor_sample_from_msg
from pisc_msgs_py.topics import JOINT_STATES, MOTOR_CURRENT, VOLTAGE, VOLTAGE_SENT

__all__ = ["BY_KEY", "BY_NAME", "CHANNELS", "DEFAULT_FIT", "NOT_PLANT", "QUANTISATION_RMS",
           "UNKNOWNS", "FitError", "IdentifyError", "Recording", "Unknown", "parse_fit",
           "read_recording", "recording_from_arrays", "rig_ticks"]

MEASURED = (JOINT_STATES.name, MOTOR_CURRENT.name, VOLTAGE.name)
QUANTISATION_RMS = 1.0 / math.sqrt(12.0)  # of a step, for a uniform error
CHANNELS = ("IR position", "encoder angle", "current")


class IdentifyError(RuntimeError):
    """The input cannot be identified from; the message says why."""


class FitError(IdentifyError):
    """The fit failed (did not converge, or the model diverged)."""


@dataclass(frozen=True)
class Unknown:
    """A parameter the fit can estimate."""

    key: str  # short name on the command line
    name: str  # the parameter it sets (dotted name)
    unit: str
    scale: float  # typical size (scales the fit, and decides what is identifiable)
    low: float
    high: float
    needs_voltage: bool  # seen only through the motor: needs a voltage that is not zero
    meaning: str


UNKNOWNS = (
    Unknown("R", "motor.resistance_ohm", "ohm", 10.0, 0.5, 500.0, True, "armature resistance"),
    Unknown("L", "motor.inductance_h", "H", 2e-3, 1e-6, 1.0, True, "armature inductance"),
    Unknown("J_m", "motor.rotor_inertia_kgm2", "kg m^2", 2e-6, 0.0, 1e-3, True,
            "rotor inertia (with M + m known)"),
    Unknown("b_m", "motor.viscous_friction_nms", "N m s/rad", 1e-5, 0.0, 1e-2, True,
            "rotor viscous friction (adds to the cart's as b_m / r^2)"),
    Unknown("cart_coulomb", "friction.cart_coulomb_n", "N", 0.05, 0.0, 5.0, True,
            "cart Coulomb friction"),
    Unknown("cart_viscous", "friction.cart_viscous_ns_per_m", "N s/m", 0.25, 0.0, 20.0, True,
            "cart viscous friction"),
    Unknown("pivot_viscous", "friction.pivot_viscous_nms", "N m s/rad", 5e-5, 0.0, 1e-2, False,
            "pivot viscous friction"),
    Unknown("M", "rig.cart_mass_kg", "kg", 0.5, 0.01, 20.0, True, "cart mass"),
    Unknown("m", "rig.pendulum_mass_kg", "kg", 0.01, 1e-4, 5.0, False, "pendulum mass"),
    Unknown("l", "rig.pendulum_com_m", "m", 0.1, 1e-3, 2.0, False,
            "pivot to the pendulum's centre of mass"),
    Unknown("I", "rig.pendulum_inertia_kgm2", "kg m^2", 3e-5, 0.0, 1.0, False,
            "pendulum inertia about its centre of mass"),
    Unknown("delay", "actuator.command_delay_s", "s", 1e-3, 0.0, 1.0, True,
            "sample to voltage, the part the bag does not record"),
    Unknown("current_offset", "current_offset", "A", 0.01, -0.5, 0.5, False,
            "error of the current sensor's zero (measured minus true current)"),
)
#: Unknowns that are not plant parameters: timing and the sensors' own errors
NOT_PLANT = ("delay", "current_offset")
BY_KEY = {u.key: u for u in UNKNOWNS}
BY_NAME = {u.name: u for u in UNKNOWNS}

#: What each experiment identifies by default (``--fit`` replaces it).
DEFAULT_FIT = {
    "excitation": ("R", "L", "J_m", "cart_coulomb", "cart_viscous", "pivot_viscous",
                   "current_offset"),
    # the swing fixes (I + m l^2) / (m l) and c / (m l) only (l and I apart need the
    # cart's reaction, which its friction holds still): l from the base, as measured
    "free_swing": ("I", "pivot_viscous"),
    "none": ("R", "L", "J_m", "cart_coulomb", "cart_viscous", "pivot_viscous",
             "current_offset"),
}


def parse_fit(spec: str | Sequence[str]) -> list[Unknown]:
    """``R,J_m,cart_coulomb`` (short or dotted names) -> the unknowns, in that order."""
    items = spec.split(",") if isinstance(spec, str) else list(spec)
    out: list[Unknown] = []
    for item in (i.strip() for i in items):
        if not item:
            continue
        unknown = BY_KEY.get(item) or BY_NAME.get(item)
        if unknown is None:
            raise IdentifyError(
                f"--fit {item}: no such parameter (known: "
                + ", ".join(f"{u.key} ({u.name})" for u in UNKNOWNS) + ")")
        if unknown not in out:
            out.append(unknown)
    if not out:
        raise IdentifyError("--fit: no parameter named")
    return out



# -- recordings ------------------------------------------------------------------------


@dataclass(frozen=True)
class Recording:
    """The measured samples of one run, with the voltage that answered each."""

    name: str
    stamps_ns: np.ndarray  # (N,) int64, the cycles' header stamps
    x: np.ndarray  # measured cart position, m
    theta: np.ndarray  # measured angle, rad
    current: np.ndarray  # measured current, A
    voltage: np.ndarray  # the voltage answering each sample, V
    latency_s: np.ndarray  # the rig's sample to its voltage (wall clock), 0 in lockstep
    wall_clock: bool
    experiment: str = "none"
    params_file: Path | None = None  # the run's controllers' parameter file, if any
    # wall clock: each sample's tick of the rig's timer (a frame lost skips one) and its
    # time from that tick to its stamp (included in latency_s), estimated from the stamps
    # (:func:`rig_ticks`); None when not estimated
    ticks: np.ndarray | None = None
    read_delay_s: np.ndarray | None = None

    @property
    def duration_s(self) -> float:
        return float(self.stamps_ns[-1] - self.stamps_ns[0]) * 1e-9


def recording_from_arrays(name: str, period_s: float, x: Any, theta: Any, current: Any,
                          voltage: Any, latency_s: Any = 0.0, experiment: str = "none",
                          wall_clock: bool = False) -> Recording:
    """A recording of samples every ``period_s`` (a pure simulation's log, for instance)."""
    x = np.asarray(x, dtype=float)
    n = len(x)
    stamps = np.arange(n, dtype=np.int64) * round(period_s * 1e9)
    return Recording(name, stamps, x, np.asarray(theta, dtype=float),
                     np.asarray(current, dtype=float), np.asarray(voltage, dtype=float),
                     np.broadcast_to(np.asarray(latency_s, dtype=float), (n,)).copy(),
                     wall_clock, experiment)


def _experiment_of(params_file: Path) -> str:
    from pisc_msgs_py.config import load_params_file

    try:
        return str(load_params_file(params_file).get("experiment.kind", "none"))
    except ConfigError:
        return "none"


def rig_ticks(stamps_ns: np.ndarray, period_s: float, window: int = 200
              ) -> tuple[np.ndarray, np.ndarray] | None:
    """(each sample's tick of the rig's timer, its time from that tick to its stamp in s,
    the earliest 0), or None when the stamps do not show the ticks.

    The rig samples on its own timer, every period; the driver stamps a frame when it
    has read it, so a late read makes a late stamp, not a late sample. With sample k
    taken at tick n_k, stamp_k - n_k T is the read's delay plus a constant and the two
    clocks' drift, and its least value over the next ``window`` samples (a read that met
    no delay) is the constant and drift alone. A frame lost (the parser refuses one whose
    bytes came apart, a byte dropped) raises that least value by a period for good from
    the next sample on: n_k = k + the lost frames before k. A line through each window's
    earliest stamp is then the ticks' time, and each stamp's distance above it its read's
    delay (reads late by half a period or more just before a lost frame would put the
    loss early: a sample just after a skipped tick and a tenth of a period or more below
    the line goes to the tick before). None when the result is not one line (some
    window's earliest half a period or more off it: a stall longer than the window, say)
    or the run is shorter than two windows."""
    n = len(stamps_ns)
    if n < 2 * window:
        return None
    k = np.arange(n)
    t = (stamps_ns - stamps_ns[0]) * 1e-9
    offset = t - k * period_s
    padded = np.concatenate([offset, np.full(window - 1, np.inf)])
    ahead = np.lib.stride_tricks.sliding_window_view(padded, window).min(axis=1)
    # lost frames: a rise of half a period or more over the level, which follows the
    # least value down and up by less than a quarter period (the clocks' drift)
    ticks = k.copy()
    level, count = ahead[0], 0
    for j in range(n):
        x = (ahead[j] - level) / period_s - count
        if x >= 0.5:
            count += int(np.rint(x))
        elif x < 0.25:
            level = ahead[j] - count * period_s
        ticks[j] += count

    def fit() -> tuple[np.ndarray, np.ndarray]:
        offset = t - ticks * period_s
        earliest = np.array([i + int(np.argmin(offset[i:i + window]))
                             for i in range(0, n, window)])
        slope, intercept = np.polyfit(ticks[earliest], offset[earliest], 1)
        return offset - (intercept + slope * ticks), earliest

    delay, earliest = fit()
    # reads late by half a period or more just before a lost frame put the loss early:
    # such a sample then sits a period before its tick; it belongs to the tick before
    early = np.flatnonzero(delay < -0.1 * period_s)
    for j in early:
        if j == 0 or ticks[j - 1] < ticks[j] - 1:
            ticks[j] -= 1
    if early.size:
        delay, earliest = fit()
    if np.ptp(delay[earliest]) >= 0.5 * period_s:
        return None
    return ticks, delay - delay.min()


def read_recording(bag: str | Path) -> Recording:
    """The measured samples of a bag; :class:`IdentifyError` when it cannot serve."""
    bag = Path(bag)
    try:
        topics = bag_topics(bag)
    except BagError as exc:
        raise IdentifyError(str(exc)) from None
    missing = [t for t in MEASURED if t not in topics]
    if missing:
        raise IdentifyError(
            f"{bag}: the bag has no {' and no '.join(missing)}: identification needs the "
            f"measured position and angle ({JOINT_STATES.name}), current "
            f"({MOTOR_CURRENT.name}) and the voltage answering each sample ({VOLTAGE.name})")
    joints: dict[int, tuple[float, float, int | None]] = {}
    current: dict[int, float] = {}
    voltage: dict[int, tuple[float, int | None]] = {}
    # through the driver: what each byte written asked for, and when it was written
    written: dict[int, tuple[float, int | None]] = {}
    own: set[int] = set()  # samples in whose period the driver wrote 0 V of its own
    try:
        for m in read_bag(bag, [*MEASURED, *([VOLTAGE_SENT.name] if VOLTAGE_SENT.name in
                                             topics else [])]):
            if m.topic == JOINT_STATES.name:
                s = joint_sample_from_msg(m.message)
                joints[s.stamp_ns] = (s.position_m, s.angle_rad, m.publish_time_ns)
            elif m.topic == MOTOR_CURRENT.name:
                c = motor_sample_from_msg(m.message)
                current[c.stamp_ns] = c.value
            elif m.topic == VOLTAGE.name:
                v = motor_sample_from_msg(m.message)
                voltage[v.stamp_ns] = (v.value, m.publish_time_ns)
            else:
                v = motor_sample_from_msg(m.message)
                if m.message.header.frame_id == "answer":
                    written.setdefault(v.stamp_ns, (v.value, m.publish_time_ns))
                elif m.message.header.frame_id == "zero":  # (a hold repeats the last byte)
                    own.add(v.stamp_ns)
    except BagError as exc:
        raise IdentifyError(str(exc)) from None
    except MessageError as exc:
        raise IdentifyError(f"{bag}: {exc}") from None
    empty = [name for name, d in zip(MEASURED, (joints, current, voltage), strict=True) if not d]
    if empty:
        raise IdentifyError(f"{bag}: no messages on {', '.join(empty)}: nothing was measured")
    if written:
        # the bytes as written: a sample the driver did not answer (its answer came too
        # late) or in whose period it wrote 0 V of its own gets no voltage, and the model
        # leaves its period out
        voltage = {k: written.get(k, (math.nan, None)) if k not in own else (math.nan, None)
                   for k in voltage}
    stamps = np.array(sorted(set(joints) & set(current) & set(voltage)), dtype=np.int64)
    if len(stamps) < 20:
        raise IdentifyError(f"{bag}: only {len(stamps)} complete samples (position, angle, "
                            "current and the voltage answering them)")
    x = np.array([joints[s][0] for s in stamps])
    theta = np.array([joints[s][1] for s in stamps])
    i = np.array([current[s] for s in stamps])
    u = np.array([voltage[s][0] for s in stamps])
    sent = [(voltage[s][1], joints[s][2]) for s in stamps]
    known = [(v, j) for v, j in sent if v is not None and j is not None]
    # a run on the wall clock stamps its samples with the time they were sent; a lockstep
    # run with simulated time, unrelated to the publish times
    wall = bool(known) and float(np.median([abs(j - s) for (_, j), s in zip(
        sent, stamps, strict=True) if j is not None])) < 1e9
    latency = np.array([(v - j) * 1e-9 if wall and v is not None and j is not None else 0.0
                        for v, j in sent])
    params_file = bag / PARAMS_FILE
    params = params_file if params_file.is_file() else None
    ticks = read = None
    if wall:
        period = float(np.median(np.diff(stamps))) * 1e-9
        found = rig_ticks(stamps, period)
        if found is not None:
            ticks, read = found
            latency = latency + read
    return Recording(str(bag), stamps, x, theta, i, u, latency, wall,
                     _experiment_of(params) if params else "none", params, ticks, read)

