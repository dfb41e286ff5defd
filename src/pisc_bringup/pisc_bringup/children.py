"""The graph runner's child processes: starting them, watching for their exit, stopping them.

Each child (the recorder, a node process, the Foxglove bridge) runs in a process group of
its own, dies with the runner (Linux: ``PR_SET_PDEATHSIG``), and has its standard error
read as it comes (the last :data:`STDERR_TAIL_LINES` lines kept for the message on its
failure). :class:`ExitAlarm` wakes the runner's executor when one exits, and nothing
while they run; :func:`stop` and :func:`stop_all` end them (the source first, 0 V), and
kill one that hangs.
"""

from __future__ import annotations

import collections
import ctypes
import os
import select
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from rclpy.node import Node

__all__ = ["EXIT_POLL_S", "STDERR_TAIL_LINES", "STOP_LIMIT_S", "STOP_PATIENCE_S", "ExitAlarm",
           "cpu_ticks", "exit_description", "spawn", "stderr_of", "stop", "stop_all"]


def _die_with_parent() -> None:  # pragma: no cover - runs in the child before exec
    """Linux: have the kernel send SIGTERM to this child if the runner dies."""
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG = 1
    except OSError:
        pass


def _batch_scheduling() -> None:  # pragma: no cover - runs in the child before exec
    """The recorder's scheduling, whatever the runner's (SCHED_FIFO with --realtime):
    SCHED_BATCH, the normal share of the CPU without preempting a thread it is woken by.
    At SCHED_OTHER its shared-memory receive thread, woken by each message, preempted the
    graph's main thread about six times a cycle on the wall clock (perf sched_switch,
    docs/soak.md); at SCHED_FIFO (inherited) it made the graph miss its periods
    (docs/driver.md)."""
    _die_with_parent()
    try:
        os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))
    except OSError:
        if os.sched_getscheduler(0) != os.SCHED_OTHER:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


STDERR_TAIL_LINES = 200  # of a child's standard error, kept for the message on its failure


def spawn(args: list[str], env: dict[str, str], stdout: int,
          batch_scheduling: bool = False) -> subprocess.Popen:
    """Start a child; a thread reads its standard error as it comes and keeps the last
    :data:`STDERR_TAIL_LINES` lines. (Read only when stopping it, the pipe filled on a
    long run: 344 lines of the driver's faults in a 10-minute soak blocked its reader
    thread in ``write`` at 163 s, and the run never ended.)"""
    preexec = _batch_scheduling if batch_scheduling else _die_with_parent
    # a process group of its own: a terminal's Ctrl-C reaches the runner alone, which
    # stops the source first (0 V) and then the rest (run_guard)
    child = subprocess.Popen(args, env=env, stdout=stdout, stderr=subprocess.PIPE,
                             preexec_fn=preexec if sys.platform == "linux" else None,
                             process_group=0)
    tail: collections.deque[bytes] = collections.deque(maxlen=STDERR_TAIL_LINES)
    stream, child.stderr = child.stderr, None  # the thread's alone: communicate() skips it
    reader = threading.Thread(target=_drain, args=(stream, tail), daemon=True,
                              name=f"stderr of {Path(args[0]).name}")
    reader.start()
    child.pisc_stderr = (tail, reader)  # type: ignore[attr-defined]
    return child


def _drain(stream: Any, tail: collections.deque[bytes]) -> None:
    with stream:
        for line in iter(stream.readline, b""):
            tail.append(line)


def stderr_of(child: subprocess.Popen) -> bytes:
    """What a child that has exited wrote on its standard error (the last lines)."""
    tail, reader = child.pisc_stderr  # type: ignore[attr-defined]
    reader.join(timeout=5.0)
    return b"".join(tail)


def cpu_ticks(pid: int) -> int | None:
    """User + system clock ticks a process has used (Linux), None when unknown."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
        return int(fields[11]) + int(fields[12])
    except (OSError, ValueError, IndexError):
        return None


STOP_PATIENCE_S = 20.0  # a stopping child that uses no CPU for this long is killed
STOP_LIMIT_S = 600.0  # and one still busy after this long


def stop(child: subprocess.Popen, signalled: bool = False,
         busy_limit_s: float | None = None, hang_is_failure: bool = True) -> tuple[str, str]:
    """SIGTERM a child (SIGINT may be ignored in background jobs; not again when
    ``signalled``) and wait for it: while it keeps using the CPU (a recorder finishing a
    long bag on a loaded machine), up to ``busy_limit_s`` (default :data:`STOP_LIMIT_S`);
    SIGKILL once it used none for :data:`STOP_PATIENCE_S`. A child killed so is a failure,
    or, unless ``hang_is_failure``, a warning on standard error (a node process whose
    work ended with the run).

    Returns (what went wrong or "", its standard output).
    """
    if not signalled and child.poll() is None:
        child.send_signal(signal.SIGTERM)
    limit_s = STOP_LIMIT_S if busy_limit_s is None else busy_limit_s
    started = time.monotonic()
    first = ticks = cpu_ticks(child.pid)
    killed = False
    while True:
        try:
            out, _ = child.communicate(timeout=STOP_PATIENCE_S)
            break
        except subprocess.TimeoutExpired:
            now = cpu_ticks(child.pid)
            if (ticks is None or now is None or now == ticks
                    or time.monotonic() - started > limit_s):
                child.kill()
                killed = True
                out, _ = child.communicate()
                break
            ticks = now
    output = out.decode(errors="replace") if out else ""
    if killed and not hang_is_failure:
        busy = ("" if first is None or ticks is None
                else f", {(ticks - first) / os.sysconf('SC_CLK_TCK'):.1f} CPU s meanwhile")
        print(f"pisc_graph: {Path(child.args[0]).name} had not exited "
              f"{time.monotonic() - started:.0f} s after SIGTERM{busy}; killed "
              "(docs/limitations.md: Fast DDS 2.14 can spin without end destroying a "
              "participant)", file=sys.stderr, flush=True)
        return "", output
    if child.returncode not in (0, -signal.SIGTERM):
        return (f"{Path(child.args[0]).name} exited with status {child.returncode}: "
                f"{stderr_of(child).decode(errors='replace').strip()}"), output
    return "", output


def stop_all(children: Sequence[subprocess.Popen]) -> list[str]:
    """Stop the run's node processes: the last (the plant or the driver) first, so that
    the controllers see no sample after their peers stopped, then the rest at once (one
    after another, each took 0.16-0.22 s to shut its node down here). Returns what went
    wrong with each, in the order stopped; a controller that has not exited
    :data:`STOP_PATIENCE_S` after SIGTERM is killed, with a warning, not a failure."""
    if not children:
        return []
    *rest, source = children
    failures = [stop(source)[0]]
    for child in rest:
        if child.poll() is None:
            child.send_signal(signal.SIGTERM)
    # a controller has nothing to finish once the source stopped: one still running after
    # STOP_PATIENCE_S is hung, busy or not (a supervisor spun for minutes in Fast DDS's
    # participant teardown, 2026-12-04), and is killed with a warning
    return failures + [stop(child, signalled=True, busy_limit_s=STOP_PATIENCE_S,
                            hang_is_failure=False)[0] for child in reversed(rest)]

# how often a runner without pidfds (:class:`ExitAlarm`) looks at its children
EXIT_POLL_S = 0.05


class ExitAlarm:
    """Runs ``on_exit`` in the executor's thread as soon as one of ``children`` has
    exited, and nothing while they run: a thread blocks on their pidfds (Linux 5.3) and
    hands ``on_exit`` to the executor (``create_task``, which an EventsExecutor takes
    from any thread) once one is readable. The runner had looked with timers, every
    50 ms at the recorder and every 20 ms at a driver's process: 70 wake-ups a second of
    its main thread and about 200 of rclpy's timer thread, in the process whose CPU is
    the controllers' (docs/soak.md). ``on_exit`` finds which child it was
    itself (``Popen.poll``); it may run more than once. Where pidfds are missing it
    looks every :data:`EXIT_POLL_S` on a timer of ``node`` instead."""

    def __init__(self, node: Node, children: Sequence[subprocess.Popen],
                 on_exit: Callable[[], None]) -> None:
        self._on_exit = on_exit
        self._fds: list[int] = []
        self._thread: threading.Thread | None = None
        self._stop_r = self._stop_w = -1
        self._exited = False  # one was gone (reaped) before its pidfd could be opened
        try:
            for child in children:
                try:
                    self._fds.append(os.pidfd_open(child.pid))
                except ProcessLookupError:
                    self._exited = True
        except (AttributeError, OSError):  # no pidfd_open: look on a timer
            self.close()
            node.create_timer(EXIT_POLL_S, on_exit)
            return
        self._stop_r, self._stop_w = os.pipe()

    def start(self, executor: Any) -> None:
        """Watch from now on (an exit before this is seen at once)."""
        if self._stop_r < 0:
            return
        if self._exited:
            executor.create_task(self._on_exit)
        self._thread = threading.Thread(target=self._wait, args=(executor,), daemon=True,
                                        name="pisc_graph_exit_alarm")
        self._thread.start()

    def _wait(self, executor: Any) -> None:
        poller = select.poll()
        for fd in (*self._fds, self._stop_r):
            poller.register(fd, select.POLLIN)
        while True:
            ready = {fd for fd, _ in poller.poll()}
            if self._stop_r in ready:
                return
            for fd in ready:  # (an exited child's pidfd stays readable: once each)
                poller.unregister(fd)
            executor.create_task(self._on_exit)

    def close(self) -> None:
        """Stop watching (before the executor is shut down) and close the descriptors."""
        if self._stop_w >= 0:
            os.write(self._stop_w, b"x")
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        for fd in (*self._fds, self._stop_r, self._stop_w):
            if fd >= 0:
                os.close(fd)
        self._fds, self._stop_r, self._stop_w = [], -1, -1

def exit_description(returncode: int) -> str:
    if returncode < 0:
        try:
            return f"was killed by {signal.Signals(-returncode).name}"
        except ValueError:
            return f"was killed by signal {-returncode}"
    return f"exited with status {returncode}"


