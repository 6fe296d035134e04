"""``/api/v1/captures``: take a capture, list them, find one again (also after a restart)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query
from fastapi.responses import FileResponse, Response
from starlette.concurrency import run_in_threadpool

from eyeserver.api.deps import ServiceDep
from eyeserver.api.schemas import (
    CaptureList,
    CaptureRequest,
    CaptureResponse,
    ErrorResponse,
    ReconstructionResponse,
)
from eyeserver.service.storage import CaptureRecord, UnknownIdError, is_capture_id

__all__ = ["router"]

router = APIRouter(tags=["captures"])


def _response(record: CaptureRecord) -> CaptureResponse:
    return CaptureResponse(id=record.id, kind=record.kind, unit=record.unit,
                           calibration_id=record.calibration_id, created=record.created,
                           frame_count=record.frame_count, status=record.status)


@router.post("/captures", status_code=201, summary="Take a capture",
             responses={409: {"model": ErrorResponse, "description": "The hardware is busy."},
                        422: {"model": ErrorResponse, "description": "Unknown unit."},
                        503: {"model": ErrorResponse, "description": "A device failed."},
                        504: {"model": ErrorResponse, "description": "A frame did not arrive."}})
async def create_capture(request: CaptureRequest, service: ServiceDep) -> CaptureResponse:
    """Capture one frame set of a unit, or of every unit interleaved (``"all"``).

    Answers once the bundle and its index row are durable, so an acknowledged capture is never
    lost. A failing device answers 503 (504 for a frame that did not arrive) and puts its unit
    in fault; the next capture reopens it.
    """
    record = await run_in_threadpool(service.capture, request.unit)
    return _response(record)


@router.get("/captures", summary="List captures")
async def list_captures(
    service: ServiceDep,
    limit: Annotated[int, Query(ge=1, le=1000, description="Page size.")] = 50,
    offset: Annotated[int, Query(ge=0, description="Captures to skip.")] = 0,
    unit: Annotated[str | None, Query(description="Only captures of this unit "
                                                  "(or 'all').")] = None,
) -> CaptureList:
    """Captures newest first, one page at a time."""
    records, total = await run_in_threadpool(service.store.list_captures, limit, offset, unit)
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


@router.post("/captures/{capture_id}/reconstruction", summary="Reconstruct a capture",
             responses={404: {"model": ErrorResponse, "description": "No such capture."},
                        409: {"model": ErrorResponse, "description": "No calibration is "
                              "active."},
                        422: {"model": ErrorResponse, "description": "The capture cannot be "
                              "reconstructed with the active calibration."}})
async def reconstruct_capture(capture_id: str, service: ServiceDep) -> ReconstructionResponse:
    """Reconstruct the capture's surface with the active calibration.

    The fused cloud is kept as the capture's ``cloud.ply`` (replacing an earlier one); the
    answer summarises it. Takes seconds: it runs on a worker thread.
    """
    summary = await run_in_threadpool(service.reconstruct, _checked(capture_id))
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
