"""The driver's decisions, free of I/O and clocks: frames to SI samples, commands to bytes.

:class:`DriverCore` is what ``driver_node`` calls with the bytes it read, the voltage
commands it received and the time (ROS time, integer nanoseconds) of each event:

* ``receive(data, now)``: parse, convert each frame to SI (SPEC section 4), stamp it
  with its arrival (a backlog that one read completes: a period apart, the newest
  ``now``);
* ``command(stamp, voltage, now)``: the byte answering a frame (SPEC section 4), unless
  the command is older than ``driver.command_max_age_periods`` periods or older than
  one already sent;
* ``tick(now)``: the safety rules between events: zero voltage once the newest command
  sent is older than the allowed age (the controllers stopped answering), a fault once
  the device has sent no frame for ``driver.silence_timeout_s``, and, while a run is
  active, an answer to every frame: when a frame arrives and the one before it got no
  byte, the driver sends one itself (the byte held, which is 0 V once the newest
  command is older than the allowed age), so that the firmware's command watchdog
  (docs/driver-protocol.md) never trips while the driver is alive;
* ``deadline_ns()``: when ``tick`` next acts on its own (the age or the silence rule's
  deadline), until which the node's reader may wait for bytes;
* ``end_run()``: the run is over (the driver stops): no more bytes of its own, so that
  once the driver is gone the firmware's watchdog zeroes the motor;
* ``hold_off(intruders)``: another publisher is on the command topic (the node pins the
  graph's own, :class:`pisc_msgs_py.watchdog.PublisherPin`): every command is 0 V while
  it is there.

The command watchdog shared with the plant (:class:`pisc_msgs_py.watchdog.CommandWatchdog`,
``driver.watchdog_periods``) counts the frames: when ``watchdog_periods`` frames in a row
went unanswered the driver sends 0 V at the next frame's arrival and ``tick`` says so
(``new_trip``), and ``witness`` (:class:`pisc_msgs_py.watchdog.StopWitness`) then
tells the node which stage stopped once it has fallen behind. The age rule above is the
stricter (0 V 10 ms after the newest command's sample, by the clock); the watchdog holds
0 V until a command answers one of the last ``watchdog_periods`` frames.

A run is active from the first command sent until ``end_run()``.
"""

from __future__ import annotations

from dataclasses import dataclass

from pisc_driver.protocol import (
    FrameParser,
    FrameToSi,
    ParserParams,
    encode_command,
    unwrap_count,
)
from pisc_msgs_py.config import any_value, in_range, param
from pisc_msgs_py.watchdog import CommandWatchdog, StopWitness
from pisc_model.params import ActuatorParams, SensorParams

__all__ = ["DriverCore", "DriverParams", "Measurement", "Trip", "ZERO"]

ZERO = 0x00  # the command byte of zero voltage
READS_KEPT = 16  # reads whose times are kept: a frame is confirmed within a few reads


@dataclass(frozen=True)
class DriverParams(ParserParams):
    """Section ``driver``: the serial link and the driver's safety rules."""

    port: str = param("", "serial device of the rig, e.g. /dev/ttyUSB0 or the pseudo-terminal "
                      "pisc_virtual_rig prints", "", any_value)
    baud: int = param(115200, "line speed, 8N1 (SPEC section 4)", "baud",
                      in_range(300, 4_000_000))
    silence_timeout_s: float = param(
        0.015, "no frame for this long (3 periods) is a device fault: report it and send 0 V",
        "s", in_range(0.001, 10.0))
    command_max_age_periods: float = param(
        2.0, "send 0 V when the newest voltage command is older than this many periods",
        "", in_range(0.5, 100.0))
    read_timeout_s: float = param(
        0.05, "longest wait for a byte when no safety rule falls due sooner (the age and "
        "silence rules wake the reader at their deadlines; this bounds how soon it sees a "
        "stop)", "s", in_range(0.0005, 0.1))
    reopen_interval_s: float = param(0.5, "wait between attempts to reopen a port that went "
                                     "away", "s", in_range(0.01, 60.0))
    watchdog_periods: int = param(3, "frames in a row left unanswered after which the driver "
                                  "sends 0 V at the next frame and names the stage of the "
                                  "chain that stopped (the plant's simulation.watchdog_periods)",
                                  "", in_range(1, 1000))
    min_subscribers: int = param(
        0, "publish the rig's samples only once joint_states and the motor current each have "
        "this many subscribers; frames before that are read and dropped (pisc_graph sets the "
        "graph's count, its recorder included, so that the bag holds every sample the driver "
        "publishes; 0 = publish at once)", "", in_range(0, 1000))
    command_node: str = param("current_loop", "the node whose command publisher the driver "
                              "pins; any other publisher on the command topic is a fault, "
                              "with 0 V while it is there", "",
                              lambda v: None if v else "must name a node")

    @property
    def parser(self) -> ParserParams:
        return ParserParams(max_rate_radps=self.max_rate_radps, frame_gap_s=self.frame_gap_s)


@dataclass(frozen=True)
class Trip:
    """The command watchdog tripped at frame ``sample`` (stamp ``stamp_ns``): the newest
    answered one was ``last_answered``."""

    sample: int
    last_answered: int
    stamp_ns: int


@dataclass(frozen=True)
class Measurement:
    """One frame in SI units, stamped with its arrival (ROS time)."""

    stamp_ns: int
    position_m: float
    angle_rad: float
    current_a: float


class DriverCore:
    def __init__(self, params: DriverParams, sensors: SensorParams, actuator: ActuatorParams,
                 period_s: float) -> None:
        self.params = params
        self.sensors = sensors
        self.actuator = actuator
        self.period_ns = round(period_s * 1e9)
        self.max_age_ns = round(params.command_max_age_periods * period_s * 1e9)
        self.silence_ns = round(params.silence_timeout_s * 1e9)
        self.parser = FrameParser(sensors, period_s, params.parser)
        self._to_si = FrameToSi(sensors)
        self._count: int | None = None  # unwrapped encoder count
        self._stamp_ns: int | None = None  # stamp of the newest sample
        self._read_ns: dict[float, int] = {}  # the latest reads' times: seconds -> ns
        self.last_frame_ns: int | None = None
        self.sent_stamp_ns: int | None = None  # stamp of the newest command sent
        self.sent_byte = ZERO
        self.silent = False
        self.active = False  # a run: from the first command sent to end_run()
        self._frames = 0  # frames received
        self._answered = 0  # frames received when the last byte was sent
        self.commands = 0
        self.stale_commands = 0
        self.zeroed = 0  # zero bytes sent because the commands stopped
        self.keepalives = 0  # bytes sent for a frame the controllers did not answer
        self.silences = 0
        self.watchdog = CommandWatchdog(params.watchdog_periods)
        self.witness = StopWitness()  # after a trip: which stage stopped
        self.new_trip: Trip | None = None  # the trip the last tick reported
        self._trip: Trip | None = None  # a trip to report at the next tick
        self.resumed_from: int | None = None  # a trip the last command ended (its sample)
        self.answered_stamp_ns: int | None = None  # stamp of the newest answered frame
        self.intruders: tuple[str, ...] = ()
        self.refused_commands = 0  # commands sent as 0 V while another publisher was there
        self.second_answers = 0  # commands answering a sample already answered (dropped)

    def receive(self, data: bytes, now_ns: int) -> list[Measurement]:
        """Bytes read at ``now_ns`` -> the samples they completed, each stamped with its
        arrival.

        A frame whose bytes all came in an earlier read (it waited for the byte that
        confirmed it) is stamped with that read's time. Frames whose last byte came in
        this read are stamped ``now_ns``, except a backlog: when one read completes
        several frames, the reader was late and the device sent them a period apart, so
        each is stamped a period before the one after it (the newest ``now_ns``). Then an
        answer to a frame that waited in the port is as old as that frame is, and the age
        rule (``command``) refuses it: a stall of the reader no longer sends the rig
        voltages computed from states up to the stall's length old (a soak
        under load: after a 178 ms stall the rig got -6.7 .. -4.5 V towards the end stop
        for 8 ms, answers to frames 170-145 ms old), nor makes the newest frame's answer
        look no fresher than theirs. A stamp keys a control cycle, so it is unique
        and increasing: at least 1 us after the one before.
        """
        out = []
        now_s = now_ns * 1e-9
        frames = self.parser.feed(data, now_s)
        for k, frame in enumerate(frames):
            self._count = (frame.count if self._count is None
                           else unwrap_count(self._count, frame.count))
            x, theta, current = self._to_si(frame, self._count)
            if frame.arrival_s is not None and frame.arrival_s < now_s:
                arrival = self._read_ns.get(frame.arrival_s, now_ns)
            else:  # completed by this read: a period before each frame after it
                arrival = now_ns - (len(frames) - 1 - k) * self.period_ns
            stamp = arrival if self._stamp_ns is None else max(arrival, self._stamp_ns + 1000)
            self._stamp_ns = stamp
            index = self._frames + len(out)
            self.watchdog.sample(index, stamp)
            self.witness.sample(index, stamp)
            if (self.watchdog.expired(index) and self.watchdog.tripped_at == index
                    and not self.intruders):  # (while they are there all is 0 V anyway)
                self._trip = Trip(index, self.watchdog.answered, stamp)
                self.witness.trip(index, self.watchdog.answered)
            out.append(Measurement(stamp, x, theta, current))
        self._read_ns[now_s] = now_ns  # for frames this read begins and a later one ends
        while len(self._read_ns) > READS_KEPT:
            del self._read_ns[next(iter(self._read_ns))]
        if out:
            self.last_frame_ns = now_ns
            self.silent = False
            self._frames += len(out)
        return out

    @property
    def newest_stamp_ns(self) -> int:
        """The stamp of the newest sample (-1 before the first)."""
        return -1 if self._stamp_ns is None else self._stamp_ns

    def command(self, stamp_ns: int, voltage_v: float, now_ns: int,
                refused: bool = False) -> int | None:
        """The byte to send for a voltage answering the sample ``stamp_ns``, or None;
        ``refused``: the node's publisher pin did not admit the message (0 V is sent)."""
        if (now_ns - stamp_ns > self.max_age_ns
                or (self.sent_stamp_ns is not None and stamp_ns < self.sent_stamp_ns)):
            self.stale_commands += 1
            return None
        if stamp_ns == self.sent_stamp_ns:  # one answer per sample, the first: the
            self.second_answers += 1  # graph's current loop answers each sample once
            return None
        self.sent_stamp_ns = stamp_ns
        if self.intruders or refused:
            self.refused_commands += 1
            self.sent_byte = ZERO
        else:
            self.sent_byte = encode_command(voltage_v, self.actuator)
            answers = self.watchdog.fresh(stamp_ns)
            if answers is not None:
                self.resumed_from = self.watchdog.answer(answers)
                self.answered_stamp_ns = stamp_ns
                if self.resumed_from is not None:
                    self.witness.resumed()
        self.commands += 1
        self.active = True
        self._answered = self._frames
        return self.sent_byte

    def hold_off(self, intruders: tuple[str, ...]) -> int | None:
        """Other publishers on the command topic (``()``: they have gone). While there
        are any, every command is sent as 0 V; returns the byte to send now (0 V when
        they appear)."""
        self.intruders = intruders
        if not intruders:
            return None
        self.sent_byte = ZERO
        self._answered = self._frames
        return ZERO

    def deadline_ns(self) -> int | None:
        """The earliest time at which :meth:`tick` acts with no new frame or command: the
        age rule zeroes the newest command, or the silence rule reports a silent device
        (a trip waiting to be reported: at once); None when it never does. Right after
        ``tick(now)`` it is None or later than ``now``. The reader waits for bytes until
        then: with frames every period and commands answering them it wakes once a frame,
        not also every ``read_timeout_s``."""
        if self._trip is not None:
            return 0
        due = None
        if self.sent_byte != ZERO:
            due = 0 if self.sent_stamp_ns is None else self.sent_stamp_ns + self.max_age_ns + 1
        if not self.silent and self.last_frame_ns is not None:
            quiet = self.last_frame_ns + self.silence_ns + 1
            due = quiet if due is None else min(due, quiet)
        return due

    def command_age_ns(self, now_ns: int) -> int | None:
        return None if self.sent_stamp_ns is None else now_ns - self.sent_stamp_ns

    def end_run(self) -> None:
        """The run is over: the driver sends no byte of its own any more."""
        self.active = False

    def tick(self, now_ns: int) -> tuple[int | None, str | None]:
        """(byte to send or None, fault message or None) at ``now_ns``: 0 V for a stale
        command or a silent device, or, in a run, the answer to a frame left unanswered."""
        byte = None
        if self.sent_byte != ZERO and (self.sent_stamp_ns is None
                                       or now_ns - self.sent_stamp_ns > self.max_age_ns):
            byte = self.sent_byte = ZERO
            self.zeroed += 1
        fault = None
        self.new_trip, trip, self._trip = self._trip, self._trip, None
        if trip is not None:
            index, answered = trip.sample, trip.last_answered
            if self.sent_byte != ZERO:  # (the age rule has mostly zeroed it already)
                byte = self.sent_byte = ZERO
            fault = (f"command watchdog: no command answered samples {answered + 1} .. "
                     f"{index}: 0 V from sample {index}")
        if (not self.silent and self.last_frame_ns is not None
                and now_ns - self.last_frame_ns > self.silence_ns):
            self.silent = True
            self.silences += 1
            silent_ms = (now_ns - self.last_frame_ns) * 1e-6
            fault = (f"device silent: no frame for {silent_ms:.1f} ms (driver.silence_timeout_s "
                     f"= {self.params.silence_timeout_s}); sending 0 V")
            if byte is None:
                byte = self.sent_byte = ZERO
        if byte is not None:
            self._answered = self._frames
        elif self.active and self._answered < self._frames - 1:
            # the frame before the newest got no byte: answer it (the newest one is the
            # controllers' to answer until the next frame comes)
            byte = self.sent_byte
            self.keepalives += 1
            self._answered = self._frames - 1
        return byte, fault
