"""The FastAPI application factory.

Nothing happens at import: :func:`create_app` builds a fresh app for the settings it is given
(tests build one per test), and the lifespan does the start-up and shut-down work.
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator, Callable
from contextlib import AbstractAsyncContextManager, asynccontextmanager

from fastapi import FastAPI

import eyeserver
from eyeserver.api.errors import install_error_handlers
from eyeserver.api.routers import health
from eyeserver.config import Settings

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
        try:
            yield
        finally:
            _log.info("eyeserver stopped")

    return lifespan


def create_app(settings: Settings) -> FastAPI:
    """Build the eyeserver API for ``settings``.

    The settings are kept in ``app.state.settings`` for the routers. The OpenAPI document is
    served at ``/api/v1/openapi.json`` and its interactive view at ``/api/v1/docs``.
    """
    app = FastAPI(
        title="eyeserver",
        summary="Eye surface and pose by single-shot fringe projection.",
        version=eyeserver.__version__,
        lifespan=_lifespan(settings),
        openapi_url=f"{API_PREFIX}/openapi.json",
        docs_url=f"{API_PREFIX}/docs",
        redoc_url=None,
    )
    app.state.settings = settings
    install_error_handlers(app)
    app.include_router(health.router, prefix=API_PREFIX)
    return app
