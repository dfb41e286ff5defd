"""The virtual rig on its pseudo-terminal, read and driven with the driver's own link and codec."""

from __future__ import annotations

import time

import numpy as np
import pytest

from pisc_driver.link import SerialLink
from pisc_driver.protocol import FrameParser, command_voltage, encode_command
from pisc_plant.plant import Plant
from pisc_plant.virtual_rig import Firmware, RigProcess, load_plant

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
        time.sleep(0.05)
        status = rig.status()
        assert status["last_byte"] == 0x7F and status["applied_v"] == pytest.approx(11.47)
        assert status["state"]["x_dot"] > 0.0  # the cart moves off
        link.write(0x00)
    finally:
        link.close()


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
