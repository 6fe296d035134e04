"""The IDS peak driver against a fake of exactly the IDS peak calls it makes.

IDS peak is not on PyPI for this platform (IDS ships it from its website under its own licence),
so it cannot be installed here, and the driver is untested on real hardware. What is tested is
that the driver drives IDS peak's documented Python API as IDS's samples do, against
:class:`~tests.hardware.fakepeak.FakePeak`: the modules ``ids_peak``, ``ids_peak.ids_peak`` and
``ids_peak.ids_peak_ipl_extension``, put into ``sys.modules`` per test, implementing the calls the
driver's docstring lists and nothing else (a call outside them fails with AttributeError).

The fake is strict where IDS peak is: nodes refuse values out of range and entries that are not
available; ``TLParamsLocked`` locks the image format while acquiring; ``DeviceManager.Instance``
needs ``Library.Initialize()``; a device is closed when its last Python reference goes (so a
driver that keeps one cannot open the camera again); buffers must be announced and queued before
the stream starts, are filled in the order queued, and are readable only between
``WaitForFinishedBuffer`` and ``QueueBuffer``; an image from ``BufferToImage`` is a view of the
buffer's memory, which the next frame into that buffer overwrites. Its camera is a UI-5240 (1280
× 1024, Mono8 and Mono10, gain a factor of 1 to 4): a software or line trigger exposes one frame,
``(column + row + frame id) mod 256`` in sensor coordinates (10 bits: that times 4), stamped with
the camera's own clock, far from the host's. It can also lose a frame whole, deliver one
incomplete, and be unplugged: IDS peak then calls the device-lost callback, or
``WaitForFinishedBuffer`` raises ``IOException``, or both.
"""

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
from eyeserver.hardware.drivers import ids
from eyeserver.hardware.drivers.ids import IdsCamera, db_to_factor, factor_to_db
from eyeserver.hardware.registry import DriverContext, create_device, driver_class
from tests.hardware.fakepeak import DEVICE_EPOCH_NS, SENSOR, FakeCamera, FakePeak
from tests.hardware.timeouts import MISSING_TIMEOUT_S, READ_TIMEOUT_S

# --- fixtures -------------------------------------------------------------------------------

LEFT, RIGHT = "4103012345", "4103012346"
ROI = {"offset_x": 16, "offset_y": 8, "width": 256, "height": 128}


@pytest.fixture
def peak(monkeypatch: pytest.MonkeyPatch) -> Iterator[FakePeak]:
    """The fake IDS peak with two cameras (the second named "right"); after the test, every
    camera closed and the library closed."""
    fake = FakePeak([FakeCamera(LEFT), FakeCamera(RIGHT, user_name="right")])
    for name, module in fake.modules.items():
        monkeypatch.setitem(sys.modules, name, module)
    yield fake
    assert not any(camera.is_open for camera in fake.cameras), "a device was kept open"
    assert not fake.initialized, "Library.Close() was not called"
    assert not fake.lost_callbacks, "a device-lost callback was left registered"


@pytest.fixture
def context() -> DriverContext:
    return DriverContext()


@pytest.fixture
def make_camera(peak: FakePeak,
                context: DriverContext) -> Iterator[Callable[..., IdsCamera]]:
    """Build cameras on the fake (software-triggered, the small region); all closed after."""
    made: list[IdsCamera] = []

    def make(**options: Any) -> IdsCamera:
        settings: dict[str, Any] = {"serial": LEFT, "trigger_source": "Software", **ROI}
        settings.update(options)
        camera = IdsCamera(settings.pop("device_id", "C1"), context=context, **settings)
        made.append(camera)
        return camera

    try:
        yield make
    finally:
        for camera in made:
            camera.close()


def fake_of(peak: FakePeak, serial: str = LEFT) -> FakeCamera:
    return next(camera for camera in peak.cameras if camera.serial == serial)


def read_next(camera: IdsCamera) -> Frame:
    camera.software_trigger()
    return camera.read_frame(READ_TIMEOUT_S)


def gradient(frame_id: int, bit_depth: int = 8) -> np.ndarray:
    """The fake's picture of the ROI for ``frame_id``."""
    y, x = np.mgrid[0:ROI["height"], 0:ROI["width"]]
    values = (x + ROI["offset_x"] + y + ROI["offset_y"] + frame_id) % 256
    return values.astype(np.uint8) if bit_depth == 8 else (values * 4).astype(np.uint16)


# --- settings reach the camera's nodes ------------------------------------------------------


def test_settings_reach_the_cameras_nodes(peak: FakePeak,
                                          make_camera: Callable[..., IdsCamera]) -> None:
    fake = fake_of(peak)
    fake.tl_locked = True  # a crashed controller left the parameters locked
    camera = make_camera(pixel_format="Mono10")
    camera.open()
    assert (fake.pixel_format, fake.offset_x, fake.offset_y, fake.width, fake.height) == (
        "Mono10", 16, 8, 256, 128)
    assert fake.triggers == {"ExposureStart": {"mode": "On", "source": "Software"},
                             "ExposureEnd": {"mode": "Off", "source": "Line0"}}
    assert (fake.trigger_activation, fake.acquisition_mode) == ("RisingEdge", "Continuous")
    assert fake.tl_locked and fake.acquiring and fake.gain_selector == "AnalogAll"
    assert (camera.width, camera.height, camera.bit_depth) == (256, 128, 10)
    info = camera.describe()
    assert (info["model"], info["serial_number"], info["trigger_selector"]) == (
        "UI-5240CP-M-GL", LEFT, "ExposureStart")
    assert (info["offset_x"], info["offset_y"], info["acquisition_frame_rate_hz"]) == (16, 8,
                                                                                      25.0)
    # The rig's ranges narrowed to the camera's: 28 µs up, and a gain factor of 1..4.
    assert camera.exposure_range_us == (28.0, 40_000.0)
    assert camera.gain_range_db == (0.0, 12.041)
    camera.set_exposure_us(1234.4)  # the fake takes whole microseconds
    camera.set_gain_db(6.0)
    assert fake.exposure_us == 1234.0 and camera.exposure_us == 1234.0
    assert fake.gains["AnalogAll"] == pytest.approx(10 ** (6 / 20))  # a factor, not dB
    assert camera.gain_db == 6.0
    meta = read_next(camera).meta
    assert (meta.exposure_us, meta.gain_db, meta.bit_depth) == (1234.0, 6.0, 10)


def test_settings_survive_a_reopen(peak: FakePeak,
                                   make_camera: Callable[..., IdsCamera]) -> None:
    camera = make_camera()
    camera.open()
    camera.set_exposure_us(2_500.0)
    camera.set_gain_db(4.0)
    camera.close()
    fake = fake_of(peak)
    assert not fake.is_open and not fake.tl_locked and not fake.acquiring
    camera.open()
    assert fake.exposure_us == 2_500.0 and fake.gains["AnalogAll"] == pytest.approx(
        db_to_factor(4.0))
    assert (camera.exposure_us, camera.gain_db) == (2_500.0, 4.0)


def test_what_the_camera_lacks_is_refused(peak: FakePeak,
                                          make_camera: Callable[..., IdsCamera]) -> None:
    with pytest.raises(DeviceValueError, match=r"PixelFormat has no 'Mono12' \(it has Mono8, "
                                               r"Mono10\)"):
        make_camera(pixel_format="Mono12").open()
    with pytest.raises(DeviceValueError, match=r"TriggerSource has no 'Line3'"):
        make_camera(trigger_source="Line3").open()
    with pytest.raises(DeviceValueError, match="OffsetX"):
        make_camera(width=SENSOR[0]).open()  # the sensor has no room for the offset
    # Each failed open let the camera go: another opens it.
    camera = make_camera()
    camera.open()
    assert read_next(camera).meta.frame_counter == 0


def test_region_the_camera_rounds_is_refused(peak: FakePeak,
                                             make_camera: Callable[..., IdsCamera]) -> None:
    fake_of(peak).width_step = 8  # a camera that rounds to its increment instead of refusing
    with pytest.raises(DeviceValueError, match=r"250x130\+16\+8 reads back as 248x130\+16\+8"):
        make_camera(width=250, height=130).open()
    camera = make_camera(width=248, height=130)
    camera.open()
    assert (camera.width, camera.height) == (248, 130)


def test_cameras_are_found_by_serial_number_or_user_name(
        peak: FakePeak, make_camera: Callable[..., IdsCamera]) -> None:
    left = make_camera(device_id="left")
    right = make_camera(device_id="right", serial="right")
    left.open()
    right.open()
    assert right.describe()["serial_number"] == RIGHT
    assert fake_of(peak, RIGHT).is_open
    with pytest.raises(DeviceDisconnectedError, match=r"'4103099999'.*UI-5240CP-M-GL "
                                                      r"4103012345") as info:
        make_camera(device_id="other", serial="4103099999").open()
    assert info.value.device_id == "other"
    assert read_next(right).meta.frame_counter == 0


# --- frames ---------------------------------------------------------------------------------


def test_frames_are_the_cameras_images(make_camera: Callable[..., IdsCamera]) -> None:
    camera = make_camera()
    camera.open()
    # More frames than buffers: each image must be a copy, not a view of a reused buffer.
    frames = [read_next(camera) for _ in range(12)]
    for n, frame in enumerate(frames):
        assert frame.extra["frame_id"] == n
        assert frame.image.dtype == np.uint8 and frame.image.flags.writeable
        np.testing.assert_array_equal(frame.image, gradient(n))


def test_ten_bit_frames(make_camera: Callable[..., IdsCamera]) -> None:
    camera = make_camera(pixel_format="Mono10")
    camera.open()
    frame = read_next(camera)
    assert frame.image.dtype == np.uint16 and int(frame.image.max()) < 1024
    np.testing.assert_array_equal(frame.image, gradient(0, bit_depth=10))


def test_hardware_trigger_line(peak: FakePeak, make_camera: Callable[..., IdsCamera]) -> None:
    camera = make_camera(trigger_source="Line0")
    camera.open()
    with pytest.raises(DeviceValueError, match="needs trigger_source 'Software'"):
        camera.software_trigger()
    with pytest.raises(DeviceTimeoutError):
        camera.read_frame(MISSING_TIMEOUT_S)
    fake_of(peak).fire("Line0")
    np.testing.assert_array_equal(camera.read_frame(READ_TIMEOUT_S).image, gradient(0))


# --- lost frames ----------------------------------------------------------------------------


def test_incomplete_buffer_is_dropped_and_counted(
        peak: FakePeak, make_camera: Callable[..., IdsCamera]) -> None:
    camera = make_camera()
    camera.open()
    first = read_next(camera)
    fake_of(peak).next_incomplete = True
    camera.software_trigger()
    with pytest.raises(DeviceTimeoutError):
        camera.read_frame(0.2)
    assert camera.dropped_frames == 1 and camera.describe()["dropped_frames"] == 1
    after = read_next(camera)
    assert (first.meta.dropped_frames, first.meta.trigger_index) == (0, 0)
    assert (after.meta.frame_counter, after.meta.dropped_frames, after.meta.trigger_index) == (
        1, 1, 2)
    np.testing.assert_array_equal(after.image, gradient(2))


def test_frames_lost_whole_are_counted_once(peak: FakePeak,
                                            make_camera: Callable[..., IdsCamera]) -> None:
    camera = make_camera()
    camera.open()
    fake = fake_of(peak)
    read_next(camera)
    fake.lose_next_whole = True  # frame id 1 never arrives
    camera.software_trigger()
    fake.next_incomplete = True  # frame id 2 arrives incomplete
    camera.software_trigger()
    after = read_next(camera)  # frame id 3: two ids skipped, one of them already counted
    assert after.extra["frame_id"] == 3
    assert (after.meta.frame_counter, after.meta.dropped_frames, after.meta.trigger_index) == (
        1, 2, 3)
    assert camera.dropped_frames == 2


def test_full_queue_drops_and_counts(make_camera: Callable[..., IdsCamera]) -> None:
    camera = make_camera(queue_size=1)
    camera.open()
    camera.software_trigger()
    camera.software_trigger()
    deadline = time.monotonic() + READ_TIMEOUT_S
    while camera.dropped_frames == 0 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert camera.read_frame(READ_TIMEOUT_S).meta.frame_counter == 0
    with pytest.raises(DeviceTimeoutError):
        camera.read_frame(MISSING_TIMEOUT_S)
    after = read_next(camera).meta
    assert (after.frame_counter, after.dropped_frames, after.trigger_index) == (1, 1, 2)


# --- time -----------------------------------------------------------------------------------


def test_device_timestamps_map_onto_the_rig_clock(make_camera: Callable[..., IdsCamera],
                                                  context: DriverContext) -> None:
    camera = make_camera()
    camera.open()
    camera.set_exposure_us(10_000.0)
    assert camera.clock_offset_ns is None
    frames = []
    for _ in range(3):
        frames.append(read_next(camera))
        time.sleep(0.01)
    stamps = [f.extra["device_timestamp_ns"] for f in frames]
    assert all(isinstance(s, int) for s in stamps)
    offset = camera.clock_offset_ns
    assert offset is not None
    # One offset for the session: intervals are the camera's own, to the nanosecond.
    for frame, stamp in zip(frames, stamps, strict=True):
        assert isinstance(stamp, int)
        assert frame.meta.t_ns == stamp + offset + 5_000_000
    # The camera's clock is DEVICE_EPOCH_NS ahead; the first frame is taken to have ended its
    # exposure when it arrived, a little after the trigger.
    assert -DEVICE_EPOCH_NS - 10_000_000 <= offset < -DEVICE_EPOCH_NS - 10_000_000 + 500_000_000
    camera.close()
    camera.open()
    assert camera.clock_offset_ns is None


def test_unexpected_sdk_error_in_the_acquisition_thread_reaches_the_reader(
        peak: FakePeak, make_camera: Callable[..., IdsCamera]) -> None:
    camera = make_camera()
    camera.open()
    stream = fake_of(peak).stream
    assert stream is not None
    stream.refuse_buffers = True  # the next buffer cannot be queued again
    camera.software_trigger()
    # The thread is gone with that frame, and the waiting reader hears why.
    with pytest.raises(DeviceDisconnectedError, match=r"acquisition failed.*cannot be queued"):
        camera.read_frame(READ_TIMEOUT_S)
    assert camera.describe()["connected"] is False
    stream.refuse_buffers = False


# --- a camera that goes away ----------------------------------------------------------------


def test_lost_device_exception_disconnects_then_recovers_on_reopen(
        peak: FakePeak, make_camera: Callable[..., IdsCamera]) -> None:
    camera = make_camera()
    camera.open()
    camera.set_exposure_us(5_000.0)
    read_next(camera)
    fake = fake_of(peak)
    peak.unplug(fake, notify=False)  # only WaitForFinishedBuffer tells
    started = time.monotonic()
    with pytest.raises(DeviceDisconnectedError, match="lost") as info:
        camera.read_frame(5.0)
    assert info.value.device_id == "C1"
    assert time.monotonic() - started < 1.0
    assert camera.describe()["connected"] is False
    with pytest.raises(DeviceDisconnectedError, match="close"):
        camera.software_trigger()
    with pytest.raises(DeviceDisconnectedError):
        camera.set_gain_db(1.0)
    camera.close()
    assert not fake.is_open  # the driver let go of the device
    with pytest.raises(DeviceDisconnectedError, match="no camera"):
        camera.open()
    assert not camera.is_open

    peak.replug(fake)  # back, power-cycled: its settings at their defaults
    camera.open()
    assert fake_of(peak).exposure_us == 5_000.0
    frame = read_next(camera)
    assert (frame.meta.frame_counter, frame.meta.dropped_frames) == (0, 0)
    assert camera.describe()["connected"] is True


def test_lost_device_callback_disconnects_only_that_camera(
        peak: FakePeak, make_camera: Callable[..., IdsCamera]) -> None:
    left = make_camera(device_id="left")
    right = make_camera(device_id="right", serial=RIGHT)
    left.open()
    right.open()
    # Only the callback tells: the stream just goes quiet, as a GigE stream would.
    peak.unplug(fake_of(peak, LEFT), raise_in_wait=False)
    with pytest.raises(DeviceDisconnectedError, match="IDS peak reports the device lost"):
        left.read_frame(READ_TIMEOUT_S)
    assert right.describe()["connected"] is True
    assert read_next(right).meta.frame_counter == 0


def test_control_call_to_a_lost_camera_marks_it_lost(
        peak: FakePeak, make_camera: Callable[..., IdsCamera]) -> None:
    camera = make_camera()
    camera.open()
    peak.unplug(fake_of(peak), notify=False, raise_in_wait=False)
    with pytest.raises(DeviceDisconnectedError, match="has been lost"):
        camera.set_exposure_us(2_000.0)
    # The reader, waiting on a quiet stream, hears of it from the failed control call.
    with pytest.raises(DeviceDisconnectedError):
        camera.read_frame(READ_TIMEOUT_S)


# --- without IDS peak -----------------------------------------------------------------------


def test_registered_and_options_checked(context: DriverContext) -> None:
    assert driver_class("camera", "IdsCamera") is IdsCamera
    camera = create_device("camera", "IdsCamera", "C1",
                           {"serial": LEFT, "width": 320, "height": 240}, context)
    assert isinstance(camera, IdsCamera)
    assert (camera.width, camera.height, camera.describe()["open"]) == (320, 240, False)
    assert camera.describe()["trigger_source"] == "Line0"
    with pytest.raises(ConfigError, match="pixel_format"):
        create_device("camera", "IdsCamera", "C1", {"serial": LEFT, "pixel_format": "Mono16"},
                      context)
    with pytest.raises(ConfigError, match=r"missing option.*serial"):
        create_device("camera", "IdsCamera", "C1", {}, context)


def test_open_without_ids_peak_says_what_to_install(monkeypatch: pytest.MonkeyPatch,
                                                    context: DriverContext) -> None:
    monkeypatch.setitem(sys.modules, "ids_peak", None)  # import ids_peak now raises ImportError
    camera = IdsCamera("C1", context=context, serial=LEFT)
    with pytest.raises(DeviceError, match=r"ids_peak.*IDS peak from IDS's website") as info:
        camera.open()
    assert info.value.device_id == "C1"
    assert not camera.is_open


def test_gain_conversion() -> None:
    assert db_to_factor(0.0) == 1.0
    assert db_to_factor(20.0) == pytest.approx(10.0)
    assert factor_to_db(2.0) == pytest.approx(6.0206, abs=1e-4)
    assert factor_to_db(db_to_factor(7.5)) == pytest.approx(7.5)
    with pytest.raises(ValueError):
        factor_to_db(0.0)


def test_library_is_initialised_once_for_all_cameras(
        peak: FakePeak, make_camera: Callable[..., IdsCamera]) -> None:
    left = make_camera(device_id="left")
    right = make_camera(device_id="right", serial=RIGHT)
    left.open()
    right.open()
    left.close()
    assert peak.initialized  # the right camera still needs it
    right.close()
    assert not peak.initialized and peak.initializations == 1
    assert ids._library_users == 0
