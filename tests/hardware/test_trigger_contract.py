"""The trigger contract: what every :class:`~eyeserver.hardware.base.Trigger` driver guarantees,
run over the simulated trigger and each real one on its fake.

====================  ==========================================================================
``sim``               :class:`~eyeserver.hardware.sim.drivers.SimTrigger` in a tiny simulated room
``software-ids``      :class:`~eyeserver.hardware.drivers.softtrigger.GenicamTrigger`, the cameras'
                      own software trigger, over four cameras on the fake IDS peak
``triggerbox-pty``    :class:`~eyeserver.hardware.drivers.triggerbox.TriggerBoxTrigger` on the
                      trigger box emulator on a pty
====================  ==========================================================================

The steps are two units' (``P1``: S1, S2; ``P2``: S3, S4), as the rig interleaves them. Nothing
here needs more than the Python environment, so no case is ever skipped. Frames matched to
pulses and missed triggers through a rig: tests/test_driver_triggerbox.py.
"""

from __future__ import annotations

import itertools
import sys
from collections.abc import Callable, Iterator, Sequence
from contextlib import AbstractContextManager, contextmanager
from pathlib import Path

import pytest

from eyeserver.errors import DeviceNotOpenError, DeviceValueError
from eyeserver.hardware.base import Camera, Trigger, TriggerStep
from eyeserver.hardware.drivers.ids import IdsCamera
from eyeserver.hardware.drivers.softtrigger import GenicamTrigger
from eyeserver.hardware.drivers.triggerbox import TriggerBoxTrigger
from eyeserver.hardware.emulators.triggerbox import TriggerBoxEmulator
from eyeserver.hardware.registry import DriverContext
from eyeserver.hardware.rig import RIG_CAMERAS
from eyeserver.hardware.sim.drivers import SimTrigger, sim_driver_context
from tests.hardware.fakepeak import FakeCamera, FakePeak
from tests.hardware.lifecycle import check_open_close_idempotent
from tests.hardware.simroom import FakeRoom

CAMERAS = ("S1", "S2", "S3", "S4")
STEPS = [TriggerStep(projectors=("P1",), cameras=("S1", "S2")),
         TriggerStep(projectors=("P2",), cameras=("S3", "S4"))]


@contextmanager
def _sim() -> Iterator[Trigger]:
    trigger = SimTrigger("T1", context=sim_driver_context(FakeRoom()))
    try:
        yield trigger
    finally:
        trigger.close()


@contextmanager
def _software(monkeypatch: pytest.MonkeyPatch) -> Iterator[Trigger]:
    peak = FakePeak([FakeCamera(f"41030123{n}") for n in range(len(CAMERAS))])
    for name, module in peak.modules.items():
        monkeypatch.setitem(sys.modules, name, module)
    cameras: dict[str, Camera] = {
        camera_id: IdsCamera(camera_id, context=DriverContext(), serial=f"41030123{n}",
                             trigger_source="Software", width=64, height=48)
        for n, camera_id in enumerate(CAMERAS)}
    for camera in cameras.values():
        camera.open()
    trigger = GenicamTrigger("T1", context=DriverContext(resources={RIG_CAMERAS: cameras}))
    try:
        yield trigger
    finally:
        trigger.close()
        for camera in cameras.values():
            camera.close()


@contextmanager
def _triggerbox(tmp_path: Path) -> Iterator[Trigger]:
    with TriggerBoxEmulator(outputs=4, link_dir=tmp_path) as box:
        trigger = TriggerBoxTrigger("T1", context=DriverContext(), port=box.port,
                                    outputs={"S1": 1, "S2": 1, "S3": 2, "S4": 2},
                                    timeout_s=0.5)
        try:
            yield trigger
        finally:
            trigger.close()


@pytest.fixture(params=["sim", "software-ids", "triggerbox-pty"])
def trigger(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch,
            tmp_path: Path) -> Iterator[Trigger]:
    makers: dict[str, Callable[[], AbstractContextManager[Trigger]]] = {
        "sim": _sim,
        "software-ids": lambda: _software(monkeypatch),
        "triggerbox-pty": lambda: _triggerbox(tmp_path),
    }
    with makers[request.param]() as made:
        yield made


@pytest.fixture
def steps() -> list[TriggerStep]:
    return list(STEPS)


def test_open_close_idempotent(trigger: Trigger) -> None:
    check_open_close_idempotent(trigger)


@pytest.mark.parametrize("call", ["set_rate_hz", "set_sequence", "fire", "start"])
def test_use_before_open_raises(trigger: Trigger, steps: Sequence[TriggerStep],
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


def test_rate_range(trigger: Trigger) -> None:
    trigger.open()
    low, high = trigger.rate_range_hz
    trigger.set_rate_hz(high)
    assert trigger.rate_hz == high
    for value in (low / 2, high * 2, 0.0):
        with pytest.raises(DeviceValueError):
            trigger.set_rate_hz(value)
    assert trigger.rate_hz == high


def test_bad_sequences_rejected(trigger: Trigger, steps: Sequence[TriggerStep]) -> None:
    trigger.open()
    with pytest.raises(DeviceValueError):
        trigger.set_sequence([])
    with pytest.raises(DeviceValueError):
        trigger.set_sequence([steps[0], TriggerStep(projectors=steps[0].projectors, cameras=())])
    assert trigger.sequence == ()


def test_fire_needs_a_sequence(trigger: Trigger) -> None:
    trigger.open()
    with pytest.raises(DeviceValueError):
        trigger.fire()
    with pytest.raises(DeviceValueError):
        trigger.start()


def test_fire_cycles_through_the_sequence(trigger: Trigger,
                                          steps: Sequence[TriggerStep]) -> None:
    trigger.open()
    trigger.set_sequence(steps)
    assert trigger.sequence == tuple(steps)
    pulses = [trigger.fire() for _ in range(2 * len(steps) + 1)]
    assert [p.index for p in pulses] == list(range(len(pulses)))
    assert [p.step for p in pulses] == [steps[n % len(steps)] for n in range(len(pulses))]
    assert all(a.t_ns <= b.t_ns for a, b in itertools.pairwise(pulses))


def test_pulse_indices_restart_on_open(trigger: Trigger, steps: Sequence[TriggerStep]) -> None:
    trigger.open()
    trigger.set_sequence(steps)
    trigger.fire()
    trigger.fire()
    trigger.close()
    trigger.open()
    trigger.set_sequence(steps)
    assert trigger.fire().index == 0


def test_set_sequence_restarts_it(trigger: Trigger, steps: Sequence[TriggerStep]) -> None:
    trigger.open()
    trigger.set_sequence(steps)
    trigger.fire()
    trigger.set_sequence(steps)
    assert trigger.fire().step == steps[0]


def test_start_stop(trigger: Trigger, steps: Sequence[TriggerStep]) -> None:
    trigger.stop()  # stopping a trigger that never ran is fine
    trigger.open()
    trigger.set_sequence(steps)
    trigger.start()
    trigger.start()
    trigger.stop()
    trigger.stop()
    trigger.close()


def test_close_stops_free_running(trigger: Trigger, steps: Sequence[TriggerStep]) -> None:
    trigger.open()
    trigger.set_sequence(steps)
    trigger.start()
    trigger.close()
    assert not trigger.is_open


def test_missed_triggers_are_counted_per_camera_until_reopened(
        trigger: Trigger, steps: Sequence[TriggerStep]) -> None:
    trigger.open()
    trigger.set_sequence(steps)
    first, second = trigger.fire(), trigger.fire()
    trigger.record_missed(first, "S2")
    trigger.record_missed(second, "S3")
    trigger.record_missed(second, "S4")
    assert trigger.missed_triggers == 3
    info = trigger.describe()
    assert info["missed_triggers"] == 3
    assert info["missed_by_camera"] == {"S2": 1, "S3": 1, "S4": 1}
    trigger.close()
    assert trigger.missed_triggers == 3  # still there for the status page once closed
    trigger.open()
    assert trigger.missed_triggers == 0


def test_describe(trigger: Trigger) -> None:
    info = trigger.describe()
    assert info["id"] == trigger.id
    assert info["kind"] == "trigger"
    assert {"rate_hz", "sequence", "missed_triggers"} <= info.keys()
