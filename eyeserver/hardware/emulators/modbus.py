"""An emulated Opto Engineering LTDVE-style LED strobe controller speaking Modbus: Modbus TCP on
loopback, or Modbus RTU on a pty.

The controller (:class:`OptoController`) is a file of sixteen-bit holding registers laid out as
:mod:`eyeserver.hardware.drivers.modbus` documents (an assumed map: see there). It is written
from that table, not from the driver's constants, so that a wrong address in the driver shows up
as a wrong register here. Registers, addressed from 0:

======================  ======  ===============================================================
``DEVICE_TYPE``         0       read only: :attr:`OptoController.device_type`
``BOOT_VERSION``        1       read only
``MCU_VERSION``         2       read only
``FPGA_VERSION``        3       read only
``ERROR_WORD``          16      read only: :attr:`OptoController.error_word`, set by the test
channel ``n`` block     256 + 16 (n - 1), for n = 1 .. :attr:`OptoController.channel_count`:
  ``MODE``              +0      0 off, 1 continuous, 2 strobe
  ``CURRENT_MA``        +1      LED current, mA, 0 .. :attr:`OptoController.rating_ma`
  ``PULSE_US``          +2      strobe pulse width, µs, 1 .. 65535
  ``DELAY_US``          +3      trigger-to-pulse delay, µs, 0 .. 65535
  ``STATUS``            +4      read only: bit 0 the output drives its LED; bits 1-5 faults
                                (:attr:`OptoChannel.faults`, set by the test)
======================  ======  ===============================================================

Function codes 0x03 (read holding registers), 0x06 (write single register) and 0x10 (write
multiple registers). Requests are checked the way a Modbus server does: another function is
exception 1 (illegal function); an address outside the map, or a write to a read-only register,
is exception 2 (illegal data address); a value out of its register's range is exception 3
(illegal data value), and then nothing of that request is written. With
:attr:`~OptoController.clamp_current` the controller instead sets a current above its rating to
the rating without saying so (as some controllers limit to the connected light's rating), which
only a driver that reads its writes back notices. :attr:`~OptoController.forced_exception` makes
every request answer that exception code (4: server device failure, 6: busy).

Both transports switch behaviour like the serial emulators
(:class:`~eyeserver.hardware.emulators.serialpty.Behaviour`): ``NORMAL``; ``GARBAGE`` answers
with frames a Modbus client must reject (RTU: the right response with a wrong CRC; TCP: an MBAP
header with a protocol id that is not 0); ``SILENT`` reads requests and answers nothing; and
``unplug()``/``replug()``: the RTU pty goes away and comes back at the same path, the TCP
listener closes its connections and stops listening, then listens again on the same port.

The servers are hand-written rather than pymodbus's: pymodbus's servers run on an asyncio loop
(one more thread and loop to manage per test), its datastores validate nothing per register and
have changed API between 3.x releases, and none of them can send a bad CRC, fall silent or stop
listening on demand; a Modbus server for three function codes is a page. Being a second,
independent implementation of the framing, it also checks the driver's use of pymodbus.
"""

from __future__ import annotations

import contextlib
import logging
import selectors
import socket
import struct
import threading
from dataclasses import dataclass
from pathlib import Path

from eyeserver.hardware.emulators.serialpty import SerialPtyEmulator
from eyeserver.hardware.emulators.served import Behaviour, ServedEmulator

__all__ = [
    "Behaviour",
    "ModbusRequest",
    "OptoChannel",
    "OptoController",
    "OptoRtuEmulator",
    "OptoTcpEmulator",
    "crc16",
]

_log = logging.getLogger(__name__)

DEVICE_TYPE, BOOT_VERSION, MCU_VERSION, FPGA_VERSION = 0, 1, 2, 3
ERROR_WORD = 16
CHANNEL_BASE, CHANNEL_STRIDE = 256, 16
MODE, CURRENT_MA, PULSE_US, DELAY_US, STATUS = range(5)
_WRITABLE = (MODE, CURRENT_MA, PULSE_US, DELAY_US)

ILLEGAL_FUNCTION, ILLEGAL_DATA_ADDRESS, ILLEGAL_DATA_VALUE = 1, 2, 3
GATEWAY_TARGET_FAILED = 0x0B

_READ_HOLDING, _WRITE_SINGLE, _WRITE_MULTIPLE = 0x03, 0x06, 0x10

def crc16(data: bytes) -> int:
    """The Modbus RTU CRC of ``data`` (CRC-16/MODBUS: reflected 0xA001, initial 0xFFFF); a
    frame carries it low byte first."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


class _RefusedError(Exception):
    def __init__(self, code: int) -> None:
        super().__init__(f"Modbus exception {code}")
        self.code = code


@dataclass
class OptoChannel:
    """One output's registers. ``current_ma`` in mA, ``pulse_us`` and ``delay_us`` in µs;
    ``faults`` are the STATUS bits 1-5 the test raises (1 open load, 2 short circuit,
    3 over-current, 4 over-temperature, 5 duty-cycle limit); ``writes`` counts register writes."""

    mode: int = 0
    current_ma: int = 0
    pulse_us: int = 100
    delay_us: int = 0
    faults: int = 0
    writes: int = 0

    @property
    def status(self) -> int:
        """The STATUS register: bit 0 while the output drives its LED, and the fault bits."""
        active = 1 if self.mode != 0 and self.current_ma > 0 else 0
        return active | (self.faults & 0x3E)


@dataclass(frozen=True)
class ModbusRequest:
    """A request the controller executed or refused: function code, first address, the values
    written (writes) or the number of registers asked for (reads), and the exception code it
    answered (None: a normal response)."""

    function: int
    address: int
    values: tuple[int, ...] = ()
    count: int = 0
    exception: int | None = None


class OptoController:
    """The register file of an emulated controller with ``channels`` outputs.

    Parameters
    ----------
    channels : int
        Number of outputs (1 to 8; LTDVE controllers have 1, 4 or 8).
    rating_ma : int
        The most current an output gives, mA; more is refused with exception 3, or clamped
        to this with ``clamp_current``.
    clamp_current : bool
        Set a current above the rating to the rating instead of refusing it.
    device_type, versions
        What DEVICE_TYPE and BOOT/MCU/FPGA_VERSION read.

    Attributes
    ----------
    channels : dict of int to OptoChannel
        Outputs by number, from 1.
    error_word : int
        The ERROR_WORD register (bit 0 no power-stage supply, bits 1-4 the LD1/2, LD3/4,
        LD5/6, LD7/8 output stages too hot, bits 5-12 a fault on LD1-LD8).
    forced_exception : int or None
        When set, every request answers this Modbus exception code.
    requests : list of ModbusRequest
        Every request handled, oldest first.
    lock : threading.RLock
        Held while a request is handled; hold it to change the registers consistently.
    """

    def __init__(self, channels: int = 4, *, rating_ma: int = 3000, clamp_current: bool = False,
                 device_type: int = 0x0804, versions: tuple[int, int, int] = (0x0100, 0x0110,
                                                                               0x0003)) -> None:
        if not 1 <= channels <= 8:
            raise ValueError(f"channels must be 1 to 8, not {channels}")
        if not 0 < rating_ma <= 0xFFFF:
            raise ValueError(f"rating_ma must be 1 to 65535, not {rating_ma}")
        self.channels = {n: OptoChannel() for n in range(1, channels + 1)}
        self.rating_ma = int(rating_ma)
        self.clamp_current = clamp_current
        self.device_type = device_type
        self.versions = versions
        self.error_word = 0
        self.forced_exception: int | None = None
        self.requests: list[ModbusRequest] = []
        self.lock = threading.RLock()

    @property
    def channel_count(self) -> int:
        """The number of outputs."""
        return len(self.channels)

    def reset(self) -> None:
        """Power-cycle the controller: every output back to its power-up registers (off, 0 mA)
        and no faults, as a controller that does not keep its settings does."""
        with self.lock:
            for number in self.channels:
                self.channels[number] = OptoChannel()
            self.error_word = 0

    def handle(self, pdu: bytes) -> bytes:
        """Execute one request PDU (function code and data) and return the response PDU: the
        normal response or an exception response (function code + 0x80, exception code)."""
        function = pdu[0] if pdu else 0
        with self.lock:
            try:
                if self.forced_exception is not None:
                    raise _RefusedError(self.forced_exception)
                return self._execute(function, pdu[1:])
            except _RefusedError as refused:
                address = int.from_bytes(pdu[1:3], "big") if len(pdu) >= 3 else 0
                self.requests.append(ModbusRequest(function, address, exception=refused.code))
                return bytes([(function | 0x80) & 0xFF, refused.code])

    def _execute(self, function: int, data: bytes) -> bytes:
        if function == _READ_HOLDING:
            if len(data) != 4:
                raise _RefusedError(ILLEGAL_DATA_VALUE)
            address, count = struct.unpack(">HH", data)
            if not 1 <= count <= 125:
                raise _RefusedError(ILLEGAL_DATA_VALUE)
            values = [self._read(address + n) for n in range(count)]
            self.requests.append(ModbusRequest(function, address, count=count))
            return struct.pack(f">BB{count}H", function, 2 * count, *values)
        if function == _WRITE_SINGLE:
            if len(data) != 4:
                raise _RefusedError(ILLEGAL_DATA_VALUE)
            address, value = struct.unpack(">HH", data)
            self._write(address, [value])
            self.requests.append(ModbusRequest(function, address, values=(value,)))
            return bytes([function]) + data
        if function == _WRITE_MULTIPLE:
            if len(data) < 5:
                raise _RefusedError(ILLEGAL_DATA_VALUE)
            address, count, byte_count = struct.unpack(">HHB", data[:5])
            if not 1 <= count <= 123 or byte_count != 2 * count or len(data) != 5 + byte_count:
                raise _RefusedError(ILLEGAL_DATA_VALUE)
            values = list(struct.unpack(f">{count}H", data[5:]))
            self._write(address, values)
            self.requests.append(ModbusRequest(function, address, values=tuple(values)))
            return struct.pack(">BHH", function, address, count)
        raise _RefusedError(ILLEGAL_FUNCTION)

    def _locate(self, address: int) -> tuple[OptoChannel, int] | None:
        """The channel and offset of a channel-block address; None for another address."""
        block, offset = divmod(address - CHANNEL_BASE, CHANNEL_STRIDE)
        if address < CHANNEL_BASE or block + 1 not in self.channels or offset > STATUS:
            return None
        return self.channels[block + 1], offset

    def _read(self, address: int) -> int:
        fixed = {DEVICE_TYPE: self.device_type, BOOT_VERSION: self.versions[0],
                 MCU_VERSION: self.versions[1], FPGA_VERSION: self.versions[2],
                 ERROR_WORD: self.error_word}
        if address in fixed:
            return fixed[address] & 0xFFFF
        located = self._locate(address)
        if located is None:
            raise _RefusedError(ILLEGAL_DATA_ADDRESS)
        channel, offset = located
        return (channel.mode, channel.current_ma, channel.pulse_us, channel.delay_us,
                channel.status)[offset]

    def _write(self, address: int, values: list[int]) -> None:
        # Every register is checked before any is written: a refused request changes nothing.
        planned: list[tuple[OptoChannel, int, int]] = []
        for n, value in enumerate(values):
            located = self._locate(address + n)
            if located is None or located[1] not in _WRITABLE:
                raise _RefusedError(ILLEGAL_DATA_ADDRESS)
            channel, offset = located
            if offset == MODE and value not in (0, 1, 2):
                raise _RefusedError(ILLEGAL_DATA_VALUE)
            if offset == CURRENT_MA and value > self.rating_ma:
                if not self.clamp_current:
                    raise _RefusedError(ILLEGAL_DATA_VALUE)
                value = self.rating_ma
            if offset == PULSE_US and value < 1:
                raise _RefusedError(ILLEGAL_DATA_VALUE)
            planned.append((channel, offset, value))
        for channel, offset, value in planned:
            field = ("mode", "current_ma", "pulse_us", "delay_us")[offset]
            setattr(channel, field, value)
            channel.writes += 1


def _rtu_request_length(buffer: bytes) -> int | None:
    """The length of the RTU request frame at the start of ``buffer`` (address, function, data,
    CRC), None while too little has arrived to tell, 0 for a function the server does not
    know (its length cannot be told from its bytes)."""
    if len(buffer) < 2:
        return None
    function = buffer[1]
    if function in (_READ_HOLDING, _WRITE_SINGLE):
        return 8
    if function == _WRITE_MULTIPLE:
        return 9 + buffer[6] if len(buffer) >= 7 else None
    return 0


class OptoRtuEmulator(SerialPtyEmulator):
    """The controller on Modbus RTU over a pty; use as a context manager or start()/stop().

    The driver opens :attr:`port` (see
    :class:`~eyeserver.hardware.emulators.serialpty.SerialPtyEmulator` for the pty, its stable
    symlink, ``behaviour``, ``unplug()`` and ``replug()``); baud rate and parity do not matter
    on a pty, but parity cannot be set on one (see :meth:`driver_options`).

    Parameters
    ----------
    controller : OptoController, optional
        The registers served; a four-output controller by default.
    unit_id : int
        The controller's Modbus address (1 to 247); it answers only requests to it (and
        executes broadcasts to 0 without answering).
    link_dir, name
        As for :class:`~eyeserver.hardware.emulators.serialpty.SerialPtyEmulator`.

    Attributes
    ----------
    received : list of str
        Every request frame read that carried a good CRC, in hex.
    bad_frames : int
        Request frames dropped for a wrong CRC.
    """

    def __init__(self, controller: OptoController | None = None, *, unit_id: int = 1,
                 link_dir: str | Path | None = None, name: str = "opto-rtu") -> None:
        super().__init__(link_dir=link_dir, name=name)
        if not 1 <= unit_id <= 247:
            raise ValueError(f"unit_id must be 1 to 247, not {unit_id}")
        self.controller = controller if controller is not None else OptoController()
        self.unit_id = unit_id
        self.bad_frames = 0

    def driver_options(self) -> dict[str, object]:
        """The :class:`~eyeserver.hardware.drivers.modbus.OptoProjector` options that reach
        this emulator: no parity, since Linux refuses parity on a pty (EINVAL)."""
        return {"transport": "rtu", "port": self.port, "unit_id": self.unit_id, "parity": "N"}

    def reply(self, command: str) -> bytes | None:
        """Not used: RTU frames are binary and length-delimited, not lines (see
        :meth:`split_request`)."""
        return None

    def split_request(self, buffer: bytes) -> tuple[bytes, bytes] | None:
        """The first RTU request frame in ``buffer``, cut by its function code's length (the
        base class cuts lines). A real server ends a frame at 3.5 characters of silence; on a
        pty a request arrives in one write, so the length alone is enough here."""
        length = _rtu_request_length(buffer)
        if length is None:
            return None
        if length == 0:
            length = len(buffer)  # unknown function: take all that came
        if len(buffer) < length:
            return None
        return buffer[:length], buffer[length:]

    def handle_request(self, request: bytes) -> None:
        """Execute one request frame and send its response frame (none for a broadcast, a
        wrong CRC or another unit's request)."""
        if len(request) < 4 or crc16(request[:-2]) != int.from_bytes(request[-2:], "little"):
            self.bad_frames += 1  # a server drops a frame with a wrong CRC without a word
            return
        unit, pdu = request[0], request[1:-2]
        if unit not in (0, self.unit_id):
            return  # another device's request on the bus
        self.received.append(request.hex())
        try:
            response = self.controller.handle(pdu)
        except Exception as exc:
            # An emulator bug, not a device behaviour: stop() raises it (see the base class).
            _log.exception("emulator failed to answer %s", request.hex())
            self.failures.append(exc)
            return
        behaviour = self.behaviour
        if unit == 0 or behaviour is Behaviour.SILENT:
            return
        answer = bytes([unit]) + response
        answer += crc16(answer).to_bytes(2, "little")
        if behaviour is Behaviour.GARBAGE:
            answer = answer[:-1] + bytes([answer[-1] ^ 0x5A])  # a noisy line: the CRC is wrong
        self.send(answer)


class OptoTcpEmulator(ServedEmulator):
    """The controller on Modbus TCP on a loopback port; use as a context manager or
    start()/stop().

    Parameters
    ----------
    controller : OptoController, optional
        The registers served; a four-output controller by default.
    unit_id : int
        The unit id the controller answers to; a request to another is answered with
        exception 0x0B (gateway target device failed to respond), as Modbus TCP gateways do.
    host : str
        The address to listen on.
    port : int
        The TCP port; 0 picks a free one (then kept across :meth:`unplug`/:meth:`replug`).

    Notes
    -----
    :meth:`unplug` closes every connection and stops listening (connecting is refused);
    :meth:`replug` listens again on the same port.

    Attributes
    ----------
    behaviour : Behaviour
        How requests are answered; may be changed at any time.
    connections : int
        Connections accepted since start.
    failures : list of Exception
        Emulator bugs met while serving; :meth:`stop` raises the first.
    """

    def __init__(self, controller: OptoController | None = None, *, unit_id: int = 1,
                 host: str = "127.0.0.1", port: int = 0) -> None:
        if not 0 <= unit_id <= 255:
            raise ValueError(f"unit_id must be 0 to 255, not {unit_id}")
        super().__init__()
        self.controller = controller if controller is not None else OptoController()
        self.unit_id = unit_id
        self.host = host
        self._port = port
        self.connections = 0
        self._listener: socket.socket | None = None
        self._clients: dict[socket.socket, bytes] = {}

    @property
    def port(self) -> int:
        """The TCP port listened on (fixed once started)."""
        return self._port

    @property
    def plugged(self) -> bool:
        """Whether the controller is listening."""
        return self._listener is not None

    def driver_options(self) -> dict[str, object]:
        """The :class:`~eyeserver.hardware.drivers.modbus.OptoProjector` options that reach
        this emulator."""
        return {"transport": "tcp", "host": self.host, "tcp_port": self.port,
                "unit_id": self.unit_id}

    # --- the serving thread: it alone opens and closes sockets ---------------------------

    def _thread_name(self) -> str:
        return f"modbus-tcp-{self._port}"

    def _readable(self, key: selectors.SelectorKey) -> None:
        if key.fileobj is self._listener:
            self._accept()
        elif isinstance(key.fileobj, socket.socket) and key.fileobj in self._clients:
            self._receive(key.fileobj)

    def _plug(self) -> None:
        listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        # The same port again after unplug(), though the old connections linger in TIME_WAIT.
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            listener.bind((self.host, self._port))
            listener.listen(4)
        except BaseException:
            listener.close()
            raise
        listener.setblocking(False)
        self._port = listener.getsockname()[1]
        self._listener = listener
        assert self._selector is not None
        self._selector.register(listener, selectors.EVENT_READ)

    def _accept(self) -> None:
        assert self._listener is not None and self._selector is not None
        try:
            connection, _ = self._listener.accept()
        except BlockingIOError:
            return
        connection.setblocking(False)
        self._clients[connection] = b""
        self._selector.register(connection, selectors.EVENT_READ)
        self.connections += 1

    def _drop(self, connection: socket.socket) -> None:
        assert self._selector is not None
        self._selector.unregister(connection)
        del self._clients[connection]
        connection.close()

    def _receive(self, connection: socket.socket) -> None:
        try:
            data = connection.recv(4096)
        except OSError:
            data = b""
        if not data:
            self._drop(connection)  # the driver hung up
            return
        buffer = self._clients[connection] + data
        # MBAP header: transaction id, protocol id (0), length of what follows, unit id.
        while len(buffer) >= 7:
            tid, protocol, length, unit = struct.unpack(">HHHB", buffer[:7])
            if protocol != 0 or not 2 <= length <= 254:
                self._drop(connection)  # not Modbus TCP: a server closes such a connection
                return
            if len(buffer) < 6 + length:
                break
            pdu, buffer = buffer[7:6 + length], buffer[6 + length:]
            answer = self._answer(tid, unit, pdu)
            if answer:
                with contextlib.suppress(OSError):  # a full or reset socket loses the reply
                    connection.sendall(answer)
        self._clients[connection] = buffer

    def _answer(self, tid: int, unit: int, pdu: bytes) -> bytes | None:
        try:
            if unit != self.unit_id:
                function = pdu[0] if pdu else 0
                response = bytes([(function | 0x80) & 0xFF, GATEWAY_TARGET_FAILED])
            else:
                response = self.controller.handle(pdu)
        except Exception as exc:
            _log.exception("emulator failed to answer %s", pdu.hex())
            self.failures.append(exc)
            return None
        behaviour = self.behaviour
        if behaviour is Behaviour.SILENT:
            return None
        protocol = 0xFFFF if behaviour is Behaviour.GARBAGE else 0  # a malformed MBAP header
        return struct.pack(">HHHB", tid, protocol, len(response) + 1, unit) + response

    def _unplug(self) -> None:
        for connection in list(self._clients):
            self._drop(connection)
        if self._listener is not None:
            assert self._selector is not None
            self._selector.unregister(self._listener)
            self._listener.close()
            self._listener = None
