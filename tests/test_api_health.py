"""The app factory, the health route and the mapping of eyeserver's errors to HTTP answers."""

from __future__ import annotations

import asyncio
import os
from pathlib import Path

import httpx
import pytest
from fastapi import FastAPI

import eyeserver
from eyeserver.api import create_app
from eyeserver.config import Settings
from eyeserver.errors import (
    ConfigError,
    DeviceDisconnectedError,
    DeviceError,
    DeviceNotOpenError,
    DeviceTimeoutError,
    DeviceValueError,
    EyeserverError,
    FormatError,
    NotBuiltError,
    StateConflictError,
)


@pytest.fixture
def settings(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Settings:
    for name in list(os.environ):
        if name.upper().startswith("EYESERVER_"):
            monkeypatch.delenv(name)
    return Settings.load(data_dir=tmp_path / "data")


@pytest.fixture
def app(settings: Settings) -> FastAPI:
    return create_app(settings)


def get(app: FastAPI, path: str) -> httpx.Response:
    """GET ``path`` from ``app`` in process, inside its lifespan as under a real server."""

    async def run() -> httpx.Response:
        async with app.router.lifespan_context(app):
            # raise_app_exceptions=False: a crashing route gives its 500 answer, as over a socket.
            transport = httpx.ASGITransport(app=app, raise_app_exceptions=False)
            async with httpx.AsyncClient(transport=transport, base_url="http://test") as client:
                return await client.get(path)

    return asyncio.run(run())


def test_health_answers_ok_with_the_version(app: FastAPI) -> None:
    response = get(app, "/api/v1/health")

    assert response.status_code == 200
    assert response.json() == {"status": "ok", "version": eyeserver.__version__}


def test_unknown_path_is_a_json_404(app: FastAPI) -> None:
    response = get(app, "/api/v1/no-such-thing")

    assert response.status_code == 404
    assert response.headers["content-type"] == "application/json"
    assert response.json() == {"detail": "Not Found"}


def test_lifespan_creates_the_data_dir(settings: Settings, app: FastAPI) -> None:
    get(app, "/api/v1/health")

    assert settings.data_dir.is_dir()


def test_building_the_app_has_no_side_effects(settings: Settings) -> None:
    create_app(settings)

    assert not settings.data_dir.exists()


def test_openapi_is_served_under_the_version_prefix(app: FastAPI) -> None:
    response = get(app, "/api/v1/openapi.json")

    assert response.status_code == 200
    assert "/api/v1/health" in response.json()["paths"]


@pytest.mark.parametrize(
    ("error", "status_code"),
    [
        (StateConflictError("a capture is running"), 409),
        (DeviceTimeoutError("cam-1", "no frame within 500 ms"), 504),
        (DeviceValueError("cam-1", "exposure_us 0 out of range"), 422),
        (DeviceError("cam-1", "sensor fault"), 503),
        (DeviceDisconnectedError("cam-1", "unplugged"), 503),
        (DeviceNotOpenError("cam-1", "not open"), 503),
        (NotBuiltError("tracking is not built yet"), 501),
        (FormatError("rig.json", "cameras", "missing"), 422),
        (ConfigError("bad room file"), 422),
        (EyeserverError("something else"), 500),
    ],
    ids=lambda value: type(value).__name__ if isinstance(value, Exception) else str(value),
)
def test_eyeserver_errors_become_json_with_their_status(
    app: FastAPI, error: EyeserverError, status_code: int
) -> None:
    @app.get("/api/v1/test-error")
    async def fail() -> None:
        raise error

    response = get(app, "/api/v1/test-error")

    assert response.status_code == status_code
    assert response.json() == {"detail": str(error)}


def test_an_unexpected_exception_is_a_json_500(app: FastAPI) -> None:
    @app.get("/api/v1/test-bug")
    async def fail() -> None:
        raise RuntimeError("a bug")

    response = get(app, "/api/v1/test-bug")

    assert response.status_code == 500
    assert response.json() == {"detail": "internal server error"}
