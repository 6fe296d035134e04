"""The stage contract: what every :class:`~eyeserver.hardware.base.Stage` driver (the
phase-to-height plate's motorised stage) guarantees, run over the simulated stage and the Zaber
driver on its emulated stage.

===============  ===============================================================================
``sim``          :class:`~eyeserver.hardware.sim.stage.SimStage`, placing a scene holder's plate
``zaber-pty``    :class:`~eyeserver.hardware.drivers.zaber.ZaberStage` on the Zaber ASCII emulator
                 on a pty
===============  ===============================================================================

Each case also says where the plate really is (the scene placed, the emulated axis's position),
so a move is checked on the device, not only in the driver's own bookkeeping. Nothing here needs
more than the Python environment, so no case is ever skipped.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass
from pathlib import Path

import pytest

from eyeserver.errors import DeviceNotOpenError, DeviceValueError
from eyeserver.hardware.base import Stage
from eyeserver.hardware.drivers.zaber import ZaberStage
from eyeserver.hardware.emulators.zaber import ZaberEmulator
from eyeserver.hardware.registry import DriverContext
from eyeserver.hardware.sim.scenes import SceneSpec
from eyeserver.hardware.sim.stage import SimStage
from tests.hardware.lifecycle import check_open_close_idempotent

MICROSTEP_MM = 0.0005
ZERO_MM = -15.0


@dataclass
class StageCase:
    """An unopened stage and a callable that reads where the device put the plate, mm."""

    stage: Stage
    plate_mm: Callable[[], float | None]


class _SceneHolder:
    def __init__(self) -> None:
        self.scene: SceneSpec | None = None

    def set_scene(self, spec: SceneSpec) -> None:
        self.scene = spec


@contextmanager
def _sim() -> Iterator[StageCase]:
    holder = _SceneHolder()
    stage = SimStage("Z1", holder)

    def plate_mm() -> float | None:
        if holder.scene is None:
            return None
        assert holder.scene.kind == "plate"
        return holder.scene.position_mm[2]

    try:
        yield StageCase(stage, plate_mm)
    finally:
        stage.close()


@contextmanager
def _zaber(tmp_path: Path) -> Iterator[StageCase]:
    with ZaberEmulator(address=1, homed=True, link_dir=tmp_path) as emulator:
        emulator.axes[1].speed = 2_000_000.0  # 30 mm in 30 ms: BUSY for a few polls
        stage = ZaberStage("Z1", context=DriverContext(), port=emulator.port,
                           microstep_mm=MICROSTEP_MM, zero_mm=ZERO_MM, timeout_s=0.5,
                           settle_timeout_s=2.0, poll_interval_s=0.005)

        def plate_mm() -> float | None:
            with emulator.lock:
                return ZERO_MM + emulator.axis().position * MICROSTEP_MM

        try:
            yield StageCase(stage, plate_mm)
        finally:
            stage.close()


@pytest.fixture(params=["sim", "zaber-pty"])
def case(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[StageCase]:
    makers: dict[str, Callable[[], AbstractContextManager[StageCase]]] = {
        "sim": _sim,
        "zaber-pty": lambda: _zaber(tmp_path),
    }
    with makers[request.param]() as made:
        yield made


@pytest.fixture
def stage(case: StageCase) -> Stage:
    return case.stage


def test_open_close_idempotent(stage: Stage) -> None:
    check_open_close_idempotent(stage)


def test_move_before_open_raises(stage: Stage) -> None:
    with pytest.raises(DeviceNotOpenError) as info:
        stage.move_to(0.0)
    assert info.value.device_id == stage.id


def test_move_after_close_raises(stage: Stage) -> None:
    stage.open()
    stage.close()
    with pytest.raises(DeviceNotOpenError):
        stage.move_to(0.0)


def test_no_position_before_the_first_move(stage: Stage) -> None:
    assert stage.position_mm is None
    stage.open()
    assert stage.position_mm is None


def test_moves_put_the_plate_at_each_height(case: StageCase) -> None:
    stage = case.stage
    stage.open()
    low, high = stage.travel_mm
    assert low < 0.0 < high
    for z_mm in (0.0, -10.0, 25.0, low, high):
        stage.move_to(z_mm)
        assert stage.position_mm == z_mm
        plate = case.plate_mm()
        assert plate is not None and plate == pytest.approx(z_mm, abs=1e-3)


@pytest.mark.parametrize("beyond_mm", [-0.5, 0.5])
def test_moves_outside_the_travel_are_refused(case: StageCase, beyond_mm: float) -> None:
    stage = case.stage
    stage.open()
    stage.move_to(5.0)
    low, high = stage.travel_mm
    with pytest.raises(DeviceValueError) as info:
        stage.move_to((low if beyond_mm < 0 else high) + beyond_mm)
    assert info.value.device_id == stage.id
    assert stage.position_mm == 5.0
    assert case.plate_mm() == pytest.approx(5.0, abs=1e-3)


def test_describe(stage: Stage) -> None:
    info = stage.describe()
    assert info["id"] == stage.id
    assert info["kind"] == "stage"
    assert info["open"] is False
    assert {"position_mm", "travel_mm"} <= info.keys()
