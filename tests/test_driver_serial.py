"""The serial drivers against emulators of their devices' protocols on ptys: the Gardasoft LED
controller (projector) and the Zaber stage, plus the line transport they share over ``loop://``.

Each fault the transport knows -- garbage, silence, a pulled cable -- is raised as the right
DeviceError and the driver works again once the emulator is back to normal or replugged.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from eyeserver.errors import (
    ConfigError,
    DeviceDisconnectedError,
    DeviceError,
    DeviceNotOpenError,
    DeviceTimeoutError,
    DeviceValueError,
)
from eyeserver.hardware.drivers.gardasoft import GardasoftProjector
from eyeserver.hardware.drivers.serialline import ReplyError, SerialLine
from eyeserver.hardware.drivers.zaber import ZaberStage
from eyeserver.hardware.emulators.gardasoft import GardasoftEmulator
from eyeserver.hardware.emulators.serialpty import Behaviour
from eyeserver.hardware.emulators.zaber import ZaberEmulator
from eyeserver.hardware.registry import DriverContext, create_device, driver_class

REPLY_TIMEOUT_S = 0.5  # the emulators answer at once; 0.2 s was missed once at load 13
"""Per-reply timeout of the drivers under test: short, since the emulators answer at once."""

MAX_CURRENT_A = 2.0
PULSE_US = 150.0
DELAY_US = 20.0

MICROSTEP_MM = 0.0005
ZERO_MM = -15.0


def steps(z_mm: float) -> int:
    return round((z_mm - ZERO_MM) / MICROSTEP_MM)


# --- the line transport ---------------------------------------------------------------------


def loop_line(reply_terminator: bytes = b"\r", **options: Any) -> SerialLine:
    """A line on pyserial's loopback: every command comes back as its own reply."""
    return SerialLine("X1", "loop://", baudrate=115200, timeout_s=0.05, write_terminator=b"\r",
                      reply_terminator=reply_terminator, **options)


def test_line_round_trip() -> None:
    line = loop_line()
    line.open()
    try:
        assert line.request("PING", lambda text: text.lower()) == "ping"
        assert line.request("PONG", str) == "PONG"
    finally:
        line.close()
    with pytest.raises(DeviceNotOpenError):
        line.request("PING", str)


def test_line_rejected_reply_names_it() -> None:
    def check(text: str) -> str:
        raise ReplyError("expected a number")

    line = loop_line()
    line.open()
    try:
        with pytest.raises(DeviceError) as info:
            line.request("PING", check)
    finally:
        line.close()
    assert type(info.value) is DeviceError
    assert info.value.device_id == "X1"
    assert "'PING'" in str(info.value) and "expected a number" in str(info.value)


def test_line_incomplete_reply_is_garbage_not_silence() -> None:
    line = loop_line(reply_terminator=b">")
    line.open()
    try:
        with pytest.raises(DeviceError) as info:
            line.request("PING", str)
    finally:
        line.close()
    assert type(info.value) is DeviceError
    assert "incomplete reply" in str(info.value) and "b'PING\\r'" in str(info.value)


def test_line_skips_ignored_lines() -> None:
    line = loop_line(ignore=lambda text: text.startswith("#"))
    line.open()
    try:
        # Both lines come back; the first is skipped as a message the device sent on its own.
        assert line.request("#note\rPING", str) == "PING"
    finally:
        line.close()


def test_line_missing_port_is_disconnected(tmp_path: Path) -> None:
    line = SerialLine("X1", str(tmp_path / "ttyNONE"), baudrate=9600, timeout_s=0.05,
                      write_terminator=b"\r", reply_terminator=b"\r")
    with pytest.raises(DeviceDisconnectedError) as info:
        line.open()
    assert "ttyNONE" in str(info.value)
    assert not line.connected


# --- the Gardasoft projector ------------------------------------------------------------------


@pytest.fixture
def gardasoft(tmp_path: Path) -> Iterator[GardasoftEmulator]:
    with GardasoftEmulator(channels=2, rating_a=3.0, link_dir=tmp_path) as emulator:
        yield emulator


def make_projector(emulator: GardasoftEmulator, **options: Any) -> GardasoftProjector:
    settings: dict[str, Any] = {
        "port": emulator.port, "channel": 1, "max_current_a": MAX_CURRENT_A,
        "pulse_us": PULSE_US, "delay_us": DELAY_US, "timeout_s": REPLY_TIMEOUT_S, **options}
    return GardasoftProjector("P1", context=DriverContext(), **settings)


@pytest.fixture
def projector(gardasoft: GardasoftEmulator) -> Iterator[GardasoftProjector]:
    projector = make_projector(gardasoft)
    yield projector
    projector.close()


def test_gardasoft_from_configuration(gardasoft: GardasoftEmulator) -> None:
    assert driver_class("projector", "GardasoftProjector") is GardasoftProjector
    options = {"port": gardasoft.port, "channel": 2, "max_current_a": 1, "pulse_us": 100,
               "delay_us": 0}
    device = create_device("projector", "GardasoftProjector", "P2", options, DriverContext())
    assert isinstance(device, GardasoftProjector) and device.channel == 2
    with pytest.raises(ConfigError, match=r"'P2'.*channel must be 1 or more"):
        create_device("projector", "GardasoftProjector", "P2", {**options, "channel": 0},
                      DriverContext())


def test_settings_reach_the_controller(gardasoft: GardasoftEmulator,
                                       projector: GardasoftProjector) -> None:
    channel = gardasoft.channels[1]
    projector.open()
    assert projector.firmware == gardasoft.model
    assert (channel.mode, channel.current_a) == ("pulse", MAX_CURRENT_A)
    assert (channel.pulse_us, channel.delay_us) == (PULSE_US, DELAY_US)
    assert gardasoft.received[-1] == "RT1,150us,20us,2A"

    projector.set_intensity(0.25)
    assert (channel.mode, channel.current_a) == ("pulse", 0.5)
    projector.set_strobe(False)
    assert (channel.mode, channel.current_a) == ("continuous", 0.5)
    assert gardasoft.received[-1] == "RS1,0.5A"
    projector.set_enabled(False)
    assert (channel.mode, channel.current_a) == ("continuous", 0.0)
    projector.set_enabled(True)
    assert (channel.mode, channel.current_a) == ("continuous", 0.5)
    projector.set_strobe(True)
    assert (channel.mode, channel.current_a, channel.pulse_us) == ("pulse", 0.5, PULSE_US)
    projector.set_enabled(False)
    assert (channel.mode, channel.current_a) == ("pulse", 0.0)
    assert gardasoft.channels[2].mode == "off"  # the other channel is not ours

    projector.close()
    assert (channel.mode, channel.current_a) == ("continuous", 0.0)  # dark when closed


def test_echoing_controller(tmp_path: Path) -> None:
    with GardasoftEmulator(echo=True, link_dir=tmp_path) as emulator:
        projector = make_projector(emulator)
        projector.open()
        try:
            projector.set_intensity(0.5)
            projector.check()
            assert emulator.channels[1].current_a == 1.0
        finally:
            projector.close()


def test_controller_error_replies_fail_with_its_text(gardasoft: GardasoftEmulator) -> None:
    projector = make_projector(gardasoft, channel=3)  # the emulated unit has two channels
    with pytest.raises(DeviceError) as info:
        projector.open()
    assert "'RT3,150us,20us,2A'" in str(info.value) and "Err 1" in str(info.value)
    assert not projector.is_open


def test_adjusted_value_fails_and_keeps_the_setting(gardasoft: GardasoftEmulator,
                                                    projector: GardasoftProjector) -> None:
    projector.open()
    projector.set_intensity(0.25)
    gardasoft.rating_a = 1.0
    with pytest.raises(DeviceError) as info:
        projector.set_intensity(0.75)  # 1.5 A: the controller clamps it to 1 A with Err 5
    assert "Err 5" in str(info.value) and "adjusted" in str(info.value)
    assert projector.intensity == 0.25


def test_check_reports_light_failures(gardasoft: GardasoftEmulator,
                                      projector: GardasoftProjector) -> None:
    gardasoft.raise_event(1, 131)  # left over from before: cleared by open
    projector.open()
    projector.check()
    gardasoft.raise_event(2, 131)  # another channel's light: not this projector's fault
    projector.check()
    gardasoft.raise_event(1, 128)  # a light was connected and works
    projector.check()
    gardasoft.raise_event(1, 131)
    with pytest.raises(DeviceError) as info:
        projector.check()
    assert "Evt1,131" in str(info.value) and "over-current" in str(info.value)
    projector.check()  # reading the event cleared it
    assert gardasoft.received.count("ST1") == 5


def test_projector_missing_port(tmp_path: Path) -> None:
    projector = GardasoftProjector("P1", context=DriverContext(), port=str(tmp_path / "ttyX"),
                                   channel=1, max_current_a=1.0, pulse_us=100.0, delay_us=0.0)
    with pytest.raises(DeviceDisconnectedError):
        projector.open()
    assert not projector.is_open


def break_line(emulator: GardasoftEmulator | ZaberEmulator, fault: str) -> None:
    if fault == "unplugged":
        emulator.unplug()
    else:
        emulator.behaviour = Behaviour(fault)


def mend_line(emulator: GardasoftEmulator | ZaberEmulator, fault: str) -> None:
    if fault == "unplugged":
        emulator.replug()
    else:
        emulator.behaviour = Behaviour.NORMAL


FAULTS = [
    pytest.param("garbage", DeviceError, "garbage", id="garbage"),
    pytest.param("silent", DeviceTimeoutError, "no reply", id="silent"),
    pytest.param("unplugged", DeviceDisconnectedError, "failed", id="unplugged"),
]


@pytest.mark.parametrize(("fault", "error", "words"), FAULTS)
def test_projector_faults_and_recovery(gardasoft: GardasoftEmulator,
                                       projector: GardasoftProjector, fault: str,
                                       error: type[DeviceError], words: str) -> None:
    projector.open()
    break_line(gardasoft, fault)
    with pytest.raises(DeviceError) as info:
        projector.set_intensity(0.5)
    assert type(info.value) is error
    assert info.value.device_id == "P1"
    assert words in str(info.value) and "RT1,150us,20us,1A" in str(info.value)
    assert projector.intensity == 1.0
    with pytest.raises(error) as info:
        projector.check()
    assert type(info.value) is error
    if fault == "unplugged":  # the port is gone now, not merely failing
        assert "cannot open" in str(info.value)

    mend_line(gardasoft, fault)
    projector.set_intensity(0.5)
    projector.check()
    assert gardasoft.channels[1].current_a == 1.0


# --- the Zaber stage --------------------------------------------------------------------------


@pytest.fixture
def zaber(tmp_path: Path) -> Iterator[ZaberEmulator]:
    with ZaberEmulator(address=1, homed=True, link_dir=tmp_path) as emulator:
        emulator.axes[1].speed = 2_000_000.0  # 30 mm in 30 ms: BUSY for a few polls
        yield emulator


def make_stage(emulator: ZaberEmulator, **options: Any) -> ZaberStage:
    settings: dict[str, Any] = {
        "port": emulator.port, "microstep_mm": MICROSTEP_MM, "zero_mm": ZERO_MM,
        "timeout_s": REPLY_TIMEOUT_S, "settle_timeout_s": 2.0, "poll_interval_s": 0.005,
        **options}
    return ZaberStage("Z1", context=DriverContext(), **settings)


@pytest.fixture
def stage(zaber: ZaberEmulator) -> Iterator[ZaberStage]:
    stage = make_stage(zaber)
    yield stage
    stage.close()


def test_stage_from_configuration(zaber: ZaberEmulator) -> None:
    options = {"port": zaber.port, "microstep_mm": MICROSTEP_MM, "timeout_s": REPLY_TIMEOUT_S}
    assert driver_class("stage", "ZaberStage") is ZaberStage
    device = create_device("stage", "ZaberStage", "Z1", options, DriverContext())
    assert isinstance(device, ZaberStage) and not device.is_open
    with pytest.raises(ConfigError, match=r"'Z1'.*unexpected option.*speed"):
        create_device("stage", "ZaberStage", "Z1", {**options, "speed": 3}, DriverContext())


def test_stage_moves_to_heights(zaber: ZaberEmulator, stage: ZaberStage) -> None:
    stage.open()
    assert stage.travel_mm == (-15.0, 30.0)  # the device's 0..100000 covers all of it
    for z_mm in (0.0, 25.0, -10.0, 30.0, -15.0):
        stage.move_to(z_mm)
        assert zaber.axis().position == steps(z_mm)
        assert not zaber.axis().busy
        assert stage.position_mm == z_mm
    assert f"/1 1 move abs {steps(25.0)}" in zaber.received
    assert zaber.axis().busy_replies > 0  # it waited through BUSY replies


def test_stage_travel_narrowed_by_device_limits(zaber: ZaberEmulator, stage: ZaberStage) -> None:
    zaber.axes[1].limit_max = steps(5.0)
    stage.open()
    assert stage.travel_mm == (-15.0, 5.0)
    with pytest.raises(DeviceValueError):
        stage.move_to(10.0)
    assert not any(command.startswith("/1 1 move") for command in zaber.received)


def test_stage_rejected_move(zaber: ZaberEmulator, stage: ZaberStage) -> None:
    stage.open()
    stage.move_to(-10.0)
    zaber.axes[1].limit_max = steps(0.0)  # the device's limit changed behind the driver's back
    with pytest.raises(DeviceError) as info:
        stage.move_to(5.0)
    assert "rejected" in str(info.value) and "BADDATA" in str(info.value)
    assert stage.position_mm == -10.0
    assert zaber.axis().position == steps(-10.0)


def test_stage_times_out_when_never_idle(zaber: ZaberEmulator) -> None:
    stage = make_stage(zaber, settle_timeout_s=0.1)
    stage.open()
    zaber.axes[1].stuck = True
    started = time.monotonic()
    try:
        with pytest.raises(DeviceTimeoutError) as info:
            stage.move_to(5.0)
        assert 0.1 <= time.monotonic() - started < 1.0
        assert "still moving" in str(info.value)
        assert zaber.received[-2:] == ["/1 1 stop", "/1 1 get pos"]  # stopped, not left running
        zaber.axes[1].stuck = False
        stage.move_to(5.0)
        assert zaber.axis().position == steps(5.0)
    finally:
        stage.close()


def test_stage_fault_flag_fails_the_move(zaber: ZaberEmulator, stage: ZaberStage) -> None:
    stage.open()
    zaber.axes[1].stall_at = steps(-5.0)
    with pytest.raises(DeviceError) as info:
        stage.move_to(10.0)
    assert "FS" in str(info.value) and "stalled and stopped" in str(info.value)
    assert zaber.axis().position == steps(-5.0)
    with pytest.raises(DeviceError):
        stage.move_to(10.0)  # the fault latches until someone clears it
    zaber.axes[1].flags.clear()
    stage.move_to(10.0)
    assert zaber.axis().position == steps(10.0)


def test_stage_without_reference(tmp_path: Path) -> None:
    with ZaberEmulator(homed=False, link_dir=tmp_path) as emulator:
        emulator.axes[1].position = 20_000
        stage = make_stage(emulator)
        with pytest.raises(DeviceError) as info:
            stage.open()
        assert "no reference position (WR)" in str(info.value)
        assert "/1 1 home" not in emulator.received

        stage = make_stage(emulator, home_on_open=True)
        stage.open()
        try:
            assert "/1 1 home" in emulator.received
            assert emulator.axis().homed and emulator.axis().position == 0
            stage.move_to(0.0)
            assert emulator.axis().position == steps(0.0)
        finally:
            stage.close()


def test_stage_wrong_address_is_silence(zaber: ZaberEmulator) -> None:
    stage = make_stage(zaber, address=2)
    with pytest.raises(DeviceTimeoutError) as info:
        stage.open()
    assert "'/2 1'" in str(info.value)
    assert not stage.is_open


@pytest.mark.parametrize(("fault", "error", "words"), FAULTS)
def test_stage_faults_and_recovery(zaber: ZaberEmulator, stage: ZaberStage, fault: str,
                                   error: type[DeviceError], words: str) -> None:
    stage.open()
    stage.move_to(0.0)
    break_line(zaber, fault)
    with pytest.raises(DeviceError) as info:
        stage.move_to(5.0)
    assert type(info.value) is error
    assert info.value.device_id == "Z1"
    assert words in str(info.value) and f"move abs {steps(5.0)}" in str(info.value)
    assert stage.position_mm == 0.0

    mend_line(zaber, fault)
    stage.move_to(5.0)
    assert zaber.axis().position == steps(5.0)
    assert stage.position_mm == 5.0


def test_an_emulator_that_cannot_plug_in_says_why(tmp_path: Path) -> None:
    """A port link that cannot be made (its directory is missing) fails start() with that
    error, not a later one from cleaning up half a pty, and leaves no descriptor open."""
    import os

    before = set(os.listdir("/proc/self/fd"))
    emulator = GardasoftEmulator(link_dir=tmp_path / "missing")
    with pytest.raises(FileNotFoundError):
        emulator.start()
    emulator.stop()
    assert set(os.listdir("/proc/self/fd")) <= before
