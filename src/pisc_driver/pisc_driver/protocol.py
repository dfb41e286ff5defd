"""The PIC16F877A rig's serial protocol as bytes <-> values (SPEC section 4). No I/O, no clock.

Device to host, every 5 ms period, 7 bytes, big-endian::

    0xAA, IR_hi, IR_lo, CUR_hi, CUR_lo, CNT_hi, CNT_lo

two 10-bit ADC codes (infrared position sensor, ACS712 current sensor) and the signed
16-bit encoder count. Host to device, one byte: bit 7 = direction (1 = negative
voltage), bits 0-6 = magnitude ``round(|u| * 127 / 11.47)``; the firmware sets an
8-bit PWM duty of ``magnitude << 1``.

There is no checksum and 0xAA occurs inside data (an ADC low byte, either encoder byte),
so a parser that waits for 0xAA and takes six bytes accepts false frames whenever a byte
is lost. :class:`FrameParser` hunts for lock on the 7-byte periodicity and on what the
sensors can physically report, stays locked while every frame passes the checks,
delivers each frame when its 7th byte arrives, and hunts again when a check fails.

The bytes alone are ambiguous: a stream read from a shifted start can itself be a stream
of plausible frames (a count resting at 0x00AA with ADC low bytes 0xAA). What
settles it is time: the device sends a frame's seven bytes in 0.61 ms every 5 ms, so a
frame whose bytes arrived more than ``frame_gap_s`` apart is two frames' pieces. The
driver passes each read's arrival time; see docs/driver-protocol.md.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field

import numpy as np

from pisc_msgs_py.config import in_range, param, positive
from pisc_model import sensors
from pisc_model.params import ActuatorParams, SensorParams

__all__ = [
    "FRAME_LENGTH",
    "HEADER",
    "Frame",
    "FrameParser",
    "FrameToSi",
    "NaiveParser",
    "ParserParams",
    "ProtocolError",
    "command_voltage",
    "decode_frame",
    "encode_command",
    "encode_frame",
    "frame_to_si",
    "pwm_duty",
    "unwrap_count",
    "wrap_count",
]

HEADER = 0xAA
FRAME_LENGTH = 7
_FRAME = struct.Struct(">BHHh")
_NEGATIVE = 0x80
_MAGNITUDE = 0x7F


class ProtocolError(ValueError):
    """Bytes or values that the rig's protocol cannot carry."""


@dataclass(frozen=True)
class Frame:
    """One device frame: raw ADC codes and the encoder count as the PIC sends them.

    ``offset`` is the position of the frame's header in the byte stream the parser
    was fed (for diagnostics and the benchmark); it takes no part in equality.
    """

    ir_code: int
    current_code: int
    count: int  # signed 16-bit, wraps every 65536 counts
    offset: int = field(default=-1, compare=False)
    # arrival of the frame's last byte as fed to :meth:`FrameParser.feed` (None: not given)
    arrival_s: float | None = field(default=None, compare=False)


def wrap_count(count: int) -> int:
    """An encoder count as the PIC's signed 16-bit register holds it."""
    return ((int(count) + 0x8000) & 0xFFFF) - 0x8000


def unwrap_count(previous: int, raw: int) -> int:
    """Continue an unwrapped count with the next 16-bit reading (the nearest turn).

    65536 counts are 16.384 revolutions, not a whole number: without unwrapping the
    angle would jump by 0.384 of a turn at each wrap of the register.
    """
    return previous + wrap_count(raw - previous)


def encode_frame(frame: Frame) -> bytes:
    """The 7 bytes the PIC sends for a frame."""
    for name, code in (("ir_code", frame.ir_code), ("current_code", frame.current_code)):
        if not 0 <= code <= 0x3FF:
            raise ProtocolError(f"{name} = {code} is not a 10-bit ADC code (0..1023)")
    if not -0x8000 <= frame.count <= 0x7FFF:
        raise ProtocolError(f"count = {frame.count} does not fit the signed 16-bit register")
    return _FRAME.pack(HEADER, frame.ir_code, frame.current_code, frame.count)


def decode_frame(data: bytes | bytearray | memoryview, offset: int = -1) -> Frame:
    """A frame from exactly 7 bytes starting with the header (no plausibility checks)."""
    if len(data) != FRAME_LENGTH:
        raise ProtocolError(f"a frame is {FRAME_LENGTH} bytes, got {len(data)}")
    header, ir_code, current_code, count = _FRAME.unpack(bytes(data))
    if header != HEADER:
        raise ProtocolError(f"frame header is 0x{header:02X}, expected 0x{HEADER:02X}")
    return Frame(ir_code, current_code, count, offset)


def _check_actuator(actuator: ActuatorParams) -> None:
    if not 1 <= actuator.command_levels <= _MAGNITUDE:
        raise ProtocolError(
            f"actuator.command_levels = {actuator.command_levels}: the command byte carries "
            f"magnitudes 1..{_MAGNITUDE} only")


def encode_command(voltage_v: float, actuator: ActuatorParams = ActuatorParams()) -> int:
    """The command byte for an armature voltage (SPEC section 4).

    ``magnitude = round(|u| * 127 / 11.47)`` (half away from zero) saturated at 127,
    bit 7 set for a negative voltage. A voltage that rounds to magnitude 0 is the byte
    0x00 whatever its sign, so "zero voltage" has one byte.

    The arithmetic of ``ActuatorParams.magnitude`` on one float, without numpy (the
    driver encodes a command a period; test_protocol pins the two equal).
    """
    if not math.isfinite(voltage_v):
        raise ProtocolError(f"voltage command {voltage_v} is not finite")
    _check_actuator(actuator)
    magnitude = min(math.floor(abs(voltage_v) / actuator.step_v + 0.5),
                    actuator.command_levels)
    if magnitude == 0:
        return 0
    return (_NEGATIVE if voltage_v < 0.0 else 0) | magnitude


def pwm_duty(command: int) -> tuple[int, bool]:
    """What the firmware does with a command byte: (8-bit PWM duty, negative direction).

    ``duty = magnitude << 1`` (SPEC section 4).
    """
    if not 0 <= command <= 0xFF:
        raise ProtocolError(f"command byte {command} is not a byte")
    return (command & _MAGNITUDE) << 1, bool(command & _NEGATIVE)


def command_voltage(command: int, actuator: ActuatorParams = ActuatorParams()) -> float:
    """Armature voltage the bridge applies for a command byte.

    The largest duty, 254 (magnitude 127), gives ``actuator.full_scale_v`` (11.47 V:
    the 12.27 V supply less the bridge's 0.8 V drop), and the voltage is proportional
    to the duty: ``u = +-full_scale * duty / (2 * levels)``.
    """
    _check_actuator(actuator)
    duty, negative = pwm_duty(command)
    if duty > 2 * actuator.command_levels:
        duty = 2 * actuator.command_levels
    voltage = actuator.full_scale_v * duty / (2 * actuator.command_levels)
    return -voltage if negative else voltage


def frame_to_si(s: SensorParams, frame: Frame, count: int | None = None
                ) -> tuple[float, float, float]:
    """(x [m], theta [rad], i [A]) with the C++ program's conversions (SPEC section 4).

    ``count`` is the unwrapped count (:func:`unwrap_count`); by default the frame's own.
    """
    x, theta, current = sensors.decode(
        s, frame.ir_code, frame.current_code, frame.count if count is None else count)
    return float(x), float(theta), float(current)


class FrameToSi:
    """:func:`frame_to_si` for one set of sensor parameters, by table look-up.

    The ADC codes are 10 bits, so the position and the current of every code are
    computed once, with :mod:`pisc_model.sensors`' own functions (numpy), when this is
    made; a frame then costs two list look-ups and one multiply-add for the angle, the
    same operations :func:`pisc_model.sensors.encoder_angle` does. The results equal
    :func:`frame_to_si`'s bit for bit (test_protocol, every code). The driver converts
    a frame every period: numpy's per-call cost on four scalars was the larger part of
    its own work per frame (docs/soak.md). A code beyond the ADC's levels
    (``sensors.adc_bits`` below 10) goes to :func:`frame_to_si`.
    """

    def __init__(self, s: SensorParams) -> None:
        self.sensors = s
        codes = np.arange(s.adc_levels)
        with np.errstate(divide="ignore", invalid="ignore"):  # (as frame_to_si gives them)
            x = sensors.ir_position(s, sensors.adc_voltage(s, codes))
            current = sensors.current_from_voltage(s, sensors.adc_voltage(s, codes))
        self._x: list[float] = x.tolist()
        self._current: list[float] = current.tolist()
        self._rad_per_count = s.encoder_rad_per_count
        self._zero_rad = s.encoder_zero_rad

    def __call__(self, frame: Frame, count: int | None = None) -> tuple[float, float, float]:
        """(x [m], theta [rad], i [A]) of ``frame``; ``count`` as for :func:`frame_to_si`."""
        n = len(self._x)
        if not (0 <= frame.ir_code < n and 0 <= frame.current_code < n):
            return frame_to_si(self.sensors, frame, count)
        c = frame.count if count is None else count
        return (self._x[frame.ir_code], float(c) * self._rad_per_count + self._zero_rad,
                self._current[frame.current_code])


@dataclass(frozen=True)
class ParserParams:
    """Plausibility bounds of the lock-hunting parser (section ``driver``)."""

    max_rate_radps: float = param(
        50.0, "largest pendulum rate the encoder can report between two frames: the pendulum "
        "falling from upright reaches 18 rad/s at the bottom (2 sqrt(m g l / (I + m l^2))); "
        "a larger change of count means a misframed or corrupted frame", "rad/s", positive)
    frame_gap_s: float = param(
        0.002, "a frame's bytes take 0.61 ms at 115200 baud and frames come 5 ms apart; a "
        "frame whose last byte arrived more than this after its header is pieces of two "
        "frames (a byte was lost) and is refused (0 = do not use arrival times: bytes only, "
        "which cannot refuse every false frame)", "s", in_range(0.0, 1.0))


class FrameParser:
    """Lock-hunting parser of the device's byte stream.

    Hunting: a 0xAA is taken as a header when the frame it starts is plausible (both ADC
    high bytes at most ``(2^bits - 1) >> 8`` = 3) and is confirmed either by another 0xAA
    exactly 7 bytes later followed by plausible ADC high bytes (they come in the same
    burst) or, when arrival times are known, by starting a burst (no byte for
    ``frame_gap_s`` before it) and arriving whole within that burst.
    Locked: each frame is checked and delivered as soon as its 7th byte arrives: header,
    ADC high bytes, encoder change since the last frame at most ``max_rate * period /
    rad_per_count`` counts per period, and the next frame's header and ADC high bytes as
    far as they are already here. A failed check drops the frame and hunts again from the
    byte after its header.
    With arrival times, hunting or locked, a frame whose first and last bytes arrived more
    than ``frame_gap_s`` apart is refused, whatever its bytes: it is the end of one burst
    and the start of the next (locked, a frame whose last byte came 5 ms later
    was accepted unless that byte was 0xAA). A reader that stalls for more than
    ``frame_gap_s`` in the middle of a frame costs that frame, never a false one.

    Parameters
    ----------
    sensors
        ADC resolution and encoder counts per revolution.
    period_s
        The device's frame period.
    params
        Plausibility bounds.
    """

    def __init__(self, sensors_params: SensorParams = SensorParams(), period_s: float = 0.005,
                 params: ParserParams = ParserParams()) -> None:
        self.max_adc_high = (sensors_params.adc_levels - 1) >> 8
        self.max_count_step = max(1, math.ceil(
            params.max_rate_radps * period_s / sensors_params.encoder_rad_per_count))
        self.period_s = period_s
        self.gap_s = params.frame_gap_s
        self._buf = bytearray()
        self._times: list[float | None] = []
        self._base = 0  # stream offset of _buf[0]
        self._prev_time: float | None = None  # arrival of the byte before _buf[0]
        self._locked = False
        self._last_count: int | None = None
        self._last_time: float | None = None
        self._last_offset = 0
        self.frames = 0
        self.discarded = 0
        self.rehunts = 0

    @property
    def locked(self) -> bool:
        return self._locked

    def feed(self, data: bytes | bytearray, time_s: float | None = None) -> list[Frame]:
        """Bytes as they arrived (``time_s``: their arrival, any monotonic clock) -> frames."""
        self._buf += data
        self._times += [time_s] * len(data)
        out: list[Frame] = []
        while True:
            if self._locked:
                if len(self._buf) < FRAME_LENGTH:
                    break
                if self._locked_ok():
                    out.append(self._take(0))
                else:
                    self._locked = False
                    self.rehunts += 1
                    self._drop(1)
            else:
                start = self._hunt()
                if start is None:
                    break
                out.append(self._take(start))
                self._locked = True
        return out

    # -- checks ------------------------------------------------------------------------

    def _plausible(self, p: int) -> bool:
        b = self._buf
        return b[p] == HEADER and b[p + 1] <= self.max_adc_high and b[p + 3] <= self.max_adc_high

    def _count_ok(self, p: int) -> bool:
        if self._last_count is None:
            return True
        count = wrap_count((self._buf[p + 5] << 8) | self._buf[p + 6])
        # no arrival times: frames elapsed from the stream positions
        periods = self._periods(self._last_time, self._times[p], -(
            -(self._base + p - self._last_offset) // FRAME_LENGTH))
        return abs(wrap_count(count - self._last_count)) <= self.max_count_step * periods

    def _periods(self, earlier: float | None, later: float | None, otherwise: int) -> int:
        """Frame periods between two arrivals (at least 1), ``otherwise`` without times."""
        if earlier is not None and later is not None:
            return max(1, round((later - earlier) / self.period_s))
        return max(1, otherwise)

    def _spans_gap(self, p: int) -> bool:
        """The candidate's bytes came in two bursts (its first byte more than ``frame_gap_s``
        before its last), so it is not a frame: a byte was lost and the rest of it belongs
        to the next frame. The device sends a frame's seven bytes in 0.61 ms and the next
        frame 5 ms later."""
        t0, t6 = self._times[p], self._times[p + FRAME_LENGTH - 1]
        return bool(self.gap_s) and t0 is not None and t6 is not None and t6 - t0 > self.gap_s

    def _follower_ok(self, p: int) -> bool:
        """The frame after the one at ``p``, as far as its bytes are already here: its
        header and ADC high bytes. (Not its count: a jump between two frames does not say
        which of them is damaged.)"""
        b = self._buf
        n = len(b)
        q = p + FRAME_LENGTH
        return not ((q < n and b[q] != HEADER)
                    or (q + 1 < n and b[q + 1] > self.max_adc_high)
                    or (q + 3 < n and b[q + 3] > self.max_adc_high))

    def _locked_ok(self) -> bool:
        return (self._plausible(0) and self._count_ok(0) and not self._spans_gap(0)
                and self._follower_ok(0))

    def _starts_burst(self, p: int) -> bool:
        t = self._times[p]
        before = self._times[p - 1] if p > 0 else self._prev_time
        return (self.gap_s > 0 and t is not None and before is not None
                and t - before > self.gap_s)

    def _hunt(self) -> int | None:
        """Index of a confirmed header in the buffer (bytes before it are discarded)."""
        b = self._buf
        n = len(b)
        p = 0
        while p + FRAME_LENGTH <= n:
            if b[p] == HEADER and self._plausible(p):
                t_end = self._times[p + FRAME_LENGTH - 1]
                q = p + FRAME_LENGTH  # the confirming header and its ADC high bytes
                if q + 3 < n:
                    confirmed = (b[q] == HEADER and b[q + 1] <= self.max_adc_high
                                 and b[q + 3] <= self.max_adc_high and not self._spans_gap(p))
                elif self._starts_burst(p) and t_end is not None:
                    t0 = self._times[p]
                    confirmed = t0 is not None and t_end - t0 <= self.gap_s
                else:
                    break  # wait for the byte that confirms or refutes this candidate
                if confirmed and self._count_ok(p):
                    self._drop(p)
                    return 0
            p += 1
        self._drop(p)
        return None

    # -- buffer ------------------------------------------------------------------------

    def _take(self, p: int) -> Frame:
        # (the checks before _take found its header; decode_frame's own checks are theirs)
        _, ir_code, current_code, count = _FRAME.unpack_from(self._buf, p)
        frame = Frame(ir_code, current_code, count, self._base + p,
                      self._times[p + FRAME_LENGTH - 1])
        self._last_count = frame.count
        self._last_time = self._times[p]
        self._last_offset = frame.offset
        self.frames += 1
        self._drop(p + FRAME_LENGTH, discard=False)
        return frame

    def _drop(self, n: int, discard: bool = True) -> None:
        if n <= 0:
            return
        if discard:
            self.discarded += n
        self._prev_time = self._times[n - 1]
        del self._buf[:n]
        del self._times[:n]
        self._base += n


class NaiveParser:
    """The parser the protocol invites: wait for 0xAA, take the next six bytes.

    Kept as the benchmark's reference (``pisc_parser_bench``), not for use.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self._base = 0
        self.frames = 0
        self.discarded = 0

    def feed(self, data: bytes | bytearray, time_s: float | None = None) -> list[Frame]:
        self._buf += data
        out = []
        while True:
            p = self._buf.find(HEADER)
            if p < 0:
                self.discarded += len(self._buf)
                self._base += len(self._buf)
                self._buf.clear()
                break
            if len(self._buf) - p < FRAME_LENGTH:
                self.discarded += p
                self._base += p
                del self._buf[:p]
                break
            out.append(decode_frame(self._buf[p:p + FRAME_LENGTH], self._base + p))
            self.frames += 1
            self.discarded += p
            self._base += p + FRAME_LENGTH
            del self._buf[:p + FRAME_LENGTH]
        return out

