"""The Opto Engineering-style Modbus strobe controller driver (OptoProjector) against its emulator,
over both transports: Modbus RTU on a pty and Modbus TCP on loopback.

Every test runs over both transports. Settings land in the emulated controller's registers and
are read back; refused requests (Modbus exception responses), status fault bits, garbage,
silence and a pulled cable are each raised as the right DeviceError naming the registers; the
driver works again once the controller is back to normal or replugged.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from eyeserver.errors import (
    ConfigError,
    DeviceDisconnectedError,
    DeviceError,
    DeviceTimeoutError,
)
from eyeserver.hardware.drivers.modbus import OptoProjector
from eyeserver.hardware.emulators.modbus import (
    Behaviour,
    ModbusRequest,
    OptoController,
    OptoRtuEmulator,
    OptoTcpEmulator,
    crc16,
)
from eyeserver.hardware.registry import DriverContext, create_device, driver_class

REPLY_TIMEOUT_S = 0.5  # the emulators answer at once; 0.2 s was missed once at load 13
"""Per-response timeout of the driver under test: short, since the emulator answers at once."""

MAX_CURRENT_MA = 2000.0
PULSE_US = 150.0
DELAY_US = 20.0

LD1, LD2 = 256, 272
"""The first register (MODE) of the LD1 and LD2 blocks."""

Emulator = OptoRtuEmulator | OptoTcpEmulator


@pytest.fixture(params=["rtu", "tcp"])
def emulator(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Emulator]:
    controller = OptoController(channels=4, rating_ma=3000)
    if request.param == "rtu":
        with OptoRtuEmulator(controller, link_dir=tmp_path) as rtu:
            yield rtu
    else:
        with OptoTcpEmulator(controller) as tcp:
            yield tcp


def make_projector(emulator: Emulator, **options: Any) -> OptoProjector:
    settings: dict[str, Any] = {
        **emulator.driver_options(), "channel": 1, "max_current_ma": MAX_CURRENT_MA,
        "pulse_us": PULSE_US, "delay_us": DELAY_US, "timeout_s": REPLY_TIMEOUT_S, **options}
    return OptoProjector("P1", context=DriverContext(), **settings)


@pytest.fixture
def projector(emulator: Emulator) -> Iterator[OptoProjector]:
    projector = make_projector(emulator)
    yield projector
    projector.close()


def block(emulator: Emulator, channel: int = 1) -> tuple[int, int, int, int]:
    """The emulated channel's MODE, CURRENT_MA, PULSE_US and DELAY_US."""
    state = emulator.controller.channels[channel]
    return state.mode, state.current_ma, state.pulse_us, state.delay_us


# --- the emulator's own framing ---------------------------------------------------------------


def test_crc16_matches_the_modbus_specification_example() -> None:
    # Read 10 holding registers from 0 of unit 1 goes out as 01 03 00 00 00 0A C5 CD.
    assert crc16(bytes.fromhex("01030000000a")).to_bytes(2, "little") == bytes.fromhex("c5cd")


def test_controller_refuses_bad_requests_without_writing() -> None:
    controller = OptoController(channels=2, rating_ma=1000)
    assert controller.handle(bytes.fromhex("10 0100 0002 04 0002 03e9")) == b"\x90\x03"
    assert controller.channels[1].mode == 0  # the good MODE was not written either
    assert controller.handle(bytes.fromhex("06 0104 0001")) == b"\x86\x02"  # STATUS: read only
    assert controller.handle(bytes.fromhex("03 0120 0001")) == b"\x83\x02"  # no LD3
    assert controller.handle(bytes.fromhex("2b 0e01 00")) == b"\xab\x01"
    assert controller.handle(bytes.fromhex("06 0101 03e8")) == bytes.fromhex("06 0101 03e8")
    assert controller.channels[1].current_ma == 1000


# --- configuration ----------------------------------------------------------------------------


def test_from_configuration(emulator: Emulator) -> None:
    assert driver_class("projector", "OptoProjector") is OptoProjector
    options = {**emulator.driver_options(), "channel": 2, "max_current_ma": 1000,
               "pulse_us": 100, "delay_us": 0}
    device = create_device("projector", "OptoProjector", "P2", options, DriverContext())
    assert isinstance(device, OptoProjector) and device.channel == 2 and not device.is_open
    bad = [({"channel": 0}, "channel must be 1 or more"),
           ({"pulse_us": 0}, "pulse_us must be 1 to 65535"),
           ({"max_current_ma": 70_000}, "max_current_ma must be"),
           ({"transport": "udp"}, "transport must be 'rtu' or 'tcp'"),
           ({"unit_id": 300}, "unit_id must be")]
    for change, words in bad:
        with pytest.raises(ConfigError, match=rf"'P2'.*{words}"):
            create_device("projector", "OptoProjector", "P2", {**options, **change},
                          DriverContext())


def test_each_transport_needs_its_address() -> None:
    common = {"channel": 1, "max_current_ma": 1000, "pulse_us": 100, "delay_us": 0}
    for options, words in [({"transport": "rtu"}, "'rtu' needs port"),
                           ({"transport": "tcp"}, "'tcp' needs host"),
                           ({"transport": "tcp", "host": "h", "port": "/dev/ttyS0"},
                            "'tcp' takes host and tcp_port"),
                           ({"transport": "rtu", "port": "/dev/ttyS0", "host": "h"},
                            "'rtu' takes port")]:
        with pytest.raises(ConfigError, match=words):
            create_device("projector", "OptoProjector", "P1", {**common, **options},
                          DriverContext())


# --- settings ---------------------------------------------------------------------------------


def test_settings_reach_the_controller(emulator: Emulator) -> None:
    projector = make_projector(emulator, channel=2)
    projector.open()
    try:
        assert block(emulator, 2) == (2, 2000, 150, 20)  # strobe, full current
        assert projector.firmware == "boot 0x0100, MCU 0x0110, FPGA 0x0003"
        assert projector.describe()["device_type"] == 0x0804
        # One write of the four settings, then a read of them and STATUS.
        assert emulator.controller.requests[-2:] == [
            ModbusRequest(0x10, LD2, values=(2, 2000, 150, 20)),
            ModbusRequest(0x03, LD2, count=5)]

        projector.set_intensity(0.25)
        assert block(emulator, 2) == (2, 500, 150, 20)
        projector.set_strobe(False)
        assert block(emulator, 2) == (1, 500, 150, 20)  # continuous
        projector.set_enabled(False)
        assert block(emulator, 2) == (0, 0, 150, 20)  # off and no current
        projector.set_enabled(True)
        assert block(emulator, 2) == (1, 500, 150, 20)
        projector.set_strobe(True)
        assert block(emulator, 2) == (2, 500, 150, 20)
        projector.check()
        assert block(emulator, 1) == (0, 0, 100, 0)  # another output: untouched
        assert all(request.address >= LD2 or request.function == 0x03
                   for request in emulator.controller.requests)
    finally:
        projector.close()
    assert block(emulator, 2) == (0, 0, 150, 20)  # dark when closed


def test_current_rounds_to_whole_milliamps(emulator: Emulator,
                                           projector: OptoProjector) -> None:
    projector.open()
    projector.set_intensity(0.3337)
    assert emulator.controller.channels[1].current_ma == 667
    assert projector.current_ma == 667


# --- refused requests and reported faults -----------------------------------------------------


def test_missing_output_is_an_illegal_address(emulator: Emulator) -> None:
    projector = make_projector(emulator, channel=5)  # the emulated controller has four
    with pytest.raises(DeviceError) as info:
        projector.open()
    message = str(info.value)
    assert type(info.value) is DeviceError
    assert "LD5 MODE..DELAY_US (registers 320-323)" in message
    assert "Modbus exception 2 (illegal data address)" in message
    assert not projector.is_open


def test_current_above_the_rating_is_refused(emulator: Emulator,
                                             projector: OptoProjector) -> None:
    projector.open()
    emulator.controller.rating_ma = 1000
    with pytest.raises(DeviceError) as info:
        projector.set_intensity(0.75)  # 1500 mA
    assert type(info.value) is DeviceError
    assert "registers 256-259) = [2, 1500, 150, 20]" in str(info.value)
    assert "Modbus exception 3 (illegal data value)" in str(info.value)
    assert projector.intensity == 1.0
    assert block(emulator) == (2, 2000, 150, 20)  # a refused request changes nothing
    projector.set_intensity(0.5)  # the connection survives a refusal
    assert block(emulator) == (2, 1000, 150, 20)


def test_exception_on_a_read_names_the_register(emulator: Emulator,
                                                projector: OptoProjector) -> None:
    projector.open()
    emulator.controller.forced_exception = 6
    with pytest.raises(DeviceError) as info:
        projector.check()
    assert type(info.value) is DeviceError
    assert "reading ERROR_WORD (register 16)" in str(info.value)
    assert "Modbus exception 6 (server device busy)" in str(info.value)
    emulator.controller.forced_exception = None
    projector.check()


def test_clamped_current_fails_the_read_back(emulator: Emulator,
                                             projector: OptoProjector) -> None:
    projector.open()
    emulator.controller.clamp_current = True
    emulator.controller.rating_ma = 1000
    with pytest.raises(DeviceError) as info:
        projector.set_intensity(0.75)  # 1500 mA, set to 1000 mA without a word
    assert "LD1 CURRENT_MA (register 257)" in str(info.value)
    assert "reads back 1000, not 1500" in str(info.value)
    assert projector.intensity == 1.0
    with pytest.raises(DeviceError, match="reads 1000, not 2000"):
        projector.check()  # the controller is not where the projector says it is
    projector.set_intensity(0.5)
    projector.check()


@pytest.mark.parametrize("channel", [1, 2, 3])
def test_check_reports_controller_errors_of_this_output(emulator: Emulator,
                                                        channel: int) -> None:
    controller = emulator.controller
    projector = make_projector(emulator, channel=channel)
    projector.open()
    try:
        pair = (channel + 1) // 2  # LD1/LD2 are pair 1, LD3/LD4 pair 2
        for other in {1, 2, 3, 4} - {channel}:
            controller.error_word = 1 << (4 + other)  # a fault on another output
            projector.check()
        controller.error_word = 1 << (1 + (pair % 4))  # another pair's stages too hot
        projector.check()

        controller.error_word = 1 << pair  # this output's stages too hot
        with pytest.raises(DeviceError) as info:
            projector.check()
        assert f"ERROR_WORD 0x{1 << pair:04x}" in str(info.value)
        assert f"LD{2 * pair - 1}/LD{2 * pair} output stages too hot" in str(info.value)
        controller.error_word = 1 << (4 + channel)
        with pytest.raises(DeviceError, match=f"bit {4 + channel}: fault on LD{channel}"):
            projector.check()
        controller.error_word = 1  # no supply for the power stages: no output lights
        with pytest.raises(DeviceError, match="no supply for the power stages"):
            projector.check()
    finally:
        controller.error_word = 0
        projector.close()


def test_check_reports_status_faults_of_this_output(emulator: Emulator,
                                                    projector: OptoProjector) -> None:
    controller = emulator.controller
    projector.open()
    projector.check()
    controller.channels[2].faults = 0b1000  # over-current on another output
    projector.check()

    controller.channels[1].faults = 0b1010  # open load and over-current
    with pytest.raises(DeviceError) as info:
        projector.check()
    assert "LD1 STATUS (register 260)" in str(info.value) and "0x000b" in str(info.value)
    assert "open load" in str(info.value) and "over-current" in str(info.value)
    with pytest.raises(DeviceError, match="LD1 STATUS"):
        projector.set_intensity(0.5)  # a setting is read back with STATUS too
    controller.channels[1].faults = 0
    # The write went through, but the projector kept its old intensity: they disagree.
    with pytest.raises(DeviceError, match=r"CURRENT_MA .* reads 1000, not 2000"):
        projector.check()
    projector.set_intensity(0.5)
    projector.check()


def test_power_cycled_controller_fails_the_check(emulator: Emulator,
                                                 projector: OptoProjector) -> None:
    projector.open()
    emulator.controller.reset()  # back to its power-up registers: off
    with pytest.raises(DeviceError) as info:
        projector.check()
    assert "LD1 MODE (register 256)" in str(info.value)
    assert "reads 0 (off), not 2 (strobe)" in str(info.value)
    projector.close()
    projector.open()  # opening writes the settings again
    projector.check()
    assert block(emulator) == (2, 2000, 150, 20)


# --- the transport --------------------------------------------------------------------------


def test_missing_port_is_disconnected(tmp_path: Path) -> None:
    projector = OptoProjector("P1", context=DriverContext(), transport="rtu",
                              port=str(tmp_path / "ttyX"), parity="N", channel=1,
                              max_current_ma=1000, pulse_us=100, delay_us=0)
    with pytest.raises(DeviceDisconnectedError) as info:
        projector.open()
    assert "cannot connect to serial port" in str(info.value) and "ttyX" in str(info.value)
    assert not projector.is_open


def test_refused_connection_is_disconnected() -> None:
    with OptoTcpEmulator() as emulator:
        emulator.unplug()  # nothing listens on the port
        projector = make_projector(emulator)
        with pytest.raises(DeviceDisconnectedError) as info:
            projector.open()
        assert f"cannot connect to Modbus TCP 127.0.0.1:{emulator.port}" in str(info.value)
        assert not projector.is_open


def test_wrong_unit_id(emulator: Emulator) -> None:
    projector = make_projector(emulator, unit_id=7)
    with pytest.raises(DeviceError) as info:
        projector.open()
    if isinstance(emulator, OptoRtuEmulator):  # on a bus, another address is silence
        assert type(info.value) is DeviceTimeoutError
        assert "reading DEVICE_TYPE (register 0)" in str(info.value)
    else:  # a Modbus TCP gateway answers for the unit it cannot reach
        assert type(info.value) is DeviceError
        assert "Modbus exception 11 (gateway target device failed to respond)" in str(
            info.value)
    assert not projector.is_open


def break_link(emulator: Emulator, fault: str) -> None:
    if fault == "unplugged":
        emulator.unplug()
    else:
        emulator.behaviour = Behaviour(fault)


def mend_link(emulator: Emulator, fault: str) -> None:
    if fault == "unplugged":
        emulator.replug()
    else:
        emulator.behaviour = Behaviour.NORMAL


FAULTS = [
    pytest.param("garbage", DeviceError, "garbage in reply to", id="garbage"),
    pytest.param("silent", DeviceTimeoutError, "no reply to", id="silent"),
    pytest.param("unplugged", DeviceDisconnectedError, "failed during", id="unplugged"),
]


@pytest.mark.parametrize(("fault", "error", "words"), FAULTS)
def test_faults_and_recovery(emulator: Emulator, projector: OptoProjector, fault: str,
                             error: type[DeviceError], words: str) -> None:
    projector.open()
    break_link(emulator, fault)
    with pytest.raises(DeviceError) as info:
        projector.set_intensity(0.5)
    assert type(info.value) is error
    assert info.value.device_id == "P1"
    assert words in str(info.value)
    assert "LD1 MODE..DELAY_US (registers 256-259) = [2, 1000, 150, 20]" in str(info.value)
    assert projector.intensity == 1.0
    with pytest.raises(DeviceError) as info:
        projector.check()
    assert type(info.value) is error
    if fault == "unplugged":  # the controller is gone now, not merely failing
        assert "cannot connect" in str(info.value)

    mend_link(emulator, fault)
    projector.set_intensity(0.5)
    projector.check()
    assert block(emulator) == (2, 1000, 150, 20)
