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
import math
import time
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Final

from pydantic import ValidationError

from eyeserver.errors import StateConflictError
from eyeserver.hardware.sim.drivers import SimCamera, SimProjector, SimTrigger
from eyeserver.hardware.sim.room import SimRoom
from eyeserver.hardware.sim.scenes import EyeSpec, SceneSpec
from eyeserver.hardware.sim.stage import SIM_STAGE_TRAVEL_MM
from eyeserver.hardware.sim.truth import room_truth
from eyeserver.service.core import Service

__all__ = ["PRERENDER_MAX_S", "STAGE_TRAVEL_MM", "SimRoomControl", "Vec3"]

Vec3 = tuple[float, float, float]

STAGE_TRAVEL_MM: Final = SIM_STAGE_TRAVEL_MM
"""Travel of the simulated motorised stage that carries the flat plate along Z, mm (inclusive).

It covers the phase-to-height calibration's −10…+25 mm (docs/design.md §5) with 5 mm to spare
each way.
"""

PRERENDER_MAX_S: Final = 120.0
"""Longest script a unit's cameras render ahead (:meth:`SimRoomControl.prerender_eye`): 25
frame sets a second of two 640 × 512 8-bit images keep ≈ 16 MB a second in memory."""

_log = logging.getLogger(__name__)


class SimRoomControl:
    """The simulated room of a :class:`Service` whose rig images one.

    Parameters
    ----------
    service : Service
        The open daemon; scene changes go through its state machine.
    room : SimRoom
        Its :attr:`Service.simulation`.

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
        room = service.simulation
        return cls(service, room) if isinstance(room, SimRoom) else None

    @property
    def scene(self) -> SceneSpec:
        """The scene in front of the cameras now."""
        return self._room.scene

    def place(self, spec: SceneSpec, *, actor: str | None = None,
              while_tracking: bool = False) -> SceneSpec:
        """Put ``spec`` in front of the cameras; a moving eye's script starts now.

        ``while_tracking``: also while live tracking runs (the eye moved under it; the frames
        of a trigger pulse fired before the change still see the old scene, so none mixes
        two: :meth:`~eyeserver.hardware.sim.room.SimRoom.set_scene`).

        Raises
        ------
        StateConflictError
            An operation holds the hardware (the message names the daemon's state).
        """
        with self._service.idle_moment("place a scene", while_tracking=while_tracking):
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
            An operation other than live tracking holds the hardware (tracking goes on with
            the eye as placed: frames rendered ahead of the old eye are forgotten).
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
        return self.place(spec, actor=actor, while_tracking=current.kind == "eye")

    def prerender_eye(self, unit_id: str, seconds: float, *, actor: str | None = None,
                      ) -> dict[str, Any]:
        """Render the moving eye's next ``seconds`` ahead for live tracking with ``unit_id``,
        then restart its script: what the unit's cameras will see at the camera rate
        (:data:`~eyeserver.service.tracking.CAMERA_RATE_HZ`), lit by the unit's projector as
        it is set now, rendered beforehand (one thread per camera; ≈ 0.3–0.5 s of work a
        second of script on 2 cores) so that a stream of them costs the host's cores nothing,
        as real cameras' frames do. The script restarts at the last whole camera period of
        the room's clock (live tracking's frames fall on whole periods:
        :class:`~eyeserver.service.tracking.RigFrameSource`). Frames at other times, or past
        the end, render as usual. Any scene change forgets them.

        Returns ``unit``, ``cameras``, ``seconds``, ``rate_hz``, ``frames`` (per camera),
        ``megabytes`` (kept in memory) and ``took_s``.

        Raises
        ------
        KeyError
            The rig has no unit ``unit_id``.
        ValueError
            ``seconds`` is not within 0…:data:`PRERENDER_MAX_S`, or the scene is not a moving
            eye.
        StateConflictError
            An operation holds the hardware, or the scene changed while it was rendered.
        """
        # Imported here: the tracking module imports the service's heavier parts.
        from eyeserver.service.tracking import CAMERA_RATE_HZ

        if not 0 < seconds <= PRERENDER_MAX_S:
            raise ValueError(f"seconds must be within 0…{PRERENDER_MAX_S:g}, not {seconds}")
        unit = self._service.rig.unit(unit_id)
        spec = self._room.scene
        if spec.kind != "eye" or not spec.moving:
            raise ValueError("the scene is not a moving eye (PUT /api/v1/sim/eye with a motion "
                             "places one): nothing to render ahead")
        cameras = [c for c in unit.cameras if isinstance(c, SimCamera)]
        with self._service.idle_moment("render the eye ahead"):
            pass  # not while an operation streams; the rendering itself holds nothing
        started = time.monotonic()
        _log.info("rendering the simulated eye ahead", extra={
            "unit": unit_id, "seconds": seconds, "actor": actor})

        def render(camera: SimCamera) -> object:
            def progress(done: float) -> None:
                _log.info("rendering ahead", extra={"camera_id": camera.id,
                                                    "done_percent": round(100 * done)})
            return camera.prerender(seconds, CAMERA_RATE_HZ, (unit.projector.id,), progress)

        with ThreadPoolExecutor(max(1, len(cameras)), thread_name_prefix="sim-prerender") as pool:
            rendered = list(pool.map(render, cameras))
        period_ns = round(1e9 / CAMERA_RATE_HZ)
        with self._service.idle_moment("render the eye ahead"):
            # The last whole period: the script's clock reads its true time from now on.
            epoch_ns = self._room.clock.now_ns() // period_ns * period_ns
            if any(s is not spec for s in rendered) or not self._room.restart_scene(spec,
                                                                                   epoch_ns):
                raise StateConflictError("the simulated scene changed while it was rendered "
                                         "ahead; render it again")
        frames = math.ceil(seconds * CAMERA_RATE_HZ)
        megabytes = sum(frames * c.width * c.height * (1 if c.bit_depth == 8 else 2)
                        for c in cameras) / 1e6
        took_s = time.monotonic() - started
        _log.info("simulated eye rendered ahead; its script restarts now", extra={
            "unit": unit_id, "frames": frames, "megabytes": round(megabytes), "took_s":
            round(took_s, 1)})
        return {"unit": unit_id, "cameras": [c.id for c in cameras], "seconds": seconds,
                "rate_hz": CAMERA_RATE_HZ, "frames": frames, "megabytes": round(megabytes, 1),
                "took_s": round(took_s, 1)}

    def prerendered(self) -> dict[str, dict[str, int]]:
        """Per camera with frames of the current scene rendered ahead: ``left``, ``used``
        and ``live`` (frames that found none for their time and settings)."""
        return self._room.prerendered()

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
