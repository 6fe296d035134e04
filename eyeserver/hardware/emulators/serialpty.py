"""The base of the serial device emulators: a device on a pseudo-terminal, served by a thread.

The emulator opens a pty and serves its master side; the driver under test opens the slave side
as if it were the device's serial port. The driver is given :attr:`SerialPtyEmulator.port`, a
symlink that the emulator points at the current pty's slave (``/dev/pts/N``), because a pty's
own path changes every time one is made: :meth:`~SerialPtyEmulator.unplug` closes the pty and
removes the symlink (the driver's open port fails with an I/O error, and opening the path fails
with "no such file", as with a USB adapter pulled out); :meth:`~SerialPtyEmulator.replug` makes a
new pty and points the same symlink at it, so a driver that reopens its configured path finds
the device again. The device's state (settings, position) survives the unplug, as a real
device's does when only its cable is pulled.

:attr:`~SerialPtyEmulator.behaviour` switches how the emulator answers, to test the drivers'
fault handling: :attr:`Behaviour.NORMAL` replies as the device does, :attr:`Behaviour.GARBAGE`
answers every command with bytes no driver can parse (as a wrong baud rate or a noisy line
does), :attr:`Behaviour.SILENT` reads commands and answers nothing (a device without power
behind a live adapter).

A subclass implements :meth:`~SerialPtyEmulator.reply` (the device's protocol) and may override
:meth:`~SerialPtyEmulator.garbage`; a device whose requests are not lines (Modbus RTU's binary
frames) overrides the framing instead: :meth:`~SerialPtyEmulator.split_request` and
:meth:`~SerialPtyEmulator.handle_request`. The serving thread and its control calls are
:class:`~eyeserver.hardware.emulators.served.ServedEmulator`'s.
"""

from __future__ import annotations

import abc
import contextlib
import logging
import os
import pty
import selectors
import shutil
import tempfile
import threading
import tty
from pathlib import Path

from eyeserver.hardware.emulators.served import Behaviour, ServedEmulator

__all__ = ["Behaviour", "SerialPtyEmulator"]

_log = logging.getLogger(__name__)


class SerialPtyEmulator(ServedEmulator):
    """A serial device emulated on a pty; use as a context manager or call start()/stop().

    Parameters
    ----------
    link_dir : path, optional
        Directory for the :attr:`port` symlink; a private temporary directory (removed by
        :meth:`stop`) by default.
    name : str
        The symlink's file name.

    Attributes
    ----------
    behaviour : Behaviour
        How commands are answered; may be changed at any time.
    received : list of str
        Every command line read, in order (without its terminator), for tests to inspect.
    failures : list of Exception
        Exceptions :meth:`reply` raised (emulator bugs); :meth:`stop` raises the first.
    lock : threading.RLock
        Held while a command is handled; hold it to read or change the device's state from
        another thread consistently.
    """

    command_terminators: bytes = b"\r\n"
    """Any of these bytes ends a command line; empty lines are ignored."""

    _failure_message = "the emulator failed to answer {count} command(s)"

    def __init__(self, *, link_dir: str | Path | None = None, name: str = "tty") -> None:
        if not name or "/" in name:
            raise ValueError(f"name must be a plain file name, not {name!r}")
        super().__init__()
        self._link_dir_given = link_dir is not None
        self._link_dir = Path(link_dir) if link_dir is not None else None
        self._name = name
        self.received: list[str] = []
        self.lock = threading.RLock()
        self._master: int | None = None
        self._slave: int | None = None
        self._buffer = b""

    # --- the protocol: subclasses -------------------------------------------------------

    @abc.abstractmethod
    def reply(self, command: str) -> bytes | None:
        """The bytes the device sends in answer to one command line (None: no answer).

        Called on the serving thread with :attr:`lock` held.
        """

    def garbage(self, command: str) -> bytes:
        """What :attr:`Behaviour.GARBAGE` sends for ``command``: by default bytes that are not
        ASCII, ending in CR LF so that a line-reading driver sees a complete, unparsable reply
        at once instead of waiting for its timeout."""
        return b"\xfe\x92~\x00\x8f?#\r\n"

    def split_request(self, buffer: bytes) -> tuple[bytes, bytes] | None:
        """The first request in ``buffer`` (the bytes read and not yet handled) and the bytes
        after it; None while it is incomplete. By default a command line, ended by any of
        :attr:`command_terminators` (the terminator is dropped).

        Called on the serving thread; the request must not be empty while ``buffer`` is not
        consumed, or the thread would loop."""
        cut = min((i for i in (buffer.find(bytes([t])) for t in self.command_terminators)
                   if i >= 0), default=-1)
        if cut < 0:
            return None
        return buffer[:cut], buffer[cut + 1:]

    def handle_request(self, request: bytes) -> None:
        """Answer one request :meth:`split_request` cut: by default a command line, recorded in
        :attr:`received` and answered as :attr:`behaviour` says (:meth:`reply` or
        :meth:`garbage`); an empty one is ignored. Called on the serving thread."""
        if request:
            self._answer(request.decode("ascii", errors="replace"))

    def send(self, data: bytes) -> None:
        """Write ``data`` to the driver, as the device. Bytes the driver cannot get are lost,
        as on a real line: when unplugged, when the pty's buffer is full (nobody reads), or
        after a hang-up."""
        if data and self._master is not None:
            with contextlib.suppress(OSError):
                os.write(self._master, data)

    # --- life cycle ---------------------------------------------------------------------

    @property
    def port(self) -> str:
        """The path a driver opens: a symlink to the current pty, stable across replugs."""
        if self._link_dir is None:
            raise RuntimeError("the emulator is not started")
        return str(self._link_dir / self._name)

    @property
    def plugged(self) -> bool:
        """Whether the device is reachable at :attr:`port`."""
        return self._master is not None

    # --- the serving thread -------------------------------------------------------------

    def _thread_name(self) -> str:
        return f"serialpty-{self._name}"

    def _readable(self, key: selectors.SelectorKey) -> None:
        if key.fd != self._master:
            return
        try:
            data = os.read(key.fd, 4096)
        except OSError:
            data = b""  # the driver's side hung up; nothing to answer
        if data:
            self._feed(data)

    def _feed(self, data: bytes) -> None:
        """Every byte read from the pty passes here."""
        self._buffer += data
        while (cut := self.split_request(self._buffer)) is not None:
            request, self._buffer = cut
            self.handle_request(request)

    def _answer(self, command: str) -> None:
        with self.lock:
            self.received.append(command)
            behaviour = self.behaviour
            if behaviour is Behaviour.SILENT:
                return
            try:
                answer = self.garbage(command) if behaviour is Behaviour.GARBAGE else (
                    self.reply(command))
            except Exception as exc:
                # A bug in the emulator, not a device behaviour: keep serving, and let stop()
                # raise it so the test that met it fails instead of timing out mysteriously.
                _log.exception("emulator failed to answer %r", command)
                self.failures.append(exc)
                return
        if answer:
            self.send(answer)

    def _plug(self) -> None:
        if self._link_dir is None:
            self._link_dir = Path(tempfile.mkdtemp(prefix="eyeserver-pty-"))
        assert self._selector is not None
        master, slave = pty.openpty()
        # Held and registered before anything else can fail, so that _unplug undoes exactly
        # what was done (a link that cannot be made then fails start() with its own error).
        self._master, self._slave = master, slave
        self._selector.register(master, selectors.EVENT_READ)
        self._buffer = b""
        # Raw on both sides of the pty whatever the driver does: no echo, no CR/LF translation.
        tty.setraw(slave)
        os.set_blocking(master, False)
        link = Path(self.port)
        link.unlink(missing_ok=True)
        link.symlink_to(os.ttyname(slave))

    def _unplug(self) -> None:
        if self._link_dir is not None:
            Path(self.port).unlink(missing_ok=True)
        if self._master is not None:
            if self._selector is not None:
                self._selector.unregister(self._master)
            os.close(self._master)
            self._master = None
        # The emulator keeps the slave open while plugged so that the master never sees a
        # hang-up between two of the driver's connections.
        if self._slave is not None:
            os.close(self._slave)
            self._slave = None

    def _close_all(self) -> None:
        super()._close_all()
        if self._link_dir is not None and not self._link_dir_given:
            shutil.rmtree(self._link_dir, ignore_errors=True)
            self._link_dir = None
