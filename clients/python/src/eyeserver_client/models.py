"""The API's resources as pydantic models, generated from the daemon's OpenAPI document.

Do not edit: ``python clients/python/scripts/generate_models.py`` writes this file from the
daemon's document (``--check`` says whether it is current; the client's tests fail when it is
not). Request bodies refuse unknown fields, as the daemon does; answers keep fields this
client does not know (``model_extra``), so a newer daemon that adds some does not break it.
Units are in the field names where they are not mm or rad (``_deg``, ``_px``, ``_s``, ``_us``).
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from eyeserver_client.extras import (
    Deviation,
    Evidence,
    FittedPose,
    MeasuredReference,
    ReferencePose,
)

__all__ = [
    "AuditLine",
    "AuditList",
    "Board",
    "CalibrationList",
    "CalibrationResponse",
    "CameraSurface",
    "CaptureList",
    "CaptureRequest",
    "CaptureResponse",
    "ChessboardPose",
    "DeviceResponse",
    "DeviceSettingsRequest",
    "DicomPlanResponse",
    "EllipsoidSpec",
    "ErrorResponse",
    "Extent",
    "EyeModelList",
    "EyeModelResponse",
    "EyeModelSpec",
    "EyeSpec",
    "HealthResponse",
    "JobList",
    "JobResponse",
    "MeasureRequest",
    "Measurement",
    "MeasurementList",
    "MotionSpec",
    "PatientRequest",
    "PatientResponse",
    "PlateRequest",
    "PrerenderRequest",
    "PrerenderResponse",
    "QaFigure",
    "QaOverride",
    "QaOverrideRequest",
    "QaRun",
    "QaRunList",
    "QaRunRequest",
    "QaStatus",
    "QaTrend",
    "QaTrendPoint",
    "QaTrends",
    "ReconstructionBatch",
    "ReconstructionRequest",
    "ReconstructionResponse",
    "ReferenceList",
    "ReferencePoseSpec",
    "ReferenceRequest",
    "ReferenceResponse",
    "SceneSpec",
    "ScriptEvent",
    "SessionRequest",
    "SimDeviceRequest",
    "SimDeviceResponse",
    "SimEyeRequest",
    "SimEyeResponse",
    "StagePosition",
    "StatusResponse",
    "TrackingStart",
    "TrackingStatus",
    "TrackingSummary",
    "UnitResponse",
    "ViewRequest",
    "WhoAmIResponse",
]


class _Answer(BaseModel):
    """Base of what the daemon answers: fields it adds later are kept, not refused."""

    model_config = ConfigDict(extra="allow", use_attribute_docstrings=True)


class _Body(BaseModel):
    """Base of request bodies: unknown fields are refused, as the daemon refuses them."""

    model_config = ConfigDict(extra="forbid", use_attribute_docstrings=True)


class AuditLine(_Answer):
    """One audited action, as its line in the audit file says."""

    time: str
    """UTC, ISO 8601 with milliseconds."""
    seq: int | None = None
    """The store's audit row; null for a failed action, which changed nothing."""
    actor: str
    """The token holder's name, or the daemon's own actor (eyeserver, retention)."""
    role: str
    """operator, physicist, or system for the daemon's actors."""
    action: str
    target: str
    """The capture, calibration or device acted on."""
    detail: dict[str, Any] | None = None
    """What else was recorded (patient ids hashed)."""
    outcome: Literal["ok", "error", "denied"]


class AuditList(_Answer):
    """The newest audit entries, newest first."""

    items: list[AuditLine]


class Board(_Body):
    """The chessboard held in front of the cameras (FORMATS.md)."""

    cols: int = 9
    """Inner corners per row."""
    rows: int = 6
    """Inner corners per column; one of cols and rows is odd, the other even."""
    square_mm: float = 4.5
    """Side of one square, mm."""


class CalibrationResponse(_Answer):
    """A calibration kept in the store."""

    id: str
    """Calibration id; sorts in order of import."""
    created: str
    """When it was computed (its calibration.json)."""
    imported: str
    """UTC import time, ISO 8601 with milliseconds."""
    active: bool
    """Whether captures and reconstructions use it now."""
    source: str
    """Where it came from: who uploaded it and the archive's SHA-256, or the directory it was
    imported from."""
    status: Literal["ok", "missing"]
    """'missing' when start-up recovery found the index row without its files."""
    quality: dict[str, Any]
    """The quality figures of its calibration.json (reprojection errors, phase-to-height residuals);
    empty when it has none."""
    version: int | None = None
    """Its place in the order of creation in this store (1 for the first); calibrations are
    immutable, so a version always means the same data."""
    parent_id: str | None = None
    """The calibration whose geometry a phase-to-height calibration extends (lineage.parent_id of
    its calibration.json); null for a stereo calibration or an upload without one."""
    session_id: str | None = None
    """The guided calibration session that made it, if any."""


class CalibrationList(_Answer):
    """Every stored calibration, newest first."""

    items: list[CalibrationResponse]


class CameraSurface(_Answer):
    """What one camera contributed to a reconstruction."""

    frame: int
    """The bundle frame its image comes from."""
    points: int
    """Points it measured before fusion."""
    partner: str | None
    """The camera that fixed its fringe order: its unit's other camera, or another unit's for a unit
    blind to the order; null when a depth prior did."""
    fringe_order: dict[str, int]
    """Points per source that fixed their fringe order."""
    method: str | None = None
    """The fringe-order method its unit used (null in reconstructions made before it was recorded).
    """
    method_reason: str | None = None
    """Why that method."""
    fringe_pixels: int | None = None
    """Its pixels that see a fringe."""
    coverage: float | None = None
    """The share of those that gave a point."""


class CaptureResponse(_Answer):
    """A stored capture (its bundle is durable on disk)."""

    id: str
    """Capture id; sorts in order of creation."""
    kind: str
    """Bundle kind (FORMATS.md)."""
    unit: str
    """The unit captured, or 'all'."""
    calibration_id: str | None
    """The calibration active when it was taken."""
    created: str
    """UTC creation time, ISO 8601 with milliseconds."""
    frame_count: int
    """Frames in the bundle: one per unit."""
    status: Literal["ok", "missing"]
    """'missing' when start-up recovery found the index row without its bundle."""


class CaptureList(_Answer):
    """One page of captures, newest first."""

    items: list[CaptureResponse]
    total: int
    """Captures matching the filter over all pages."""
    limit: int
    offset: int


class CaptureRequest(_Body):
    """Capture one frame set."""

    unit: str
    """A unit id, or 'all' for every unit, interleaved (one trigger pulse per unit)."""


class ChessboardPose(_Body):
    """Where the calibration chessboard stands (the room's default board)."""

    position_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """The board's centre in the WCS, mm; at the origin and unrotated it is the origin board."""
    rotation_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Rotation about X, Y, Z, degrees (applied Rz·Ry·Rx, board → world)."""


class DeviceResponse(_Answer):
    """One device of the rig and its health."""

    id: str
    """Device id from the rig configuration."""
    kind: str
    """camera, projector or trigger."""
    driver: str
    """Driver that runs it."""
    unit: str | None
    """The unit it belongs to; null for the trigger, which serves every unit."""
    open: bool
    """Whether the device is open."""
    health: Literal["ok", "fault"]
    """'fault' after the device failed, until it works again."""
    reason: str | None
    """Why it is in fault; null when ok."""
    details: dict[str, Any]
    """The driver's own description: current settings, sizes."""


class DeviceSettingsRequest(_Body):
    """New settings for one device; fields left out (or null) stay as they are.

    Projectors take ``enabled`` and ``intensity``, cameras ``exposure_us`` and ``gain_db``; a
    field that does not apply to the device's kind is refused (422), as is a value outside the
    device's range."""

    enabled: bool | None = None
    """Projector: whether it may light."""
    intensity: float | None = None
    """Projector: relative drive level, 0 (dark) to 1 (full current)."""
    exposure_us: float | None = None
    """Camera: exposure time in microseconds."""
    gain_db: float | None = None
    """Camera: analogue gain in dB (0 dB = unity)."""


class EllipsoidSpec(_Body):
    """The anterior segment as an ellipsoid (from MRI)."""

    centre_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Centre in the imaging (MRI) frame, kept for the record; the fit finds where the eye is in the
    room."""
    semi_axes_mm: tuple[float, float, float]
    """Semi-axes a, b, c, mm."""
    orientation: tuple[
        tuple[float, float, float],
        tuple[float, float, float],
        tuple[float, float, float],
    ] = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    """Rotation from the ellipsoid's axes to the WCS as three rows; its columns are the semi-axes'
    directions. Must be a rotation (orthonormal, determinant +1)."""


class EyeModelSpec(_Body):
    """A patient's eye model as imported: a sphere, an ellipsoid, or population defaults.

    ``{}`` is the population model: the globe's radius is fitted, cornea 7.8 mm, limbus 11.7 mm.
    Give ``globe_radius_mm`` for a spherical globe of known size, or ``ellipsoid`` for the
    MRI-derived anterior segment (not both)."""

    globe_radius_mm: float | None = None
    """A spherical globe's radius, mm; null: fitted."""
    ellipsoid: EllipsoidSpec | None = None
    """The anterior segment's ellipsoid; null: a sphere."""
    cornea_radius_mm: float = 7.8
    """Anterior corneal radius of curvature, mm."""
    limbus_diameter_mm: float = 11.7
    """Limbus (white-to-white) diameter, mm."""
    globe_sd_mm: float | None = None
    """The sd of globe_radius_mm or of each ellipsoid semi-axis (the MRI's measurement error), mm;
    null: 0.2 mm, the typical MRI error. It moves the fitted centre along the gaze, counts
    against a planned reference and cancels from one captured at set-up with the same model."""
    source: str | None = None
    """Where the model comes from (free text, e.g. the MRI study)."""


class EyeModelResponse(_Answer):
    """One version of a patient's eye model."""

    version: int
    """1, 2, …: the newest is used."""
    created: str
    actor: str
    population: bool
    """True when the globe's shape is not given (fitted)."""
    model: EyeModelSpec


class ReferenceResponse(_Answer):
    """One version of a fraction's reference pose."""

    fraction: int
    version: int
    created: str
    actor: str
    source: Literal["plan", "capture"]
    plan: str | None
    pose: ReferencePose
    """centre_mm, gaze (unit vector), limbus_centre_mm (or null), WCS."""
    evidence: dict[str, Any] | None
    """For a captured reference: capture_id, unit, calibration_id, eye_model_version, fit."""


class DicomPlanResponse(_Answer):
    """What an import of the plan's DICOM stored, and what it read."""

    eye_model: EyeModelResponse
    """The new eye-model version."""
    reference: ReferenceResponse | None
    """The fraction's new reference version; null when none was set (see notes)."""
    read: dict[str, Any]
    """planned_eye (the structure set's UID, the ROIs used and their fits in its frame, mm),
    registration_uid, wcs_frame_of_reference_uid, notes (what was not set, why)."""


class ErrorResponse(_Answer):
    """Body of every error the API reports on purpose."""

    detail: str
    """Why the request failed, in words meant for a person."""
    errors: list[dict[str, Any]] | None = None
    """For a request that failed validation (422): each problem with its location (loc), message
    (msg) and type, as pydantic reports it; null otherwise."""


class Extent(_Answer):
    """The bounding box of a point cloud, in mm (world coordinates)."""

    min: list[float]
    max: list[float]


class EyeModelList(_Answer):
    """Every eye-model version of a patient, oldest first."""

    items: list[EyeModelResponse]


class ScriptEvent(_Body):
    """One scripted event: a gaze shift (saccade) or a blink starting at ``t_s``."""

    t_s: float
    kind: Literal["saccade", "blink", "shift"]
    gaze_deg: tuple[float, float] = (0.0, 0.0)
    """saccade target (yaw, pitch) relative to the base gaze"""
    shift_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """'shift': new head offset relative to the base position"""
    duration_s: float = 0.03


class MotionSpec(_Body):
    """How the simulated eye moves. All zero rates and no script: a still eye.

    Every number is finite and bounded (an eye's rates and amplitudes, with room to spare): an
    unbounded saccade rate held memory for every saccade time, an infinite one broke every
    capture until the scene was replaced (issue 35)."""

    seed: int = 0
    drift_deg: float = 0.05
    """RMS fixational drift"""
    saccade_rate_hz: float = 1.0
    saccade_amplitude_deg: float = 0.3
    blink_rate_hz: float = 0.0
    blink_duration_s: float = 0.25
    script: list[ScriptEvent] | None = None


class EyeSpec(_Body):
    """The patient eye's anatomy, optics and lids, and where it looks.

    The defaults are the old painted eye (``eyeserver.hardware.sim.population.SHARP``): a
    spherical globe, a spherical cornea, a sharp limbus between constant reflectances, no glints,
    no lashes. A patient's eye varies every one of these
    (:func:`eyeserver.hardware.sim.population.draw_eye`; ranges and sources in
    docs/eye-model.md). Lengths in mm; the eye's own frame has x along the room's +X when the eye
    looks straight, y up and z along the gaze."""

    globe_radius_mm: float = 12.0
    globe_semi_axes_mm: tuple[float, float, float] | None = None
    """(horizontal, vertical, axial) semi-axes of an ellipsoidal globe in the eye's frame; None: a
    sphere of globe_radius_mm"""
    cornea_radius_mm: float = 7.8
    cornea_asphericity: float = 0.0
    """the anterior cornea's conic constant Q (0 a sphere, < 0 flattening towards the limbus as
    corneas do)"""
    limbus_diameter_mm: float = 11.7
    """horizontal diameter of the corneoscleral junction, where the cornea meets the globe (the
    visible iris diameter across)"""
    limbus_vertical_ratio: float = 1.0
    """vertical over horizontal diameter of the visible limbus: the opaque sclera overlaps the
    cornea's periphery above and below"""
    limbus_width_mm: float = 0.0
    """10–90 % width of the visible limbus's transition from the iris's reflectance to the sclera's;
    0 a sharp step"""
    limbus_offset_mm: tuple[float, float] = (0.0, 0.0)
    """the limbus's centre across the globe's axis (x, y in the eye's frame): the cornea, the limbus
    and the iris decentred on the globe, their axis still along the gaze; (0, 0) the limbus
    centred on the globe's axis"""
    limbus_scatter: float = 0.0
    """share of the fringe's modulation lost to light scattered within the translucent limbal band,
    at its middle"""
    sclera_albedo: float = 0.42
    """near-infrared reflectance of the sclera (white plate 1)"""
    iris_albedo: float = 0.06
    """what comes back through the cornea: the iris's near-infrared reflectance (a light iris
    reflects more, a dark one less)"""
    iris_depth_mm: float = 3.0
    """apparent depth of the iris behind the corneal apex, as seen through the cornea (a patient's
    eye: the cornea is clear and the iris lies behind it; the sharp eye paints the iris on the
    cornea)"""
    pupil_diameter_mm: float = 4.0
    tear_reflectance: float = 0.0
    """specular reflectance of the tear film at normal incidence (≈ 0.02 for water): each
    projector's glint on cornea and sclera; 0 none"""
    tear_glints: int = 0
    """small bumps in the tear film (mucus, debris) that each glint"""
    gaze_deg: tuple[float, float] = (0.0, 0.0)
    """(yaw towards +X, pitch towards +Y) of the gaze, degrees"""
    aperture_mm: tuple[float, float] = (11.0, 7.5)
    """half-width and half-height of the lid opening (retractors; 1000 mm: no lids in the way)"""
    aperture_offset_mm: tuple[float, float] = (0.0, 0.0)
    """the lid opening's centre from the globe's axis at rest (x, y): a low upper lid covers the top
    of the limbus"""
    lid_gap_mm: float = 1.2
    lashes: int = 0
    """lashes on the upper lid's margin, thin dark occluders"""
    features_seed: int = 0
    """places the tear-film bumps and the lashes"""
    motion: MotionSpec | None = None


class HealthResponse(_Answer):
    """The daemon is up and answering."""

    status: Literal["ok"]
    """Always 'ok': any answer at all means the daemon is up."""
    version: str
    """Version of the running eyeserver."""


class JobResponse(_Answer):
    """One job."""

    id: str
    kind: str
    """What it does: reconstructions, stereo-solve, phase-height-solve."""
    actor: str
    """Who asked for it."""
    state: Literal["queued", "running", "succeeded", "failed", "cancelled"]
    progress: float
    """How far it got, 0 to 1."""
    message: str
    """What it is doing, or did last."""
    result: dict[str, Any] | None
    """What it produced once succeeded; for a failed or cancelled job, what it had finished (each
    item complete)."""
    error: str | None
    """Why it failed or was cancelled."""
    created: str
    started: str | None
    finished: str | None


class JobList(_Answer):
    """The jobs remembered, newest first."""

    items: list[JobResponse]


class MeasureRequest(_Body):
    """Which patient and fraction to verify."""

    patient_id: str
    fraction: int


class Measurement(_Answer):
    """A stored pose measurement."""

    id: str
    """pose-<UTC time>-<hex>; sorts in order of creation."""
    patient_id: str
    fraction: int
    eye: str
    """The treated eye."""
    created: str
    actor: str
    passed: bool
    """In tolerance and confident enough."""
    in_tolerance: bool
    """|Δ| and the gaze deviation within tolerance."""
    reasons: list[str]
    """Why it failed (empty when it passed)."""
    deviation: Deviation
    """delta_mm [ΔX, ΔY, ΔZ] (measured − reference globe centre, WCS, mm), length_mm, gaze_deg,
    limbus_delta_mm (or null), model_sd_mm (the globe shape's sd along the gaze, mm),
    measured_sd_mm (the measurements' own sd per axis, mm)."""
    tolerances: dict[str, float]
    """translation_mm, gaze_deg, min_confidence."""
    pose: FittedPose
    """The fit: centre_mm, centre_sd_mm, globe_radius_mm, limbus_centre_mm, limbus_sd_mm, gaze,
    gaze_sd_deg, torsion_deg, surface_mad_mm, sclera_points, confidence."""
    reference: MeasuredReference
    """The reference compared with: version, source, pose."""
    evidence: Evidence
    """capture_id (its bundle and cloud.ply: /api/v1/captures/{id}/…), unit, calibration_id,
    eye_model_version (null: population), eye_model, cloud_points, units (each unit of the
    set-up: the points it gave, per camera; one below 500 fails the measurement), fit."""


class MeasurementList(_Answer):
    """One page of measurements, newest first."""

    items: list[Measurement]
    total: int
    limit: int
    offset: int


class PatientRequest(_Body):
    """A patient's treated eye, measuring unit and tolerances."""

    eye: Literal["right", "left"]
    """The treated eye."""
    unit: str = "all"
    """The unit whose cameras see the treated eye ('all': every unit, interleaved; in the simulated
    room both units see the eye)."""
    tolerance_mm: float = 0.2
    """Largest accepted length of the translation vector, mm."""
    tolerance_gaze_deg: float = 1.0
    """Largest accepted gaze deviation, degrees."""
    min_confidence: float = 0.5
    """Smallest fit confidence with which a measurement may pass."""


class PatientResponse(_Answer):
    """A patient as stored."""

    patient_id: str
    key: str
    """The daemon's opaque key for the patient (directory name, audit target)."""
    eye: Literal["right", "left"]
    unit: str
    tolerance_mm: float
    tolerance_gaze_deg: float
    min_confidence: float
    eye_model_version: int | None
    """The eye model in use; null: population defaults."""
    created: str
    updated: str


class PlateRequest(_Body):
    """One plate height."""

    z_mm: float
    """Nominal Z of the plate's surface, mm."""
    move_stage: bool = False
    """true: the daemon's motorised stage moves the plate there first; false: it was put there by
    hand."""


class PrerenderRequest(_Body):
    """Which unit's cameras render the moving eye ahead, and for how long."""

    unit: str
    """The unit that will track (the treated eye's side)."""
    seconds: float
    """Seconds of the eye's script to render, from its restart (≈ 16 MB of memory a second for two
    8-bit cameras)."""


class PrerenderResponse(_Answer):
    """What was rendered ahead; the eye's script restarted when it was done."""

    unit: str
    cameras: list[str]
    seconds: float
    rate_hz: float
    """Frames a second, at whole camera periods of the clock."""
    frames: int
    """Frames rendered per camera."""
    megabytes: float
    """Memory the frames hold until they are used."""
    took_s: float
    """How long the rendering took."""


class QaFigure(_Answer):
    """One figure of a run against its threshold."""

    value: float | None
    """mm; null when it could not be measured (then it fails)."""
    threshold: float
    """The pass limit when the run was made, mm."""
    passed: bool


class QaOverride(_Answer):
    """An override of the lockout."""

    id: str
    actor: str
    reason: str
    created: str
    day: str
    calibration_id: str | None
    until: str
    """When it ends by itself: the end of its day (UTC)."""
    lockout_reason: str | None
    """What it overrode."""
    withdrawn: dict[str, Any] | None
    """actor and time, once withdrawn."""


class QaOverrideRequest(_Body):
    """Why the lockout is overridden (kept in the audit and the day's report)."""

    reason: str


class QaRun(_Answer):
    """A stored QA run."""

    id: str
    """qa-<UTC time>-<hex>; sorts in order of creation."""
    created: str
    """UTC, ISO 8601."""
    day: str
    """The daemon host's local date the run counts for."""
    actor: str
    calibration_id: str
    """The calibration it measured with."""
    phantom: str
    capture_ids: list[str]
    """The captures of the phantom (ordinary measurement captures)."""
    frames: int
    passed: bool
    """Every figure within its threshold, and the calibration has a QA baseline."""
    reasons: list[str]
    """Why it failed (empty when it passed)."""
    figures: dict[str, QaFigure]
    """localisation_mm, surface_mm, fiducial_mm, cross_unit_mm, static_noise_mm, drift_mm
    (docs/qa.md)."""
    baseline: bool
    """This run became the calibration's QA baseline."""
    baseline_run_id: str | None
    """The baseline the drift was measured against (this run's own id when it is one)."""
    drift_vectors_mm: dict[str, list[float]]
    """Per unit what the drift is measured with: its dots' mean miss against the phantom placed by
    all units (one unit: its ball centre), WCS, mm."""
    details: dict[str, Any]
    """How each figure was measured: points, dots matched and their residuals, placement, per-camera
    noise."""
    problems: list[str]
    """What could not be measured."""


class QaRunList(_Answer):
    """One page of QA runs, newest first."""

    items: list[QaRun]
    total: int
    limit: int
    offset: int


class QaRunRequest(_Body):
    """A QA run: the QA phantom must stand at its QA position."""

    baseline: bool = False
    """Make this run the active calibration's QA baseline if every other figure passes (physicists
    only); needed once after every new calibration."""
    frames: int | None = None
    """Captures of the still phantom (default: the setting qa.frames, 4)."""


class QaStatus(_Answer):
    """Whether position verification and tracking are locked, and why."""

    required: bool
    """The setting qa.required."""
    locked: bool
    """Verification and tracking answer 409."""
    reason: str | None
    """Why they are locked (null when not)."""
    qa_reason: str | None
    """What the QA lacks today even when an override (or qa.required = false) lifts the lockout."""
    day: str
    """Today, the daemon host's local date."""
    calibration_id: str | None
    baseline_run_id: str | None
    """The active calibration's QA baseline."""
    last_pass: str | None
    """Today's last passing run with the active calibration."""
    last_run: str | None
    failures_since_pass: int
    max_consecutive_failures: int
    override: QaOverride | None
    """The override in force."""


class QaTrendPoint(_Answer):
    """One run's value of a figure."""

    run_id: str
    created: str
    day: str
    calibration_id: str
    value: float | None
    threshold: float | None
    passed: bool
    baseline: bool


class QaTrend(_Answer):
    """One figure's history."""

    description: str
    unit: str
    threshold: float
    """The current threshold."""
    points: list[QaTrendPoint]
    """Oldest first."""


class QaTrends(_Answer):
    """Every figure's history over the last ``days`` days."""

    days: int
    since: str
    figures: dict[str, QaTrend]


class ReconstructionBatch(_Body):
    """Captures to reconstruct, in order, with the active calibration."""

    capture_ids: list[str]
    """Capture ids; each reconstruction is kept beside its capture as soon as it is done."""


class ReconstructionRequest(_Body):
    """Options of a reconstruction (those of ``eyeserver reconstruct``); all optional."""

    method: Literal["auto", "multi-view", "spatial"] = "auto"
    """Fringe order per pixel from the unit's other camera (multi-view: fast, needs a unit whose
    calibration found a clear fringe-order margin), spatial unwrapping with one order per region
    voted by the other camera (spatial: slower, keeps more of what only one camera sees), or
    auto: spatial for every unit whose calibration found a fringe-order margin."""
    depth_prior_mm: float | None = None
    """Height (mm) the surface lies near, within half a fringe's depth; fixes the order of a camera
    alone in its unit and of regions the other camera cannot judge."""
    roi: list[float] | None = None
    """[x0, y0, z0, x1, y1, z1]: keep only points inside this WCS box (mm); each low corner value
    below the high one."""
    min_quality: float = 0.0
    """Drop points of quality below this."""


class ReconstructionResponse(_Answer):
    """The surface of a capture, reconstructed and stored as its cloud.ply."""

    capture_id: str
    calibration_id: str
    """The (active) calibration used."""
    points: int
    """Points in the fused cloud."""
    extent_mm: Extent | None = None
    """Bounding box; null for an empty cloud."""
    empty_reason: str | None = None
    """Why the cloud is empty (a valid answer: nothing in view carried fringes); null when it is
    not."""
    cameras: dict[str, CameraSurface]
    """Per camera, by camera id."""
    dropped: dict[str, int]
    """Points removed during fusion, by reason."""
    method: str
    """The fringe-order method asked for (auto: chosen per unit, each camera says which and why)."""
    options: ReconstructionRequest
    """The options it was made with, defaults filled in."""
    reconstructed: str
    """UTC time it finished, ISO 8601 with milliseconds."""
    duration_s: float
    """Seconds it took."""


class ReferenceList(_Answer):
    """Every version of a fraction's reference pose, oldest first."""

    items: list[ReferenceResponse]


class ReferencePoseSpec(_Body):
    """A reference pose in the WCS, from the treatment plan."""

    centre_mm: tuple[float, float, float]
    """Globe centre, mm, WCS."""
    gaze: tuple[float, float, float]
    """Gaze direction (normalised when stored), WCS."""
    limbus_centre_mm: tuple[float, float, float] | None = None
    """Limbus centre, mm, WCS, if planned."""
    plan: str | None = None
    """Which plan it comes from (free text)."""


class ReferenceRequest(_Body):
    """The reference plane, put in place by hand."""

    z_mm: float = 10.0
    """Nominal Z of the reference plane, mm (docs/design.md §5: +10 mm)."""


class SceneSpec(_Body):
    """What stands in the room: a scene kind, its pose and its parameters."""

    kind: Literal[
        "empty",
        "chessboard",
        "plate",
        "reference",
        "pyramid",
        "wedge",
        "eye_phantom_1",
        "eye_phantom_2",
        "eye",
    ] = "empty"
    position_mm: tuple[float, float, float] | None = None
    """None: the kind's default position"""
    rotation_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    cols: int = 9
    rows: int = 6
    square_mm: float = 4.5
    eye: EyeSpec = Field(
        default={
            "globe_radius_mm": 12.0,
            "cornea_radius_mm": 7.8,
            "cornea_asphericity": 0.0,
            "limbus_diameter_mm": 11.7,
            "limbus_vertical_ratio": 1.0,
            "limbus_width_mm": 0.0,
            "limbus_offset_mm": [0.0, 0.0],
            "limbus_scatter": 0.0,
            "sclera_albedo": 0.42,
            "iris_albedo": 0.06,
            "iris_depth_mm": 3.0,
            "pupil_diameter_mm": 4.0,
            "tear_reflectance": 0.0,
            "tear_glints": 0,
            "gaze_deg": [0.0, 0.0],
            "aperture_mm": [11.0, 7.5],
            "aperture_offset_mm": [0.0, 0.0],
            "lid_gap_mm": 1.2,
            "lashes": 0,
            "features_seed": 0,
        },
        validate_default=True,
    )


class SessionRequest(_Body):
    """A new guided calibration session."""

    kind: Literal["stereo", "phase-height"]
    board: Board | None = None
    """Stereo: the board (default: the simulated room's 9 × 6 corners, 4.5 mm squares)."""
    calibration_id: str | None = None
    """Phase-height: the stored calibration whose geometry the new one extends (its parent)."""
    z_range_mm: tuple[float, float] | None = None
    """Phase-height: the Z range to calibrate, mm (default: the parent's calibrated range, else
    −10…+25). The session's plan lists the plate heights this range needs on this rig."""


class SimDeviceRequest(_Body):
    """The cable of a simulated device."""

    connected: bool
    """false unplugs the device, true plugs it back in."""


class SimDeviceResponse(_Answer):
    """A simulated device's cable after the change."""

    id: str
    kind: Literal["camera", "projector", "trigger"]
    connected: bool
    """Whether it is plugged in. A device plugged back in works again once the next operation has
    reopened it."""


class SimEyeRequest(_Body):
    """The patient eye's pose, anatomy or motion; fields left out keep their current values."""

    position_mm: tuple[float, float, float] | None = None
    """The globe centre at rest, WCS, mm (default eye: (0, 0, -10))."""
    rotation_deg: tuple[float, float, float] | None = None
    """The head's rotation about X, Y, Z, degrees (Rz·Ry·Rx)."""
    gaze_deg: tuple[float, float] | None = None
    """(yaw towards +X, pitch towards +Y) of the gaze, degrees."""
    globe_radius_mm: float | None = None
    cornea_radius_mm: float | None = None
    limbus_diameter_mm: float | None = None
    motion: MotionSpec | None = None
    """Drift, saccades, blinks and scripted events (saccade, blink, shift) from now; null stops the
    motion, leaving it out keeps the current one."""


class SimEyeResponse(_Answer):
    """The eye scene and the eye's true pose now (ground truth: for people and tests)."""

    scene: SceneSpec
    t_s: float
    """Seconds since the scene was placed (a script's clock)."""
    eye: dict[str, Any]
    """centre_mm, gaze, limbus_centre_mm, globe_radius_mm, cornea_radius_mm, openness (WCS, mm)."""


class StagePosition(_Body):
    """Where the simulated motorised stage puts the flat calibration plate."""

    z_mm: float
    """Z of the plate's surface in the WCS, within the stage's travel -15.0…30.0 mm; the plate stays
    normal to Z, centred on the axis."""


class TrackingSummary(_Answer):
    """Live tracking at a glance (``GET /api/v1/tracking`` has the whole status)."""

    running: bool
    beam_hold: bool
    """The beam-hold flag now (true whenever tracking is not watching a good eye)."""
    stalled: dict[str, Any] | None
    """While no processed frame came within the deadline: its reason (no_frames, worker_stalled),
    since when, the silence (ms)."""


class UnitResponse(_Answer):
    """One optical unit: a projector and its cameras; in fault while one of them is."""

    id: str
    projector: str
    cameras: list[str]
    health: Literal["ok", "fault"]
    reason: str | None


class StatusResponse(_Answer):
    """What the daemon is doing and how its hardware is."""

    state: Literal["idle", "capturing", "calibrating", "tracking", "fault"]
    """The state machine: one hardware operation at a time; 'fault' after a device failed."""
    devices: list[DeviceResponse]
    units: list[UnitResponse]
    active_calibration_id: str | None
    """The calibration new captures are taken with; null before one is active."""
    uptime_s: float
    """Seconds since the daemon opened its hardware."""
    version: str
    """Version of the running eyeserver."""
    tracking: TrackingSummary | None = None
    """Live tracking's beam hold and fail-safe (null: tracking is not available)."""


class TrackingStart(_Body):
    """Whom to track, and how the beam hold behaves."""

    patient_id: str
    fraction: int
    dwell_frames: int = 3
    """Good frames in a row before the beam hold falls."""
    hold_on_drop: bool = True
    """Hold the beam (and restart the dwell) when more than two frames went unprocessed before a
    processed one (shorter gaps are counted, not held)."""


class TrackingStatus(_Answer):
    """The running or last tracking session."""

    running: bool
    started: str | None
    stopped: str | None
    frames_acquired: int
    """Camera frames acquired."""
    frames_processed: int
    """Frames reconstructed and fitted (one message each on /ws/pose)."""
    frames_dropped: int
    """Frames acquired but replaced by a newer one before processing (the newest frame wins)."""
    frames_missed: int
    """Camera periods the rig could not serve in time."""
    frames_held: int
    """Processed frames with the beam held."""
    beam_hold: bool
    stalled: dict[str, Any] | None = None
    """While no processed frame came within the deadline: its reason (no_frames, worker_stalled),
    since when, and the silence (ms)."""
    stalls: int = 0
    """Times the deadline passed without a processed frame."""
    deadline_ms: float | None = None
    """The fail-safe's deadline."""
    error: str | None
    """Why the session ended by itself, if it did."""
    last_message: dict[str, Any] | None
    """The last pose message."""


class ViewRequest(_Body):
    """One chessboard view."""

    origin: bool | None = None
    """Whether this board defines the WCS. By default the first view does; post the first with false
    to mark a later one true instead (exactly one origin)."""


class WhoAmIResponse(_Answer):
    """The holder of the request's token."""

    name: str
    """The token holder's name, as the audit trail records it."""
    role: Literal["operator", "physicist"]
    """The token's role."""
    roles: list[Literal["operator", "physicist"]]
    """Every role the token may act as: its own and the lower ones (a physicist may do what an
    operator may)."""
