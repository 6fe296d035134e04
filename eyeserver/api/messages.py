"""The messages of the daemon's WebSocket streams, as pydantic models: what the AsyncAPI
document (:mod:`eyeserver.api.asyncapi`, ``GET /api/v1/asyncapi.json``) describes.

``/api/v1/ws/events`` sends a :class:`Hello`, then every event of the daemon in order (each with
``seq`` increasing by one and ``time``, UTC ISO 8601 with ms); ``/api/v1/ws/pose`` sends a
:class:`PoseMessage` per processed tracking frame, a :class:`HoldMessage` when the daemon holds
the beam without a frame and a :class:`Heartbeat` after a second of silence. Both send
:class:`Dropped` before the next message when a slow reader lost ``count`` of them.

The services build the messages as dicts (the event bus stamps ``type``, ``seq`` and
``time``); these models forbid fields they do not name, so a field added to a message without
its model fails the tests that validate every message a live daemon sends
(tests/test_asyncapi.py).
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field

__all__ = ["EVENT_MESSAGES", "POSE_MESSAGES", "Dropped", "Heartbeat", "Hello", "HoldMessage",
           "PoseMessage"]

Vector = Annotated[list[float], Field(min_length=3, max_length=3)]


class _Message(BaseModel):
    model_config = ConfigDict(extra="forbid", use_attribute_docstrings=True)


class _Event(_Message):
    seq: int = Field(ge=1, description="Increases by one per event of the daemon.")
    time: str = Field(description="UTC, ISO 8601 with milliseconds.",
                      examples=["2026-11-23T15:12:00.123Z"])


class Dropped(_Message):
    """``count`` messages were lost right here because the client read too slowly (the daemon
    keeps ``event_queue_size`` for it); the next event's ``seq`` has moved on by ``count + 1``.
    Before the close 4008 (the client stopped reading) it counts every message the client will
    never get."""

    type: Literal["dropped"]
    count: int = Field(ge=1)


# --- /ws/events ------------------------------------------------------------------------------


class HelloUnit(_Message):
    """A unit's health: ``ok`` or ``fault`` (with the reason)."""

    id: str
    health: str
    reason: str | None


class Hello(_Message):
    """The first message of ``/ws/events``: the daemon as it is. ``last_seq`` is the ``seq`` of
    the event before the first one this connection sends."""

    type: Literal["hello"]
    time: str
    state: Literal["idle", "capturing", "calibrating", "tracking", "fault"]
    units: list[HelloUnit]
    active_calibration_id: str | None
    version: str
    queue_size: int = Field(description="Events kept for a slow reader before the oldest is "
                            "dropped (the setting event_queue_size).")
    last_seq: int


class StateChanged(_Event):
    """The daemon's state changed."""

    type: Literal["state"]
    state: Literal["idle", "capturing", "calibrating", "tracking", "fault"]
    previous: Literal["idle", "capturing", "calibrating", "tracking", "fault"]
    session_id: str | None = Field(None, description="The calibration session that holds (or "
                                   "released) the daemon.")


class DeviceFault(_Event):
    """A device failed; its unit is in fault until it works again."""

    type: Literal["device.fault"]
    device_id: str
    unit: str | None = Field(description="Null for the trigger, which serves every unit.")
    reason: str


class DeviceRecovered(_Event):
    """A device that had failed works again."""

    type: Literal["device.recovered"]
    device_id: str


class CaptureStored(_Event):
    """A capture's bundle and index entry are on disk."""

    type: Literal["capture.stored"]
    capture_id: str
    unit: str
    calibration_id: str | None


class ReconstructionDone(_Event):
    """A capture was reconstructed."""

    type: Literal["reconstruction.done"]
    capture_id: str
    calibration_id: str
    points: int


class CalibrationChanged(_Event):
    """A calibration was imported or activated, by ``actor``."""

    type: Literal["calibration.imported", "calibration.activated"]
    calibration_id: str
    actor: str


class CalibrationCreated(_Event):
    """A guided calibration session's solve stored a new calibration (not activated)."""

    type: Literal["calibration.created"]
    calibration_id: str
    session_id: str
    actor: str


class CalibrationSessionOpened(_Event):
    """A guided calibration session was opened (the daemon is calibrating)."""

    type: Literal["calibration_session.opened"]
    session_id: str
    kind: Literal["stereo", "phase_height"]
    actor: str


class CalibrationSessionView(_Event):
    """A stereo session acquired a chessboard view: where the board was found, and whether the
    session can be solved now."""

    type: Literal["calibration_session.view"]
    session_id: str
    capture_id: str
    found: dict[str, bool]
    ready: bool


class CalibrationSessionPlate(_Event):
    """A phase-to-height session acquired a plate (``reference``: the reference plane) at
    ``z_mm``."""

    type: Literal["calibration_session.plate"]
    session_id: str
    capture_id: str
    z_mm: float
    reference: bool


class JobStateChanged(_Event):
    """A job was queued, started or finished."""

    type: Literal["job.state"]
    job_id: str
    kind: str
    state: Literal["queued", "running", "succeeded", "failed", "cancelled"]
    error: str | None = None


class JobProgress(_Event):
    """A running job's progress (0–1) and what it is doing."""

    type: Literal["job.progress"]
    job_id: str
    kind: str
    progress: float = Field(ge=0, le=1)
    message: str


class PoseMeasured(_Event):
    """A pose measurement was stored (no patient id on the stream: the verdict only)."""

    type: Literal["pose.measured"]
    measurement_id: str
    fraction: int
    passed: bool
    length_mm: float
    gaze_deg: float


class TrackingStarted(_Event):
    """Live tracking started for a fraction on a unit."""

    type: Literal["tracking.started"]
    fraction: int
    unit: str


class TrackingStopped(_Event):
    """Live tracking ended (``error``: why, when it ended by itself)."""

    type: Literal["tracking.stopped"]
    frames_processed: int
    frames_dropped: int
    error: str | None


class QaRunDone(_Event):
    """A daily QA run (or a physicist's baseline) was stored."""

    type: Literal["qa.run"]
    run_id: str
    passed: bool
    calibration_id: str
    baseline: bool


class QaOverridden(_Event):
    """A physicist lifted the daily QA's lockout for the rest of the day."""

    type: Literal["qa.override"]
    override_id: str
    actor: str


class QaOverrideWithdrawn(_Event):
    """A physicist withdrew the QA override in force: a lockout it lifted holds again."""

    type: Literal["qa.override_withdrawn"]
    override_id: str
    actor: str


# --- /ws/pose ----------------------------------------------------------------------------------


class FramePose(_Message):
    """The eye's pose in one tracked frame, WCS, mm."""

    centre_mm: Vector
    """Globe centre."""
    limbus_centre_mm: Vector | None
    gaze: Vector
    """Unit gaze vector."""


class FrameDeviation(_Message):
    """Measured − the fraction's reference, for one tracked frame."""

    delta_mm: Vector
    """ΔX, ΔY, ΔZ of the globe centre, mm, WCS."""
    length_mm: float | None
    gaze_deg: float | None


class PoseMessage(_Event):
    """One processed tracking frame: the pose, its deviation and the beam-hold flag.

    ``beam_hold`` is what a beam controller acts on: true whenever the eye is out of tolerance,
    blinking, lost, fitted below the patient's ``min_confidence``, after a gap of unprocessed
    frames, or until ``dwell_frames`` good frames followed a hold. ``pose`` and ``deviation``
    are null when no eye was fitted (``eye`` says why, ``error`` the reason).
    """

    type: Literal["pose"]
    t: float
    """The frame's mid-exposure time, s, on the rig's monotonic clock."""
    t_ns: int
    frame: int
    """The camera frame number since tracking started (one per camera period)."""
    pose: FramePose | None
    deviation: FrameDeviation | None
    in_tolerance: bool
    beam_hold: bool
    latency_ms: float
    """From mid-exposure to this send, ms."""
    confidence: float
    eye: str
    """What the frame showed of the eye: ``seen``, ``blink``, ``lost``, ..."""
    reasons: list[str]
    """Why the beam is held (empty when it is not)."""
    dropped_frames: int
    """Frames replaced by a newer one before processing, in this session so far."""
    missed_frames: int
    """Camera periods the rig could not serve, in this session so far."""
    delivery_ms: float | None
    """Of ``latency_ms``: until the frames were in the daemon's hands."""
    processing_ms: float
    """Of ``latency_ms``: reconstruction and fit."""
    error: str | None = None


class HoldMessage(_Event):
    """The daemon holds the beam without a frame: ``no_frames`` (nothing came from the rig) or
    ``worker_stalled`` (frames came, none was processed) within ``tracking_deadline_ms``, or
    ``ended`` (the session ended). The beam then stays held until ``dwell_frames`` good frames
    came again."""

    type: Literal["hold"]
    reason: Literal["no_frames", "worker_stalled", "ended"]
    beam_hold: Literal[True]
    at_ns: int
    """When the hold was decided, ns on the rig's clock."""
    last_frame: int
    """The last frame published (-1: none)."""
    silent_ms: float | None = None
    frames_acquired: int | None = None


class Heartbeat(_Message):
    """Sent first on the pose stream, and whenever it has sent nothing for a second. A client
    that hears nothing for longer must take the link as dead and hold the beam."""

    type: Literal["heartbeat"]
    time: str
    tracking: bool
    beam_hold: bool
    stalled: dict[str, Any] | None


EVENT_MESSAGES: tuple[type[BaseModel], ...] = (
    Hello, StateChanged, DeviceFault, DeviceRecovered, CaptureStored, ReconstructionDone,
    CalibrationChanged, CalibrationCreated, CalibrationSessionOpened, CalibrationSessionView,
    CalibrationSessionPlate, JobStateChanged, JobProgress, PoseMeasured, QaRunDone, QaOverridden,
    QaOverrideWithdrawn, TrackingStarted, TrackingStopped, Dropped)
"""What ``/ws/events`` sends."""

POSE_MESSAGES: tuple[type[BaseModel], ...] = (PoseMessage, HoldMessage, Heartbeat, Dropped)
"""What ``/ws/pose`` sends."""
