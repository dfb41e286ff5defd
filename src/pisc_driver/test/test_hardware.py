"""The real rig on a serial port: skipped unless PISC_SERIAL_PORT names it.

    PISC_SERIAL_PORT=/dev/ttyUSB0 .venv/bin/python -m pytest -m hardware src/pisc_driver/test/test_hardware.py

Safe to run with the pendulum hanging: the motor only ever receives zero voltage.
"""

from __future__ import annotations

import os
import time

import numpy as np
import pytest

from pisc_driver.driver import ZERO, DriverCore, DriverParams
from pisc_driver.link import SerialLink
from pisc_model.params import ActuatorParams, SensorParams

PORT = os.environ.get("PISC_SERIAL_PORT")

pytestmark = [
    pytest.mark.hardware,
    pytest.mark.skipif(not PORT, reason="no rig: set PISC_SERIAL_PORT to its serial device"),
]


@pytest.fixture
def link():
    link = SerialLink(PORT, 115200, read_timeout_s=0.01)
    link.open()
    try:
        yield link
    finally:
        link.write(ZERO)
        link.close()


def read_samples(link: SerialLink, core: DriverCore, seconds: float):
    samples = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        data = link.read()
        samples += core.receive(data, time.monotonic_ns()) if data else []
        link.write(ZERO)
    return samples


def test_the_rig_sends_a_frame_every_5_ms_with_plausible_values(link):
    core = DriverCore(DriverParams(port=PORT), SensorParams(), ActuatorParams(), 0.005)
    samples = read_samples(link, core, 2.0)
    assert 380 <= len(samples) <= 410, len(samples)  # 400 frames in 2 s, paced by the PIC
    assert core.parser.rehunts == 0
    stamps = np.array([s.stamp_ns for s in samples]) * 1e-9
    assert np.median(np.diff(stamps)) == pytest.approx(0.005, abs=0.0005)
    x = np.array([s.position_m for s in samples])
    current = np.array([s.current_a for s in samples])
    assert np.all((x > -0.25) & (x < 0.15)), (x.min(), x.max())  # on the track
    assert np.all(np.abs(current) < 0.3), np.abs(current).max()  # no voltage, no current

