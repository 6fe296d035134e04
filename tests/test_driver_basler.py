"""The Basler driver through pypylon, against pylon's own camera emulation.

pylon's emulation transport layer (``BaslerCamEmu``) makes ``PYLON_CAMEMU=<n>`` emulated cameras
(serial numbers ``0815-0000``, ``0815-0001``, ...) that go through pylon's whole InstantCamera
path: features, the trigger, the grab engine and its buffers. pylon reads the variable at each
device enumeration, so the fixture sets it per test. Tests that need pypylon are skipped, with the
reason, only where it is not installed (the proposed ``basler`` extra installs it).

What the emulation shows: settings as a camera takes them (exposure in 1 µs steps, gain through a
fixed-point register), software triggering, the test images the Basler documentation describes
(Testimage1, a fixed diagonal grey gradient ``(column + row) mod 256``; Testimage2, the same
moving one pixel per acquisition: ``+ counter``), 12-bit pixels, and a failed buffer
(``ForceFailedBuffer``). What it cannot, so what stays untested on a device: a hardware trigger
line firing (its Line1 never does), device timestamps and their tick rate (it stamps 0; the tick
arithmetic is tested on numbers), frames lost whole (its block ids never skip), a region the
camera rounds (it takes any; the shared read-back check is tested over the IDS fake), user ids
(it keeps ``DeviceUserID`` out of the enumeration), ``GainAbs``/``GainRaw`` cameras, and a camera
unplugged: pylon's removal flag is simulated by wrapping the emulated camera's pylon object
(:class:`RemovedCamera`).
"""

# The stand-in for pylon's camera spells pylon's method names.
# ruff: noqa: N802

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest

from eyeserver.core.frames import Frame
from eyeserver.errors import (
    ConfigError,
    DeviceDisconnectedError,
    DeviceError,
    DeviceTimeoutError,
    DeviceValueError,
)
from eyeserver.hardware.drivers.basler import BaslerCamera, ticks_to_ns
from eyeserver.hardware.registry import DriverContext, create_device, driver_class
from tests.hardware.needs import needs_pylon
from tests.hardware.timeouts import MISSING_TIMEOUT_S, READ_TIMEOUT_S

ROI = {"offset_x": 16, "offset_y": 8, "width": 256, "height": 128}
"""A small region: quick frames, and offsets that show in the test images."""

FIRST, SECOND = "0815-0000", "0815-0001"
"""The serial numbers of the first two emulated cameras."""


def emulated_image(number: int, counter: int, bit_depth: int = 8) -> np.ndarray:
    """The emulator's test image ``number`` of the ROI for the ``counter``-th acquisition since
    grabbing started (1 for the first): the 8-bit diagonal gradient, in sensor coordinates, in the
    top bits of a 10- or 12-bit pixel (observed of pylon 26.10's emulation)."""
    y, x = np.mgrid[0:ROI["height"], 0:ROI["width"]]
    moving = counter if number == 2 else 0
    gradient = (x + ROI["offset_x"] + y + ROI["offset_y"] + moving) % 256
    if bit_depth == 8:
        return gradient.astype(np.uint8)
    return (gradient << (bit_depth - 8)).astype(np.uint16)


@pytest.fixture
def context() -> DriverContext:
    return DriverContext()


@pytest.fixture
def make_camera(monkeypatch: pytest.MonkeyPatch,
                context: DriverContext) -> Iterator[Callable[..., BaslerCamera]]:
    """Build cameras on pylon's emulation (software-triggered, Testimage2, the small region);
    all closed afterwards."""
    monkeypatch.setenv("PYLON_CAMEMU", "2")
    made: list[BaslerCamera] = []

    def make(**options: Any) -> BaslerCamera:
        settings: dict[str, Any] = {"serial": FIRST, "device_class": "BaslerCamEmu",
                                    "trigger_source": "Software", "test_image": "Testimage2",
                                    **ROI}
        settings.update(options)
        camera = BaslerCamera(settings.pop("device_id", "C1"), context=context, **settings)
        made.append(camera)
        return camera

    try:
        yield make
    finally:
        for camera in made:
            camera.close()


def read_next(camera: BaslerCamera) -> Frame:
    camera.software_trigger()
    return camera.read_frame(READ_TIMEOUT_S)


def pylon_camera(camera: BaslerCamera) -> Any:
    """The open camera's pylon InstantCamera, for the emulator's own features (failed buffers)
    and for simulating a removal; the driver offers neither."""
    link = camera._link
    assert link is not None
    return link._camera


# --- settings as the camera reports them ----------------------------------------------------


@needs_pylon
def test_settings_are_read_back_from_the_camera(
        make_camera: Callable[..., BaslerCamera]) -> None:
    camera = make_camera()
    camera.open()
    info = camera.describe()
    assert (camera.width, camera.height, camera.bit_depth) == (256, 128, 8)
    assert (info["offset_x"], info["offset_y"]) == (16, 8)
    assert (info["vendor"], info["model"], info["serial_number"]) == ("Basler", "Emulation",
                                                                      FIRST)
    assert (info["pixel_format"], info["trigger_source"], info["test_image"]) == (
        "Mono8", "Software", "Testimage2")
    assert (info["exposure_feature"], info["gain_feature"]) == ("ExposureTime", "Gain")
    # The emulator takes 1..10^7 µs and 0..48 dB: the rig's policy ranges are the narrower.
    assert camera.exposure_range_us == (10.0, 40_000.0)
    assert camera.gain_range_db == (0.0, 24.0)
    # Exposure goes in whole microseconds, so what the camera took differs from what was asked,
    # and that is what the driver reports; gain comes back 3.0 to the register's rounding.
    camera.set_exposure_us(1234.5)
    camera.set_gain_db(3.0)
    assert (camera.exposure_us, camera.gain_db) == (1235.0, 3.0)
    node_map = pylon_camera(camera).GetNodeMap()
    assert node_map.GetNode("ExposureTime").GetValue() == 1235.0
    assert node_map.GetNode("Gain").GetValue() == pytest.approx(3.0, abs=1e-4)
    assert node_map.GetNode("TriggerMode").GetValue() == "On"
    assert node_map.GetNode("AcquisitionFrameRateEnable").GetValue() is False
    meta = read_next(camera).meta
    assert (meta.exposure_us, meta.gain_db) == (1235.0, 3.0)


@needs_pylon
def test_settings_survive_a_reopen(make_camera: Callable[..., BaslerCamera]) -> None:
    camera = make_camera()
    camera.open()
    camera.set_exposure_us(2_500.0)
    camera.set_gain_db(4.0)
    camera.close()
    camera.open()
    assert (camera.exposure_us, camera.gain_db) == (2_500.0, 4.0)
    assert pylon_camera(camera).GetNodeMap().GetNode("ExposureTime").GetValue() == 2_500.0
    assert read_next(camera).meta.exposure_us == 2_500.0


@needs_pylon
def test_test_image_is_turned_off_unless_asked_for(
        make_camera: Callable[..., BaslerCamera]) -> None:
    camera = make_camera(test_image=None)
    camera.open()
    assert camera.describe()["test_image"] == "Off"
    # The emulator's default is Testimage2: a real camera left so must not pass for a picture.
    frame = read_next(camera)
    assert not np.array_equal(frame.image, emulated_image(2, 1))


# --- triggering -----------------------------------------------------------------------------


@needs_pylon
def test_each_software_trigger_gives_one_frame(
        make_camera: Callable[..., BaslerCamera]) -> None:
    camera = make_camera()
    camera.open()
    for _ in range(3):
        camera.software_trigger()
    frames = [camera.read_frame(READ_TIMEOUT_S) for _ in range(3)]
    with pytest.raises(DeviceTimeoutError):
        camera.read_frame(0.2)
    assert [f.meta.frame_counter for f in frames] == [0, 1, 2]
    assert [f.extra["block_id"] for f in frames] == [0, 1, 2]
    assert camera.dropped_frames == 0


@needs_pylon
def test_hardware_trigger_source(make_camera: Callable[..., BaslerCamera]) -> None:
    with pytest.raises(DeviceValueError, match=r"TriggerSource has no 'Line9' \(it has .*Line1"):
        make_camera(trigger_source="Line9").open()
    # Line1 exists but nothing drives it: a triggered camera then sends nothing at all.
    camera = make_camera(trigger_source="Line1")
    camera.open()
    assert camera.describe()["trigger_source"] == "Line1"
    assert pylon_camera(camera).GetNodeMap().GetNode("TriggerSource").GetValue() == "Line1"
    with pytest.raises(DeviceValueError, match="needs trigger_source 'Software'"):
        camera.software_trigger()
    with pytest.raises(DeviceTimeoutError):
        camera.read_frame(0.2)
    assert camera.dropped_frames == 0


# --- images ---------------------------------------------------------------------------------


@needs_pylon
def test_frames_are_the_emulators_test_images(
        make_camera: Callable[..., BaslerCamera]) -> None:
    fixed = make_camera(test_image="Testimage1")
    fixed.open()
    for _ in range(2):
        np.testing.assert_array_equal(read_next(fixed).image, emulated_image(1, 0))
    fixed.close()
    moving = make_camera(test_image="Testimage2")
    moving.open()
    for counter in (1, 2, 3):
        frame = read_next(moving)
        assert frame.image.dtype == np.uint8 and frame.image.flags.writeable
        np.testing.assert_array_equal(frame.image, emulated_image(2, counter))


@needs_pylon
def test_twelve_bit_frames(make_camera: Callable[..., BaslerCamera]) -> None:
    camera = make_camera(pixel_format="Mono12", test_image="Testimage1")
    camera.open()
    frame = read_next(camera)
    assert (camera.bit_depth, frame.meta.bit_depth) == (12, 12)
    assert frame.image.dtype == np.uint16 and int(frame.image.max()) < 4096
    np.testing.assert_array_equal(frame.image, emulated_image(1, 0, bit_depth=12))


# --- lost frames ----------------------------------------------------------------------------


@needs_pylon
def test_failed_grab_is_dropped_and_counted(make_camera: Callable[..., BaslerCamera]) -> None:
    camera = make_camera()
    camera.open()
    emulator = pylon_camera(camera)
    emulator.ForceFailedBufferCount.SetValue(1)
    first = read_next(camera)
    emulator.ForceFailedBuffer.Execute()  # the next buffer comes back failed
    camera.software_trigger()
    with pytest.raises(DeviceTimeoutError):
        camera.read_frame(0.3)
    assert camera.dropped_frames == 1 and camera.describe()["dropped_frames"] == 1
    after = read_next(camera)
    assert (first.meta.frame_counter, first.meta.dropped_frames, first.meta.trigger_index) == (
        0, 0, 0)
    assert (after.meta.frame_counter, after.meta.dropped_frames, after.meta.trigger_index) == (
        1, 1, 2)
    # The frame after the failed one is the third acquisition's picture, not the second's.
    np.testing.assert_array_equal(after.image, emulated_image(2, 3))


@needs_pylon
def test_full_queue_drops_and_counts(make_camera: Callable[..., BaslerCamera]) -> None:
    camera = make_camera(queue_size=1)
    camera.open()
    for _ in range(2):
        camera.software_trigger()
    deadline = time.monotonic() + READ_TIMEOUT_S
    while camera.dropped_frames == 0 and time.monotonic() < deadline:
        time.sleep(0.01)
    first = camera.read_frame(READ_TIMEOUT_S)
    assert (first.meta.frame_counter, first.meta.dropped_frames) == (0, 0)
    with pytest.raises(DeviceTimeoutError):
        camera.read_frame(MISSING_TIMEOUT_S)
    assert camera.dropped_frames == 1
    after = read_next(camera).meta
    assert (after.frame_counter, after.dropped_frames, after.trigger_index) == (1, 1, 2)


# --- time -----------------------------------------------------------------------------------


@needs_pylon
def test_frames_without_device_timestamps_get_their_arrival_time(
        make_camera: Callable[..., BaslerCamera], context: DriverContext) -> None:
    camera = make_camera()
    camera.open()
    camera.set_exposure_us(10_000.0)
    for _ in range(2):
        before = context.clock.now_ns()
        frame = read_next(camera)
        after = context.clock.now_ns()
        # The emulator stamps 0: mid-exposure is the arrival time less half the exposure.
        assert frame.extra["device_timestamp_ns"] == 0
        assert before - 5_000_000 <= frame.meta.t_ns <= after - 5_000_000
    assert camera.clock_offset_ns is None


def test_ticks_to_ns() -> None:
    assert ticks_to_ns(2**62 + 1, 1_000_000_000) == 2**62 + 1  # USB3 Vision: nanoseconds
    assert ticks_to_ns(125_000_000, 125_000_000) == 1_000_000_000  # ace GigE: 8 ns ticks
    assert ticks_to_ns(2**60 + 3, 125_000_000) == (2**60 + 3) * 8  # exact, not via a float
    with pytest.raises(ValueError):
        ticks_to_ns(1, 0)


# --- which camera ---------------------------------------------------------------------------


@needs_pylon
def test_cameras_are_found_by_serial_number(make_camera: Callable[..., BaslerCamera]) -> None:
    left = make_camera(device_id="left", serial=FIRST, test_image="Testimage1")
    right = make_camera(device_id="right", serial=SECOND, test_image="Testimage2")
    left.open()
    right.open()
    assert (left.describe()["serial_number"], right.describe()["serial_number"]) == (FIRST,
                                                                                      SECOND)
    np.testing.assert_array_equal(read_next(right).image, emulated_image(2, 1))
    np.testing.assert_array_equal(read_next(left).image, emulated_image(1, 0))
    assert left.dropped_frames == right.dropped_frames == 0


@needs_pylon
def test_missing_camera_is_disconnected_and_names_what_pylon_finds(
        make_camera: Callable[..., BaslerCamera]) -> None:
    camera = make_camera(serial="21234567")
    with pytest.raises(DeviceDisconnectedError, match=r"'21234567'.*Emulation 0815-0000") as info:
        camera.open()
    assert info.value.device_id == "C1"
    assert not camera.is_open


# --- a camera that goes away ----------------------------------------------------------------


class RemovedCamera:
    """A pylon InstantCamera as pylon leaves it once the camera is unplugged: it reports itself
    removed, and retrieving either times out (``raises=False``) or raises pylon's
    RuntimeException; everything else (closing it) goes to the real one."""

    def __init__(self, camera: Any, *, raises: bool) -> None:
        self._camera = camera
        self._raises = raises

    def IsCameraDeviceRemoved(self) -> bool:
        return True

    def RetrieveResult(self, timeout_ms: int, handling: Any) -> Any:
        if self._raises:
            from pypylon import genicam

            raise genicam.RuntimeException("The device has been removed from the PC.")
        return self._camera.RetrieveResult(timeout_ms, handling)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._camera, name)


@needs_pylon
@pytest.mark.parametrize("raises", [False, True], ids=["times-out", "raises"])
def test_removed_camera_disconnects_then_recovers_on_reopen(
        make_camera: Callable[..., BaslerCamera], raises: bool) -> None:
    camera = make_camera()
    camera.open()
    camera.set_exposure_us(5_000.0)
    read_next(camera)
    link = camera._link
    assert link is not None
    link._camera = RemovedCamera(link._camera, raises=raises)
    started = time.monotonic()
    with pytest.raises(DeviceDisconnectedError, match="removed") as info:
        camera.read_frame(5.0)  # a waiting read wakes when the camera is found gone
    assert info.value.device_id == "C1"
    assert time.monotonic() - started < 1.0
    assert camera.describe()["connected"] is False
    with pytest.raises(DeviceDisconnectedError):
        camera.read_frame(0.1)
    with pytest.raises(DeviceDisconnectedError, match="close"):
        camera.software_trigger()
    with pytest.raises(DeviceDisconnectedError):
        camera.set_gain_db(1.0)
    camera.close()
    camera.open()  # the camera is back (it never left the emulator)
    assert camera.exposure_us == 5_000.0
    frame = read_next(camera)
    assert (frame.meta.frame_counter, frame.meta.dropped_frames) == (0, 0)
    assert camera.describe()["connected"] is True


# --- without pylon --------------------------------------------------------------------------


def test_registered_and_options_checked(context: DriverContext) -> None:
    assert driver_class("camera", "BaslerCamera") is BaslerCamera
    camera = create_device("camera", "BaslerCamera", "C1",
                           {"serial": "21234567", "width": 320, "height": 240}, context)
    assert isinstance(camera, BaslerCamera)
    assert (camera.width, camera.height, camera.describe()["open"]) == (320, 240, False)
    with pytest.raises(ConfigError, match="pixel_format"):
        create_device("camera", "BaslerCamera", "C1",
                      {"serial": "21234567", "pixel_format": "Mono16"}, context)
    with pytest.raises(ConfigError, match="test_image"):
        create_device("camera", "BaslerCamera", "C1",
                      {"serial": "21234567", "test_image": "Off"}, context)
    with pytest.raises(ConfigError, match=r"missing option.*serial"):
        create_device("camera", "BaslerCamera", "C1", {}, context)


def test_open_without_pypylon_says_what_to_install(monkeypatch: pytest.MonkeyPatch,
                                                   context: DriverContext) -> None:
    monkeypatch.setitem(sys.modules, "pypylon", None)  # import pypylon now raises ImportError
    monkeypatch.delitem(sys.modules, "pypylon.pylon", raising=False)
    camera = BaslerCamera("C1", context=context, serial="21234567")
    with pytest.raises(DeviceError, match=r"pypylon.*pip install") as info:
        camera.open()
    assert info.value.device_id == "C1"
    assert not camera.is_open
