"""The camera contract: what every :class:`~eyeserver.hardware.base.Camera` driver guarantees,
run over the simulated camera and each real driver on its transport-level fake (after
python-microscope's test mixins, as one parametrised suite).

========================  ==========================================================================
``sim-8bit``, ``sim-12bit``  :class:`~eyeserver.hardware.sim.drivers.SimCamera` in a tiny simulated
                          room (tests/hardware/simroom.py), exposed by a ``SimTrigger``
``genicam-fakegv``        :class:`~eyeserver.hardware.drivers.genicam.GenicamCamera` through Aravis
                          on Aravis's fake GigE Vision camera on loopback
``basler-camemu``         :class:`~eyeserver.hardware.drivers.basler.BaslerCamera` through pypylon
                          on pylon's camera emulation (``PYLON_CAMEMU``)
``ids-fakepeak``          :class:`~eyeserver.hardware.drivers.ids.IdsCamera` on the fake of the IDS
                          peak calls it makes (tests/hardware/fakepeak.py)
========================  ==========================================================================

A case is skipped, with the reason printed, only where the machine lacks what its fake needs
(tests/hardware/needs.py). The real drivers are exposed by their software trigger; each driver's
own file tests the rest (its protocol, settings read back, faults and recovery).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass

import numpy as np
import pytest

from eyeserver.core.clock import ManualClock
from eyeserver.errors import DeviceNotOpenError, DeviceTimeoutError, DeviceValueError
from eyeserver.hardware.base import Camera, TriggerStep
from eyeserver.hardware.drivers.basler import BaslerCamera
from eyeserver.hardware.drivers.genicam import GenicamCamera
from eyeserver.hardware.drivers.ids import IdsCamera
from eyeserver.hardware.emulators.fakegv import FakeGigECamera
from eyeserver.hardware.registry import DriverContext
from eyeserver.hardware.sim.drivers import SimCamera, SimTrigger, sim_driver_context
from tests.hardware.fakepeak import FakeCamera, FakePeak
from tests.hardware.lifecycle import check_open_close_idempotent
from tests.hardware.needs import needs_aravis, needs_pylon
from tests.hardware.simroom import FakeRoom
from tests.hardware.timeouts import MISSING_TIMEOUT_S, READ_TIMEOUT_S

ROI = {"offset_x": 16, "offset_y": 8, "width": 256, "height": 128}
"""The real drivers' region: small frames, quick to move."""


@dataclass
class CameraCase:
    """An unopened camera and a callable that fires one pulse exposing it (once it is open)."""

    camera: Camera
    expose: Callable[[], None]


@contextmanager
def _sim(camera_id: str) -> Iterator[CameraCase]:
    room = FakeRoom()  # S1 is 8-bit, S4 12-bit
    context = sim_driver_context(room)
    camera = SimCamera(camera_id, context=context)
    trigger = SimTrigger("T1", context=context)
    clock = room.clock
    assert isinstance(clock, ManualClock)

    def expose() -> None:
        if not trigger.is_open:
            trigger.open()
            trigger.set_sequence([TriggerStep(projectors=("P1",), cameras=(camera_id,))])
        trigger.fire()
        clock.advance(0.04)

    try:
        yield CameraCase(camera, expose)
    finally:
        trigger.close()
        camera.close()


@contextmanager
def _genicam() -> Iterator[CameraCase]:
    with FakeGigECamera() as fake:
        camera = GenicamCamera("C1", context=DriverContext(), address=fake.address,
                               trigger_source="Software", packet_size=1400, liveness_s=0.3,
                               **ROI)
        try:
            yield CameraCase(camera, camera.software_trigger)
        finally:
            camera.close()
            assert camera.wait_released(), "the camera's teardown did not end"


@contextmanager
def _basler(monkeypatch: pytest.MonkeyPatch) -> Iterator[CameraCase]:
    monkeypatch.setenv("PYLON_CAMEMU", "2")
    camera = BaslerCamera("C1", context=DriverContext(), serial="0815-0000",
                          device_class="BaslerCamEmu", trigger_source="Software",
                          test_image="Testimage2", **ROI)
    try:
        yield CameraCase(camera, camera.software_trigger)
    finally:
        camera.close()


@contextmanager
def _ids(monkeypatch: pytest.MonkeyPatch) -> Iterator[CameraCase]:
    peak = FakePeak([FakeCamera("4103012345")])
    for name, module in peak.modules.items():
        monkeypatch.setitem(sys.modules, name, module)
    camera = IdsCamera("C1", context=DriverContext(), serial="4103012345",
                       trigger_source="Software", **ROI)
    try:
        yield CameraCase(camera, camera.software_trigger)
    finally:
        camera.close()
    assert not any(c.is_open for c in peak.cameras), "a device was kept open"
    assert not peak.initialized, "Library.Close() was not called"


@pytest.fixture(params=[
    "sim-8bit", "sim-12bit",
    pytest.param("genicam-fakegv", marks=needs_aravis),
    pytest.param("basler-camemu", marks=needs_pylon),
    "ids-fakepeak",
])
def case(request: pytest.FixtureRequest,
         monkeypatch: pytest.MonkeyPatch) -> Iterator[CameraCase]:
    makers: dict[str, Callable[[], AbstractContextManager[CameraCase]]] = {
        "sim-8bit": lambda: _sim("S1"),
        "sim-12bit": lambda: _sim("S4"),
        "genicam-fakegv": _genicam,
        "basler-camemu": lambda: _basler(monkeypatch),
        "ids-fakepeak": lambda: _ids(monkeypatch),
    }
    with makers[request.param]() as built:
        yield built


@pytest.fixture
def camera(case: CameraCase) -> Camera:
    return case.camera


@pytest.fixture
def expose(case: CameraCase) -> Callable[[], None]:
    return case.expose


def test_open_close_idempotent(camera: Camera) -> None:
    check_open_close_idempotent(camera)


def test_reopens_after_close(camera: Camera, expose: Callable[[], None]) -> None:
    camera.open()
    camera.close()
    camera.open()
    expose()
    assert camera.read_frame(READ_TIMEOUT_S).meta.camera_id == camera.id


def _call(camera: Camera, call: str) -> None:
    if call == "set_exposure_us":
        camera.set_exposure_us(camera.exposure_range_us[0])
    elif call == "set_gain_db":
        camera.set_gain_db(camera.gain_range_db[0])
    else:
        camera.read_frame(MISSING_TIMEOUT_S)


@pytest.mark.parametrize("call", ["set_exposure_us", "set_gain_db", "read_frame"])
def test_use_before_open_raises(camera: Camera, call: str) -> None:
    with pytest.raises(DeviceNotOpenError) as info:
        _call(camera, call)
    assert info.value.device_id == camera.id


@pytest.mark.parametrize("call", ["set_exposure_us", "set_gain_db", "read_frame"])
def test_use_after_close_raises(camera: Camera, call: str) -> None:
    camera.open()
    camera.close()
    with pytest.raises(DeviceNotOpenError):
        _call(camera, call)


def test_format(camera: Camera) -> None:
    assert camera.width > 0 and camera.height > 0
    assert camera.bit_depth in (8, 10, 12)


def test_exposure_range(camera: Camera) -> None:
    camera.open()
    low, high = camera.exposure_range_us
    for value in (low, high, (low + high) / 2):
        camera.set_exposure_us(value)
        assert camera.exposure_us == value
    for value in (low - 1.0, high + 1.0, -1.0):
        with pytest.raises(DeviceValueError) as info:
            camera.set_exposure_us(value)
        assert info.value.device_id == camera.id
    assert camera.exposure_us == (low + high) / 2


def test_gain_range(camera: Camera) -> None:
    camera.open()
    low, high = camera.gain_range_db
    camera.set_gain_db(high)
    assert camera.gain_db == high
    for value in (low - 0.5, high + 0.5):
        with pytest.raises(DeviceValueError):
            camera.set_gain_db(value)
    assert camera.gain_db == high


def test_nonpositive_timeout_rejected(camera: Camera) -> None:
    camera.open()
    with pytest.raises(ValueError):
        camera.read_frame(0.0)


def test_read_frame_shape_dtype_meta(camera: Camera, expose: Callable[[], None]) -> None:
    camera.open()
    camera.set_exposure_us(5_000.0)
    camera.set_gain_db(3.0)
    expose()
    frame = camera.read_frame(READ_TIMEOUT_S)
    assert frame.image.shape == (camera.height, camera.width)
    assert frame.image.dtype == (np.uint8 if camera.bit_depth == 8 else np.uint16)
    assert int(frame.image.max()) < 2**camera.bit_depth
    meta = frame.meta
    assert meta.camera_id == camera.id
    assert meta.frame_counter == 0
    assert meta.bit_depth == camera.bit_depth
    assert meta.exposure_us == 5_000.0
    assert meta.gain_db == 3.0
    assert meta.dropped_frames == 0
    assert all(isinstance(p, str) for p in meta.projectors_on)


def test_frame_counter_and_time_increase(camera: Camera, expose: Callable[[], None]) -> None:
    camera.open()
    metas = []
    for _ in range(3):
        expose()
        metas.append(camera.read_frame(READ_TIMEOUT_S).meta)
    assert [m.frame_counter for m in metas] == [0, 1, 2]
    assert metas[0].t_ns <= metas[1].t_ns <= metas[2].t_ns
    assert metas[0].trigger_index < metas[1].trigger_index < metas[2].trigger_index


def test_frame_counter_restarts_on_open(camera: Camera, expose: Callable[[], None]) -> None:
    camera.open()
    expose()
    camera.read_frame(READ_TIMEOUT_S)
    camera.close()
    camera.open()
    expose()
    assert camera.read_frame(READ_TIMEOUT_S).meta.frame_counter == 0


def test_timeout_without_pulse(camera: Camera) -> None:
    camera.open()
    started = time.monotonic()
    with pytest.raises(DeviceTimeoutError) as info:
        camera.read_frame(MISSING_TIMEOUT_S)
    assert info.value.device_id == camera.id
    assert MISSING_TIMEOUT_S * 0.9 <= time.monotonic() - started < 1.0


def test_one_frame_per_pulse(camera: Camera, expose: Callable[[], None]) -> None:
    camera.open()
    expose()
    camera.read_frame(READ_TIMEOUT_S)
    with pytest.raises(DeviceTimeoutError):
        camera.read_frame(MISSING_TIMEOUT_S)


def test_describe(camera: Camera) -> None:
    info = camera.describe()
    assert info["id"] == camera.id
    assert info["kind"] == "camera"
    assert info["open"] is False
    assert {"width", "height", "bit_depth", "exposure_us", "gain_db"} <= info.keys()
