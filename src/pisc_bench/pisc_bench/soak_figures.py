"""The soak's figures and its targets: per-cycle latency, the cycles a run's span holds,
a process's CPU and memory over a window, what an outside observer saw against the bag,
and which targets a report misses (:func:`missed_targets`).

Pure: numbers in, numbers out; the run itself is :mod:`pisc_bench.soak_run`.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["MB", "PERIOD_S", "START_AFTER_S", "Sample", "Targets", "expected_cycles",
           "latency_figures", "missed_targets", "observer_check", "usage_over"]

PERIOD_S = 0.005  # loop.period_s of every shipped configuration (SPEC: 5 ms)
START_AFTER_S = 10.0  # the memory and CPU window starts this long after the first cycle
MB = 1_000_000


def latency_figures(latencies_ms: Sequence[float], period_s: float = PERIOD_S
                    ) -> dict[str, float]:
    """Median, p99, p99.9 and max of per-cycle latencies [ms], and cycles over the period.

    Percentiles are numpy's linear interpolation, as :mod:`pisc_runs.summary` takes
    them; a cycle is over when its latency exceeds the period (summary's deadline miss).
    """
    values = np.asarray(latencies_ms, dtype=float)
    if values.size == 0:
        raise ValueError("no latency: no complete cycle with both publish times")
    return {"median_ms": float(np.median(values)),
            "p99_ms": float(np.percentile(values, 99)),
            "p999_ms": float(np.percentile(values, 99.9)),
            "max_ms": float(np.max(values)),
            "over_period": int(np.sum(values > period_s * 1e3)),
            "cycles": int(values.size)}


def expected_cycles(stamps_ns: Sequence[int], period_s: float = PERIOD_S,
                    window: int = 200) -> int:
    """Cycles the run's span holds: its frame periods + 1, from the samples' stamps.

    With the simulated plant a stamp is the sample's time on the period grid and this is
    ``(last - first) / period + 1``. Through the driver a stamp is the frame's arrival
    (``DriverCore.receive``): its time on the device's grid plus a lateness >= 0 (the
    reader was busy; frames one read completes are stamped 1 us apart), so the plain span
    is short by a period when the first sample arrived more than half a period later than
    the last (a 20 s run counted 4003 cycles against 4002 "expected"). Here:

    * the start is ``min(s_j - j T)`` over the first ``window`` samples: sample ``j`` was
      sent at least ``j`` periods after the first, and arrived no earlier than it was
      sent, so each term bounds the first sample's on-time stamp from above, and the
      least one is it (a late or lost sample only raises its term);
    * the end is the last stamp less its lateness relative to the last ``window``
      samples: the median of ``s_last - s_j - (n - 1 - j) T`` wrapped into
      [-T/2, T/2) (frames lost or periods the plant skipped are whole periods and drop
      out; the last sample of a burst is its newest frame, late by less than a period);
    * never fewer than the samples: each sample is a frame of its own period.

    The median assumes most of the last ``window`` samples arrived on time (true of
    every run measured: median latency < 1 ms).
    """
    s = np.sort(np.asarray(stamps_ns, dtype=np.int64))
    n = s.size
    if n == 0:
        raise ValueError("no samples: no span to count")
    period_ns = round(period_s * 1e9)
    head = np.arange(min(window, n))
    start = int(np.min(s[head] - head * period_ns))
    tail = np.arange(max(0, n - window), n)
    lateness = s[-1] - s[tail] - (n - 1 - tail) * period_ns
    wrapped = (lateness + period_ns // 2) % period_ns - period_ns // 2
    end = int(s[-1] - np.median(wrapped))
    return max(n, round((end - start) / period_ns) + 1)



def observer_check(observed: dict[str, Sequence[int]], in_bag: dict[str, Sequence[int]]
                   ) -> dict[str, dict[str, int]]:
    """Per topic of ``in_bag``: messages the observer received, messages in the bag, and
    those received but not in the bag, by header stamp, counting repeats (a stamp the
    observer received twice must be in the bag twice)."""
    out = {}
    for topic, stamps in in_bag.items():
        seen = observed.get(topic, [])
        missing = Counter(seen) - Counter(stamps)
        out[topic] = {"observed": len(seen), "in_bag": len(stamps),
                      "missing_from_bag": sum(missing.values())}
    return out


@dataclass(frozen=True)
class Sample:
    """One look at a process: Unix time, CPU seconds (user + system), resident bytes."""

    unix_s: float
    cpu_s: float
    rss_bytes: int


def usage_over(samples: Sequence[Sample], start_s: float, end_s: float) -> dict[str, float]:
    """A process's CPU and memory over [start_s, end_s] (Unix seconds), from its samples:
    the first sample at or after ``start_s`` and the last at or before ``end_s``.

    Returns cpu_s, cpu_percent (of one core), rss_start_mb, rss_end_mb, growth_mb,
    window_s; ValueError when fewer than two samples fall in the window.
    """
    inside = [s for s in samples if start_s <= s.unix_s <= end_s]
    if len(inside) < 2:
        raise ValueError(f"{len(inside)} sample(s) between {start_s:.1f} and {end_s:.1f}: "
                         "the process was not seen over the window")
    a, b = inside[0], inside[-1]
    window = b.unix_s - a.unix_s
    cpu = b.cpu_s - a.cpu_s
    return {"cpu_s": cpu, "cpu_percent": 100.0 * cpu / window if window > 0 else math.nan,
            "rss_start_mb": a.rss_bytes / MB, "rss_end_mb": b.rss_bytes / MB,
            "growth_mb": (b.rss_bytes - a.rss_bytes) / MB, "window_s": window}



#: Sample-to-voltage p99 [ms] in one process: 99 % of the cycles answer their sample within
#: a fifth of the 5 ms period
P99_MS = 1.0
#: ... through the serial driver, whose own process, pseudo-terminal and the rig's read
#: lie on every cycle's way
P99_DRIVER_MS = 2.0
#: Cycles whose latency exceeds the period: each such voltage reached the rig a period late
OVER_PERIOD = 0
#: CPU of the four nodes (the graph's process, and the driver's) [% of one core]: what the
#: loop may take of the rig computer, beside the recorder and everything else it runs
NODES_CPU_PERCENT = 15.0
#: Resident memory growth of each process of the run over the window [MB]: what a run of
#: minutes may gain without leaking
GROWTH_MB = 2.0


@dataclass(frozen=True)
class Targets:
    """What a soak must meet: sample-to-voltage p99 (:data:`P99_MS`, or
    :data:`P99_DRIVER_MS` through the driver), no cycle over the period
    (:data:`OVER_PERIOD`; under ``--load``, no more than the bare timer's), the four nodes'
    CPU (:data:`NODES_CPU_PERCENT`) and each process's memory growth (:data:`GROWTH_MB`)."""

    p99_ms: float = P99_MS
    over_period: int = OVER_PERIOD
    nodes_cpu_percent: float = NODES_CPU_PERCENT
    growth_mb: float = GROWTH_MB

    @staticmethod
    def for_run(driver: bool) -> Targets:
        return Targets(p99_ms=P99_DRIVER_MS) if driver else Targets()


def missed_targets(report: dict[str, Any], targets: Targets) -> list[str]:
    """Each target the report misses, said with its figure and the target."""
    missed = []
    lat = report["latency"]
    if lat["p99_ms"] > targets.p99_ms:
        missed.append(f"sample-to-voltage p99 {lat['p99_ms']:.3f} ms > {targets.p99_ms} ms")
    machine = report.get("machine", {})
    over_target = targets.over_period
    if report.get("load"):  # a loaded machine: no more late cycles than its bare timer's
        over_target = machine.get("over_period", targets.over_period)
    if lat["over_period"] > over_target:
        near = ("" if "overs_near" not in machine else
                f"; {machine['overs_near']} within {machine['near_s']:g} s of the bare "
                "timer's stalls")
        bare = " (the bare timer's wake-ups over it)" if report.get("load") else ""
        missed.append(f"{lat['over_period']} cycles over the {report['period_s'] * 1e3:g} ms "
                      f"period (target {over_target}{bare}{near})")
    cycles = report["cycles"]
    if not report["faults"] and cycles["completed"] < cycles["expected"]:
        missed.append(f"{cycles['completed']} cycles completed of {cycles['expected']} "
                      "expected")
    nodes = report["nodes_cpu_percent"]
    if nodes is None or nodes > targets.nodes_cpu_percent:
        shown = "not measured" if nodes is None else f"{nodes:.1f} %"
        missed.append(f"the four nodes' CPU {shown} of one core > "
                      f"{targets.nodes_cpu_percent:g} %")
    for name, usage in report["processes"].items():
        if "error" in usage:
            missed.append(f"{name}: {usage['error']}")
        elif usage["growth_mb"] > targets.growth_mb:
            missed.append(f"{name}: resident memory grew {usage['growth_mb']:.2f} MB > "
                          f"{targets.growth_mb:g} MB")
    if not report["held"]:
        missed.append("the pendulum was not held" + (
            " (outside the silences and their recoveries)" if report["faults"] else ""))
    if report["faults"]:
        lost = [r for r in report["recoveries"] if r["recovery_s"] is None]
        if lost:
            missed.append(f"{len(lost)} of {len(report['recoveries'])} silences not "
                          "recovered (" + ", ".join(f"{r['requested_s']:.1f} s"
                                                    for r in lost) + ")")
        for topic, seen in report["observer"].items():
            if seen["missing_from_bag"]:
                missed.append(f"{topic}: {seen['missing_from_bag']} messages the observer "
                              "received are not in the bag")
            if seen["observed"] == 0:
                missed.append(f"{topic}: the observer received nothing")
    return missed
