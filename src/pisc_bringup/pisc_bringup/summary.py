"""What a run did, read back from its bag: catch time, final state, tracking, latency.

Everything is computed from the recorded messages, keyed by the header stamp of the
cycle, so it works the same for a simulated run and for the rig. Run time ``t`` is the
stamp minus the first sample's stamp.

Latency of a cycle is the time from the plant (or driver) sending sample k to the
current loop sending the voltage stamped k, from the DDS source timestamps the bag
keeps as ``publish_time``: it is measured in wall-clock time in both lockstep and
real-time runs. A cycle whose latency exceeds the period missed its deadline.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pisc_bringup.bag import BagError, BagMessage, read_bag
from pisc_msgs_py.convert import (
    joint_sample_from_msg,
    mode_from_msg,
    motor_sample_from_msg,
    true_state_from_msg,
)
from pisc_msgs_py.topics import (
    CURRENT_SETPOINT,
    JOINT_STATES,
    MODE,
    MOTOR_CURRENT,
    SIM_STATE,
    VOLTAGE,
)
from pisc_msgs_py.types import Mode
from pisc_model.dynamics import wrap_to_upright

__all__ = ["HoldCriteria", "RunSummary", "summarise", "summarise_bag"]


@dataclass(frozen=True)
class HoldCriteria:
    """Balance requirement: from ``start_s`` on, |theta| and |x| stay below the limits."""

    start_s: float = 6.0
    theta_rad: float = 0.05
    x_m: float = 0.02


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
    hold_theta_rad: float  # largest |theta| from hold.start_s on
    hold_x_m: float
    held: bool
    state_source: str  # 'true' (simulator) or 'measured'
    current_rms_error_a: float
    latency_ms: dict[str, float] = field(default_factory=dict)
    deadline_misses: int = 0
    period_s: float = 0.005

    @property
    def caught(self) -> bool:
        return self.caught_at_s is not None and self.held

    def format(self) -> str:
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
            f"balance from 6 s       |theta| <= {self.hold_theta_rad:.4f} rad, |x| <= "
            f"{self.hold_x_m:.4f} m: {'held' if self.held else 'NOT held'}",
            f"current tracking RMS   {self.current_rms_error_a:.4f} A (i_d - i, same cycle)",
        ]
        if lat:
            lines.append(
                f"sample-to-voltage      median {lat['median']:.3f} ms, p90 {lat['p90']:.3f} ms, "
                f"p99 {lat['p99']:.3f} ms, max {lat['max']:.3f} ms; "
                f"{self.deadline_misses} cycles over the {self.period_s * 1e3:.0f} ms period")
        for fault in self.faults:
            lines.append(f"FAULT                  {fault}")
        lines.append("result                 " + ("CAUGHT" if self.caught else "NOT CAUGHT"))
        return "\n".join(lines)


def _percentiles(values: np.ndarray) -> dict[str, float]:
    if len(values) == 0:
        return {}
    return {
        "median": float(np.median(values)),
        "p90": float(np.percentile(values, 90)),
        "p99": float(np.percentile(values, 99)),
        "max": float(np.max(values)),
    }


def summarise(
    messages: Iterable[BagMessage], period_s: float, hold: HoldCriteria = HoldCriteria()
) -> RunSummary:
    joints: dict[int, tuple[float, float, int | None]] = {}
    true: dict[int, tuple[float, float]] = {}
    current: dict[int, float] = {}
    setpoint: dict[int, float] = {}
    voltage_pub: dict[int, int | None] = {}
    modes: list[tuple[int, Mode, str]] = []
    for m in messages:
        if m.topic == JOINT_STATES.name:
            s = joint_sample_from_msg(m.message)
            joints[s.stamp_ns] = (s.position_m, s.angle_rad, m.publish_time_ns)
        elif m.topic == SIM_STATE.name:
            s = true_state_from_msg(m.message)
            true[s.stamp_ns] = (s.position_m, s.angle_rad)
        elif m.topic == MOTOR_CURRENT.name:
            s = motor_sample_from_msg(m.message)
            current[s.stamp_ns] = s.value
        elif m.topic == CURRENT_SETPOINT.name:
            s = motor_sample_from_msg(m.message)
            setpoint[s.stamp_ns] = s.value
        elif m.topic == VOLTAGE.name:
            s = motor_sample_from_msg(m.message)
            voltage_pub[s.stamp_ns] = m.publish_time_ns
        elif m.topic == MODE.name:
            r = mode_from_msg(m.message)
            modes.append((r.stamp_ns, r.mode, r.reason))
    # A cycle is complete when its voltage was recorded.
    stamps = sorted(s for s in joints if s in voltage_pub)
    if not stamps:
        raise BagError("no complete control cycle (joint_states with its voltage) in the bag")
    t0 = stamps[0]
    t = (np.array(stamps) - t0) * 1e-9
    source = "true" if all(s in true for s in stamps) else "measured"
    xs = np.array([(true if source == "true" else joints)[s][0] for s in stamps])
    thetas = np.array([(true if source == "true" else joints)[s][1] for s in stamps])
    th_up = wrap_to_upright(thetas)

    modes.sort(key=lambda r: r[0])
    catches = [s for s, mode, _ in modes if mode is Mode.CATCH]
    first_catch = (catches[0] - t0) * 1e-9 if catches else None
    caught_at = None
    if modes and modes[-1][1] is Mode.CATCH:
        caught_at = (modes[-1][0] - t0) * 1e-9
    changes = sum(1 for a, b in zip(modes, modes[1:], strict=False) if a[1] is not b[1])
    faults = [reason for _, mode, reason in modes if mode is Mode.FAULT]

    late = t >= hold.start_s
    hold_theta = float(np.max(np.abs(th_up[late]))) if late.any() else math.inf
    hold_x = float(np.max(np.abs(xs[late]))) if late.any() else math.inf
    held = bool(late.any() and hold_theta < hold.theta_rad and hold_x < hold.x_m)

    tracked = [s for s in stamps if s in setpoint and s in current]
    errors = np.array([setpoint[s] - current[s] for s in tracked])
    rms = float(np.sqrt(np.mean(errors**2))) if len(errors) else math.nan

    latencies = np.array([
        (voltage_pub[s] - joints[s][2]) * 1e-6 for s in stamps
        if voltage_pub[s] is not None and joints[s][2] is not None
    ])
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
    )


def summarise_bag(directory: str | Path, period_s: float,
                  hold: HoldCriteria = HoldCriteria()) -> RunSummary:
    return summarise(read_bag(directory), period_s, hold)
