"""What the graph runner, the soak and the tests share about the processes they start
(ROS-free): the command of a console entry point, and a ROS domain id claimed for a run.
"""

from __future__ import annotations

import fcntl
import os
import shutil
import sys
import tempfile
from pathlib import Path

__all__ = ["DOMAIN_LOCKS", "DomainClaim", "console_command"]

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


class DomainClaim:
    """A ROS domain id no other process on this machine uses while the claim is held, so
    runs in parallel (test runs of several checkouts, CI, a soak) never hear each other's
    graphs. :class:`RuntimeError` when all of 1..100 are claimed."""

    def __init__(self) -> None:
        DOMAIN_LOCKS.mkdir(exist_ok=True)
        for domain in range(1, 101):
            handle = (DOMAIN_LOCKS / f"{domain}.lock").open("w")
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                handle.close()
                continue
            self.domain_id = domain
            self._handle = handle
            return
        raise RuntimeError(f"no free ROS domain id: all of 1..100 are claimed in {DOMAIN_LOCKS}")

    def release(self) -> None:
        self._handle.close()
