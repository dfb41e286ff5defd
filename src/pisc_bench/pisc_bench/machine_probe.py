"""The machine's own timer latency: the anchor of a soak's cycles over the period.

    python -m pisc_bench.machine_probe_cli --cpu N [--priority P] [--period 0.005] --out FILE

A bare loop that sleeps to absolute deadlines one period apart and keeps how late it
woke at each (like cyclictest(8) of rt-tests, in Python: ``time.sleep`` is
``clock_nanosleep`` on CLOCK_MONOTONIC here, and nothing else runs in the loop), pinned
to one CPU, at ``SCHED_FIFO`` priority ``P`` (0: normal scheduling). It says ``ready``
on standard output, runs until SIGTERM or SIGINT (or ``--max-duration``) and writes
``FILE`` (numpy ``.npz``: ``lateness_ns`` per deadline, ``start_unix_ns``, ``period_ns``,
``cpu``, ``priority``).

A deadline missed while the loop was stalled is counted late like any other (a 12 ms
stall at a 5 ms period makes wake-ups 12, 7 and 2 ms late), as a graph's cycles are
when their process stalls. ``pisc_soak`` runs one per CPU beside the graph
(:class:`Probes`) and prints :func:`probe_figures`: when a loop that does nothing wakes
over a period late, no node at that scheduling could have kept its cycle either.
docs/soak.md has what cyclictest itself measured beside it.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["ProbeRun", "Probes", "load", "near_share", "probe_figures", "run_loop"]


def run_loop(period_ns: int, count: int, stop: list) -> tuple[int, np.ndarray]:
    """Sleep to ``count`` deadlines ``period_ns`` apart, or until ``stop`` is not empty.

    Returns (the first deadline's Unix time [ns], lateness of each deadline reached [ns]).
    """
    lateness = np.full(count, -1, dtype=np.int64)  # written now: no page fault in the loop
    start = time.monotonic_ns()
    start_unix_ns = time.time_ns() + period_ns
    deadline = start
    i = 0
    while i < count and not stop:
        deadline += period_ns
        wait = deadline - time.monotonic_ns()
        if wait > 0:
            time.sleep(wait * 1e-9)
        lateness[i] = time.monotonic_ns() - deadline
        i += 1
    return start_unix_ns, lateness[:i]


@dataclass(frozen=True)
class ProbeRun:
    """One loop's result: its CPU, priority, period and each deadline's lateness."""

    cpu: int
    priority: int
    period_ns: int
    start_unix_ns: int
    lateness_ns: np.ndarray

    def deadlines_unix_s(self) -> np.ndarray:
        return (self.start_unix_ns + self.period_ns * np.arange(self.lateness_ns.size)) * 1e-9


def load(path: Path) -> ProbeRun:
    """A probe's file, or ValueError naming what is wrong with it."""
    try:
        with np.load(path) as data:
            return ProbeRun(int(data["cpu"]), int(data["priority"]), int(data["period_ns"]),
                            int(data["start_unix_ns"]), data["lateness_ns"].astype(np.int64))
    except (OSError, KeyError, ValueError) as exc:
        raise ValueError(f"machine probe {path}: {exc}") from exc


def near_share(intervals: Sequence[tuple[float, float]], lo: float, hi: float,
               times: Sequence[float]) -> tuple[float, int, int]:
    """How much of [lo, hi] the ``intervals`` (sorted by start) cover, as a share; how
    many of ``times`` fall in [lo, hi]; and how many of those fall in an interval."""
    covered, reach = 0.0, lo  # the union of the intervals, clipped to the window
    for a, b in intervals:
        a, b = max(a, reach), min(b, hi)
        if b > a:
            covered += b - a
            reach = b
    inside = [t for t in times if lo <= t <= hi]
    near = sum(any(a <= t <= b for a, b in intervals) for t in inside)
    return (covered / (hi - lo) if hi > lo else math.nan), len(inside), near


def probe_figures(runs: Sequence[ProbeRun], start_s: float, end_s: float,
                  overs_unix_s: Sequence[float], stall_ms: float = 1.0,
                  near_s: float = 0.1) -> dict[str, float | int | list]:
    """The probes over [start_s, end_s] (Unix seconds): per CPU and in all, wake-ups,
    p99 and max lateness [ms] and wake-ups later than a period; and how many of the
    run's cycles over the period (``overs_unix_s``) fell within ``near_s`` of a wake-up
    later than ``stall_ms`` on any CPU, beside the share of the window so near (what
    chance alone would give). ValueError when no wake-up falls in the window."""
    per_cpu, stalls, all_late = [], [], []
    for run in runs:
        times = run.deadlines_unix_s()
        keep = (times >= start_s) & (times <= end_s)
        late_ms = run.lateness_ns[keep] * 1e-6
        if late_ms.size == 0:
            continue
        period_ms = run.period_ns * 1e-6
        per_cpu.append({"cpu": run.cpu, "wakeups": int(late_ms.size),
                        "p99_ms": float(np.percentile(late_ms, 99)),
                        "max_ms": float(late_ms.max()),
                        "over_period": int(np.sum(late_ms > period_ms))})
        stalls.extend(times[keep][late_ms > stall_ms])
        all_late.append(late_ms)
    if not per_cpu:
        raise ValueError(f"no probe wake-up between {start_s:.1f} and {end_s:.1f}")
    late = np.concatenate(all_late)
    intervals = sorted((t - near_s, t + near_s) for t in stalls)
    share, overs, near = near_share(intervals, start_s, end_s, overs_unix_s)
    return {"cpus": per_cpu, "wakeups": int(late.size),
            "p99_ms": float(np.percentile(late, 99)), "max_ms": float(late.max()),
            "over_period": sum(c["over_period"] for c in per_cpu),
            "stall_ms": stall_ms, "stalls": len(stalls), "near_s": near_s,
            "near_share": share, "overs": overs, "overs_near": near}


class Probes:
    """One probe process per CPU this process may run on, started at once; :meth:`stop`
    ends them and reads their files, or raises ValueError naming a probe that failed
    with its output."""

    def __init__(self, out_dir: Path, priority: int, period_s: float,
                 max_duration_s: float) -> None:
        self.files: list[Path] = []
        self.processes: list[subprocess.Popen] = []
        try:
            for cpu in sorted(os.sched_getaffinity(0)):
                path = out_dir / f"probe-cpu{cpu}.npz"
                process = subprocess.Popen(
                    [sys.executable, "-m", "pisc_bench.machine_probe_cli", "--cpu", str(cpu),
                     "--priority", str(priority), "--period", repr(period_s),
                     "--max-duration", repr(max_duration_s), "--out", str(path)],
                    stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
                self.files.append(path)
                self.processes.append(process)
                if process.stdout.readline().strip() != "ready":
                    process.wait(timeout=30)
                    raise RuntimeError(f"the machine probe on CPU {cpu} did not start: "
                                       f"{process.stderr.read().strip()}")
        except BaseException:
            self._end()
            raise

    def stop(self) -> list[ProbeRun]:
        self._end()
        for path, process in zip(self.files, self.processes):
            if process.returncode != 0:
                raise ValueError(f"machine probe {path.name} exited with status "
                                 f"{process.returncode}: {process.stderr.read().strip()}")
        return [load(path) for path in self.files]

    def _end(self) -> None:
        for process in self.processes:
            if process.poll() is None:
                process.send_signal(signal.SIGTERM)
        for process in self.processes:
            try:
                process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
