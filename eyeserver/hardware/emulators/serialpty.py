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
:meth:`~SerialPtyEmulator.garbage`. All file descriptors are opened and closed by the serving
thread (control calls are handed to it), so none is closed under a ``select`` that still uses it.
"""

from __future__ import annotations

import abc
import contextlib
import enum
import logging
import os
import pty
import queue
import selectors
import shutil
import tempfile
import threading
import tty
from pathlib import Path
from types import TracebackType
from typing import Self

__all__ = ["Behaviour", "SerialPtyEmulator"]

_log = logging.getLogger(__name__)

_CALL_TIMEOUT_S = 5.0
"""How long a control call (unplug, replug, stop) waits for the serving thread, seconds."""


class Behaviour(enum.Enum):
    """How the emulator answers the commands it reads."""

    NORMAL = "normal"
    """As the device does."""
    GARBAGE = "garbage"
    """With bytes that are not a reply (see :meth:`SerialPtyEmulator.garbage`)."""
    SILENT = "silent"
    """Not at all."""


class SerialPtyEmulator(abc.ABC):
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

    def __init__(self, *, link_dir: str | Path | None = None, name: str = "tty") -> None:
        if not name or "/" in name:
            raise ValueError(f"name must be a plain file name, not {name!r}")
        self._link_dir_given = link_dir is not None
        self._link_dir = Path(link_dir) if link_dir is not None else None
        self._name = name
        self.behaviour = Behaviour.NORMAL
        self.received: list[str] = []
        self.failures: list[Exception] = []
        self.lock = threading.RLock()
        self._master: int | None = None
        self._slave: int | None = None
        self._wake_r: int | None = None
        self._wake_w: int | None = None
        self._thread: threading.Thread | None = None
        self._calls: queue.SimpleQueue[tuple[str, threading.Event]] = queue.SimpleQueue()
        self._selector: selectors.BaseSelector | None = None
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

    def start(self) -> None:
        """Make the pty, point :attr:`port` at it and start serving. Idempotent."""
        if self._thread is not None:
            return
        if self._link_dir is None:
            self._link_dir = Path(tempfile.mkdtemp(prefix="eyeserver-pty-"))
        self._wake_r, self._wake_w = os.pipe()
        self._selector = selectors.DefaultSelector()
        self._selector.register(self._wake_r, selectors.EVENT_READ)
        try:
            self._plug()
        except BaseException:
            self._close_all()
            raise
        self._thread = threading.Thread(target=self._serve, name=f"serialpty-{self._name}",
                                        daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop serving, close the pty and remove the symlink (and its temporary directory).
        Idempotent.

        Raises
        ------
        RuntimeError
            :meth:`reply` raised while serving (the first such exception is its cause).
        """
        if self._thread is not None:
            self._call("stop")
            self._thread.join(_CALL_TIMEOUT_S)
            self._thread = None
        self._close_all()
        if self.failures:
            failures, self.failures = self.failures, []
            raise RuntimeError(f"the emulator failed to answer {len(failures)} command(s)"
                               ) from failures[0]

    def unplug(self) -> None:
        """Pull the cable: close the pty and remove :attr:`port`."""
        self._call("unplug")

    def replug(self) -> None:
        """Plug the cable back in: a new pty behind the same :attr:`port`."""
        self._call("replug")

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 traceback: TracebackType | None) -> None:
        self.stop()

    # --- the serving thread -------------------------------------------------------------

    def _call(self, action: str) -> None:
        if self._thread is None or self._wake_w is None:
            raise RuntimeError(f"cannot {action}: the emulator is not started")
        done = threading.Event()
        self._calls.put((action, done))
        os.write(self._wake_w, b"x")
        if not done.wait(_CALL_TIMEOUT_S):
            raise RuntimeError(f"the emulator's thread did not {action} within "
                               f"{_CALL_TIMEOUT_S} s")

    def _serve(self) -> None:
        selector = self._selector
        assert selector is not None
        while True:
            for key, _ in selector.select():
                if key.fd == self._wake_r:
                    os.read(key.fd, 512)
                    if self._run_calls():
                        return
                elif key.fd == self._master:
                    try:
                        data = os.read(key.fd, 4096)
                    except OSError:
                        data = b""  # the driver's side hung up; nothing to answer
                    if data:
                        self._feed(data)

    def _run_calls(self) -> bool:
        """Run the queued control calls; True when told to stop."""
        stopping = False
        while not self._calls.empty():
            action, done = self._calls.get()
            if action == "unplug":
                self._unplug()
            elif action == "replug":
                if self._master is None:
                    self._plug()
            elif action == "stop":
                self._unplug()
                stopping = True
            done.set()
        return stopping

    def _feed(self, data: bytes) -> None:
        self._buffer += data
        while True:
            cut = min((i for i in (self._buffer.find(bytes([t]))
                                   for t in self.command_terminators) if i >= 0), default=-1)
            if cut < 0:
                return
            line, self._buffer = self._buffer[:cut], self._buffer[cut + 1:]
            if line:
                self._answer(line.decode("ascii", errors="replace"))

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
        if answer and self._master is not None:
            # A full pty buffer (nobody reads) or a hang-up loses the bytes, as on a real line.
            with contextlib.suppress(OSError):
                os.write(self._master, answer)

    def _plug(self) -> None:
        master, slave = pty.openpty()
        # Raw on both sides of the pty whatever the driver does: no echo, no CR/LF translation.
        tty.setraw(slave)
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        link = Path(self.port)
        link.unlink(missing_ok=True)
        link.symlink_to(os.ttyname(slave))
        assert self._selector is not None
        self._selector.register(master, selectors.EVENT_READ)
        self._buffer = b""

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
        self._unplug()
        if self._selector is not None:
            self._selector.close()
            self._selector = None
        for fd in (self._wake_r, self._wake_w):
            if fd is not None:
                os.close(fd)
        self._wake_r = self._wake_w = None
        if self._link_dir is not None and not self._link_dir_given:
            shutil.rmtree(self._link_dir, ignore_errors=True)
            self._link_dir = None
