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

Memory: :func:`replay_bag` reads the bag as columns
(:mod:`pisc_bag.bag_columns`) and keeps the samples and the recorded and recomputed
outputs as numpy columns (:class:`StampTable`, :class:`Samples`: about 100 bytes a
cycle), not as decoded messages and dictionaries (about 2 kB a cycle); a bag the
columns cannot read without guessing goes through the messages, whose errors name the
message. Both give the same run, so the same report.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Collection, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pisc_bag.run_files import PARAMS_FILE, recorded_params
from pisc_bag.bag import BagError, BagMessage, bag_topics, read_bag
from pisc_runs.summary import foreign_in_bag
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
    JOINT_NAMES,
    JOINT_STATES,
    MODE,
    MOTOR_CURRENT,
    MOTOR_JOINT,
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
    "Samples",
    "StampTable",
    "bag_config",
    "compare",
    "load_recorded",
    "load_recorded_bag",
    "replay_bag",
    "replay_cores",
]

COMPARED_TOPICS = (STATE.name, CART_FORCE.name, MODE.name, CURRENT_SETPOINT.name, VOLTAGE.name)
# the values each compared topic carries, in the order they are compared
FIELDS = {
    STATE.name: ("x_dot", "theta_dot"),
    CART_FORCE.name: ("force",),
    MODE.name: ("mode",),
    CURRENT_SETPOINT.name: ("i_d",),
    VOLTAGE.name: ("voltage",),
}

#: per compared topic: stamp -> values (a mode is its Mode); a dict or a StampTable
Outputs = dict[str, Mapping[int, tuple[Any, ...]]]


class StampTable(Mapping[int, tuple[float, ...]]):
    """stamp -> values of one topic, held as numpy columns: the stamps in increasing
    order, one row of float values each (what a dict of tuples holds, in 16 bytes a
    value instead of about 200)."""

    def __init__(self, stamps: np.ndarray, values: np.ndarray) -> None:
        self.stamps = np.asarray(stamps, dtype=np.int64)
        self.values = np.asarray(values, dtype=np.float64)
        if self.values.ndim == 1:
            self.values = self.values.reshape(-1, 1)

    @classmethod
    def first_of(cls, stamps: np.ndarray, values: np.ndarray) -> StampTable:
        """From messages in file order: the first message of each stamp (a resent sample
        is answered again with the same message), as :func:`load_recorded` keeps it."""
        unique, first = np.unique(stamps, return_index=True)
        return cls(unique, values[first])

    def _at(self, stamp: int) -> int:
        i = int(np.searchsorted(self.stamps, stamp))
        return i if i < len(self.stamps) and self.stamps[i] == stamp else -1

    def __getitem__(self, stamp: int) -> tuple[float, ...]:
        i = self._at(stamp)
        if i < 0:
            raise KeyError(stamp)
        return tuple(self.values[i].tolist())

    def __contains__(self, stamp: object) -> bool:
        return isinstance(stamp, (int, np.integer)) and self._at(int(stamp)) >= 0

    def __iter__(self) -> Iterator[int]:
        return iter(self.stamps.tolist())

    def __len__(self) -> int:
        return len(self.stamps)

    def drop_after(self, last: int) -> None:
        """Forget the stamps after ``last``."""
        keep = int(np.searchsorted(self.stamps, last, side="right"))
        self.stamps, self.values = self.stamps[:keep], self.values[:keep]


class Samples(Sequence[tuple[int, float, float, float]]):
    """(stamp, x, theta, i) of each sample in order, held as numpy columns."""

    def __init__(self, stamps: np.ndarray, x: np.ndarray, theta: np.ndarray,
                 current: np.ndarray) -> None:
        self.stamps, self.x, self.theta, self.current = stamps, x, theta, current

    def __len__(self) -> int:
        return len(self.stamps)

    def __getitem__(self, k: Any) -> Any:
        if isinstance(k, slice):
            return [self[i] for i in range(*k.indices(len(self)))]
        return (int(self.stamps[k]), float(self.x[k]), float(self.theta[k]),
                float(self.current[k]))

    def __iter__(self) -> Iterator[tuple[int, float, float, float]]:
        return zip(self.stamps.tolist(), self.x.tolist(), self.theta.tolist(),
                   self.current.tolist(), strict=True)


@dataclass(frozen=True)
class RecordedRun:
    """The samples a run fed its controllers and the outputs they answered, by stamp."""

    samples: Sequence[tuple[int, float, float, float]]  # (stamp, x, theta, i) in order
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
    return _recorded_run(joints, currents, outputs, where)


def _drop_after(table: Any, last: int) -> None:
    if isinstance(table, StampTable):
        table.drop_after(last)
    else:
        for s in [s for s in table if s > last]:
            del table[s]


def _recorded_run(joints: Mapping[int, tuple[float, float]], currents: Mapping[int, Any],
                  outputs: Outputs, where: str) -> RecordedRun:
    """The run from its tables (dicts from the messages, or StampTables from the
    columns, where a current is a 1-tuple): the incomplete last cycle dropped, every
    other sample whole (see :func:`load_recorded`)."""
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
        for table in (joints, currents, *outputs.values()):
            _drop_after(table, last)
        if not outputs[VOLTAGE.name]:
            raise BagError(f"{where}: no {VOLTAGE.name} message before the incomplete last "
                           "cycle: nothing to compare with")
    if isinstance(joints, StampTable) and isinstance(currents, StampTable):
        both = np.isin(joints.stamps, currents.stamps)
        if not both.all():
            stamp = int(joints.stamps[np.argmin(both)])
            raise BagError(f"{where}: {JOINT_STATES.name} at stamp {stamp} has no "
                           f"{MOTOR_CURRENT.name} of the same stamp (the current loop needs "
                           "both)")
        current = currents.values[np.searchsorted(currents.stamps, joints.stamps), 0]
        return RecordedRun(Samples(joints.stamps, joints.values[:, 0], joints.values[:, 1],
                                   current), outputs, notes)
    samples = []
    for stamp in sorted(joints):
        if stamp not in currents:
            raise BagError(f"{where}: {JOINT_STATES.name} at stamp {stamp} has no "
                           f"{MOTOR_CURRENT.name} of the same stamp (the current loop needs "
                           "both)")
        samples.append((stamp, *joints[stamp], currents[stamp]))
    return RecordedRun(samples, outputs, notes)


#: the columns each topic's values are read from, by topic: (type's joint names, the
#: fields the message path checks, the field replay takes, its joint or None for all)
_COLUMNS = {
    JOINT_STATES.name: (JOINT_NAMES, ("position",), "position"),
    MOTOR_CURRENT.name: ((MOTOR_JOINT,), ("effort",), "effort"),
    STATE.name: (JOINT_NAMES, ("position", "velocity"), "velocity"),
    CART_FORCE.name: (("x", "y", "z"), ("force",), "force"),
    CURRENT_SETPOINT.name: ((MOTOR_JOINT,), ("effort",), "effort"),
    VOLTAGE.name: ((MOTOR_JOINT,), ("effort",), "effort"),
}


def load_recorded_columns(bag: str | Path, where: str = "bag") -> RecordedRun:
    """:func:`load_recorded` of a bag's messages, read as columns (bounded memory); the
    same run. :class:`~pisc_bag.bag_columns.FastPathRefused` where a message would
    have to be decoded to say what is wrong with it."""
    from pisc_bag.bag_columns import FastPathRefused, read_columns

    columns, modes = read_columns(bag, list(_COLUMNS), [MODE.name])
    tables: dict[str, StampTable] = {}
    for topic, (names, checked, taken) in _COLUMNS.items():
        c = columns[topic]
        if len(c) and (c.names != names or any(f not in c.values for f in checked)):
            raise FastPathRefused(f"{topic}: not the joints or fields replay reads")
        values = c.values[taken] if len(c) else np.zeros((0, len(names)))
        if topic == CART_FORCE.name:
            values = values[:, :1]  # force.x
        tables[topic] = StampTable.first_of(c.stamp_ns, values)
    del columns
    mode_table: dict[int, tuple[Any, ...]] = {}
    for _, _, _, msg in modes:
        try:
            report = mode_from_msg(msg)
        except MessageError as exc:
            raise BagError(f"{where}: {MODE.name}: {exc}") from None
        _first(mode_table, report.stamp_ns, (report.mode,))
    outputs: Outputs = {name: tables[name] if name != MODE.name else mode_table
                        for name in COMPARED_TOPICS}
    return _recorded_run(tables[JOINT_STATES.name], tables[MOTOR_CURRENT.name], outputs,
                         where)


def load_recorded_bag(bag: str | Path) -> RecordedRun:
    """The recorded run of a bag: through its columns, else through its messages."""
    from pisc_bag.bag_columns import FastPathRefused

    try:
        return load_recorded_columns(bag, str(bag))
    except FastPathRefused:
        return load_recorded(read_bag(bag), str(bag))


def replay_cores(run: RecordedRun, config: GraphConfig) -> Outputs:
    """Every sample of ``run`` through the controller cores; outputs keyed by stamp (as
    :class:`StampTable` columns: the samples come in increasing stamp order).

    The mode is reported at changes only, as the supervisor node publishes it.
    """
    controllers = Controllers(config)
    n = len(run.samples)
    stamps = np.empty(n, dtype=np.int64)
    # per sample: x_dot, theta_dot, force, i_d, u
    values = np.empty((n, 5), dtype=np.float64)
    modes: dict[int, tuple[Any, ...]] = {}
    mode: Mode | None = None
    for k, (stamp, x, theta, current) in enumerate(run.samples):
        o = controllers.step(x, theta, current)
        stamps[k] = stamp
        values[k] = (o.x_dot, o.theta_dot, o.force, o.i_d, o.voltage)
        if o.mode is not mode:
            modes[stamp] = (o.mode,)
            mode = o.mode
    if n > 1 and not np.all(np.diff(stamps) > 0):  # a run made by hand: a later output wins
        tables = [(STATE.name, 0, 2), (CART_FORCE.name, 2, 3), (CURRENT_SETPOINT.name, 3, 4),
                  (VOLTAGE.name, 4, 5)]
        out: Outputs = {name: {int(t): tuple(v) for t, v in zip(stamps.tolist(), values[:, a:b]
                                                               .tolist(), strict=True)}
                        for name, a, b in tables}
        out[MODE.name] = modes
        return {name: out[name] for name in COMPARED_TOPICS}
    return {STATE.name: StampTable(stamps, values[:, 0:2]),
            CART_FORCE.name: StampTable(stamps, values[:, 2:3]),
            MODE.name: modes,
            CURRENT_SETPOINT.name: StampTable(stamps, values[:, 3:4]),
            VOLTAGE.name: StampTable(stamps, values[:, 4:5])}


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
    # "TOPIC: publishers" the bag marks as foreign (/pisc/recorder/foreign): its messages
    # may not be the graph's, so nothing it holds is called reproduced
    foreign: list[str] = field(default_factory=list)

    @property
    def reproduced(self) -> bool:
        return not self.foreign and all(t.differ == 0 for t in self.topics)

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
        for foreign in self.foreign:
            lines.append(f"the bag marks another publisher than the graph's on {foreign}")
        verdict = ("CONTESTED" if self.foreign else
                   "REPRODUCED" if self.reproduced else "MISMATCH")
        lines.append(f"result: {verdict} (tolerance {self.tolerance:g})")
        return "\n".join(lines)


def _difference(a: Any, b: Any) -> float:
    if isinstance(a, Mode) or isinstance(b, Mode):
        return 0.0 if a is b else math.inf
    if a == b:  # also two equal infinities
        return 0.0
    d = abs(a - b)
    return math.inf if math.isnan(d) else d


_ROWS = 8192  # stamps looked up at a time in compare()


def _rows(table: Mapping[int, tuple[Any, ...]], keys: list[int]) -> list[Any]:
    """``[table.get(s) for s in keys]``, for a StampTable looked up all at once."""
    if not isinstance(table, StampTable):
        return [table.get(s) for s in keys]
    if not len(table):
        return [None] * len(keys)
    wanted = np.asarray(keys, dtype=np.int64)
    at = np.minimum(np.searchsorted(table.stamps, wanted), len(table) - 1)
    found = (table.stamps[at] == wanted).tolist()
    return [tuple(row) if f else None
            for row, f in zip(table.values[at].tolist(), found, strict=True)]


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
        for stamp, a, b in ((stamp, a, b) for lo in range(0, len(keys), _ROWS)
                            for stamp, a, b in zip(keys[lo:lo + _ROWS],
                                                   _rows(rec, keys[lo:lo + _ROWS]),
                                                   _rows(new, keys[lo:lo + _ROWS]),
                                                   strict=True)):
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
        recorded_params(bag, required=True)  # refused here, naming the bag, if missing
        source = str(Path(bag) / PARAMS_FILE)
    cfg, _ = load_graph_config(source, overrides)
    return cfg, source


def replay_bag(bag: str | Path, config: str | None = None,
               overrides: Mapping[str, Any] | None = None,
               tolerance: float = 0.0) -> ReplayReport:
    """Regression replay of a bag through the controller cores."""
    cfg, source = bag_config(bag, config, overrides)
    run = load_recorded_bag(bag)
    report = compare(run, replay_cores(run, cfg), tolerance, str(bag), "cores",
                     bag_topics(bag))
    report.foreign.extend(foreign_in_bag(bag))
    changed = ", ".join(f"{k}={v}" for k, v in (overrides or {}).items())
    report.notes.append(f"configuration: {source}" + (f" with {changed}" if changed else ""))
    return report
