"""What the soak reads of the machine from ``/proc``: each process's CPU time and resident
memory, the hypervisor's steal time, a process's children; :class:`Monitor` samples the
run's processes once a second."""

from __future__ import annotations

import os
import time
from collections.abc import Sequence
from pathlib import Path

from pisc_bench.machine_probe import near_share
from pisc_bench.soak_figures import Sample

__all__ = ["Monitor", "children_of", "read_proc", "read_steal", "steal_figures"]

_TICK_S = 1.0 / os.sysconf("SC_CLK_TCK")


def read_proc(pid: int) -> tuple[float, int] | None:
    """(user + system CPU seconds, resident bytes) of a live process, from /proc; None
    once it has gone."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        status = Path(f"/proc/{pid}/status").read_text()
    except (FileNotFoundError, ProcessLookupError):
        return None
    fields = stat[stat.rindex(")") + 2:].split()  # after "pid (comm) "
    cpu = (int(fields[11]) + int(fields[12])) * _TICK_S  # utime, stime (fields 14, 15)
    rss = next((int(line.split()[1]) * 1024 for line in status.splitlines()
                if line.startswith("VmRSS:")), 0)
    return cpu, rss


def read_steal() -> float | None:
    """The machine's steal time so far, in seconds, summed over its CPUs: time the
    hypervisor ran something else while a virtual CPU had work (``/proc/stat``'s ``cpu``
    line, its eighth value; proc(5)). None where there is no such line."""
    try:
        for line in Path("/proc/stat").read_text().splitlines():
            if line.startswith("cpu "):
                return int(line.split()[8]) * _TICK_S
    except (FileNotFoundError, IndexError, ValueError):
        return None
    return None


def steal_figures(samples: Sequence[tuple[float, float]], start_s: float, end_s: float,
                  over_unix_s: Sequence[float], near_s: float = 1.0) -> dict[str, float]:
    """The hypervisor's steal over [start_s, end_s] (Unix seconds), from the machine's
    samples (Unix time, steal seconds so far; about one a second), and how many of the
    cycles over the period (``over_unix_s``: their samples' publish times) fell within
    ``near_s`` of a sampling interval in which steal grew. ``near_share``: the share of
    the window so near, the share of those cycles chance alone would put there.

    Returns steal_s, intervals_with_steal, near_s, near_share, overs, overs_near;
    ValueError when fewer than two samples fall in the window."""
    inside = [s for s in samples if start_s <= s[0] <= end_s]
    if len(inside) < 2:
        raise ValueError(f"{len(inside)} steal sample(s) between {start_s:.1f} and "
                         f"{end_s:.1f}")
    stolen = [(a[0] - near_s, b[0] + near_s) for a, b in zip(inside, inside[1:])
              if b[1] > a[1]]
    share, overs, near = near_share(stolen, inside[0][0], inside[-1][0], over_unix_s)
    return {"steal_s": inside[-1][1] - inside[0][1], "intervals_with_steal": len(stolen),
            "near_s": near_s, "near_share": share, "overs": overs, "overs_near": near}


def children_of(pid: int) -> dict[int, str]:
    """The live child processes of ``pid``: pid -> its command line."""
    found = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            if int(stat[stat.rindex(")") + 2:].split()[1]) != pid:
                continue
            found[int(entry.name)] = (entry / "cmdline").read_bytes().replace(
                b"\0", b" ").decode(errors="replace")
        except (FileNotFoundError, ProcessLookupError, ValueError, IndexError):
            continue
    return found


class Monitor:
    """Samples the run's processes once a second: the graph, its children (the recorder,
    the driver, node processes) and any process added by name."""

    ROLES = (("pisc_record", "recorder"), ("driver_node", "driver"))

    def __init__(self, graph_pid: int) -> None:
        self.graph_pid = graph_pid
        self.pids: dict[str, int] = {"graph": graph_pid}
        self.samples: dict[str, list[Sample]] = {"graph": []}
        self.steal: list[tuple[float, float]] = []  # the machine's: (Unix s, steal s)

    def add(self, name: str, pid: int) -> None:
        self.pids[name] = pid
        self.samples.setdefault(name, [])

    def sample(self) -> None:
        if len(self.pids) < 1 + len(self.ROLES) + 2:
            for pid, command in children_of(self.graph_pid).items():
                for key, role in self.ROLES:
                    if key in command and role not in self.pids:
                        self.add(role, pid)
        now = time.time()
        for name, pid in self.pids.items():
            seen = read_proc(pid)
            if seen is not None:
                self.samples[name].append(Sample(now, seen[0], seen[1]))
        steal = read_steal()
        if steal is not None:
            self.steal.append((now, steal))

