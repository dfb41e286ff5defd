"""The soak's report: from the bag (one pass: the run summary and what it does not keep)
and the run's samples (:func:`analyse`), printed by :func:`format_report`."""

from __future__ import annotations

import math
import sys
from collections.abc import Callable, Iterable, Iterator
from dataclasses import asdict
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from pisc_bench.machine_probe import probe_figures
from pisc_bench.soak_faults import HELD_FROM_S, RECOVERY_BAND_RAD, Recovery, recoveries
from pisc_bench.soak_figures import (
    PERIOD_S,
    START_AFTER_S,
    expected_cycles,
    latency_figures,
    observer_check,
    usage_over,
)
from pisc_bench.soak_options import SoakOptions
from pisc_bench.soak_proc import steal_figures
from pisc_bench.soak_run import RunRecord

__all__ = ["analyse", "format_report"]


def _tee(messages: Iterable[Any], keep: Callable[[Any], None]) -> Iterator[Any]:
    for m in messages:
        keep(m)
        yield m


def analyse(options: SoakOptions, out: Path, record: RunRecord) -> dict[str, Any]:
    """The report, from the bag (one pass: the run summary and what it does not keep)
    and the samples."""
    from pisc_bag.bag import read_bag
    from pisc_runs.summary import summarise
    from pisc_msgs_py.convert import joint_sample_from_msg, stamp_from_msg
    from pisc_msgs_py.topics import (
        CURRENT_SETPOINT, DIAGNOSTICS, JOINT_STATES, MODE, MOTOR_CURRENT, SIM_STATE,
        VOLTAGE)
    from pisc_model.dynamics import wrap_to_upright

    bag = out / "bag"
    joints: dict[int, tuple[int | None, float, float]] = {}
    voltages: dict[int, int | None] = {}
    joint_stamps: list[int] = []
    current: list[int] = []
    driver_diagnostics: list[int] = []

    def keep(m: Any) -> None:
        if m.topic == JOINT_STATES.name:
            s = joint_sample_from_msg(m.message)
            joint_stamps.append(s.stamp_ns)
            joints[s.stamp_ns] = (m.publish_time_ns, s.position_m, s.angle_rad)
        elif m.topic == VOLTAGE.name:
            voltages[stamp_from_msg(m.message.header.stamp)] = m.publish_time_ns
        elif m.topic == MOTOR_CURRENT.name:
            current.append(stamp_from_msg(m.message.header.stamp))
        elif m.topic == DIAGNOSTICS.name and any(
                s.name == "pisc/driver" for s in m.message.status):
            driver_diagnostics.append(stamp_from_msg(m.message.header.stamp))

    topics = [JOINT_STATES.name, MOTOR_CURRENT.name, SIM_STATE.name, CURRENT_SETPOINT.name,
              VOLTAGE.name, MODE.name] + ([DIAGNOSTICS.name] if options.faults else [])
    summary = summarise(_tee(read_bag(bag, topics), keep), PERIOD_S)
    # per cycle, the summary's own rule: the voltage's publish time minus its sample's
    stamps = sorted(s for s in joints if s in voltages)
    # (the sample's publish time [ns], the cycle's latency [ms])
    cycles_ms = [(joints[s][0], (voltages[s] - joints[s][0]) * 1e-6) for s in stamps
                 if voltages[s] is not None and joints[s][0] is not None]
    figures = latency_figures([latency for _, latency in cycles_ms], PERIOD_S)
    for key in ("median", "p99", "max"):  # the same cycles and rule as the summary's
        if not math.isclose(figures[f"{key}_ms"], summary.latency_ms[key], abs_tol=1e-9):
            raise RuntimeError(f"latency {key}: {figures[key + '_ms']} here, "
                               f"{summary.latency_ms[key]} in the run summary")
    first, last = stamps[0], stamps[-1]
    inside_stamps = [s for s in joints if first <= s <= last]
    expected = expected_cycles(inside_stamps, PERIOD_S)
    inside = len(inside_stamps)
    t0 = first * 1e-9
    report: dict[str, Any] = {
        "date": datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "command": "pisc_soak " + " ".join(sys.argv[1:]) if sys.argv else "pisc_soak",
        "duration_s": options.duration_s, "driver": options.driver,
        "faults": options.faults, "realtime": options.realtime, "seed": options.seed,
        "load": options.load, "bag": str(bag), "period_s": PERIOD_S, "graph_status": record.graph_status,
        "latency": figures,
        "cycles": {"completed": summary.cycles, "expected": expected,
                   "nominal": round(options.duration_s / PERIOD_S) + 1,
                   "samples_in_span": inside, "unanswered": inside - summary.cycles},
        "caught_at_s": summary.caught_at_s, "summary_held": summary.held,
        "hold_theta_rad": summary.hold_theta_rad, "hold_x_m": summary.hold_x_m,
        "state_source": summary.state_source, "faults_seen": summary.faults,
    }
    # CPU and memory over the window: 10 s after the first cycle to the last
    start, end = t0 + START_AFTER_S, last * 1e-9
    processes: dict[str, dict[str, float | str]] = {}
    for name, samples in record.monitor.samples.items():
        try:
            processes[name] = usage_over(samples, start, end)
        except ValueError as exc:
            processes[name] = {"error": str(exc)}
    report["processes"] = processes
    # the cycles over the period beside the hypervisor's steal: a virtual CPU that does
    # not run stalls every process on it, whatever their scheduling (docs/soak.md)
    over_s = [sample_ns * 1e-9 for sample_ns, latency in cycles_ms
              if latency > PERIOD_S * 1e3]  # latency_figures' rule
    try:
        report["steal"] = steal_figures(record.monitor.steal, t0, end, over_s)
    except ValueError as exc:
        report["steal"] = {"error": str(exc)}
    try:
        if isinstance(record.probes, str):
            raise ValueError(record.probes)
        report["machine"] = probe_figures(record.probes, t0, end, over_s)
    except ValueError as exc:
        report["machine"] = {"error": str(exc)}
    nodes = [n for n in ("graph", "driver") if n in processes]
    report["nodes_processes"] = nodes
    report["nodes_cpu_percent"] = (
        None if any("error" in processes[n] for n in nodes) or (
            options.driver and "driver" not in processes)
        else sum(float(processes[n]["cpu_percent"]) for n in nodes))
    if record.observer_samples:
        try:
            report["observer_process"] = usage_over(record.observer_samples, start, end)
        except ValueError as exc:
            report["observer_process"] = {"error": str(exc)}
    if options.faults:
        # the run's span: the driver also publishes before the first answer and after
        # the controllers stopped
        run_samples = sorted(s for s in joints if first <= s <= last)
        t = np.array([(s - first) * 1e-9 for s in run_samples])
        theta = wrap_to_upright(np.array([joints[s][2] for s in run_samples]))
        x = np.array([joints[s][1] for s in run_samples])
        asked = [u - t0 for u, r in record.sent if "silence_s" in r]
        found = recoveries(t, theta, asked, end_s=(last - first) * 1e-9)
        report["recoveries"] = [asdict(r) for r in found]
        report["garbage_bursts"] = [(round(u - t0, 3), r["garbage"])
                                    for u, r in record.sent if "garbage" in r]
        excluded = np.zeros(t.shape, dtype=bool)
        for r in found:
            if r.ended_s is not None:
                until = r.ended_s + (r.recovery_s if r.recovery_s is not None else math.inf)
                excluded |= (t >= r.requested_s - 0.05) & (t <= until)
        judged = (t >= HELD_FROM_S) & ~excluded
        outside_theta = float(np.abs(theta[judged]).max(initial=0.0))
        report["held_outside_silences"] = {
            "theta_rad": outside_theta, "x_m": float(np.abs(x[judged]).max(initial=0.0)),
            "samples": int(judged.sum())}
        report["held"] = bool(judged.any() and outside_theta < RECOVERY_BAND_RAD
                              and not summary.faults and not any(r.lost for r in found))
        report["observer"] = observer_check(
            record.observed or {}, {JOINT_STATES.name: joint_stamps,
                                    MOTOR_CURRENT.name: current,
                                    DIAGNOSTICS.name: driver_diagnostics})
        report["rig"] = {k: record.rig_final.get(k) for k in (
            "frames", "dropped", "bytes_received", "watchdog_trips", "overruns",
            "refused_requests")}
    else:
        report["held"] = summary.held
    return report


def format_report(report: dict[str, Any]) -> str:
    lat, cycles = report["latency"], report["cycles"]
    through = "driver and virtual rig" if report["driver"] else "simulated plant"
    lines = [
        f"PISC soak: {report['duration_s']:g} s wall clock, {through}"
        + (", faults (seed " + str(report["seed"]) + ")" if report["faults"] else "")
        + (f", SCHED_FIFO {report['realtime']}" if report["realtime"] else "")
        + (f", under load ({report['load']} busy loops, one per CPU)"
           if report.get("load") else "")
        + f"; {report['date']}",
        f"bag                    {report['bag']}",
        f"sample-to-voltage      median {lat['median_ms']:.3f} ms, p99 {lat['p99_ms']:.3f} ms, "
        f"p99.9 {lat['p999_ms']:.3f} ms, max {lat['max_ms']:.3f} ms",
        f"cycles over 5 ms       {lat['over_period']} of {lat['cycles']}",
        f"cycles                 {cycles['completed']} completed of {cycles['expected']} "
        f"expected over the span ({cycles['nominal']} nominal); "
        f"{cycles['unanswered']} samples unanswered",
        f"CPU and memory         from {START_AFTER_S:g} s after the first cycle to the last:",
    ]
    for name, u in report["processes"].items():
        if "error" in u:
            lines.append(f"  {name:20s} {u['error']}")
            continue
        lines.append(f"  {name:20s} {u['cpu_s']:8.1f} CPU s {u['cpu_percent']:6.1f} % of a "
                     f"core; resident {u['rss_start_mb']:7.1f} -> {u['rss_end_mb']:7.1f} MB "
                     f"({u['growth_mb']:+.2f} MB)")
    if "observer_process" in report and "error" not in report["observer_process"]:
        u = report["observer_process"]
        lines.append(f"  {'(outside observer)':20s} {u['cpu_s']:8.1f} CPU s "
                     f"{u['cpu_percent']:6.1f} % of a core")
    steal = report.get("steal", {"error": "not measured"})
    if "error" in steal:
        lines.append(f"steal (hypervisor)     {steal['error']}")
    else:
        lines.append(f"steal (hypervisor)     {steal['steal_s']:.2f} s in "
                     f"{steal['intervals_with_steal']} seconds; {steal['overs_near']} of the "
                     f"{steal['overs']} cycles over 5 ms within {steal['near_s']:g} s of one "
                     f"({100 * steal['near_share']:.1f} % of the window is)")
    machine = report.get("machine", {"error": "not measured"})
    if "error" in machine:
        lines.append(f"machine (bare timer)   {machine['error']}")
    else:
        lines.append(f"machine (bare timer)   {len(machine['cpus'])} loops, one per CPU: p99 "
                     f"{machine['p99_ms']:.3f} ms, max {machine['max_ms']:.3f} ms late, "
                     f"{machine['over_period']} wake-ups over 5 ms of {machine['wakeups']}")
        lines.append(f"                       {machine['overs_near']} of the {machine['overs']} "
                     f"cycles over 5 ms within {machine['near_s']:g} s of a wake-up over "
                     f"{machine['stall_ms']:g} ms late ({machine['stalls']} such; "
                     f"{100 * machine['near_share']:.1f} % of the window is)")
    nodes = report["nodes_cpu_percent"]
    lines.append(f"four nodes             "
                 f"{'not measured' if nodes is None else f'{nodes:.1f} % of one core'} "
                 f"({' + '.join(report['nodes_processes'])})")
    caught = report["caught_at_s"]
    lines.append(f"caught                 {'never' if caught is None else f'{caught:.3f} s'}; "
                 f"from {HELD_FROM_S:g} s |theta| <= {report['hold_theta_rad']:.4f} rad, |x| <= "
                 f"{report['hold_x_m']:.4f} m ({report['state_source']} state)")
    if report["faults"]:
        for r in report["recoveries"]:
            lines.append("silence                " + Recovery(**r).format())
        lines.append(f"garbage bursts         {len(report['garbage_bursts'])} "
                     f"({sum(n for _, n in report['garbage_bursts'])} bytes)")
        rig = report["rig"]
        lines.append(f"rig                    {rig['frames']} frames, {rig['dropped']} bytes "
                     f"dropped, {rig['watchdog_trips']} watchdog trips, {rig['overruns']} "
                     "overruns")
        h = report["held_outside_silences"]
        lines.append(f"outside silences       |theta| <= {h['theta_rad']:.4f} rad, |x| <= "
                     f"{h['x_m']:.4f} m from {HELD_FROM_S:g} s")
        for topic, seen in report["observer"].items():
            lines.append(f"observer {topic:22s} {seen['observed']} received, "
                         f"{seen['in_bag']} in the bag, {seen['missing_from_bag']} missing "
                         "from the bag")
    for fault in report["faults_seen"]:
        lines.append(f"FAULT                  {fault}")
    lines.append(f"held                   {'yes' if report['held'] else 'NO'}")
    return "\n".join(lines)
