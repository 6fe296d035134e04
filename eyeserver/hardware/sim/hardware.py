"""The simulated treatment room as the daemon's hardware (:func:`simulated_room`, the room
``"sim"`` of :mod:`eyeserver.hardware.room`)."""

from __future__ import annotations

from pathlib import Path

from eyeserver.hardware.room import RoomHardware
from eyeserver.hardware.sim.config import load_room
from eyeserver.hardware.sim.drivers import build_sim_rig
from eyeserver.hardware.sim.room import SimRoom
from eyeserver.hardware.sim.scenes import SceneSpec
from eyeserver.hardware.sim.stage import SimStage

__all__ = ["SIM_STAGE_ID", "simulated_room"]

SIM_STAGE_ID = "Z1"
"""Id of the simulated motorised stage."""


def simulated_room(room_file: Path | None) -> RoomHardware:
    """The room of ``room_file`` (None: the default room) with an eye in front of the cameras:
    its rig of simulated drivers, its stage and its lights (nothing opened).

    Raises
    ------
    FormatError
        The room file cannot be read or is not a valid room.
    """
    room = SimRoom(load_room(room_file))
    room.set_scene(SceneSpec(kind="eye"))
    return RoomHardware(rig=build_sim_rig(room), stage=SimStage(SIM_STAGE_ID, room),
                        lights=room.set_room_lights, simulation=room)
