"""A Zaber motorised linear stage carrying the calibration plate, over Zaber's ASCII protocol.

The stage moves the flat plate along the WCS Z axis for phase-to-height calibration
(:class:`~eyeserver.hardware.base.Stage`). It speaks Zaber's ASCII protocol (firmware 6 and 7)
on RS232 or USB-serial, 115200 baud by default, 8N1. A command is
``/<address> <axis> <command>`` ended by LF; the device answers one line::

    @01 1 OK IDLE -- 1200
    device axis  OK|RJ  BUSY|IDLE  warning flag (-- for none)  data

Commands used, for the configured ``address`` and ``axis``:

========================  ========================================================================
``/a x``                  status (open: the device answers; after a move: polled until IDLE)
``/a x home``             on open, only with ``home_on_open`` and only when the axis has no
                          reference position (``WR``/``WH``, after power-up)
``/a x get limit.min``    on open: the travel the device allows, microsteps, which narrows
``/a x get limit.max``    :attr:`ZaberStage.travel_mm`
``/a x move abs <n>``     move to ``n`` microsteps
``/a x get pos``          after the move: the position reached, checked against the target
``/a x stop``             when the stage is still BUSY ``settle_timeout_s`` after a move
========================  ========================================================================

Positions convert as ``z_mm = zero_mm + microsteps × microstep_mm``. Every reply is checked:
``RJ`` (the command was rejected; the data is the reason, e.g. ``BADDATA`` for a target outside
the device's limits) is a :class:`~eyeserver.errors.DeviceError`, as is a fault flag (any
``F…``, e.g. ``FS`` stalled and stopped, ``FQ`` encoder error, ``FZ`` peripheral inactive) or
``WL`` (unexpected limit trigger) -- the flags Zaber's own EPICS driver treats as faults -- and
``WR``/``WH`` (no reference position) outside homing. The device shows only its
highest-priority flag in a reply. Faults latch in the device until cleared
(``/a x warnings clear``, e.g. from Zaber Launcher) by someone who has looked at the stage; the
driver does not clear them.

Assumed: message ids and checksums are off (the factory default: replies carry neither); lines
the device sends on its own (``#`` info, ``!`` alerts) are skipped; the device answers only
commands addressed to it, so a wrong ``address`` is silence (a timeout).
"""

from __future__ import annotations

import logging
import re
import time
from dataclasses import dataclass

from eyeserver.errors import DeviceDisconnectedError, DeviceError, DeviceTimeoutError
from eyeserver.hardware.base import Stage
from eyeserver.hardware.drivers.serialline import ReplyError, SerialLine, answered
from eyeserver.hardware.registry import DriverContext, register_driver

__all__ = ["PROBE_BAUDRATE", "ZaberDevice", "ZaberStage", "probe"]

_log = logging.getLogger(__name__)

_REPLY = re.compile(r"@(?P<address>\d{2}) (?P<axis>\d+) (?P<flag>OK|RJ) (?P<status>IDLE|BUSY) "
                    r"(?P<warning>--|[A-Z]{2}) (?P<data>\S.*)")

_FLAG_NAMES = {
    "FF": "critical system error", "FN": "peripheral not supported",
    "FZ": "peripheral inactive", "FH": "hardware emergency stop",
    "FV": "overvoltage or undervoltage", "FO": "driver disabled",
    "FC": "current inrush error", "FM": "motor temperature error", "FD": "driver disabled",
    "FQ": "encoder error", "FI": "index error", "FA": "analog encoder sync error",
    "FR": "overdrive limit exceeded", "FS": "stalled and stopped", "FB": "stream bounds error",
    "FP": "interpolated path deviation", "FE": "limit error", "FT": "excessive twist",
    "WL": "unexpected limit trigger", "WV": "voltage out of range",
    "WT": "controller temperature high", "WS": "stalled with recovery",
    "WM": "displaced when stationary", "WP": "invalid calibration type",
    "WR": "no reference position", "WH": "device not homed", "NC": "manual control",
    "NI": "movement interrupted", "ND": "stream discontinuity", "NR": "value rounded",
    "NT": "value truncated", "NU": "setting update pending", "NJ": "joystick calibrating",
}
"""Warning flags as the Zaber Motion Library names them."""

_UNREFERENCED = frozenset({"WR", "WH"})

_REJECTIONS = {
    "BADDATA": "a value is out of range or malformed",
    "BADCOMMAND": "the device does not know the command",
    "BADAXIS": "the device has no such axis",
    "DEVICEONLY": "the command is for the whole device, not an axis",
    "PARKED": "the axis is parked",
    "DRIVERDISABLED": "the motor driver is disabled",
    "STATUSBUSY": "the axis is busy",
    "AGAIN": "the device is busy; try again",
    "INACTIVE": "the peripheral is inactive",
    "NOTSUPPORTED": "the command is not supported",
}
"""Rejection reasons (the data of an RJ reply) the driver explains."""


PROBE_BAUDRATE = 115200
"""The baud rate :func:`probe` asks at: the ASCII protocol's default (and the driver's)."""

_DEVICE_ID_SETTINGS = ("device.id", "deviceid")
"""The setting holding a device's product id: its firmware 7 name, then its firmware 6 one."""


@dataclass(frozen=True)
class ZaberDevice:
    """A Zaber device that answered :func:`probe`: its ``address`` on the daisy chain (the
    driver's ``address`` option) and its product id (``device.id``; None where it would not
    say), which Zaber's device database names (e.g. in Zaber Launcher)."""

    address: int
    product_id: int | None


@dataclass(frozen=True)
class _Reply:
    busy: bool
    warning: str
    data: str


@register_driver("stage", "ZaberStage")
class ZaberStage(Stage):
    """One axis of a Zaber linear stage carrying the calibration plate along Z.

    Parameters
    ----------
    device_id : str
        The stage's id.
    context : DriverContext
        Unused (the stage keeps its own time).
    port : str
        The serial port of the daisy chain.
    microstep_mm : float
        Millimetres of plate travel per microstep along +Z; negative where the stage's positive
        direction lowers the plate.
    zero_mm : float
        The plate surface's Z (mm) at stage position 0.
    address : int
        The device's address on the chain (1-99).
    axis : int
        The axis carrying the plate (1 for a single-axis device).
    baudrate : int
        The chain's baud rate.
    settle_timeout_s : float
        The longest a move (or homing) may take, seconds.
    timeout_s : float
        Time allowed for each reply, seconds.
    home_on_open : bool
        Home on open when the axis has no reference position (after power-up). Homing drives
        the plate to the end of its travel, so it is off unless the configuration asks.
    poll_interval_s : float
        Pause between status queries while waiting for a move to end, seconds.
    """

    def __init__(self, device_id: str, *, context: DriverContext, port: str,
                 microstep_mm: float, zero_mm: float = 0.0, address: int = 1, axis: int = 1,
                 baudrate: int = 115200, settle_timeout_s: float = 30.0,
                 timeout_s: float = 0.5, home_on_open: bool = False,
                 poll_interval_s: float = 0.05) -> None:
        super().__init__(device_id)
        if microstep_mm == 0:
            raise ValueError("microstep_mm must not be 0")
        if not 1 <= address <= 99:
            raise ValueError(f"address must be 1 to 99, not {address}")
        if axis < 1:
            raise ValueError(f"axis must be 1 or more, not {axis}")
        if not settle_timeout_s > 0:
            raise ValueError(f"settle_timeout_s must be positive, not {settle_timeout_s}")
        if not poll_interval_s > 0:
            raise ValueError(f"poll_interval_s must be positive, not {poll_interval_s}")
        self.microstep_mm = float(microstep_mm)
        self.zero_mm = float(zero_mm)
        self.address = int(address)
        self.axis = int(axis)
        self.settle_timeout_s = float(settle_timeout_s)
        self.home_on_open = bool(home_on_open)
        self.poll_interval_s = float(poll_interval_s)
        self._line = SerialLine(device_id, port, baudrate=baudrate, timeout_s=timeout_s,
                                write_terminator=b"\n", reply_terminator=b"\r\n",
                                ignore=lambda text: text.startswith(("#", "!")))

    def microsteps(self, z_mm: float) -> int:
        """The stage position (microsteps) that puts the plate at ``z_mm``."""
        return round((z_mm - self.zero_mm) / self.microstep_mm)

    def z_mm(self, microsteps: int) -> float:
        """The plate's Z (mm) at stage position ``microsteps``."""
        return self.zero_mm + microsteps * self.microstep_mm

    def _do_open(self) -> None:
        self._line.open()
        try:
            status = self._request("", "opening", allow_unreferenced=True)
            if status.warning in _UNREFERENCED:
                if not self.home_on_open:
                    raise DeviceError(self.id, f"axis {self.axis} of Zaber device "
                                               f"{self.address} on {self._line.port} has no "
                                               f"reference position ({status.warning}): home "
                                               f"it, or set home_on_open")
                self._request("home", "homing", allow_unreferenced=True)
                self._wait_idle("homing", allow_unreferenced=True)
                self._request("", "checking the homing")
            elif status.busy:
                self._wait_idle("waiting for a move begun elsewhere to end")
            low = self.z_mm(self._get("limit.min", "opening"))
            high = self.z_mm(self._get("limit.max", "opening"))
            low, high = min(low, high), max(low, high)
            travel = (max(type(self).travel_mm[0], low), min(type(self).travel_mm[1], high))
            if travel[0] > travel[1]:
                raise DeviceError(self.id, f"the stage's limits put the plate at "
                                           f"{low:g}..{high:g} mm, outside the travel "
                                           f"{type(self).travel_mm} mm: check zero_mm and "
                                           f"microstep_mm")
            self.travel_mm = travel
        except BaseException:
            self._line.close()
            raise

    def _do_close(self) -> None:
        self._line.close()

    def _move_to(self, z_mm: float) -> None:
        target = self.microsteps(z_mm)
        doing = f"moving to {z_mm:g} mm ({target} microsteps)"
        self._request(f"move abs {target}", doing)
        self._wait_idle(doing)
        position = self._get("pos", doing)
        if abs(position - target) > 1:
            raise DeviceError(self.id, f"the stage stopped at {position} microsteps "
                                       f"({self.z_mm(position):.4f} mm) while {doing}")

    def describe(self) -> dict[str, object]:
        return {**super().describe(), "port": self._line.port, "address": self.address,
                "axis": self.axis, "microstep_mm": self.microstep_mm, "zero_mm": self.zero_mm}

    def _wait_idle(self, doing: str, *, allow_unreferenced: bool = False) -> None:
        deadline = time.monotonic() + self.settle_timeout_s
        while True:
            if not self._request("", doing, allow_unreferenced=allow_unreferenced).busy:
                return
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                where = self._stop()
                raise DeviceTimeoutError(self.id, f"still moving {self.settle_timeout_s:g} s "
                                                  f"after {doing}; stopped it{where}")
            time.sleep(min(self.poll_interval_s, remaining))

    def _stop(self) -> str:
        """Stop the axis (best effort: the caller is already failing); where it stopped."""
        try:
            self._request("stop", "stopping", allow_unreferenced=True)
            position = self._get("pos", "stopping", allow_unreferenced=True)
        except DeviceError as exc:
            _log.warning("%s: could not stop the stage: %s", self.id, exc,
                         extra={"device_id": self.id})
            return ""
        return f" at {position} microsteps ({self.z_mm(position):.4f} mm)"

    def _get(self, setting: str, doing: str, *, allow_unreferenced: bool = False) -> int:
        reply = self._request(f"get {setting}", doing, allow_unreferenced=allow_unreferenced)
        try:
            return int(reply.data)
        except ValueError:
            raise DeviceError(self.id, f"'get {setting}' on {self._line.port} gave "
                                       f"{reply.data!r}, not a whole number") from None

    def _request(self, words: str, doing: str, *, allow_unreferenced: bool = False) -> _Reply:
        """Send ``words`` to the axis and check the reply: accepted, from this axis, and no
        flag that means the stage cannot be trusted."""
        command = f"/{self.address} {self.axis} {words}".rstrip()

        def check(text: str) -> _Reply:
            match = _REPLY.fullmatch(text.strip())
            if match is None:
                raise ReplyError("not a Zaber reply")
            if (int(match["address"]), int(match["axis"])) != (self.address, self.axis):
                raise ReplyError(f"from device {match['address']} axis {match['axis']}, not "
                                 f"{self.address} axis {self.axis}")
            reply = _Reply(busy=match["status"] == "BUSY", warning=match["warning"],
                           data=match["data"])
            if match["flag"] == "RJ":
                reason = _REJECTIONS.get(reply.data, "see the Zaber ASCII protocol manual")
                raise DeviceError(self.id, f"the stage rejected {command!r} while {doing}: "
                                           f"{reply.data} ({reason})")
            flag = reply.warning
            if flag.startswith("F") or flag == "WL":
                raise DeviceError(self.id, f"the stage reports {flag} "
                                           f"({_FLAG_NAMES.get(flag, 'fault')}) while {doing}; "
                                           f"check it, then clear the flag "
                                           f"('/{self.address} {self.axis} warnings clear')")
            if flag in _UNREFERENCED and not allow_unreferenced:
                raise DeviceError(self.id, f"the stage has lost its reference position "
                                           f"({flag}) while {doing}: home it")
            return reply

        return self._line.request(command, check)


def probe(port: str, timeout_s: float = 0.3, *,
          baudrate: int = PROBE_BAUDRATE) -> list[ZaberDevice]:
    """The Zaber devices answering the ASCII protocol on ``port``, by address; empty when none.

    Sends the empty broadcast command ``/`` (a status query every device on the chain answers,
    changing nothing), then asks each device that answered for its product id
    (``/<address> get device.id``, or ``deviceid`` on firmware 6). Devices answer only in the
    ASCII protocol at this baud rate; one set to the Binary protocol stays silent. The port is
    closed again before this returns, whatever happens.

    Parameters
    ----------
    port : str
        Device path (``/dev/ttyUSB0``, a ``/dev/serial/by-id/...`` link) or pyserial URL.
    timeout_s : float
        How long the chain is given to answer the broadcast, and each device its product id,
        seconds. Every device answers the broadcast, so it is always waited out in full.
    baudrate : int
        Bits per second (8N1).

    Raises
    ------
    DeviceDisconnectedError
        The port cannot be opened (missing, busy, no access) or failed while probing; its
        cause is pyserial's error, with the ``errno`` where the system gave one.
    """
    addresses: set[int] = set()
    broadcasting = True

    def skip(text: str) -> bool:
        if broadcasting:
            match = _REPLY.fullmatch(text.strip())
            if match is not None:
                addresses.add(int(match["address"]))
            return True
        return text.startswith(("#", "!"))  # what the device sends on its own, as the driver

    # SerialLine reads one reply per request, and a broadcast has one from each device on the
    # chain: while broadcasting, each is collected and skipped by ``ignore``, so the request
    # runs to its timeout, the window in which the chain answers.
    line = SerialLine(f"probe of {port}", port, baudrate=baudrate, timeout_s=timeout_s,
                      write_terminator=b"\n", reply_terminator=b"\r\n", ignore=skip)
    line.open()
    try:
        # The window's end (a timeout) or garbage is no failure here: keep who answered.
        answered(lambda: line.request("/", str))
        broadcasting = False
        return [ZaberDevice(address, _product_id(line, address))
                for address in sorted(addresses)]
    finally:
        line.close()


def _product_id(line: SerialLine, address: int) -> int | None:
    """The product id of the device at ``address``, or None when it answers neither setting."""

    def check(text: str) -> int | None:
        match = _REPLY.fullmatch(text.strip())
        if match is None or int(match["address"]) != address:
            raise ReplyError(f"not a reply from Zaber device {address}")
        if match["flag"] == "RJ" or not match["data"].isdigit():
            return None  # BADCOMMAND: the other firmware's name for the setting
        return int(match["data"])

    for setting in _DEVICE_ID_SETTINGS:
        try:
            product_id = line.request(f"/{address} get {setting}", check)
        except DeviceDisconnectedError:
            raise
        except DeviceError:
            return None
        if product_id is not None:
            return product_id
    return None
