"""A line-oriented request/reply transport over a serial port, shared by the serial drivers.

A driver sends one command and reads one reply, then checks it: :meth:`SerialLine.request`
writes the command and its terminator, reads until the reply terminator, decodes it as ASCII and
hands the text to the driver's check, which returns what the driver wants from it or raises
:class:`ReplyError`. Every failure becomes a :class:`~eyeserver.errors.DeviceError` that names
the device, the port, the command and what came back:

==============================================  ==============================================
what happened                                   raised
==============================================  ==============================================
port missing, unplugged, or I/O error on it     :class:`~eyeserver.errors.DeviceDisconnectedError`
nothing at all within the request's timeout     :class:`~eyeserver.errors.DeviceTimeoutError`
bytes that are not a reply the check accepts    :class:`~eyeserver.errors.DeviceError`
(not ASCII, no terminator, too long, rejected)
==============================================  ==============================================

After a lost port or a timeout the port is closed and the next request opens it again, so a
device whose cable comes back (or whose USB adapter re-enumerates at the same path) recovers
without reopening the driver. Stale bytes (a late reply to a timed-out request, the tail of
garbage) are discarded before every request, so one bad reply never shifts the next ones.

The port is opened with :func:`serial.serial_for_url`: a device path (``/dev/ttyUSB0``, a pty or
a symlink to one) or a pyserial URL such as ``loop://``.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable
from typing import Any, TypeVar

import serial

from eyeserver.errors import (
    DeviceDisconnectedError,
    DeviceError,
    DeviceNotOpenError,
    DeviceTimeoutError,
)

__all__ = ["ReplyError", "SerialLine", "answered"]

_T = TypeVar("_T")

try:  # termios is POSIX-only; pyserial raises its error from tcflush on a hung-up tty.
    import termios

    _PORT_ERRORS: tuple[type[BaseException], ...] = (serial.SerialException, OSError,
                                                     termios.error)
except ImportError:  # pragma: no cover - not on the Linux hosts eyeserver runs on
    _PORT_ERRORS = (serial.SerialException, OSError)


def answered(request: Callable[[], _T]) -> _T | None:
    """``request()``'s result, or None where the device did not answer as one that a probe
    looks for: silence, garbage, a rejected reply (any :class:`~eyeserver.errors.DeviceError`
    but a lost port). A probe tells "no such device here" from "no port" with it.

    Raises
    ------
    DeviceDisconnectedError
        The port is missing or failed.
    """
    try:
        return request()
    except DeviceDisconnectedError:
        raise
    except DeviceError:
        return None


class ReplyError(Exception):
    """Raised by a reply check: the reply is not what the command expects.

    The transport turns it into a :class:`~eyeserver.errors.DeviceError` that adds the device,
    the port, the command and the reply, so the check only says what is wrong with it.
    """


class SerialLine:
    """One serial port spoken to one command at a time.

    Parameters
    ----------
    device_id : str
        The device the port belongs to; every error names it.
    port : str
        Device path or pyserial URL (``loop://``).
    baudrate : int
        Bits per second; 8 data bits, no parity, 1 stop bit, no handshake.
    timeout_s : float
        Default time allowed for a whole reply, seconds, from the end of writing the command.
    write_terminator : bytes
        Appended to every command (``b"\\r"``, ``b"\\n"``).
    reply_terminator : bytes
        Ends a reply (``b"\\r\\n"``, or a prompt such as ``b">"``); not part of the reply text.
    ignore : callable, optional
        Replies for which it returns True are skipped and the next one is read: messages the
        device sends on its own (alerts, info lines) rather than in answer to the command.
    max_reply_bytes : int
        A reply longer than this without its terminator is garbage, not a slow reply.
    """

    def __init__(self, device_id: str, port: str, *, baudrate: int, timeout_s: float,
                 write_terminator: bytes, reply_terminator: bytes,
                 ignore: Callable[[str], bool] | None = None,
                 max_reply_bytes: int = 4096) -> None:
        if not port:
            raise ValueError("port must name a serial device or a pyserial URL")
        if baudrate <= 0:
            raise ValueError(f"baudrate must be positive, not {baudrate}")
        if timeout_s <= 0:
            raise ValueError(f"timeout_s must be positive, not {timeout_s}")
        if not write_terminator or not reply_terminator:
            raise ValueError("the write and reply terminators must not be empty")
        self.device_id = device_id
        self.port = port
        self.baudrate = int(baudrate)
        self.timeout_s = float(timeout_s)
        self._write_terminator = write_terminator
        self._reply_terminator = reply_terminator
        self._ignore = ignore
        self._max_reply_bytes = max_reply_bytes
        self._lock = threading.Lock()
        self._serial: Any = None  # serial.Serial (untyped) while connected
        self._active = False  # between open() and close(): requests reconnect as needed
        self._pending = b""

    @property
    def connected(self) -> bool:
        """Whether the port is open right now (False after a fault until the next request)."""
        return self._serial is not None

    def open(self) -> None:
        """Open the port now, so a missing port fails the driver's ``open()``.

        Raises
        ------
        DeviceDisconnectedError
            The port does not exist or cannot be opened.
        """
        with self._lock:
            self._active = True
            if self._serial is None:
                self._connect()

    def close(self) -> None:
        """Close the port; later requests raise :class:`DeviceNotOpenError`. Idempotent."""
        with self._lock:
            self._active = False
            self._drop()

    def request(self, command: str, check: Callable[[str], _T], *,
                timeout_s: float | None = None) -> _T:
        """Send ``command``, read one reply and return ``check(reply)``.

        Parameters
        ----------
        command : str
            ASCII command without its terminator.
        check : callable
            Takes the reply text (terminator removed) and returns what the caller needs; raises
            :class:`ReplyError` for a reply the command does not expect, or a
            :class:`~eyeserver.errors.DeviceError` of its own (the device reported a fault).
        timeout_s : float, optional
            Time allowed for this reply, seconds; the line's ``timeout_s`` by default.

        Raises
        ------
        DeviceNotOpenError
            :meth:`open` was not called, or :meth:`close` was.
        DeviceDisconnectedError
            The port is missing or failed.
        DeviceTimeoutError
            Nothing arrived in time.
        DeviceError
            The reply was garbage or the check rejected it.
        """
        timeout = self.timeout_s if timeout_s is None else float(timeout_s)
        with self._lock:
            if not self._active:
                raise DeviceNotOpenError(self.device_id, f"serial port {self.port} is not open")
            if self._serial is None:
                self._connect()
            self._send(command)
            deadline = time.monotonic() + timeout
            while True:
                text = self._read_reply(command, deadline, timeout)
                if self._ignore is not None and self._ignore(text):
                    continue
                try:
                    return check(text)
                except ReplyError as exc:
                    raise DeviceError(self.device_id, f"unexpected reply to {command!r} on "
                                                      f"{self.port}: {text!r} ({exc})") from exc

    def _connect(self) -> None:
        try:
            self._serial = serial.serial_for_url(
                self.port, baudrate=self.baudrate, bytesize=serial.EIGHTBITS,
                parity=serial.PARITY_NONE, stopbits=serial.STOPBITS_ONE,
                timeout=self.timeout_s, write_timeout=self.timeout_s)
        except _PORT_ERRORS as exc:
            raise DeviceDisconnectedError(
                self.device_id, f"cannot open serial port {self.port}: {exc}") from exc
        self._pending = b""

    def _drop(self) -> None:
        port, self._serial = self._serial, None
        self._pending = b""
        if port is not None:
            # A port that is already gone needs no more than its close() attempted.
            with contextlib.suppress(*_PORT_ERRORS):
                port.close()

    def _lost(self, exc: BaseException, command: str) -> DeviceDisconnectedError:
        self._drop()
        return DeviceDisconnectedError(self.device_id, f"serial port {self.port} failed during "
                                                       f"{command!r}: {exc}")

    def _send(self, command: str) -> None:
        try:
            payload = command.encode("ascii") + self._write_terminator
        except UnicodeEncodeError as exc:
            raise ValueError(f"command {command!r} is not ASCII") from exc
        try:
            self._serial.reset_input_buffer()
            self._serial.write(payload)
            self._serial.flush()
        except serial.SerialTimeoutException as exc:
            self._drop()
            raise DeviceTimeoutError(self.device_id, f"could not send {command!r} on "
                                                     f"{self.port}: the port did not take it "
                                                     f"within {self.timeout_s:g} s") from exc
        except _PORT_ERRORS as exc:
            raise self._lost(exc, command) from exc

    def _read_reply(self, command: str, deadline: float, timeout: float) -> str:
        terminator = self._reply_terminator
        buffer = self._pending
        while True:
            end = buffer.find(terminator)
            if end >= 0:
                raw, self._pending = buffer[:end], buffer[end + len(terminator):]
                break
            if len(buffer) > self._max_reply_bytes:
                self._pending = b""
                raise DeviceError(self.device_id, f"garbage in reply to {command!r} on "
                                                  f"{self.port}: {len(buffer)} bytes without "
                                                  f"{terminator!r}, starting {buffer[:64]!r}")
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                self._pending = b""
                if buffer:
                    raise DeviceError(self.device_id, f"incomplete reply to {command!r} on "
                                                      f"{self.port}: {buffer!r} (no "
                                                      f"{terminator!r} within {timeout:g} s)")
                # Silence may be a device that lost power behind a live USB adapter: reopen.
                self._drop()
                raise DeviceTimeoutError(self.device_id, f"no reply to {command!r} on "
                                                         f"{self.port} within {timeout:g} s")
            try:
                self._serial.timeout = remaining
                chunk = self._serial.read(max(1, self._serial.in_waiting))
            except _PORT_ERRORS as exc:
                raise self._lost(exc, command) from exc
            buffer += chunk
        try:
            return raw.decode("ascii")
        except UnicodeDecodeError as exc:
            raise DeviceError(self.device_id, f"garbage in reply to {command!r} on "
                                              f"{self.port}: {raw!r} is not ASCII text") from exc
