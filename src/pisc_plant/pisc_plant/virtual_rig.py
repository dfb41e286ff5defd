"""``pisc_virtual_rig``: the simulated rig behind a pseudo-terminal, acting as its PIC16F877A.

    pisc_virtual_rig [--params-file FILE] [--set NAME=VALUE ...] [--x0 M]
                     [--drop-rate P] [--flip-rate P] [--seed N] [--log FILE]
                     [--watchdog-ms MS]

It prints ``device /dev/pts/N``: give that path to the driver (``driver.port``). Every
5 ms it sends the frame ``0xAA, IR_hi, IR_lo, CUR_hi, CUR_lo, CNT_hi, CNT_lo`` of the
simulated state with the parameter file's measurement noise (``noise.*``), encoded
through the inverse calibrations and quantised like the real converters
(:mod:`pisc_model.sensors`); each command byte is applied the moment it
arrives, as the firmware does: PWM duty ``magnitude << 1``, bit 7 the direction, the
duty 254 giving the full-scale voltage (SPEC section 4).

A command watchdog, as docs/driver-protocol.md specifies it for the PIC's firmware:
the 5 ms timer tick that sends a frame also counts the ticks since the last command byte,
and once more than ``--watchdog-ms`` / 5 ms (default 50 ms: 10 periods) have passed
without one, it sets the duty to 0 (0 V), between 50 and 55 ms after the last byte;
the next byte is applied as usual and ends the trip (``--watchdog-ms 0``: no watchdog,
the thesis's firmware, which holds the last byte's PWM for ever).

This file is the firmware's side of the protocol written on its own, from SPEC section 4,
not with the driver's codec: the tests check that the two agree byte for byte.

Faults on request, from the command line or as JSON lines on standard input::

    {"drop_rate": 0.01}   lose each sent byte with this probability (0..1)
    {"flip_rate": 0.001}  flip one bit of each sent byte with this probability (0..1)
    {"silence_s": 0.1}    send nothing for this long (the device goes quiet; 0 .. 3600 s)
    {"garbage": 20}       send this many random bytes before the next frame (0..1024)
    {"status": true}      print the rig's status as one JSON line
    {"quit": true}        stop

A request is one JSON object of these keys. Anything else (not JSON, an unknown key, a
value of the wrong type, not finite, negative or out of range) is refused whole, nothing
of it applied: the rig says why on standard error, naming the key and the rule, answers
``{"error": ...}`` on standard output (for a client waiting for a status line) and keeps
running.

On exit (end of input is not an exit; SIGINT, SIGTERM or quit are) it prints its
status as the last line. ``--log`` writes the true state of every period as CSV, with
the monotonic and the Unix time each frame was sent (a driver stamps samples with ROS
time, the Unix clock, so a bag and the log line up).
"""

from __future__ import annotations

import argparse
import collections
import difflib
import json
import math
import os
import select
import signal
import struct
import subprocess
import sys
import threading
import time
import tty
import weakref
from dataclasses import dataclass, field
from typing import Any, ClassVar, TextIO

import numpy as np

from pisc_msgs_py.config import ConfigError, from_flat, load_params_file, parse_overrides
from pisc_model.params import (
    InitialParams,
    check_models_use,
)
from pisc_plant.plant import (
    PLANT_SECTIONS,
    THETA,
    THETA_DOT,
    X_DOT,
    Plant,
    PlantConfig,
    X,
)

__all__ = ["Firmware", "RequestError", "Rig", "RigFaults", "RigProcess", "check_request",
           "main"]

HEADER = 0xAA
DEFAULT_WATCHDOG_MS = 50.0  # 10 periods; docs/driver-protocol.md says why
MAX_GARBAGE = 1024  # bytes per request: 89 ms of the line at 115200 baud
MAX_REQUEST = 4096  # bytes of one request line


class RequestError(ValueError):
    """A fault request the rig refuses; the message names the key and the rule."""


def _number(key: str, value: Any, rule: str) -> float:
    """``value`` as a finite float, or RequestError naming ``key`` and ``rule``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise RequestError(f"{key} = {json.dumps(value)} must be a number ({rule}), "
                           f"not {_json_type(value)}")
    try:
        number = float(value)
    except OverflowError:
        number = math.inf
    if not math.isfinite(number):
        raise RequestError(f"{key} = {json.dumps(value)} must be a finite number ({rule})")
    return number


def _json_type(value: Any) -> str:
    for cls, name in ((bool, "true/false"), ((int, float), "a number"), (str, "a string"),
                      (list, "a list"), (dict, "an object"), (type(None), "null")):
        if isinstance(value, cls):
            return name
    return type(value).__name__


def _probability(key: str, value: Any) -> float:
    rule = "a probability per byte, 0 to 1"
    number = _number(key, value, rule)
    if not 0.0 <= number <= 1.0:
        raise RequestError(f"{key} = {json.dumps(value)} must lie in [0, 1] ({rule})")
    return number


MAX_SILENCE_S = 3600.0  # a longer silence is no test of a link (1e308 was taken)


def _silence(key: str, value: Any) -> float:
    rule = f"seconds without frames, 0 .. {MAX_SILENCE_S:g}"
    number = _number(key, value, rule)
    if number < 0.0:
        raise RequestError(f"{key} = {json.dumps(value)} must not be negative ({rule})")
    if number > MAX_SILENCE_S:
        raise RequestError(f"{key} = {json.dumps(value)} is too long ({rule})")
    return number


def _garbage(key: str, value: Any) -> int:
    rule = f"random bytes to send, a whole number from 0 to {MAX_GARBAGE}"
    number = _number(key, value, rule)
    if number != math.floor(number) or not 0 <= number <= MAX_GARBAGE:
        raise RequestError(f"{key} = {json.dumps(value)} must be a whole number from 0 to "
                           f"{MAX_GARBAGE} (random bytes to send before the next frame)")
    return int(number)


def _flag(key: str, value: Any) -> bool:
    if not isinstance(value, bool):
        raise RequestError(f"{key} = {json.dumps(value)} must be true or false, "
                           f"not {_json_type(value)}")
    return value


REQUESTS = {"drop_rate": _probability, "flip_rate": _probability, "silence_s": _silence,
            "garbage": _garbage, "status": _flag, "quit": _flag}


def check_request(request: Any) -> dict[str, Any]:
    """A fault request (a parsed JSON value) checked whole: the values to apply, or
    RequestError for the first key that breaks its rule (nothing is applied then)."""
    if not isinstance(request, dict):
        raise RequestError(f"a request is a JSON object of {', '.join(REQUESTS)}; "
                           f"got {_json_type(request)}")
    checked = {}
    for key, value in request.items():
        if key not in REQUESTS:
            match = difflib.get_close_matches(key, list(REQUESTS), n=1)
            hint = f"; did you mean {match[0]}?" if match else ""
            raise RequestError(f"{json.dumps(key)} is not a request (known: "
                               f"{', '.join(REQUESTS)}){hint}")
        checked[key] = REQUESTS[key](key, value)
    return checked


@dataclass
class RigFaults:
    drop_rate: float = 0.0
    flip_rate: float = 0.0
    silent_until: float = -math.inf  # monotonic time
    garbage: int = 0

    def update(self, request: dict[str, Any], now: float) -> None:
        """Apply a request (:func:`check_request` first: all of it or, refused, none)."""
        request = check_request(request)
        if self.garbage + request.get("garbage", 0) > MAX_GARBAGE:
            raise RequestError(f"garbage = {request['garbage']}: {self.garbage} bytes are "
                               f"already waiting, and at most {MAX_GARBAGE} may")
        for key in ("drop_rate", "flip_rate"):
            if key in request:
                setattr(self, key, request[key])
        if "silence_s" in request:
            self.silent_until = now + request["silence_s"]
        self.garbage += request.get("garbage", 0)


@dataclass
class Firmware:
    """The PIC's behaviour around a simulated plant; times are passed in (seconds).

    ``frame()`` is the 7 bytes of the current sample; ``receive(byte, t)`` applies a
    command byte at time ``t`` into the current period; ``advance()`` integrates the
    period with the voltage changing where the bytes arrived, then runs the period's
    timer tick: the command watchdog (``watchdog_s``, 0 = none) counts the ticks since the
    last byte and, at the first tick more than ``ceil(watchdog_s / period)`` of them
    after it, applies 0 V until the next byte. It is armed by the first byte (before it
    the duty is 0 anyway).
    """

    plant: Plant
    state: np.ndarray
    applied_v: float = 0.0
    time_s: float = 0.0
    watchdog_s: float = DEFAULT_WATCHDOG_MS * 1e-3
    silent_ticks: int = 0  # timer ticks since the last command byte
    armed: bool = False
    tripped: bool = False
    trips: int = 0
    last_byte_s: float | None = None  # firmware time of the last command byte
    trip_delay_s: float | None = None  # last trip: its time after the last byte
    # a hand on the rig (``--hold``): the state stays as it is until the first command
    # byte of a nonzero voltage, from which it moves; time and frames go on meanwhile
    held: bool = False
    released_s: float | None = None  # firmware time of that byte
    _changes: list[tuple[float, float]] = field(default_factory=list)
    # the sensors' noise (``noise.*``), drawn as the simulator's sampled plant draws it
    _noise: np.random.Generator | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.watchdog_s) and self.watchdog_s >= 0.0):
            raise ValueError(f"watchdog = {self.watchdog_s} s must be a finite number >= 0")
        noise = self.plant.config.noise
        self._noise = np.random.default_rng(noise.seed) if noise.any else None

    @property
    def watchdog_periods(self) -> int:
        """N: the watchdog trips at the (N+1)th tick without a byte (0 = no watchdog)."""
        if self.watchdog_s == 0.0:
            return 0
        return max(1, math.ceil(self.watchdog_s / self.plant.config.loop.period_s - 1e-9))

    def frame(self) -> bytes:
        """The frame of the state now: the sensors read with the voltage applied (the
        current of a quasi-static armature depends on it) and the parameter file's
        measurement noise (``noise.*``, one standard normal draw per sensor and frame
        from ``noise.seed``, as the simulator's plant node draws them)."""
        noise = None if self._noise is None else self._noise.standard_normal(3)
        ir, cur, count = self.plant.raw_measurement(self.state, self.applied_v, noise)
        count16 = ((int(count) + 0x8000) & 0xFFFF) - 0x8000  # the 16-bit counter register
        return struct.pack(">BHHh", HEADER, int(ir), int(cur), count16)

    def voltage(self, command: int) -> float:
        """PWM duty = magnitude << 1; duty 254 = full scale; bit 7 = negative."""
        a = self.plant.config.actuator
        duty = (command & 0x7F) << 1
        volts = a.full_scale_v * min(duty, 254) / 254
        return -volts if command & 0x80 else volts

    def receive(self, command: int, offset_s: float) -> None:
        """A command byte ``offset_s`` into the current period: applied from there (it
        also ends a watchdog trip) and the watchdog's count starts again."""
        self._changes.append((offset_s, self.voltage(command)))
        period = self.plant.config.loop.period_s
        self.last_byte_s = self.time_s + min(max(offset_s, 0.0), period)
        self.silent_ticks = 0
        self.armed = True
        self.tripped = False

    def advance(self) -> None:
        period = self.plant.config.loop.period_s
        t = 0.0
        if self.held:  # the state moves from the first nonzero byte on, or not at all
            release = next((o for o, volts in self._changes if volts != 0.0), None)
            if release is None:
                t = period
            else:
                t = min(max(release, 0.0), period)
                self.held = False
                self.released_s = self.time_s + t
        for offset, volts in self._changes:
            offset = min(max(offset, 0.0), period)
            if offset > t:
                self.state = self.plant.advance(self.state, self.applied_v, offset - t)
                t = offset
            self.applied_v = volts
        if period > t:
            self.state = self.plant.advance(self.state, self.applied_v, period - t)
        self._changes.clear()
        self.time_s += period
        self._tick()

    def _tick(self) -> None:
        """The timer tick at the end of a period: the command watchdog."""
        n = self.watchdog_periods
        if not n or not self.armed:
            return
        self.silent_ticks += 1
        if self.silent_ticks > n and not self.tripped:
            self.applied_v = 0.0
            self.tripped = True
            self.trips += 1
            self.trip_delay_s = self.time_s - self.last_byte_s


def load_plant(params_file: str | None, overrides: dict[str, Any]
               ) -> tuple[PlantConfig, InitialParams]:
    flat: dict[str, Any] = load_params_file(params_file) if params_file else {}
    flat.update(overrides)
    sections = {**PLANT_SECTIONS, "initial": InitialParams}
    known = {k for k in flat if k.split(".", 1)[0] in sections}
    unknown = [k for k in overrides if k not in known]
    if unknown:
        raise ConfigError(f"{unknown[0]}: not a parameter of the rig (sections: "
                          f"{', '.join(sections)})")
    values = {name: from_flat(cls, {k: flat[k] for k in known}, name)
              for name, cls in sections.items()}
    check_models_use({k: flat[k] for k in known})  # a value the plant would ignore
    initial = values.pop("initial")
    config = PlantConfig(**values)
    if config.models.force_input:
        raise ConfigError("models.armature = 'ideal_force': the rig takes voltage bytes, so "
                          "its plant needs a motor armature ('full' or 'quasi_static')")
    return config, initial


class Rig:
    """The firmware on a pseudo-terminal, paced by the monotonic clock."""

    def __init__(self, firmware: Firmware, faults: RigFaults, seed: int = 0,
                 log: TextIO | None = None) -> None:
        self.firmware = firmware
        # load (or compile) the plant's kernel now, not in the first period
        firmware.plant.advance(firmware.state, 0.0, firmware.plant.config.loop.period_s)
        firmware.plant.raw_measurement(firmware.state)
        self.faults = faults
        self.rng = np.random.default_rng(seed)
        self.log = log
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # no echo, no line editing, before anyone opens it
        os.set_blocking(self.master, False)
        self.device = os.ttyname(self.slave)
        self.frames = 0
        self.bytes_sent = 0
        self.bytes_received = 0
        self.dropped = 0
        self.flipped = 0
        self.unread = 0  # frames the pty could not take (nobody reading)
        self.overruns = 0
        self.last_byte: int | None = None
        self.last_byte_time: float | None = None
        self.last_frame_time: float | None = None
        self.silence_start: float | None = None  # last frame before the current silence
        self.zero_after_silence_s: float | None = None
        self.refused = 0  # fault requests refused
        self.watchdog_trip_time: float | None = None  # monotonic, the last trip's tick
        self.running = True

    def status(self) -> dict[str, Any]:
        y = self.firmware.state
        return {
            "device": self.device, "time_s": round(self.firmware.time_s, 6),
            "frames": self.frames, "bytes_sent": self.bytes_sent,
            "bytes_received": self.bytes_received, "dropped": self.dropped,
            "flipped": self.flipped, "unread": self.unread, "overruns": self.overruns,
            "last_byte": self.last_byte, "last_byte_time": self.last_byte_time,
            "last_frame_time": self.last_frame_time,
            "silence_start": self.silence_start,
            "zero_after_silence_s": self.zero_after_silence_s,
            "applied_v": self.firmware.applied_v,
            "watchdog_ms": self.firmware.watchdog_s * 1e3,
            "watchdog_trips": self.firmware.trips,
            "watchdog_tripped": self.firmware.tripped,
            "watchdog_delay_s": self.firmware.trip_delay_s,
            "watchdog_trip_time": self.watchdog_trip_time,
            "refused_requests": self.refused,
            "held": self.firmware.held, "released_s": self.firmware.released_s,
            "state": {"x": float(y[X]), "x_dot": float(y[X_DOT]), "theta": float(y[THETA]),
                      "theta_dot": float(y[THETA_DOT]),
                      "i": float(self.firmware.plant.current(y))},
        }

    def _damage(self, data: bytes) -> bytes:
        f = self.faults
        if f.drop_rate == 0.0 and f.flip_rate == 0.0:
            return data
        out = bytearray()
        for byte in data:
            if self.rng.random() < f.drop_rate:
                self.dropped += 1
                continue
            if self.rng.random() < f.flip_rate:
                byte ^= 1 << int(self.rng.integers(0, 8))
                self.flipped += 1
            out.append(byte)
        return bytes(out)

    def _send_frame(self, now: float) -> None:
        f = self.faults
        if now < f.silent_until:
            if self.silence_start is None:
                self.silence_start = self.last_frame_time
                self.zero_after_silence_s = None
            return
        data = self.firmware.frame()
        if f.garbage:
            data = self.rng.integers(0, 256, f.garbage, dtype=np.uint8).tobytes() + data
            f.garbage = 0
        data = self._damage(data)
        sent_unix = time.time()  # before the write: a reader's arrival stamp is later
        try:
            written = os.write(self.master, data)
            self.bytes_sent += written
            if written < len(data):  # the pty took part of it (nobody reading)
                self.unread += 1
        except BlockingIOError:
            self.unread += 1
        self.frames += 1
        self.last_frame_time = now
        if self.log is not None:
            y = self.firmware.state
            self.log.write(f"{self.firmware.time_s:.6f},{now:.6f},{sent_unix:.6f},"
                           f"{y[X]:.9g},{y[X_DOT]:.9g},"
                           f"{y[THETA]:.9g},{y[THETA_DOT]:.9g},"
                           f"{float(self.firmware.plant.current(y, self.firmware.applied_v)):.9g},"
                           f"{self.firmware.applied_v:.6g}\n")

    def _receive(self, period_start: float) -> None:
        try:
            data = os.read(self.master, 256)
        except (BlockingIOError, OSError):
            return
        now = time.monotonic()
        for byte in data:
            self.firmware.receive(byte, now - period_start)
            self.bytes_received += 1
            self.last_byte = byte
            self.last_byte_time = now
            if (byte == 0 and self.silence_start is not None
                    and self.zero_after_silence_s is None):
                self.zero_after_silence_s = now - self.silence_start

    def _control(self, line: str, out: TextIO, err: TextIO = sys.stderr) -> None:
        """One request line: applied whole, or refused whole with the reason on ``err``
        (and as ``{"error": ...}`` on ``out``); the rig runs on either way."""
        try:
            try:
                request = json.loads(line)
            except RecursionError:
                raise RequestError("not a JSON object (nested too deep)") from None
            except ValueError as exc:
                raise RequestError(f"not JSON ({exc})") from None
            self.faults.update(request, time.monotonic())
            if self.faults.silent_until > time.monotonic():
                self.silence_start = None
        except RequestError as exc:
            self.refused += 1
            shown = line.strip()
            shown = shown if len(shown) <= 200 else shown[:200] + "..."
            print(f"pisc_virtual_rig: refused {shown} (nothing of it applied): {exc}",
                  file=err, flush=True)
            print(json.dumps({"error": f"{shown}: {exc}"}), file=out, flush=True)
            return
        if request.get("status"):
            print(json.dumps(self.status()), file=out, flush=True)
        if request.get("quit"):
            self.running = False

    def run(self, control_fd: int | None, out: TextIO) -> None:
        """Pace frames until stopped; JSON requests are read from ``control_fd``."""
        period = self.firmware.plant.config.loop.period_s
        next_tick = time.monotonic()
        period_start = next_tick
        started = False
        watch = [self.master] + ([control_fd] if control_fd is not None else [])
        pending = b""
        skipping = False  # inside a line too long to be a request: up to its end
        while self.running:
            now = time.monotonic()
            if now >= next_tick:
                if started:
                    trips = self.firmware.trips
                    self.firmware.advance()
                    if self.firmware.trips != trips:
                        self.watchdog_trip_time = now
                started = True
                # the PIC's timer samples on time: a late wake of this process delays the
                # frame's sending, not the period, and bytes apply from the tick's time
                # (a wake a period or more late is an overrun: from now)
                period_start = next_tick if now - next_tick < period else now
                self._send_frame(now)
                next_tick += period
                if now - next_tick > 4 * period:  # far behind (machine overloaded)
                    self.overruns += 1
                    next_tick = now + period
                continue
            try:
                ready, _, _ = select.select(watch, [], [], max(0.0, next_tick - now))
            except InterruptedError:
                continue
            if self.master in ready:
                self._receive(period_start)
            if control_fd is not None and control_fd in ready:
                chunk = os.read(control_fd, 4096)
                if not chunk:  # end of input: keep running
                    watch.remove(control_fd)
                    control_fd = None
                pending += chunk
                *lines, pending = pending.split(b"\n")
                if skipping and lines:  # the end of the long line
                    lines.pop(0)
                    skipping = False
                long = [line for line in lines if len(line) > MAX_REQUEST]
                if not skipping and len(pending) > MAX_REQUEST:
                    long.append(pending)
                    skipping = True
                if skipping:
                    pending = b""
                for line in lines:
                    if len(line) <= MAX_REQUEST and line.strip():
                        self._control(line.decode(errors="replace"), out)
                for line in long:
                    self.refused += 1
                    message = (f"a request is one line of at most {MAX_REQUEST} bytes; this "
                               f"one starts {line[:40].decode(errors='replace')!r}")
                    print(f"pisc_virtual_rig: refused a line (nothing of it applied): "
                          f"{message}", file=sys.stderr, flush=True)
                    print(json.dumps({"error": message}), file=out, flush=True)

    def close(self) -> None:
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass


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
            [sys.executable, "-m", "pisc_plant.virtual_rig", *args], stdin=subprocess.PIPE,
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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="pisc_virtual_rig",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--params-file", help="ROS 2 parameter file (plant sections and "
                        "initial.*), e.g. pisc_bringup's config/default.yaml")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    parser.add_argument("--x0", type=float, help="initial cart position [m]")
    parser.add_argument("--drop-rate", type=float, default=0.0)
    parser.add_argument("--flip-rate", type=float, default=0.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--log", help="CSV of the true state each period")
    parser.add_argument("--realtime", type=int, default=0, metavar="PRIORITY",
                        help="run under SCHED_FIFO at this priority (1-99) so that a loaded "
                        "machine does not delay frames, as the PIC's timer never does; "
                        "needs CAP_SYS_NICE (0 = normal scheduling)")
    parser.add_argument("--no-control", action="store_true",
                        help="do not read JSON requests from standard input")
    parser.add_argument("--watchdog-ms", type=float, default=DEFAULT_WATCHDOG_MS,
                        metavar="MS",
                        help="command watchdog: no command byte for this long applies 0 V "
                        "until the next byte (checked at each 5 ms tick, so 0 V comes "
                        "within one period after it); 0 = none, the thesis's firmware "
                        f"(default {DEFAULT_WATCHDOG_MS:g} ms: 10 periods)")
    parser.add_argument("--hold", action="store_true",
                        help="hold the cart and pendulum at the initial state, as a hand "
                        "would, until the first command byte of a nonzero voltage lets go: "
                        "a run started at a state (near upright, to be caught) starts there "
                        "however long the graph takes to come up; frames are sent meanwhile")
    args = parser.parse_args(argv)
    try:
        if not (math.isfinite(args.watchdog_ms) and 0.0 <= args.watchdog_ms <= 60_000.0):
            raise ValueError(f"--watchdog-ms {args.watchdog_ms:g} must lie in [0, 60000] ms "
                             "(0 = no watchdog)")
        overrides = parse_overrides(args.set)
        if args.x0 is not None:
            overrides["initial.x_m"] = args.x0
        config, initial = load_plant(args.params_file, overrides)
        faults = RigFaults()
        faults.update({"drop_rate": args.drop_rate, "flip_rate": args.flip_rate}, 0.0)
    except (ConfigError, ValueError) as exc:
        print(f"pisc_virtual_rig: {exc}", file=sys.stderr)
        return 2
    if args.realtime:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.realtime))
        except (OSError, AttributeError) as exc:
            print(f"pisc_virtual_rig: --realtime {args.realtime}: cannot use SCHED_FIFO "
                  f"({exc}); running with normal scheduling", file=sys.stderr)
    plant = Plant(config)
    state = plant.initial_state(initial.x_m, initial.x_dot_mps, initial.theta_rad,
                                initial.theta_dot_radps)
    # a large buffer: a flush that waits for the disk must not delay a frame
    log = open(args.log, "w", buffering=1 << 20) if args.log else None  # noqa: SIM115
    if log is not None:
        log.write("t_s,monotonic_s,unix_s,x,x_dot,theta,theta_dot,i,applied_v\n")
    rig = Rig(Firmware(plant, state, watchdog_s=args.watchdog_ms * 1e-3, held=args.hold),
              faults, args.seed, log)

    def stop(signum: int, frame: Any) -> None:
        rig.running = False

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    print(f"device {rig.device}", flush=True)
    try:
        rig.run(None if args.no_control else sys.stdin.fileno(), sys.stdout)
    finally:
        print(json.dumps(rig.status()), flush=True)
        rig.close()
        if log is not None:
            log.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
