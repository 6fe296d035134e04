"""``/api/v1/tracking`` and ``/api/v1/ws/pose``: live tracking of the patient's eye.

``POST /tracking/start`` starts tracking a patient's eye for a fraction (operator): the rig
streams the patient's unit at the camera rate and every frame the pipeline keeps up with is
reconstructed, fitted and compared with the fraction's reference
(:mod:`eyeserver.service.tracking`); the daemon is ``tracking`` meanwhile (captures get 409).
While the daily QA locks tracking (:mod:`eyeserver.api.routers.qa`), ``POST /tracking/start``
answers 409 with the reason. ``POST /tracking/stop`` ends it; ``GET /tracking`` counts frames
acquired, processed, dropped (newest frame wins) and missed, and holds the last message.
``GET /tracking/preview/{camera}.jpg`` is the newest frame a camera of the tracked unit gave the
session, for people to watch.

``/ws/pose`` sends a heartbeat at once (whether tracking runs and the beam is held), then every
processed frame's message as JSON text, a ``hold`` message when the daemon holds the beam
without a frame, and a heartbeat whenever it has sent nothing for a second;
authenticate as for
``/ws/events`` (``?token=`` or ``Authorization: Bearer``; otherwise closed with 1008 before any
message). Each message is ``{"type": "pose", "seq", "time", "t", "t_ns", "frame", "pose",
"deviation", "in_tolerance", "beam_hold", "latency_ms", "confidence", "eye", "reasons",
"dropped_frames", "missed_frames", "delivery_ms", "processing_ms"}``: ``t`` is the frame's
mid-exposure time (seconds on the rig's monotonic clock), ``latency_ms`` the time from it to this
send, of which ``delivery_ms`` until the frames were in the daemon's hands and ``processing_ms``
the reconstruction and fit. ``{"type": "hold", "reason", "beam_hold": true, "at_ns",
...}`` says the beam is held without a frame: ``no_frames`` (no frame from the rig) or
``worker_stalled`` (frames, but none processed) when no processed frame was published for the
setting ``tracking_deadline_ms`` (80 ms: two camera periods; then also ``silent_ms``,
``last_frame``, ``frames_acquired``), ``ended`` when the session ended; the beam then stays held
until ``dwell_frames`` good frames came again. ``{"type": "heartbeat", "time", "tracking",
"beam_hold", "stalled"}`` comes first and whenever nothing else was sent for a second: a client
that hears nothing for longer must take the link as dead and hold the beam. A client
that reads too slowly loses its oldest messages (at most ``event_queue_size`` are kept for it)
and gets ``{"type": "dropped", "count": n}`` before the next one, as on ``/ws/events``; it never
slows the daemon or the other clients. One whose socket accepts nothing for ``ws_stall_s`` gets a
last notice and the close code 4008, as there.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Depends, HTTPException, Request, Response, WebSocket
from pydantic import BaseModel, ConfigDict, Field
from starlette.concurrency import run_in_threadpool

from eyeserver.api.auth import OperatorDep
from eyeserver.api.routers.qa import QA_LOCKED, qa_gate
from eyeserver.api.schemas import ErrorResponse
from eyeserver.api.streaming import opened, stream
from eyeserver.service.events import event_time
from eyeserver.service.patients import PATIENT_ID_PATTERN
from eyeserver.service.preview import camera_jpeg
from eyeserver.service.tracking import TrackingControl

__all__ = ["HEARTBEAT_S", "PREVIEW_MAX_SIDE_PX", "router", "ws_router"]

HEARTBEAT_S = 1.0
"""``/ws/pose`` sends a heartbeat when it has sent nothing for this long (seconds)."""

router = APIRouter(prefix="/tracking", tags=["tracking"])
ws_router = APIRouter(tags=["tracking"])

async def get_tracking(request: Request) -> TrackingControl:
    """The daemon's live tracking (503 while it is not running)."""
    tracking = getattr(request.app.state, "tracking", None)
    if not isinstance(tracking, TrackingControl):
        raise HTTPException(status_code=503, detail="the daemon is not running")
    return tracking


TrackingDep = Annotated[TrackingControl, Depends(get_tracking)]


class TrackingStart(BaseModel):
    """Whom to track, and how the beam hold behaves."""

    model_config = ConfigDict(extra="forbid")

    patient_id: str = Field(pattern=PATIENT_ID_PATTERN, examples=["P-0001"])
    fraction: int = Field(ge=1, le=1000, examples=[3])
    dwell_frames: int = Field(3, ge=1, le=250, description="Good frames in a row before the "
                              "beam hold falls.")
    hold_on_drop: bool = Field(True, description="Hold the beam (and restart the dwell) when "
                               "more than two frames went unprocessed before a processed one "
                               "(shorter gaps are counted, not held).")


class TrackingStatus(BaseModel):
    """The running or last tracking session."""

    model_config = ConfigDict(extra="allow")

    running: bool
    started: str | None
    stopped: str | None
    frames_acquired: int = Field(description="Camera frames acquired.")
    frames_processed: int = Field(description="Frames reconstructed and fitted (one message "
                                  "each on /ws/pose).")
    frames_dropped: int = Field(description="Frames acquired but replaced by a newer one "
                                "before processing (the newest frame wins).")
    frames_missed: int = Field(description="Camera periods the rig could not serve in time.")
    frames_held: int = Field(description="Processed frames with the beam held.")
    beam_hold: bool
    stalled: dict[str, Any] | None = Field(None, description="While no processed frame came "
                                           "within the deadline: its reason (no_frames, "
                                           "worker_stalled), since when, and the silence (ms).")
    stalls: int = Field(0, description="Times the deadline passed without a processed frame.")
    deadline_ms: float | None = Field(None, description="The fail-safe's deadline.")
    error: str | None = Field(description="Why the session ended by itself, if it did.")
    last_message: dict[str, Any] | None = Field(description="The last pose message.")


_RESPONSES: dict[int | str, dict[str, Any]] = {
    404: {"model": ErrorResponse, "description": "No such patient, or the fraction has no "
          "reference pose."},
    409: {"model": ErrorResponse, "description": "No active calibration, the daemon is "
          f"busy (already tracking, capturing, calibrating), or {QA_LOCKED}."},
}


@router.post("/start", status_code=201, summary="Start live tracking", responses=_RESPONSES,
             dependencies=[Depends(qa_gate("tracking"))])
async def start(body: TrackingStart, tracking: TrackingDep, caller: OperatorDep,
                ) -> TrackingStatus:
    """Stream the patient's unit at the camera rate, reconstruct and fit each frame it keeps up
    with, compare with the fraction's reference and publish on ``/api/v1/ws/pose``."""
    status = await run_in_threadpool(lambda: tracking.start(
        body.patient_id, body.fraction, actor=caller.name, dwell_frames=body.dwell_frames,
        hold_on_drop=body.hold_on_drop))
    return TrackingStatus.model_validate(status)


@router.post("/stop", summary="Stop live tracking",
             responses={409: {"model": ErrorResponse, "description": "Not tracking."}})
async def stop(tracking: TrackingDep, caller: OperatorDep) -> TrackingStatus:
    """End the session (the frame being processed finishes); the daemon returns to idle."""
    return TrackingStatus.model_validate(
        await run_in_threadpool(lambda: tracking.stop(actor=caller.name)))


@router.get("", summary="Live tracking status")
async def status(tracking: TrackingDep) -> TrackingStatus:
    """Frames acquired, processed, dropped and missed, the beam hold and the last message."""
    return TrackingStatus.model_validate(await run_in_threadpool(tracking.status))


PREVIEW_MAX_SIDE_PX = 640
"""A preview's longer side at most (pixels): enough for the therapist's screen."""


@router.get("/preview/{camera}.jpg", summary="The tracked unit's newest camera image",
            response_class=Response,
            responses={200: {"content": {"image/jpeg": {}},
                             "description": "The newest frame of that camera the tracking "
                             "session acquired, as a grey JPEG (no extra exposure: the frame "
                             "the pose is measured from). Headers ``X-Frame`` (the camera frame "
                             "number since tracking started) and ``X-Frame-Time-Ns`` "
                             "(mid-exposure, ns on the rig's clock)."},
                       404: {"model": ErrorResponse, "description": "The camera is not one of "
                             "the tracked unit's."},
                       409: {"model": ErrorResponse, "description": "Not tracking, or no frame "
                             "acquired yet."}})
async def preview(camera: str, tracking: TrackingDep) -> Response:
    """The tracked unit's live view for people, at whatever rate the client polls (a few per
    second is plenty; the frame is the one tracking already has, so polling costs the stream
    nothing but the JPEG encoding, off the event loop)."""
    try:
        frame, number = tracking.newest_frame(camera)
    except KeyError:
        raise HTTPException(status_code=404, detail=f"camera {camera!r} is not one of the "
                            "tracked unit's") from None
    jpeg = await run_in_threadpool(lambda: camera_jpeg(
        frame.image, bit_depth=frame.meta.bit_depth, max_side_px=PREVIEW_MAX_SIDE_PX))
    return Response(jpeg, media_type="image/jpeg", headers={
        "Cache-Control": "no-store", "X-Frame": str(number),
        "X-Frame-Time-Ns": str(frame.meta.t_ns)})


@ws_router.websocket("/ws/pose", name="pose")
async def stream_pose(websocket: WebSocket) -> None:
    """Send every processed frame's pose message until the client leaves."""
    found = await opened(websocket, "tracking", TrackingControl)
    if found is None:
        return
    tracking, settings = found
    clock = tracking.clock

    def stamped(message: dict[str, Any]) -> dict[str, Any]:
        t_ns = message.get("t_ns")
        if not isinstance(t_ns, int):
            return message
        # Measured here, at the send, on the rig's clock: what the beam controller sees.
        return {**message, "latency_ms": (clock.now_ns() - t_ns) / 1e6}

    def heartbeat() -> dict[str, Any]:
        status = tracking.status()
        return {"type": "heartbeat", "time": event_time(), "tracking": status["running"],
                "beam_hold": status["beam_hold"], "stalled": status["stalled"]}

    with tracking.messages.subscribe(settings.event_queue_size) as subscription:
        await websocket.accept()
        # A heartbeat first: a client that just connected knows at once whether tracking runs
        # and the beam is held, as /ws/events's hello tells its state.
        await stream(websocket, subscription, first=[heartbeat()], prepare=stamped,
                     heartbeat=(HEARTBEAT_S, heartbeat), stall_s=settings.ws_stall_s)
