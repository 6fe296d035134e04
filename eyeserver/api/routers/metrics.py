"""``GET /metrics``: the daemon's figures in the Prometheus text format.

At the root, not under ``/api/v1``, where scrapers look by default. It needs a bearer token of
any role, like everything but the health check (the figures name devices and show activity):
Prometheus sends one with ``authorization: {credentials: <token>}`` in its scrape config
(``credentials_file`` to keep it out of the config). See :mod:`eyeserver.service.metrics` for
the metrics.
"""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import Response
from starlette.concurrency import run_in_threadpool

from eyeserver.api.deps import ServiceDep
from eyeserver.service.metrics import CONTENT_TYPE

__all__ = ["router"]

router = APIRouter(tags=["metrics"])


@router.get("/metrics", summary="Prometheus metrics", response_class=Response,
            responses={200: {"content": {CONTENT_TYPE: {}},
                             "description": "The Prometheus text format, version 0.0.4."}})
async def get_metrics(service: ServiceDep) -> Response:
    """Frames, captures, reconstruction times, queues, events, devices and state."""
    # Devices describe themselves at scrape time: that may block.
    body = await run_in_threadpool(service.metrics.render)
    return Response(content=body, media_type=CONTENT_TYPE)
