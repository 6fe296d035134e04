"""A hardware trigger controller: a microcontroller pulse generator (an Arduino-class board)
whose outputs trigger the cameras of each unit, over a small ASCII protocol on USB-serial.

Each unit's cameras hang on one output (and the unit's LED controller's trigger input on the
same output, so its strobe and its cameras' exposures start on the same edge). The rig's
sequence is one output mask per step, so ``[left, right]`` interleaves the two units pulse by
pulse at the camera rate; the box's own timer fires a pulse scheduled ahead at its moment, and
it reports every pulse with its number and its own time, which the driver maps onto the rig's
clock. The rig matches each frame to its pulse by time and counts a pulse whose frame never came
as a missed trigger (:meth:`~eyeserver.hardware.base.Trigger.record_missed`), shown in
:meth:`TriggerBoxTrigger.describe` and so in the device's status.

The protocol (version 1; commands end in LF, each reply is one line ended by CR LF):

=====================  ==========================================================================
``ID``                 ``EYETRIG 1 <outputs>`` (on open: the box answers, and has the outputs
                       the configuration names)
``RST``                ``OK``: pulse counter and sequence position to 0 (on open)
``PW <us>``            ``OK``: output pulse width, microseconds (on open)
``SEQ <m>[,<m>...]``   ``OK``: the sequence of output masks (bit ``k``: output ``k + 1``), from its
                       first step
``FIRE [<t_us>]``      ``P <index> <t_us> <mask>``: the pulse fired now, or at box time ``t_us``
``CLK``                ``T <t_us>``: the box's clock, microseconds (on open, for the clock mapping)
=====================  ==========================================================================

An error answers ``ERR <n> <text>``. Every reply is checked: a pulse whose number or mask is not
the one expected (the box was reset or lost a command) is a :class:`~eyeserver.errors.DeviceError`.

Not confirmed on hardware: no firmware for this protocol ships with eyeserver, and the driver is
tested only against :class:`~eyeserver.hardware.emulators.triggerbox.TriggerBoxEmulator`
(docs/notes/camera-drivers.md, "The trigger box"). The box's clock is mapped with one offset taken
at open (no drift correction): a crystal's 50 ppm is 0.2 ms over an hour's session.
"""

from __future__ import annotations

import re
import threading
from collections.abc import Mapping

from eyeserver.errors import DeviceError, DeviceValueError
from eyeserver.hardware.base import PacedTrigger, TriggerPulse, TriggerStep
from eyeserver.hardware.drivers.serialline import ReplyError, SerialLine
from eyeserver.hardware.registry import DriverContext, register_driver

__all__ = ["PROTOCOL", "TriggerBoxTrigger"]

PROTOCOL = 1
"""The protocol version the driver speaks."""

_ID = re.compile(r"EYETRIG (\d+) (\d+)")
_PULSE = re.compile(r"P (\d+) (\d+) (\d+)")
_CLOCK = re.compile(r"T (\d+)")
_ERROR = re.compile(r"ERR (\d+)(?: (.*))?")

_MAX_AHEAD_S = 2.0
"""The furthest ahead the box schedules a pulse, seconds (protocol limit)."""


@register_driver("trigger", "TriggerBoxTrigger")
class TriggerBoxTrigger(PacedTrigger):
    """The trigger box: pulses on its outputs, each exposing the cameras wired to it.

    Parameters
    ----------
    device_id : str
        The trigger's id.
    context : DriverContext
        The rig's clock (pulse times are mapped onto it).
    port : str
        The box's serial port (``/dev/ttyACM0``, a ``/dev/serial/by-id/...`` link).
    outputs : mapping of str to int
        Which output (from 1) triggers each camera, by camera id: a unit's cameras share one.
    pulse_us : int
        Output pulse width, microseconds (the cameras' trigger inputs need a few).
    baudrate : int
        The box's baud rate.
    timeout_s : float
        Time allowed for each reply, seconds.
    """

    def __init__(self, device_id: str, *, context: DriverContext, port: str,
                 outputs: Mapping[str, int], pulse_us: int = 100, baudrate: int = 115200,
                 timeout_s: float = 0.5) -> None:
        super().__init__(device_id, context.clock)
        if not outputs:
            raise ValueError("outputs must wire at least one camera to an output")
        for camera_id, output in outputs.items():
            if not isinstance(output, int) or not 1 <= output <= 8:
                raise ValueError(f"outputs: camera {camera_id!r} on output {output!r}; "
                                 "outputs are numbered 1 to 8")
        if not 1 <= pulse_us <= 100_000:
            raise ValueError(f"pulse_us must be 1 to 100000, not {pulse_us}")
        self.outputs = dict(outputs)
        self.pulse_us = int(pulse_us)
        self.box_outputs: int | None = None
        self._offset_ns = 0
        self._masks: tuple[int, ...] = ()
        self._position = 0
        self._next_index = 0
        self._last_index: int | None = None
        self._fire_lock = threading.Lock()
        self._line = SerialLine(device_id, port, baudrate=baudrate, timeout_s=timeout_s,
                                write_terminator=b"\n", reply_terminator=b"\r\n")

    def _do_open(self) -> None:
        self._line.open()
        try:
            protocol, outputs = self._request("ID", _ID)
            if int(protocol) != PROTOCOL:
                raise DeviceError(self.id, f"the box on {self._line.port} speaks protocol "
                                           f"{protocol}, not {PROTOCOL}")
            self.box_outputs = int(outputs)
            beyond = sorted(c for c, o in self.outputs.items() if o > self.box_outputs)
            if beyond:
                raise DeviceError(self.id, f"the box on {self._line.port} has "
                                           f"{self.box_outputs} outputs; camera(s) "
                                           f"{', '.join(beyond)} are wired beyond them")
            self._request("RST", None)
            self._request(f"PW {self.pulse_us}", None)
            self._map_clock()
            with self._fire_lock:
                self._masks, self._position, self._next_index = (), 0, 0
                self._last_index = None
        except BaseException:
            self._line.close()
            raise

    def _do_close(self) -> None:
        self.stop()
        self._line.close()

    def _map_clock(self) -> None:
        """Offset of the box's clock from the rig's, from the ``CLK`` read that took least
        time of a few (its reply came from between the two host readings)."""
        best: tuple[int, int] | None = None
        for _ in range(3):
            before = self._clock.now_ns()
            (box_us,) = self._request("CLK", _CLOCK)
            after = self._clock.now_ns()
            if best is None or after - before < best[0]:
                best = (after - before, (before + after) // 2 - int(box_us) * 1000)
        assert best is not None
        self._offset_ns = best[1]

    def _apply_rate_hz(self, value: float) -> None:
        pass  # the paced thread reads the rate at every pulse

    def _apply_sequence(self, steps: tuple[TriggerStep, ...]) -> None:
        masks = [self._mask(n, step) for n, step in enumerate(steps)]
        with self._fire_lock:
            self._request("SEQ " + ",".join(str(m) for m in masks), None)
            self._sequence = steps
            self._masks = tuple(masks)
            self._position = 0

    def _mask(self, n: int, step: TriggerStep) -> int:
        unwired = [c for c in step.cameras if c not in self.outputs]
        if unwired:
            raise DeviceValueError(self.id, f"sequence step {n} exposes camera(s) "
                                            f"{', '.join(unwired)}, wired to no output")
        lines = {self.outputs[c] for c in step.cameras}
        # An output exposes every camera on it: one the step does not name would take an extra
        # frame, which a later pulse would then be given.
        extra = sorted(c for c, o in self.outputs.items() if o in lines and c not in step.cameras)
        if extra:
            raise DeviceValueError(self.id, f"sequence step {n} would also expose "
                                            f"{', '.join(extra)} (same output)")
        return sum(1 << (line - 1) for line in lines)

    def _fire(self, at_ns: int | None) -> TriggerPulse:
        command = "FIRE"
        timeout_s = self._line.timeout_s
        if at_ns is not None:
            ahead_s = (at_ns - self._clock.now_ns()) / 1e9
            if ahead_s > _MAX_AHEAD_S:
                self._clock.sleep(ahead_s - _MAX_AHEAD_S / 2)
                ahead_s = _MAX_AHEAD_S / 2
            if ahead_s > 0:
                command = f"FIRE {(at_ns - self._offset_ns) // 1000}"
                timeout_s += ahead_s
        with self._fire_lock:
            index, box_us, mask = (int(v) for v in self._request(command, _PULSE, timeout_s))
            expected = self._masks[self._position % len(self._masks)]
            if index != self._next_index or mask != expected:
                raise DeviceError(self.id, f"the box on {self._line.port} fired pulse {index} "
                                           f"on outputs {mask:#x}; expected pulse "
                                           f"{self._next_index} on {expected:#x} (was it reset?)")
            step = self._sequence[self._position % len(self._sequence)]
            self._position += 1
            self._next_index = index + 1
            self._last_index = index
            return TriggerPulse(index=index, t_ns=box_us * 1000 + self._offset_ns, step=step)

    def _request(self, command: str, reply: re.Pattern[str] | None,
                 timeout_s: float | None = None) -> tuple[str, ...]:
        """Send ``command``; the groups of its reply (``reply`` None: ``OK`` expected)."""

        def check(text: str) -> tuple[str, ...]:
            text = text.strip()
            error = _ERROR.fullmatch(text)
            if error is not None:
                raise DeviceError(self.id, f"the box on {self._line.port} refused {command!r}: "
                                           f"{text}")
            if reply is None:
                if text != "OK":
                    raise ReplyError("expected OK")
                return ()
            match = reply.fullmatch(text)
            if match is None:
                raise ReplyError(f"expected {reply.pattern!r}")
            return match.groups()

        return self._line.request(command, check, timeout_s=timeout_s)

    def describe(self) -> dict[str, object]:
        return {**super().describe(), "port": self._line.port, "outputs": dict(self.outputs),
                "pulse_us": self.pulse_us, "box_outputs": self.box_outputs,
                "last_pulse": self._last_index, "connected": self._line.connected}
