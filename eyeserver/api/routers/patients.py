"""``/api/v1/patients``: patients (treated eye, measuring unit, tolerances), their versioned eye
models and the reference pose of each fraction.

Physicists create and change patients, import eye models and set reference poses (from the plan
— also from the plan's DICOM, :mod:`eyeserver.io.dicom` — or captured at set-up); any token
reads them. Nothing is ever deleted: a new model or reference is a new version, and the newest
is used. Patient ids reach the audit file only hashed.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal, TypeVar

from fastapi import APIRouter, Depends, Path, Request, Response
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from starlette.concurrency import run_in_threadpool

from eyeserver.api.auth import OperatorDep, PhysicistDep
from eyeserver.api.deps import ServiceDep, app_state
from eyeserver.api.routers.calibrations import _read_limited
from eyeserver.api.schemas import MAX_SQL_INT, ErrorResponse
from eyeserver.core.validation import NumbersOnly
from eyeserver.errors import FormatError
from eyeserver.io import dicom
from eyeserver.service.patients import (
    DEFAULT_MIN_CONFIDENCE,
    DEFAULT_TOLERANCE_GAZE_DEG,
    DEFAULT_TOLERANCE_MM,
    PATIENT_ID_PATTERN,
    EyeModelSpec,
    EyeModelVersion,
    Patient,
    Patients,
    ReferencePose,
    ReferencePoseSpec,
    Tolerances,
)
from eyeserver.service.storage import UnknownIdError
from eyeserver.service.verification import PoseVerification

__all__ = ["PatientIdPath", "router"]

_Spec = TypeVar("_Spec", bound=BaseModel)

router = APIRouter(prefix="/patients", tags=["patients"])

PatientIdPath = Annotated[str, Path(pattern=PATIENT_ID_PATTERN, description="The patient's "
                                    "id as the OIS gives it (printable ASCII without spaces, "
                                    "'/' and '\\', up to 128 characters).",
                                    examples=["P-0001"])]
FractionPath = Annotated[int, Path(ge=1, le=1000, description="Fraction number, from 1.")]

_UNKNOWN: dict[int | str, dict[str, Any]] = {
    404: {"model": ErrorResponse, "description": "No such patient."}}


get_patients = app_state("patients", Patients)
get_verification = app_state("verification", PoseVerification)


PatientsDep = Annotated[Patients, Depends(get_patients)]
VerificationDep = Annotated[PoseVerification, Depends(get_verification)]


class PatientRequest(NumbersOnly):
    """A patient's treated eye, measuring unit and tolerances."""

    model_config = ConfigDict(extra="forbid")

    eye: Literal["right", "left"] = Field(description="The treated eye.")
    unit: str = Field("all", description="The unit whose cameras see the treated eye ('all': "
                      "every unit, interleaved; in the simulated room both units see the eye).",
                      examples=["all", "left"])
    tolerance_mm: float = Field(DEFAULT_TOLERANCE_MM, gt=0, le=50, description="Largest "
                                "accepted length of the translation vector, mm.")
    tolerance_gaze_deg: float = Field(DEFAULT_TOLERANCE_GAZE_DEG, gt=0, le=90,
                                      description="Largest accepted gaze deviation, degrees.")
    min_confidence: float = Field(DEFAULT_MIN_CONFIDENCE, ge=0, le=1, description="Smallest "
                                  "fit confidence with which a measurement may pass.")


class PatientResponse(BaseModel):
    """A patient as stored."""

    patient_id: str = Field(examples=["P-0001"])
    key: str = Field(description="The daemon's opaque key for the patient (directory name, "
                     "audit target).", examples=["pat-3f2a9c1d0b7e4a65"])
    eye: Literal["right", "left"]
    unit: str
    tolerance_mm: float
    tolerance_gaze_deg: float
    min_confidence: float
    eye_model_version: int | None = Field(description="The eye model in use; null: population "
                                          "defaults.")
    created: str
    updated: str


class EyeModelResponse(BaseModel):
    """One version of a patient's eye model."""

    version: int = Field(description="1, 2, …: the newest is used.")
    created: str
    actor: str
    population: bool = Field(description="True when the globe's shape is not given (fitted).")
    model: EyeModelSpec


class EyeModelList(BaseModel):
    """Every eye-model version of a patient, oldest first."""

    items: list[EyeModelResponse]


class ReferenceResponse(BaseModel):
    """One version of a fraction's reference pose."""

    fraction: int
    version: int
    created: str
    actor: str
    source: Literal["plan", "capture"]
    plan: str | None
    pose: dict[str, Any] = Field(description="centre_mm, gaze (unit vector), limbus_centre_mm "
                                 "(or null), WCS.")
    evidence: dict[str, Any] | None = Field(description="For a captured reference: capture_id, "
                                            "unit, calibration_id, eye_model_version, fit.")


class ReferenceList(BaseModel):
    """Every version of a fraction's reference pose, oldest first."""

    items: list[ReferenceResponse]


def _patient(record: Patient) -> PatientResponse:
    t = record.tolerances
    return PatientResponse(patient_id=record.patient_id, key=record.key, eye=record.eye,
                           unit=record.unit, tolerance_mm=t.translation_mm,
                           tolerance_gaze_deg=t.gaze_deg, min_confidence=t.min_confidence,
                           eye_model_version=record.eye_model_version, created=record.created,
                           updated=record.updated)


def _model(record: EyeModelVersion) -> EyeModelResponse:
    return EyeModelResponse(version=record.version, created=record.created, actor=record.actor,
                            population=record.model.population, model=record.model)


def _reference(record: ReferencePose) -> ReferenceResponse:
    return ReferenceResponse(fraction=record.fraction, version=record.version,
                             created=record.created, actor=record.actor, source=record.source,
                             plan=record.plan, pose=record.pose, evidence=record.evidence)


@router.put("/{patient_id}", summary="Create or update a patient",
            responses={201: {"model": PatientResponse, "description": "Created."},
                       422: {"description": "Bad body, or a unit the rig does not have."}})
async def put_patient(patient_id: PatientIdPath, body: PatientRequest, service: ServiceDep,
                      patients: PatientsDep, caller: PhysicistDep, response: Response,
                      ) -> PatientResponse:
    """Store a patient's treated eye, measuring unit and tolerances (physicists only; audited
    with the patient id hashed). 201 when created, 200 when updated."""
    service.unit_ids(body.unit)  # UnknownUnitError (422) for a unit the rig lacks
    tolerances = Tolerances(body.tolerance_mm, body.tolerance_gaze_deg, body.min_confidence)
    record, created = await run_in_threadpool(lambda: patients.put(
        patient_id, eye=body.eye, unit=body.unit, tolerances=tolerances, actor=caller.name))
    response.status_code = 201 if created else 200
    return _patient(record)


@router.get("/{patient_id}", summary="One patient", responses=_UNKNOWN)
async def get_patient(patient_id: PatientIdPath, patients: PatientsDep) -> PatientResponse:
    """A patient with the eye-model version in use."""
    return _patient(await run_in_threadpool(patients.get, patient_id))


@router.post("/{patient_id}/eye-models", status_code=201, summary="Import an eye model",
             responses=_UNKNOWN)
async def post_eye_model(patient_id: PatientIdPath, body: EyeModelSpec, patients: PatientsDep,
                         caller: PhysicistDep) -> EyeModelResponse:
    """Store a new version of the patient's eye model, used from now on (physicists only).

    ``{}`` stores the population defaults; ``globe_radius_mm`` a spherical globe;
    ``ellipsoid`` (``centre_mm``, ``semi_axes_mm``, ``orientation``) the MRI-derived anterior
    segment; ``cornea_radius_mm`` and ``limbus_diameter_mm`` default to 7.8 and 11.7 mm.
    """
    return _model(await run_in_threadpool(lambda: patients.add_eye_model(
        patient_id, body, actor=caller.name)))


@router.get("/{patient_id}/eye-models", summary="A patient's eye-model versions",
            responses=_UNKNOWN)
async def list_eye_models(patient_id: PatientIdPath, patients: PatientsDep) -> EyeModelList:
    """Every version, oldest first; the last is in use."""
    records = await run_in_threadpool(patients.eye_models, patient_id)
    return EyeModelList(items=[_model(r) for r in records])


@router.get("/{patient_id}/eye-models/{version}", summary="One eye-model version",
            responses={404: {"model": ErrorResponse, "description": "No such patient or "
                             "version."}})
async def get_eye_model(patient_id: PatientIdPath,
                        version: Annotated[int, Path(ge=1, le=MAX_SQL_INT)],
                        patients: PatientsDep) -> EyeModelResponse:
    """One stored version."""
    record = await run_in_threadpool(patients.eye_model, patient_id, version)
    if record is None:
        raise UnknownIdError(str(version), "eye-model version")
    return _model(record)


@router.put("/{patient_id}/fractions/{fraction}/reference", status_code=201,
            summary="Import a fraction's reference pose", responses=_UNKNOWN)
async def put_reference(patient_id: PatientIdPath, fraction: FractionPath,
                        body: ReferencePoseSpec, patients: PatientsDep, caller: PhysicistDep,
                        ) -> ReferenceResponse:
    """Store the planned pose (globe centre, gaze, optional limbus centre, WCS) as the
    fraction's next reference version (physicists only; the gaze is normalised)."""
    return _reference(await run_in_threadpool(lambda: patients.set_reference(
        patient_id, fraction, body.pose(), source="plan", plan=body.plan, actor=caller.name)))


@router.post("/{patient_id}/fractions/{fraction}/reference/capture", status_code=201,
             summary="Capture a fraction's reference pose at set-up",
             responses={**_UNKNOWN,
                        409: {"model": ErrorResponse, "description": "No active calibration, "
                              "or the daemon is busy."},
                        422: {"model": ErrorResponse, "description": "No eye could be "
                              "fitted, the pose is less confident than the patient's "
                              "min_confidence, or live tracking's blink test would take this "
                              "open eye for shut lids; the reason says why."}})
async def capture_reference(patient_id: PatientIdPath, fraction: FractionPath,
                            verification: VerificationDep, caller: OperatorDep,
                            ) -> ReferenceResponse:
    """Capture the patient's unit, reconstruct, fit the patient's eye model and store the pose
    as the fraction's next reference version, with its evidence. Operators may: the therapist
    who sets the patient up captures it (a new version; the earlier ones are kept, and the
    audit trail names who made each); the physicist owns the calibration, the plan's
    reference (``PUT``) and the eye model. A pose below the patient's ``min_confidence``, or
    one whose own capture tracking's blink test takes for shut lids (its gaze off), is not
    taken (422): every later check and tracked frame is compared with the reference."""
    return _reference(await run_in_threadpool(lambda: verification.capture_reference(
        patient_id, fraction, actor=caller.name)))


@router.get("/{patient_id}/fractions/{fraction}/reference", summary="A fraction's reference",
            responses={404: {"model": ErrorResponse, "description": "No such patient, or the "
                             "fraction has no reference."}})
async def get_reference(patient_id: PatientIdPath, fraction: FractionPath,
                        patients: PatientsDep) -> ReferenceResponse:
    """The reference in use (the newest version)."""
    return _reference(await run_in_threadpool(patients.reference, patient_id, fraction))


@router.get("/{patient_id}/fractions/{fraction}/references",
            summary="Every version of a fraction's reference", responses=_UNKNOWN)
async def list_references(patient_id: PatientIdPath, fraction: FractionPath,
                          patients: PatientsDep) -> ReferenceList:
    """Every version, oldest first; the last is in use."""
    records = await run_in_threadpool(patients.references, patient_id, fraction)
    return ReferenceList(items=[_reference(r) for r in records])


class DicomPlanResponse(BaseModel):
    """What an import of the plan's DICOM stored, and what it read."""

    eye_model: EyeModelResponse = Field(description="The new eye-model version.")
    reference: ReferenceResponse | None = Field(description="The fraction's new reference "
                                                "version; null when none was set (see notes).")
    read: dict[str, Any] = Field(description="planned_eye (the structure set's UID, the ROIs "
                                 "used and their fits in its frame, mm), registration_uid, "
                                 "wcs_frame_of_reference_uid, notes (what was not set, why).")


def _from_dicom(spec: type[_Spec], fields: dict[str, Any]) -> _Spec:
    """``fields`` read from DICOM as ``spec``; a figure out of its range is the file's fault
    (422 naming it), not the request's shape."""
    try:
        return spec.model_validate(fields)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(part) for part in first["loc"])
        raise FormatError("<uploaded DICOM>", where or None,
                          f"{first['msg']} (read: {first.get('input')!r})") from exc


@router.post("/{patient_id}/fractions/{fraction}/dicom", status_code=201,
             summary="Import the planned eye from DICOM",
             openapi_extra={"requestBody": {"required": True, "content": {
                 "application/zip": {"schema": {"type": "string", "format": "binary"}},
                 "application/dicom": {"schema": {"type": "string", "format": "binary"}}}}},
             responses={**_UNKNOWN,
                        413: {"model": ErrorResponse, "description": "The upload is too "
                              "large."},
                        422: {"model": ErrorResponse, "description": "Not one RT Structure Set "
                              "(and at most one Spatial Registration) with a globe ROI; the "
                              "reason names the object and attribute."}})
async def import_dicom_plan(patient_id: PatientIdPath, fraction: FractionPath, request: Request,
                            patients: PatientsDep, caller: PhysicistDep) -> DicomPlanResponse:
    """Read the planned eye from the plan's RT Structure Set and, with a Spatial Registration
    from its frame to the room's WCS, the planned pose; store them as the patient's next eye
    model and the fraction's next reference version (physicists only).

    The body is one DICOM object (``application/dicom``) or a zip of them
    (``application/zip``): one RT Structure Set, at most one Spatial Registration. The eye
    model: the globe ROI's ellipsoid turned into the WCS by the registration (without one, its
    sphere), the cornea ROI's radius and the limbus ROI's diameter where they exist. The
    reference pose (globe centre, gaze to the limbus or cornea, limbus centre; WCS) needs the
    registration and a cornea or limbus ROI; ``read.notes`` says why it was not set.
    """
    limit = request.app.state.settings.max_upload_mb * 2**20
    body = await _read_limited(request, limit)
    content_type = request.headers.get("content-type", "").split(";")[0].strip().lower()

    def store() -> DicomPlanResponse:
        patient = patients.get(patient_id)
        plan = dicom.read_plan(dicom.dicom_objects(body, content_type, limit), patient.eye)
        model = _from_dicom(EyeModelSpec, plan.eye_model)
        reference = None if plan.reference is None else _from_dicom(ReferencePoseSpec,
                                                                     plan.reference)
        stored_model = patients.add_eye_model(patient_id, model, actor=caller.name)
        stored_reference = None if reference is None else patients.set_reference(
            patient_id, fraction, reference.pose(), source="plan", plan=reference.plan,
            actor=caller.name)
        return DicomPlanResponse(
            eye_model=_model(stored_model),
            reference=None if stored_reference is None else _reference(stored_reference),
            read=plan.to_dict())

    return await run_in_threadpool(store)
