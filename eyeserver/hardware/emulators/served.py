"""The base of the device emulators served by a thread of their own: the pty emulators
(:mod:`~eyeserver.hardware.emulators.serialpty`) and the Modbus TCP one
(:mod:`~eyeserver.hardware.emulators.modbus`).

One thread waits on a selector for what the driver sends and answers it; control calls from the
test (:meth:`~ServedEmulator.unplug`, :meth:`~ServedEmulator.replug`,
:meth:`~ServedEmulator.stop`) are queued and the thread woken through a pipe to run them, so it
alone opens and closes the emulator's file descriptors and none is closed under a ``select``
that still uses it. A subclass says how the device is plugged in and out (``_plug``,
``_unplug``) and what to do with what became readable (``_readable``).
"""

from __future__ import annotations

import abc
import enum
import os
import queue
import selectors
import threading
from types import TracebackType
from typing import Self

__all__ = ["Behaviour", "ServedEmulator"]

_CALL_TIMEOUT_S = 5.0
"""How long a control call (unplug, replug, stop) waits for the serving thread, seconds."""


class Behaviour(enum.Enum):
    """How the emulator answers the commands it reads."""

    NORMAL = "normal"
    """As the device does."""
    GARBAGE = "garbage"
    """With bytes that are not a reply (the pty emulators: see
    :meth:`~eyeserver.hardware.emulators.serialpty.SerialPtyEmulator.garbage`)."""
    SILENT = "silent"
    """Not at all."""


class ServedEmulator(abc.ABC):
    """An emulated device served by a thread; use as a context manager or call start()/stop().

    Attributes
    ----------
    behaviour : Behaviour
        How commands are answered; may be changed at any time.
    failures : list of Exception
        Emulator bugs met while serving; :meth:`stop` raises the first.
    """

    _failure_message = "the emulator failed {count} time(s)"
    """What :meth:`stop` says when the emulator failed while serving."""

    def __init__(self) -> None:
        self.behaviour = Behaviour.NORMAL
        self.failures: list[Exception] = []
        self._selector: selectors.BaseSelector | None = None
        self._wake_r: int | None = None
        self._wake_w: int | None = None
        self._thread: threading.Thread | None = None
        self._calls: queue.SimpleQueue[tuple[str, threading.Event]] = queue.SimpleQueue()

    # --- the device: subclasses -------------------------------------------------------------

    @property
    @abc.abstractmethod
    def plugged(self) -> bool:
        """Whether the driver can reach the device."""

    @abc.abstractmethod
    def _thread_name(self) -> str:
        """The serving thread's name (called once plugged)."""

    @abc.abstractmethod
    def _plug(self) -> None:
        """Make the device reachable and register what the thread waits on with
        ``self._selector``."""

    @abc.abstractmethod
    def _unplug(self) -> None:
        """Make the device unreachable, unregistering and closing what :meth:`_plug` opened;
        nothing when it is unplugged."""

    @abc.abstractmethod
    def _readable(self, key: selectors.SelectorKey) -> None:
        """Handle what became readable on one of the device's registered file objects."""

    # --- life cycle ---------------------------------------------------------------------------

    def start(self) -> None:
        """Plug the device in and start serving. Idempotent."""
        if self._thread is not None:
            return
        self._wake_r, self._wake_w = os.pipe()
        self._selector = selectors.DefaultSelector()
        self._selector.register(self._wake_r, selectors.EVENT_READ)
        try:
            self._plug()
        except BaseException:
            self._close_all()
            raise
        self._thread = threading.Thread(target=self._serve, name=self._thread_name(),
                                        daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop serving and close everything the emulator opened. Idempotent.

        Raises
        ------
        RuntimeError
            The emulator failed while serving (the first such exception is its cause).
        """
        if self._thread is not None:
            self._call("stop")
            self._thread.join(_CALL_TIMEOUT_S)
            self._thread = None
        self._close_all()
        if self.failures:
            failures, self.failures = self.failures, []
            raise RuntimeError(self._failure_message.format(count=len(failures))
                               ) from failures[0]

    def unplug(self) -> None:
        """Pull the cable: the driver cannot reach the device until :meth:`replug` (how it
        fails is the subclass's)."""
        self._call("unplug")

    def replug(self) -> None:
        """Plug the cable back in, where the driver found the device before."""
        self._call("replug")

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 traceback: TracebackType | None) -> None:
        self.stop()

    # --- the serving thread -------------------------------------------------------------------

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
                else:
                    self._readable(key)

    def _run_calls(self) -> bool:
        """Run the queued control calls; True when told to stop."""
        stopping = False
        while not self._calls.empty():
            action, done = self._calls.get()
            if action in ("unplug", "stop"):
                self._unplug()
                stopping = stopping or action == "stop"
            elif action == "replug" and not self.plugged:
                self._plug()
            done.set()
        return stopping

    def _close_all(self) -> None:
        """Unplug, and close the selector and the wake-up pipe (after the thread has ended, or
        when it never started)."""
        self._unplug()
        if self._selector is not None:
            self._selector.close()
            self._selector = None
        for fd in (self._wake_r, self._wake_w):
            if fd is not None:
                os.close(fd)
        self._wake_r = self._wake_w = None
