"""DriverCore: samples from bytes, command bytes, the zero-voltage rules, with times given."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest

from pisc_driver.driver import ZERO, DriverCore, DriverParams, Trip
from pisc_model.params import ActuatorParams, SensorParams
from pisc_model.sensors import decode

MS = 1_000_000


def frame(ir: int, cur: int, count: int) -> bytes:
    return struct.pack(">BHHh", 0xAA, ir, cur, count)


def core(**params) -> DriverCore:
    return DriverCore(DriverParams(**params), SensorParams(), ActuatorParams(), 0.005)


def test_each_frame_becomes_a_sample_in_si_stamped_at_arrival():
    c = core()
    data = frame(400, 780, 0) + frame(401, 781, 3) + frame(402, 782, 6)
    assert c.receive(data[:10], 1000 * MS) == []
    # first frame confirmed by the second, whose bytes came 0.3 ms apart (a frame whose
    # bytes came more than driver.frame_gap_s apart is refused: test_protocol)
    samples = c.receive(data[10:14], 1000 * MS + 300_000)
    samples += c.receive(data[14:], 1005 * MS)
    # the chunk that confirms the first frame also completes the second: the first is
    # stamped with the read its bytes came in, the second with its own
    assert [s.stamp_ns for s in samples] == [1000 * MS, 1000 * MS + 300_000, 1005 * MS]
    x, theta, i = decode(SensorParams(), 401, 781, 3)
    assert samples[1].position_m == pytest.approx(float(x), abs=0)
    assert samples[1].angle_rad == pytest.approx(math.pi + 3 * math.pi / 2000, rel=1e-12)
    assert samples[1].current_a == pytest.approx(float(i), abs=0)


def test_a_backlog_one_read_completes_is_stamped_a_period_apart_ending_at_the_read():
    c = core()
    second = frame(400, 780, 1)
    assert [s.stamp_ns for s in c.receive(frame(400, 780, 0) + second[:4], 1000 * MS)
            ] == [1000 * MS]
    assert [s.stamp_ns for s in c.receive(second[4:], 1000 * MS + 300_000)
            ] == [1000 * MS + 300_000]
    # the reader stalls 30 ms: six frames wait in the port and come in one read
    backlog = b"".join(frame(400, 780, n) for n in range(2, 8))
    samples = c.receive(backlog, 1030 * MS)
    assert [s.stamp_ns for s in samples] == [1030 * MS - k * 5 * MS for k in range(5, -1, -1)]
    # an answer is as old as the frame it answers: those to the frames that waited more
    # than two periods are refused; before, each was stamped 1 us after the one before
    # and the rig got voltages computed from states up to the stall's length old
    assert c.command(samples[0].stamp_ns, -6.0, 1031 * MS) is None
    assert c.command(samples[3].stamp_ns, -6.0, 1031 * MS) is None
    assert c.command(samples[4].stamp_ns, 11.47, 1031 * MS) == 0x7F
    assert c.command(samples[5].stamp_ns, 11.47, 1032 * MS) == 0x7F
    assert c.stale_commands == 2


def test_backlog_stamps_never_go_back_past_the_newest_sample():
    c = core()
    c.receive(frame(400, 780, 0) + frame(400, 780, 1), 1000 * MS)  # stamps 995, 1000 ms
    samples = c.receive(frame(400, 780, 2) + frame(400, 780, 3), 1002 * MS)
    assert [s.stamp_ns for s in samples] == [1000 * MS + 1000, 1002 * MS]


def test_the_16_bit_count_is_unwrapped_across_its_wrap():
    c = core()
    counts = [32766, 32767, -32768, -32767]
    data = b"".join(frame(400, 780, n) for n in counts) + frame(400, 780, -32766)
    angles = [s.angle_rad for s in c.receive(data, 0)]
    steps = [b - a for a, b in zip(angles, angles[1:])]
    assert steps == pytest.approx([2 * math.pi / 4000] * 4)


def test_a_fresh_command_is_sent_a_stale_or_superseded_one_is_not():
    c = core()
    assert c.command(100 * MS, 11.47, 101 * MS) == 0x7F
    assert c.command(105 * MS, -5.0, 106 * MS) == 0xB7
    assert c.command(100 * MS, 1.0, 107 * MS) is None  # older than the one sent
    assert c.command(110 * MS, 1.0, 120 * MS + 1) is None  # 10 ms + 1 ns old: two periods
    assert c.command(115 * MS, 0.0, 125 * MS) == ZERO  # exactly two periods old: still sent
    assert (c.commands, c.stale_commands) == (3, 2)
    assert c.command_age_ns(130 * MS) == 15 * MS
    # a message the node's publisher pin did not admit is sent as 0 V, answering nothing
    answered = c.watchdog.answered
    assert c.command(130 * MS, 11.47, 131 * MS, refused=True) == ZERO
    assert c.refused_commands == 1 and c.watchdog.answered == answered
    # a second answer to a sample (another publisher the pin does not know of yet):
    # dropped, the first stands
    assert c.command(135 * MS, 3.0, 136 * MS) == 0x21
    assert c.command(135 * MS, 11.47, 136 * MS) is None and c.second_answers == 1
    assert c.sent_byte == 0x21


def test_zero_voltage_once_the_newest_command_is_older_than_two_periods():
    c = core()
    assert c.tick(0) == (None, None)  # nothing sent yet, no frame yet
    c.command(100 * MS, 3.0, 101 * MS)
    assert c.tick(110 * MS) == (None, None)
    assert c.tick(110 * MS + 1) == (ZERO, None)
    assert c.tick(111 * MS) == (None, None)  # once
    assert c.zeroed == 1
    c3 = core(command_max_age_periods=3.0)
    c3.command(0, 3.0, 0)
    assert c3.tick(15 * MS) == (None, None) and c3.tick(15 * MS + 1) == (ZERO, None)


def test_device_silence_is_a_fault_with_zero_voltage_reported_once_per_silence():
    c = core(command_max_age_periods=10.0)  # the age rule is not what is tested here
    c.receive(frame(400, 780, 0) + frame(400, 780, 0) + frame(400, 780, 0)[:6], 0)
    c.receive(b"\x00", 2 * MS)  # last byte of the third frame... and then nothing
    c.command(2 * MS, 2.0, 3 * MS)
    assert c.tick(17 * MS) == (None, None)  # 15 ms after the last frame: not yet
    byte, fault = c.tick(17 * MS + 1)
    assert byte == ZERO
    assert fault == ("device silent: no frame for 15.0 ms (driver.silence_timeout_s = 0.015); "
                     "sending 0 V")
    assert c.tick(30 * MS) == (None, None)
    c.receive(frame(400, 780, 0), 40 * MS)
    assert not c.silent
    assert c.tick(56 * MS)[1].startswith("device silent")
    assert c.silences == 2


def run_frames(c: DriverCore, until_ms: int, answer=lambda k: None) -> list[tuple[int, int]]:
    """A frame every 5 ms and a read every 1 ms up to ``until_ms``; ``answer(k)`` is the
    voltage the controllers send 1 ms after frame k (None: no answer). Returns the
    (time in ms, byte) the driver sent."""
    if not c.parser.locked:  # lock on the frames sent before
        c.receive(frame(400, 780, 0) * 2, -5 * MS)
    sent = []
    for t in range(until_ms + 1):
        if t % 5 == 0:
            c.receive(frame(400, 780, 0), t * MS)
        elif t % 5 == 1 and answer(t // 5) is not None:
            byte = c.command((t - 1) * MS, answer(t // 5), t * MS)
            if byte is not None:
                sent.append((t, byte))
        byte, _ = c.tick(t * MS)
        if byte is not None:
            sent.append((t, byte))
    return sent


def test_no_byte_of_its_own_before_the_run_starts():
    c = core()
    assert run_frames(c, 200) == [] and not c.active


def test_every_frame_is_answered_while_the_controllers_are_silent():
    """Found by a hostile test: the driver sent one zero byte and then nothing, so a
    firmware watchdog would trip (and tell a live host from a dead one no more)."""
    c = core()
    sent = run_frames(c, 200, answer=lambda k: 3.0 if k < 4 else None)
    assert sent[:4] == [(1, 0x21), (6, 0x21), (11, 0x21), (16, 0x21)]  # the controllers'
    # frame 4 (20 ms) unanswered: at frame 5 the driver answers it with the byte held,
    # still fresh (10 ms old); 0 V once it is stale (answering frame 5); then each
    # frame's zero byte when the next frame arrives
    assert sent[4:6] == [(25, 0x21), (26, ZERO)]
    assert sent[6:] == [(t, ZERO) for t in range(35, 201, 5)]
    assert (c.commands, c.zeroed, c.keepalives) == (4, 1, 1 + len(range(35, 201, 5)))
    gaps = np.diff([t for t, _ in sent])
    assert gaps.max() <= 9  # never more than two periods without a byte


def test_a_frame_the_controllers_answer_gets_no_second_byte():
    c = core()
    sent = run_frames(c, 200, answer=lambda k: 1.0)
    assert sent == [(5 * k + 1, 0x0B) for k in range(40)] and c.keepalives == 0
    # answering every other frame: the driver answers the others (when the next frame
    # arrives, with the byte held): one byte per frame
    c = core()
    sent = run_frames(c, 200, answer=lambda k: 1.0 if k % 2 == 0 else None)
    assert sent[:5] == [(1, 0x0B), (10, 0x0B), (11, 0x0B), (20, 0x0B), (21, 0x0B)]
    assert len(sent) == 40 and c.keepalives == 20 and c.zeroed == 0


def test_no_byte_of_its_own_once_the_run_ends():
    c = core()
    run_frames(c, 50, answer=lambda k: 2.0)
    c.end_run()
    sent = [(t, b) for t, b in run_frames(c, 200)]
    assert all(b == ZERO for _, b in sent) and len(sent) <= 1  # at most the stale zero
    assert not c.active


def test_the_shared_watchdog_trips_at_the_third_unanswered_frame_and_resumes():
    """The hostile tests' crash matrix at the driver: the plant's CommandWatchdog counts
    the frames; with the age rule out of the way (command_max_age_periods 10) it alone
    zeroes."""
    c = core(command_max_age_periods=10.0)
    sent = run_frames(c, 60, answer=lambda k: 3.0 if k < 4 else None)
    assert c.watchdog.answered >= 0
    first = c.watchdog.answered - 3  # the index of the frame at 0 ms
    # frames 0..3 answered, 4 and 5 not: at frame 6 (30 ms) 0 V, said once
    assert (30, ZERO) in sent and all(b == 0x21 for t, b in sent if t < 30)
    assert c.watchdog.tripped_at == first + 6
    assert all(b == ZERO for t, b in sent if t >= 30)
    # a command answering one of the last 3 frames resumes
    stamp = c.watchdog.stamp_of(c.watchdog.tripped_at + 4)
    assert c.command(stamp, 3.0, stamp + MS) == 0x21
    assert c.resumed_from == first + 6 and c.watchdog.tripped_at is None


def test_the_watchdog_trip_is_reported_with_its_samples():
    c = core(command_max_age_periods=10.0)
    reports = []
    c.receive(frame(400, 780, 0) * 2, -5 * MS)
    for k in range(8):
        c.receive(frame(400, 780, 0), k * 5 * MS)
        if k < 2:
            c.command(k * 5 * MS, 1.0, k * 5 * MS + MS)
        byte, fault = c.tick(k * 5 * MS)
        if fault:
            reports.append((k, byte, fault, c.new_trip))
    [(k, byte, fault, trip)] = reports  # once
    last = c.watchdog.answered
    assert k == 4 and byte == ZERO and trip == Trip(last + 3, last, 20 * MS)
    assert c.witness.pending == (last + 3, last, 20 * MS)  # the stage: named later
    assert fault == f"command watchdog: no command answered samples {last + 1} .. " \
                   f"{last + 3}: 0 V from sample {last + 3}"
    # a command answering the newest frame ends the trip and the question of who stopped
    newest = c.newest_stamp_ns
    c.command(newest, 1.0, newest + MS)
    assert c.resumed_from == last + 3 and c.witness.pending is None


def test_while_another_publisher_is_there_every_command_is_zero_volts():
    c = core()
    assert c.command(100 * MS, 11.47, 101 * MS) == 0x7F
    assert c.hold_off(("/visitor",)) == ZERO  # at once
    assert c.command(105 * MS, 11.47, 106 * MS) == ZERO  # anyone's: sent as 0 V
    assert c.command(110 * MS, -3.0, 111 * MS) == ZERO
    assert c.refused_commands == 2 and c.sent_byte == ZERO
    assert c.hold_off(()) is None  # gone: the next command applies
    assert c.command(115 * MS, 3.0, 116 * MS) == 0x21
    # frames left unanswered while it is there are answered with 0 V, not the held byte
    c = core()
    sent = run_frames(c, 10, answer=lambda k: 3.0)
    c.hold_off(("/visitor",))
    sent = run_frames(c, 40)
    assert sent and all(b == ZERO for _, b in sent)


def run_on_deadlines(c: DriverCore, frames_ms: list[int], answer=lambda k: None,
                     longest_ms: int = 50) -> tuple[list[tuple[int, int]], int]:
    """Frames at ``frames_ms`` and the controllers' answers 1 ms after frame k
    (``answer(k)``, None: none), read the way driver_node's reader reads: it
    ticks only when it wakes, at a frame, at the core's deadline as it stood after its
    last tick, ``longest_ms`` after that tick, or when a command sets a deadline sooner
    than its wake (the node's wake()). Returns the (time in ns, byte) the driver sent and
    the reader's wake-ups."""
    c.receive(frame(400, 780, 0) * 2, -5 * MS)  # locked on the frames before
    events = sorted([(t * MS, 0, k) for k, t in enumerate(frames_ms)]
                    + [(t * MS + MS, 1, k) for k, t in enumerate(frames_ms)
                       if answer(k) is not None])
    sent: list[tuple[int, int]] = []
    wakes = 0

    def wake(now: int, data: bytes = b"") -> int:  # one pass of the reader's loop
        nonlocal wakes
        wakes += 1
        if data:
            c.receive(data, now)
        byte, _ = c.tick(now)
        if byte is not None:
            sent.append((now, byte))
        due = c.deadline_ns()
        assert due is None or due > now  # the reader never spins
        return now + longest_ms * MS if due is None else min(due, now + longest_ms * MS)

    planned = wake(0)
    for at, kind, k in events:
        while planned < at:  # its wait ended before this event
            planned = wake(planned)
        if kind == 0:
            planned = wake(at, frame(400, 780, 0))
        else:
            byte = c.command(frames_ms[k] * MS, answer(k), at)
            if byte is not None:
                sent.append((at, byte))
            due = c.deadline_ns()
            if due is not None and due < planned:
                planned = wake(at)
    return sent, wakes


@pytest.mark.parametrize("answer, frames_ms", [
    (lambda k: 1.0, range(0, 201, 5)),  # every frame answered
    (lambda k: 3.0 if k < 4 else None, range(0, 201, 5)),  # the controllers stop
    (lambda k: 1.0 if k % 2 == 0 else None, range(0, 201, 5)),  # every other frame
    (lambda k: 2.0, [*range(0, 51, 5), *range(120, 201, 5)]),  # the device falls silent
    (lambda k: 2.0 if k != 3 else None, [0, 5, 10, 15, 40, 45, 50]),  # ... a command first
], ids=["answered", "stopped", "every-other", "silence", "silence-unanswered"])
def test_a_reader_woken_only_at_frames_and_deadlines_sends_what_a_fine_poll_sends(
        answer, frames_ms):
    """The reader no longer wakes every read_timeout_s to apply the age and silence rules
    (three wake-ups a period, two of them for nothing); it waits until the
    core's deadline. It sends the bytes a reader ticking every 0.1 ms would send, each at
    the rule's deadline itself (to the nanosecond), so never later. (A 1 ms tick sends
    fewer: answering every other frame, it ticks only after the next answer came and
    misses the 0 V due 1 ns after the command before it turned 10 ms old.)"""
    frames_ms = list(frames_ms)
    step = MS // 10
    polled = core()
    polled.receive(frame(400, 780, 0) * 2, -5 * MS)
    want = []
    for t in range(0, frames_ms[-1] * MS + 1, step):
        if t % MS == 0 and t // MS in frames_ms:
            polled.receive(frame(400, 780, 0), t)
        elif t % MS == 0 and t // MS - 1 in frames_ms:
            k = frames_ms.index(t // MS - 1)
            byte = None if answer(k) is None else polled.command(t - MS, answer(k), t)
            if byte is not None:
                want.append((t, byte))
        byte, _ = polled.tick(t)
        if byte is not None:
            want.append((t, byte))
    got, wakes = run_on_deadlines(core(), frames_ms, answer)
    got = [(t, b) for t, b in got if t <= frames_ms[-1] * MS]
    assert [b for _, b in got] == [b for _, b in want]
    assert all(0 <= w - g < step for (g, _), (w, _) in zip(got, want)), (got, want)
    if all(answer(k) is not None for k in range(len(frames_ms))) and frames_ms == list(
            range(0, 201, 5)):
        # once a frame; also the first pass and the first command (a deadline sooner
        # than the wait the reader began after 0 V)
        assert wakes == len(frames_ms) + 2


def test_the_deadline_is_the_age_or_the_silence_rule_whichever_comes_first():
    c = core()
    assert c.deadline_ns() is None  # no frame, nothing sent: nothing falls due
    c.receive(frame(400, 780, 0) * 2 + frame(400, 780, 0)[:6], 0)
    c.receive(b"\x00", 2 * MS)
    assert c.deadline_ns() == 17 * MS + 1  # silence: 15 ms after the last frame
    c.command(2 * MS, 3.0, 3 * MS)
    assert c.deadline_ns() == 12 * MS + 1  # the age rule: 10 ms after its sample
    assert c.tick(12 * MS) == (None, None) and c.tick(12 * MS + 1) == (ZERO, None)
    assert c.deadline_ns() == 17 * MS + 1  # 0 V sent: the age rule has nothing to do
    assert c.tick(17 * MS + 1)[1].startswith("device silent")
    assert c.deadline_ns() is None  # silent, 0 V: until a frame comes
