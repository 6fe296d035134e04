"""``/api/v1/calibrations``: upload a calibration, list and inspect them, choose the active one."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, Request
from starlette.concurrency import run_in_threadpool

from eyeserver.api.auth import PhysicistDep
from eyeserver.api.deps import ServiceDep
from eyeserver.api.schemas import CalibrationList, CalibrationResponse, ErrorResponse
from eyeserver.service.storage import CalibrationRecord, UnknownIdError, is_calibration_id
from eyeserver.service.uploads import UploadTooLargeError

__all__ = ["router"]

router = APIRouter(tags=["calibrations"])

_ZIP_TYPES = ("application/zip", "application/x-zip-compressed")


def _response(record: CalibrationRecord) -> CalibrationResponse:
    return CalibrationResponse(id=record.id, created=record.created, imported=record.imported,
                               active=record.active, status=record.status, source=record.source,
                               quality=dict(record.quality))


async def _read_limited(request: Request, limit: int) -> bytes:
    """The request body, refused (413) as soon as it grows past ``limit`` bytes."""
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > limit:
        raise UploadTooLargeError(f"the upload ({declared} bytes) exceeds {limit} bytes")
    body = bytearray()
    async for chunk in request.stream():
        body += chunk
        if len(body) > limit:
            raise UploadTooLargeError(f"the upload exceeds {limit} bytes")
    return bytes(body)


@router.post(
    "/calibrations", status_code=201, summary="Upload a calibration",
    openapi_extra={"requestBody": {"required": True, "content": {"application/zip": {
        "schema": {"type": "string", "format": "binary"}}}}},
    responses={413: {"model": ErrorResponse, "description": "The archive is too large."},
               415: {"model": ErrorResponse, "description": "The body is not application/zip."},
               422: {"model": ErrorResponse, "description": "Not a safe zip of a valid "
                     "calibration for this rig; the reason names the member or field."}})
async def import_calibration(request: Request, service: ServiceDep,
                             caller: PhysicistDep) -> CalibrationResponse:
    """Store a calibration: the body is a zip of the directory ``eyeserver calibrate`` writes
    (``calibration.json`` and ``arrays.npz``, flat or in one folder).

    The calibration is checked as the pipeline will read it and must have been made for this
    daemon's rig. It is not activated. Physicists only.
    """
    content_type = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if content_type not in _ZIP_TYPES:
        raise HTTPException(415, f"the body must be application/zip, not {content_type!r}")
    limit = request.app.state.settings.max_upload_mb * 2**20
    archive = await _read_limited(request, limit)
    record = await run_in_threadpool(lambda: service.import_calibration(archive, actor=caller.name))
    return _response(record)


@router.get("/calibrations", summary="List calibrations")
async def list_calibrations(service: ServiceDep) -> CalibrationList:
    """Every stored calibration, newest first, with its quality figures."""
    records = await run_in_threadpool(service.store.list_calibrations)
    return CalibrationList(items=[_response(r) for r in records])


@router.get("/calibrations/{calibration_id}", summary="One calibration",
            responses={404: {"model": ErrorResponse, "description": "No such calibration."}})
async def get_calibration(calibration_id: str, service: ServiceDep) -> CalibrationResponse:
    """A calibration's metadata and quality figures."""
    if not is_calibration_id(calibration_id):
        raise UnknownIdError(calibration_id, "calibration")
    record = await run_in_threadpool(service.store.get_calibration, calibration_id)
    return _response(record)


@router.post("/calibrations/{calibration_id}/activate", summary="Activate a calibration",
             responses={404: {"model": ErrorResponse, "description": "No such calibration."},
                        409: {"model": ErrorResponse, "description": "The hardware is busy."}})
async def activate_calibration(calibration_id: str, service: ServiceDep,
                               caller: PhysicistDep) -> CalibrationResponse:
    """Make this calibration the one new captures and reconstructions use (physicists only).

    Only while the daemon is idle (or in fault): a capture in progress answers 409.
    """
    if not is_calibration_id(calibration_id):
        raise UnknownIdError(calibration_id, "calibration")
    record = await run_in_threadpool(
        lambda: service.activate_calibration(calibration_id, actor=caller.name))
    return _response(record)
