"""The thesis's experiment as data, and a scorer that judges a run against it.

The thesis reports one run of its rig under its own controller (Section 6.6, Figures
6.3-6.8): from hanging at rest with the cart off zero, three oscillations, the hand-over
to the linear controller after about 2.34 s, the pendulum at 0 rad after about 3.25 s and
held there, the voltage saturating when the current does. An experiment file
(``src/pisc_robust/experiments/*.yaml``) holds such a run: the configuration, the start
(fixed values, and the range of the cart's unknown start), the duration of a simulated
run, and its events, each with the thesis's value and the tolerance its rounding and
plots allow::

    experiment:
      description: thesis Section 6.6
      configuration: thesis
      duration_s: 10.0
      start: {theta_rad: 3.14159, theta_dot_radps: 0.0, x_dot_mps: 0.0, x_m: [-0.225, 0.125]}
      events:
        hand_over_s: {value: 2.34, tolerance: 0.2}

An event is measured on a run's cycles (:class:`Traces`, one column per rig, so a batch
of simulated rigs and one recorded run are measured alike) and passes when the measured
value lies within ``tolerance`` of ``value``. :data:`EVENTS` says how each is measured;
an unknown event, or a tolerance that is not a positive number, is refused naming it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pisc_msgs_py.config import ConfigError, find_file, load_keyed_yaml, package_dir
from pisc_msgs_py.types import Mode

__all__ = ["EVENTS", "EXPERIMENT_DIR", "Event", "Experiment", "Traces", "experiment_names",
           "format_score", "judge", "load_experiment", "measure", "traces_from_log",
           "traces_from_run"]

EXPERIMENT_DIR = package_dir("pisc_robust", "experiments")
KEYS = ("description", "configuration", "duration_s", "start", "events")
START = ("x_m", "x_dot_mps", "theta_rad", "theta_dot_radps")
EVENT_KEYS = ("value", "tolerance")

#: |theta| from upright [rad] below which the pendulum is "at 0 rad" (Fig. 6.5)
UPRIGHT_RAD = 0.05
#: a pass through hanging counts once the pendulum is this far [rad] on the other side
HANGING_BAND_RAD = 0.05
#: the voltage counts as at its limit from this share of it (the C++ program's anti-windup
#: resets the integral to 0.95 VM, appendix A.2)
SATURATED_SHARE = 0.95

#: name: (unit, how it is measured)
EVENTS: dict[str, tuple[str, str]] = {
    "oscillations": ("", "passes through hanging (theta = pi + 2 pi n, beyond "
                     f"{HANGING_BAND_RAD} rad each side) before the hand-over, two to an "
                     "oscillation"),
    "hand_over_s": ("s", "time of the first cycle in the catch mode (switching rule (4.1))"),
    "upright_s": ("s", f"time from which |theta| from upright stays below {UPRIGHT_RAD} rad "
                  "to the end of the run (inf if it never does)"),
    "catch_exits": ("", "times the supervisor left the catch mode after the hand-over"),
    "saturation_overlap": ("", "of the cycles with the voltage (from "
                           f"{SATURATED_SHARE} of its limit) or the current set-point at its "
                           "limit, the share with both, of one sign (0 if neither ever is)"),
}


@dataclass(frozen=True)
class Event:
    name: str
    value: float
    tolerance: float

    def miss(self, measured: np.ndarray) -> np.ndarray:
        """|measured - value| in tolerances (inf for a value never seen or not a number)."""
        m = np.abs(np.asarray(measured, dtype=float) - self.value) / self.tolerance
        return np.where(np.isnan(m), np.inf, m)

    def passes(self, measured: np.ndarray) -> np.ndarray:
        """Whether each measured value lies within the tolerance of the thesis's value."""
        return self.miss(measured) <= 1.0

    def describe(self) -> str:
        unit = EVENTS[self.name][0]
        return f"{self.name} {self.value:g} +- {self.tolerance:g}{' ' + unit if unit else ''}"


@dataclass(frozen=True)
class Experiment:
    name: str
    description: str
    configuration: str
    duration_s: float
    start: dict[str, float]  # the fixed initial values, by InitialParams field
    x_range_m: tuple[float, float]  # the cart's unknown start: anywhere in this range
    events: tuple[Event, ...]
    text: str  # the file as read, for provenance

    def event(self, name: str) -> Event | None:
        return next((e for e in self.events if e.name == name), None)


def experiment_names() -> list[str]:
    return sorted(p.stem for p in EXPERIMENT_DIR.glob("*.yaml"))


def _number(where: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(
            value):
        raise ConfigError(f"{where}: expected a finite number, got {value!r}")
    return float(value)


def _event(path: Path, name: str, spec: Any) -> Event:
    where = f"{path}: experiment.events.{name}"
    if name not in EVENTS:
        raise ConfigError(f"{where}: unknown event (known: {', '.join(EVENTS)})")
    if not isinstance(spec, Mapping) or set(spec) != set(EVENT_KEYS):
        raise ConfigError(f"{where}: expected {{value: V, tolerance: T}}, got {spec!r}")
    value = _number(f"{where}.value", spec["value"])
    tolerance = _number(f"{where}.tolerance", spec["tolerance"])
    if tolerance <= 0.0:
        raise ConfigError(f"{where}.tolerance = {tolerance:g}: must be above 0 (an event "
                          "is matched within its tolerance)")
    return Event(name, value, tolerance)


def load_experiment(name_or_path: str) -> Experiment:
    """Read and check an experiment file (a shipped name or a path); ConfigError names
    the file and the key or event that is wrong."""
    path = find_file(name_or_path, EXPERIMENT_DIR, "experiment", experiment_names)
    body = load_keyed_yaml(path, "experiment", KEYS, "experiment")
    for key in ("configuration", "duration_s", "start", "events"):
        if key not in body:
            raise ConfigError(f"{path}: experiment.{key}: missing")
    duration = _number(f"{path}: experiment.duration_s", body["duration_s"])
    if duration <= 0.0:
        raise ConfigError(f"{path}: experiment.duration_s = {duration:g}: must be above 0")
    start = body["start"]
    if not isinstance(start, Mapping) or set(start) != set(START):
        raise ConfigError(f"{path}: experiment.start: give each of {', '.join(START)} "
                          f"(x_m as [low, high]), got {sorted(start) if isinstance(start, Mapping) else start!r}")
    fixed = {k: _number(f"{path}: experiment.start.{k}", start[k]) for k in START[1:]}
    span = start["x_m"]
    if not (isinstance(span, list) and len(span) == 2):
        raise ConfigError(f"{path}: experiment.start.x_m: expected [low, high], got {span!r}")
    low, high = (_number(f"{path}: experiment.start.x_m", v) for v in span)
    if not low < high:
        raise ConfigError(f"{path}: experiment.start.x_m: [{low:g}, {high:g}] is empty")
    events = body["events"]
    if not isinstance(events, Mapping) or not events:
        raise ConfigError(f"{path}: experiment.events: map each event to "
                          "{value, tolerance}")
    return Experiment(path.stem, str(body.get("description", "")), str(body["configuration"]),
                      duration, fixed, (low, high),
                      tuple(_event(path, str(n), s) for n, s in events.items()),
                      path.read_text())


@dataclass(frozen=True)
class Traces:
    """A run's cycles, one row a cycle and one column a rig: what the host logged."""

    period_s: float
    theta_rad: np.ndarray  # measured angle (T, n)
    mode: np.ndarray  # mode code (Mode.code) in force at each cycle (T, n)
    voltage_v: np.ndarray  # commanded voltage (3.47) (T, n)
    setpoint_a: np.ndarray  # current set-point i_d (4.2) (T, n)
    voltage_limit_v: float
    current_limit_a: float


def traces_from_run(trace: Any, voltage_limit_v: float, current_limit_a: float,
                    period_s: float) -> Traces:
    """One recorded run (:class:`pisc_runs.analysis.RunTrace`) as one column."""
    modes = np.array([m.code for m in trace.mode])
    return Traces(period_s, trace.theta[:, None], modes[:, None], trace.u[:, None],
                  trace.i_d[:, None], voltage_limit_v, current_limit_a)


def traces_from_log(log: Any, voltage_limit_v: float, current_limit_a: float,
                    period_s: float) -> Traces:
    """One pure simulation (:class:`pisc_sim.closed_loop.CycleLog`) as one column."""
    return Traces(period_s, log["theta"][:, None], log["mode"][:, None].astype(int),
                  log["u"][:, None], log["i_d"][:, None], voltage_limit_v, current_limit_a)


def _hanging_passes(theta: np.ndarray, before: np.ndarray) -> np.ndarray:
    """Passes through hanging of each column in the rows before ``before`` (per column).

    The offset from the nearest hanging angle pi + 2 pi b changes side when the pendulum
    swings through the bottom, or when it goes over the top (b changes): only the first
    counts, and only once it is ``HANGING_BAND_RAD`` past each side."""
    n = theta.shape[1]
    side = np.zeros(n)
    count = np.zeros(n)
    previous = np.round((theta[0] - np.pi) / (2 * np.pi))
    for k in range(theta.shape[0]):
        u = theta[k] - np.pi
        b = np.round(u / (2 * np.pi))
        d = u - 2 * np.pi * b
        new = np.where(d > HANGING_BAND_RAD, 1.0, np.where(d < -HANGING_BAND_RAD, -1.0, 0.0))
        side = np.where(b != previous, 0.0, side)  # over the top: no pass through hanging
        count += (k < before) & (new != 0.0) & (side != 0.0) & (new != side)
        side = np.where(new != 0.0, new, side)
        previous = b
    return count


def measure(traces: Traces) -> dict[str, np.ndarray]:
    """Every event of :data:`EVENTS` measured on each column of ``traces``."""
    theta, mode = traces.theta_rad, traces.mode
    cycles = theta.shape[0]
    t = np.arange(cycles) * traces.period_s
    catch = mode == Mode.CATCH.code
    caught = catch.any(axis=0)
    first = np.where(caught, np.argmax(catch, axis=0), cycles)
    rows = np.arange(cycles)[:, None]
    after = rows >= first
    hand_over = np.where(caught, t[np.minimum(first, cycles - 1)], np.inf)
    exits = np.sum(after[1:] & catch[:-1] & ~catch[1:], axis=0).astype(float)
    # upright: the first row from which every later row is within UPRIGHT_RAD, after the
    # hand-over (wrap_to_upright, (4.1)'s angle from the nearest upright)
    off = np.abs(theta - 2.0 * np.pi * np.floor(theta / (2.0 * np.pi) + 0.5)) >= UPRIGHT_RAD
    bad = off | ~after
    last_bad = cycles - 1 - np.argmax(bad[::-1], axis=0)
    settled = np.where(bad.any(axis=0), last_bad + 1, 0)
    upright = np.where(caught & (settled < cycles), t[np.minimum(settled, cycles - 1)], np.inf)
    u, i_d = traces.voltage_v, traces.setpoint_a
    v_sat = np.abs(u) >= SATURATED_SHARE * traces.voltage_limit_v
    i_sat = np.abs(i_d) >= traces.current_limit_a * (1.0 - 1e-9)
    both = np.sum(v_sat & i_sat & (np.sign(u) == np.sign(i_d)), axis=0)
    either = np.sum(v_sat | i_sat, axis=0)
    overlap = np.where(either > 0, both / np.maximum(either, 1), 0.0)
    return {"oscillations": _hanging_passes(theta, first) / 2.0, "hand_over_s": hand_over,
            "upright_s": upright, "catch_exits": exits, "saturation_overlap": overlap}


def judge(experiment: Experiment, measured: Mapping[str, np.ndarray]) -> np.ndarray:
    """Whether each column meets every event of ``experiment`` (a boolean array)."""
    ok = np.ones(len(next(iter(measured.values()))), dtype=bool)
    for event in experiment.events:
        ok &= event.passes(measured[event.name])
    return ok


def format_score(experiment: Experiment, measured: Mapping[str, np.ndarray],
                 column: int = 0) -> list[str]:
    """One line an event: the thesis's value and tolerance, the run's, pass or miss."""
    lines = []
    for event in experiment.events:
        value = float(measured[event.name][column])
        mark = "meets" if bool(event.passes(value)) else "MISSES"
        lines.append(f"  {event.describe():40s} run {value:8.3f}   {mark}")
    return lines
