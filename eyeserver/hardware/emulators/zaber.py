"""An emulated Zaber motorised linear stage controller on a pty, speaking the Zaber ASCII protocol.

Commands are ``/[device] [axis] [command words]`` ended by CR and/or LF; device 0 or no device
addresses every device, axis 0 or no axis the whole device. A device answers only commands
addressed to it, with one reply line::

    @01 1 OK BUSY -- 0
     │  │ │  │    │  └ data: the value asked for, a rejection reason, or 0
     │  │ │  │    └── the highest-priority warning flag, -- for none
     │  │ │  └─────── BUSY while the axis moves, IDLE otherwise
     │  │ └────────── OK, or RJ for a rejected command
     │  └──────────── the axis the reply is about (0: the device)
     └─────────────── the device's address, two digits

The commands emulated: the empty command (status), ``get pos``, ``get limit.min``,
``get limit.max``, ``move abs <microsteps>``, ``home``, ``stop``, ``warnings`` (data: the number
of flags, then the flags) and ``warnings clear`` (the same, then clears them). Rejections carry
the firmware's reasons: ``BADCOMMAND`` (unknown command), ``BADAXIS`` (no such axis),
``BADDATA`` (a target outside ``limit.min``..``limit.max`` or not an integer).

Warning flags, highest priority first: the faults (``F…``) the test sets with
:meth:`ZaberAxis.fault` or a stall (``FS``, stalled and stopped, at
:attr:`ZaberAxis.stall_at`), then ``WR`` (no reference position) until the axis is homed.

Motion takes time: an axis moves at :attr:`ZaberAxis.speed` microsteps per second, reporting
``BUSY`` until it arrives; :attr:`ZaberAxis.stuck` keeps it ``BUSY`` for ever without arriving
(a jammed carriage whose controller keeps trying).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

from eyeserver.hardware.emulators.serialpty import SerialPtyEmulator

__all__ = ["ZaberAxis", "ZaberEmulator"]


def _priority(flag: str) -> tuple[int, str]:
    return ({"F": 0, "W": 1, "N": 2}.get(flag[:1], 3), flag)


@dataclass
class ZaberAxis:
    """One axis of the emulated device; positions in microsteps, speed in microsteps/s.

    ``homed`` starts False as after power-up (the ``WR`` flag); ``flags`` holds latched fault
    flags until ``warnings clear``; ``stall_at`` makes the next move through that position stop
    there with ``FS``; ``stuck`` keeps every move ``BUSY`` without arriving.
    """

    position: int = 0
    limit_min: int = 0
    limit_max: int = 100_000
    speed: float = 1_000_000.0
    homed: bool = False
    stuck: bool = False
    stall_at: int | None = None
    flags: set[str] = field(default_factory=set)
    busy_replies: int = 0
    _start: int = 0
    _target: int = 0
    _t0: float = 0.0
    _moving: bool = False
    _homing: bool = False

    def fault(self, flag: str) -> None:
        """Latch warning flag ``flag`` (``FS``, ``FQ``, ...) until ``warnings clear``."""
        self.flags.add(flag)

    def update(self, now: float) -> None:
        """Advance the motion to ``now`` (time.monotonic seconds)."""
        if not self._moving:
            return
        if self.stuck:
            return
        travelled = self.speed * (now - self._t0)
        distance = self._target - self._start
        direction = 1 if distance >= 0 else -1
        if self.stall_at is not None and min(self._start, self._target) <= self.stall_at <= max(
                self._start, self._target) and travelled >= abs(self.stall_at - self._start):
            self.position, self._moving, self._homing = self.stall_at, False, False
            self.stall_at = None
            self.flags.add("FS")
            return
        if travelled >= abs(distance):
            self.position, self._moving = self._target, False
            if self._homing:
                self.homed, self._homing = True, False
        else:
            self.position = self._start + direction * int(travelled)

    def move(self, target: int, now: float, *, homing: bool = False) -> None:
        """Start moving to ``target`` microsteps at ``now``."""
        self.update(now)
        self._start, self._target, self._t0 = self.position, target, now
        self._moving, self._homing = True, homing

    def stop(self, now: float) -> None:
        """Stop where the axis is now."""
        self.update(now)
        self._moving = self._homing = False

    @property
    def busy(self) -> bool:
        """Whether the axis is moving (call :meth:`update` first)."""
        return self._moving

    def warning(self) -> str:
        """The highest-priority warning flag, ``--`` for none."""
        flags = self.all_flags()
        return flags[0] if flags else "--"

    def all_flags(self) -> list[str]:
        """Every active flag, highest priority first: faults (F), warnings (W), notes (N)."""
        flags = self.flags | ({"WR"} if not self.homed else set())
        return sorted(flags, key=_priority)


class ZaberEmulator(SerialPtyEmulator):
    """A Zaber device at ``address`` with ``axes`` axes (numbered from 1).

    Parameters
    ----------
    address : int
        The device's address on the daisy chain (1 to 99).
    axes : int
        Number of axes.
    homed : bool
        Start with a reference position (as if homed since power-up) instead of ``WR``.
    link_dir, name
        As for :class:`~eyeserver.hardware.emulators.serialpty.SerialPtyEmulator`.

    Attributes
    ----------
    axes : dict of int to ZaberAxis
        Axis state by axis number.
    """

    command_terminators = b"\r\n"

    def __init__(self, address: int = 1, axes: int = 1, *, homed: bool = False,
                 link_dir: str | Path | None = None, name: str = "zaber") -> None:
        super().__init__(link_dir=link_dir, name=name)
        if not 1 <= address <= 99:
            raise ValueError(f"address must be 1 to 99, not {address}")
        if axes < 1:
            raise ValueError(f"axes must be at least 1, not {axes}")
        self.address = address
        self.axes = {n: ZaberAxis(homed=homed) for n in range(1, axes + 1)}

    def axis(self, number: int = 1) -> ZaberAxis:
        """Axis ``number``, brought up to date (position and BUSY/IDLE as of now)."""
        with self.lock:
            state = self.axes[number]
            state.update(time.monotonic())
            return state

    def reply(self, command: str) -> bytes | None:
        if not command.startswith("/"):
            return None  # not a command; a real device ignores the line
        words = command[1:].split()
        device = 0
        if words and words[0].isdigit():
            device = int(words.pop(0))
        if device not in (0, self.address):
            return None  # addressed to another device on the chain
        axis = 0
        if words and words[0].isdigit():
            axis = int(words.pop(0))
        now = time.monotonic()
        for state in self.axes.values():
            state.update(now)
        if axis != 0 and axis not in self.axes:
            return self._line(axis, "RJ", "BADAXIS")
        return self._execute(axis, words, now)

    def _execute(self, axis: int, words: list[str], now: float) -> bytes:
        targets = [self.axes[axis]] if axis else list(self.axes.values())
        if not words:
            for state in targets:
                state.busy_replies += state.busy
            return self._line(axis, "OK", "0")
        if words == ["stop"]:
            for state in targets:
                state.stop(now)
            return self._line(axis, "OK", "0")
        if words == ["home"]:
            for state in targets:
                state.move(0, now, homing=True)
            return self._line(axis, "OK", "0")
        if words[0] == "warnings" and words[1:] in ([], ["clear"]):
            flags = sorted({flag for state in targets for flag in state.all_flags()},
                           key=_priority)
            if words[1:] == ["clear"]:
                for state in targets:
                    state.flags.clear()
            return self._line(axis, "OK", " ".join([f"{len(flags):02d}", *flags]))
        if words[0] == "get" and len(words) == 2 and words[1] in ("pos", "limit.min",
                                                                    "limit.max"):
            attribute = {"pos": "position", "limit.min": "limit_min",
                         "limit.max": "limit_max"}[words[1]]
            return self._line(axis, "OK", " ".join(str(getattr(state, attribute))
                                                   for state in targets))
        if words[:2] == ["move", "abs"] and len(words) == 3:
            if axis == 0 and len(self.axes) > 1:
                return self._line(axis, "RJ", "BADAXIS")
            state = targets[0]
            try:
                target = int(words[2])
            except ValueError:
                return self._line(axis, "RJ", "BADDATA")
            if not state.limit_min <= target <= state.limit_max:
                return self._line(axis, "RJ", "BADDATA")
            state.move(target, now)
            return self._line(axis, "OK", "0")
        return self._line(axis, "RJ", "BADCOMMAND")

    def _line(self, axis: int, flag: str, data: str) -> bytes:
        states = [self.axes[axis]] if axis in self.axes else list(self.axes.values())
        busy = any(state.busy for state in states)
        flags = sorted((flag for state in states for flag in state.all_flags()), key=_priority)
        return (f"@{self.address:02d} {axis} {flag} {'BUSY' if busy else 'IDLE'} "
                f"{flags[0] if flags else '--'} {data}\r\n").encode("ascii")
