"""One channel of a Gardasoft RT-series LED lighting controller as a fringe projector.

The projector's LED is driven by one output channel of a Gardasoft RTxxx controller on RS232
(RT260, RT460, RT860: 115200 baud, 8N1, no handshake). Commands and replies follow Gardasoft's
RTxxx user manual (section 12, command configuration):

* a command is two letters and comma-separated parameters, ended by CR; times are in
  milliseconds unless suffixed ``us``/``ms``/``s``, currents in amps unless suffixed
  ``A``/``mA`` -- the driver always writes the suffix, so no default unit is assumed;
* the controller answers with any output lines and then the prompt ``>`` (the reply ends at the
  prompt); a command it cannot carry out answers ``Err <n>``.

Commands used, with channel ``c`` (the ``channel`` option):

=============================  ================================================================
``VR``                         on open: the firmware version, to check the controller answers
``GR``                         on open (clearing events left from before) and in
                               :meth:`~eyeserver.hardware.base.Projector.check`: the last event
                               or error, ``Evt<c>,<e>``, or nothing; it clears them
``RTc,<p>us,<d>us,<I>A``       strobe on: pulse for ``pulse_us`` after ``delay_us`` on each
                               trigger, at current ``I``
``RSc,<I>A``                   strobe off: continuous at current ``I``; ``RSc,0A`` on close
``STc``                        in ``check()``: the channel's settings (only checked to be a
                               reply, not an error; its layout varies between models)
=============================  ================================================================

``I`` is ``intensity × max_current_a`` while enabled and 0 A while disabled (a dark LED in the
same mode, so enabling again needs no other command). Every reply is checked: an ``Err <n>``
line is a :class:`~eyeserver.errors.DeviceError` quoting it -- including ``Err 5``, which the
manual calls a warning (a value was out of range and the controller adjusted it), because the
LED would then not do what the configuration says; any other unexpected line is a
:class:`~eyeserver.errors.DeviceError` naming it. ``GR`` events that mean the light failed
(error codes 1-127; 129-132, 139, 140) on this channel or the unit (channel 0) fail ``check()``.

Assumed, not confirmed on hardware: the brightness parameter of ``RS``/``RT`` is a current in
amps (controllers whose SafeSense takes brightness in percent of the light's rating are not
supported); a command line may come back echoed before its reply (tolerated: a first line equal
to the command is dropped); ``GR`` answers on RS232 as it does on Ethernet; output lines end in
CR, LF or both (any is accepted).
"""

from __future__ import annotations

import logging
import re

from eyeserver.errors import DeviceError
from eyeserver.hardware.base import Projector
from eyeserver.hardware.drivers.serialline import ReplyError, SerialLine, answered
from eyeserver.hardware.registry import DriverContext, register_driver

__all__ = ["PROBE_BAUDRATE", "GardasoftProjector", "probe"]

_log = logging.getLogger(__name__)

_ERROR = re.compile(r"Err\s*(\d+)", re.IGNORECASE)
_EVENT = re.compile(r"Evt\s*(\d+)\s*,\s*(\d+)", re.IGNORECASE)

_ERROR_MEANINGS = {
    1: "a parameter value is invalid",
    2: "command not recognised",
    3: "a number is in the wrong format",
    4: "wrong number of parameters",
    5: "a parameter was out of range and the controller adjusted it",
    19: "a light is connected but has no rating",
    44: "the controller is too hot",
    45: "a channel is giving more current than expected",
    46: "a channel is dissipating more than 30 W",
    47: "the output driver's protection stopped it overheating",
}
"""``Err`` numbers from the RTxxx manual's error tables (section 13)."""

_EVENT_MEANINGS = {
    128: "a light was connected and works",
    129: "a light was connected without a current or voltage rating",
    130: "over-temperature",
    131: "over-current",
    132: "sensing the light's rating failed",
    138: "SafePower training completed",
    139: "SafePower training failed or was cancelled",
    140: "the light was switched off because its duty cycle is too high",
}
"""``Evt`` codes from the RTxxx manual (section 13.5); 1-127 are error numbers."""

_HARMLESS_EVENTS = frozenset({128, 138})

PROBE_BAUDRATE = 115200
"""The baud rate :func:`probe` asks at: the RT-series RS232 models' (and the driver's default)."""


def _number(value: float) -> str:
    """A parameter as the controller reads it: plain decimal, no exponent, no trailing zeros."""
    text = f"{value:.3f}".rstrip("0").rstrip(".")
    return "0" if text in ("", "-0") else text


def _lines(text: str) -> list[str]:
    return [line.strip() for line in re.split(r"[\r\n]+", text) if line.strip()]


@register_driver("projector", "GardasoftProjector")
class GardasoftProjector(Projector):
    """A fringe projector's LED on one channel of a Gardasoft RT-series controller (RS232).

    Parameters
    ----------
    device_id : str
        The projector's id.
    context : DriverContext
        Unused (the controller keeps its own time).
    port : str
        The controller's serial port (``/dev/ttyUSB0``, a ``/dev/serial/by-id/...`` link).
    channel : int
        The controller output the LED is wired to, from 1.
    max_current_a : float
        The current at intensity 1, amps: the LED's rating for the pulse width used.
    pulse_us : float
        Strobe pulse width, microseconds: the exposure the LED must cover.
    delay_us : float
        Delay from trigger to pulse, microseconds. Some controllers raise a delay below their
        minimum and answer ``Err 5``, which fails the projector: configure the minimum or more.
    baudrate : int
        The controller's baud rate (115200 on RT-series RS232 models).
    timeout_s : float
        Time allowed for each reply, seconds.
    """

    def __init__(self, device_id: str, *, context: DriverContext, port: str, channel: int,
                 max_current_a: float, pulse_us: float, delay_us: float,
                 baudrate: int = 115200, timeout_s: float = 0.5) -> None:
        super().__init__(device_id)
        if channel < 1:
            raise ValueError(f"channel must be 1 or more, not {channel}")
        if not max_current_a > 0:
            raise ValueError(f"max_current_a must be positive, not {max_current_a}")
        if not pulse_us > 0:
            raise ValueError(f"pulse_us must be positive, not {pulse_us}")
        if not delay_us >= 0:
            raise ValueError(f"delay_us must be 0 or more, not {delay_us}")
        self.channel = int(channel)
        self.max_current_a = float(max_current_a)
        self.pulse_us = float(pulse_us)
        self.delay_us = float(delay_us)
        self.firmware: str | None = None
        self._line = SerialLine(device_id, port, baudrate=baudrate, timeout_s=timeout_s,
                                write_terminator=b"\r", reply_terminator=b">")

    @property
    def current_a(self) -> float:
        """The LED current the settings ask for, amps (0 while disabled)."""
        return self.max_current_a * self.intensity if self.enabled else 0.0

    def _do_open(self) -> None:
        self._line.open()
        try:
            version = self._command("VR")
            if len(version) != 1:
                raise DeviceError(self.id, f"'VR' on {self._line.port} gave {version!r}, "
                                           f"not one version line")
            self.firmware = version[0]
            stale = self._events()
            if stale:
                _log.warning("%s: cleared events left on the controller: %s", self.id,
                             "; ".join(stale), extra={"device_id": self.id})
            self._push(self.enabled, self.intensity, self.strobe)
        except BaseException:
            self._line.close()
            raise

    def _do_close(self) -> None:
        # Dark on close: a channel left continuous would stay lit in the patient's eye after
        # the daemon stops.
        try:
            self._command(f"RS{self.channel},0A")
        except DeviceError as exc:
            _log.warning("%s: could not switch the LED off on close: %s", self.id, exc,
                         extra={"device_id": self.id})
        finally:
            self._line.close()

    def _check(self) -> None:
        status = self._command(f"ST{self.channel}")
        if not status:
            raise DeviceError(self.id, f"'ST{self.channel}' on {self._line.port} gave no status")
        failures = self._events(failures_only=True)
        if failures:
            raise DeviceError(self.id, f"the controller on {self._line.port} reports "
                                       f"{'; '.join(failures)}")

    def _apply_enabled(self, value: bool) -> None:
        self._push(value, self.intensity, self.strobe)

    def _apply_intensity(self, value: float) -> None:
        self._push(self.enabled, value, self.strobe)

    def _apply_strobe(self, value: bool) -> None:
        self._push(self.enabled, self.intensity, value)

    def describe(self) -> dict[str, object]:
        return {**super().describe(), "port": self._line.port, "channel": self.channel,
                "current_a": self.current_a, "pulse_us": self.pulse_us,
                "delay_us": self.delay_us, "firmware": self.firmware}

    def _push(self, enabled: bool, intensity: float, strobe: bool) -> None:
        """Send the one command that puts the channel in the state these settings describe."""
        current = _number(self.max_current_a * intensity if enabled else 0.0)
        if strobe:
            self._command(f"RT{self.channel},{_number(self.pulse_us)}us,"
                          f"{_number(self.delay_us)}us,{current}A")
        else:
            self._command(f"RS{self.channel},{current}A")

    def _events(self, *, failures_only: bool = False) -> list[str]:
        """Read and clear the controller's events with ``GR``, described; with
        ``failures_only`` just those that mean this channel's light (or the unit) failed."""
        described = []
        for line in self._command("GR"):
            match = _EVENT.fullmatch(line)
            if match is None:
                raise DeviceError(self.id, f"unexpected reply to 'GR' on {self._line.port}: "
                                           f"{line!r} (not an event)")
            channel, code = int(match.group(1)), int(match.group(2))
            meaning = _EVENT_MEANINGS.get(code) or _ERROR_MEANINGS.get(code, "error")
            if failures_only and (code in _HARMLESS_EVENTS or channel not in (0, self.channel)):
                _log.info("%s: controller event %s (%s)", self.id, line, meaning,
                          extra={"device_id": self.id})
                continue
            described.append(f"{line} ({meaning})")
        return described

    def _command(self, command: str) -> list[str]:
        """Send ``command``; its output lines, or :class:`DeviceError` for an ``Err`` reply."""

        def check(text: str) -> list[str]:
            lines = _lines(text)
            if lines and lines[0] == command:
                lines = lines[1:]  # the controller echoed the command
            for line in lines:
                match = _ERROR.fullmatch(line)
                if match is not None:
                    meaning = _ERROR_MEANINGS.get(int(match.group(1)), "unknown error")
                    raise DeviceError(self.id, f"the controller on {self._line.port} refused "
                                               f"{command!r}: {line} ({meaning})")
            if command[:2] in ("RS", "RT") and lines:
                raise ReplyError("a setting command answers only the prompt")
            return lines

        return self._line.request(command, check)


def probe(port: str, timeout_s: float = 0.3, *, baudrate: int = PROBE_BAUDRATE) -> str | None:
    """The firmware version line of a Gardasoft RT-series controller on ``port``, or None when
    nothing there answers as one.

    Sends ``VR`` once, as the driver does on open: it only reads the version, so it changes
    nothing on a controller, and other devices ignore it or answer something that is not one
    line ended by the ``>`` prompt. The port is closed again before this returns, whatever
    happens.

    Parameters
    ----------
    port : str
        Device path (``/dev/ttyUSB0``, a ``/dev/serial/by-id/...`` link) or pyserial URL.
    timeout_s : float
        Time allowed for the reply, seconds; silence for this long is "no controller".
    baudrate : int
        Bits per second (8N1).

    Raises
    ------
    DeviceDisconnectedError
        The port cannot be opened (missing, busy, no access) or failed while probing; its
        cause is pyserial's error, with the ``errno`` where the system gave one.
    """
    line = SerialLine(f"probe of {port}", port, baudrate=baudrate, timeout_s=timeout_s,
                      write_terminator=b"\r", reply_terminator=b">")

    def version(text: str) -> str:
        lines = _lines(text)
        if lines and lines[0] == "VR":
            lines = lines[1:]  # the controller echoed the command
        if len(lines) != 1 or _ERROR.fullmatch(lines[0]) is not None:
            raise ReplyError("not one version line")
        return lines[0]

    line.open()
    try:
        # Silence, garbage or another reply: not a Gardasoft controller.
        return answered(lambda: line.request("VR", version))
    finally:
        line.close()
