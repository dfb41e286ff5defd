"""What the graph runner, the soak and the tests share about the processes they start
(ROS-free): the command of a console entry point, stopping a child, and a ROS domain id
claimed for a run.
"""

from __future__ import annotations

import fcntl
import os
import shutil
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

__all__ = ["DOMAIN_LOCKS", "DomainClaim", "console_command", "stop_child"]

#: One lock file per ROS domain id 1..100; a claim holds an exclusive lock on one.
DOMAIN_LOCKS = Path(tempfile.gettempdir()) / "pisc-ros-domains"


def console_command(executable: str, module: str) -> list[str]:
    """The console entry point: beside this interpreter (a virtual environment), on PATH
    (a colcon install), else ``python -m module``."""
    beside = Path(sys.executable).parent / executable
    if beside.is_file() and os.access(beside, os.X_OK):
        return [str(beside)]
    path = shutil.which(executable)
    return [path] if path else [sys.executable, "-m", module]


def stop_child(child: subprocess.Popen, sig: int = signal.SIGINT,
               timeout_s: float = 30.0) -> None:
    """Ask ``child`` to stop with ``sig`` (SIGINT: as on Ctrl-C, so a graph zeroes the
    motor and ends its recorder) and kill it only if it has not ended after ``timeout_s``;
    its pipes are read to the end either way."""
    if child.poll() is None:
        child.send_signal(sig)
    try:
        child.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        child.kill()
        child.communicate()


class DomainClaim:
    """A ROS domain id no other process on this machine uses while the claim is held, so
    runs in parallel (test runs of several checkouts, CI, a soak) never hear each other's
    graphs. :class:`RuntimeError` when all of 1..100 are claimed.

    Of the free ids the one claimed or released longest ago is taken (each lock file's
    modification time says when). What a run leaves in its domain after it (a node a
    failed test still holds, a process killed with SIGKILL) is then met by the next claim
    of that id only once every other free id has been used. Taking the lowest free id gave
    nearly every test of a run the same domain: in a test run on 2026-12-03, every graph
    after the first failed tests met "another publisher on /pisc/motor/voltage:
    /current_loop, /current_loop" (33 failed tests), what a node left alive by a failed
    test looks like from its domain (``src/pisc_msgs_py/test/test_isolation.py``)."""

    def __init__(self) -> None:
        DOMAIN_LOCKS.mkdir(exist_ok=True)
        for domain in sorted(range(1, 101), key=_last_used):
            handle = (DOMAIN_LOCKS / f"{domain}.lock").open("a")
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                handle.close()
                continue
            os.utime(handle.fileno())  # a claimer killed before its release counts from here
            self.domain_id = domain
            self._handle = handle
            return
        raise RuntimeError(f"no free ROS domain id: all of 1..100 are claimed in {DOMAIN_LOCKS}")

    def release(self) -> None:
        if self._handle.closed:
            return
        os.utime(self._handle.fileno())  # released now: the last of the free ids to reuse
        self._handle.close()


def _last_used(domain: int) -> tuple[float, int]:
    """When the id was last claimed or released (never: first), then the id."""
    try:
        return (os.stat(DOMAIN_LOCKS / f"{domain}.lock").st_mtime, domain)
    except FileNotFoundError:
        return (float("-inf"), domain)
