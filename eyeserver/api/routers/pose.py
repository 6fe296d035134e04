"""``/api/v1/pose``: position verification, the call the OIS makes before irradiation.

``POST /pose/measure`` captures the patient's eye, fits its model and compares the pose with
the fraction's reference (measured − reference, WCS), answering the pose, the deviation, the
verdict and the evidence; the measurement is stored and found again by id or by patient and
fraction (:mod:`eyeserver.service.verification`), also as DICOM (:mod:`eyeserver.io.dicom`).
Any token may measure and read. While the daily QA locks verification (:mod:`eyeserver.api.
routers.qa`), ``POST /pose/measure`` answers 409 with the reason.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Depends, Query, Response
from pydantic import BaseModel, ConfigDict, Field
from starlette.concurrency import run_in_threadpool

import eyeserver
from eyeserver.api.auth import OperatorDep
from eyeserver.api.deps import ServiceDep
from eyeserver.api.routers.patients import VerificationDep
from eyeserver.api.routers.qa import QA_LOCKED, qa_gate
from eyeserver.api.schemas import MAX_SQL_INT, ErrorResponse
from eyeserver.io import dicom
from eyeserver.service.core import NoCloudError
from eyeserver.service.patients import PATIENT_ID_PATTERN
from eyeserver.service.storage import UnknownIdError

__all__ = ["router"]

router = APIRouter(prefix="/pose", tags=["pose"])


class MeasureRequest(BaseModel):
    """Which patient and fraction to verify."""

    model_config = ConfigDict(extra="forbid")

    patient_id: str = Field(pattern=PATIENT_ID_PATTERN, examples=["P-0001"])
    fraction: int = Field(ge=1, le=1000, examples=[3])


class Measurement(BaseModel):
    """A stored pose measurement."""

    model_config = ConfigDict(extra="allow")

    id: str = Field(description="pose-<UTC time>-<hex>; sorts in order of creation.",
                    examples=["pose-20261123T151200123Z-4f2a"])
    patient_id: str
    fraction: int
    eye: str = Field(description="The treated eye.")
    created: str
    actor: str
    passed: bool = Field(description="In tolerance and confident enough.")
    in_tolerance: bool = Field(description="|Δ| and the gaze deviation within tolerance.")
    reasons: list[str] = Field(description="Why it failed (empty when it passed).")
    deviation: dict[str, Any] = Field(description="delta_mm [ΔX, ΔY, ΔZ] (measured − "
                                      "reference globe centre, WCS, mm), length_mm, gaze_deg, "
                                      "limbus_delta_mm (or null), model_sd_mm (the globe "
                                      "shape's sd along the gaze, mm), measured_sd_mm (the "
                                      "measurements' own sd per axis, mm).")
    tolerances: dict[str, float] = Field(description="translation_mm, gaze_deg, "
                                         "min_confidence.")
    pose: dict[str, Any] = Field(description="The fit: centre_mm, centre_sd_mm, "
                                 "globe_radius_mm, limbus_centre_mm, limbus_sd_mm, gaze, "
                                 "gaze_sd_deg, torsion_deg, surface_mad_mm, sclera_points, "
                                 "confidence.")
    reference: dict[str, Any] = Field(description="The reference compared with: version, "
                                      "source, pose.")
    evidence: dict[str, Any] = Field(description="capture_id (its bundle and cloud.ply: "
                                     "/api/v1/captures/{id}/…), unit, calibration_id, "
                                     "eye_model_version (null: population), eye_model, "
                                     "cloud_points, units (each unit of the set-up: the "
                                     "points it gave, per camera; one below 500 fails the "
                                     "measurement), fit.")


class MeasurementList(BaseModel):
    """One page of measurements, newest first."""

    items: list[Measurement]
    total: int
    limit: int
    offset: int


@router.post("/measure", status_code=201, summary="Verify the eye position",
             responses={404: {"model": ErrorResponse, "description": "No such patient, or the "
                              "fraction has no reference pose."},
                        409: {"model": ErrorResponse, "description": "No active calibration, "
                              f"the daemon is calibrating or tracking, or {QA_LOCKED}."},
                        422: {"model": ErrorResponse, "description": "Bad body, or no eye could "
                              "be fitted (the reason says why)."},
                        503: {"model": ErrorResponse, "description": "A device failed, or a "
                              "queue is full."}},
             dependencies=[Depends(qa_gate("position verification"))])
async def measure(body: MeasureRequest, verification: VerificationDep, caller: OperatorDep,
                  ) -> Measurement:
    """Capture the unit on the treated eye's side, reconstruct with the active calibration, fit
    the patient's eye model and compare with the fraction's reference: deviation = measured −
    reference, pass/fail against the patient's tolerances. Stored with its evidence; takes
    seconds (a capture and a reconstruction)."""
    document = await run_in_threadpool(lambda: verification.measure(
        body.patient_id, body.fraction, actor=caller.name))
    return Measurement.model_validate(document)


@router.get("/measurements", summary="A patient's measurements",
            responses={404: {"model": ErrorResponse, "description": "No such patient."}})
async def list_measurements(
    verification: VerificationDep,
    patient_id: Annotated[str, Query(pattern=PATIENT_ID_PATTERN)],
    fraction: Annotated[int | None, Query(ge=1, le=1000)] = None,
    limit: Annotated[int, Query(ge=1, le=1000)] = 50,
    offset: Annotated[int, Query(ge=0, le=MAX_SQL_INT)] = 0,
) -> MeasurementList:
    """A patient's measurements (of one fraction with ``fraction``), newest first."""
    items, total = await run_in_threadpool(lambda: verification.find(
        patient_id, fraction, limit=limit, offset=offset))
    return MeasurementList(items=[Measurement.model_validate(i) for i in items], total=total,
                           limit=limit, offset=offset)


@router.get("/measurements/{measurement_id}", summary="One measurement",
            responses={404: {"model": ErrorResponse, "description": "No such measurement."}})
async def get_measurement(measurement_id: str, verification: VerificationDep) -> Measurement:
    """A stored measurement with its evidence, also after a restart."""
    return Measurement.model_validate(await run_in_threadpool(verification.get, measurement_id))


@router.get("/measurements/{measurement_id}/dicom", summary="One measurement as DICOM",
            response_class=Response,
            responses={200: {"content": {"application/zip": {}, "application/dicom": {}},
                             "description": "Without ``object``: a zip of registration.dcm "
                             "and surface.dcm; with it, that one object."},
                       404: {"model": ErrorResponse, "description": "No such measurement."},
                       409: {"model": ErrorResponse, "description": "The measurement has no "
                             "reference pose to register against."}})
async def get_measurement_dicom(
    measurement_id: str, verification: VerificationDep, service: ServiceDep,
    dicom_object: Annotated[dicom.DicomObject | None, Query(
        alias="object", description="registration: the Spatial Registration alone; surface: "
        "the Surface Segmentation alone (application/dicom).")] = None,
) -> Response:
    """A stored measurement as a DICOM Spatial Registration (the eye's rigid motion from the
    fraction's reference pose to the measured pose, 4 × 4, RIGID) and a DICOM Surface
    Segmentation (the measured points near the eye and the fitted globe), both in the
    fraction's Frame of Reference (the room's WCS, mm; :mod:`eyeserver.io.dicom`)."""
    def export() -> dict[str, bytes]:
        document = verification.get(measurement_id)
        patient = verification.patients.get(document["patient_id"])
        try:  # the capture is the measurement's evidence; its cloud may have gone (none)
            cloud = service.cloud_path(str(document["evidence"]["capture_id"]))
        except (NoCloudError, UnknownIdError, KeyError, TypeError):
            cloud = None
        return dicom.export_measurement(
            document, patient_key=patient.key,
            equipment=dicom.Equipment.this_host(eyeserver.__version__), cloud_path=cloud,
            objects=("registration", "surface") if dicom_object is None else (dicom_object,))

    files = await run_in_threadpool(export)
    if dicom_object is not None:
        return Response(files[dicom.DICOM_OBJECTS[dicom_object]], media_type="application/dicom",
                        headers={"Content-Disposition": f'attachment; filename="{measurement_id}'
                                 f'-{dicom_object}.dcm"'})
    return Response(dicom.zip_objects(files), media_type="application/zip",
                    headers={"Content-Disposition": f'attachment; filename="{measurement_id}'
                             '-dicom.zip"'})
