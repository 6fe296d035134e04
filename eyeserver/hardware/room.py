"""What one treatment room gives the daemon: the rig, the stage under the calibration plate, and
a switch for the room lights; found by name, like the drivers, so that the daemon never imports
the simulator.

Two are built in. The simulated room (``"sim"``, the default): its rig of simulated drivers, its
motorised stage and its lights, plus the room itself as an opaque ``simulation`` handle that
only the ``/sim`` control (:mod:`eyeserver.service.simroom`) opens. A room of real devices
(``"devices"``, :mod:`eyeserver.hardware.devices`): its room file names each device's driver
and connection, built through :func:`~eyeserver.hardware.rig.build_rig`.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Final

from eyeserver.errors import ConfigError
from eyeserver.hardware.base import Stage
from eyeserver.hardware.rig import Rig

__all__ = ["KNOWN_ROOMS", "RoomHardware", "room_hardware"]


@dataclass(frozen=True)
class RoomHardware:
    """The devices of a room, none of them open yet.

    Attributes
    ----------
    rig : Rig
        The units' cameras and projectors and the trigger.
    stage : Stage or None
        The motorised stage that carries the calibration plate; None where the plate is placed
        by hand.
    lights : callable or None
        Switches the room lights on (True) or off, for unlit calibration frames; None where the
        room is simply lit while the board is shown.
    simulation : object or None
        The simulated room behind the rig (ground truth and scene control, for people and tests
        only); None on real hardware.
    """

    rig: Rig
    stage: Stage | None = None
    lights: Callable[[bool], None] | None = None
    simulation: object | None = None


KNOWN_ROOMS: Final[dict[str, str]] = {
    "sim": "eyeserver.hardware.sim.hardware:simulated_room",
    "devices": "eyeserver.hardware.devices:device_room",
}
"""Each built-in room by name, as ``module:function`` taking the room file (None: the default
room) and returning :class:`RoomHardware`; imported only when asked for."""


def room_hardware(name: str, room_file: Path | None = None) -> RoomHardware:
    """The hardware of the room ``name`` described by ``room_file`` (not opened).

    Raises
    ------
    ConfigError
        An unknown room.
    FormatError
        The room file cannot be read or does not describe a room.
    """
    target = KNOWN_ROOMS.get(name)
    if target is None:
        raise ConfigError(f"unknown room {name!r}; known rooms: {', '.join(KNOWN_ROOMS)}")
    module, _, function = target.partition(":")
    build: Callable[[Path | None], RoomHardware] = getattr(importlib.import_module(module),
                                                           function)
    return build(room_file)
