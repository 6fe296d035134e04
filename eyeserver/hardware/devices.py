"""A treatment room of real devices (the room ``"devices"`` of :mod:`eyeserver.hardware.room`):
its room file names every device's driver and connection.

The room file (TOML, or JSON by extension; docs/room-file.md, "A room of real devices")::

    [[devices]]
    kind = "camera"
    id = "S1"
    driver = "GenicamCamera"
    options = { address = "192.168.10.11", trigger_source = "Line1" }

    [[devices]]
    kind = "projector"
    id = "P1"
    driver = "GardasoftProjector"
    options = { port = "/dev/eyeserver-led", channel = 1, max_current_a = 1.0,
                pulse_us = 8000, delay_us = 10 }

    [trigger]
    id = "T1"
    driver = "GenicamTrigger"

    [[units]]
    id = "left"
    projector = "P1"
    cameras = ["S1", "S2"]

    [stage]                       # optional: the calibration plate's motorised stage
    id = "Z1"
    driver = "ZaberStage"
    options = { port = "/dev/eyeserver-stage", microstep_mm = 0.000047625 }

Every entry is checked when the daemon starts, before a device is opened: an unknown key, a
missing one, an unknown driver or an option the driver does not take fails with the file and
the field named (:class:`~eyeserver.errors.FormatError`), or the device named
(:class:`~eyeserver.errors.ConfigError`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Final

from pydantic import Field

from eyeserver.core.validation import StrictModel, read_table, validated
from eyeserver.errors import ConfigError
from eyeserver.hardware.base import Stage
from eyeserver.hardware.registry import DriverContext, create_device
from eyeserver.hardware.rig import DeviceId, HardwareConfig, build_rig
from eyeserver.hardware.room import RoomHardware

__all__ = ["DEVICE_ROOM_KEYS_DOC", "DeviceRoomConfig", "StageConfig", "device_room",
           "load_device_room"]

DEVICE_ROOM_KEYS_DOC: Final = "docs/room-file.md (A room of real devices)"
"""Where a user finds the keys of a device room file."""


class StageConfig(StrictModel):
    """The motorised stage under the calibration plate: its id, driver and the driver's
    options."""

    id: DeviceId
    driver: str = Field(description="registered stage driver name, e.g. ZaberStage")
    options: dict[str, object] = Field(default_factory=dict,
                                       description="keyword arguments for the driver")


class DeviceRoomConfig(HardwareConfig):
    """A room of real devices: the rig's devices, trigger and units, and optionally the stage."""

    stage: StageConfig | None = None

    def device_ids(self) -> list[str]:
        """Every device's id, the trigger's and the stage's included (checked unique)."""
        return super().device_ids() + ([self.stage.id] if self.stage is not None else [])


def load_device_room(path: str | Path) -> DeviceRoomConfig:
    """Read and check a device room file (nothing is constructed or opened).

    Raises
    ------
    FormatError
        The file cannot be read, does not parse, or an entry is missing, unknown or invalid;
        the message names the file and the field.
    """
    return validated(DeviceRoomConfig, read_table(path, "room file"), path, DEVICE_ROOM_KEYS_DOC)


def device_room(room_file: Path | None) -> RoomHardware:
    """The devices of ``room_file``: the rig and the stage, constructed, none opened.

    Raises
    ------
    ConfigError
        No room file was given, or a device's driver is unknown or refuses its options (the
        message names the device).
    FormatError
        The room file is unreadable or invalid (file and field named).
    """
    if room_file is None:
        raise ConfigError("the room 'devices' needs a room file naming its devices "
                          f"(room_file; {DEVICE_ROOM_KEYS_DOC})")
    config = load_device_room(room_file)
    context = DriverContext()
    rig = build_rig(config, context)
    stage = None
    if config.stage is not None:
        made = create_device("stage", config.stage.driver, config.stage.id,
                             config.stage.options, context)
        if not isinstance(made, Stage):  # the registry checks kinds: only a broken driver
            raise ConfigError(f"device {config.stage.id!r}: driver {config.stage.driver} made a "
                              f"{type(made).__name__}, not a stage")
        stage = made
    return RoomHardware(rig=rig, stage=stage)
