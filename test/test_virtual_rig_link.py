"""The virtual rig on its pseudo-terminal, read and driven with the driver's own link and codec."""

from __future__ import annotations

import time

import numpy as np
import pytest

from pisc_driver.link import SerialLink
from pisc_driver.protocol import FrameParser, command_voltage, encode_command
from pisc_plant.plant import Plant
from pisc_plant.firmware import Firmware
from pisc_plant.rig_process import RigProcess
from pisc_plant.virtual_rig import load_plant

pytestmark = pytest.mark.integration


def read_for(link: SerialLink, parser: FrameParser, seconds: float):
    """Frames read for ``seconds`` (the last read may block up to its timeout past it)."""
    frames, times = [], []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        data = link.read()
        now = time.monotonic()
        for f in parser.feed(data, now):
            frames.append(f)
            times.append(now)
    return frames, np.array(times)


def test_firmware_and_driver_codec_agree_on_every_command_byte():
    fw = Firmware(Plant(load_plant(None, {})[0]), np.zeros(7))
    for byte in range(256):
        assert fw.voltage(byte) == pytest.approx(command_voltage(byte), abs=1e-12)
    for volts in np.linspace(-12, 12, 2401):
        assert fw.voltage(encode_command(volts)) == pytest.approx(
            np.clip(round(abs(volts) * 127 / 11.47), 0, 127) * 11.47 / 127 * np.sign(volts),
            abs=1e-12)


@pytest.fixture
def rig():
    process = RigProcess(["--x0", "0.05"])
    yield process
    process.stop()


@pytest.mark.realtime
def test_rig_paces_frames_every_5_ms_and_applies_a_byte(rig):
    link = SerialLink(rig.device, read_timeout_s=0.01)
    link.open()
    parser = FrameParser()
    try:
        started = time.monotonic()
        frames, times = read_for(link, parser, 0.5)
        elapsed = time.monotonic() - started
        # one frame per period of the time read, plus one that may have been waiting
        assert 80 <= len(frames) <= elapsed / 0.005 + 1, (len(frames), elapsed)
        assert parser.discarded == 0 and parser.rehunts == 0
        # the median spacing is the period (the mean is loaded-machine jitter)
        assert np.median(np.diff(times)) == pytest.approx(0.005, abs=0.001)
        assert frames[-1].count == 0  # hanging at rest: count 0
        link.write(0x7F)
        time.sleep(0.02)  # (within the watchdog's 50 ms)
        status = rig.status()
        assert status["last_byte"] == 0x7F and status["applied_v"] == pytest.approx(11.47)
        assert status["state"]["x_dot"] > 0.0  # the cart moves off
        link.write(0x00)
    finally:
        link.close()


@pytest.mark.realtime
def test_rig_injects_faults_on_request(rig):
    link = SerialLink(rig.device, read_timeout_s=0.01)
    link.open()
    parser = FrameParser()
    try:
        read_for(link, parser, 0.1)
        rig.request(silence_s=0.3)
        rig.status()  # requests are handled in order: the silence has begun
        read_for(link, parser, 0.01)  # frames sent before it, still in the pty
        frames, _ = read_for(link, parser, 0.1)
        assert frames == []
        time.sleep(0.25)
        rig.request(garbage=40)
        frames, _ = read_for(link, parser, 0.2)
        assert len(frames) >= 20 and parser.discarded >= 40
        rig.request(drop_rate=1.0)
        rig.status()
        read_for(link, parser, 0.01)
        assert read_for(link, parser, 0.05)[0] == []
        rig.request(drop_rate=0.0, flip_rate=0.0)
        status = rig.status()
        assert status["dropped"] >= 7
        with pytest.raises(ValueError, match="drop_rate = 3.0 must lie in"):
            rig.request(drop_rate=3.0)
            rig.status()
    finally:
        link.close()


def wait_status(rig: RigProcess, predicate, timeout_s: float = 5.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while True:
        status = rig.status()
        if predicate(status) or time.monotonic() > deadline:
            return status
        time.sleep(0.002)


@pytest.mark.realtime
def test_the_watchdog_zeroes_the_motor_when_the_bytes_stop_and_the_next_byte_resumes(tmp_path):
    """Found by a hostile test: the host that stops sending (crashed) leaves 0 V, not its
    last byte. Judged on the rig's own clock (its log, one line per period), not the wall
    clock."""
    rig = RigProcess(["--x0", "0.05", "--log", str(tmp_path / "rig.csv")])
    link = SerialLink(rig.device, read_timeout_s=0.01)
    link.open()
    parser = FrameParser()
    try:
        read_for(link, parser, 0.05)
        assert rig.status()["watchdog_trips"] == 0  # armed by the first byte only
        link.write(0xB5)  # the -4.79 V of the crash
        status = wait_status(rig, lambda s: s["watchdog_trips"] == 1)
        assert status["last_byte"] == 0xB5 and status["applied_v"] == 0.0
        assert status["watchdog_tripped"] and status["watchdog_ms"] == 50.0
        # at the 11th tick after the byte: 50-55 ms after it by the firmware's clock
        assert 0.050 < status["watchdog_delay_s"] <= 0.055 + 1e-9
        print(f"0 V {(status['watchdog_trip_time'] - status['last_byte_time']) * 1e3:.1f} ms "
              "after the last byte by the monotonic clock")
        link.write(0x40)  # the next byte resumes, and is cut off in turn
        status = wait_status(rig, lambda s: s["watchdog_trips"] == 2)
        assert status["last_byte"] == 0x40 and status["applied_v"] == 0.0
        assert parser.rehunts == 0
    finally:
        link.close()
        rig.stop()
    log = np.genfromtxt(tmp_path / "rig.csv", delimiter=",", names=True)
    applied = log["applied_v"]
    # runs of the voltage applied at each tick: each byte held for ten periods, then 0 V
    changes = np.flatnonzero(np.diff(applied)) + 1
    runs = [(float(v), len(r)) for v, r in zip(applied[np.r_[0, changes]],
                                                np.split(applied, changes), strict=True)]
    held = [(round(v, 2), n) for v, n in runs if v != 0.0]
    assert held == [(-4.79, 10), (5.78, 10)], runs
    assert runs[-1][0] == 0.0


@pytest.mark.realtime
def test_without_the_watchdog_the_last_byte_is_held_as_the_thesis_firmware_holds_it():
    rig = RigProcess(["--x0", "0.05", "--watchdog-ms", "0"])
    link = SerialLink(rig.device, read_timeout_s=0.01)
    link.open()
    try:
        link.write(0x81)  # the smallest negative step: the cart barely moves
        read_for(link, FrameParser(), 0.2)  # four times the watchdog's default
        status = rig.status()
        assert status["last_byte"] == 0x81 and status["applied_v"] == pytest.approx(-11.47 / 127)
        assert status["watchdog_trips"] == 0 and status["watchdog_ms"] == 0.0
    finally:
        link.close()
        rig.stop()
