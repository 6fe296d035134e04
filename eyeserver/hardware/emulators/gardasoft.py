"""An emulated Gardasoft RT-series LED lighting controller on a pty (RS232 models: RT260 etc.).

It speaks the subset of the ASCII command protocol that
:class:`~eyeserver.hardware.drivers.gardasoft.GardasoftProjector` uses, as Gardasoft's RTxxx
manual describes it: two-letter commands with comma-separated numeric parameters, ended by CR;
times in milliseconds unless suffixed ``s``/``ms``/``us``, currents in amps unless suffixed
``A``/``mA``; several commands on one line separated by ``;``. The controller answers each
command with its output lines (CR LF after each) and then the prompt ``>``; a command it cannot
carry out answers ``Err <n>`` instead.

=====================  ===========================================================================
``VR``                 the firmware version line
``RSc,s``              channel ``c`` continuous at current ``s``
``RTc,p,d,s[,r]``      channel ``c`` pulsed: width ``p``, delay ``d``, current ``s`` (retrigger
                       ``r``), on each trigger
``STc``                channel ``c``'s settings, one line (format: :meth:`GardasoftEmulator.status`)
``GR``                 the last event or error as ``Evt<c>,<e>`` (nothing if none), then clears
                       them all
``TRc``                simulate a trigger on input ``c`` (counts a pulse on a pulsed channel)
=====================  ===========================================================================

Errors, numbered as in the manual: ``Err 1`` a parameter value is invalid (a channel the unit
does not have, a negative time or current), ``Err 2`` command not recognised, ``Err 3`` a number
in the wrong format, ``Err 4`` wrong number of parameters, ``Err 5`` (a warning) a parameter was
out of range and has been adjusted: a current above the channel's rating is set to the rating, a
delay below :attr:`~GardasoftEmulator.min_delay_us` to that minimum. Events queued with
:meth:`~GardasoftEmulator.raise_event` (an over-current on a channel, say) are what ``GR``
reports.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from eyeserver.hardware.emulators.serialpty import SerialPtyEmulator

__all__ = ["GardasoftChannel", "GardasoftEmulator"]

_TIME_UNITS_US = {"": 1000.0, "ms": 1000.0, "us": 1.0, "s": 1_000_000.0}
_CURRENT_UNITS_A = {"": 1.0, "a": 1.0, "ma": 0.001}
_NUMBER = re.compile(r"\s*([-+]?(?:\d+\.?\d*|\.\d+))\s*([a-zA-Z]*)\s*")


class _CommandError(Exception):
    def __init__(self, code: int) -> None:
        super().__init__(f"Err {code}")
        self.code = code


@dataclass
class GardasoftChannel:
    """One output channel's settings.

    ``mode`` is ``"off"`` (never set since power-up), ``"continuous"`` or ``"pulse"``;
    ``current_a`` the continuous or pulse current, amps; ``pulse_us``, ``delay_us`` and
    ``retrigger_us`` the pulse timing, microseconds; ``pulses`` the pulses fired by ``TR``.
    """

    mode: str = "off"
    current_a: float = 0.0
    pulse_us: float = 0.0
    delay_us: float = 0.0
    retrigger_us: float = 0.0
    pulses: int = 0


class GardasoftEmulator(SerialPtyEmulator):
    """An RT-series controller with ``channels`` outputs, each rated ``rating_a`` amps.

    Parameters
    ----------
    channels : int
        Number of outputs (1 to 8).
    rating_a : float
        The most current an output gives, amps; more is clamped with ``Err 5``.
    min_delay_us : float
        The shortest pulse delay, microseconds; less is raised to it with ``Err 5``.
    echo : bool
        Echo each command line (followed by CR LF) before its reply, as a terminal session
        with the controller shows it.
    model : str
        What ``VR`` answers.
    link_dir, name
        As for :class:`~eyeserver.hardware.emulators.serialpty.SerialPtyEmulator`.

    Attributes
    ----------
    channels : dict of int to GardasoftChannel
        Channel state by channel number (from 1).
    events : list of (int, int)
        Events not yet read by ``GR``, oldest first: (channel, event code).
    """

    command_terminators = b"\r\n"
    line_end = b"\r\n"
    prompt = b">"

    def __init__(self, channels: int = 2, *, rating_a: float = 3.0, min_delay_us: float = 0.0,
                 echo: bool = False, model: str = "RT260-20 (emulated) V001",
                 link_dir: str | Path | None = None, name: str = "gardasoft") -> None:
        super().__init__(link_dir=link_dir, name=name)
        if not 1 <= channels <= 8:
            raise ValueError(f"channels must be 1 to 8, not {channels}")
        self.channels = {n: GardasoftChannel() for n in range(1, channels + 1)}
        self.rating_a = float(rating_a)
        self.min_delay_us = float(min_delay_us)
        self.echo = echo
        self.model = model
        self.events: list[tuple[int, int]] = []

    def raise_event(self, channel: int, code: int) -> None:
        """Queue event ``code`` on ``channel`` (0: the unit), as the controller does when a
        light fails (e.g. 131 over-current, 130 over-temperature)."""
        with self.lock:
            self.events.append((channel, code))

    def status(self, channel: int) -> str:
        """The ``ST`` line for ``channel``, in the ``KEY value, KEY value`` form of the manual's
        ``ST0`` example: ``CH 1, MD P, PW 100.0us, DL 20.0us, S 1.500A``; ``MD`` is ``C``
        (continuous), ``P`` (pulse) or ``-`` (not set)."""
        state = self.channels[channel]
        mode = {"continuous": "C", "pulse": "P"}.get(state.mode, "-")
        return (f"CH {channel}, MD {mode}, PW {state.pulse_us:.1f}us, DL {state.delay_us:.1f}us, "
                f"S {state.current_a:.3f}A")

    def garbage(self, command: str) -> bytes:
        """Non-ASCII noise ended by the prompt, so the driver gets a complete, unparsable
        reply at once."""
        return b"\xfe\x92~\x00\x8f?#" + self.prompt

    def reply(self, command: str) -> bytes:
        out = command.encode("ascii", errors="replace") + self.line_end if self.echo else b""
        for part in command.split(";"):
            part = part.replace(" ", "")
            if not part:
                continue
            try:
                lines = self._execute(part)
            except _CommandError as exc:
                lines = [str(exc)]
            out += b"".join(line.encode("ascii") + self.line_end for line in lines)
        return out + self.prompt

    def _execute(self, command: str) -> list[str]:
        code, arguments = command[:2].upper(), command[2:]
        params = arguments.split(",") if arguments else []
        if code == "VR":
            self._count(params, 0)
            return [self.model]
        if code == "GR":
            self._count(params, 0)
            if not self.events:
                return []
            channel, event = self.events[-1]
            self.events.clear()
            return [f"Evt{channel},{event}"]
        if code == "ST":
            self._count(params, 1)
            return [self.status(self._channel(params[0]))]
        if code == "TR":
            self._count(params, 1)
            state = self.channels[self._channel(params[0])]
            if state.mode == "pulse":
                state.pulses += 1
            return []
        if code == "RS":
            self._count(params, 2)
            channel = self._channel(params[0])
            current, adjusted = self._current(params[1])
            state = self.channels[channel]
            state.mode, state.current_a = "continuous", current
            return ["Err 5"] if adjusted else []
        if code == "RT":
            if len(params) not in (4, 5):
                raise _CommandError(4)
            channel = self._channel(params[0])
            pulse_us = self._time_us(params[1])
            delay_us = self._time_us(params[2])
            current, adjusted = self._current(params[3])
            retrigger_us = self._time_us(params[4]) if len(params) == 5 else 0.0
            if pulse_us <= 0:
                raise _CommandError(1)
            if delay_us < self.min_delay_us:
                delay_us, adjusted = self.min_delay_us, True
            state = self.channels[channel]
            state.mode, state.current_a = "pulse", current
            state.pulse_us, state.delay_us, state.retrigger_us = pulse_us, delay_us, retrigger_us
            return ["Err 5"] if adjusted else []
        raise _CommandError(2)

    @staticmethod
    def _count(params: list[str], expected: int) -> None:
        if len(params) != expected:
            raise _CommandError(4)

    def _channel(self, text: str) -> int:
        if not text.isdigit():
            raise _CommandError(3)
        channel = int(text)
        if channel not in self.channels:
            raise _CommandError(1)
        return channel

    @staticmethod
    def _number(text: str, units: dict[str, float]) -> float:
        match = _NUMBER.fullmatch(text)
        if match is None:
            raise _CommandError(3)
        scale = units.get(match.group(2).lower())
        if scale is None:
            raise _CommandError(3)
        value = float(match.group(1)) * scale
        if value < 0:
            raise _CommandError(1)
        return value

    def _time_us(self, text: str) -> float:
        return self._number(text, _TIME_UNITS_US)

    def _current(self, text: str) -> tuple[float, bool]:
        current = self._number(text, _CURRENT_UNITS_A)
        if current > self.rating_a:
            return self.rating_a, True
        return current, False
