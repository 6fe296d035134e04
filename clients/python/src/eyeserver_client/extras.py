"""Models of answers the daemon's OpenAPI document leaves untyped, written from the daemon.

The document types these as bare objects (``dict``): a pose measurement's deviation, fitted
pose, reference and evidence, a reference's pose, the guided calibration sessions and their
steps, and the drift between two calibrations. Their shape here follows the daemon's code
(``eyeserver/service/verification.py``, ``calibration_session.py``,
``eyeserver/calibration/compare.py``); every model keeps fields it does not know, and the
client's tests read each of them from a live daemon, so a change there shows.

Coordinates are the room's world coordinate system (WCS), lengths in mm; angles in degrees
where the name says ``_deg``.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict

__all__ = [
    "CalibrationComparison",
    "CalibrationSession",
    "CameraCoverage",
    "CameraDrift",
    "Deviation",
    "DriftSummary",
    "Evidence",
    "FittedPose",
    "HeightChange",
    "MeasuredReference",
    "PlatePlan",
    "PlateStep",
    "ReferencePlaneStep",
    "ReferencePose",
    "SessionBoard",
    "SessionPlate",
    "SessionReference",
    "SessionView",
    "StereoCoverage",
    "ViewStep",
]

Vector = tuple[float, float, float]


class _Answer(BaseModel):
    model_config = ConfigDict(extra="allow", use_attribute_docstrings=True)


# --- position verification -----------------------------------------------------------------


class Deviation(_Answer):
    """Measured − reference, in the WCS: what the verdict is judged on."""

    delta_mm: Vector
    """ΔX, ΔY, ΔZ of the globe centre, mm."""
    length_mm: float
    """Length of ``delta_mm``, mm (judged against the patient's ``tolerance_mm``)."""
    gaze_deg: float
    """Angle between measured and reference gaze, degrees."""
    limbus_delta_mm: Vector | None = None
    """The limbus centre's shift, mm, when the reference has a limbus centre."""
    model_sd_mm: float | None = None
    """The share of the deviation the eye model's unknown globe shape may explain (1 sd, mm)."""
    measured_sd_mm: Vector | None = None
    """The deviation's sd per WCS axis from the measurements themselves (the pose's and a
    captured reference's, mm): beyond the tolerance on any axis the measurement fails."""


class FittedPose(_Answer):
    """The eye's pose as fitted (``eyeserver pose``), with its uncertainties."""

    centre_mm: Vector
    """Globe centre, mm, WCS."""
    centre_sd_mm: Vector
    """Its standard deviation per axis, mm."""
    globe_radius_mm: float
    limbus_centre_mm: Vector | None = None
    limbus_sd_mm: float | None = None
    gaze: Vector
    """Unit gaze vector, WCS."""
    gaze_sd_deg: float
    torsion_deg: float | None = None
    surface_mad_mm: float
    """Median absolute distance of the surface to the model, mm."""
    sclera_points: int
    confidence: float
    """0–1: how many sclera points place the globe, how well the surface fits, how sharp the
    gaze is; a verification fails below the patient's ``min_confidence``."""
    gaze_source: str | None = None
    """``limbus (images)`` when the fringe images gave the limbus, else how the cloud did."""
    shape_sd_mm: float | None = None
    """What the model does not know of the globe's shape (1 sd along the gaze, mm)."""


class ReferencePose(_Answer):
    """A reference pose (planned or captured at set-up), WCS."""

    centre_mm: Vector
    """Globe centre, mm."""
    gaze: Vector
    """Unit gaze vector."""
    limbus_centre_mm: Vector | None = None
    """Limbus centre, mm, when known."""


class MeasuredReference(_Answer):
    """The reference a measurement was compared with."""

    version: int
    source: Literal["plan", "capture"]
    pose: ReferencePose


class Evidence(_Answer):
    """What a measurement (or a captured reference) is based on: find the capture's bundle and
    cloud under ``/api/v1/captures/{capture_id}/…``."""

    capture_id: str
    unit: str
    calibration_id: str
    eye_model_version: int | None = None
    """The patient's eye-model version used; null: population defaults."""
    eye_model: dict[str, Any] | None = None
    cloud_points: int | None = None
    units: dict[str, Any] | None = None
    """Each unit of the set-up: the points it gave, per camera (below 500 fails)."""
    fit: dict[str, Any] | None = None


# --- guided calibration sessions -----------------------------------------------------------


class SessionBoard(_Answer):
    """A stereo session's chessboard: inner corners and the square's side (mm)."""

    cols: int
    rows: int
    square_mm: float


class SessionView(_Answer):
    """One acquired chessboard view."""

    capture_id: str
    origin: bool
    """Whether this board defines the WCS."""
    found: dict[str, bool]
    """Per camera: whether it found the board."""


class CameraCoverage(_Answer):
    """How far one camera's field is covered by detected corners so far."""

    views_found: int
    coverage: float
    """Share (0–1) of the 4 × 4 image cells its corners touched."""
    cells_covered: int
    cells_total: int
    uncovered_cells: list[list[int]]
    """(row, col) of each cell not yet touched: where to hold the board next."""
    origin_found: bool


class StereoCoverage(_Answer):
    """A stereo session's coverage per camera, and what is still missing."""

    cameras: dict[str, CameraCoverage]
    ready: bool
    missing: list[str]


class SessionPlate(_Answer):
    """One acquired plate height."""

    capture_id: str
    z_mm: float
    moved_by_stage: bool


class SessionReference(_Answer):
    """The acquired reference plane."""

    capture_id: str
    z_mm: float


class PlatePlan(_Answer):
    """A phase-height session's plan: which plate heights this rig needs.

    The solve walks each pixel's fringe phase from plane to plane along Z; a step that moves
    the phase by π or more slips by a fringe, so neighbouring planes (the reference among them)
    may be at most ``max_step_mm`` apart, from the fringe phase's sensitivity to height
    (``sensitivity_rad_per_mm`` per camera). The sensitivity is known at the opening when the
    parent calibration has phase-to-height models, else measured on the reference plane and a
    probe plate 1 mm from it; until then the heights are None and ``next`` says what to do.
    """

    z_range_mm: list[float]
    sensitivity_rad_per_mm: dict[str, float] | None = None
    sensitivity_source: str | None = None
    max_step_mm: float | None = None
    needed_heights_mm: list[float] | None = None
    """Every height still needed (mm, ascending; empty: none), None while not known."""
    next: str
    """What to acquire next, in words."""
    sensitivity_error: str | None = None


class CalibrationSession(_Answer):
    """A guided calibration session (kept in the daemon's memory until it restarts).

    ``state``: ``acquiring`` (the daemon is ``calibrating``), ``solving`` (its job runs, the
    daemon is free again), ``done`` (``calibration_id`` names the new calibration), ``failed``
    (``error`` says why) or ``closed``. Stereo sessions have ``board``, ``views`` and
    ``coverage``; phase-height sessions ``parent_id``, ``plates``, ``reference``, ``ready`` and
    ``missing``.
    """

    id: str
    kind: Literal["stereo", "phase-height"]
    actor: str
    created: str
    state: Literal["acquiring", "solving", "done", "failed", "closed"]
    job_id: str | None = None
    calibration_id: str | None = None
    error: str | None = None
    board: SessionBoard | None = None
    views: list[SessionView] | None = None
    coverage: StereoCoverage | None = None
    parent_id: str | None = None
    plates: list[SessionPlate] | None = None
    reference: SessionReference | None = None
    ready: bool | None = None
    missing: list[str] | None = None
    plan: PlatePlan | None = None
    """Phase-height: the heights this rig needs (see :class:`PlatePlan`)."""
    failures: list[dict[str, Any]] | None = None
    """Phase-height: the solves that failed before (job id, error, the heights then)."""

    @property
    def is_ready(self) -> bool:
        """Whether the session may be solved (either kind)."""
        if self.coverage is not None:
            return self.coverage.ready
        return bool(self.ready)

    @property
    def still_missing(self) -> list[str]:
        """What the session still needs before it can be solved (either kind)."""
        if self.coverage is not None:
            return list(self.coverage.missing)
        return list(self.missing or [])


class ViewStep(StereoCoverage):
    """The answer to a chessboard view: which cameras found it and the coverage so far."""

    capture_id: str
    origin: bool
    found: dict[str, bool]


class PlateStep(_Answer):
    """The answer to a plate acquisition, with what the session still needs."""

    capture_id: str
    z_mm: float
    moved_by_stage: bool
    ready: bool
    missing: list[str]
    plan: PlatePlan | None = None


class ReferencePlaneStep(_Answer):
    """The answer to the reference plane's acquisition, with what the session still needs."""

    capture_id: str
    z_mm: float
    ready: bool
    missing: list[str]
    plan: PlatePlan | None = None


# --- calibration drift ---------------------------------------------------------------------


class HeightChange(_Answer):
    """How far heights measured with B differ from A's over the calibrated volume."""

    z_range_mm: tuple[float, float]
    samples: int
    median_abs_mm: float
    max_abs_mm: float


class CameraDrift(_Answer):
    """One camera's drift from calibration A to B."""

    rotation_deg: float
    centre_shift_mm: Vector
    centre_shift_norm_mm: float
    focal_change_px: tuple[float, float]
    principal_point_change_px: tuple[float, float]
    phase_to_height: HeightChange | None = None
    """Null unless both calibrations have phase-to-height models."""


class DriftSummary(_Answer):
    """The largest drift over the cameras."""

    max_rotation_deg: float
    max_centre_shift_mm: float
    max_height_change_mm: float | None = None


class CalibrationComparison(_Answer):
    """``GET /calibrations/compare``: drift from A to B per camera."""

    cameras: dict[str, CameraDrift]
    summary: DriftSummary
