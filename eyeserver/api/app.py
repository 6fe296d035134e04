"""The FastAPI application factory.

Nothing happens at import: :func:`create_app` builds a fresh app for the settings it is given
(tests build one per test), and the lifespan does the start-up and shut-down work.
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator, Callable
from contextlib import AbstractAsyncContextManager, asynccontextmanager
from typing import Annotated, Any

from fastapi import Depends, FastAPI
from fastapi.responses import JSONResponse
from starlette.concurrency import run_in_threadpool
from starlette.types import Receive, Scope, Send

import eyeserver
from eyeserver.api import apidocs, asyncapi, examples
from eyeserver.api.auth import Caller, TokenTable, require
from eyeserver.api.errors import AUTH_RESPONSES, install_error_handlers
from eyeserver.api.fastpath import ReadFastPath
from eyeserver.api.routers import (
    audit,
    calibration_sessions,
    calibrations,
    captures,
    console,
    devices,
    events,
    health,
    jobs,
    metrics,
    patients,
    pose,
    qa,
    sim,
    status,
    tracking,
    whoami,
)
from eyeserver.config import Settings
from eyeserver.service.calibration_session import CalibrationSessions
from eyeserver.service.core import Service
from eyeserver.service.operations import operations
from eyeserver.service.patients import Patients
from eyeserver.service.tracking import TrackingControl
from eyeserver.service.verification import PoseVerification

__all__ = ["API_PREFIX", "create_app"]

#: Every route of this API version lives under this prefix.
API_PREFIX = "/api/v1"

_log = logging.getLogger(__name__)


def _lifespan(settings: Settings) -> Callable[[FastAPI], AbstractAsyncContextManager[None]]:
    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        data_dir = settings.ensure_data_dir()
        _log.info(
            "eyeserver starting",
            extra={
                "version": eyeserver.__version__,
                "data_dir": str(data_dir),
                "room_file": None if settings.room_file is None else str(settings.room_file),
            },
        )
        app.state.tokens = await run_in_threadpool(TokenTable.for_settings, settings)
        # Opening devices and the store blocks; it runs on a worker thread, as does closing.
        service = Service(settings)
        service.audit.set_roles(app.state.tokens.roles())
        await run_in_threadpool(service.open)
        app.state.service = service
        app.state.calibration_sessions = CalibrationSessions(service)
        app.state.patients = Patients(service.store, service.audit)
        app.state.verification = PoseVerification(service, app.state.patients)
        app.state.tracking = TrackingControl(service, app.state.patients,
                                             workers=settings.tracking_workers,
                                             deadline_s=settings.tracking_deadline_ms / 1e3)
        try:
            # systemd: READY=1 now, WATCHDOG=1 while healthy, STOPPING=1 on leaving; retention.
            async with operations(service, settings):
                yield
        finally:
            await run_in_threadpool(app.state.tracking.close)
            del app.state.tracking
            del app.state.service
            del app.state.verification, app.state.patients
            await run_in_threadpool(app.state.calibration_sessions.close_all)
            del app.state.calibration_sessions
            await run_in_threadpool(service.close)
            _log.info("eyeserver stopped")

    return lifespan


class _Daemon(FastAPI):
    """FastAPI with :class:`ReadFastPath` in front of everything, its middleware included:
    health and status reads are answered before any of FastAPI's per-request machinery
    (issue 35, item 13)."""

    def __init__(self, **options: Any) -> None:
        super().__init__(**options)
        self._reads = ReadFastPath(super().__call__, state=self.state, prefix=API_PREFIX)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        await self._reads(scope, receive, send)


def create_app(settings: Settings) -> FastAPI:
    """Build the eyeserver API for ``settings``.

    The settings are kept in ``app.state.settings`` for the routers; the lifespan opens a
    :class:`~eyeserver.service.core.Service` (store, then rig) into ``app.state.service`` and
    closes it on shut-down, after reading the bearer tokens into ``app.state.tokens``
    (:mod:`eyeserver.api.auth`). ``/health`` uses neither. The OpenAPI document is
    served at ``/api/v1/openapi.json`` and its interactive view at ``/api/v1/docs``, without a
    token unless ``public_api_docs`` is off (then the document needs one and the view is off).
    """
    app = _Daemon(
        title="eyeserver",
        summary="Eye surface and pose by single-shot fringe projection.",
        version=eyeserver.__version__,
        lifespan=_lifespan(settings),
        openapi_url=f"{API_PREFIX}/openapi.json" if settings.public_api_docs else None,
        docs_url=None,  # served with its assets, not from a CDN (apidocs.mount below)
        redoc_url=None,
    )
    app.state.settings = settings
    if settings.public_api_docs:
        apidocs.mount(app, API_PREFIX)
    else:
        async def openapi_document(_: Annotated[Caller, Depends(require("operator"))]
                                   ) -> JSONResponse:
            return JSONResponse(app.openapi())

        app.add_api_route(f"{API_PREFIX}/openapi.json", openapi_document,
                          include_in_schema=False)
    asyncapi.mount(app, API_PREFIX, public=settings.public_api_docs)
    install_error_handlers(app)
    app.include_router(health.router, prefix=API_PREFIX)
    # WebSocket routes authenticate themselves before accepting (websocket_caller).
    app.include_router(events.router, prefix=API_PREFIX)
    app.include_router(tracking.ws_router, prefix=API_PREFIX)
    # Everything else needs a token; routes that need more than an operator say so themselves.
    authenticated = [Depends(require("operator"))]
    for router in (status.router, devices.router, captures.router, calibrations.router,
                   sim.router, audit.router, jobs.router, calibration_sessions.router,
                   patients.router, pose.router, tracking.router, whoami.router, qa.router):
        app.include_router(router, prefix=API_PREFIX, dependencies=authenticated,
                           responses=AUTH_RESPONSES)
    # Where Prometheus looks by default, outside the versioned API; a token all the same.
    app.include_router(metrics.router, dependencies=authenticated, responses=AUTH_RESPONSES)
    # The browser console's files (no data, no token): /console/.
    console.mount(app)
    _document_every_answer(app)
    examples.install(app, API_PREFIX)
    return app


_EVERY_OPERATION = {
    "500": "A bug (the body says only that; the log has the details).",
    "507": "The data directory's disk is full; nothing was changed.",
}
_WITH_A_BODY = {"400": "The body could not be read (not UTF-8, not JSON)."}


def _document_every_answer(app: FastAPI) -> None:
    """Make the OpenAPI document describe every answer the daemon gives: a validation error's
    body is :class:`~eyeserver.api.schemas.ErrorResponse` like every other error's (FastAPI
    documents its own list under ``detail``), and every operation may answer 500 and 507, one
    with a body also 400 (issue 35: 596 fuzzed answers had a status the document did not
    list)."""
    generate = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is not None:
            return app.openapi_schema
        schema = generate()
        components = schema.setdefault("components", {}).setdefault("schemas", {})
        if "ErrorResponse" in components:
            components["HTTPValidationError"] = {**components["ErrorResponse"],
                                                 "title": "HTTPValidationError"}
        error = {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorResponse"}}}
        for methods in schema.get("paths", {}).values():
            for operation in methods.values():
                answers = operation.setdefault("responses", {})
                extra = {**_EVERY_OPERATION,
                         **(_WITH_A_BODY if "requestBody" in operation else {})}
                for status_code, description in extra.items():
                    answers.setdefault(status_code, {"description": description,
                                                     "content": error})
        app.openapi_schema = schema
        return schema

    app.openapi = openapi  # type: ignore[method-assign]
