"""An emulated trigger box on a pty: a microcontroller pulse generator whose outputs expose the
cameras of a unit (and strobe that unit's LED controller), speaking the trigger box protocol of
:mod:`eyeserver.hardware.drivers.triggerbox`.

Commands end in LF (CR is ignored); every reply is one line ended by CR LF:

=====================  ==========================================================================
``ID``                 ``EYETRIG <protocol> <outputs>``: what the box is
``RST``                ``OK``: the pulse counter and the sequence position back to 0
``PW <us>``            ``OK``: the width of every output pulse, microseconds (1 to 100000)
``SEQ <m>[,<m>...]``   ``OK``: the sequence of output masks (bit ``k`` drives output ``k + 1``),
                       up to 16 steps; restarts it at its first step
``FIRE [<t_us>]``      fire the sequence's next step now, or at box time ``t_us`` when that is
                       ahead (at most :data:`MAX_AHEAD_US`), and answer
                       ``P <index> <t_us> <mask>``: the pulse's number since ``RST``, the box time
                       its rising edge left, the outputs it drove
``CLK``                ``T <t_us>``: the box's clock, microseconds since power-up
``CNT``                ``C <pulses>``: pulses fired since ``RST``
=====================  ==========================================================================

A command the box cannot carry out answers ``ERR <n> <text>``: 1 unknown command, 2 a parameter
is missing, malformed or out of range, 3 ``FIRE`` with no sequence set, 4 ``FIRE`` too far ahead.

The wires: :meth:`TriggerBoxEmulator.wire` connects an output to a callable that stands for what
hangs on it (a camera's trigger input: in the tests, the camera driver's software trigger), called
on the serving thread as the pulse leaves, before the reply. What the tests break:
:meth:`~TriggerBoxEmulator.drop_next` loses the next pulse of an output on its way to the
cameras (the box counts and reports it, the cameras never see it: a loose trigger cable, a
camera that missed the edge), :meth:`~TriggerBoxEmulator.delay_next` makes it reach them late
(their frame then arrives after the rig gave up on it).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path

from eyeserver.hardware.emulators.serialpty import SerialPtyEmulator

__all__ = ["MAX_AHEAD_US", "PROTOCOL", "TriggerBoxEmulator"]

PROTOCOL = 1
"""The protocol version ``ID`` reports."""

MAX_AHEAD_US = 2_000_000
"""The furthest ahead a ``FIRE`` may be scheduled, microseconds."""

_MAX_STEPS = 16

_log = logging.getLogger(__name__)


def _deliver(receiver: Callable[[], None], output: int) -> None:
    # What hangs on a wire is not the box: a camera that cannot take the pulse (closed, gone)
    # simply misses it, and the box goes on.
    try:
        receiver()
    except Exception as exc:
        _log.info("output %d: the pulse did not reach a receiver: %s", output, exc)


class _CommandError(Exception):
    def __init__(self, code: int, text: str) -> None:
        super().__init__(f"ERR {code} {text}")


class TriggerBoxEmulator(SerialPtyEmulator):
    """A trigger box with ``outputs`` output lines.

    Parameters
    ----------
    outputs : int
        Number of outputs (1 to 8).
    link_dir, name
        As for :class:`~eyeserver.hardware.emulators.serialpty.SerialPtyEmulator`.

    Attributes
    ----------
    pulses : list of tuple
        Every pulse fired since start, oldest first: (index, box time in µs, mask).
    lost : list of tuple
        (pulse index, output) of every pulse that :meth:`drop_next` kept from its cameras.
    pulse_us : int
        The pulse width last set.
    """

    command_terminators = b"\n"
    line_end = b"\r\n"

    def __init__(self, outputs: int = 4, *, link_dir: str | Path | None = None,
                 name: str = "triggerbox") -> None:
        super().__init__(link_dir=link_dir, name=name)
        if not 1 <= outputs <= 8:
            raise ValueError(f"outputs must be 1 to 8, not {outputs}")
        self.outputs = outputs
        self.pulse_us = 1000
        self.pulses: list[tuple[int, int, int]] = []
        self.lost: list[tuple[int, int]] = []
        self._wires: dict[int, list[Callable[[], None]]] = {n: [] for n in range(1, outputs + 1)}
        self._drop: dict[int, int] = {}
        self._delay_s: dict[int, float] = {}
        self._sequence: list[int] = []
        self._position = 0
        self._count = 0
        self._epoch_ns = time.monotonic_ns()

    def wire(self, output: int, receiver: Callable[[], None]) -> None:
        """Connect ``receiver`` to ``output``: it is called once for every pulse the output
        carries to it."""
        with self.lock:
            self._wires[self._output(output)].append(receiver)

    def drop_next(self, output: int, pulses: int = 1) -> None:
        """Lose the next ``pulses`` pulses of ``output`` between the box and its cameras."""
        with self.lock:
            output = self._output(output)
            self._drop[output] = self._drop.get(output, 0) + pulses

    def delay_next(self, output: int, delay_s: float) -> None:
        """Let the next pulse of ``output`` reach its cameras ``delay_s`` late."""
        with self.lock:
            self._delay_s[self._output(output)] = delay_s

    def now_us(self) -> int:
        """The box's clock, microseconds since it was made."""
        return (time.monotonic_ns() - self._epoch_ns) // 1000

    def _output(self, output: int) -> int:
        if output not in self._wires:
            raise ValueError(f"output must be 1 to {self.outputs}, not {output}")
        return output

    def reply(self, command: str) -> bytes:
        words = command.strip().split()
        if not words:
            return b""
        try:
            line = self._execute(words[0].upper(), words[1:])
        except _CommandError as exc:
            line = str(exc)
        return line.encode("ascii") + self.line_end

    def _execute(self, code: str, params: list[str]) -> str:
        if code == "ID":
            self._count_params(params, 0)
            return f"EYETRIG {PROTOCOL} {self.outputs}"
        if code == "RST":
            self._count_params(params, 0)
            self._count, self._position = 0, 0
            return "OK"
        if code == "PW":
            self._count_params(params, 1)
            self.pulse_us = self._integer(params[0], 1, 100_000)
            return "OK"
        if code == "SEQ":
            self._count_params(params, 1)
            masks = [self._integer(m, 1, 2**self.outputs - 1) for m in params[0].split(",")]
            if len(masks) > _MAX_STEPS:
                raise _CommandError(2, f"at most {_MAX_STEPS} steps")
            self._sequence, self._position = masks, 0
            return "OK"
        if code == "CLK":
            self._count_params(params, 0)
            return f"T {self.now_us()}"
        if code == "CNT":
            self._count_params(params, 0)
            return f"C {self._count}"
        if code == "FIRE":
            if len(params) > 1:
                raise _CommandError(2, "FIRE takes at most a time")
            if not self._sequence:
                raise _CommandError(3, "no sequence")
            at_us = self._integer(params[0], 0, 2**63) if params else None
            return self._fire(at_us)
        raise _CommandError(1, f"unknown command {code}")

    def _fire(self, at_us: int | None) -> str:
        now = self.now_us()
        if at_us is not None and at_us > now:
            if at_us - now > MAX_AHEAD_US:
                raise _CommandError(4, "too far ahead")
            # The box's timer fires the edge then; the serving thread simply waits for it.
            time.sleep((at_us - now) / 1e6)
            now = at_us
        mask = self._sequence[self._position % len(self._sequence)]
        self._position += 1
        index, self._count = self._count, self._count + 1
        self.pulses.append((index, now, mask))
        for output in range(1, self.outputs + 1):
            if not mask & (1 << (output - 1)):
                continue
            if self._drop.get(output, 0) > 0:
                self._drop[output] -= 1
                self.lost.append((index, output))
                continue
            delay_s = self._delay_s.pop(output, 0.0)
            for receiver in self._wires[output]:
                if delay_s > 0:
                    timer = threading.Timer(delay_s, _deliver, args=(receiver, output))
                    timer.daemon = True
                    timer.start()
                else:
                    _deliver(receiver, output)
        return f"P {index} {now} {mask}"

    @staticmethod
    def _count_params(params: list[str], expected: int) -> None:
        if len(params) != expected:
            raise _CommandError(2, f"expected {expected} parameter(s)")

    @staticmethod
    def _integer(text: str, low: int, high: int) -> int:
        if not text.isdigit():
            raise _CommandError(2, f"not a number: {text}")
        value = int(text)
        if not low <= value <= high:
            raise _CommandError(2, f"{value} outside {low}..{high}")
        return value
