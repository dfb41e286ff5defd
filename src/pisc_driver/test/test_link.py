"""The serial transport on a pseudo-terminal: open errors, bursts, writes, a vanishing device."""

from __future__ import annotations

import os
import threading
import time
import tty

import pytest

from pisc_driver.link import LinkError, SerialLink
from pisc_msgs_py.config import ConfigError


@pytest.fixture
def pty():
    master, slave = os.openpty()
    tty.setraw(slave)
    fds = [master, slave]
    yield master, os.ttyname(slave), fds
    for fd in fds:
        try:
            os.close(fd)
        except OSError:
            pass


def test_empty_and_missing_ports_are_refused_by_name():
    with pytest.raises(LinkError, match="driver.port is empty"):
        SerialLink("").open()
    with pytest.raises(LinkError, match=r"driver.port = '/dev/pisc-no-such-port': no such device"):
        SerialLink("/dev/pisc-no-such-port").open()
    assert issubclass(LinkError, ConfigError)  # a node refuses to start, exit status 2


def test_a_busy_port_is_refused_and_says_so(pty):
    _, path, _ = pty
    first = SerialLink(path)
    first.open()
    try:
        with pytest.raises(LinkError, match=r"the port is busy, another program has it open"):
            SerialLink(path).open()
    finally:
        first.close()


def test_a_port_that_is_not_a_serial_device_is_refused(tmp_path):
    path = tmp_path / "not-a-tty"
    path.write_text("")
    with pytest.raises(LinkError, match=r"driver.port = '.*not-a-tty'"):
        SerialLink(str(path)).open()


def test_old_bytes_are_dropped_on_open_then_a_burst_is_read_whole(pty):
    master, path, _ = pty
    os.write(master, b"\x01\x02stale")
    link = SerialLink(path, read_timeout_s=0.05)
    link.open()
    try:
        assert link.read() == b""  # what was buffered before opening is gone
        os.write(master, bytes([0xAA, 0x01, 0xF4, 0x02, 0x08, 0x00, 0x0A]))
        time.sleep(0.01)
        assert link.read() == bytes([0xAA, 0x01, 0xF4, 0x02, 0x08, 0x00, 0x0A])
        assert link.write(0x81) and link.write(0x00)
        time.sleep(0.01)
        assert os.read(master, 16) == b"\x81\x00"
    finally:
        link.close()


def test_a_device_that_goes_away_is_a_link_error_not_a_crash(pty):
    master, path, fds = pty
    link = SerialLink(path, read_timeout_s=0.05)
    link.open()
    for fd in fds:
        os.close(fd)
    fds.clear()
    with pytest.raises(LinkError, match=r"read failed, the device went away"):
        for _ in range(3):
            link.read()
    assert link.is_open  # the caller (the driver's reader) closes it
    link.close()
    assert not link.is_open
    with pytest.raises(LinkError, match="no such device|cannot open"):
        link.open()


def test_wake_ends_a_reads_wait_from_another_thread_and_is_used_once(pty):
    """The driver's reader waits until the core's next deadline (up to read_timeout_s);
    a command that sets a sooner one wakes it."""
    master, path, _ = pty
    link = SerialLink(path, read_timeout_s=0.05)
    link.open()
    try:
        waker = threading.Timer(0.05, link.wake)
        waker.start()
        started = time.monotonic()
        assert link.read(wait_s=30.0) == b""  # woken, with nothing to read
        waited = time.monotonic() - started
        waker.join()
        assert 0.04 <= waited < 15.0  # ended by the wake, not by the 30 s wait
        started = time.monotonic()
        assert link.read(wait_s=0.1) == b""  # the wake was used: this read waits it out
        assert time.monotonic() - started >= 0.09
        link.wake()  # a wake before the read: the read returns at once ...
        os.write(master, b"\xAA\x01")
        time.sleep(0.01)
        assert link.read(wait_s=30.0) == b"\xAA\x01"  # ... with what is there
        started = time.monotonic()
        assert link.read(wait_s=0.1) == b""
        assert time.monotonic() - started >= 0.09
    finally:
        link.close()
    link.wake()  # closed: nothing to wake, no error


@pytest.mark.parametrize("wait_s", [-0.001, float("nan"), float("inf")])
def test_a_wait_that_poll_would_never_end_is_refused_by_name(pty, wait_s):
    _, path, _ = pty
    link = SerialLink(path)
    link.open()
    try:
        with pytest.raises(ValueError, match=r"wait_s = .*: must be a finite number of "
                                             r"seconds >= 0"):
            link.read(wait_s)
        assert link.read(0.0) == b""  # 0: look and return
    finally:
        link.close()
