"""``GET /api/v1/status``: the state machine, the devices' and units' health, the uptime."""

from __future__ import annotations

from dataclasses import asdict

from fastapi import APIRouter, Request
from starlette.concurrency import run_in_threadpool

from eyeserver.api.deps import ServiceDep
from eyeserver.api.schemas import StatusResponse, TrackingSummary
from eyeserver.service.tracking import TrackingControl

__all__ = ["router"]

router = APIRouter(tags=["status"])


@router.get("/status", summary="What is the daemon doing?")
async def get_status(service: ServiceDep, request: Request) -> StatusResponse:
    """The daemon's state, every device and unit with its health, the active calibration, and
    live tracking's beam hold."""
    # Devices describe themselves and the store answers from SQLite: both may block.
    status = await run_in_threadpool(service.status)
    tracking = getattr(request.app.state, "tracking", None)
    summary = None
    if isinstance(tracking, TrackingControl):
        now = tracking.status()
        summary = TrackingSummary(running=now["running"], beam_hold=now["beam_hold"],
                                  stalled=now["stalled"])
    return StatusResponse.model_validate({**asdict(status), "tracking": summary})
