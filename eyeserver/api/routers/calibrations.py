"""``/api/v1/calibrations``: upload a calibration, list and inspect them, choose the active one,
download one with its inputs and compare two."""

from __future__ import annotations

from collections.abc import Iterator
from typing import IO, Annotated, Any

from fastapi import APIRouter, HTTPException, Query, Request
from fastapi.responses import StreamingResponse
from starlette.background import BackgroundTask
from starlette.concurrency import run_in_threadpool

from eyeserver.api.auth import PhysicistDep
from eyeserver.api.deps import ServiceDep
from eyeserver.api.schemas import CalibrationList, CalibrationResponse, ErrorResponse
from eyeserver.service.calibration_files import Lineage, calibration_archive, compare, lineage
from eyeserver.service.storage import (
    CalibrationRecord,
    Store,
    UnknownIdError,
    is_calibration_id,
)
from eyeserver.service.uploads import UploadTooLargeError

__all__ = ["router"]

router = APIRouter(tags=["calibrations"])

_ZIP_TYPES = ("application/zip", "application/x-zip-compressed")


def _response(record: CalibrationRecord, line: Lineage | None = None) -> CalibrationResponse:
    return CalibrationResponse(id=record.id, created=record.created, imported=record.imported,
                               active=record.active, status=record.status, source=record.source,
                               quality=dict(record.quality),
                               version=None if line is None else line.version,
                               parent_id=None if line is None else line.parent_id,
                               session_id=None if line is None else line.session_id)


def _with_lineage(store: Store, record: CalibrationRecord) -> CalibrationResponse:
    return _response(record, lineage(store, record))


def _checked(calibration_id: str) -> str:
    if not is_calibration_id(calibration_id):
        raise UnknownIdError(calibration_id, "calibration")
    return calibration_id


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
    (``calibration.json`` and ``arrays.npz``, flat or in one folder), or a calibration
    downloaded from a daemon (its evidence under ``inputs/`` is not imported: keep the zip).

    The calibration is checked as the pipeline will read it and must have been made for this
    daemon's rig. It is not activated. Physicists only.
    """
    content_type = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if content_type not in _ZIP_TYPES:
        raise HTTPException(415, f"the body must be application/zip, not {content_type!r}")
    limit = request.app.state.settings.max_upload_mb * 2**20
    archive = await _read_limited(request, limit)
    record = await run_in_threadpool(lambda: service.import_calibration(archive, actor=caller.name))
    return await run_in_threadpool(_with_lineage, service.store, record)


@router.get("/calibrations", summary="List calibrations")
async def list_calibrations(service: ServiceDep) -> CalibrationList:
    """Every stored calibration, newest first, with its quality figures."""
    def listing() -> CalibrationList:
        records = service.store.list_calibrations()
        return CalibrationList(items=[_response(r, lineage(service.store, r, records))
                                     for r in records])

    return await run_in_threadpool(listing)


@router.get("/calibrations/compare", summary="Compare two calibrations",
            responses={404: {"model": ErrorResponse, "description": "No such calibration."}})
async def compare_calibrations(
    service: ServiceDep,
    a: Annotated[str, Query(description="The older calibration's id.")],
    b: Annotated[str, Query(description="The newer calibration's id.")],
) -> dict[str, Any]:
    """How far B has drifted from A, per camera: ``rotation_deg`` and ``centre_shift_mm``
    between the two WCS poses, ``focal_change_px`` and ``principal_point_change_px``, and, when
    both have phase-to-height models, ``phase_to_height`` (median and largest |Z_B − Z_A| at
    sample pixels over the calibrated volume); ``summary`` holds the largest of each."""
    return await run_in_threadpool(compare, service.store, _checked(a), _checked(b))


@router.get("/calibrations/{calibration_id}", summary="One calibration",
            responses={404: {"model": ErrorResponse, "description": "No such calibration."}})
async def get_calibration(calibration_id: str, service: ServiceDep) -> CalibrationResponse:
    """A calibration's metadata and quality figures."""
    record = await run_in_threadpool(service.store.get_calibration, _checked(calibration_id))
    return await run_in_threadpool(_with_lineage, service.store, record)


def _chunks(archive: IO[bytes]) -> Iterator[bytes]:
    # A plain iterator: Starlette reads it on a worker thread, off the event loop.
    try:
        while chunk := archive.read(1 << 20):
            yield chunk
    finally:
        archive.close()


@router.get("/calibrations/{calibration_id}/download", summary="Download a calibration",
            response_class=StreamingResponse,
            responses={200: {"content": {"application/zip": {}},
                             "description": "One folder named after the calibration: "
                             "calibration.json, arrays.npz and inputs/<capture id>/ bundles."},
                       404: {"model": ErrorResponse, "description": "No such calibration."}})
async def download_calibration(calibration_id: str, service: ServiceDep) -> StreamingResponse:
    """The calibration directory as a zip, with the input bundles of a calibration made in a
    guided session (the evidence) under ``inputs/``. Unzipped, the folder is a calibration
    directory the command line reads and each ``inputs/<capture id>/`` a capture bundle."""
    archive, size = await run_in_threadpool(calibration_archive, service.store,
                                            _checked(calibration_id))
    return StreamingResponse(
        _chunks(archive), media_type="application/zip",
        headers={"Content-Disposition": f'attachment; filename="{calibration_id}.zip"',
                 "Content-Length": str(size)},
        background=BackgroundTask(archive.close))


@router.post("/calibrations/{calibration_id}/activate", summary="Activate a calibration",
             responses={404: {"model": ErrorResponse, "description": "No such calibration."},
                        409: {"model": ErrorResponse, "description": "The hardware is busy."}})
async def activate_calibration(calibration_id: str, service: ServiceDep,
                               caller: PhysicistDep) -> CalibrationResponse:
    """Make this calibration the one new captures and reconstructions use (physicists only).

    Only while the daemon is idle (or in fault): a capture in progress answers 409.
    """
    _checked(calibration_id)
    record = await run_in_threadpool(
        lambda: service.activate_calibration(calibration_id, actor=caller.name))
    return await run_in_threadpool(_with_lineage, service.store, record)
