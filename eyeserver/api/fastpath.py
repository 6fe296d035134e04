"""``GET /status`` and ``GET /health`` answered beside FastAPI, so that probes stay fast whatever
the acquisition does (issue 35, item 13).

Under 100 connections reading the status while captures are posted, each status cost the event
loop ≈ 1.7 ms, half of it FastAPI's routing and dependency solving, and every request asked every
device to describe itself: the loop, not a lock, was the queue (docs/notes/hardening.md). This
pure ASGI middleware answers those two reads itself: the health from bytes made once, the status
from a snapshot that concurrent readers share. A snapshot is shared only by requests that arrived
before it was started, so no reader is ever answered with a state older than its request.
Anything it does not answer as FastAPI would (another path or method, a missing or unknown token,
a failure while building the snapshot) goes on to the application unchanged, which owns every
error answer and its audit line.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable
from dataclasses import asdict
from typing import Any

from starlette.concurrency import run_in_threadpool
from starlette.types import ASGIApp, Receive, Scope, Send

import eyeserver
from eyeserver.api.auth import TokenTable
from eyeserver.api.schemas import HealthResponse, StatusResponse, TrackingSummary
from eyeserver.service.core import Service
from eyeserver.service.tracking import TrackingControl

__all__ = ["ReadFastPath", "status_response"]


def status_response(service: Service, tracking: object) -> StatusResponse:
    """The body of ``GET /status``: the service's snapshot with live tracking's beam hold
    (``tracking`` is the app's :class:`TrackingControl`, or anything else when there is none).
    Blocks: devices describe themselves and the store answers from SQLite."""
    status = service.status()
    summary = None
    if isinstance(tracking, TrackingControl):
        now = tracking.status()
        summary = TrackingSummary(running=now["running"], beam_hold=now["beam_hold"],
                                  stalled=now["stalled"])
    return StatusResponse.model_validate({**asdict(status), "tracking": summary})


class _SharedRead:
    """Runs a blocking ``build`` for concurrent callers: a caller that arrives while one build
    runs waits for the next, which starts when that one ends and serves everyone who arrived
    meanwhile. So at most one build runs, and each caller's result was begun after it asked."""

    def __init__(self, build: Callable[[], bytes]) -> None:
        self._build = build
        self._next: asyncio.Future[bytes] | None = None
        self._running = False

    async def get(self) -> bytes:
        """The result of a build begun after this call. Raises what the build raised."""
        future = self._next
        if future is None:
            future = self._next = asyncio.get_running_loop().create_future()
            if not self._running:
                self._start()
        # Shielded: a reader that goes away must not cancel the others' result.
        return await asyncio.shield(future)

    def _start(self) -> None:
        future, self._next = self._next, None
        assert future is not None
        self._running = True
        self._task = asyncio.ensure_future(self._run(future))  # the loop holds tasks weakly

    async def _run(self, future: asyncio.Future[bytes]) -> None:
        try:
            body = await run_in_threadpool(self._build)
        except Exception as exc:  # handed to every waiter, who falls back to the app
            if not future.done():
                future.set_exception(exc)
                future.exception()  # retrieved: no "never retrieved" warning if all left
        else:
            if not future.done():
                future.set_result(body)
        finally:
            self._running = False
            if self._next is not None:
                self._start()


class ReadFastPath:
    """Pure ASGI middleware: answers ``GET {prefix}/health`` and, for a caller with a valid
    token, ``GET {prefix}/status`` without FastAPI; hands every other request to ``app``.

    ``state`` is the FastAPI app's state, where the lifespan puts the token table, the service
    and the tracking control."""

    def __init__(self, app: ASGIApp, *, state: Any, prefix: str) -> None:
        self.app = app
        self._state = state
        self._health_path = f"{prefix}/health"
        self._status_path = f"{prefix}/status"
        self._health = HealthResponse(status="ok", version=eyeserver.__version__
                                      ).model_dump_json().encode()
        self._status = _SharedRead(self._build_status)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http" and scope["method"] == "GET":
            if scope["path"] == self._health_path:
                await _answer(send, self._health)
                return
            if scope["path"] == self._status_path and self._authorised(scope):
                body = None
                with contextlib.suppress(Exception):  # the application will answer it
                    body = await self._status.get()
                if body is not None:
                    await _answer(send, body)
                    return
        await self.app(scope, receive, send)

    def _authorised(self, scope: Scope) -> bool:
        """Whether the request carries a token of the table as FastAPI's ``HTTPBearer`` would
        read it (``Bearer <token>``, the scheme in any case); every role may read the status."""
        tokens = getattr(self._state, "tokens", None)
        if not isinstance(tokens, TokenTable):
            return False
        header = next((value for name, value in scope["headers"] if name == b"authorization"),
                      None)
        if header is None:
            return False
        scheme, _, token = header.decode("latin-1").partition(" ")
        return scheme.lower() == "bearer" and tokens.caller(token) is not None

    def _build_status(self) -> bytes:
        service = getattr(self._state, "service", None)
        if not isinstance(service, Service):
            raise RuntimeError("the daemon is not running")
        tracking = getattr(self._state, "tracking", None)
        return status_response(service, tracking).model_dump_json().encode()


async def _answer(send: Send, body: bytes) -> None:
    """A 200 with a JSON body, the headers FastAPI's ``JSONResponse`` would send."""
    await send({"type": "http.response.start", "status": 200,
                "headers": [(b"content-length", str(len(body)).encode()),
                            (b"content-type", b"application/json")]})
    await send({"type": "http.response.body", "body": body})
