"""``GET /api/v1/health``: is the daemon up? Needs no authentication."""

from __future__ import annotations

from fastapi import APIRouter

import eyeserver
from eyeserver.api.schemas import HealthResponse

__all__ = ["router"]

router = APIRouter(tags=["health"])


@router.get("/health", summary="Is the daemon up?")
async def get_health() -> HealthResponse:
    """Answer 200 whenever the daemon is running; used by probes, scripts and tests."""
    return HealthResponse(status="ok", version=eyeserver.__version__)
