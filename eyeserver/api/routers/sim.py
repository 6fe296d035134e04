"""``/api/v1/sim/…``: the simulated room, for demonstrations and tests.

Place a scene, move the flat plate on the simulated stage, place the calibration chessboard,
read the scene's ground truth, unplug and replug a simulated device. The routes are always
there, but a daemon that drives real hardware answers every one of them 404 with the reason.
Ground truth goes to people and tests only; the measurement path never sees it.

Roles: any token (operator and up) may read the scene and its truth and place scenes, the stage
and the chessboard, as one would in a demonstration; unplugging a device breaks the rig for
everyone, so it needs the physicist role. Scene changes answer 409 while the hardware is busy.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, HTTPException, Query
from pydantic import BaseModel, ConfigDict, Field
from starlette.concurrency import run_in_threadpool

from eyeserver.api.auth import OperatorDep, PhysicistDep
from eyeserver.api.deps import ServiceDep
from eyeserver.api.schemas import ErrorResponse
from eyeserver.core.validation import NumbersOnly
from eyeserver.hardware.sim.motion import GazeAngle, MotionSpec
from eyeserver.hardware.sim.scenes import Position, Rotation, SceneSpec
from eyeserver.service.simroom import PRERENDER_MAX_S, STAGE_TRAVEL_MM, SimRoomControl

__all__ = ["NO_SIM_ROOM", "router"]

NO_SIM_ROOM = "the daemon drives real hardware: there is no simulated room"
"""The reason of the 404 every route answers on a daemon without a simulated room."""

_NOT_SIMULATED: dict[int | str, dict[str, Any]] = {
    404: {"model": ErrorResponse, "description": "The daemon drives real hardware."}}
_BUSY: dict[int | str, dict[str, Any]] = {
    409: {"model": ErrorResponse, "description": "The hardware is busy; the reason names the "
          "daemon's state."}}

router = APIRouter(prefix="/sim", tags=["simulated room"], responses=_NOT_SIMULATED)


async def _sim_room(service: ServiceDep) -> SimRoomControl:
    control = SimRoomControl.of(service)
    if control is None:
        raise HTTPException(404, NO_SIM_ROOM)
    return control


SimRoomDep = Annotated[SimRoomControl, Depends(_sim_room)]


class StagePosition(NumbersOnly):
    """Where the simulated motorised stage puts the flat calibration plate."""

    model_config = ConfigDict(extra="forbid")

    z_mm: float = Field(ge=STAGE_TRAVEL_MM[0], le=STAGE_TRAVEL_MM[1],
                        description="Z of the plate's surface in the WCS, within the stage's "
                        f"travel {STAGE_TRAVEL_MM[0]}…{STAGE_TRAVEL_MM[1]} mm; the plate stays "
                        "normal to Z, centred on the axis.", examples=[10.0])


class ChessboardPose(NumbersOnly):
    """Where the calibration chessboard stands (the room's default board)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    position_mm: Position = Field((0.0, 0.0, 0.0), description="The board's centre in the WCS, "
                              "mm; at the origin and unrotated it is the origin board.",
                              examples=[(0.0, 0.0, 5.0)])
    rotation_deg: Rotation = Field((0.0, 0.0, 0.0), description="Rotation about X, Y, Z, degrees "
                               "(applied Rz·Ry·Rx, board → world).", examples=[(20.0, 0.0, 0.0)])


class SimDeviceRequest(BaseModel):
    """The cable of a simulated device."""

    model_config = ConfigDict(extra="forbid")

    connected: bool = Field(description="false unplugs the device, true plugs it back in.")


class SimDeviceResponse(BaseModel):
    """A simulated device's cable after the change."""

    id: str = Field(examples=["S3"])
    kind: Literal["camera", "projector", "trigger"]
    connected: bool = Field(description="Whether it is plugged in. A device plugged back in "
                            "works again once the next operation has reopened it.")


@router.get("/scene", summary="The simulated scene")
async def get_scene(room: SimRoomDep) -> SceneSpec:
    """What stands in front of the cameras now (``position_mm`` null: the kind's default)."""
    return room.scene


@router.put("/scene", summary="Place a simulated scene", responses=_BUSY)
async def put_scene(spec: SceneSpec, room: SimRoomDep, caller: OperatorDep) -> SceneSpec:
    """Replace the scene: a kind (empty, chessboard, plate, reference, pyramid, wedge,
    eye_phantom_1, eye_phantom_2, eye), its pose and parameters (the eye's anatomy, gaze and
    motion). A moving eye's script starts now. 409 while the hardware is busy."""
    return await run_in_threadpool(lambda: room.place(spec, actor=caller.name))


@router.put("/stage", summary="Move the flat plate", responses=_BUSY)
async def put_stage(position: StagePosition, room: SimRoomDep, caller: OperatorDep,
                    ) -> SceneSpec:
    """The simulated motorised stage puts the flat calibration plate at ``z_mm`` (the scene
    becomes that plate); 422 beyond the stage's travel, 409 while the hardware is busy."""
    return await run_in_threadpool(lambda: room.move_stage(position.z_mm, actor=caller.name))


@router.put("/chessboard", summary="Place the calibration chessboard", responses=_BUSY)
async def put_chessboard(pose: ChessboardPose, room: SimRoomDep, caller: OperatorDep,
                         ) -> SceneSpec:
    """Put the calibration chessboard in the given pose (the scene becomes that board); 409
    while the hardware is busy."""
    return await run_in_threadpool(lambda: room.place_chessboard(
        pose.position_mm, pose.rotation_deg, actor=caller.name))


class SimEyeRequest(NumbersOnly):
    """The patient eye's pose, anatomy or motion; fields left out keep their current values."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    position_mm: Position | None = Field(None, description="The globe centre at rest, WCS, mm "
                                     "(default eye: (0, 0, -10)).", examples=[(0.5, 0.0, -10.0)])
    rotation_deg: Rotation | None = Field(None, description="The head's rotation about X, Y, Z, "
                                      "degrees (Rz·Ry·Rx).")
    gaze_deg: tuple[GazeAngle, GazeAngle] | None = Field(None, description="(yaw towards +X, pitch "
                                                 "towards +Y) of the gaze, degrees.",
                                                 examples=[(2.0, -1.0)])
    globe_radius_mm: float | None = Field(None, gt=5, lt=20)
    cornea_radius_mm: float | None = Field(None, gt=4, lt=15)
    limbus_diameter_mm: float | None = Field(None, gt=6, lt=16)
    motion: MotionSpec | None = Field(None, description="Drift, saccades, blinks and scripted "
                                      "events (saccade, blink, shift) from now; null stops the "
                                      "motion, leaving it out keeps the current one.")


class SimEyeResponse(BaseModel):
    """The eye scene and the eye's true pose now (ground truth: for people and tests)."""

    scene: SceneSpec
    t_s: float = Field(description="Seconds since the scene was placed (a script's clock).")
    eye: dict[str, Any] = Field(description="centre_mm, gaze, limbus_centre_mm, "
                                "globe_radius_mm, cornea_radius_mm, openness (WCS, mm).")


@router.get("/eye", summary="The simulated patient eye",
            responses={409: {"model": ErrorResponse, "description": "The scene is not the "
                             "patient eye."}})
async def get_eye(room: SimRoomDep) -> SimEyeResponse:
    """The eye scene and where the eye is and looks now (its motion evaluated at this time)."""
    return SimEyeResponse.model_validate(await run_in_threadpool(room.eye_truth))


@router.put("/eye", summary="Pose or move the simulated patient eye", responses=_BUSY)
async def put_eye(request: SimEyeRequest, room: SimRoomDep, caller: OperatorDep,
                  ) -> SimEyeResponse:
    """Place the patient eye (the scene becomes the eye if it was not): its position, gaze and
    globe parameters, or a motion script (MotionSpec) that starts now. Fields left out keep
    their current values; ``"motion": null`` stops the motion. 422 for an impossible eye, 409
    while the hardware is busy; live tracking goes on with the eye moved under it (the scene
    must be the eye already)."""
    given = request.model_fields_set
    eye = {name: getattr(request, name) for name in
           ("gaze_deg", "globe_radius_mm", "cornea_radius_mm", "limbus_diameter_mm")
           if getattr(request, name) is not None}
    if "motion" in given:
        eye["motion"] = request.motion

    def place() -> dict[str, Any]:
        try:
            room.place_eye(position_mm=request.position_mm, rotation_deg=request.rotation_deg,
                           eye=eye, actor=caller.name)
        except ValueError as exc:
            raise HTTPException(422, str(exc)) from None
        return room.eye_truth()

    return SimEyeResponse.model_validate(await run_in_threadpool(place))


class PrerenderRequest(BaseModel):
    """Which unit's cameras render the moving eye ahead, and for how long."""

    model_config = ConfigDict(extra="forbid")

    unit: str = Field(description="The unit that will track (the treated eye's side).",
                      examples=["left"])
    seconds: float = Field(gt=0, le=PRERENDER_MAX_S, description="Seconds of the eye's "
                           "script to render, from its restart (≈ 16 MB of memory a second "
                           "for two 8-bit cameras).", examples=[65.0])


class PrerenderResponse(BaseModel):
    """What was rendered ahead; the eye's script restarted when it was done."""

    unit: str
    cameras: list[str]
    seconds: float
    rate_hz: float = Field(description="Frames a second, at whole camera periods of the clock.")
    frames: int = Field(description="Frames rendered per camera.")
    megabytes: float = Field(description="Memory the frames hold until they are used.")
    took_s: float = Field(description="How long the rendering took.")


@router.post("/eye/prerender", summary="Render the moving eye ahead for live tracking",
             responses={**_BUSY, 422: {"model": ErrorResponse, "description": "No such unit, "
                                       "or the scene is not a moving eye."}})
async def post_prerender(request: PrerenderRequest, room: SimRoomDep, caller: OperatorDep,
                         ) -> PrerenderResponse:
    """Render what the unit's cameras will see of the moving eye (PUT /sim/eye with a motion)
    over its next ``seconds``, at the camera rate, before answering (≈ 0.3–0.5 s of work a
    second of script on a 2-core machine; progress in the daemon's log), then restart the
    eye's script. Live
    tracking with that unit then takes these frames instead of rendering each on the cores it
    runs on, as real cameras' frames cost the host nothing: it measures what the daemon
    itself adds. Frames at other times or settings, or after the end, render as usual; any
    scene change forgets them. 409 while the hardware is busy."""
    def render() -> dict[str, Any]:
        try:
            return room.prerender_eye(request.unit, request.seconds, actor=caller.name)
        except KeyError:
            raise HTTPException(422, f"the rig has no unit {request.unit!r}") from None
        except ValueError as exc:
            raise HTTPException(422, str(exc)) from None

    return PrerenderResponse.model_validate(await run_in_threadpool(render))


@router.get("/eye/prerender", summary="What is left of the frames rendered ahead")
async def get_prerender(room: SimRoomDep) -> dict[str, dict[str, int]]:
    """Per camera with frames of the current scene rendered ahead: ``left`` (not yet taken),
    ``used`` (frames that took one) and ``live`` (frames rendered at once: none for their time
    or settings). Empty when nothing was rendered ahead of this scene."""
    return room.prerendered()


@router.get("/truth", summary="The scene's ground truth")
async def get_truth(
    room: SimRoomDep,
    t_s: Annotated[float | None, Query(description="Clock time in seconds (a frame's t_ns / "
                                       "1e9) for a moving eye; default: now.")] = None,
) -> dict[str, Any]:
    """The ground truth of the current scene, the document ``eyeserver sim render`` writes as
    ``truth.json``: the scene, fiducial centres, the eye's pose, surfaces and the devices' true
    optics. For people and tests; the measurement path never sees it."""
    return await run_in_threadpool(room.truth, t_s)


@router.put("/devices/{device_id}", summary="Unplug or replug a simulated device",
            responses={404: {"model": ErrorResponse, "description": "No such simulated device, "
                             "or the daemon drives real hardware."}})
async def put_device(device_id: str, cable: SimDeviceRequest, room: SimRoomDep,
                     caller: PhysicistDep) -> SimDeviceResponse:
    """Fault injection for demonstrations: an unplugged device makes the next operation that
    needs it fail (503) and its unit go into fault; plugged back in, the next operation reopens
    it and the daemon recovers. Allowed at any time, as pulling a real cable is. Physicists
    only."""
    try:
        kind = await run_in_threadpool(lambda: room.set_connected(
            device_id, cable.connected, actor=caller.name))
    except KeyError:
        raise HTTPException(404, f"no simulated device with id {device_id!r}") from None
    return SimDeviceResponse.model_validate(
        {"id": device_id, "kind": kind, "connected": cable.connected})
