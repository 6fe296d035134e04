"""The GenICam driver through Aravis, against Aravis's own fake GigE Vision camera on loopback.

The fake (``arv-fake-gv-camera-0.8``, :mod:`eyeserver.hardware.emulators.fakegv`) is a real
GigE Vision device on the wire, so these tests go through Aravis's whole control and stream
path. Tests that need it are skipped, with the reason, only where Aravis or PyGObject is not
installed (scripts/system-packages.sh and the ``genicam`` extra install them, and CI runs
them). Each test starts its own fake and stops it, whatever happens.

What the fake cannot show, so what stays untested on a device: Mono10/Mono12 images (it has
neither; their decoding is tested on bytes), a hardware trigger line firing (its Line0 never
does; Software stands in), a camera's own exposure-start timestamp latch and clock drift (its
timestamps are the host's real-time clock at send), packet resends (it ignores requests), and
opening by device id with frames (discovery finds it, but loopback drops its stream sent to
another interface's address). Only one fake can run, on 127.0.0.1.
"""

from __future__ import annotations

import itertools
import sys
import time
from collections.abc import Callable, Iterator

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
from eyeserver.hardware.drivers import camerathread
from eyeserver.hardware.drivers.genicam import GenicamCamera, image_from_payload
from eyeserver.hardware.emulators.fakegv import FakeGigECamera
from eyeserver.hardware.registry import DriverContext, create_device, driver_class
from tests.hardware.needs import needs_aravis
from tests.hardware.timeouts import READ_TIMEOUT_S

ROI = {"offset_x": 16, "offset_y": 8, "width": 256, "height": 128}
"""A small region: 32 kB frames, 24 GVSP packets of 1400 bytes each."""


def ramp(block_id: int, width: int, height: int) -> np.ndarray:
    """The fake's image at unity scale (gain 0, 10 ms): ``(x + y + frame id) % 255``."""
    y, x = np.mgrid[0:height, 0:width]
    return ((x + y + block_id) % 255).astype(np.uint8)


@pytest.fixture
def fake() -> Iterator[FakeGigECamera]:
    camera = FakeGigECamera()
    camera.start()
    try:
        yield camera
    finally:
        camera.stop()


@pytest.fixture
def context() -> DriverContext:
    return DriverContext()


@pytest.fixture
def make_camera(fake: FakeGigECamera,
                context: DriverContext) -> Iterator[Callable[..., GenicamCamera]]:
    """Build cameras on the fake (software-triggered, the small region); all closed after."""
    made: list[GenicamCamera] = []

    def make(**options: object) -> GenicamCamera:
        settings: dict[str, object] = {"address": fake.address, "trigger_source": "Software",
                                       "packet_size": 1400, "liveness_s": 0.3, **ROI}
        settings.update(options)
        camera = GenicamCamera("C1", context=context, **settings)
        made.append(camera)
        return camera

    try:
        yield make
    finally:
        for camera in made:
            camera.close()
        for camera in made:
            assert camera.wait_released(), "a lost camera's teardown did not end"


def read_next(camera: GenicamCamera) -> Frame:
    camera.software_trigger()
    return camera.read_frame(READ_TIMEOUT_S)


# --- settings as the camera reports them ----------------------------------------------------


@needs_aravis
def test_settings_are_read_back_from_the_camera(
        make_camera: Callable[..., GenicamCamera]) -> None:
    camera = make_camera()
    camera.open()
    info = camera.describe()
    assert (camera.width, camera.height, camera.bit_depth) == (256, 128, 8)
    assert (info["offset_x"], info["offset_y"]) == (16, 8)
    assert (info["vendor"], info["model"], info["pixel_format"]) == ("Aravis", "Fake", "Mono8")
    assert info["trigger_source"] == "Software" and info["packet_size"] == 1400
    # The fake's exposure is whole microseconds and its gain an integer GainRaw of 0..10, so
    # what it took differs from what was asked, and that is what the driver reports.
    assert camera.exposure_range_us == (10.0, 40_000.0)
    assert camera.gain_range_db == (0.0, 10.0) and info["gain_feature"] == "GainRaw"
    camera.set_exposure_us(1234.0)
    camera.set_gain_db(2.7)
    assert (camera.exposure_us, camera.gain_db) == (1234.0, 2.0)
    meta = read_next(camera).meta
    assert (meta.exposure_us, meta.gain_db) == (1234.0, 2.0)


@needs_aravis
def test_one_fake_per_address(fake: FakeGigECamera) -> None:
    with pytest.raises(RuntimeError, match="already answers"):
        FakeGigECamera(fake.address).start()
    assert fake.is_running


@needs_aravis
def test_frames_are_the_fakes_images(make_camera: Callable[..., GenicamCamera]) -> None:
    camera = make_camera()
    camera.open()
    camera.set_exposure_us(10_000.0)
    camera.set_gain_db(0.0)
    for _ in range(2):
        frame = read_next(camera)
        assert isinstance(frame.extra["block_id"], int)
        np.testing.assert_array_equal(frame.image, ramp(frame.extra["block_id"], 256, 128))


@needs_aravis
def test_settings_survive_a_reopen(make_camera: Callable[..., GenicamCamera]) -> None:
    camera = make_camera()
    camera.open()
    camera.set_exposure_us(2_500.0)
    camera.set_gain_db(4.0)
    camera.close()
    camera.open()
    assert (camera.exposure_us, camera.gain_db) == (2_500.0, 4.0)
    assert read_next(camera).meta.exposure_us == 2_500.0


@needs_aravis
def test_pixel_format_the_fake_lacks_is_refused(
        make_camera: Callable[..., GenicamCamera]) -> None:
    # The fake has Mono8 and Mono16 but neither Mono10 nor Mono12.
    camera = make_camera(pixel_format="Mono12")
    with pytest.raises(DeviceValueError, match=r"no Mono12 \(it has .*Mono8.*Mono16"):
        camera.open()
    assert not camera.is_open
    assert camera.bit_depth == 12
    # The failed open gave the camera up: another open takes control of it.
    other = make_camera()
    other.open()
    assert read_next(other).meta.frame_counter == 0


@needs_aravis
def test_hardware_trigger_source(make_camera: Callable[..., GenicamCamera]) -> None:
    with pytest.raises(DeviceValueError, match=r"no trigger source 'Line1' \(it has Line0"):
        make_camera(trigger_source="Line1").open()
    # Line0 exists but nothing drives it: a triggered camera then sends nothing at all.
    camera = make_camera(trigger_source="Line0")
    camera.open()
    assert camera.describe()["trigger_source"] == "Line0"
    with pytest.raises(DeviceValueError, match="needs trigger_source 'Software'"):
        camera.software_trigger()
    with pytest.raises(DeviceTimeoutError):
        camera.read_frame(0.3)
    assert camera.dropped_frames == 0


@needs_aravis
def test_full_queue_drops_and_counts(make_camera: Callable[..., GenicamCamera]) -> None:
    camera = make_camera(queue_size=1)
    camera.open()
    for _ in range(2):  # the fake looks for a software trigger every 40 ms
        camera.software_trigger()
        time.sleep(0.15)
    first = camera.read_frame(READ_TIMEOUT_S)
    assert (first.meta.frame_counter, first.meta.dropped_frames) == (0, 0)
    with pytest.raises(DeviceTimeoutError):
        camera.read_frame(0.1)
    assert camera.dropped_frames == 1 and camera.describe()["dropped_frames"] == 1
    after = read_next(camera).meta
    assert (after.frame_counter, after.dropped_frames, after.trigger_index) == (1, 1, 2)


# --- time -----------------------------------------------------------------------------------


@needs_aravis
def test_device_timestamps_map_onto_the_rig_clock(make_camera: Callable[..., GenicamCamera],
                                                  context: DriverContext) -> None:
    camera = make_camera()
    camera.open()
    camera.set_exposure_us(10_000.0)
    assert camera.describe()["tick_frequency_hz"] == 1_000_000_000
    assert camera.clock_offset_ns is None
    spans, frames = [], []
    for _ in range(4):
        before = context.clock.now_ns()
        frames.append(read_next(camera))
        spans.append((before, context.clock.now_ns()))
    device = [f.extra["device_timestamp_ns"] for f in frames]
    assert all(isinstance(t, int) and t > 0 for t in device)
    assert all(a < b for a, b in itertools.pairwise(device))
    # One offset for the session: intervals are the camera's own, to the nanosecond.
    offset = camera.clock_offset_ns
    assert offset is not None
    for frame, stamp in zip(frames, device, strict=True):
        assert isinstance(stamp, int)
        assert frame.meta.t_ns == stamp + offset + 5_000_000
    # Mid-exposure lands between the trigger and the frame's arrival, give or take what the
    # offset's guess may be off by: the exposure, and the first frame's delivery latency.
    for frame, (before, after) in zip(frames, spans, strict=True):
        assert before - 10_000_000 <= frame.meta.t_ns <= after + 20_000_000
    camera.close()
    camera.open()
    assert camera.clock_offset_ns is None


# --- lost packets ---------------------------------------------------------------------------


@needs_aravis
@pytest.mark.slow
def test_lost_packets_drop_frames_that_are_never_returned(context: DriverContext) -> None:
    # 3 % of packets lost: about half the 26-packet frames lose one; the fake never resends.
    with FakeGigECamera(packet_loss_per_mille=30.0) as lossy:
        camera = GenicamCamera("C1", context=context, address=lossy.address,
                               trigger_source="Software", packet_size=1400, **ROI)
        try:
            camera.open()
            camera.set_exposure_us(10_000.0)
            camera.set_gain_db(0.0)
            frames: list[Frame] = []
            triggers = 0

            def trigger_and_wait() -> bool:
                """One exposure: wait until it comes whole or is counted as dropped."""
                nonlocal triggers
                dropped = camera.dropped_frames
                camera.software_trigger()
                triggers += 1
                deadline = time.monotonic() + 0.4
                while time.monotonic() < deadline:
                    try:
                        frames.append(camera.read_frame(0.02))
                        return True
                    except DeviceTimeoutError:
                        if camera.dropped_frames > dropped:
                            return False
                return False  # lost whole: counted when the next frame's id skips it

            for _ in range(20):
                trigger_and_wait()
            # End on a whole frame, so that every exposure before it has been accounted for.
            for _ in range(30):
                if trigger_and_wait():
                    break
            assert frames, "no frame came whole"
            assert camera.dropped_frames > 0, "no frame was dropped"
            assert len(frames) + camera.dropped_frames == triggers
            assert camera.describe()["dropped_frames"] == camera.dropped_frames
            for n, frame in enumerate(frames):
                assert frame.meta.frame_counter == n
                block_id = frame.extra["block_id"]
                assert isinstance(block_id, int)
                np.testing.assert_array_equal(frame.image, ramp(block_id, 256, 128))
            ids = [f.extra["block_id"] for f in frames]
            assert len(set(ids)) == len(ids)
            assert [f.meta.dropped_frames for f in frames] == sorted(
                f.meta.dropped_frames for f in frames)
        finally:
            camera.close()


# --- a camera that goes away ----------------------------------------------------------------


@needs_aravis
@pytest.mark.slow
def test_killed_camera_disconnects_then_recovers_on_reopen(
        fake: FakeGigECamera, make_camera: Callable[..., GenicamCamera]) -> None:
    camera = make_camera()
    camera.open()
    camera.set_exposure_us(5_000.0)
    read_next(camera)
    fake.kill()
    started = time.monotonic()
    with pytest.raises(DeviceDisconnectedError) as info:
        camera.read_frame(8.0)  # a waiting read wakes when the camera is found gone
    assert info.value.device_id == "C1"
    assert time.monotonic() - started < 5.0
    assert camera.describe()["connected"] is False
    with pytest.raises(DeviceDisconnectedError):
        camera.read_frame(0.1)
    with pytest.raises(DeviceDisconnectedError, match="close"):
        camera.software_trigger()
    with pytest.raises(DeviceDisconnectedError):
        camera.set_gain_db(1.0)
    started = time.monotonic()
    camera.close()  # without waiting out Aravis's goodbyes to a camera that is gone
    assert time.monotonic() - started < 1.0
    with pytest.raises(DeviceDisconnectedError, match=r"127\.0\.0\.1"):
        camera.open()
    assert not camera.is_open

    fake.start()  # the camera comes back with its settings at their defaults
    camera.open()
    assert camera.exposure_us == 5_000.0
    frame = read_next(camera)
    assert (frame.meta.frame_counter, frame.meta.dropped_frames) == (0, 0)
    assert camera.describe()["connected"] is True


@needs_aravis
def test_restarted_camera_is_noticed(fake: FakeGigECamera,
                                     make_camera: Callable[..., GenicamCamera]) -> None:
    camera = make_camera()
    camera.open()
    read_next(camera)
    fake.restart()  # power-cycled between two heartbeats: it answers, but not as ours
    with pytest.raises(DeviceDisconnectedError, match="controller"):
        camera.read_frame(3.0)
    camera.close()
    camera.open()
    assert read_next(camera).meta.frame_counter == 0


# --- without Aravis -------------------------------------------------------------------------


def test_registered_and_options_checked(context: DriverContext) -> None:
    assert driver_class("camera", "GenicamCamera") is GenicamCamera
    camera = create_device("camera", "GenicamCamera", "C1",
                           {"address": "127.0.0.1", "width": 320, "height": 240}, context)
    assert isinstance(camera, GenicamCamera)
    assert (camera.width, camera.height, camera.describe()["open"]) == (320, 240, False)
    with pytest.raises(ConfigError, match="pixel_format"):
        create_device("camera", "GenicamCamera", "C1",
                      {"address": "127.0.0.1", "pixel_format": "Mono16"}, context)
    with pytest.raises(ConfigError, match=r"missing option.*address"):
        create_device("camera", "GenicamCamera", "C1", {}, context)


def test_open_without_pygobject_says_what_to_install(monkeypatch: pytest.MonkeyPatch,
                                                     context: DriverContext) -> None:
    monkeypatch.setitem(sys.modules, "gi", None)  # import gi now raises ImportError
    camera = GenicamCamera("C1", context=context, address="127.0.0.1")
    with pytest.raises(DeviceError, match=r"PyGObject.*gir1\.2-aravis-0\.8") as info:
        camera.open()
    assert info.value.device_id == "C1"
    assert not camera.is_open


def test_image_from_payload() -> None:
    words = np.array([[0, 1, 4095], [256, 2048, 7]], dtype="<u2")
    image = image_from_payload(words.tobytes(), 3, 2, 12)
    assert image.dtype == np.uint16 and image.flags.writeable
    np.testing.assert_array_equal(image, words)
    mono8 = image_from_payload(bytes(range(6)) + b"tail", 3, 2, 8)
    np.testing.assert_array_equal(mono8, [[0, 1, 2], [3, 4, 5]])
    with pytest.raises(ValueError, match="short"):
        image_from_payload(bytes(11), 3, 2, 10)


@pytest.mark.parametrize(("last", "new", "skipped"), [
    (10, 11, 0), (10, 14, 3), (65534, 65535, 0), (65535, 1, 0), (65534, 2, 2),
    (500, 3, 0),  # the camera restarted its count: nothing to tell
])
def test_skipped_block_ids(last: int, new: int, skipped: int) -> None:
    assert camerathread.skipped_frame_ids(last, new) == skipped
