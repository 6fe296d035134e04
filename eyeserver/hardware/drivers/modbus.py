"""One output of an Opto Engineering LTDVE-series LED strobe controller, over Modbus RTU (RS485)
or Modbus TCP, as a fringe projector.

The register map (documented and assumed), what the driver writes and reads, and how
it maps transport faults: docs/notes/modbus-controller.md. **Most of the register map
is an assumption** to check against the device's manual before it meets a controller.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Sequence
from typing import Literal

import serial
from pymodbus.client import ModbusBaseSyncClient, ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
from pymodbus.framer import FramerType
from pymodbus.pdu import ModbusPDU

from eyeserver.errors import (
    DeviceDisconnectedError,
    DeviceError,
    DeviceNotOpenError,
    DeviceTimeoutError,
)
from eyeserver.hardware.base import Projector
from eyeserver.hardware.drivers.serialline import answered
from eyeserver.hardware.registry import DriverContext, register_driver

__all__ = ["PROBE_BAUDRATE", "PROBE_PARITY", "PROBE_UNIT_ID", "OptoProjector", "probe"]

_log = logging.getLogger(__name__)

try:  # termios is POSIX-only; pyserial can raise its error from a hung-up tty.
    import termios

    _PORT_ERRORS: tuple[type[BaseException], ...] = (serial.SerialException, OSError,
                                                     termios.error)
except ImportError:  # pragma: no cover - not on the Linux hosts eyeserver runs on
    _PORT_ERRORS = (serial.SerialException, OSError)

DEVICE_TYPE = 0
VERSIONS = 1  # BOOT_VERSION, MCU_VERSION, FPGA_VERSION
ERROR_WORD = 16
CHANNEL_BASE = 256
CHANNEL_STRIDE = 16
_CHANNEL_REGISTERS = ("MODE", "CURRENT_MA", "PULSE_US", "DELAY_US", "STATUS")

MODE_OFF, MODE_CONTINUOUS, MODE_STROBE = 0, 1, 2
_MODE_NAMES = {MODE_OFF: "off", MODE_CONTINUOUS: "continuous", MODE_STROBE: "strobe"}

_STATUS_FAULTS = {
    1: "open load (no LED connected)",
    2: "short circuit",
    3: "over-current",
    4: "over-temperature",
    5: "duty-cycle limit (pulses skipped)",
}
"""STATUS bits that mean the output cannot light as set (assumed map)."""

_EXCEPTION_MEANINGS = {
    1: "illegal function",
    2: "illegal data address",
    3: "illegal data value",
    4: "server device failure",
    5: "acknowledge (still processing)",
    6: "server device busy",
    8: "memory parity error",
    10: "gateway path unavailable",
    11: "gateway target device failed to respond",
}
"""Modbus exception codes (Modbus Application Protocol Specification V1.1b3, section 7)."""

_U16 = 0xFFFF


PROBE_UNIT_ID = 1
PROBE_BAUDRATE = 19200
PROBE_PARITY: Literal["E", "O", "N"] = "E"
"""What :func:`probe` asks at by default: unit 1 at the Modbus-over-serial defaults (19200
baud, even parity), as a controller leaves the factory -- assumed, like the driver's own
defaults."""


def _firmware(boot: int, mcu: int, fpga: int) -> str:
    """BOOT_VERSION, MCU_VERSION and FPGA_VERSION as one text."""
    return f"boot {boot:#06x}, MCU {mcu:#06x}, FPGA {fpga:#06x}"


def _rtu_client(port: str, *, baudrate: int, parity: str, timeout_s: float,
                trace: Callable[[bool, bytes], bytes]) -> ModbusSerialClient:
    """pymodbus's RTU client as every use here builds it: 8 data bits, two stop bits without
    parity and one with (as Modbus over serial line asks), no retries (see the module's
    docstring), ``trace`` as its packet hook."""
    return ModbusSerialClient(port, framer=FramerType.RTU, baudrate=baudrate, bytesize=8,
                              parity=parity, stopbits=2 if parity == "N" else 1,
                              timeout=timeout_s, retries=0, trace_packet=trace)


def _error_word_faults(word: int, channel: int) -> tuple[list[str], list[str]]:
    """ERROR_WORD's set bits, described: (those that stop ``channel`` lighting, the others)."""
    ours: list[str] = []
    others: list[str] = []
    if word & 1:
        ours.append("bit 0: no supply for the power stages")
    for pair in range(4):
        if word & (1 << (1 + pair)):
            text = f"bit {1 + pair}: LD{2 * pair + 1}/LD{2 * pair + 2} output stages too hot"
            (ours if (channel - 1) // 2 == pair else others).append(text)
    for output in range(1, 9):
        if word & (1 << (4 + output)):
            text = f"bit {4 + output}: fault on LD{output}"
            (ours if output == channel else others).append(text)
    if word & ~0x1FFF & _U16:
        others.append(f"undocumented bits 0x{word & ~0x1FFF & _U16:04x}")
    return ours, others


class _ModbusLink:
    """One Modbus client, RTU or TCP, used one request at a time, its failures translated.

    Parameters
    ----------
    device_id : str
        The device every error names.
    where : str
        The transport and address, for messages (``serial port /dev/ttyUSB0``).
    unit_id : int
        The controller's Modbus address (unit id).
    timeout_s : float
        The client's timeout, for messages.

    Attributes
    ----------
    client : ModbusBaseSyncClient
        The pymodbus sync client, set by the driver before :meth:`open`: built with
        ``retries=0`` and :meth:`trace` as its ``trace_packet``.
    """

    def __init__(self, device_id: str, where: str, unit_id: int, timeout_s: float) -> None:
        self.device_id = device_id
        self.where = where
        self.unit_id = unit_id
        self.timeout_s = timeout_s
        self.client: ModbusBaseSyncClient | None = None
        self._lock = threading.Lock()
        self._active = False
        self._connected = False
        self._received = b""

    def trace(self, sending: bool, packet: bytes) -> bytes:
        """pymodbus's ``trace_packet`` hook: remembers what came back, so that a request that
        ends without a response can tell garbage (bytes that were no response) from silence."""
        if not sending:
            self._received = bytes(packet)
        return packet

    def open(self) -> None:
        """Connect now, so that a missing controller fails the driver's ``open()``."""
        with self._lock:
            self._active = True
            self._connect()

    def close(self) -> None:
        """Disconnect; later requests raise :class:`DeviceNotOpenError`. Idempotent."""
        with self._lock:
            self._active = False
            self._drop()

    def read(self, address: int, count: int, what: str) -> list[int]:
        """Read ``count`` holding registers from ``address``; ``what`` names them."""
        response = self._request(f"reading {what}", lambda client: client.read_holding_registers(
            address, count=count, device_id=self.unit_id))
        registers = list(response.registers)
        if response.function_code != 0x03 or len(registers) != count:
            raise DeviceError(self.device_id, f"unexpected response to reading {what} on "
                                              f"{self.where}: {response} (not {count} "
                                              f"register(s))")
        return registers

    def write(self, address: int, values: Sequence[int], what: str) -> None:
        """Write ``values`` to the holding registers from ``address``; ``what`` names them."""
        action = f"writing {what} = {list(values)}"
        response = self._request(action, lambda client: client.write_registers(
            address, list(values), device_id=self.unit_id))
        if (response.function_code, response.address, response.count) != (
                0x10, address, len(values)):
            raise DeviceError(self.device_id, f"unexpected response to {action} on "
                                              f"{self.where}: {response}")

    def _request(self, action: str,
                 call: Callable[[ModbusBaseSyncClient], ModbusPDU]) -> ModbusPDU:
        with self._lock:
            if not self._active:
                raise DeviceNotOpenError(self.device_id, f"{self.where} is not open")
            client = self._connect()
            self._received = b""
            try:
                response = call(client)
            except ConnectionException as exc:
                self._drop()
                raise DeviceDisconnectedError(self.device_id, f"{self.where} failed during "
                                                              f"{action}: {exc}") from exc
            except ModbusIOException as exc:
                self._drop()
                # pymodbus drops frames it cannot decode and waits on: garbage ends as a
                # timeout too, told apart by the bytes that did arrive.
                if self._received:
                    raise DeviceError(self.device_id, f"garbage in reply to {action} on "
                                                      f"{self.where}: {self._received[:64]!r} "
                                                      f"is not a Modbus response") from exc
                raise DeviceTimeoutError(self.device_id, f"no reply to {action} on "
                                                         f"{self.where} within "
                                                         f"{self.timeout_s:g} s") from exc
            except ModbusException as exc:
                self._drop()
                raise DeviceError(self.device_id, f"{action} on {self.where} failed: "
                                                  f"{exc}") from exc
            except _PORT_ERRORS as exc:
                self._drop()
                raise DeviceDisconnectedError(self.device_id, f"{self.where} failed during "
                                                              f"{action}: {exc}") from exc
        if response.isError():
            code = response.exception_code
            meaning = _EXCEPTION_MEANINGS.get(code, "unknown exception")
            raise DeviceError(self.device_id, f"the controller on {self.where} refused {action}: "
                                              f"Modbus exception {code} ({meaning})")
        return response

    def _connect(self) -> ModbusBaseSyncClient:
        assert self.client is not None
        if not self._connected:
            try:
                connected = self.client.connect()
            except _PORT_ERRORS as exc:  # pymodbus reports most failures as False, not all
                connected = False
                _log.debug("%s: connecting raised %r", self.device_id, exc)
            if not connected:
                self.client.close()  # type: ignore[no-untyped-call]  # pymodbus: unannotated
                raise DeviceDisconnectedError(self.device_id, f"cannot connect to {self.where}"
                                                              f" (missing, refused or in use)")
            self._connected = True
        return self.client

    def _drop(self) -> None:
        self._connected = False
        if self.client is not None:
            try:
                self.client.close()  # type: ignore[no-untyped-call]  # pymodbus: unannotated
            except _PORT_ERRORS as exc:  # a port that is already gone needs no more
                _log.debug("%s: closing raised %r", self.device_id, exc)


@register_driver("projector", "OptoProjector")
class OptoProjector(Projector):
    """A fringe projector's LED on one output of an Opto Engineering LTDVE-style strobe
    controller, over Modbus RTU or Modbus TCP (register map: the module's docstring).

    Parameters
    ----------
    device_id : str
        The projector's id.
    context : DriverContext
        Unused (the controller keeps its own time).
    transport : {"rtu", "tcp"}
        Modbus RTU on a serial port (RS485 adapter), or Modbus TCP.
    channel : int
        The light output the LED is wired to (LD1 is 1).
    max_current_ma : float
        The current at intensity 1, mA: the LED's rating for the pulse width used. Written
        rounded to whole mA (the register's resolution).
    pulse_us : float
        Strobe pulse width, µs (1 to 65535, rounded to whole µs): the exposure it must cover.
    delay_us : float
        Delay from trigger to pulse, µs (0 to 65535, rounded to whole µs).
    port : str, optional
        ``rtu``: the serial port (``/dev/ttyUSB0``, a ``/dev/serial/by-id/...`` link).
    host : str, optional
        ``tcp``: the controller's address.
    tcp_port : int
        ``tcp``: its TCP port (502, Modbus TCP's).
    unit_id : int
        The controller's Modbus address: 1 to 247 on RTU, 0 to 255 on TCP.
    baudrate : int
        ``rtu``: bits per second (19200, the Modbus-over-serial default).
    parity : {"E", "O", "N"}
        ``rtu``: even (the Modbus-over-serial default), odd or none; two stop bits without
        parity, one with, as Modbus over serial line asks.
    timeout_s : float
        Time allowed for each response (and for connecting), seconds.
    """

    def __init__(self, device_id: str, *, context: DriverContext,
                 transport: Literal["rtu", "tcp"], channel: int, max_current_ma: float,
                 pulse_us: float, delay_us: float, port: str | None = None,
                 host: str | None = None, tcp_port: int = 502, unit_id: int = 1,
                 baudrate: int = 19200, parity: Literal["E", "O", "N"] = "E",
                 timeout_s: float = 0.5) -> None:
        super().__init__(device_id)
        if not 1 <= channel <= (_U16 - CHANNEL_BASE) // CHANNEL_STRIDE:
            raise ValueError(f"channel must be 1 or more, not {channel}")
        if not 0 < max_current_ma <= _U16:
            raise ValueError(f"max_current_ma must be above 0 and at most {_U16}, "
                             f"not {max_current_ma}")
        if not 1 <= round(pulse_us) <= _U16:
            raise ValueError(f"pulse_us must be 1 to {_U16} µs, not {pulse_us}")
        if not 0 <= round(delay_us) <= _U16:
            raise ValueError(f"delay_us must be 0 to {_U16} µs, not {delay_us}")
        if not timeout_s > 0:
            raise ValueError(f"timeout_s must be positive, not {timeout_s}")
        self.transport = transport
        self.channel = int(channel)
        self.max_current_ma = float(max_current_ma)
        self.pulse_us = round(pulse_us)
        self.delay_us = round(delay_us)
        self.device_type: int | None = None
        self.firmware: str | None = None
        self._base = CHANNEL_BASE + CHANNEL_STRIDE * (self.channel - 1)
        self._lock = threading.RLock()
        if transport == "rtu":
            if not port:
                raise ValueError("transport 'rtu' needs port (the serial device)")
            if host is not None:
                raise ValueError("host is for transport 'tcp'; 'rtu' takes port")
            if not 1 <= unit_id <= 247:
                raise ValueError(f"unit_id must be 1 to 247 on Modbus RTU, not {unit_id}")
            if baudrate <= 0:
                raise ValueError(f"baudrate must be positive, not {baudrate}")
            if parity not in ("E", "O", "N"):
                raise ValueError(f"parity must be 'E', 'O' or 'N', not {parity!r}")
            self._link = _ModbusLink(device_id, f"serial port {port} (Modbus RTU unit "
                                                f"{unit_id})", unit_id, timeout_s)
            self._link.client = _rtu_client(port, baudrate=baudrate, parity=parity,
                                            timeout_s=timeout_s, trace=self._link.trace)
        elif transport == "tcp":
            if not host:
                raise ValueError("transport 'tcp' needs host (the controller's address)")
            if port is not None:
                raise ValueError("port is the serial device of transport 'rtu'; 'tcp' takes "
                                 "host and tcp_port")
            if not 1 <= tcp_port <= _U16:
                raise ValueError(f"tcp_port must be 1 to {_U16}, not {tcp_port}")
            if not 0 <= unit_id <= 255:
                raise ValueError(f"unit_id must be 0 to 255 on Modbus TCP, not {unit_id}")
            self._link = _ModbusLink(device_id, f"Modbus TCP {host}:{tcp_port} unit {unit_id}",
                                     unit_id, timeout_s)
            self._link.client = ModbusTcpClient(host, port=tcp_port, timeout=timeout_s,
                                                retries=0, trace_packet=self._link.trace)
        else:
            raise ValueError(f"transport must be 'rtu' or 'tcp', not {transport!r}")

    @property
    def current_ma(self) -> int:
        """The LED current the settings ask for, mA (0 while disabled)."""
        return round(self.max_current_ma * self.intensity) if self.enabled else 0

    def _do_open(self) -> None:
        self._link.open()
        try:
            self.device_type = self._link.read(DEVICE_TYPE, 1, "DEVICE_TYPE (register 0)")[0]
            boot, mcu, fpga = self._link.read(VERSIONS, 3, "BOOT/MCU/FPGA_VERSION "
                                                           "(registers 1-3)")
            self.firmware = _firmware(boot, mcu, fpga)
            self._push(self.enabled, self.intensity, self.strobe)
        except BaseException:
            self._link.close()
            raise

    def _do_close(self) -> None:
        # Dark on close: a channel left on would stay lit in the patient's eye after the
        # daemon stops.
        try:
            self._link.write(self._base, [MODE_OFF, 0, self.pulse_us, self.delay_us],
                             self._block_name(4))
        except DeviceError as exc:
            _log.warning("%s: could not switch LD%d off on close: %s", self.id, self.channel,
                         exc, extra={"device_id": self.id})
        finally:
            self._link.close()

    def _check(self) -> None:
        with self._lock:
            word = self._link.read(ERROR_WORD, 1, "ERROR_WORD (register 16)")[0]
            ours, others = _error_word_faults(word, self.channel)
            if others:
                _log.info("%s: controller errors not on LD%d: %s", self.id, self.channel,
                          "; ".join(others), extra={"device_id": self.id})
            if ours:
                raise DeviceError(self.id, f"the controller on {self._link.where} reports "
                                           f"ERROR_WORD 0x{word:04x}: {'; '.join(ours)}")
            block = self._link.read(self._base, 5, self._block_name(5))
            self._check_block(block, self._settings(self.enabled, self.intensity, self.strobe),
                              "reads")

    def _apply_enabled(self, value: bool) -> None:
        self._push(value, self.intensity, self.strobe)

    def _apply_intensity(self, value: float) -> None:
        self._push(self.enabled, value, self.strobe)

    def _apply_strobe(self, value: bool) -> None:
        self._push(self.enabled, self.intensity, value)

    def describe(self) -> dict[str, object]:
        return {**super().describe(), "transport": self.transport, "link": self._link.where,
                "channel": self.channel, "current_ma": self.current_ma,
                "pulse_us": self.pulse_us, "delay_us": self.delay_us,
                "device_type": self.device_type, "firmware": self.firmware}

    def _settings(self, enabled: bool, intensity: float, strobe: bool) -> list[int]:
        """MODE, CURRENT_MA, PULSE_US and DELAY_US for this state."""
        if not enabled:
            return [MODE_OFF, 0, self.pulse_us, self.delay_us]
        return [MODE_STROBE if strobe else MODE_CONTINUOUS,
                round(self.max_current_ma * intensity), self.pulse_us, self.delay_us]

    def _push(self, enabled: bool, intensity: float, strobe: bool) -> None:
        """Write the channel's four settings for this state, then read them back."""
        values = self._settings(enabled, intensity, strobe)
        with self._lock:
            self._link.write(self._base, values, self._block_name(4))
            self._check_block(self._link.read(self._base, 5, self._block_name(5)), values,
                              "reads back")

    def _check_block(self, block: list[int], expected: list[int], verb: str) -> None:
        """Fail unless the channel's registers hold ``expected`` and STATUS shows no fault.

        ``check()`` compares with the settings the projector reports, not with the last write
        that may have failed half-way: a controller that is not in the state the projector
        says it is fails the check."""
        for n, (wanted, found) in enumerate(zip(expected, block, strict=False)):
            if wanted != found:
                if n == 0:
                    wanted_text = f"{wanted} ({_MODE_NAMES[wanted]})"
                    found_text = f"{found} ({_MODE_NAMES.get(found, 'unknown')})"
                else:
                    wanted_text, found_text = str(wanted), str(found)
                raise DeviceError(self.id, f"{self._register_name(n)} on {self._link.where} "
                                           f"{verb} {found_text}, not {wanted_text}")
        status = block[4]
        faults = [f"bit {bit}: {text}" for bit, text in _STATUS_FAULTS.items()
                  if status & (1 << bit)]
        if faults:
            raise DeviceError(self.id, f"{self._register_name(4)} on {self._link.where} is "
                                       f"0x{status:04x}: {'; '.join(faults)}")

    def _register_name(self, offset: int) -> str:
        return (f"LD{self.channel} {_CHANNEL_REGISTERS[offset]} "
                f"(register {self._base + offset})")

    def _block_name(self, count: int) -> str:
        return (f"LD{self.channel} {_CHANNEL_REGISTERS[0]}..{_CHANNEL_REGISTERS[count - 1]} "
                f"(registers {self._base}-{self._base + count - 1})")


def probe(port: str, timeout_s: float = 0.3, *, unit_id: int = PROBE_UNIT_ID,
          baudrate: int = PROBE_BAUDRATE,
          parity: Literal["E", "O", "N"] = PROBE_PARITY) -> str | None:
    """What an Opto Engineering-style controller on Modbus RTU at ``port`` says it is
    (``DEVICE_TYPE 0x0804, firmware boot …``), or None when nothing answers as one.

    Reads DEVICE_TYPE (register 0, the documented start of the map) from unit ``unit_id``, then
    the firmware versions (registers 1-3) if it can: reads only, so nothing changes on a
    controller. Any other reply -- an exception response, bytes that are no Modbus response --
    or silence is None. The port is closed again before this returns, whatever happens.

    Parameters
    ----------
    port : str
        Device path of the RS485 adapter (``/dev/ttyUSB0``, a ``/dev/serial/by-id/...`` link).
    timeout_s : float
        Time allowed for each response, seconds; silence for this long is "no controller".
    unit_id : int
        The controller's Modbus address (1 to 247).
    baudrate : int
        Bits per second.
    parity : {"E", "O", "N"}
        Even, odd or none (then two stop bits).

    Raises
    ------
    DeviceDisconnectedError
        The port cannot be opened with these settings (missing, busy, no access, or parity a
        port cannot take: a pty takes none) or failed while probing.
    """
    link = _ModbusLink(f"probe of {port}", f"serial port {port} (Modbus RTU unit {unit_id})",
                       unit_id, timeout_s)
    link.client = _rtu_client(port, baudrate=baudrate, parity=parity, timeout_s=timeout_s,
                              trace=link.trace)
    link.open()
    try:
        device_type = answered(lambda: link.read(DEVICE_TYPE, 1, "DEVICE_TYPE (register 0)"))
        if device_type is None:
            return None  # silence, garbage or refused: not the controller
        versions = answered(lambda: link.read(VERSIONS, 3,
                                              "BOOT/MCU/FPGA_VERSION (registers 1-3)"))
        if versions is None:
            return f"DEVICE_TYPE {device_type[0]:#06x}"
        boot, mcu, fpga = versions
        return f"DEVICE_TYPE {device_type[0]:#06x}, firmware {_firmware(boot, mcu, fpga)}"
    finally:
        link.close()
