"""Regression replay: a bag's measurements through the controllers, every output compared.

The recorded samples (``/pisc/joint_states`` and ``/pisc/motor/current``, keyed by
header stamp) go through the estimator, supervisor and current-loop cores
(:class:`pisc_sim.closed_loop.Controllers`, what the nodes and the simulation
run), with the configuration the run used (the bag's ``pisc_params.yaml``) or another.
A bag of a simulated run also holds ``plant_params.yaml``, what the plant ran (with model
error it differs from the controllers' file); replay does not read it: the recorded
samples carry the plant. Each recomputed output is compared with the recorded one of the
same stamp:

* ``/pisc/state``: the velocities (4.7), (4.9) (the positions pass through);
* ``/pisc/cart_force``: the force (3.30) or (3.46);
* ``/pisc/mode``: the mode at every change (4.1);
* ``/pisc/motor/current_setpoint``: i_d (4.2);
* ``/pisc/motor/voltage``: u (3.47).

With the same configuration the outputs are the same bits (tolerance 0). A report
gives, per topic, how many outputs were compared, how many differ by more than the
tolerance, the largest difference and the first divergence. The same comparison runs
on the outputs of the real nodes over topics (:mod:`pisc_bringup.replay_node`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Collection, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pisc_bringup.bag import BagError, BagMessage, bag_topics, read_bag
from pisc_sim.closed_loop import Controllers
from pisc_sim.configuration import GraphConfig, load_graph_config
from pisc_msgs_py.convert import (
    MessageError,
    cart_force_from_msg,
    joint_sample_from_msg,
    mode_from_msg,
    motor_sample_from_msg,
    state_from_msg,
)
from pisc_msgs_py.topics import (
    CART_FORCE,
    CURRENT_SETPOINT,
    JOINT_STATES,
    MODE,
    MOTOR_CURRENT,
    STATE,
    VOLTAGE,
)
from pisc_msgs_py.types import Mode

__all__ = [
    "COMPARED_TOPICS",
    "Outputs",
    "RecordedRun",
    "ReplayReport",
    "TopicComparison",
    "bag_config",
    "compare",
    "load_recorded",
    "replay_bag",
    "replay_cores",
]

PARAMS_FILE = "pisc_params.yaml"
COMPARED_TOPICS = (STATE.name, CART_FORCE.name, MODE.name, CURRENT_SETPOINT.name, VOLTAGE.name)
# the values each compared topic carries, in the order they are compared
FIELDS = {
    STATE.name: ("x_dot", "theta_dot"),
    CART_FORCE.name: ("force",),
    MODE.name: ("mode",),
    CURRENT_SETPOINT.name: ("i_d",),
    VOLTAGE.name: ("voltage",),
}

#: per compared topic: stamp -> values (a mode is its Mode)
Outputs = dict[str, dict[int, tuple[Any, ...]]]


@dataclass(frozen=True)
class RecordedRun:
    """The samples a run fed its controllers and the outputs they answered, by stamp."""

    samples: list[tuple[int, float, float, float]]  # (stamp, x, theta, i) in order
    outputs: Outputs
    notes: list[str] = field(default_factory=list)  # what was dropped, and why

    @property
    def first_stamp_ns(self) -> int:
        return self.samples[0][0]


def _first(table: dict[int, Any], stamp: int, value: Any) -> None:
    # a resent sample is answered again with the same message: keep the first
    table.setdefault(stamp, value)


def load_recorded(messages: Iterable[BagMessage], where: str = "bag") -> RecordedRun:
    """Samples and outputs of a run from its messages; :class:`BagError` if unusable.

    A sample is a stamp's ``/pisc/joint_states`` with its ``/pisc/motor/current``. A
    recording that ended inside a cycle (a recorder that died, its bag repaired) holds
    part of its last cycle: the stamps after the last whole sample are dropped, their
    outputs with them, and the run's notes say so. A sample missing anywhere before
    is an error.
    """
    joints: dict[int, tuple[float, float]] = {}
    currents: dict[int, float] = {}
    outputs: Outputs = {name: {} for name in COMPARED_TOPICS}
    readers: dict[str, Callable[[Any], None]] = {
        JOINT_STATES.name: lambda m: _first(
            joints, (s := joint_sample_from_msg(m)).stamp_ns, (s.position_m, s.angle_rad)),
        MOTOR_CURRENT.name: lambda m: _first(
            currents, (s := motor_sample_from_msg(m)).stamp_ns, s.value),
        STATE.name: lambda m: _first(
            outputs[STATE.name], (s := state_from_msg(m)).stamp_ns,
            (s.velocity_mps, s.rate_radps)),
        CART_FORCE.name: lambda m: _first(
            outputs[CART_FORCE.name], (s := cart_force_from_msg(m)).stamp_ns, (s.force_n,)),
        MODE.name: lambda m: _first(
            outputs[MODE.name], (s := mode_from_msg(m)).stamp_ns, (s.mode,)),
        CURRENT_SETPOINT.name: lambda m: _first(
            outputs[CURRENT_SETPOINT.name], (s := motor_sample_from_msg(m)).stamp_ns, (s.value,)),
        VOLTAGE.name: lambda m: _first(
            outputs[VOLTAGE.name], (s := motor_sample_from_msg(m)).stamp_ns, (s.value,)),
    }
    for m in messages:
        reader = readers.get(m.topic)
        if reader is None:
            continue
        try:
            reader(m.message)
        except MessageError as exc:
            raise BagError(f"{where}: {m.topic}: {exc}") from None
    if not joints:
        raise BagError(f"{where}: no {JOINT_STATES.name} message: nothing to replay")
    if not outputs[VOLTAGE.name]:
        raise BagError(f"{where}: no {VOLTAGE.name} message: nothing to compare with")
    whole = [s for s in joints if s in currents]
    last = max(whole, default=None)
    notes = []
    partial = sorted(s for s in set(joints) | set(currents) if last is None or s > last)
    if last is not None and partial:
        missing = {s: MOTOR_CURRENT.name if s in joints else JOINT_STATES.name for s in partial}
        t0 = min(whole)
        notes.append("dropped the incomplete last cycle" + ("s" if len(partial) > 1 else "")
                     + ", the recording ended inside it: " + "; ".join(
                         f"stamp {s} (t = {(s - t0) * 1e-9:.3f} s) has no {missing[s]}"
                         for s in partial))
        for s in partial:
            joints.pop(s, None)
            currents.pop(s, None)
        for table in outputs.values():
            for s in [s for s in table if s > last]:
                del table[s]
        if not outputs[VOLTAGE.name]:
            raise BagError(f"{where}: no {VOLTAGE.name} message before the incomplete last "
                           "cycle: nothing to compare with")
    samples = []
    for stamp in sorted(joints):
        if stamp not in currents:
            raise BagError(f"{where}: {JOINT_STATES.name} at stamp {stamp} has no "
                           f"{MOTOR_CURRENT.name} of the same stamp (the current loop needs "
                           "both)")
        samples.append((stamp, *joints[stamp], currents[stamp]))
    return RecordedRun(samples, outputs, notes)


def replay_cores(run: RecordedRun, config: GraphConfig) -> Outputs:
    """Every sample of ``run`` through the controller cores; outputs keyed by stamp.

    The mode is reported at changes only, as the supervisor node publishes it.
    """
    controllers = Controllers(config)
    out: Outputs = {name: {} for name in COMPARED_TOPICS}
    mode: Mode | None = None
    for stamp, x, theta, current in run.samples:
        o = controllers.step(x, theta, current)
        out[STATE.name][stamp] = (o.x_dot, o.theta_dot)
        out[CART_FORCE.name][stamp] = (o.force,)
        if o.mode is not mode:
            out[MODE.name][stamp] = (o.mode,)
            mode = o.mode
        out[CURRENT_SETPOINT.name][stamp] = (o.i_d,)
        out[VOLTAGE.name][stamp] = (o.voltage,)
    return out


@dataclass(frozen=True)
class Divergence:
    stamp_ns: int
    t_s: float  # run time: stamp minus the first sample's
    field: str
    recorded: Any  # None: not in the bag
    recomputed: Any  # None: not recomputed

    def format(self) -> str:
        def show(v: Any) -> str:
            if v is None:
                return "none"
            return v.value if isinstance(v, Mode) else repr(v)

        return (f"t = {self.t_s:.3f} s (stamp {self.stamp_ns}) {self.field}: recorded "
                f"{show(self.recorded)}, recomputed {show(self.recomputed)}")


@dataclass(frozen=True)
class TopicComparison:
    topic: str
    compared: int  # stamps present in both
    differ: int  # stamps whose values differ beyond the tolerance, or present in one only
    largest: float  # largest |recorded - recomputed| over the compared values (mode: 0/inf)
    largest_at: Divergence | None
    first: Divergence | None


@dataclass(frozen=True)
class ReplayReport:
    bag: str
    how: str  # 'cores' or 'nodes'
    cycles: int
    tolerance: float
    topics: list[TopicComparison]
    unanswered: int = 0  # samples after the last recorded voltage (the run ended)
    notes: list[str] = field(default_factory=list)

    @property
    def reproduced(self) -> bool:
        return all(t.differ == 0 for t in self.topics)

    def format(self) -> str:
        what = ("the estimator, supervisor and current loop cores" if self.how == "cores"
                else "the estimator, supervisor and current loop nodes over topics")
        lines = [f"replay {self.bag}: {self.cycles} cycles through {what}", *self.notes]
        lines.append(f"{'topic':<31}{'compared':>9}{'differ':>8}  largest |diff|")
        for t in self.topics:
            largest = f"{t.largest:.6g}"
            if t.largest_at is not None and t.largest > 0:
                largest += f" at t = {t.largest_at.t_s:.3f} s ({t.largest_at.field})"
            lines.append(f"{t.topic:<31}{t.compared:>9}{t.differ:>8}  {largest}")
        diverged = sorted((t for t in self.topics if t.first is not None),
                          key=lambda t: t.first.stamp_ns)  # the earliest first
        for t in diverged:
            lines.append(f"first divergence on {t.topic}: {t.first.format()}")
        if self.unanswered:
            lines.append(f"{self.unanswered} sample(s) after the last recorded voltage "
                         "(the run ended before their answer) not compared")
        verdict = ("REPRODUCED" if self.reproduced else "MISMATCH")
        lines.append(f"result: {verdict} (tolerance {self.tolerance:g})")
        return "\n".join(lines)


def _difference(a: Any, b: Any) -> float:
    if isinstance(a, Mode) or isinstance(b, Mode):
        return 0.0 if a is b else math.inf
    if a == b:  # also two equal infinities
        return 0.0
    d = abs(a - b)
    return math.inf if math.isnan(d) else d


def compare(run: RecordedRun, recomputed: Outputs, tolerance: float = 0.0,
            bag: str = "bag", how: str = "cores",
            recorded: Collection[str] | None = None) -> ReplayReport:
    """Compare recomputed outputs with the recorded ones, stamp by stamp.

    ``recorded``: the topics the bag recorded (None: all); the others are not compared,
    and the report says so.
    """
    t0 = run.first_stamp_ns
    last_answered = max(run.outputs[VOLTAGE.name])
    stamps = [s for s, *_ in run.samples if s <= last_answered]
    unanswered = len(run.samples) - len(stamps)
    comparisons = []
    skipped = [t for t in COMPARED_TOPICS if recorded is not None and t not in recorded]
    for topic in COMPARED_TOPICS:
        if topic in skipped:
            continue
        rec, new = run.outputs[topic], recomputed.get(topic, {})
        if topic == MODE.name:
            keys = sorted(s for s in set(rec) | set(new) if s <= last_answered)
        else:
            keys = stamps
        compared = differ = 0
        largest, largest_at, first = 0.0, None, None
        for stamp in keys:
            a, b = rec.get(stamp), new.get(stamp)
            if a is None or b is None:
                differ += 1
                d = Divergence(stamp, (stamp - t0) * 1e-9, FIELDS[topic][0],
                               None if a is None else a[0], None if b is None else b[0])
                first = first or d
                continue
            compared += 1
            bad = None
            for name, x, y in zip(FIELDS[topic], a, b, strict=True):
                diff = _difference(x, y)
                if diff > largest or (largest_at is None and diff == largest):
                    largest = diff
                    largest_at = Divergence(stamp, (stamp - t0) * 1e-9, name, x, y)
                if diff > tolerance and bad is None:
                    bad = Divergence(stamp, (stamp - t0) * 1e-9, name, x, y)
            if bad is not None:
                differ += 1
                first = first or bad
        comparisons.append(TopicComparison(topic, compared, differ, largest, largest_at, first))
    notes = [*run.notes,
             *([f"not recorded, so not compared: {', '.join(skipped)}"] if skipped else [])]
    return ReplayReport(bag, how, len(stamps), tolerance, comparisons, unanswered, notes)


def bag_config(bag: str | Path, config: str | None = None,
               overrides: Mapping[str, Any] | None = None) -> tuple[GraphConfig, str]:
    """The configuration a bag was recorded with (its ``pisc_params.yaml``), or ``config``.

    Returns the configuration and where it came from.
    """
    source = config
    if not Path(bag).is_dir():
        raise BagError(f"{bag}: no such bag directory")
    if source is None:
        params = Path(bag) / PARAMS_FILE
        if not params.exists():
            raise BagError(f"{bag}: no {PARAMS_FILE} (the parameters of the run); name the "
                           "configuration it ran with (--config)")
        source = str(params)
    cfg, _ = load_graph_config(source, overrides)
    return cfg, source


def replay_bag(bag: str | Path, config: str | None = None,
               overrides: Mapping[str, Any] | None = None,
               tolerance: float = 0.0) -> ReplayReport:
    """Regression replay of a bag through the controller cores."""
    cfg, source = bag_config(bag, config, overrides)
    run = load_recorded(read_bag(bag), str(bag))
    report = compare(run, replay_cores(run, cfg), tolerance, str(bag), "cores",
                     bag_topics(bag))
    changed = ", ".join(f"{k}={v}" for k, v in (overrides or {}).items())
    report.notes.append(f"configuration: {source}" + (f" with {changed}" if changed else ""))
    return report
