"""The one place where eyeserver's exception tree becomes HTTP status codes.

============================  ======
error                         status
============================  ======
``StateConflictError``        409
``UnknownIdError``            404
``NoCloudError``              404
``UnknownPatientError``       404
``NoReferenceError``          404
``PoseError``                 422
``CaptureDataNotFoundError``  404
``UploadTooLargeError``       413
``ReconstructionError``       422
``UnknownUnitError``          422
``QueueFullError``            503 (with ``Retry-After``)
``DeviceTimeoutError``        504
``DeviceValueError``          422
other ``DeviceError``         503 (with ``Retry-After``)
``NotBuiltError``             501
``FormatError``               422
``ConfigError``               422
other ``EyeserverError``      500
a full disk (SQLite, ENOSPC)  507
============================  ======

The body is always :class:`~eyeserver.api.schemas.ErrorResponse`, ``{"detail": "<reason>"}``.
"""

from __future__ import annotations

import errno
import logging
import math
import re
import sqlite3
from typing import Any

from fastapi import FastAPI, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from eyeserver.api.schemas import ErrorResponse
from eyeserver.errors import (
    ConfigError,
    DeviceError,
    DeviceTimeoutError,
    DeviceValueError,
    EyeserverError,
    FormatError,
    NotBuiltError,
    StateConflictError,
)
from eyeserver.eye import PoseError
from eyeserver.reconstruction import ReconstructionError
from eyeserver.service.capture_files import CaptureDataNotFoundError
from eyeserver.service.core import NoCloudError, UnknownUnitError
from eyeserver.service.patients import NoReferenceError, UnknownPatientError
from eyeserver.service.storage import UnknownIdError
from eyeserver.service.uploads import UploadTooLargeError
from eyeserver.service.workers import QueueFullError

__all__ = ["AUTH_RESPONSES", "install_error_handlers", "status_code_for"]

_log = logging.getLogger(__name__)

AUTH_RESPONSES: dict[int | str, dict[str, Any]] = {
    401: {"model": ErrorResponse, "description": "No valid bearer token."},
    403: {"model": ErrorResponse, "description": "The token's role may not do this."},
}
"""The answers every authenticated route may give, for the OpenAPI document."""

# First match wins, so subclasses come before their bases.
_STATUS_BY_ERROR: tuple[tuple[type[EyeserverError], int], ...] = (
    (StateConflictError, 409),
    (UnknownIdError, 404),
    (NoCloudError, 404),
    (UnknownPatientError, 404),
    (NoReferenceError, 404),
    (PoseError, 422),
    (CaptureDataNotFoundError, 404),
    (UploadTooLargeError, 413),
    (ReconstructionError, 422),
    (UnknownUnitError, 422),
    (QueueFullError, 503),
    (DeviceTimeoutError, 504),
    (DeviceValueError, 422),
    (DeviceError, 503),
    (NotBuiltError, 501),
    (FormatError, 422),
    (ConfigError, 422),
)


QUEUE_RETRY_AFTER_S = 1
"""The ``Retry-After`` (seconds) of a 503 for a full queue: its jobs take tens of milliseconds (a
device setting) to about a second (a reconstruction), and a client that honours it (the Python
client repeats an idempotent request after it) should not hammer the daemon meanwhile."""


def status_code_for(error: EyeserverError) -> int:
    """The HTTP status code that reports ``error`` (see the table in the module docstring)."""
    for error_type, status_code in _STATUS_BY_ERROR:
        if isinstance(error, error_type):
            return status_code
    return 500


async def _eyeserver_error(request: Request, exc: Exception) -> JSONResponse:
    # Starlette's handler signature takes any Exception; only EyeserverError is registered here.
    assert isinstance(exc, EyeserverError)
    status_code = 507 if _disk_full(exc) else status_code_for(exc)
    _log.log(
        logging.ERROR if status_code >= 500 else logging.INFO,
        "request failed",
        extra={
            "method": request.method,
            "path": request.url.path,
            "status_code": status_code,
            "error": type(exc).__name__,
            "reason": str(exc),
        },
    )
    headers = None
    if isinstance(exc, QueueFullError):
        headers = {"Retry-After": str(QUEUE_RETRY_AFTER_S)}
    elif isinstance(exc, DeviceError) and status_code == 503:
        # A failed device: until the background recovery next tries it, nothing changes.
        service = getattr(request.app.state, "service", None)
        if service is not None:
            headers = {"Retry-After": str(service.device_retry_after_s())}
    return _answer(status_code, str(exc), headers=headers)


def _answer(status_code: int, detail: str, errors: list[Any] | None = None,
            headers: dict[str, str] | None = None) -> JSONResponse:
    """An error's answer: :class:`~eyeserver.api.schemas.ErrorResponse` (``errors`` only where
    there are some)."""
    return JSONResponse(status_code=status_code, headers=headers, content=ErrorResponse(
        detail=detail, errors=errors).model_dump(exclude_none=True))


def _disk_full(exc: BaseException) -> bool:
    """Whether ``exc`` (or what caused it) says the data directory's disk is full."""
    while exc is not None:
        if isinstance(exc, OSError) and exc.errno == errno.ENOSPC:
            return True
        if isinstance(exc, sqlite3.OperationalError) and "full" in str(exc):
            return True  # SQLite's "database or disk is full"
        exc = exc.__cause__ or exc.__context__  # type: ignore[assignment]
    return False


def _finite(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if isinstance(value, dict):
        return {key: _finite(item) for key, item in value.items()}
    if isinstance(value, list):
        return [_finite(item) for item in value]
    return value


async def _invalid_request(request: Request, exc: Exception) -> JSONResponse:
    # Like every error: "detail" a string (each problem's location and message), with
    # FastAPI's list of problems under "errors" (it had them under "detail", which the
    # document says is a string, issue 35). Each bad input is echoed there: a JSON body may
    # hold NaN or Infinity (Python's parser reads them) but a response cannot, so those are
    # echoed as text instead of failing with a 500.
    assert isinstance(exc, RequestValidationError)
    errors = _finite(jsonable_encoder(exc.errors()))
    reasons = "; ".join(f"{'.'.join(str(part) for part in e.get('loc', ()))}: {e.get('msg')}"
                        for e in errors)
    return _answer(422, reasons or "invalid request", errors)


def _allowed_methods(app: FastAPI, path: str) -> list[str]:
    """The methods the OpenAPI document lists for the path template ``path`` matches."""
    matches: list[tuple[int, list[str]]] = []
    for template, methods in app.openapi().get("paths", {}).items():
        parts = re.split(r"(\{[^/}]+\})", template)
        pattern = "".join("[^/]+" if part.startswith("{") else re.escape(part) for part in parts)
        if re.fullmatch(pattern, path):
            matches.append((template.count("{"), [method.upper() for method in methods]))
    # The most literal template is the path's (/jobs/reconstructions, not /jobs/{job_id}).
    fewest = min((count for count, _ in matches), default=0)
    return sorted({m for count, methods in matches if count == fewest for m in methods})


async def _http_error(request: Request, exc: Exception) -> Response:
    """Starlette's HTTP errors as FastAPI answers them, but a 405's ``Allow`` lists every
    method of the path: Starlette lists only those of the first route of that path, and the
    methods of one path can lie in several routers (GET and PATCH /devices/{id}: the API
    fuzz, issue 35)."""
    assert isinstance(exc, StarletteHTTPException)
    if exc.status_code == 405:
        allowed = _allowed_methods(request.app, request.url.path)
        if allowed:
            return _answer(405, "Method Not Allowed", headers={"Allow": ", ".join(allowed)})
    return await http_exception_handler(request, exc)


class _CaughtBugs:
    """Pure ASGI middleware: an exception no handler reported becomes a JSON 500 (a bug: the
    details go to the log with the traceback, the client only learns that it was not its
    fault), or 507 where it says the disk is full (SQLite's "database or disk is full" from
    any write of the index: it gave 500, issue 35), and goes no further.

    Starlette's outermost layer answers such an exception with a 500 too, but then raises it
    on to the server, which drops the connection: the client's next request on the same
    keep-alive connection was reset (issue 35). Caught here, inside that layer, the
    connection stays usable. An exception after the response began cannot be answered; it is
    raised on as before.
    """

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = False

        async def tracked(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, receive, tracked)
        except Exception as exc:
            if started:
                raise
            where = {"method": scope.get("method"), "path": scope.get("path")}
            if _disk_full(exc):
                _log.error("request failed: the disk is full", extra={**where,
                                                                       "reason": str(exc)})
                response = _answer(507, "the data directory's disk is full: nothing was "
                                   "changed; free space (or let retention delete old "
                                   "captures) and retry")
            else:
                _log.exception("request failed: a bug", extra=where)
                response = _answer(500, "internal server error")
            await response(scope, receive, send)


def install_error_handlers(app: FastAPI) -> None:
    """Register the handlers that turn exceptions into JSON error responses on ``app``."""
    app.add_exception_handler(EyeserverError, _eyeserver_error)
    app.add_exception_handler(RequestValidationError, _invalid_request)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_middleware(_CaughtBugs)
