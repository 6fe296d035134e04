"""Pydantic models of the API's request and response bodies (they make the OpenAPI schema)."""

from __future__ import annotations

import math
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

__all__ = [
    "CalibrationList",
    "CalibrationResponse",
    "CameraSurface",
    "CaptureList",
    "CaptureRequest",
    "CaptureResponse",
    "DeviceResponse",
    "DeviceSettingsRequest",
    "ErrorResponse",
    "Extent",
    "HealthResponse",
    "ReconstructionRequest",
    "ReconstructionResponse",
    "StatusResponse",
    "UnitResponse",
]

_CAPTURE_ID_EXAMPLE = "cap-20261123T151200123Z-4f2a"
_CALIBRATION_ID_EXAMPLE = "cal-20261123T151200123Z-9c1d"


MAX_SQL_INT = 2**63 - 1
"""The largest integer SQLite stores: offsets and versions beyond it are 422, not a 500 from
the store (issue 35)."""


class HealthResponse(BaseModel):
    """The daemon is up and answering."""

    status: Literal["ok"] = Field(
        description="Always 'ok': any answer at all means the daemon is up."
    )
    version: str = Field(description="Version of the running eyeserver.", examples=["0.1.0"])


class ErrorResponse(BaseModel):
    """Body of every error the API reports on purpose."""

    detail: str = Field(
        description="Why the request failed, in words meant for a person.",
        examples=["cam-left: no frame within 500 ms"],
    )
    errors: list[dict[str, Any]] | None = Field(
        None, description="For a request that failed validation (422): each problem with its "
        "location (loc), message (msg) and type, as pydantic reports it; null otherwise.")


Health = Literal["ok", "fault"]


class DeviceResponse(BaseModel):
    """One device of the rig and its health."""

    id: str = Field(description="Device id from the rig configuration.", examples=["S1"])
    kind: str = Field(description="camera, projector or trigger.", examples=["camera"])
    driver: str = Field(description="Driver that runs it.", examples=["SimCamera"])
    unit: str | None = Field(description="The unit it belongs to; null for the trigger, which "
                             "serves every unit.", examples=["left"])
    open: bool = Field(description="Whether the device is open.")
    health: Health = Field(description="'fault' after the device failed, until it works again.")
    reason: str | None = Field(description="Why it is in fault; null when ok.",
                               examples=[None, "camera is not responding"])
    details: dict[str, object] = Field(
        description="The driver's own description: current settings, sizes.",
        examples=[{"id": "S1", "kind": "camera", "driver": "SimCamera", "open": True,
                   "width": 1280, "height": 1024, "bit_depth": 8}])


class DeviceSettingsRequest(BaseModel):
    """New settings for one device; fields left out (or null) stay as they are.

    Projectors take ``enabled`` and ``intensity``, cameras ``exposure_us`` and ``gain_db``; a
    field that does not apply to the device's kind is refused (422), as is a value outside the
    device's range.
    """

    model_config = ConfigDict(extra="forbid")

    enabled: bool | None = Field(default=None, description="Projector: whether it may light.",
                                 examples=[True])
    intensity: float | None = Field(default=None, description="Projector: relative drive "
                                    "level, 0 (dark) to 1 (full current).", examples=[0.8])
    exposure_us: float | None = Field(default=None, description="Camera: exposure time in "
                                      "microseconds.", examples=[8000.0])
    gain_db: float | None = Field(default=None, description="Camera: analogue gain in dB "
                                  "(0 dB = unity).", examples=[6.0])


class UnitResponse(BaseModel):
    """One optical unit: a projector and its cameras; in fault while one of them is."""

    id: str = Field(examples=["left"])
    projector: str = Field(examples=["P1"])
    cameras: list[str] = Field(examples=[["S1", "S2"]])
    health: Health
    reason: str | None = Field(examples=[None, "S1: camera is not responding"])


class TrackingSummary(BaseModel):
    """Live tracking at a glance (``GET /api/v1/tracking`` has the whole status)."""

    running: bool
    beam_hold: bool = Field(description="The beam-hold flag now (true whenever tracking is not "
                            "watching a good eye).")
    stalled: dict[str, Any] | None = Field(description="While no processed frame came within "
                                           "the deadline: its reason (no_frames, "
                                           "worker_stalled), since when, the silence (ms).")


class StatusResponse(BaseModel):
    """What the daemon is doing and how its hardware is."""

    state: Literal["idle", "capturing", "calibrating", "tracking", "fault"] = Field(
        description="The state machine: one hardware operation at a time; 'fault' after a "
        "device failed.", examples=["idle"])
    devices: list[DeviceResponse]
    units: list[UnitResponse]
    active_calibration_id: str | None = Field(
        description="The calibration new captures are taken with; null before one is active.",
        examples=[None, "cal-20261123T151200123Z-9c1d"])
    uptime_s: float = Field(description="Seconds since the daemon opened its hardware.",
                            examples=[12.5])
    version: str = Field(description="Version of the running eyeserver.", examples=["0.1.0"])
    tracking: TrackingSummary | None = Field(None, description="Live tracking's beam hold and "
                                             "fail-safe (null: tracking is not available).")


class CaptureRequest(BaseModel):
    """Capture one frame set."""

    model_config = ConfigDict(extra="forbid")

    unit: str = Field(description="A unit id, or 'all' for every unit, interleaved (one "
                      "trigger pulse per unit).", examples=["all", "left"])


class CaptureResponse(BaseModel):
    """A stored capture (its bundle is durable on disk)."""

    id: str = Field(description="Capture id; sorts in order of creation.",
                    examples=[_CAPTURE_ID_EXAMPLE])
    kind: str = Field(description="Bundle kind (FORMATS.md).", examples=["measurement"])
    unit: str = Field(description="The unit captured, or 'all'.", examples=["all"])
    calibration_id: str | None = Field(description="The calibration active when it was taken.",
                                       examples=[None])
    created: str = Field(description="UTC creation time, ISO 8601 with milliseconds.",
                         examples=["2026-11-23T15:12:00.123Z"])
    frame_count: int = Field(description="Frames in the bundle: one per unit.", examples=[2])
    status: Literal["ok", "missing"] = Field(
        description="'missing' when start-up recovery found the index row without its bundle.")


class CaptureList(BaseModel):
    """One page of captures, newest first."""

    items: list[CaptureResponse]
    total: int = Field(description="Captures matching the filter over all pages.", examples=[1])
    limit: int = Field(examples=[50])
    offset: int = Field(examples=[0])


class CalibrationResponse(BaseModel):
    """A calibration kept in the store."""

    id: str = Field(description="Calibration id; sorts in order of import.",
                    examples=[_CALIBRATION_ID_EXAMPLE])
    created: str = Field(description="When it was computed (its calibration.json).",
                         examples=["2026-11-23T14:02:11Z"])
    imported: str = Field(description="UTC import time, ISO 8601 with milliseconds.",
                          examples=["2026-11-23T15:12:00.123Z"])
    active: bool = Field(description="Whether captures and reconstructions use it now.")
    source: str = Field(description="Where it came from: who uploaded it and the archive's "
                        "SHA-256, or the directory it was imported from.",
                        examples=["upload by physicist, sha256:9f86d081884c7d65…"])
    status: Literal["ok", "missing"] = Field(
        description="'missing' when start-up recovery found the index row without its files.")
    quality: dict[str, object] = Field(
        description="The quality figures of its calibration.json (reprojection errors, "
        "phase-to-height residuals); empty when it has none.",
        examples=[{"stereo": {"left": {"rms_px": 0.12}}}])
    version: int | None = Field(
        None, description="Its place in the order of creation in this store (1 for the "
        "first); calibrations are immutable, so a version always means the same data.",
        examples=[3])
    parent_id: str | None = Field(
        None, description="The calibration whose geometry a phase-to-height calibration "
        "extends (lineage.parent_id of its calibration.json); null for a stereo calibration "
        "or an upload without one.")
    session_id: str | None = Field(
        None, description="The guided calibration session that made it, if any.")


class CalibrationList(BaseModel):
    """Every stored calibration, newest first."""

    items: list[CalibrationResponse]


class Extent(BaseModel):
    """The bounding box of a point cloud, in mm (world coordinates)."""

    min: list[float] = Field(examples=[[-6.1, -5.9, 1.2]])
    max: list[float] = Field(examples=[[6.0, 6.2, 4.8]])


class CameraSurface(BaseModel):
    """What one camera contributed to a reconstruction."""

    frame: int = Field(description="The bundle frame its image comes from.", examples=[0])
    points: int = Field(description="Points it measured before fusion.", examples=[120000])
    partner: str | None = Field(description="The camera that fixed its fringe order: its "
                                "unit's other camera, or another unit's for a unit blind to "
                                "the order; null when a depth prior did.", examples=["S2"])
    fringe_order: dict[str, int] = Field(
        description="Points per source that fixed their fringe order.",
        examples=[{"multi-view": 118000, "spatial + multi-view": 2000}])
    method: str | None = Field(None, description="The fringe-order method its unit used "
                               "(null in reconstructions made before it was recorded).",
                               examples=["multi-view"])
    method_reason: str | None = Field(None, description="Why that method.", examples=[
        "fringe-order margin 0.69 rad, at least 0.5 rad"])
    fringe_pixels: int | None = Field(None, description="Its pixels that see a fringe.",
                                      examples=[160000])
    coverage: float | None = Field(None, description="The share of those that gave a point.",
                                   examples=[0.75])


class ReconstructionRequest(BaseModel):
    """Options of a reconstruction (those of ``eyeserver reconstruct``); all optional."""

    model_config = ConfigDict(extra="forbid")

    method: Literal["auto", "multi-view", "spatial"] = Field(
        default="auto", description="Fringe order per pixel from the unit's other camera "
        "(multi-view: fast, needs a unit whose calibration found a clear fringe-order margin), "
        "spatial unwrapping with one order per region voted by the other camera (spatial: "
        "slower, keeps more of what only one camera sees), or auto: spatial for every unit "
        "whose calibration found a fringe-order margin.")
    depth_prior_mm: float | None = Field(
        default=None, allow_inf_nan=False, description="Height (mm) the surface lies near, "
        "within half a fringe's depth; fixes the order of a camera alone in its unit and of "
        "regions the other camera cannot judge.", examples=[None, 3.0])
    roi: list[float] | None = Field(
        default=None, min_length=6, max_length=6, description="[x0, y0, z0, x1, y1, z1]: keep "
        "only points inside this WCS box (mm); each low corner value below the high one.",
        examples=[[-5.0, -5.0, 0.0, 5.0, 5.0, 10.0]])
    min_quality: float = Field(default=0.0, ge=0.0, le=1.0, allow_inf_nan=False,
                               description="Drop points of quality below this.")

    @model_validator(mode="after")
    def _roi_is_a_box(self) -> ReconstructionRequest:
        if self.roi is not None:
            if not all(math.isfinite(value) for value in self.roi):
                raise ValueError("roi: every value must be finite")
            low, high = self.roi[:3], self.roi[3:]
            if any(lo >= hi for lo, hi in zip(low, high, strict=True)):
                raise ValueError(f"roi: the low corner {low} must be below the high corner "
                                 f"{high} on every axis")
        return self


class ReconstructionResponse(BaseModel):
    """The surface of a capture, reconstructed and stored as its cloud.ply."""

    capture_id: str = Field(examples=[_CAPTURE_ID_EXAMPLE])
    calibration_id: str = Field(description="The (active) calibration used.",
                                examples=[_CALIBRATION_ID_EXAMPLE])
    points: int = Field(description="Points in the fused cloud.", examples=[240000])
    extent_mm: Extent | None = Field(None, description="Bounding box; null for an empty "
                                     "cloud.")
    empty_reason: str | None = Field(None, description="Why the cloud is empty (a valid "
                                     "answer: nothing in view carried fringes); null when it "
                                     "is not.")
    cameras: dict[str, CameraSurface] = Field(description="Per camera, by camera id.")
    dropped: dict[str, int] = Field(
        description="Points removed during fusion, by reason.",
        examples=[{"seam_conflict": 120, "low_quality": 0, "outside_region": 0}])
    method: str = Field(description="The fringe-order method asked for (auto: chosen per "
                        "unit, each camera says which and why).", examples=["auto"])
    options: ReconstructionRequest = Field(description="The options it was made with, "
                                           "defaults filled in.")
    reconstructed: str = Field(description="UTC time it finished, ISO 8601 with milliseconds.",
                               examples=["2026-11-23T15:12:03.456Z"])
    duration_s: float = Field(description="Seconds it took.", examples=[2.7])
