"""What a run did, read back from its bag: catch time, final state, tracking, latency.

Everything is computed from the recorded messages, keyed by the header stamp of the
cycle, so it works the same for a simulated run and for the rig. Run time ``t`` is the
stamp minus the first sample's stamp.

**The verdict** is the robustness benchmark's (:class:`pisc_runs.verdict.Criteria`,
:func:`pisc_runs.verdict.judge`), judged on the simulator's true state where the bag
has it, else on the measured one: *safe* (no fault, never outside the safe range),
*caught* (safe, caught for good by 8 s, held from 9 s to the end of the run) and *fast*
(by 3 s, held from 6 s). The summary prints each tier's verdict with its rule; its
``result`` line and the runner's exit status follow one tier (``caught`` unless told).
A run that ends before a tier's hold window starts does not pass that tier.

Latency of a cycle is the time from the plant (or driver) sending sample k to the
current loop sending the voltage stamped k, from the DDS source timestamps the bag
keeps as ``publish_time``: it is measured in wall-clock time in both lockstep and
real-time runs. A cycle whose latency exceeds the period missed its deadline.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from pisc_bag.bag import BagError, BagMessage, read_bag
from pisc_runs.verdict import TIERS, Criteria, Outcomes, judge
from pisc_msgs_py.convert import (
    MessageError,
    joint_sample_from_msg,
    mode_from_msg,
    motor_sample_from_msg,
    state_from_msg,
    true_state_from_msg,
)
from pisc_msgs_py.topics import (
    CURRENT_SETPOINT,
    JOINT_NAMES,
    JOINT_STATES,
    FOREIGN,
    MODE,
    MOTOR_CURRENT,
    MOTOR_JOINT,
    SIM_STATE,
    STATE,
    VOLTAGE,
)
from pisc_msgs_py.types import Mode
from pisc_model.dynamics import wrap_to_upright

__all__ = ["RunSummary", "RunTables", "Table", "foreign_in_bag", "member", "safe_range_of",
           "summarise", "summarise_bag", "summarise_tables", "tables_of", "tables_of_bag"]

#: The tier the ``result`` line and the exit status follow unless told otherwise
VERDICT_TIER = "caught"


@dataclass(frozen=True)
class RunSummary:
    duration_s: float
    cycles: int
    first_catch_s: float | None
    caught_at_s: float | None  # start of the catch that lasted to the end of the run
    mode_changes: int
    faults: list[str]
    final_theta_rad: float  # from the nearest upright
    final_x_m: float
    max_abs_x_m: float
    x_range_m: tuple[float, float]
    hold_theta_rad: float  # largest |theta| from the fast tier's hold window (6 s) on
    hold_x_m: float
    held: bool  # inside the hold box from the fast tier's hold window to the end
    state_source: str  # 'true' (simulator) or 'measured'
    current_rms_error_a: float
    latency_ms: dict[str, float] = field(default_factory=dict)
    deadline_misses: int = 0
    period_s: float = 0.005
    # "TOPIC: publishers" for each publisher other than the graph's the bag marks
    # (/pisc/recorder/foreign) or the run saw: such a run is never CAUGHT
    foreign: list[str] = field(default_factory=list)
    # cycles whose voltage was published before their sample: their times cannot be
    # the graph's own (another publisher, or a clock that stepped back)
    negative_latencies: int = 0

    criteria: Criteria = field(default_factory=Criteria)
    safe_range_m: tuple[float, float] = (-math.inf, math.inf)
    unheld_at_s: float = -math.inf  # the last sample outside the hold box; -inf if none
    left_range: bool = False  # outside the safe range at some sample
    passed: dict[str, bool] = field(default_factory=dict)  # each tier's verdict
    why: dict[str, str] = field(default_factory=dict)  # why a tier failed ('' if it passed)
    tier: str = VERDICT_TIER  # the tier of ``caught`` and the result line

    @property
    def caught(self) -> bool:
        """Whether the run passes :attr:`tier` (the benchmark's rule)."""
        return self.passed.get(self.tier, False)

    def rules(self) -> dict[str, str]:
        """Each tier's rule in words, for this run's length."""
        c = self.criteria
        box = f"|theta| < {c.theta_rad:g} rad, |x| < {c.x_m:g} m"
        out = {"safe": f"no fault, inside the safe range {self.safe_range_m[0]:+.3f} .. "
                       f"{self.safe_range_m[1]:+.3f} m"}
        for name in ("caught", "fast"):
            by, hold = c.rule(name)
            out[name] = (f"caught for good by {by:g} s, held ({box}) from {hold:g} s to "
                         f"the end ({self.duration_s:.3g} s)")
        return out

    def verdict_lines(self, tier: str | None = None) -> list[str]:
        """Each tier's verdict with its rule, and the result line of ``tier``."""
        tier = tier or self.tier
        rules = self.rules()
        lines = [f"{name:<23}{'yes' if self.passed[name] else 'NO'}: {rules[name]}"
                 + ("" if self.passed[name] else f" ({self.why[name]})")
                 for name in TIERS]
        word = "CAUGHT" if tier != "safe" else "SAFE"
        result = word if self.passed[tier] else f"NOT {word}"
        lines.append(f"result                 {result} (the {tier} tier: {rules[tier]})")
        return lines

    def format(self, tier: str | None = None, experiment: str = "none") -> str:
        """The summary; its verdict by ``tier`` (default :attr:`tier`), or for an
        experiment run (``experiment.kind``) what the experiment did instead of a
        swing-up's verdict."""
        def t(v: float | None) -> str:
            return "never" if v is None else f"{v:.3f} s"

        lat = self.latency_ms
        lines = [
            f"cycles                 {self.cycles} ({self.duration_s:.3f} s)",
            f"first catch            {t(self.first_catch_s)}",
            f"caught for good        {t(self.caught_at_s)}",
            f"mode changes           {self.mode_changes}",
            f"final |theta|, |x|     {abs(self.final_theta_rad):.4f} rad, "
            f"{abs(self.final_x_m):.4f} m ({self.state_source} state)",
            f"largest |x|            {self.max_abs_x_m:.4f} m (range {self.x_range_m[0]:+.4f} .."
            f" {self.x_range_m[1]:+.4f} m)",
            f"balance from {self.criteria.fast_hold_from_s:g} s       |theta| <= "
            f"{self.hold_theta_rad:.4f} rad, |x| <= {self.hold_x_m:.4f} m: "
            f"{'held' if self.held else 'NOT held'}",
            f"current tracking RMS   {self.current_rms_error_a:.4f} A (i_d - i, same cycle)",
        ]
        if lat:
            lines.append(
                f"sample-to-voltage      median {lat['median']:.3f} ms, p90 {lat['p90']:.3f} ms, "
                f"p99 {lat['p99']:.3f} ms, max {lat['max']:.3f} ms; "
                f"{self.deadline_misses} cycles over the {self.period_s * 1e3:.0f} ms period")
        if self.negative_latencies:
            lines.append(f"TIMES                  {self.negative_latencies} cycles whose "
                         "voltage was published before their sample: not the graph's own "
                         "timing (another publisher, or a clock that stepped back)")
        for fault in self.faults:
            lines.append(f"FAULT                  {fault}")
        for foreign in self.foreign:
            lines.append(f"FOREIGN PUBLISHER      {foreign}")
        if experiment != "none":  # nothing was to be caught: what the experiment did
            lines.append(f"experiment             {experiment}: " + (
                f"FAULT ({self.faults[0]})" if self.faults else "completed without a fault")
                + f"; cart within {self.x_range_m[0]:+.4f} .. {self.x_range_m[1]:+.4f} m")
            return "\n".join(lines)
        return "\n".join(lines + self.verdict_lines(tier))


def _percentiles(values: np.ndarray) -> dict[str, float]:
    if len(values) == 0:
        return {}
    return {
        "median": float(np.median(values)),
        "p90": float(np.percentile(values, 90)),
        "p99": float(np.percentile(values, 99)),
        "max": float(np.max(values)),
    }


@dataclass
class Table:
    """One topic's numbers in file order: header stamps, publish times (:data:`NO_TIME`
    where a message has none) and values, one row per message."""

    stamp_ns: np.ndarray  # int64
    publish_ns: np.ndarray  # int64
    values: np.ndarray  # float64, (n, k)

    def pick(self, which: str) -> tuple[np.ndarray, np.ndarray]:
        """(sorted unique stamps, index of the message kept for each): the ``first`` or
        the ``last`` in file order (a lockstep plant that sends a sample again records
        it twice)."""
        stamps = self.stamp_ns
        if np.all(stamps[1:] > stamps[:-1]):  # the usual case: each once, in order
            return stamps, np.arange(len(stamps))
        order = np.argsort(stamps, kind="stable")  # equal stamps stay in file order
        ordered = stamps[order]
        change = ordered[1:] != ordered[:-1]
        keep = (np.concatenate([[True], change]) if which == "first"
                else np.concatenate([change, [True]]))
        return ordered[keep], order[keep]


NO_TIME = np.iinfo(np.int64).min


def member(values: np.ndarray, sorted_set: np.ndarray) -> np.ndarray:
    """Which of ``values`` are in ``sorted_set`` (sorted, unique): ``np.isin`` by binary
    search, without its hashing."""
    if not len(sorted_set):
        return np.zeros(len(values), dtype=bool)
    at = np.minimum(np.searchsorted(sorted_set, values), len(sorted_set) - 1)
    return sorted_set[at] == values


@dataclass
class RunTables:
    """What the summary and the analysis read from a run, by topic (see :func:`tables_of`)."""

    joints: Table  # position: x, theta
    state: Table  # velocity: x_dot, theta_dot
    current: Table  # effort: i
    setpoint: Table  # i_d
    voltage: Table  # u
    true: Table  # position: x, theta (the simulator's; empty on the rig)
    modes: list[tuple[int, Mode, str]]  # (stamp, mode, reason) in file order
    # "TOPIC: publishers" the recorder marked (/pisc/recorder/foreign), in file order
    foreign: list[str] = field(default_factory=list)


# topic -> (RunTables field, JointState field, number of joints read)
TABLE_TOPICS = {
    JOINT_STATES.name: ("joints", "position", 2),
    STATE.name: ("state", "velocity", 2),
    MOTOR_CURRENT.name: ("current", "effort", 1),
    CURRENT_SETPOINT.name: ("setpoint", "effort", 1),
    VOLTAGE.name: ("voltage", "effort", 1),
    SIM_STATE.name: ("true", "position", 2),
}


def tables_of(messages: Iterable[BagMessage], where: str = "") -> RunTables:
    """The tables of decoded messages; :class:`BagError` names a malformed one (after
    ``where``)."""
    rows: dict[str, list[tuple[int, int, tuple[float, ...]]]] = {t: [] for t in TABLE_TOPICS}
    modes: list[tuple[int, Mode, str]] = []
    foreign: list[str] = []
    for m in messages:
        try:
            if m.topic == JOINT_STATES.name:
                s = joint_sample_from_msg(m.message)
                values: tuple[float, ...] = (s.position_m, s.angle_rad)
            elif m.topic == STATE.name:
                e = state_from_msg(m.message)
                s, values = e, (e.velocity_mps, e.rate_radps)
            elif m.topic in (MOTOR_CURRENT.name, CURRENT_SETPOINT.name, VOLTAGE.name):
                s = motor_sample_from_msg(m.message)
                values = (s.value,)
            elif m.topic == SIM_STATE.name:
                s = true_state_from_msg(m.message)
                values = (s.position_m, s.angle_rad)
            elif m.topic == MODE.name:
                r = mode_from_msg(m.message)
                modes.append((r.stamp_ns, r.mode, r.reason))
                continue
            elif m.topic == FOREIGN.name:
                _note_foreign(foreign, m.message)
                continue
            else:
                continue
        except MessageError as exc:
            raise BagError(f"{where}{m.topic}: {exc}") from None
        rows[m.topic].append((s.stamp_ns, NO_TIME if m.publish_time_ns is None
                              else m.publish_time_ns, values))
    tables = {}
    for topic, (name, _, k) in TABLE_TOPICS.items():
        r = rows[topic]
        tables[name] = Table(np.array([x[0] for x in r], dtype=np.int64),
                             np.array([x[1] for x in r], dtype=np.int64),
                             np.array([x[2] for x in r], dtype=np.float64).reshape(len(r), k))
    return RunTables(**tables, modes=modes, foreign=foreign)


def _note_foreign(foreign: list[str], message: Any) -> None:
    """A recorder's mark (:data:`pisc_msgs_py.topics.FOREIGN`): its ERROR statuses'
    ``TOPIC: publishers``, once each."""
    for status in message.status:
        values = {kv.key: kv.value for kv in status.values}
        level = status.level[0] if isinstance(status.level, bytes) else int(status.level)
        if level == 2 and "topic" in values:
            topic, who = values["topic"], values.get("publishers", "unknown")
            entry = f"{topic}: {who}"
            unnamed = f"{topic}: a publisher the ROS graph does not name yet"
            if unnamed in foreign:  # named now
                foreign.remove(unnamed)
            if entry not in foreign and not (entry == unnamed and any(
                    f.startswith(f"{topic}: ") for f in foreign)):
                foreign.append(entry)


def foreign_in_bag(directory: str | Path) -> list[str]:
    """``TOPIC: publishers`` for each foreign publisher the bag's recorder marked
    (:data:`pisc_msgs_py.topics.FOREIGN`); empty for a bag without marks."""
    foreign: list[str] = []
    for m in read_bag(directory, [FOREIGN.name]):
        _note_foreign(foreign, m.message)
    return foreign


def tables_of_bag(directory: str | Path) -> RunTables:
    """The tables of a bag, read as columns (:mod:`pisc_bag.bag_columns`) where it
    can be done without guessing, else message by message (:func:`tables_of`, whose
    errors name the bag and the message); :class:`BagError` says what is wrong."""
    from pisc_bag.bag_columns import FastPathRefused, read_columns

    try:
        columns, others = read_columns(directory, list(TABLE_TOPICS), [MODE.name, FOREIGN.name])
    except FastPathRefused:
        return tables_of(read_bag(directory, [*TABLE_TOPICS, MODE.name, FOREIGN.name]),
                         f"{directory}: ")
    tables = {}
    for topic, (name, field_name, k) in TABLE_TOPICS.items():
        c = columns[topic]
        expected = {"joints": JOINT_NAMES, "state": JOINT_NAMES, "true": (*JOINT_NAMES, MOTOR_JOINT)
                    }.get(name, (MOTOR_JOINT,))
        # every field the message path's converter reads (and checks)
        needed = {"state": ("position", "velocity"), "true": ("position", "velocity", "effort")
                  }.get(name, (field_name,))
        if len(c) and (c.names != expected or any(f not in c.values for f in needed)):
            return tables_of(read_bag(directory, [*TABLE_TOPICS, MODE.name, FOREIGN.name]),
                             f"{directory}: ")
        values = (c.values[field_name][:, :k] if len(c) else np.zeros((0, k)))
        tables[name] = Table(c.stamp_ns, c.publish_ns, np.ascontiguousarray(values))
    modes = []
    foreign: list[str] = []
    for topic, _, _, msg in others:
        if topic == FOREIGN.name:
            _note_foreign(foreign, msg)
            continue
        try:
            r = mode_from_msg(msg)
        except MessageError as exc:
            raise BagError(f"{directory}: {topic}: {exc}") from None
        modes.append((r.stamp_ns, r.mode, r.reason))
    return RunTables(**tables, modes=modes, foreign=foreign)


def summarise(
    messages: Iterable[BagMessage], period_s: float, criteria: Criteria = Criteria(),
    safe_range_m: tuple[float, float] | None = None, tier: str = VERDICT_TIER,
) -> RunSummary:
    """The summary of a run's decoded messages (:func:`summarise_tables`)."""
    return summarise_tables(tables_of(messages), period_s, criteria, safe_range_m, tier)


def _at(unique: np.ndarray, index: np.ndarray, stamps: np.ndarray) -> np.ndarray:
    """Rows of ``table`` for ``stamps`` (each one of ``unique``)."""
    return index[np.searchsorted(unique, stamps)]


def safe_range_of(bag: str | Path | None) -> tuple[float, float]:
    """The safe range of a run: its bag's parameter file (``safety.*``), else the
    controllers' defaults."""
    from pisc_bag.run_files import recorded_section
    from pisc_control.supervisor import SafetyParams

    safety = SafetyParams() if bag is None else recorded_section(bag, SafetyParams, "safety")
    return safety.x_min_m, safety.x_max_m


def summarise_tables(tables: RunTables, period_s: float, criteria: Criteria = Criteria(),
                     safe_range_m: tuple[float, float] | None = None,
                     tier: str = VERDICT_TIER) -> RunSummary:
    """The summary of a run's tables, judged by ``criteria``'s tiers with the safe range
    ``safe_range_m`` (default: the controllers' default safety limits)."""
    if tier not in TIERS:
        raise ValueError(f"tier {tier!r}: one of {', '.join(TIERS)}")
    if safe_range_m is None:
        safe_range_m = safe_range_of(None)
    # the last message of each stamp counts
    j_stamps, j_index = tables.joints.pick("last")
    v_stamps, v_index = tables.voltage.pick("last")
    # A cycle is complete when its voltage was recorded.
    stamps = np.intersect1d(j_stamps, v_stamps)
    if not len(stamps):
        raise BagError("no complete control cycle (joint_states with its voltage) in the bag")
    t0 = int(stamps[0])
    t = (stamps - t0) * 1e-9
    t_stamps, t_index = tables.true.pick("last")
    source = "true" if np.all(member(stamps, t_stamps)) else "measured"
    if source == "true":
        rows = tables.true.values[_at(t_stamps, t_index, stamps)]
    else:
        rows = tables.joints.values[_at(j_stamps, j_index, stamps)]
    xs, thetas = rows[:, 0].copy(), rows[:, 1].copy()
    th_up = wrap_to_upright(thetas)

    modes = sorted(tables.modes, key=lambda r: r[0])
    catches = [s for s, mode, _ in modes if mode is Mode.CATCH]
    first_catch = (catches[0] - t0) * 1e-9 if catches else None
    caught_at = None
    if modes and modes[-1][1] is Mode.CATCH:
        caught_at = (modes[-1][0] - t0) * 1e-9
    changes = sum(1 for a, b in zip(modes, modes[1:], strict=False) if a[1] is not b[1])
    faults = [reason for _, mode, reason in modes if mode is Mode.FAULT]

    late = t >= criteria.fast_hold_from_s
    hold_theta = float(np.max(np.abs(th_up[late]))) if late.any() else math.inf
    hold_x = float(np.max(np.abs(xs[late]))) if late.any() else math.inf
    held = bool(late.any() and hold_theta < criteria.theta_rad and hold_x < criteria.x_m)
    outside = np.flatnonzero((np.abs(th_up) >= criteria.theta_rad) | (np.abs(xs) >= criteria.x_m))
    unheld_at = float(t[outside[-1]]) if len(outside) else -math.inf
    left = bool(np.any(xs < safe_range_m[0]) or np.any(xs > safe_range_m[1]))
    passed, why = _verdicts(criteria, bool(faults), left, caught_at, first_catch, unheld_at,
                            float(np.max(np.abs(xs))), float(t[-1]), bool(tables.foreign))

    s_stamps, s_index = tables.setpoint.pick("last")
    c_stamps, c_index = tables.current.pick("last")
    tracked = stamps[member(stamps, s_stamps) & member(stamps, c_stamps)]
    errors = (tables.setpoint.values[_at(s_stamps, s_index, tracked), 0]
              - tables.current.values[_at(c_stamps, c_index, tracked), 0])
    rms = float(np.sqrt(np.mean(errors**2))) if len(errors) else math.nan

    v_pub = tables.voltage.publish_ns[_at(v_stamps, v_index, stamps)]
    j_pub = tables.joints.publish_ns[_at(j_stamps, j_index, stamps)]
    timed = (v_pub != NO_TIME) & (j_pub != NO_TIME)
    latencies = (v_pub[timed] - j_pub[timed]) * 1e-6
    return RunSummary(
        duration_s=float(t[-1]),
        cycles=len(stamps),
        first_catch_s=first_catch,
        caught_at_s=caught_at,
        mode_changes=changes,
        faults=faults,
        final_theta_rad=float(th_up[-1]),
        final_x_m=float(xs[-1]),
        max_abs_x_m=float(np.max(np.abs(xs))),
        x_range_m=(float(xs.min()), float(xs.max())),
        hold_theta_rad=hold_theta,
        hold_x_m=hold_x,
        held=held,
        state_source=source,
        current_rms_error_a=rms,
        latency_ms=_percentiles(latencies),
        deadline_misses=int(np.sum(latencies > period_s * 1e3)),
        period_s=period_s,
        criteria=criteria,
        safe_range_m=(float(safe_range_m[0]), float(safe_range_m[1])),
        unheld_at_s=unheld_at,
        left_range=left,
        passed=passed,
        why=why,
        tier=tier,
        foreign=list(tables.foreign),
        negative_latencies=int(np.sum(latencies < 0.0)),
    )


def _verdicts(criteria: Criteria, faulted: bool, left: bool, caught_at: float | None,
              first_catch: float | None, unheld_at: float, largest_x: float,
              duration: float, foreign: bool = False
              ) -> tuple[dict[str, bool], dict[str, str]]:
    """Each tier's verdict and why it failed, by the benchmark's own rule and words
    (:func:`~pisc_runs.verdict.judge`, :meth:`Outcomes.why`). A run with a foreign
    publisher on the graph's topics passes no tier: what moved the rig may not have been
    the graph."""
    inf = math.inf
    one = Outcomes(*(np.array([v]) for v in (
        False, False, False, inf if caught_at is None else caught_at,
        inf if first_catch is None else first_catch, largest_x, unheld_at, 0.0, 0.0, 0.0,
        faulted, left)))
    safe, caught, fast = judge(criteria, one.faulted, one.left_range, one.caught_at_s,
                               one.unheld_at_s)
    one = replace(one, safe=safe, caught=caught, fast=fast)
    passed, why = {}, {}
    for name in TIERS:
        ok = bool(one.passed(name)[0])
        reason = one.why(0, criteria, name)
        if ok and name != "safe" and duration <= criteria.rule(name)[1]:
            # a hold window the run never reached is not a hold
            ok, reason = False, (f"the run ended at {duration:.2f} s, before the hold "
                                 f"window from {criteria.rule(name)[1]:g} s")
        if foreign:
            ok, reason = False, "a foreign publisher on the graph's topics"
        passed[name], why[name] = ok, reason
    return passed, why


def summarise_bag(directory: str | Path, period_s: float, criteria: Criteria = Criteria(),
                  safe_range_m: tuple[float, float] | None = None,
                  tier: str = VERDICT_TIER) -> RunSummary:
    """The summary of a bag, read as columns where it can be (:func:`tables_of_bag`); the
    safe range, unless given, is the bag's parameter file's (:func:`safe_range_of`)."""
    if safe_range_m is None:
        safe_range_m = safe_range_of(directory)
    return summarise_tables(tables_of_bag(directory), period_s, criteria, safe_range_m, tier)
