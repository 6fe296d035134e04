"""``GET /api/v1/status``: the state machine, the devices' and units' health, the uptime."""

from __future__ import annotations

from dataclasses import asdict

from fastapi import APIRouter
from starlette.concurrency import run_in_threadpool

from eyeserver.api.deps import ServiceDep
from eyeserver.api.schemas import StatusResponse

__all__ = ["router"]

router = APIRouter(tags=["status"])


@router.get("/status", summary="What is the daemon doing?")
async def get_status(service: ServiceDep) -> StatusResponse:
    """The daemon's state, every device and unit with its health, the active calibration."""
    # Devices describe themselves and the store answers from SQLite: both may block.
    status = await run_in_threadpool(service.status)
    return StatusResponse.model_validate(asdict(status))
