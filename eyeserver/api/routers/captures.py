"""``/api/v1/captures``: take a capture, list and filter them, find one again (also after a
restart), fetch its bundle and images, reconstruct it, delete it (physicists, audited)."""

from __future__ import annotations

from collections.abc import Iterator
from datetime import datetime
from typing import IO, Annotated

from fastapi import APIRouter, Body, HTTPException, Query
from fastapi.responses import FileResponse, Response, StreamingResponse
from pydantic import BeforeValidator
from starlette.background import BackgroundTask
from starlette.concurrency import run_in_threadpool

from eyeserver.api.auth import PhysicistDep
from eyeserver.api.deps import ServiceDep
from eyeserver.api.schemas import (
    MAX_SQL_INT,
    CaptureList,
    CaptureRequest,
    CaptureResponse,
    ErrorResponse,
    ReconstructionRequest,
    ReconstructionResponse,
)
from eyeserver.io import BundleKind
from eyeserver.reconstruction import ReconstructionOptions
from eyeserver.service.capture_files import bundle_archive, bundle_image
from eyeserver.service.storage import CaptureRecord, UnknownIdError, is_capture_id

__all__ = ["router"]

router = APIRouter(tags=["captures"])

_CHUNK_BYTES = 2**20
_CALIBRATION_ID_PATTERN = r"^cal-\d{8}T\d{9}Z-[0-9a-f]{4}$"


def _iso8601(value: object) -> object:
    # Stricter than pydantic's own datetime parsing, which also takes Unix times and naive times.
    if not isinstance(value, str):
        raise ValueError("must be an ISO 8601 time")
    try:
        moment = datetime.fromisoformat(value)
    except ValueError:
        raise ValueError(f"not an ISO 8601 time: {value!r} (e.g. 2026-11-23T15:12:00Z)"
                         ) from None
    if moment.tzinfo is None:
        raise ValueError(f"{value!r} has no time zone: add Z for UTC")
    return moment


_UtcTime = Annotated[datetime, BeforeValidator(_iso8601)]


def _response(record: CaptureRecord) -> CaptureResponse:
    return CaptureResponse(id=record.id, kind=record.kind, unit=record.unit,
                           calibration_id=record.calibration_id, created=record.created,
                           frame_count=record.frame_count, status=record.status)


@router.post("/captures", status_code=201, summary="Take a capture",
             responses={409: {"model": ErrorResponse, "description": "The daemon is "
                              "calibrating or tracking."},
                        422: {"model": ErrorResponse, "description": "Unknown unit."},
                        503: {"model": ErrorResponse, "description": "A device failed, or the "
                              "acquisition queue is full."},
                        504: {"model": ErrorResponse, "description": "A frame did not arrive."}})
async def create_capture(request: CaptureRequest, service: ServiceDep) -> CaptureResponse:
    """Capture one frame set of a unit, or of every unit interleaved (``"all"``).

    Answers once the bundle and its index row are durable, so an acknowledged capture is never
    lost. A capture asked for while others run waits its turn; a full acquisition queue answers
    503 at once. A failing device answers 503 (504 for a frame that did not arrive) and puts its
    unit in fault; the next capture, or the background retry, reopens it.
    """
    record = await run_in_threadpool(service.capture, request.unit)
    return _response(record)


@router.get("/captures", summary="List captures",
            responses={422: {"description": "A malformed filter: kind, calibration id, time, "
                             "or since after until."}})
async def list_captures(
    service: ServiceDep,
    limit: Annotated[int, Query(ge=1, le=1000, description="Page size.")] = 50,
    offset: Annotated[int, Query(ge=0, le=MAX_SQL_INT, description="Captures to skip.")] = 0,
    unit: Annotated[str | None, Query(description="Only captures of this unit "
                                                  "(or 'all').")] = None,
    kind: Annotated[BundleKind | None, Query(description="Only captures of this bundle "
                                                         "kind.")] = None,
    calibration_id: Annotated[str | None, Query(
        pattern=_CALIBRATION_ID_PATTERN,
        description="Only captures taken while this calibration was active.")] = None,
    since: Annotated[_UtcTime | None, Query(
        description="Only captures created at or after this time (ISO 8601 with a time zone, "
        "e.g. 2026-11-23T15:00:00Z).")] = None,
    until: Annotated[_UtcTime | None, Query(
        description="Only captures created before this time (ISO 8601 with a time zone).")
    ] = None,
) -> CaptureList:
    """Captures newest first, one page at a time; every filter given must hold."""
    if since is not None and until is not None and since > until:
        raise HTTPException(422, f"since ({since.isoformat()}) must not be after until "
                                 f"({until.isoformat()})")
    records, total = await run_in_threadpool(
        lambda: service.store.list_captures(limit, offset, unit, since, until=until, kind=kind,
                                            calibration_id=calibration_id))
    return CaptureList(items=[_response(r) for r in records], total=total, limit=limit,
                       offset=offset)


@router.get("/captures/{capture_id}", summary="One capture",
            responses={404: {"model": ErrorResponse, "description": "No such capture."}})
async def get_capture(capture_id: str, service: ServiceDep) -> CaptureResponse:
    """A capture's metadata, found again after a restart or a crash."""
    if not is_capture_id(capture_id):
        raise UnknownIdError(capture_id, "capture")
    record = await run_in_threadpool(service.store.get_capture, capture_id)
    return _response(record)


def _checked(capture_id: str) -> str:
    if not is_capture_id(capture_id):
        raise UnknownIdError(capture_id, "capture")
    return capture_id


@router.delete("/captures/{capture_id}", status_code=204, summary="Delete a capture",
               response_class=Response,
               responses={204: {"description": "Deleted, with its cloud and summary."},
                          404: {"model": ErrorResponse, "description": "No such capture."},
                          422: {"description": "No reason given."}})
async def delete_capture(
    capture_id: str, service: ServiceDep, caller: PhysicistDep,
    reason: Annotated[str, Query(min_length=1, max_length=1000, pattern=r"\S",
                                 description="Why it is deleted; kept in the audit log with "
                                 "the caller's name.", examples=["test shot, lens cap on"])],
) -> Response:
    """Delete a capture: its bundle, cloud and summary, and its index entry (physicists only).

    The request is written to the audit log (who, when, why) before anything is removed; a
    deletion interrupted by a crash is finished at the next start. Nothing else is deleted.
    The reason is a query parameter (``?reason=…``): a body on DELETE is dropped by some
    clients and proxies.
    """
    await run_in_threadpool(lambda: service.delete_capture(_checked(capture_id),
                                                           actor=caller.name, reason=reason))
    return Response(status_code=204)


def _chunks(archive: IO[bytes]) -> Iterator[bytes]:
    # A plain iterator: Starlette reads it on a worker thread, off the event loop.
    try:
        while chunk := archive.read(_CHUNK_BYTES):
            yield chunk
    finally:
        archive.close()


@router.get("/captures/{capture_id}/bundle.zip", summary="A capture's bundle as a zip",
            response_class=StreamingResponse,
            responses={200: {"content": {"application/zip": {}},
                             "description": "One folder named after the capture holding "
                             "bundle.json and its PNG images, byte for byte (FORMATS.md)."},
                       404: {"model": ErrorResponse, "description": "No such capture, or its "
                             "bundle is missing."}})
async def get_bundle_zip(capture_id: str, service: ServiceDep) -> StreamingResponse:
    """The capture bundle (``bundle.json`` and the images it names) as a zip archive.

    Unzipped, it is a bundle directory the command line reads. Images are stored, not
    deflated (PNG is compressed already); clouds and summaries have their own routes.
    """
    archive, size = await run_in_threadpool(bundle_archive, service.store, _checked(capture_id))
    return StreamingResponse(
        _chunks(archive), media_type="application/zip",
        headers={"Content-Disposition": f'attachment; filename="{capture_id}.zip"',
                 "Content-Length": str(size)},
        background=BackgroundTask(archive.close))  # also when the client hangs up early


@router.get("/captures/{capture_id}/frames/{frame}/{camera}.png", summary="One stored image",
            response_class=Response,
            responses={200: {"content": {"image/png": {}},
                             "description": "The image as stored: single-channel PNG, 8- or "
                             "16-bit (a bundle's bit_depth applies)."},
                       404: {"model": ErrorResponse, "description": "No such capture, frame, "
                             "or image of that camera in the frame; the reason says which."}})
async def get_image(capture_id: str, frame: int, camera: str, service: ServiceDep) -> Response:
    """One camera's image of one frame (``frame`` is the bundle's frame index)."""
    png = await run_in_threadpool(bundle_image, service.store, _checked(capture_id), frame,
                                  camera)
    return Response(png, media_type="image/png")


@router.post("/captures/{capture_id}/reconstruction", summary="Reconstruct a capture",
             responses={404: {"model": ErrorResponse, "description": "No such capture."},
                        409: {"model": ErrorResponse, "description": "No calibration is "
                              "active."},
                        422: {"model": ErrorResponse, "description": "Bad options, or the "
                              "capture cannot be reconstructed with the active calibration."},
                        503: {"model": ErrorResponse, "description": "The reconstruction queue "
                              "is full."}})
async def reconstruct_capture(
    capture_id: str, service: ServiceDep,
    options: Annotated[ReconstructionRequest | None, Body(
        description="Optional: method, depth prior, region and minimum quality (the options "
        "of 'eyeserver reconstruct'); without a body, the defaults.")] = None,
) -> ReconstructionResponse:
    """Reconstruct the capture's surface with the active calibration.

    The fused cloud is kept as the capture's ``cloud.ply`` and this answer as its
    ``reconstruction`` (both replacing earlier ones). Takes seconds: it runs on a worker thread.
    """
    chosen = options or ReconstructionRequest()
    settings = ReconstructionOptions(
        method=chosen.method, depth_prior_mm=chosen.depth_prior_mm,
        roi=None if chosen.roi is None else tuple(chosen.roi), min_quality=chosen.min_quality)
    summary = await run_in_threadpool(service.reconstruct, _checked(capture_id), settings)
    return ReconstructionResponse.model_validate(summary)


@router.get("/captures/{capture_id}/reconstruction", summary="A capture's reconstruction",
            responses={404: {"model": ErrorResponse, "description": "No such capture, or it "
                             "has not been reconstructed."}})
async def get_reconstruction(capture_id: str, service: ServiceDep) -> ReconstructionResponse:
    """The summary of the capture's last reconstruction, as its POST answered (with the
    options used), kept beside its cloud."""
    summary = await run_in_threadpool(service.reconstruction_summary, _checked(capture_id))
    return ReconstructionResponse.model_validate(summary)


@router.get("/captures/{capture_id}/cloud.ply", summary="A capture's point cloud",
            response_class=FileResponse,
            responses={200: {"content": {"application/octet-stream": {}},
                             "description": "Binary little-endian PLY (FORMATS.md)."},
                       404: {"model": ErrorResponse, "description": "No such capture, or it "
                             "has not been reconstructed."}})
async def get_cloud(capture_id: str, service: ServiceDep) -> FileResponse:
    """The stored cloud of a reconstructed capture: x, y, z in mm, quality, camera index."""
    path = await run_in_threadpool(service.cloud_path, _checked(capture_id))
    return FileResponse(path, media_type="application/octet-stream",
                        filename=f"{capture_id}.ply")


@router.get("/captures/{capture_id}/preview.png", summary="A height map of a capture",
            response_class=Response,
            responses={200: {"content": {"image/png": {}},
                             "description": "Z colour-coded over X and Y (turbo: blue low, "
                             "red high)."},
                       404: {"model": ErrorResponse, "description": "No such capture, or it "
                             "has not been reconstructed."}})
async def get_preview(capture_id: str, service: ServiceDep) -> Response:
    """A colour-coded height map of the capture's stored cloud, seen along Z."""
    png = await run_in_threadpool(service.preview_png, _checked(capture_id))
    return Response(png, media_type="image/png")
