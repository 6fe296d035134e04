"""The simulated motorised stage: it puts the simulated room's flat plate at a height."""

from __future__ import annotations

from typing import Protocol

from eyeserver.hardware.base import Stage
from eyeserver.hardware.sim.scenes import SceneSpec

__all__ = ["SIM_STAGE_TRAVEL_MM", "SceneHolder", "SimStage"]

SIM_STAGE_TRAVEL_MM = (-15.0, 30.0)
"""Travel of the simulated stage, mm (inclusive): the phase-to-height calibration's −10…+25 mm
(docs/design.md §5) with 5 mm to spare each way."""


class SceneHolder(Protocol):
    """What the stage needs of the room: a way to place the scene."""

    def set_scene(self, spec: SceneSpec) -> None: ...


class SimStage(Stage):
    """A stage that moves at once: the room's scene becomes the flat plate, normal to Z and
    centred on the axis, at the height asked for."""

    travel_mm = SIM_STAGE_TRAVEL_MM

    def __init__(self, device_id: str, room: SceneHolder) -> None:
        super().__init__(device_id)
        self._room = room

    def _do_open(self) -> None:
        pass

    def _do_close(self) -> None:
        pass

    def _move_to(self, z_mm: float) -> None:
        self._room.set_scene(SceneSpec(kind="plate", position_mm=(0.0, 0.0, float(z_mm))))
