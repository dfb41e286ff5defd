"""Driver node: the rig's serial link on the graph's topics, a drop-in for the plant node.

A reader thread blocks on the port (it releases the interpreter lock while it waits) and
publishes each frame's sample the moment the frame's last byte arrives, stamped with its
arrival; the voltage answering it is written from the subscription callback as soon as
it arrives. The executor spins in the main thread (``run_node``). Every decision is
:class:`pisc_driver.driver.DriverCore`'s; this file does I/O and ROS only.

From the first command sent until the node stops, every frame is answered: a frame the
controllers leave unanswered gets the byte held (0 V once the newest command is stale)
when the next frame arrives, so the firmware's command watchdog trips only when this
process is gone or stalled (docs/driver-protocol.md). On stopping (SIGINT, SIGTERM, a
parameter change) it sends 0 V and then nothing. Each byte written while it runs is
published on ``/pisc/motor/voltage_sent`` right after the write (the voltage it encodes,
whether it answers a sample or is the driver's own hold or 0 V), so a bag keeps what the
rig was sent and when.

The same guards as the plant (docs/safety.md, :mod:`pisc_msgs_py.watchdog`): the command
publisher of ``driver.command_node`` is pinned when first seen, and while any other
publisher is matched on the command topic every command is sent as 0 V and
``/diagnostics`` names it (checked on every command and at every frame); when
``driver.watchdog_periods`` frames in a row went unanswered the driver sends 0 V and names
the stage of the chain that stopped (it watches the estimator's and the supervisor's
outputs for that).
"""

from __future__ import annotations

import threading
import time
from typing import Any

from pisc_driver.driver import ZERO, DriverCore, DriverParams
from pisc_driver.protocol import command_voltage
from pisc_driver.link import LinkError, SerialLink
from pisc_msgs_py.base_node import ERROR, OK, WARN, PiscNode, run_node
from pisc_msgs_py.convert import (
    joint_sample_to_cdr,
    motor_sample_from_msg,
    motor_sample_to_cdr,
)
from pisc_msgs_py.topics import JOINT_STATES, MOTOR_CURRENT, VOLTAGE, VOLTAGE_SENT
from pisc_msgs_py.types import JointSample, MotorSample
from pisc_msgs_py.watchdog import (
    CHAIN,
    PublisherPin,
    listed_publishers,
    named_trip,
    who_publishes,
)
from pisc_model.params import ActuatorParams, LoopParams, SensorParams

# The command publisher is looked at on every command, by the reader at every frame, and
# every PIN_LOOK_S besides (while no frame comes). A timer each period woke the executor's
# and rclpy's timer threads 200 times a second for it: about 2.5 % of a core in a 15 s
# per-thread sample (docs/soak.md).
PIN_LOOK_S = 0.1

SECTIONS = {"driver": DriverParams, "sensors": SensorParams, "actuator": ActuatorParams,
            "loop": LoopParams}


class DriverNode(PiscNode):
    def __init__(self, **kwargs: Any) -> None:
        super().__init__("driver", SECTIONS, **kwargs)
        self._lock = threading.Lock()  # the core and the port, shared with the reader
        self._joint_pub = self.publisher(JOINT_STATES)
        self._current_pub = self.publisher(MOTOR_CURRENT)
        self._sent_pub = self.publisher(VOLTAGE_SENT)  # each byte as it is written
        # pinned by the driver itself (_check_publishers): 0 V while another one is there
        self._sub = self.subscription(VOLTAGE, self._on_voltage, motor_sample_from_msg,
                                      "voltage command", WARN, guarded=False)
        # newest stamp out of each stage of the chain, to say which one stopped
        self._upstream = self.newest_stamps(CHAIN)
        self._pin = PublisherPin(self.config.params.command_node)
        self._pin_lock = threading.Lock()  # the pin: the executor's thread and the reader
        self._pin_timer = self.create_timer(PIN_LOOK_S, self._check_publishers)
        self._reader: threading.Thread | None = None
        self._running = False
        self._wake_ns = 0  # when the reader's wait for bytes ends at the latest (ROS time)
        self._unwritten = 0  # command bytes the port did not take
        self._ready = False  # the graph's subscribers are there (driver.min_subscribers)
        self.dropped_before_ready = 0  # frames read before then, not published
        self._start(self.config)  # a missing or busy port raises LinkError here

    def build(self, flat: dict[str, Any]) -> DriverCore:
        driver, sensors, actuator, loop = (self.section(flat, s) for s in SECTIONS)
        return DriverCore(driver, sensors, actuator, loop.period_s)

    # -- life cycle ----------------------------------------------------------------------

    def _start(self, core: DriverCore, must_open: bool = True) -> None:
        """Open the port and start the reader; ``must_open=False`` leaves a port that
        cannot be opened to the reader, which retries it."""
        p = core.params
        if p.command_node != self._pin.owner:
            self._pin = PublisherPin(p.command_node)
        core.intruders = self._pin.intruders  # (after a parameter change: still there)
        self._core = core
        self._link = SerialLink(p.port, p.baud, p.read_timeout_s)
        try:
            self._link.open()
            self.diagnose(OK, f"opened {p.port} at {p.baud} baud")
        except LinkError as exc:
            if must_open:
                raise
            self.diagnose(ERROR, f"{exc}; retrying every {p.reopen_interval_s} s")
        self._running = True
        self._reader = threading.Thread(target=self._read_loop, name="pisc_driver_reader",
                                        daemon=True)
        self._reader.start()

    def _stop(self) -> None:
        """End the run, stop the reader, send zero voltage, close the port; from here on
        the driver sends nothing, and the firmware's watchdog holds 0 V."""
        with self._lock:
            self._core.end_run()
        self._running = False
        with self._lock:
            self._link.wake()
        if self._reader is not None:
            self._reader.join(timeout=1.0)
            self._reader = None
        if self.context.ok():  # (a signal has shut it down already: nothing to say it on)
            self._name_the_stopped_stage(force=True)
        with self._lock:
            self._send(ZERO)
            self._link.close()

    def on_config(self, config: Any) -> None:
        self._stop()
        self.diagnose(WARN, "parameters changed: sent 0 V, reopening the port")
        self.config = config
        self._start(config, must_open=False)

    def destroy_node(self) -> None:
        self._stop()
        super().destroy_node()

    # -- I/O -----------------------------------------------------------------------------

    def _now_ns(self) -> int:
        return self.get_clock().now().nanoseconds

    def _send(self, byte: int) -> bool:
        """Write a command byte (under the lock); whether the port took it. The reader
        alone closes a failed port."""
        if self._link.is_open:
            try:
                if self._link.write(byte):
                    return True
                self._unwritten += 1
            except LinkError:
                self._unwritten += 1  # the reader finds the port gone and reports it
        return False

    def _sent(self, stamp_ns: int, byte: int, origin: str) -> None:
        """Say on VOLTAGE_SENT that ``byte`` was written just now (outside the lock: the
        write is not delayed by it, and its publish time is the write's to within the
        call)."""
        self._sent_pub.publish(motor_sample_to_cdr(
            MotorSample(stamp_ns, command_voltage(byte, self._core.actuator)), origin))

    def _on_voltage(self, command: MotorSample) -> None:
        with self._pin_lock:
            self._look_at_publishers()
            admitted = self._pin.admits(command.stamp_ns)
        with self._lock:
            core = self._core
            byte = core.command(command.stamp_ns, command.value, self._now_ns(),
                                refused=not admitted)
            written = byte is not None and self._send(byte)
            resumed, core.resumed_from = core.resumed_from, None
            due = core.deadline_ns()
            if due is not None and due < self._wake_ns:  # (a first command after 0 V:
                self._link.wake()  # the age rule's deadline comes before the reader's)
        if written:
            self._sent(command.stamp_ns, byte, "answer")
        if resumed is not None:
            self.diagnose(OK, f"command watchdog: commands resumed at sample "
                          f"{core.watchdog.answered} (0 V from sample {resumed})",
                          command.stamp_ns)

    def _check_publishers(self) -> None:
        """Pin the graph's command publisher; 0 V and a fault while any other one is
        matched (on every command, at every frame and every PIN_LOOK_S; from the
        executor's thread and the reader's)."""
        with self._pin_lock:
            self._look_at_publishers()

    def _look_at_publishers(self) -> None:  # (holding the pin's lock)
        matched = self._sub.get_publisher_count()
        if not self._pin.needs_look(matched):
            return
        with self._lock:
            newest_ns = self._core.newest_stamp_ns
        change = self._pin.look(matched, listed_publishers(self, VOLTAGE.name), newest_ns)
        if change is None:
            return
        now = self._now_ns()
        with self._lock:
            byte = self._core.hold_off(self._pin.intruders)
            written = byte is not None and self._send(byte)
            newest = self._core.newest_stamp_ns
        if written and newest >= 0:
            self._sent(newest, byte, "zero")
        if change.intruders:
            intruders = ", ".join(change.intruders)
            self._report(ERROR, f"another publisher on {VOLTAGE.name}: {intruders}; the "
                         f"driver sends 0 V while it is there (only "
                         f"/{self._pin.owner}, pinned at the start, drives the motor)", now,
                         intruders=intruders, applied_v=0.0)
        else:
            self._report(OK, f"{', '.join(change.left)} left {VOLTAGE.name}: commands "
                         "apply again", now)

    def _name_the_stopped_stage(self, force: bool = False) -> None:
        """After a trip, once the evidence is in (``force``: now), the stage that
        stopped, on /diagnostics with the trip's stamp and values."""
        core = self._core
        with self._lock:
            if core.witness.pending is None:  # no trip to name a stage for
                return
            answered = -1 if core.answered_stamp_ns is None else core.answered_stamp_ns
            verdict = core.witness.verdict(self._upstream.read(), answered, force=force)
        if verdict is None:
            return
        who = who_publishes(self, verdict.topic or VOLTAGE)
        self._report(
            ERROR, named_trip(verdict, who, VOLTAGE), verdict.trip_stamp_ns,
            sample=verdict.trip, last_answered_sample=verdict.last_answered, applied_v=0.0,
            silent=who, behind=verdict.behind, sure=verdict.sure,
            last_answered_stamp_ns=answered)

    def _read_loop(self) -> None:
        """Read bytes, publish the frames, apply the safety rules. The wait for bytes
        ends at the next frame, at the core's next deadline (``DriverCore.deadline_ns``;
        :meth:`_on_voltage` wakes the reader when a command sets one sooner) or after
        ``driver.read_timeout_s``: once a frame when the graph answers every frame."""
        core = self._core
        link = self._link
        longest_ns = round(core.params.read_timeout_s * 1e9)
        with self._lock:
            self._wake_ns = self._now_ns() + longest_ns
        wait_s = core.params.read_timeout_s
        while self._running and self.context.ok():
            try:
                if not link.is_open:
                    time.sleep(core.params.reopen_interval_s)
                    link.open()
                    self.diagnose(OK, f"{link.port} reopened", port=link.port, link="reopened")
                data = link.read(wait_s)
                now = self._now_ns()
                with self._lock:
                    samples = core.receive(data, now) if data else []
                    byte, fault = core.tick(now)
                    written = byte is not None and self._send(byte)
                    trip = core.new_trip
                    newest = core.newest_stamp_ns
                    due = core.deadline_ns()  # (after tick: None or later than now)
                    self._wake_ns = now + longest_ns if due is None else min(
                        due, now + longest_ns)
                wait_s = (self._wake_ns - now) * 1e-9
                if samples and not self._subscribers_ready():
                    self.dropped_before_ready += len(samples)
                    samples = []
                for s in samples:
                    self._joint_pub.publish(joint_sample_to_cdr(
                        JointSample(s.stamp_ns, s.position_m, s.angle_rad)))
                    self._current_pub.publish(motor_sample_to_cdr(
                        MotorSample(s.stamp_ns, s.current_a)))
                    if self.routine_diagnostics(core.parser.frames):  # once a second
                        # (names the port: a recorder started with this process may
                        # have missed the "opened" status of its start)
                        self._report(OK, f"link up on {link.port}", now)
                if written and newest >= 0:  # (after the samples: they start a cycle)
                    self._sent(newest, byte, "zero" if byte == ZERO else "hold")
                if samples:  # a period: who publishes commands (cheap unless it changed)
                    self._check_publishers()
                if trip is not None:
                    self._report(ERROR, f"{fault} (the stage that stopped is named when it "
                                 "has fallen behind)", trip.stamp_ns, sample=trip.sample,
                                 last_answered_sample=trip.last_answered, applied_v=0.0,
                                 last_answered_stamp_ns=core.answered_stamp_ns)
                elif fault:
                    self._report(ERROR, fault, now)
                if samples and core.witness.pending is not None:
                    self._name_the_stopped_stage()
            except LinkError as exc:
                with self._lock:
                    link.close()
                    core.silent = False  # report silence again after the port comes back
                # (``link``: pisc_graph ends a run whose port stays gone, naming it)
                self._report(ERROR, f"{exc}; retrying every {core.params.reopen_interval_s} s",
                             self._now_ns(), port=link.port, link="lost")
            except Exception as exc:  # a bug must not leave the motor driven
                with self._lock:
                    self._send(ZERO)
                if not self.context.ok():
                    return  # shutting down: the publishers are gone, _stop closes the port
                self._report(ERROR, f"driver fault: {exc!r}; sent 0 V", self._now_ns())
                time.sleep(core.params.reopen_interval_s)

    def _subscribers_ready(self) -> bool:
        """Whether the samples may be published: every reader the graph expects has
        matched both sample topics (checked until it is true, then never again)."""
        if not self._ready:
            need = self._core.params.min_subscribers
            self._ready = (self._joint_pub.get_subscription_count() >= need
                           and self._current_pub.get_subscription_count() >= need)
            if self._ready and self.dropped_before_ready:
                self._report(OK, f"link up on {self._link.port}: the graph's {need} "
                             f"subscribers are there; {self.dropped_before_ready} frames "
                             "read before them were not published", self._now_ns())
        return self._ready

    def _report(self, level: int, message: str, now_ns: int, **values: Any) -> None:
        core = self._core
        age = core.command_age_ns(now_ns)
        self.diagnose(level, message, now_ns, **values, frames_accepted=core.parser.frames,
                      bytes_discarded=core.parser.discarded, rehunts=core.parser.rehunts,
                      command_age_ms="none" if age is None else f"{age * 1e-6:.2f}",
                      commands_sent=core.commands, stale_commands=core.stale_commands,
                      zeroed_for_age=core.zeroed, keepalives_sent=core.keepalives,
                      silences=core.silences, refused_commands=core.refused_commands,
                      second_answers=core.second_answers,
                      bytes_not_written=self._unwritten)


def main(args: list[str] | None = None) -> int:
    return run_node(DriverNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
