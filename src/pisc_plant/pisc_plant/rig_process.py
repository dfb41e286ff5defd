"""``pisc_virtual_rig`` as a child process, for tests and runners (:class:`RigProcess`)."""

from __future__ import annotations

import collections
import json
import select
import signal
import subprocess
import sys
import threading
import weakref
from typing import Any, ClassVar

__all__ = ["RigProcess"]


class RigProcess:
    """``pisc_virtual_rig`` as a child process, controlled through its standard input.

    For tests and runners: ``device`` is the path to give the driver; ``request``
    sends a fault request; ``status()`` asks for and returns the status; ``stop()``
    ends the rig (SIGTERM) and returns its final status. ``stderr_lines()`` is what the
    rig said on standard error (a thread reads it, so that it never fills the pipe).
    """

    #: the rigs started and not stopped (a test's fixture stops what its test left)
    running: ClassVar[weakref.WeakSet[RigProcess]] = weakref.WeakSet()

    def __init__(self, args: list[str] = (), env: dict[str, str] | None = None,
                 timeout_s: float = 30.0) -> None:
        self.process = subprocess.Popen(
            [sys.executable, "-m", "pisc_plant.virtual_rig_cli", *args], stdin=subprocess.PIPE,
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, bufsize=1)
        RigProcess.running.add(self)
        self._final: dict[str, Any] | None = None
        self._stderr: collections.deque[str] = collections.deque(maxlen=1000)
        self._stderr_reader = threading.Thread(target=self._read_stderr, daemon=True,
                                               name="pisc_virtual_rig_stderr")
        self._stderr_reader.start()
        line = self._line(timeout_s)
        if not line.startswith("device "):
            if self.process.poll() is not None:
                self._stderr_reader.join(timeout=5.0)
            raise RuntimeError(f"pisc_virtual_rig did not start: {line!r} "
                               f"{''.join(self._stderr)}")
        self.device = line.split(" ", 1)[1].strip()

    def _read_stderr(self) -> None:
        for line in self.process.stderr:
            self._stderr.append(line)

    def stderr_lines(self) -> list[str]:
        return [line.rstrip("\n") for line in self._stderr]

    def _line(self, timeout_s: float) -> str:
        ready, _, _ = select.select([self.process.stdout], [], [], timeout_s)
        if not ready:
            raise TimeoutError(f"pisc_virtual_rig said nothing for {timeout_s} s")
        return self.process.stdout.readline()

    def request(self, **request: Any) -> None:
        self.send_line(json.dumps(request))

    def send_line(self, line: str) -> None:
        """One raw line on the rig's standard input (a request, or anything)."""
        self.process.stdin.write(line + "\n")
        self.process.stdin.flush()

    def reply(self, timeout_s: float = 10.0) -> dict[str, Any]:
        """The next JSON line on the rig's standard output (a status or an error)."""
        return json.loads(self._line(timeout_s))

    def status(self, timeout_s: float = 10.0) -> dict[str, Any]:
        self.request(status=True)
        reply = self.reply(timeout_s)
        if "error" in reply:
            raise ValueError(reply["error"])
        return reply

    def stop(self, timeout_s: float = 10.0) -> dict[str, Any]:
        """End the rig (once; later calls return the same final status)."""
        if self._final is None:
            if self.process.poll() is None:
                self.process.send_signal(signal.SIGTERM)
            try:
                out, _ = self.process.communicate(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self.process.kill()
                out, _ = self.process.communicate()
            RigProcess.running.discard(self)
            lines = [line for line in out.splitlines() if line.startswith("{")]
            self._final = json.loads(lines[-1]) if lines else {}
        return self._final
