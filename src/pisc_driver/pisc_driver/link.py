"""The serial port to the rig (pyserial): open with clear errors, read bursts, write bytes.

The driver talks to this transport, never to a device: a USB-serial adapter on the real
rig, or the pseudo-terminal that ``pisc_virtual_rig`` prints. 115200 baud, 8N1
(SPEC section 4).
"""

from __future__ import annotations

import errno
import math
import os
import select

import serial

from pisc_msgs_py.config import ConfigError

__all__ = ["LinkError", "SerialLink"]

READ_CHUNK = 4096  # most bytes one read takes (115200 baud: 11,520 bytes a second)


class LinkError(ConfigError):
    """The serial port is missing, busy, refused or failed; the message names it."""


class SerialLink:
    """One serial port, opened exclusively.

    Parameters
    ----------
    port
        Device path (``driver.port``).
    baud
        Line speed (``driver.baud``); 8 data bits, no parity, one stop bit.
    read_timeout_s
        How long :meth:`read` waits for a first byte before returning nothing, unless
        told otherwise (its ``wait_s``) or woken (:meth:`wake`).
    """

    def __init__(self, port: str, baud: int = 115200, read_timeout_s: float = 0.05) -> None:
        self.port = port
        self.baud = baud
        self.read_timeout_s = read_timeout_s
        self._serial: serial.Serial | None = None
        self._poll: select.poll | None = None
        self._wake_fd: int | None = None  # an eventfd in the poll: wake() ends a read's wait

    @property
    def is_open(self) -> bool:
        return self._serial is not None

    def open(self) -> None:
        """Open the port and drop whatever it buffered before; raise LinkError saying why not."""
        if not self.port:
            raise LinkError("driver.port is empty: give the rig's serial device (e.g. "
                            "/dev/ttyUSB0) or the path pisc_virtual_rig prints")
        if not os.path.exists(self.port):
            raise LinkError(f"driver.port = {self.port!r}: no such device (is the rig plugged "
                            "in, or the virtual rig running?)")
        try:
            port = serial.Serial(self.port, self.baud, bytesize=serial.EIGHTBITS,
                                 parity=serial.PARITY_NONE, stopbits=serial.STOPBITS_ONE,
                                 timeout=self.read_timeout_s,
                                 exclusive=True)
        except serial.SerialException as exc:
            raise LinkError(_why(self.port, exc)) from exc
        except OSError as exc:
            raise LinkError(_why(self.port, exc)) from exc
        port.reset_input_buffer()
        self._wake_fd = os.eventfd(0, os.EFD_NONBLOCK | os.EFD_CLOEXEC)
        self._poll = select.poll()
        self._poll.register(port.fileno(), select.POLLIN)
        self._poll.register(self._wake_fd, select.POLLIN)
        self._serial = port

    def wake(self) -> None:
        """End the wait of a :meth:`read` in progress (or the next one's, at once): it
        returns what arrived, maybe nothing. From any thread; nothing when closed."""
        if self._wake_fd is not None:
            os.eventfd_write(self._wake_fd, 1)

    def read(self, wait_s: float | None = None) -> bytes:
        """The bytes that arrived: waits up to ``wait_s`` (default ``read_timeout_s``)
        for the first, then takes what is there (a device burst), so a frame reaches the
        parser when it arrives; b"" when the wait ends first or :meth:`wake` ended it.
        A device that went away raises LinkError; the caller closes the port. A negative
        or non-finite ``wait_s`` raises ValueError (a negative poll would never return).

        One ``poll`` and one ``read`` of the non-blocking descriptor pyserial opened, as
        :meth:`write` does: pyserial's ``read(1)``, ``in_waiting`` and ``read(n)`` took
        two ``select`` calls, two reads and an ioctl per burst (the reader then
        woke 400-600 times a second; now about once a frame, 200).
        """
        wait = self.read_timeout_s if wait_s is None else wait_s
        if not (math.isfinite(wait) and wait >= 0.0):  # (poll waits for ever on a negative)
            raise ValueError(f"wait_s = {wait_s}: must be a finite number of seconds >= 0")
        port = self._require()
        fd = port.fileno()
        try:
            ready = False
            for f, _ in self._poll.poll(wait * 1e3):
                if f == fd:
                    ready = True
                else:  # woken
                    os.eventfd_read(self._wake_fd)
            if not ready:
                return b""
            data = os.read(fd, READ_CHUNK)
        except BlockingIOError:
            return b""  # (another reader took what woke it: nothing there now)
        except OSError as exc:
            raise LinkError(f"driver.port = {self.port!r}: read failed, the device went away "
                            f"({exc})") from exc
        if not data:
            raise LinkError(f"driver.port = {self.port!r}: read failed, the device went away "
                            "(ready to read but returned no data: disconnected?)")
        return data

    def write(self, byte: int) -> bool:
        """Send one byte at once; False when the port cannot take it now (output full).

        Written straight to the non-blocking descriptor pyserial opened: pyserial's own
        write reports a timeout whenever the calling thread was descheduled past the
        timeout, even after the byte went out. A write never closes the port (the reader
        owns it); a device that went away raises LinkError.
        """
        port = self._require()
        try:
            return os.write(port.fileno(), bytes([byte])) == 1
        except BlockingIOError:
            return False
        except (serial.SerialException, OSError) as exc:
            raise LinkError(f"driver.port = {self.port!r}: write failed, the device went away "
                            f"({exc})") from exc

    def close(self) -> None:
        port, self._serial, self._poll = self._serial, None, None
        wake_fd, self._wake_fd = self._wake_fd, None
        if wake_fd is not None:
            os.close(wake_fd)
        if port is not None:
            try:
                port.close()
            except (serial.SerialException, OSError):
                pass

    def _require(self) -> serial.Serial:
        if self._serial is None:
            raise LinkError(f"driver.port = {self.port!r}: the port is not open")
        return self._serial


def _why(port: str, exc: BaseException) -> str:
    text = str(exc)
    code = getattr(exc, "errno", None)
    if "exclusively lock" in text or code in (errno.EBUSY, errno.EAGAIN):
        return (f"driver.port = {port!r}: the port is busy, another program has it open "
                f"({text})")
    if code == errno.EACCES or "Permission denied" in text:
        return (f"driver.port = {port!r}: permission denied (add the user to the 'dialout' "
                f"group) ({text})")
    if code == errno.ENOENT or "No such file" in text:
        return f"driver.port = {port!r}: no such device ({text})"
    return f"driver.port = {port!r}: cannot open the serial port ({text})"
