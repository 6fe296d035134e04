"""The simulated room of a running daemon, driven by people and tests (``/api/v1/sim/…``).

What stands in front of the cameras (a scene, the flat plate on the motorised stage, the
calibration chessboard), the scene's ground truth, and the cables of the simulated devices.
Ground truth leaves the daemon only through here, for demonstrations and tests: the measurement
path (pipeline, calibration, io) never imports the simulator, which import-linter checks.

Scene changes never land in the middle of an operation: they wait for no one but answer
:class:`~eyeserver.errors.StateConflictError` (409) while the hardware is busy, because the
simulated cameras render the scene when a frame is read, and a capture that straddled two scenes
would mix them. Unplugging a device is allowed at any time: that is the fault being simulated.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import Any, Final

from pydantic import ValidationError

from eyeserver.errors import StateConflictError
from eyeserver.hardware.sim.drivers import SimCamera, SimProjector, SimTrigger
from eyeserver.hardware.sim.room import SimRoom
from eyeserver.hardware.sim.scenes import EyeSpec, SceneSpec
from eyeserver.hardware.sim.stage import SIM_STAGE_TRAVEL_MM
from eyeserver.hardware.sim.truth import room_truth
from eyeserver.service.core import Service

__all__ = ["STAGE_TRAVEL_MM", "SimRoomControl", "Vec3"]

Vec3 = tuple[float, float, float]

STAGE_TRAVEL_MM: Final = SIM_STAGE_TRAVEL_MM
"""Travel of the simulated motorised stage that carries the flat plate along Z, mm (inclusive).

It covers the phase-to-height calibration's −10…+25 mm (DESIGN §5) with 5 mm to spare each way.
"""

_log = logging.getLogger(__name__)


class SimRoomControl:
    """The simulated room of a :class:`Service` whose rig images one.

    Parameters
    ----------
    service : Service
        The open daemon; scene changes go through its state machine.
    room : SimRoom
        Its :attr:`Service.sim_room`.

    Notes
    -----
    Every method is quick except :meth:`truth` for an eye scene (it builds the scene's geometry,
    milliseconds); none touches the hardware.
    """

    def __init__(self, service: Service, room: SimRoom) -> None:
        self._service = service
        self._room = room

    @classmethod
    def of(cls, service: Service) -> SimRoomControl | None:
        """The control of ``service``'s simulated room, or None when it drives real hardware."""
        room = service.sim_room
        return None if room is None else cls(service, room)

    @property
    def scene(self) -> SceneSpec:
        """The scene in front of the cameras now."""
        return self._room.scene

    def place(self, spec: SceneSpec, *, actor: str | None = None) -> SceneSpec:
        """Put ``spec`` in front of the cameras; a moving eye's script starts now.

        Raises
        ------
        StateConflictError
            An operation holds the hardware (the message names the daemon's state).
        """
        with self._service.idle_moment("place a scene"):
            self._room.set_scene(spec)
        _log.info("simulated scene placed", extra={"kind": spec.kind, "actor": actor})
        return spec

    def move_stage(self, z_mm: float, *, actor: str | None = None) -> SceneSpec:
        """Put the flat calibration plate, normal to Z and centred on the axis, at ``z_mm``.

        Raises
        ------
        ValueError
            ``z_mm`` is outside :data:`STAGE_TRAVEL_MM`.
        StateConflictError
            An operation holds the hardware.
        """
        low, high = STAGE_TRAVEL_MM
        if not low <= z_mm <= high:
            raise ValueError(f"z_mm {z_mm} is outside the stage's travel {low}…{high} mm")
        stage = self._service.stage
        if stage is None:
            return self.place(SceneSpec(kind="plate", position_mm=(0.0, 0.0, float(z_mm))),
                              actor=actor)
        with self._service.idle_moment("place a scene"):
            stage.move_to(float(z_mm))  # the simulated stage places the plate at once
        _log.info("simulated stage moved", extra={"z_mm": z_mm, "actor": actor})
        return self._room.scene

    def place_chessboard(self, position_mm: Vec3, rotation_deg: Vec3, *,
                         actor: str | None = None) -> SceneSpec:
        """Put the room's calibration chessboard (the default board of :class:`SceneSpec`) at
        ``position_mm`` turned by ``rotation_deg`` (``Rz·Ry·Rx``, degrees).

        Raises
        ------
        StateConflictError
            An operation holds the hardware.
        """
        return self.place(SceneSpec(kind="chessboard", position_mm=position_mm,
                                    rotation_deg=rotation_deg), actor=actor)

    def place_eye(self, *, position_mm: Vec3 | None = None, rotation_deg: Vec3 | None = None,
                  eye: Mapping[str, Any] | None = None, actor: str | None = None) -> SceneSpec:
        """Put the patient eye in front of the cameras, changing only what is given.

        ``eye`` holds :class:`~eyeserver.hardware.sim.scenes.EyeSpec` fields (``gaze_deg``,
        ``globe_radius_mm``, ``cornea_radius_mm``, ``limbus_diameter_mm``, ``motion``…); what
        is left out keeps its current value when the scene is an eye already (else the
        default eye's). ``motion`` None stops a script; any change restarts the script's clock.

        Raises
        ------
        ValueError
            The resulting eye is invalid (e.g. a limbus wider than the cornea).
        StateConflictError
            An operation holds the hardware.
        """
        current = self._room.scene
        base = current if current.kind == "eye" else SceneSpec(kind="eye")
        try:
            new_eye = EyeSpec.model_validate({**base.eye.model_dump(), **dict(eye or {})})
            spec = SceneSpec.model_validate({
                **base.model_dump(), "kind": "eye", "eye": new_eye,
                "position_mm": base.position_mm if position_mm is None else position_mm,
                "rotation_deg": base.rotation_deg if rotation_deg is None else rotation_deg})
        except ValidationError as exc:
            raise ValueError("; ".join(f"{'.'.join(str(p) for p in e['loc']) or 'eye'}: "
                                       f"{e['msg']}" for e in exc.errors())) from None
        return self.place(spec, actor=actor)

    def eye_truth(self, t_s: float | None = None) -> dict[str, Any]:
        """The eye scene and the eye's true pose at clock time ``t_s`` (default: now):
        ``scene``, ``t_s`` (seconds since the scene was placed) and ``eye`` (``centre_mm``,
        ``gaze``, ``limbus_centre_mm``, ``globe_radius_mm``, ``openness``…).

        Raises
        ------
        StateConflictError
            The scene is not the patient eye.
        """
        truth = room_truth(self._room, t_s)
        if self._room.scene.kind != "eye" or truth.get("eye") is None:
            raise StateConflictError(f"the simulated scene is {self._room.scene.kind}, not the "
                                     "patient eye (PUT /api/v1/sim/eye places it)")
        return {"scene": truth["scene"], "t_s": truth["t_s"], "eye": truth["eye"]}

    def truth(self, t_s: float | None = None) -> dict[str, Any]:
        """The current scene's ground truth at clock time ``t_s`` (default: now) with the
        devices' optics: the document ``eyeserver sim render`` writes as ``truth.json``."""
        return room_truth(self._room, t_s)

    def set_connected(self, device_id: str, connected: bool, *,
                      actor: str | None = None) -> str:
        """Unplug (``connected=False``) or plug back in a simulated device; returns its kind.

        An unplugged device fails every call, so the next operation that needs it answers 503
        and puts its unit in fault; once plugged back in, the next operation reopens it and the
        daemon recovers, as with real hardware.

        Raises
        ------
        KeyError
            The rig has no simulated device ``device_id``.
        """
        device = next((d for d in self._service.rig.devices if d.id == device_id), None)
        if not isinstance(device, SimCamera | SimProjector | SimTrigger):
            raise KeyError(device_id)
        if connected:
            device.reconnect()
        else:
            device.inject_fault("disconnect")
        _log.warning("simulated device plugged in" if connected else
                     "simulated device unplugged", extra={"device_id": device_id, "actor": actor})
        return device.kind
