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

Faults on request, from the command line or as JSON lines on standard input (one JSON
object a line: :mod:`pisc_plant.rig_faults` says which). A request refused (not JSON,
an unknown key, a value of the wrong type, not finite, negative or out of range) is
refused whole, nothing of it applied: the rig says why on standard error, naming the key
and the rule, answers ``{"error": ...}`` on standard output (for a client waiting for a
status line) and keeps running. The firmware's behaviour is :mod:`pisc_plant.firmware`;
:class:`pisc_plant.rig_process.RigProcess` runs this command as a child process.

On exit (end of input is not an exit; SIGINT, SIGTERM or quit are) it prints its
status as the last line. ``--log`` writes the true state of every period as CSV, with
the monotonic and the Unix time each frame was sent (a driver stamps samples with ROS
time, the Unix clock, so a bag and the log line up).
"""

from __future__ import annotations

import json
import os
import select
import sys
import time
import tty
from typing import Any, TextIO

import numpy as np

from pisc_msgs_py.config import ConfigError, from_flat, load_params_file
from pisc_model.params import (
    InitialParams,
    check_models_use,
)
from pisc_plant.firmware import Firmware
from pisc_plant.plant import THETA, THETA_DOT, X_DOT, X
from pisc_plant.plant_config import PLANT_SECTIONS, PlantConfig
from pisc_plant.rig_faults import MAX_REQUEST, RequestError, RigFaults

__all__ = ["Rig", "load_plant"]


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
