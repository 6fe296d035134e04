"""The messages of the daemon's two WebSocket streams, and the client's own notices.

``/api/v1/ws/events`` sends a :class:`Hello` (the daemon as it is), then every event of the
daemon in order, each with ``seq`` increasing by one and ``time`` (UTC, ISO 8601 with ms).
``/api/v1/ws/pose`` sends a :class:`PoseMessage` per processed tracking frame, a
:class:`HoldMessage` when the daemon holds the beam without a frame, and a :class:`Heartbeat`
first and after a second of silence. Both send :class:`Dropped` before the next message when a slow
reader lost ``count`` of them.

The OpenAPI document does not describe WebSocket messages; these models follow the daemon's
documentation (README, ``eyeserver/api/routers/events.py`` and ``tracking.py``) and code. A
message of a type not listed here arrives as :class:`Event` (with ``seq``) or :class:`Message`,
its fields kept.

The client adds two notices of its own (type ``client.…``, never sent by the daemon):
:class:`Disconnected` the moment the link is lost, and :class:`Resumed` once it is back, saying
how many messages went by meanwhile. A beam controller must hold the beam on a
:class:`Disconnected` until a :class:`PoseMessage` says otherwise.
"""

from __future__ import annotations

import logging
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, ValidationError

__all__ = [
    "CalibrationCreated",
    "CalibrationEvent",
    "CalibrationSessionOpened",
    "CalibrationSessionPlate",
    "CalibrationSessionView",
    "CaptureStored",
    "DeviceFault",
    "DeviceRecovered",
    "Disconnected",
    "Dropped",
    "Event",
    "EventStreamMessage",
    "FrameDeviation",
    "FramePose",
    "Heartbeat",
    "Hello",
    "HelloUnit",
    "HoldMessage",
    "JobProgress",
    "JobStateChanged",
    "Message",
    "PoseMeasured",
    "PoseMessage",
    "PoseStreamMessage",
    "QaOverridden",
    "QaOverrideWithdrawn",
    "QaRunDone",
    "ReconstructionDone",
    "Resumed",
    "StateChanged",
    "TrackingStarted",
    "TrackingStopped",
    "parse_event_message",
    "parse_pose_message",
]

_log = logging.getLogger("eyeserver_client")

Vector = tuple[float, float, float]


class Message(BaseModel):
    """Any message: its ``type`` and whatever fields it has (kept as they are)."""

    model_config = ConfigDict(extra="allow", use_attribute_docstrings=True)

    type: str


class Event(Message):
    """A daemon event: ``seq`` increases by one per event of the daemon."""

    seq: int
    time: str
    """UTC, ISO 8601 with milliseconds (``2026-11-23T15:12:00.123Z``)."""


class Dropped(Message):
    """``count`` messages were lost right here because this client read too slowly (the daemon
    keeps ``event_queue_size`` for it); the next message's ``seq`` has moved on by
    ``count + 1``. Before the close 4008 (the client stopped reading) it counts every message
    the client will never get."""

    type: Literal["dropped"]
    count: int


# --- /ws/events ------------------------------------------------------------------------------


class HelloUnit(BaseModel):
    """A unit's health in a :class:`Hello`: ``ok`` or ``fault`` (with the reason)."""

    model_config = ConfigDict(extra="allow")

    id: str
    health: str
    reason: str | None = None


class Hello(Message):
    """The first message of ``/ws/events`` (and of every reconnection): the daemon as it is.
    ``last_seq`` is the ``seq`` of the event before the first one this connection sends."""

    type: Literal["hello"]
    time: str
    state: str
    """idle, capturing, calibrating, tracking or fault."""
    units: list[HelloUnit]
    active_calibration_id: str | None = None
    version: str
    queue_size: int
    """Events the daemon keeps for a slow reader before dropping the oldest."""
    last_seq: int


class StateChanged(Event):
    """The daemon's state changed (idle, capturing, calibrating, tracking, fault)."""

    type: Literal["state"]
    state: str
    previous: str
    session_id: str | None = None
    """The calibration session that holds (or released) the daemon."""


class DeviceFault(Event):
    """A device failed; its unit is in fault until it works again."""

    type: Literal["device.fault"]
    device_id: str
    unit: str | None = None
    """Null for the trigger, which serves every unit."""
    reason: str


class DeviceRecovered(Event):
    """A device that had failed works again."""

    type: Literal["device.recovered"]
    device_id: str


class CaptureStored(Event):
    """A capture's bundle and index entry are on disk."""

    type: Literal["capture.stored"]
    capture_id: str
    unit: str
    calibration_id: str | None = None


class ReconstructionDone(Event):
    """A capture was reconstructed."""

    type: Literal["reconstruction.done"]
    capture_id: str
    calibration_id: str
    points: int


class CalibrationEvent(Event):
    """A calibration was imported or activated, by ``actor``."""

    type: Literal["calibration.imported", "calibration.activated"]
    calibration_id: str
    actor: str


class CalibrationCreated(Event):
    """A guided calibration session's solve stored a new calibration (not activated)."""

    type: Literal["calibration.created"]
    calibration_id: str
    session_id: str
    actor: str


class CalibrationSessionOpened(Event):
    """A guided calibration session was opened (the daemon is calibrating)."""

    type: Literal["calibration_session.opened"]
    session_id: str
    kind: str
    actor: str


class CalibrationSessionView(Event):
    """A stereo session acquired a chessboard view."""

    type: Literal["calibration_session.view"]
    session_id: str
    capture_id: str
    found: dict[str, bool]
    ready: bool


class CalibrationSessionPlate(Event):
    """A phase-height session acquired a plate (or, with ``reference``, the reference plane)
    at ``z_mm``."""

    type: Literal["calibration_session.plate"]
    session_id: str
    capture_id: str
    z_mm: float
    reference: bool


class JobStateChanged(Event):
    """A job was queued, started or finished (succeeded, failed, cancelled)."""

    type: Literal["job.state"]
    job_id: str
    kind: str
    state: str
    error: str | None = None


class JobProgress(Event):
    """A running job's progress (0–1) and what it is doing."""

    type: Literal["job.progress"]
    job_id: str
    kind: str
    progress: float
    message: str


class PoseMeasured(Event):
    """A pose measurement was stored (no patient id on the stream: the verdict only)."""

    type: Literal["pose.measured"]
    measurement_id: str
    fraction: int
    passed: bool
    length_mm: float
    gaze_deg: float


class QaRunDone(Event):
    """A daily QA run was stored, passed or not (``baseline``: it became the calibration's QA
    baseline); ``client.qa_run(run_id)`` has its figures."""

    type: Literal["qa.run"]
    run_id: str
    passed: bool
    calibration_id: str
    baseline: bool


class QaOverridden(Event):
    """A physicist lifted the daily QA's lockout for the rest of the day."""

    type: Literal["qa.override"]
    override_id: str
    actor: str


class QaOverrideWithdrawn(Event):
    """A physicist withdrew the QA override in force: a lockout it lifted holds again."""

    type: Literal["qa.override_withdrawn"]
    override_id: str
    actor: str


class TrackingStarted(Event):
    """Live tracking started for a fraction on a unit."""

    type: Literal["tracking.started"]
    fraction: int
    unit: str


class TrackingStopped(Event):
    """Live tracking ended (``error``: why, when it ended by itself)."""

    type: Literal["tracking.stopped"]
    frames_processed: int
    frames_dropped: int
    error: str | None = None


# --- /ws/pose ----------------------------------------------------------------------------------


class FramePose(BaseModel):
    """The eye's pose in one tracked frame, WCS, mm."""

    model_config = ConfigDict(extra="allow", use_attribute_docstrings=True)

    centre_mm: Vector
    """Globe centre."""
    limbus_centre_mm: Vector | None = None
    gaze: Vector
    """Unit gaze vector."""


class FrameDeviation(BaseModel):
    """Measured − the fraction's reference, for one tracked frame."""

    model_config = ConfigDict(extra="allow", use_attribute_docstrings=True)

    delta_mm: Vector
    """ΔX, ΔY, ΔZ of the globe centre, mm, WCS."""
    length_mm: float | None = None
    gaze_deg: float | None = None


class PoseMessage(Event):
    """One processed tracking frame: the pose, its deviation and the beam-hold flag.

    ``beam_hold`` is what a beam controller acts on: true whenever the eye is out of
    tolerance, blinking, lost, fitted below the patient's ``min_confidence``, after a gap of
    unprocessed frames, or until ``dwell_frames`` good frames followed a hold. ``pose`` and
    ``deviation`` are null when no eye was fitted (``eye`` says why: e.g. ``blink``,
    ``lost``; ``error`` the reason).
    """

    type: Literal["pose"]
    t: float
    """The frame's mid-exposure time, s, on the rig's monotonic clock."""
    t_ns: int
    frame: int
    pose: FramePose | None = None
    deviation: FrameDeviation | None = None
    in_tolerance: bool
    beam_hold: bool
    latency_ms: float
    """From mid-exposure to the send, ms."""
    confidence: float
    eye: str
    reasons: list[str]
    """Why the beam is held (empty when it is not)."""
    dropped_frames: int
    """Frames replaced by a newer one before processing, in this session so far."""
    missed_frames: int
    """Camera periods the rig could not serve, in this session so far."""
    delivery_ms: float | None = None
    """Of ``latency_ms``: until the frames were in the daemon's hands."""
    processing_ms: float
    """Of ``latency_ms``: reconstruction and fit."""
    error: str | None = None


class HoldMessage(Event):
    """The daemon holds the beam without a frame: ``no_frames`` (nothing came from the rig)
    or ``worker_stalled`` (frames came, none was processed) within ``tracking_deadline_ms``,
    or ``ended`` (the session ended). The beam then stays held until ``dwell_frames`` good
    frames came again."""

    type: Literal["hold"]
    reason: str
    beam_hold: bool
    at_ns: int
    silent_ms: float | None = None
    last_frame: int | None = None
    frames_acquired: int | None = None


class Heartbeat(Message):
    """Sent first on the pose stream, and whenever it has sent nothing for a second. A client
    that hears nothing for longer must take the link as dead and hold the beam (the pose
    stream of this client does so: :class:`Disconnected`)."""

    type: Literal["heartbeat"]
    time: str
    tracking: bool
    beam_hold: bool
    stalled: dict[str, Any] | None = None


# --- the client's own notices ---------------------------------------------------------------


class Disconnected(Message):
    """The client lost the stream (closed, broken, or silent for longer than allowed); it
    reconnects at the next read. On the pose stream: hold the beam."""

    type: Literal["client.disconnected"] = "client.disconnected"
    reason: str
    last_seq: int | None = None
    """The ``seq`` of the last message received before the loss."""
    beam_hold: Literal[True] = True


class Resumed(Message):
    """The client is connected again after a :class:`Disconnected`.

    ``missed`` is how many messages (by ``seq``) went by while it was away and are lost: 0
    when nothing was, None when it cannot be known (``restarted``: the daemon started anew,
    its ``seq`` too; or no numbered message had come before the loss). The event stream gets
    again the events that went by, as long as the daemon keeps them (its newest 1024), right
    after the :class:`Hello`; the pose stream's messages that went by are gone. For the whole
    picture read ``GET /api/v1/status`` (the :class:`Hello` on ``/ws/events`` has it).
    """

    type: Literal["client.resumed"] = "client.resumed"
    last_seq: int | None = None
    """The last ``seq`` received before the loss."""
    missed: int | None = None
    restarted: bool = False


EventStreamMessage = (
    Hello | Dropped | StateChanged | DeviceFault | DeviceRecovered | CaptureStored
    | ReconstructionDone | CalibrationEvent | CalibrationCreated | CalibrationSessionOpened
    | CalibrationSessionView | CalibrationSessionPlate | JobStateChanged | JobProgress
    | PoseMeasured | QaRunDone | QaOverridden | QaOverrideWithdrawn | TrackingStarted
    | TrackingStopped | Disconnected | Resumed | Event | Message
)
"""What iterating ``/ws/events`` yields."""

PoseStreamMessage = (
    PoseMessage | HoldMessage | Heartbeat | Dropped | Disconnected | Resumed | Event | Message
)
"""What iterating ``/ws/pose`` yields."""

_EVENT_TYPES: dict[str, type[Message]] = {
    "hello": Hello, "dropped": Dropped, "state": StateChanged, "device.fault": DeviceFault,
    "device.recovered": DeviceRecovered, "capture.stored": CaptureStored,
    "reconstruction.done": ReconstructionDone, "calibration.imported": CalibrationEvent,
    "calibration.activated": CalibrationEvent, "calibration.created": CalibrationCreated,
    "calibration_session.opened": CalibrationSessionOpened,
    "calibration_session.view": CalibrationSessionView,
    "calibration_session.plate": CalibrationSessionPlate, "job.state": JobStateChanged,
    "job.progress": JobProgress, "pose.measured": PoseMeasured, "qa.run": QaRunDone,
    "qa.override": QaOverridden, "qa.override_withdrawn": QaOverrideWithdrawn,
    "tracking.started": TrackingStarted, "tracking.stopped": TrackingStopped,
}
_POSE_TYPES: dict[str, type[Message]] = {
    "pose": PoseMessage, "hold": HoldMessage, "heartbeat": Heartbeat, "dropped": Dropped,
}


def _parse(data: dict[str, Any], types: dict[str, type[Message]]) -> Message:
    kind = data.get("type")
    model = types.get(kind) if isinstance(kind, str) else None
    if model is not None:
        try:
            return model.model_validate(data)
        except ValidationError as exc:
            # Not a reason to break a stream: the fields are kept on the generic message.
            _log.warning("a %r message did not match its model (%s); kept as it is", kind,
                         exc.errors()[0].get("msg"))
    generic: type[Message] = Event if isinstance(data.get("seq"), int) else Message
    if not isinstance(kind, str):
        data = {**data, "type": "unknown"}
    return generic.model_validate(data)


def parse_event_message(data: dict[str, Any]) -> Message:
    """A decoded ``/ws/events`` message as its model (:data:`EventStreamMessage`)."""
    return _parse(data, _EVENT_TYPES)


def parse_pose_message(data: dict[str, Any]) -> Message:
    """A decoded ``/ws/pose`` message as its model (:data:`PoseStreamMessage`)."""
    return _parse(data, _POSE_TYPES)
