"""Contract tests every driver must pass, as mixins (after python-microscope's test mixins).

A driver's test module subclasses a mixin and provides its fixtures:

``CameraContract``
    ``camera``: an unopened camera (the fixture closes it afterwards); ``expose``: a callable that
    fires one trigger pulse exposing that camera (it may assume the camera is open).
``ProjectorContract``
    ``projector``: an unopened projector.
``TriggerContract``
    ``trigger``: an unopened trigger; ``steps``: a valid sequence of at least two steps whose
    devices the trigger is wired to.

Run them against the simulated drivers and against each real driver over a transport-level fake.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable, Sequence

import numpy as np
import pytest

from eyeserver.errors import DeviceNotOpenError, DeviceTimeoutError, DeviceValueError
from eyeserver.hardware.base import Camera, Projector, Trigger, TriggerStep

READ_TIMEOUT_S = 1.0
"""Generous wait for a frame that is expected to arrive."""

MISSING_TIMEOUT_S = 0.05
"""Short wait for a frame that is expected not to arrive."""


class CameraContract:
    """What every :class:`~eyeserver.hardware.base.Camera` driver guarantees."""

    def test_open_close_idempotent(self, camera: Camera) -> None:
        assert not camera.is_open
        camera.open()
        camera.open()
        assert camera.is_open
        camera.close()
        camera.close()
        assert not camera.is_open

    def test_reopens_after_close(self, camera: Camera, expose: Callable[[], None]) -> None:
        camera.open()
        camera.close()
        camera.open()
        expose()
        assert camera.read_frame(READ_TIMEOUT_S).meta.camera_id == camera.id

    @pytest.mark.parametrize("call", ["set_exposure_us", "set_gain_db", "read_frame"])
    def test_use_before_open_raises(self, camera: Camera, call: str) -> None:
        with pytest.raises(DeviceNotOpenError) as info:
            self._call(camera, call)
        assert info.value.device_id == camera.id

    @pytest.mark.parametrize("call", ["set_exposure_us", "set_gain_db", "read_frame"])
    def test_use_after_close_raises(self, camera: Camera, call: str) -> None:
        camera.open()
        camera.close()
        with pytest.raises(DeviceNotOpenError):
            self._call(camera, call)

    @staticmethod
    def _call(camera: Camera, call: str) -> None:
        if call == "set_exposure_us":
            camera.set_exposure_us(camera.exposure_range_us[0])
        elif call == "set_gain_db":
            camera.set_gain_db(camera.gain_range_db[0])
        else:
            camera.read_frame(MISSING_TIMEOUT_S)

    def test_format(self, camera: Camera) -> None:
        assert camera.width > 0 and camera.height > 0
        assert camera.bit_depth in (8, 10, 12)

    def test_exposure_range(self, camera: Camera) -> None:
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

    def test_gain_range(self, camera: Camera) -> None:
        camera.open()
        low, high = camera.gain_range_db
        camera.set_gain_db(high)
        assert camera.gain_db == high
        for value in (low - 0.5, high + 0.5):
            with pytest.raises(DeviceValueError):
                camera.set_gain_db(value)
        assert camera.gain_db == high

    def test_nonpositive_timeout_rejected(self, camera: Camera) -> None:
        camera.open()
        with pytest.raises(ValueError):
            camera.read_frame(0.0)

    def test_read_frame_shape_dtype_meta(self, camera: Camera,
                                         expose: Callable[[], None]) -> None:
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

    def test_frame_counter_and_time_increase(self, camera: Camera,
                                             expose: Callable[[], None]) -> None:
        camera.open()
        metas = []
        for _ in range(3):
            expose()
            metas.append(camera.read_frame(READ_TIMEOUT_S).meta)
        assert [m.frame_counter for m in metas] == [0, 1, 2]
        assert metas[0].t_ns <= metas[1].t_ns <= metas[2].t_ns
        assert metas[0].trigger_index < metas[1].trigger_index < metas[2].trigger_index

    def test_frame_counter_restarts_on_open(self, camera: Camera,
                                            expose: Callable[[], None]) -> None:
        camera.open()
        expose()
        camera.read_frame(READ_TIMEOUT_S)
        camera.close()
        camera.open()
        expose()
        assert camera.read_frame(READ_TIMEOUT_S).meta.frame_counter == 0

    def test_timeout_without_pulse(self, camera: Camera) -> None:
        camera.open()
        started = time.monotonic()
        with pytest.raises(DeviceTimeoutError) as info:
            camera.read_frame(MISSING_TIMEOUT_S)
        assert info.value.device_id == camera.id
        assert MISSING_TIMEOUT_S * 0.9 <= time.monotonic() - started < 1.0

    def test_one_frame_per_pulse(self, camera: Camera, expose: Callable[[], None]) -> None:
        camera.open()
        expose()
        camera.read_frame(READ_TIMEOUT_S)
        with pytest.raises(DeviceTimeoutError):
            camera.read_frame(MISSING_TIMEOUT_S)

    def test_describe(self, camera: Camera) -> None:
        info = camera.describe()
        assert info["id"] == camera.id
        assert info["kind"] == "camera"
        assert info["open"] is False
        assert {"width", "height", "bit_depth", "exposure_us", "gain_db"} <= info.keys()


class ProjectorContract:
    """What every :class:`~eyeserver.hardware.base.Projector` driver guarantees."""

    def test_open_close_idempotent(self, projector: Projector) -> None:
        assert not projector.is_open
        projector.open()
        projector.open()
        assert projector.is_open
        projector.close()
        projector.close()
        assert not projector.is_open

    @pytest.mark.parametrize("call", ["set_enabled", "set_intensity", "set_strobe"])
    def test_use_before_open_raises(self, projector: Projector, call: str) -> None:
        with pytest.raises(DeviceNotOpenError) as info:
            self._call(projector, call)
        assert info.value.device_id == projector.id

    @pytest.mark.parametrize("call", ["set_enabled", "set_intensity", "set_strobe"])
    def test_use_after_close_raises(self, projector: Projector, call: str) -> None:
        projector.open()
        projector.close()
        with pytest.raises(DeviceNotOpenError):
            self._call(projector, call)

    @staticmethod
    def _call(projector: Projector, call: str) -> None:
        if call == "set_enabled":
            projector.set_enabled(False)
        elif call == "set_intensity":
            projector.set_intensity(0.5)
        else:
            projector.set_strobe(False)

    def test_defaults(self, projector: Projector) -> None:
        assert projector.enabled is True
        assert projector.strobe is True
        assert 0.0 <= projector.intensity <= 1.0

    def test_settings_round_trip(self, projector: Projector) -> None:
        projector.open()
        projector.set_enabled(False)
        projector.set_strobe(False)
        projector.set_intensity(0.25)
        assert (projector.enabled, projector.strobe, projector.intensity) == (False, False, 0.25)
        projector.set_enabled(True)
        projector.set_strobe(True)
        assert (projector.enabled, projector.strobe) == (True, True)

    @pytest.mark.parametrize("value", [-0.1, 1.01, 2.0])
    def test_intensity_range(self, projector: Projector, value: float) -> None:
        projector.open()
        projector.set_intensity(0.5)
        with pytest.raises(DeviceValueError) as info:
            projector.set_intensity(value)
        assert info.value.device_id == projector.id
        assert projector.intensity == 0.5

    def test_describe(self, projector: Projector) -> None:
        info = projector.describe()
        assert info["id"] == projector.id
        assert info["kind"] == "projector"
        assert {"enabled", "intensity", "strobe"} <= info.keys()


class TriggerContract:
    """What every :class:`~eyeserver.hardware.base.Trigger` driver guarantees."""

    def test_open_close_idempotent(self, trigger: Trigger) -> None:
        assert not trigger.is_open
        trigger.open()
        trigger.open()
        assert trigger.is_open
        trigger.close()
        trigger.close()
        assert not trigger.is_open

    @pytest.mark.parametrize("call", ["set_rate_hz", "set_sequence", "fire", "start"])
    def test_use_before_open_raises(self, trigger: Trigger, steps: Sequence[TriggerStep],
                                    call: str) -> None:
        with pytest.raises(DeviceNotOpenError) as info:
            if call == "set_rate_hz":
                trigger.set_rate_hz(10.0)
            elif call == "set_sequence":
                trigger.set_sequence(steps)
            elif call == "fire":
                trigger.fire()
            else:
                trigger.start()
        assert info.value.device_id == trigger.id

    def test_rate_range(self, trigger: Trigger) -> None:
        trigger.open()
        low, high = trigger.rate_range_hz
        trigger.set_rate_hz(high)
        assert trigger.rate_hz == high
        for value in (low / 2, high * 2, 0.0):
            with pytest.raises(DeviceValueError):
                trigger.set_rate_hz(value)
        assert trigger.rate_hz == high

    def test_bad_sequences_rejected(self, trigger: Trigger, steps: Sequence[TriggerStep]) -> None:
        trigger.open()
        with pytest.raises(DeviceValueError):
            trigger.set_sequence([])
        with pytest.raises(DeviceValueError):
            trigger.set_sequence([steps[0], TriggerStep(projectors=steps[0].projectors,
                                                        cameras=())])
        assert trigger.sequence == ()

    def test_fire_needs_a_sequence(self, trigger: Trigger) -> None:
        trigger.open()
        with pytest.raises(DeviceValueError):
            trigger.fire()
        with pytest.raises(DeviceValueError):
            trigger.start()

    def test_fire_cycles_through_the_sequence(self, trigger: Trigger,
                                              steps: Sequence[TriggerStep]) -> None:
        trigger.open()
        trigger.set_sequence(steps)
        assert trigger.sequence == tuple(steps)
        pulses = [trigger.fire() for _ in range(2 * len(steps) + 1)]
        assert [p.index for p in pulses] == list(range(len(pulses)))
        assert [p.step for p in pulses] == [steps[n % len(steps)] for n in range(len(pulses))]
        assert all(a.t_ns <= b.t_ns for a, b in itertools.pairwise(pulses))

    def test_set_sequence_restarts_it(self, trigger: Trigger,
                                      steps: Sequence[TriggerStep]) -> None:
        trigger.open()
        trigger.set_sequence(steps)
        trigger.fire()
        trigger.set_sequence(steps)
        assert trigger.fire().step == steps[0]

    def test_start_stop(self, trigger: Trigger, steps: Sequence[TriggerStep]) -> None:
        trigger.stop()  # stopping a trigger that never ran is fine
        trigger.open()
        trigger.set_sequence(steps)
        trigger.start()
        trigger.start()
        trigger.stop()
        trigger.stop()
        trigger.close()

    def test_close_stops_free_running(self, trigger: Trigger,
                                      steps: Sequence[TriggerStep]) -> None:
        trigger.open()
        trigger.set_sequence(steps)
        trigger.start()
        trigger.close()
        assert not trigger.is_open

    def test_describe(self, trigger: Trigger) -> None:
        info = trigger.describe()
        assert info["id"] == trigger.id
        assert info["kind"] == "trigger"
        assert {"rate_hz", "sequence"} <= info.keys()
