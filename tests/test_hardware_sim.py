"""The simulated drivers, the driver registry and the rig, against a tiny fake room."""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pydantic import ValidationError

from eyeserver.core.clock import ManualClock, MonotonicClock
from eyeserver.core.frames import Frame
from eyeserver.errors import (
    ConfigError,
    DeviceDisconnectedError,
    DeviceNotOpenError,
    DeviceTimeoutError,
    DeviceValueError,
    FormatError,
)
from eyeserver.hardware import registry
from eyeserver.hardware.base import Camera, Projector, Trigger, TriggerPulse, TriggerStep
from eyeserver.hardware.registry import (
    DriverContext,
    create_device,
    known_drivers,
    register_driver,
)
from eyeserver.hardware.rig import HardwareConfig, Rig, Unit, build_rig
from eyeserver.hardware.room import room_hardware
from eyeserver.hardware.sim.drivers import (
    LINK_BYTES_PER_S,
    SIM_WIRING,
    SimCamera,
    SimProjector,
    SimTrigger,
    SimWiring,
    build_sim_rig,
    sim_driver_context,
    sim_hardware_config,
)
from eyeserver.hardware.sim.room import SimRoom
from tests.hardware.simroom import BACKGROUND_DN, FRINGE_DN, START_NS, FakeRoom
from tests.hardware.timeouts import MISSING_TIMEOUT_S, READ_TIMEOUT_S


@pytest.fixture
def room() -> FakeRoom:
    return FakeRoom()


@pytest.fixture
def context(room: FakeRoom) -> DriverContext:
    return sim_driver_context(room)


@pytest.fixture
def rig(room: FakeRoom) -> Iterator[Rig]:
    rig = build_sim_rig(room)
    yield rig
    rig.close()


@pytest.fixture
def open_rig(rig: Rig) -> Rig:
    rig.open()
    return rig


def sim_camera(rig: Rig, camera_id: str) -> SimCamera:
    camera = rig.camera(camera_id)
    assert isinstance(camera, SimCamera)
    return camera


def sim_projector(rig: Rig, projector_id: str) -> SimProjector:
    projector = rig.projector(projector_id)
    assert isinstance(projector, SimProjector)
    return projector


def sim_trigger(rig: Rig) -> SimTrigger:
    assert isinstance(rig.trigger, SimTrigger)
    return rig.trigger


def fire_step(rig: Rig, cameras: tuple[str, ...], projectors: tuple[str, ...] = ("P1",),
              pulses: int = 1) -> list[TriggerPulse]:
    rig.trigger.set_sequence([TriggerStep(projectors=projectors, cameras=cameras)])
    return [rig.trigger.fire() for _ in range(pulses)]


# --- registry -------------------------------------------------------------------------------


@pytest.fixture
def scratch_registry(monkeypatch: pytest.MonkeyPatch) -> None:
    """Let a test register drivers without leaking them into other tests."""
    known_drivers("camera")  # load the built-in drivers into the copy
    monkeypatch.setattr(registry, "_registry",
                        {kind: dict(drivers) for kind, drivers in registry._registry.items()})


def test_sim_drivers_are_registered() -> None:
    assert "SimCamera" in known_drivers("camera")
    assert "SimProjector" in known_drivers("projector")
    assert "SimTrigger" in known_drivers("trigger")


def test_create_device_builds_an_unopened_driver(context: DriverContext) -> None:
    camera = create_device("camera", "SimCamera", "S2", {"queue_size": 3}, context)
    assert isinstance(camera, SimCamera)
    assert (camera.id, camera.width, camera.height, camera.is_open) == ("S2", 32, 24, False)


def test_unknown_driver_lists_known_ones(context: DriverContext) -> None:
    with pytest.raises(ConfigError, match=r"'AcmeCamera'.*SimCamera"):
        create_device("camera", "AcmeCamera", "S1", {}, context)


def test_unknown_kind(context: DriverContext) -> None:
    with pytest.raises(ConfigError, match="known kinds: camera, projector, trigger"):
        create_device("laser", "SimLaser", "L1", {}, context)


def test_driver_of_another_kind_is_unknown(context: DriverContext) -> None:
    with pytest.raises(ConfigError, match="unknown projector driver 'SimCamera'"):
        create_device("projector", "SimCamera", "P1", {}, context)


def test_unexpected_option_names_the_device(context: DriverContext) -> None:
    with pytest.raises(ConfigError, match=r"'S3'.*queue_sise.*accepted options: queue_size"):
        create_device("camera", "SimCamera", "S3", {"queue_sise": 4}, context)


@pytest.mark.parametrize("reserved", ["context", "device_id"])
def test_reserved_option_rejected(context: DriverContext, reserved: str) -> None:
    with pytest.raises(ConfigError, match=f"'S1'.*{reserved}"):
        create_device("camera", "SimCamera", "S1", {reserved: None}, context)


def test_bad_option_value_names_the_device(context: DriverContext) -> None:
    with pytest.raises(ConfigError, match=r"'S1'.*queue_size must be at least 1"):
        create_device("camera", "SimCamera", "S1", {"queue_size": 0}, context)


def test_device_missing_from_room(context: DriverContext) -> None:
    with pytest.raises(ConfigError, match=r"'S9'.*no camera 'S9'"):
        create_device("camera", "SimCamera", "S9", {}, context)


def test_sim_driver_needs_the_wiring() -> None:
    with pytest.raises(ConfigError, match=r"sim\.wiring"):
        create_device("camera", "SimCamera", "S1", {}, DriverContext(clock=ManualClock()))
    wrong = DriverContext(resources={SIM_WIRING: object()})
    with pytest.raises(ConfigError, match="not a SimWiring"):
        create_device("trigger", "SimTrigger", "T1", {}, wrong)


def test_the_simulated_room_is_found_by_name_with_its_stage_and_lights(tmp_path: Path) -> None:
    hardware = room_hardware("sim")

    assert isinstance(hardware.simulation, SimRoom)
    assert hardware.simulation.scene.kind == "eye"
    assert [u.id for u in hardware.rig.units] == [u[0] for u in hardware.simulation.units()]
    assert not any(d.is_open for d in hardware.rig.devices)
    assert hardware.stage is not None and not hardware.stage.is_open
    assert hardware.lights is not None
    with pytest.raises(ConfigError, match="unknown room 'basler'; known rooms: sim"):
        room_hardware("basler")
    broken = tmp_path / "room.toml"
    broken.write_text("units = 3\n")
    with pytest.raises(FormatError, match=r"room\.toml"):
        room_hardware("sim", broken)


@pytest.mark.usefixtures("scratch_registry")
def test_register_driver_checks_name_base_and_clashes(context: DriverContext) -> None:
    for bad_name in ("Camera", "AcmeCam", "acmeCamera", "Acme Camera"):
        with pytest.raises(ValueError, match="<Vendor>Camera"):
            register_driver("camera", bad_name)
    with pytest.raises(TypeError, match="does not derive from Camera"):
        register_driver("camera", "AcmeCamera")(SimProjector)
    with pytest.raises(ValueError, match="already taken"):
        register_driver("camera", "SimCamera")(RecordingCamera)

    @register_driver("camera", "AcmeCamera")
    class AcmeCamera(RecordingCamera):
        def __init__(self, device_id: str, *, context: DriverContext, serial: str) -> None:
            super().__init__(device_id, [])
            self.serial = serial

    assert "AcmeCamera" in known_drivers("camera")
    made = create_device("camera", "AcmeCamera", "C7", {"serial": "X1"}, context)
    assert isinstance(made, AcmeCamera) and made.serial == "X1"
    with pytest.raises(ConfigError, match=r"'C7'.*missing option\(s\) serial"):
        create_device("camera", "AcmeCamera", "C7", {}, context)


# --- rig: validation, spec, lifecycle -------------------------------------------------------


class RecordingDevice:
    """Mixin: log open/close into a shared list and fail on request."""

    id: str
    log: list[str]
    fail_open = False
    fail_close = False

    def _do_open(self) -> None:
        self.log.append(f"open {self.id}")
        if self.fail_open:
            raise DeviceDisconnectedError(self.id, "refuses to open")

    def _do_close(self) -> None:
        self.log.append(f"close {self.id}")
        if self.fail_close:
            raise DeviceDisconnectedError(self.id, "refuses to close")


class RecordingCamera(RecordingDevice, Camera):
    def __init__(self, device_id: str, log: list[str]) -> None:
        super().__init__(device_id, 8, 6)
        self.log = log

    def _apply_exposure_us(self, value: float) -> None:
        pass

    def _apply_gain_db(self, value: float) -> None:
        pass

    def _read_frame(self, timeout_s: float) -> Frame:
        raise DeviceTimeoutError(self.id, "never triggered")


class RecordingProjector(RecordingDevice, Projector):
    def __init__(self, device_id: str, log: list[str]) -> None:
        super().__init__(device_id)
        self.log = log

    def _apply_enabled(self, value: bool) -> None:
        pass

    def _apply_intensity(self, value: float) -> None:
        pass

    def _apply_strobe(self, value: bool) -> None:
        pass


class RecordingTrigger(RecordingDevice, Trigger):
    def __init__(self, device_id: str, log: list[str]) -> None:
        super().__init__(device_id)
        self.log = log

    def _apply_rate_hz(self, value: float) -> None:
        pass

    def _apply_sequence(self, steps: tuple[TriggerStep, ...]) -> None:
        pass

    def _fire(self) -> TriggerPulse:
        return TriggerPulse(index=0, t_ns=0, step=self.sequence[0])

    def start(self) -> None:
        pass

    def stop(self) -> None:
        self.log.append(f"stop {self.id}")


@pytest.fixture
def recorded() -> tuple[Rig, list[str]]:
    log: list[str] = []
    cameras = [RecordingCamera(f"S{n}", log) for n in range(1, 5)]
    projectors = [RecordingProjector("P1", log), RecordingProjector("P2", log)]
    units = [Unit("left", projectors[0], tuple(cameras[:2])),
             Unit("right", projectors[1], tuple(cameras[2:]))]
    return Rig(cameras, projectors, RecordingTrigger("T1", log), units), log


OPEN_ORDER = ["open P1", "open P2", "open S1", "open S2", "open S3", "open S4", "open T1"]
CLOSE_ORDER = ["stop T1", "close T1", "close S4", "close S3", "close S2", "close S1",
               "close P2", "close P1"]


def test_rig_opens_in_order_and_closes_in_reverse(recorded: tuple[Rig, list[str]]) -> None:
    rig, log = recorded
    rig.open()
    assert rig.is_open
    assert log == OPEN_ORDER
    log.clear()
    assert rig.close() == {}
    assert log == CLOSE_ORDER
    assert not any(d.is_open for d in rig.devices)


@pytest.mark.parametrize("failing", ["S3", "T1", "P1"])
def test_rig_open_rolls_back(recorded: tuple[Rig, list[str]], failing: str) -> None:
    rig, log = recorded
    device = next(d for d in rig.devices if d.id == failing)
    device.fail_open = True  # type: ignore[attr-defined]
    with pytest.raises(DeviceDisconnectedError, match="refuses to open"):
        rig.open()
    opened = OPEN_ORDER[:OPEN_ORDER.index(f"open {failing}")]
    assert log == [*opened, f"open {failing}",
                   *(entry.replace("open", "close") for entry in reversed(opened))]
    assert not any(d.is_open for d in rig.devices)


def test_rig_open_keeps_going_when_rollback_fails(recorded: tuple[Rig, list[str]]) -> None:
    rig, log = recorded
    rig.camera("S2").fail_open = True  # type: ignore[attr-defined]
    rig.camera("S1").fail_close = True  # type: ignore[attr-defined]
    with pytest.raises(DeviceDisconnectedError, match="S2: refuses to open"):
        rig.open()
    assert log[-3:] == ["close S1", "close P2", "close P1"]


def test_rig_close_never_raises(recorded: tuple[Rig, list[str]],
                                caplog: pytest.LogCaptureFixture) -> None:
    rig, log = recorded
    rig.open()
    rig.camera("S2").fail_close = True  # type: ignore[attr-defined]
    rig.trigger.fail_close = True  # type: ignore[attr-defined]
    log.clear()
    with caplog.at_level(logging.WARNING, logger="eyeserver.hardware.rig"):
        errors = rig.close()
    assert sorted(errors) == ["S2", "T1"]
    assert log == CLOSE_ORDER
    assert not any(d.is_open for d in rig.devices)
    assert "S2 failed to close" in caplog.text


def test_rig_context_manager(recorded: tuple[Rig, list[str]]) -> None:
    rig, log = recorded
    with rig as entered:
        assert entered is rig and rig.is_open
    assert log == OPEN_ORDER + CLOSE_ORDER


def test_rig_validation() -> None:
    log: list[str] = []
    s1, s2, s3 = (RecordingCamera(n, log) for n in ("S1", "S2", "S3"))
    p1, p2 = RecordingProjector("P1", log), RecordingProjector("P2", log)
    t1 = RecordingTrigger("T1", log)
    with pytest.raises(ConfigError, match="camera 'S3' belongs to no unit"):
        Rig([s1, s2, s3], [p1], t1, [Unit("a", p1, (s1, s2))])
    with pytest.raises(ConfigError, match="camera 'S2' belongs to units a, b"):
        Rig([s1, s2], [p1, p2], t1, [Unit("a", p1, (s1, s2)), Unit("b", p2, (s2,))])
    with pytest.raises(ConfigError, match="projector 'P2' belongs to no unit"):
        Rig([s1], [p1, p2], t1, [Unit("a", p1, (s1,))])
    with pytest.raises(ConfigError, match="projector 'P2' is not one of the rig's"):
        Rig([s1], [p1], t1, [Unit("a", p2, (s1,))])
    with pytest.raises(ConfigError, match="camera 'S2' is not one of the rig's"):
        Rig([s1], [p1], t1, [Unit("a", p1, (s1, s2))])
    with pytest.raises(ConfigError, match="unit 'a' has no camera"):
        Rig([], [p1], t1, [Unit("a", p1, ())])
    with pytest.raises(ConfigError, match="duplicate device id"):
        Rig([s1, RecordingCamera("S1", log)], [p1], t1, [Unit("a", p1, (s1,))])
    with pytest.raises(ConfigError, match="duplicate unit id"):
        Rig([s1, s2], [p1, p2], t1, [Unit("a", p1, (s1,)), Unit("a", p2, (s2,))])
    with pytest.raises(ConfigError, match="at least one unit"):
        Rig([], [], t1, [])


def test_rig_spec_is_the_rig_file(rig: Rig) -> None:
    spec = rig.spec()
    assert spec == {
        "format": "eyeserver.rig/1",
        "cameras": [{"id": "S1", "width": 32, "height": 24},
                    {"id": "S2", "width": 32, "height": 24},
                    {"id": "S3", "width": 32, "height": 24},
                    {"id": "S4", "width": 24, "height": 16}],
        "projectors": [{"id": "P1"}, {"id": "P2"}],
        "units": [{"id": "left", "projector": "P1", "cameras": ["S1", "S2"]},
                  {"id": "right", "projector": "P2", "cameras": ["S3", "S4"]}],
    }
    assert json.loads(json.dumps(spec)) == spec
    assert rig.trigger.id == "T1"
    assert rig.unit_of("S3").id == "right" and rig.unit_of("P1").id == "left"
    assert json.dumps(rig.describe())


def test_hardware_config_validation(room: FakeRoom) -> None:
    good = sim_hardware_config(room).model_dump()

    def broken(change: Callable[[dict[str, Any]], None]) -> dict[str, Any]:
        data: dict[str, Any] = json.loads(json.dumps(good))
        change(data)
        return data

    cases = {
        "duplicate device id": lambda d: d["devices"].append(dict(d["devices"][0])),
        "not a configured camera": lambda d: d["units"][0]["cameras"].append("P2"),
        "camera 'S2' belongs to no unit": lambda d: d["units"][0]["cameras"].remove("S2"),
        "duplicate unit id": lambda d: d["units"][1].update(id="left"),
        "letters, digits": lambda d: d["trigger"].update(id="T 1"),
        "Input should be 'camera' or 'projector'": lambda d: d["devices"][0].update(
            kind="trigger"),
        "Extra inputs are not permitted": lambda d: d["devices"][0].update(port="/dev/x"),
    }
    HardwareConfig.model_validate(good)
    for message, change in cases.items():
        with pytest.raises(ValidationError, match=message):
            HardwareConfig.model_validate(broken(change))


def test_build_rig_names_the_device_with_a_bad_option(room: FakeRoom) -> None:
    data = sim_hardware_config(room).model_dump()
    data["devices"][3]["options"] = {"exposure": 3}
    with pytest.raises(ConfigError, match=r"device 'S2'.*exposure"):
        build_rig(HardwareConfig.model_validate(data), sim_driver_context(room))


# --- acquisition ----------------------------------------------------------------------------


def test_interleaved_acquire(open_rig: Rig, room: FakeRoom) -> None:
    left, right = open_rig.acquire(["left", "right"], timeout_s=READ_TIMEOUT_S)
    assert left.pulse.step == TriggerStep(projectors=("P1",), cameras=("S1", "S2"))
    assert right.pulse.step == TriggerStep(projectors=("P2",), cameras=("S3", "S4"))
    assert (left.pulse.index, right.pulse.index) == (0, 1)
    assert sorted(left.frames) == ["S1", "S2"] and sorted(right.frames) == ["S3", "S4"]
    for step, projector in ((left, "P1"), (right, "P2")):
        for frame in step.frames.values():
            assert frame.meta.projectors_on == (projector,)
            assert frame.meta.trigger_index == step.pulse.index
            assert frame.meta.frame_counter == 0
            assert abs(frame.image.mean() - (BACKGROUND_DN + FRINGE_DN)) < 2.0
    assert {r["camera"]: r["projectors"] for r in room.renders} == {
        "S1": {"P1": 1.0}, "S2": {"P1": 1.0}, "S3": {"P2": 1.0}, "S4": {"P2": 1.0}}
    assert right.frames["S4"].image.dtype == np.uint16
    assert right.frames["S4"].meta.bit_depth == 12


def test_acquire_times_mid_exposure(open_rig: Rig, room: FakeRoom) -> None:
    open_rig.camera("S1").set_exposure_us(8_000.0)
    (step,) = open_rig.acquire(["left"])
    assert step.pulse.t_ns == START_NS
    assert step.frames["S1"].meta.t_ns == START_NS + 4_000_000
    assert step.frames["S2"].meta.t_ns == START_NS + 5_000_000  # default 10 ms exposure
    assert room.renders[0]["t_s"] == pytest.approx(1.004)
    assert room.renders[0]["exposure_us"] == 8_000.0


def test_a_pulse_scheduled_ahead_is_rendered_at_once_and_delivered_when_a_camera_would(
        open_rig: Rig, room: FakeRoom) -> None:
    at_ns = START_NS + 40_000_000
    (step,) = open_rig.acquire(["left"], at_ns=at_ns)
    assert step.pulse.t_ns == at_ns
    assert [step.frames[c].meta.t_ns for c in ("S1", "S2")] == [at_ns + 5_000_000] * 2
    assert [r["t_s"] for r in room.renders] == pytest.approx([1.045, 1.045])
    assert room.renders[0]["rendered_ns"] == START_NS  # before its pulse: ahead
    # Delivered at the end of the 10 ms exposure plus the transfer over the link, not sooner.
    transfer_ns = round(1e9 * 32 * 24 / LINK_BYTES_PER_S)
    assert room.clock.now_ns() == at_ns + 10_000_000 + transfer_ns
    # A moment already past fires now.
    now = room.clock.now_ns()
    (late,) = open_rig.acquire(["left"], at_ns=START_NS)
    assert late.pulse.t_ns == now


class SideBySideRoom(FakeRoom):
    """A room whose renders of one pulse wait for each other: only cameras that render side
    by side get their images."""

    def __init__(self) -> None:
        super().__init__()
        self.together = threading.Barrier(2, timeout=5.0)
        self.threads: list[str] = []

    def render(self, camera_id: str, **kwargs: Any) -> np.ndarray:
        self.threads.append(threading.current_thread().name)
        self.together.wait()
        return super().render(camera_id, **kwargs)


def test_a_pulse_is_rendered_on_the_cameras_own_threads_side_by_side_before_any_read() -> None:
    room = SideBySideRoom()
    context = sim_driver_context(room)
    first, second = (SimCamera(c, context=context) for c in ("S1", "S2"))
    trigger = SimTrigger("T1", context=context)
    second.open()
    try:
        with camera_and_trigger(first, trigger):
            (pulse,) = fire_step_on(trigger, ("S1", "S2"), pulses=1)
            deadline = time.monotonic() + 5.0
            while len(room.renders) < 2 and time.monotonic() < deadline:
                time.sleep(0.001)
            assert sorted(r["camera"] for r in room.renders) == ["S1", "S2"]  # none read yet
            assert threading.current_thread().name not in room.threads
            assert len(set(room.threads)) == 2
            frames = [camera.read_frame(READ_TIMEOUT_S) for camera in (first, second)]
    finally:
        second.close()
    assert [f.meta.trigger_index for f in frames] == [pulse.index] * 2


def test_acquire_one_unit_and_bad_unit_lists(open_rig: Rig) -> None:
    (step,) = open_rig.acquire(["right"])
    assert sorted(step.frames) == ["S3", "S4"]
    for unit_ids, message in (([], "at least one"), (["centre"], "unknown unit"),
                              (["left", "left"], "repeats")):
        with pytest.raises(ValueError, match=message):
            open_rig.acquire(unit_ids)
    with pytest.raises(ValueError, match="timeout_s"):
        open_rig.acquire(["left"], timeout_s=0)


def test_the_rig_prepares_a_units_cameras_for_a_stream(open_rig: Rig, room: FakeRoom) -> None:
    open_rig.prepare_stream(["right"])
    # Each camera of the unit, lit by the unit's projector, and nothing rendered.
    assert room.prepared == [("S3", ("P2",)), ("S4", ("P2",))]
    assert room.renders == []
    with pytest.raises(ValueError, match="unknown unit"):
        open_rig.prepare_stream(["centre"])
    sim_camera(open_rig, "S3").inject_fault("disconnect")
    with pytest.raises(DeviceDisconnectedError):
        open_rig.prepare_stream(["right"])


def test_a_closed_rig_prepares_nothing(rig: Rig, room: FakeRoom) -> None:
    with pytest.raises(DeviceNotOpenError):
        rig.prepare_stream(["left"])
    assert room.prepared == []


def test_acquire_on_a_closed_rig(rig: Rig) -> None:
    with pytest.raises(DeviceNotOpenError):
        rig.acquire(["left"])


def test_acquire_unlit(open_rig: Rig) -> None:
    step = open_rig.acquire_unlit(timeout_s=READ_TIMEOUT_S)
    assert step.pulse.step.projectors == ()
    assert sorted(step.frames) == ["S1", "S2", "S3", "S4"]
    for frame in step.frames.values():
        assert frame.meta.projectors_on == ()
        assert abs(frame.image.mean() - BACKGROUND_DN) < 2.0


def test_projector_modes_decide_what_is_lit(open_rig: Rig, room: FakeRoom) -> None:
    p1, p2 = open_rig.projector("P1"), open_rig.projector("P2")
    p2.set_strobe(False)  # continuous: lit on every pulse
    p1.set_intensity(0.5)
    (left,) = open_rig.acquire(["left"])
    assert left.frames["S1"].meta.projectors_on == ("P1", "P2")
    assert room.renders[-1]["projectors"] == {"P1": 0.5, "P2": 1.0}
    assert open_rig.acquire_unlit().frames["S3"].meta.projectors_on == ("P2",)
    p1.set_enabled(False)
    p2.set_enabled(False)
    (left,) = open_rig.acquire(["left"])
    assert left.frames["S2"].meta.projectors_on == ()
    p1.set_enabled(True)
    p1.set_intensity(0.0)
    (left,) = open_rig.acquire(["left"])
    assert left.frames["S2"].meta.projectors_on == ()


def test_closed_projector_does_not_light(open_rig: Rig) -> None:
    open_rig.projector("P1").close()
    fire_step(open_rig, ("S1",))
    assert open_rig.camera("S1").read_frame(READ_TIMEOUT_S).meta.projectors_on == ()


def test_the_rig_asks_each_projector_before_its_pulse(open_rig: Rig) -> None:
    # A capture with its projector gone fails instead of storing fringe-less images.
    projector = open_rig.projector("P1")
    assert isinstance(projector, SimProjector)
    projector.inject_fault("disconnect")
    with pytest.raises(DeviceDisconnectedError, match="not responding"):
        open_rig.acquire(["left"])
    projector.close()
    with pytest.raises(DeviceNotOpenError):
        open_rig.acquire(["left"])
    (right,) = open_rig.acquire(["right"])  # the other unit's projector answers
    assert right.frames["S3"].meta.projectors_on == ("P2",)


def test_frames_carry_the_exposure_of_their_pulse(open_rig: Rig) -> None:
    camera = open_rig.camera("S1")
    camera.set_gain_db(6.0)
    fire_step(open_rig, ("S1",))
    camera.set_gain_db(0.0)  # after the pulse: must not change the latched exposure
    assert camera.read_frame(READ_TIMEOUT_S).meta.gain_db == 6.0


def test_full_buffer_drops_and_counts(room: FakeRoom) -> None:
    context = sim_driver_context(room)
    camera = SimCamera("S1", context=context, queue_size=2)
    trigger = SimTrigger("T1", context=context)
    with camera_and_trigger(camera, trigger):
        pulses = [p.index for p in fire_step_on(trigger, ("S1",), pulses=4)]
        frames = [camera.read_frame(READ_TIMEOUT_S) for _ in range(2)]
        assert [f.meta.trigger_index for f in frames] == pulses[:2]
        assert [f.meta.dropped_frames for f in frames] == [2, 2]
        assert camera.dropped_frames == 2
        with pytest.raises(DeviceTimeoutError):
            camera.read_frame(MISSING_TIMEOUT_S)


class camera_and_trigger:  # noqa: N801 - used like a function
    """Open a camera and a trigger for the duration of a ``with`` block."""

    def __init__(self, camera: SimCamera, trigger: SimTrigger) -> None:
        self.camera, self.trigger = camera, trigger

    def __enter__(self) -> None:
        self.camera.open()
        self.trigger.open()

    def __exit__(self, *exc_info: object) -> None:
        self.trigger.close()
        self.camera.close()


def fire_step_on(trigger: Trigger, cameras: tuple[str, ...], pulses: int) -> list[TriggerPulse]:
    trigger.set_sequence([TriggerStep(projectors=("P1",), cameras=cameras)])
    return [trigger.fire() for _ in range(pulses)]


def test_trigger_rejects_devices_it_is_not_wired_to(open_rig: Rig) -> None:
    with pytest.raises(DeviceValueError, match="S9"):
        open_rig.trigger.set_sequence([TriggerStep(projectors=("P1",), cameras=("S9",))])
    with pytest.raises(DeviceValueError, match="P7"):
        open_rig.trigger.set_sequence([TriggerStep(projectors=("P7",), cameras=("S1",))])


def test_two_open_cameras_cannot_share_an_id(context: DriverContext) -> None:
    first, second = SimCamera("S1", context=context), SimCamera("S1", context=context)
    first.open()
    try:
        with pytest.raises(DeviceValueError, match="already has this id"):
            second.open()
        first.close()
        second.open()
        second.close()
    finally:
        first.close()


def test_closing_wakes_a_waiting_reader(open_rig: Rig) -> None:
    camera = open_rig.camera("S1")
    outcome: list[BaseException] = []

    def read() -> None:
        try:
            camera.read_frame(10.0)
        except BaseException as exc:
            outcome.append(exc)

    reader = threading.Thread(target=read)
    reader.start()
    time.sleep(0.05)
    started = time.monotonic()
    camera.close()
    reader.join(5.0)
    assert not reader.is_alive()
    assert time.monotonic() - started < 1.0
    assert len(outcome) == 1 and isinstance(outcome[0], DeviceNotOpenError)


# --- free-running trigger -------------------------------------------------------------------


def test_free_running_trigger_paces_pulses_on_the_clock(open_rig: Rig) -> None:
    trigger = sim_trigger(open_rig)
    trigger.set_rate_hz(25.0)
    trigger.set_sequence([TriggerStep(projectors=("P1",), cameras=("S1",)),
                          TriggerStep(projectors=("P2",), cameras=("S3",))])
    trigger.start()
    assert trigger.running
    s1 = [open_rig.camera("S1").read_frame(READ_TIMEOUT_S).meta for _ in range(3)]
    s3 = [open_rig.camera("S3").read_frame(READ_TIMEOUT_S).meta for _ in range(3)]
    trigger.stop()
    assert not trigger.running
    assert [m.trigger_index for m in s1] == [0, 2, 4]
    assert [m.trigger_index for m in s3] == [1, 3, 5]
    assert [m.t_ns - s1[0].t_ns for m in s1] == [0, 80_000_000, 160_000_000]
    assert s3[0].t_ns - s1[0].t_ns == 40_000_000
    assert all(m.projectors_on == ("P1",) for m in s1)


def test_close_joins_the_free_running_thread(open_rig: Rig) -> None:
    trigger = sim_trigger(open_rig)
    trigger.set_sequence([TriggerStep(projectors=("P1",), cameras=("S1",))])
    trigger.start()
    thread = trigger._thread
    assert thread is not None
    open_rig.close()
    assert not thread.is_alive()
    assert not trigger.running


def test_free_running_on_the_monotonic_clock() -> None:
    room = FakeRoom(clock=MonotonicClock())
    with build_sim_rig(room) as rig:
        rig.trigger.set_rate_hz(100.0)
        rig.trigger.set_sequence([TriggerStep(projectors=("P1",), cameras=("S1",))])
        rig.trigger.start()
        metas = [rig.camera("S1").read_frame(READ_TIMEOUT_S).meta for _ in range(3)]
        rig.trigger.stop()
    gaps_ms = np.diff([m.t_ns for m in metas]) / 1e6
    assert np.all(gaps_ms >= 9.0), gaps_ms


# --- faults ---------------------------------------------------------------------------------


def test_drop_fault(open_rig: Rig) -> None:
    camera = sim_camera(open_rig, "S1")
    camera.inject_fault("drop")
    pulses = fire_step(open_rig, ("S1",), pulses=2)
    frame = camera.read_frame(READ_TIMEOUT_S)
    assert frame.meta.trigger_index == pulses[1].index
    assert (frame.meta.frame_counter, frame.meta.dropped_frames) == (0, 1)
    with pytest.raises(DeviceTimeoutError):
        camera.read_frame(MISSING_TIMEOUT_S)


def test_drop_fault_makes_acquire_time_out(open_rig: Rig) -> None:
    sim_camera(open_rig, "S2").inject_fault("drop", count=2)
    for _ in range(2):
        with pytest.raises(DeviceTimeoutError, match="S2"):
            open_rig.acquire(["left"], timeout_s=MISSING_TIMEOUT_S)
    (left,) = open_rig.acquire(["left"])
    assert left.frames["S2"].meta.dropped_frames == 2


def test_timeout_fault(open_rig: Rig) -> None:
    camera = sim_camera(open_rig, "S3")
    camera.inject_fault("timeout")
    fire_step(open_rig, ("S3",))
    started = time.monotonic()
    with pytest.raises(DeviceTimeoutError, match="S3"):
        camera.read_frame(MISSING_TIMEOUT_S)
    assert time.monotonic() - started >= MISSING_TIMEOUT_S * 0.9
    # The lost frame does not linger to be mistaken for the next pulse's.
    with pytest.raises(DeviceTimeoutError):
        camera.read_frame(MISSING_TIMEOUT_S)
    (right,) = open_rig.acquire(["right"])
    assert right.frames["S3"].meta.dropped_frames == 1
    assert right.frames["S3"].meta.frame_counter == 0


def test_camera_disconnect_and_recovery(open_rig: Rig) -> None:
    camera = sim_camera(open_rig, "S3")
    camera.inject_fault("disconnect")
    assert not camera.connected
    with pytest.raises(DeviceDisconnectedError, match="S3"):
        open_rig.acquire(["left", "right"])
    with pytest.raises(DeviceDisconnectedError):
        camera.set_exposure_us(1_000.0)
    assert open_rig.acquire(["left"])  # the other unit keeps working
    camera.reconnect()
    with pytest.raises(DeviceDisconnectedError, match="close and reopen"):
        camera.read_frame(MISSING_TIMEOUT_S)
    camera.close()
    camera.open()
    _, right = open_rig.acquire(["left", "right"])
    assert sorted(right.frames) == ["S3", "S4"]


def test_disconnected_camera_cannot_open_until_it_is_back(open_rig: Rig) -> None:
    camera = sim_camera(open_rig, "S1")
    camera.inject_fault("disconnect")
    assert open_rig.close() == {}
    with pytest.raises(DeviceDisconnectedError, match="not responding"):
        open_rig.open()
    assert not any(d.is_open for d in open_rig.devices)
    camera.reconnect()
    open_rig.open()
    assert sorted(open_rig.acquire(["left"])[0].frames) == ["S1", "S2"]


def test_disconnect_wakes_a_waiting_reader(open_rig: Rig) -> None:
    camera = sim_camera(open_rig, "S2")
    outcome: list[BaseException] = []

    def read() -> None:
        try:
            camera.read_frame(10.0)
        except BaseException as exc:
            outcome.append(exc)

    reader = threading.Thread(target=read)
    reader.start()
    time.sleep(0.05)
    camera.inject_fault("disconnect")
    reader.join(5.0)
    assert not reader.is_alive()
    assert len(outcome) == 1 and isinstance(outcome[0], DeviceDisconnectedError)


def test_projector_disconnect_and_recovery(open_rig: Rig) -> None:
    projector = sim_projector(open_rig, "P1")
    projector.inject_fault("disconnect")
    with pytest.raises(DeviceDisconnectedError, match="P1"):
        projector.set_intensity(0.5)
    fire_step(open_rig, ("S1",))
    frame = open_rig.camera("S1").read_frame(READ_TIMEOUT_S)
    assert frame.meta.projectors_on == ()  # a vanished LED driver does not light
    with pytest.raises(DeviceDisconnectedError, match="P1"):
        open_rig.acquire(["left"])  # and the rig, asking it first, does not capture
    projector.close()
    with pytest.raises(DeviceDisconnectedError):
        projector.open()
    projector.reconnect()
    projector.open()
    projector.set_intensity(0.5)
    (left,) = open_rig.acquire(["left"])
    assert left.frames["S1"].meta.projectors_on == ("P1",)


def test_trigger_disconnect_and_recovery(open_rig: Rig) -> None:
    trigger = sim_trigger(open_rig)
    trigger.inject_fault("disconnect")
    with pytest.raises(DeviceDisconnectedError, match="T1"):
        open_rig.acquire(["left"])
    with pytest.raises(DeviceDisconnectedError):
        trigger.set_rate_hz(10.0)
    trigger.reconnect()
    trigger.close()
    trigger.open()
    assert open_rig.acquire(["left"])


def test_trigger_disconnect_stops_free_running(open_rig: Rig) -> None:
    trigger = sim_trigger(open_rig)
    trigger.set_sequence([TriggerStep(projectors=("P1",), cameras=("S1",))])
    trigger.start()
    open_rig.camera("S1").read_frame(READ_TIMEOUT_S)
    trigger.inject_fault("disconnect")
    deadline = time.monotonic() + 5.0
    while trigger.running and time.monotonic() < deadline:
        time.sleep(0.01)
    assert not trigger.running
    assert isinstance(trigger.last_run_error, DeviceDisconnectedError)
    with pytest.raises(DeviceDisconnectedError):
        trigger.start()


def test_clear_faults(open_rig: Rig) -> None:
    camera = sim_camera(open_rig, "S1")
    camera.inject_fault("drop", count=3)
    camera.inject_fault("timeout")
    camera.inject_fault("disconnect")
    camera.clear_faults()
    assert camera.connected
    (left,) = open_rig.acquire(["left"])
    assert left.frames["S1"].meta.dropped_frames == 0
    projector, trigger = sim_projector(open_rig, "P1"), sim_trigger(open_rig)
    projector.inject_fault("disconnect")
    trigger.inject_fault("disconnect")
    projector.clear_faults()
    trigger.clear_faults()
    assert open_rig.acquire(["left"])[0].frames["S1"].meta.projectors_on == ("P1",)


@pytest.mark.parametrize("device_id", ["P1", "T1"])
def test_only_cameras_drop_or_time_out(open_rig: Rig, device_id: str) -> None:
    device = next(d for d in open_rig.devices if d.id == device_id)
    assert isinstance(device, SimProjector | SimTrigger)
    for kind in ("drop", "timeout"):
        with pytest.raises(ValueError, match="supports the faults disconnect"):
            device.inject_fault(kind)


def test_fault_arguments_are_checked(open_rig: Rig) -> None:
    camera = sim_camera(open_rig, "S1")
    with pytest.raises(ValueError, match="count"):
        camera.inject_fault("drop", count=0)
    with pytest.raises(ValueError, match="not 'melt'"):
        camera.inject_fault("melt")  # type: ignore[arg-type]


# --- reproducibility ------------------------------------------------------------------------


def capture_images(seed: int, repeats: int = 2) -> list[dict[str, np.ndarray]]:
    with build_sim_rig(FakeRoom(seed=seed)) as rig:
        return [{camera_id: frame.image for step in rig.acquire(["left", "right"])
                 for camera_id, frame in step.frames.items()} for _ in range(repeats)]


def test_seed_reproduces_the_render_sequence() -> None:
    first, again, other = capture_images(7), capture_images(7), capture_images(8)
    for a, b in zip(first, again, strict=True):
        assert a.keys() == b.keys()
        assert all(np.array_equal(a[c], b[c]) for c in a)
    assert not np.array_equal(first[0]["S1"], first[1]["S1"])  # noise moves on between reads
    assert not np.array_equal(first[0]["S1"], first[0]["S2"])  # each camera has its own stream
    assert not np.array_equal(first[0]["S1"], other[0]["S1"])


def test_build_sim_rig_uses_the_given_clock(room: FakeRoom) -> None:
    clock = ManualClock(5_000_000_000)
    with build_sim_rig(room, clock=clock) as rig:
        (left,) = rig.acquire(["left"])
    assert left.pulse.t_ns == 5_000_000_000


def test_sim_wiring_is_in_the_context(room: FakeRoom) -> None:
    context = sim_driver_context(room)
    wiring = context.resource(SIM_WIRING, SimWiring)
    assert wiring.room is room and context.clock is room.clock
