"""``GET /api/v1/status``: the state machine, the devices' and units' health, the uptime.

With a valid token it is answered by :class:`eyeserver.api.fastpath.ReadFastPath` before it
reaches this route; the route documents it and answers when the fast path hands it on."""

from __future__ import annotations

from fastapi import APIRouter, Request
from starlette.concurrency import run_in_threadpool

from eyeserver.api.deps import ServiceDep
from eyeserver.api.fastpath import status_response
from eyeserver.api.schemas import StatusResponse

__all__ = ["router"]

router = APIRouter(tags=["status"])


@router.get("/status", summary="What is the daemon doing?")
async def get_status(service: ServiceDep, request: Request) -> StatusResponse:
    """The daemon's state, every device and unit with its health, the active calibration, and
    live tracking's beam hold."""
    # Devices describe themselves and the store answers from SQLite: both may block.
    return await run_in_threadpool(status_response, service,
                                   getattr(request.app.state, "tracking", None))
