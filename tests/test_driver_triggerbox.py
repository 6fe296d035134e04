"""The trigger box driver (:mod:`eyeserver.hardware.drivers.triggerbox`) against its emulator on
a pty, alone and as the trigger of a rig whose cameras hang on its outputs.

The rig: two units (``left``: P1 with S1, S2 on output 1; ``right``: P2 with S3, S4 on output 2),
the cameras IDS cameras on the fake IDS peak whose software trigger the emulator's outputs call
(the trigger cable), the projectors two channels of the emulated Gardasoft controller. The
contract every trigger keeps is tests/hardware/test_trigger_contract.py.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from eyeserver.core.clock import MonotonicClock
from eyeserver.errors import (
    ConfigError,
    DeviceDisconnectedError,
    DeviceError,
    DeviceTimeoutError,
    DeviceValueError,
)
from eyeserver.hardware.base import TriggerStep
from eyeserver.hardware.devices import device_room
from eyeserver.hardware.drivers.triggerbox import TriggerBoxTrigger
from eyeserver.hardware.emulators.gardasoft import GardasoftEmulator
from eyeserver.hardware.emulators.serialpty import Behaviour
from eyeserver.hardware.emulators.triggerbox import TriggerBoxEmulator
from eyeserver.hardware.registry import DriverContext, create_device, driver_class
from eyeserver.hardware.rig import HardwareConfig, Rig, build_rig
from tests.hardware.fakepeak import FakeCamera, FakePeak

OUTPUTS = {"S1": 1, "S2": 1, "S3": 2, "S4": 2}
SERIALS = {"S1": "4103012301", "S2": "4103012302", "S3": "4103012303", "S4": "4103012304"}
TIMEOUT_S = 0.3
"""The rig's wait for each frame in these tests, seconds."""


@pytest.fixture
def box(tmp_path: Path) -> Iterator[TriggerBoxEmulator]:
    with TriggerBoxEmulator(outputs=4, link_dir=tmp_path) as emulator:
        yield emulator


def make_trigger(box: TriggerBoxEmulator, **options: Any) -> TriggerBoxTrigger:
    settings: dict[str, Any] = {"port": box.port, "outputs": OUTPUTS, "timeout_s": 0.5,
                                **options}
    return TriggerBoxTrigger("T1", context=DriverContext(), **settings)


@pytest.fixture
def trigger(box: TriggerBoxEmulator) -> Iterator[TriggerBoxTrigger]:
    trigger = make_trigger(box)
    yield trigger
    trigger.close()


@pytest.fixture
def rig(box: TriggerBoxEmulator, tmp_path: Path,
        monkeypatch: pytest.MonkeyPatch) -> Iterator[Rig]:
    peak = FakePeak([FakeCamera(serial) for serial in SERIALS.values()])
    for name, module in peak.modules.items():
        monkeypatch.setitem(sys.modules, name, module)
    with GardasoftEmulator(channels=2, link_dir=tmp_path, name="led") as leds:
        config = HardwareConfig.model_validate({
            "devices": [
                *({"kind": "camera", "id": camera_id, "driver": "IdsCamera",
                   "options": {"serial": serial, "trigger_source": "Software", "width": 64,
                               "height": 48}} for camera_id, serial in SERIALS.items()),
                *({"kind": "projector", "id": f"P{n}", "driver": "GardasoftProjector",
                   "options": {"port": leds.port, "channel": n, "max_current_a": 1.0,
                               "pulse_us": 8000, "delay_us": 10}} for n in (1, 2)),
            ],
            "trigger": {"id": "T1", "driver": "TriggerBoxTrigger",
                        "options": {"port": box.port, "outputs": OUTPUTS}},
            "units": [{"id": "left", "projector": "P1", "cameras": ["S1", "S2"]},
                      {"id": "right", "projector": "P2", "cameras": ["S3", "S4"]}],
        })
        rig = build_rig(config, DriverContext())
        rig.open()
        # The trigger cables: each output exposes the cameras on it.
        for camera_id, output in OUTPUTS.items():
            box.wire(output, rig.camera(camera_id).software_trigger)  # type: ignore[attr-defined]
        try:
            yield rig
        finally:
            rig.close()


def test_registered_and_options_checked(box: TriggerBoxEmulator) -> None:
    assert driver_class("trigger", "TriggerBoxTrigger") is TriggerBoxTrigger
    options = {"port": box.port, "outputs": OUTPUTS}
    assert isinstance(create_device("trigger", "TriggerBoxTrigger", "T1", options,
                                    DriverContext()), TriggerBoxTrigger)
    with pytest.raises(ConfigError, match=r"'T1'.*camera 'S1' on output 9"):
        create_device("trigger", "TriggerBoxTrigger", "T1",
                      {**options, "outputs": {"S1": 9}}, DriverContext())
    with pytest.raises(ConfigError, match=r"'T1'.*missing option.*outputs"):
        create_device("trigger", "TriggerBoxTrigger", "T1", {"port": box.port},
                      DriverContext())


def test_open_sets_the_box_up(box: TriggerBoxEmulator, trigger: TriggerBoxTrigger) -> None:
    trigger.open()
    assert box.received[:3] == ["ID", "RST", "PW 100"]
    assert box.pulse_us == 100
    trigger.set_sequence([TriggerStep(("P1",), ("S1", "S2")), TriggerStep(("P2",), ("S3", "S4"))])
    assert box.received[-1] == "SEQ 1,2"
    assert trigger.describe()["box_outputs"] == 4


def test_cameras_beyond_the_box_outputs_fail_the_open(tmp_path: Path) -> None:
    with TriggerBoxEmulator(outputs=1, link_dir=tmp_path) as small:
        trigger = make_trigger(small)
        with pytest.raises(DeviceError, match=r"1 outputs.*S3, S4"):
            trigger.open()
        assert not trigger.is_open


def test_steps_must_match_the_wiring(trigger: TriggerBoxTrigger) -> None:
    trigger.open()
    with pytest.raises(DeviceValueError, match=r"S9.*wired to no output"):
        trigger.set_sequence([TriggerStep(("P1",), ("S9",))])
    # S1 alone would expose S2 too (same output), and S2's extra frame be given to a later pulse.
    with pytest.raises(DeviceValueError, match="also expose S2"):
        trigger.set_sequence([TriggerStep(("P1",), ("S1",))])


def test_pulse_times_are_the_boxes_on_the_rig_clock(box: TriggerBoxEmulator,
                                                    trigger: TriggerBoxTrigger) -> None:
    trigger.open()
    trigger.set_sequence([TriggerStep(("P1",), ("S1", "S2"))])
    clock = MonotonicClock()
    before = clock.now_ns()
    pulse = trigger.fire()
    after = clock.now_ns()
    assert before - 2_000_000 <= pulse.t_ns <= after + 2_000_000
    assert box.pulses[-1][0] == pulse.index == 0


def test_a_pulse_scheduled_ahead_fires_at_its_time(box: TriggerBoxEmulator,
                                                   trigger: TriggerBoxTrigger) -> None:
    trigger.open()
    trigger.set_sequence([TriggerStep(("P1",), ("S1", "S2"))])
    at_ns = MonotonicClock().now_ns() + 80_000_000
    pulse = trigger.fire(at_ns)
    # The box's timer fired it then: the pulse's time is the one asked for, to the microsecond.
    assert at_ns - 1000 < pulse.t_ns <= at_ns
    assert MonotonicClock().now_ns() >= at_ns - 2_000_000
    assert box.received[-1].startswith("FIRE ")


def test_interleaved_frames_are_matched_to_their_pulses(box: TriggerBoxEmulator,
                                                        rig: Rig) -> None:
    for n in range(3):
        left, right = rig.acquire(["left", "right"], timeout_s=TIMEOUT_S)
        assert (left.pulse.index, right.pulse.index) == (2 * n, 2 * n + 1)
        for step, cameras in ((left, ("S1", "S2")), (right, ("S3", "S4"))):
            assert tuple(step.frames) == cameras
            for frame in step.frames.values():
                assert frame.meta.frame_counter == n
                assert abs(frame.meta.t_ns - step.pulse.t_ns) < 50_000_000
    assert [mask for _, _, mask in box.pulses] == [1, 2] * 3
    assert rig.trigger.describe()["missed_triggers"] == 0


def test_a_lost_pulse_is_a_missed_trigger(box: TriggerBoxEmulator, rig: Rig) -> None:
    rig.acquire(["left", "right"], timeout_s=TIMEOUT_S)
    box.drop_next(2)  # the right unit's cable loses one pulse
    with pytest.raises(DeviceTimeoutError) as info:
        rig.acquire(["left", "right"], timeout_s=TIMEOUT_S)
    assert info.value.device_id == "S3"
    assert box.lost == [(3, 2)]
    status = rig.trigger.describe()
    assert status["missed_triggers"] == 1
    assert status["missed_by_camera"] == {"S3": 1}
    # The next capture is whole: no frame was waiting to be taken for the wrong pulse.
    _, right = rig.acquire(["left", "right"], timeout_s=TIMEOUT_S)
    assert right.frames["S3"].meta.frame_counter == 1
    assert rig.trigger.describe()["missed_triggers"] == 1


def test_a_late_frame_is_not_taken_for_the_next_pulse(box: TriggerBoxEmulator,
                                                      rig: Rig) -> None:
    rig.acquire(["left"], timeout_s=TIMEOUT_S)
    box.delay_next(1, TIMEOUT_S + 0.1)  # exposes S1 and S2 after the rig gave up
    with pytest.raises(DeviceTimeoutError):
        rig.acquire(["left"], timeout_s=TIMEOUT_S)
    time.sleep(0.5)  # the late frames are in S1's and S2's queues now
    (left,) = rig.acquire(["left"], timeout_s=TIMEOUT_S)
    for frame in left.frames.values():
        assert frame.meta.frame_counter == 2  # the third frame, not the late second
        assert abs(frame.meta.t_ns - left.pulse.t_ns) < 50_000_000
    assert rig.trigger.describe()["missed_by_camera"] == {"S1": 1}


def test_a_reset_box_is_noticed(box: TriggerBoxEmulator, trigger: TriggerBoxTrigger) -> None:
    trigger.open()
    trigger.set_sequence([TriggerStep(("P1",), ("S1", "S2"))])
    trigger.fire()
    trigger.fire()
    with box.lock:
        box.reply("RST")  # power-cycled behind the driver's back: its count starts again
    with pytest.raises(DeviceError, match=r"fired pulse 0.*expected pulse 2"):
        trigger.fire()


def test_refused_command_names_the_box_error(box: TriggerBoxEmulator,
                                             trigger: TriggerBoxTrigger) -> None:
    trigger.open()
    trigger.set_sequence([TriggerStep(("P1",), ("S1", "S2"))])
    with box.lock:
        box._sequence = []  # lost its sequence (a firmware restart): it refuses to fire
    with pytest.raises(DeviceError, match=r"refused 'FIRE': ERR 3 no sequence"):
        trigger.fire()


@pytest.mark.parametrize("fault", ["silent", "garbage", "unplugged"])
def test_faults_and_recovery(box: TriggerBoxEmulator, trigger: TriggerBoxTrigger,
                             fault: str) -> None:
    trigger.open()
    trigger.set_sequence([TriggerStep(("P1",), ("S1", "S2"))])
    assert trigger.fire().index == 0
    expected: type[DeviceError] = {"silent": DeviceTimeoutError, "garbage": DeviceError,
                                   "unplugged": DeviceDisconnectedError}[fault]
    if fault == "unplugged":
        box.unplug()
    else:
        box.behaviour = Behaviour.SILENT if fault == "silent" else Behaviour.GARBAGE
    with pytest.raises(expected) as info:
        trigger.fire()
    assert info.value.device_id == "T1"
    if fault == "unplugged":
        box.replug()
    else:
        box.behaviour = Behaviour.NORMAL
    # A silent or garbled box may have fired the lost pulse: reopening starts a fresh count.
    trigger.close()
    trigger.open()
    trigger.set_sequence([TriggerStep(("P1",), ("S1", "S2"))])
    assert trigger.fire().index == 0


def test_a_room_file_names_the_trigger_box(box: TriggerBoxEmulator, tmp_path: Path) -> None:
    room = tmp_path / "room.toml"
    cameras = "".join(f'[[devices]]\nkind = "camera"\nid = "{c}"\ndriver = "IdsCamera"\n'
                      f'options = {{ serial = "{s}" }}\n\n' for c, s in SERIALS.items())
    room.write_text(
        f'{cameras}[[devices]]\nkind = "projector"\nid = "P1"\ndriver = "GardasoftProjector"\n'
        'options = { port = "/dev/null", channel = 1, max_current_a = 1.0, pulse_us = 8000, '
        'delay_us = 10 }\n\n'
        '[trigger]\nid = "T1"\ndriver = "TriggerBoxTrigger"\n'
        f'options = {{ port = "{box.port}", outputs = {{ S1 = 1, S2 = 1, S3 = 1, S4 = 1 }} }}\n\n'
        '[[units]]\nid = "left"\nprojector = "P1"\ncameras = ["S1", "S2", "S3", "S4"]\n')
    hardware = device_room(room)
    assert isinstance(hardware.rig.trigger, TriggerBoxTrigger)
    assert hardware.rig.trigger.outputs == {"S1": 1, "S2": 1, "S3": 1, "S4": 1}
    room.write_text(room.read_text().replace("S4 = 1 }", "S4 = 12 }"))
    with pytest.raises(ConfigError, match=r"device 'T1' \(driver TriggerBoxTrigger\).*"
                                          r"'S4' on output 12"):
        device_room(room)
