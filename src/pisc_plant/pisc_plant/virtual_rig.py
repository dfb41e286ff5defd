"""``pisc_virtual_rig``: the simulated rig behind a pseudo-terminal, acting as its PIC16F877A.

    pisc_virtual_rig [--params-file FILE] [--set NAME=VALUE ...] [--x0 M]
                     [--drop-rate P] [--flip-rate P] [--seed N] [--log FILE]

It prints ``device /dev/pts/N``: give that path to the driver (``driver.port``). Every
5 ms it sends the frame ``0xAA, IR_hi, IR_lo, CUR_hi, CUR_lo, CNT_hi, CNT_lo`` of the
simulated state, encoded through the inverse calibrations and quantised like the real
converters (:mod:`pisc_plant.sensors`); each command byte is applied the moment it
arrives, as the firmware does: PWM duty ``magnitude << 1``, bit 7 the direction, the
duty 254 giving the full-scale voltage (SPEC section 4).

This file is the firmware's side of the protocol written on its own, from SPEC section 4,
not with the driver's codec: the tests check that the two agree byte for byte.

Faults on request, from the command line or as JSON lines on standard input::

    {"drop_rate": 0.01}   lose each sent byte with this probability
    {"flip_rate": 0.001}  flip one bit of each sent byte with this probability
    {"silence_s": 0.1}    send nothing for this long (the device goes quiet)
    {"garbage": 20}       send this many random bytes before the next frame
    {"status": true}      print the rig's status as one JSON line
    {"quit": true}        stop

On exit (end of input is not an exit; SIGINT, SIGTERM or quit are) it prints its
status as the last line. ``--log`` writes the true state of every period as CSV, with
the monotonic and the Unix time each frame was sent (a driver stamps samples with ROS
time, the Unix clock, so a bag and the log line up).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import select
import signal
import struct
import subprocess
import sys
import time
import tty
from dataclasses import dataclass, field
from typing import Any, TextIO

import numpy as np

from pisc_msgs_py.config import ConfigError, from_flat, load_params_file, parse_overrides
from pisc_plant.params import (
    InitialParams,
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

__all__ = ["Firmware", "Rig", "RigFaults", "RigProcess", "main"]

HEADER = 0xAA


@dataclass
class RigFaults:
    drop_rate: float = 0.0
    flip_rate: float = 0.0
    silent_until: float = -math.inf  # monotonic time
    garbage: int = 0

    def update(self, request: dict[str, Any], now: float) -> None:
        for key in ("drop_rate", "flip_rate"):
            if key in request:
                value = float(request[key])
                if not 0.0 <= value <= 1.0:
                    raise ValueError(f"{key} = {value} must lie in [0, 1]")
                setattr(self, key, value)
        if "silence_s" in request:
            self.silent_until = now + float(request["silence_s"])
        if "garbage" in request:
            self.garbage += int(request["garbage"])


@dataclass
class Firmware:
    """The PIC's behaviour around a simulated plant; times are passed in (seconds).

    ``frame()`` is the 7 bytes of the current sample; ``receive(byte, t)`` applies a
    command byte at time ``t`` into the current period; ``advance()`` integrates the
    period with the voltage changing where the bytes arrived.
    """

    plant: Plant
    state: np.ndarray
    applied_v: float = 0.0
    time_s: float = 0.0
    _changes: list[tuple[float, float]] = field(default_factory=list)

    def frame(self) -> bytes:
        ir, cur, count = self.plant.raw_measurement(self.state)
        count16 = ((int(count) + 0x8000) & 0xFFFF) - 0x8000  # the 16-bit counter register
        return struct.pack(">BHHh", HEADER, int(ir), int(cur), count16)

    def voltage(self, command: int) -> float:
        """PWM duty = magnitude << 1; duty 254 = full scale; bit 7 = negative."""
        a = self.plant.config.actuator
        duty = (command & 0x7F) << 1
        volts = a.full_scale_v * min(duty, 254) / 254
        return -volts if command & 0x80 else volts

    def receive(self, command: int, offset_s: float) -> None:
        self._changes.append((offset_s, self.voltage(command)))

    def advance(self) -> None:
        period = self.plant.config.loop.period_s
        t = 0.0
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
            os.write(self.master, data)
            self.bytes_sent += len(data)
        except BlockingIOError:
            self.unread += 1
        self.frames += 1
        self.last_frame_time = now
        if self.log is not None:
            y = self.firmware.state
            self.log.write(f"{self.firmware.time_s:.6f},{now:.6f},{sent_unix:.6f},"
                           f"{y[X]:.9g},{y[X_DOT]:.9g},"
                           f"{y[THETA]:.9g},{y[THETA_DOT]:.9g},{float(self.firmware.plant.current(y)):.9g},"
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

    def _control(self, line: str, out: TextIO) -> None:
        try:
            request = json.loads(line)
            if not isinstance(request, dict):
                raise ValueError("expected a JSON object")
            self.faults.update(request, time.monotonic())
            if self.faults.silent_until > time.monotonic():
                self.silence_start = None
        except (ValueError, TypeError) as exc:
            print(json.dumps({"error": f"{line.strip()!r}: {exc}"}), file=out, flush=True)
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
        while self.running:
            now = time.monotonic()
            if now >= next_tick:
                if started:
                    self.firmware.advance()
                started = True
                period_start = now
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
                for line in lines:
                    if line.strip():
                        self._control(line.decode(errors="replace"), out)

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
    ends the rig (SIGTERM) and returns its final status.
    """

    def __init__(self, args: list[str] = (), env: dict[str, str] | None = None,
                 timeout_s: float = 30.0) -> None:
        self.process = subprocess.Popen(
            [sys.executable, "-m", "pisc_plant.virtual_rig", *args], stdin=subprocess.PIPE,
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, bufsize=1)
        self._final: dict[str, Any] | None = None
        line = self._line(timeout_s)
        if not line.startswith("device "):
            err = self.process.stderr.read() if self.process.poll() is not None else ""
            raise RuntimeError(f"pisc_virtual_rig did not start: {line!r} {err}")
        self.device = line.split(" ", 1)[1].strip()

    def _line(self, timeout_s: float) -> str:
        ready, _, _ = select.select([self.process.stdout], [], [], timeout_s)
        if not ready:
            raise TimeoutError(f"pisc_virtual_rig said nothing for {timeout_s} s")
        return self.process.stdout.readline()

    def request(self, **request: Any) -> None:
        self.process.stdin.write(json.dumps(request) + "\n")
        self.process.stdin.flush()

    def status(self, timeout_s: float = 10.0) -> dict[str, Any]:
        self.request(status=True)
        line = self._line(timeout_s)
        reply = json.loads(line)
        if "error" in reply:
            raise ValueError(reply["error"])
        return reply

    def stop(self, timeout_s: float = 10.0) -> dict[str, Any]:
        """End the rig (once; later calls return the same final status)."""
        if self._final is None:
            if self.process.poll() is None:
                self.process.send_signal(signal.SIGTERM)
            out, _ = self.process.communicate(timeout=timeout_s)
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
    args = parser.parse_args(argv)
    try:
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
    rig = Rig(Firmware(plant, state), faults, args.seed, log)

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
