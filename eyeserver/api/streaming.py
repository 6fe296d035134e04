"""Sending a bus subscription to a WebSocket client until it leaves (``/ws/events``,
``/ws/pose``).

The subscription's bounded queue is what keeps a slow client from holding anyone up; this only
moves its messages to the socket, watches for the client leaving and says goodbye (1001) when
the daemon closes the bus.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

from fastapi import WebSocket, WebSocketDisconnect

from eyeserver.api.auth import websocket_caller
from eyeserver.config import Settings
from eyeserver.service.events import Subscription, SubscriptionClosedError

__all__ = ["WS_TRY_AGAIN_LATER", "opened", "stream"]

WS_GOING_AWAY = 1001
WS_TRY_AGAIN_LATER = 1013
"""Close code for a socket opened while the daemon is not running."""

Message = dict[str, Any]
T = TypeVar("T")


async def opened(websocket: WebSocket, name: str, kind: type[T]) -> tuple[T, Settings] | None:
    """``app.state.<name>`` (a ``kind``) and the settings for a stream, once the caller is
    checked; None when the socket was closed instead: 1008 with the reason for a caller
    without a valid token, 1013 while the daemon is not running. Not yet accepted."""
    if await websocket_caller(websocket) is None:
        return None  # closed with 1008 and the reason
    found = getattr(websocket.app.state, name, None)
    settings = websocket.app.state.settings
    if not isinstance(found, kind) or not isinstance(settings, Settings):
        await websocket.close(code=WS_TRY_AGAIN_LATER, reason="the daemon is not running")
        return None
    return found, settings


async def stream(websocket: WebSocket, subscription: Subscription, *,
                 first: Sequence[Message] = (),
                 prepare: Callable[[Message], Message] | None = None,
                 heartbeat: tuple[float, Callable[[], Message]] | None = None) -> None:
    """Send ``first``, then every message of ``subscription`` (through ``prepare``, at the
    send) until the client disconnects or the bus closes. The socket must be accepted.

    ``heartbeat`` ``(seconds, message)``: when nothing was sent for that long, send
    ``message()``, so that a client can tell a quiet daemon from a dead link.
    """
    sender = asyncio.create_task(_forward(websocket, subscription, first, prepare, heartbeat))
    reader = asyncio.create_task(_read_until_disconnect(websocket))
    try:
        await asyncio.wait((sender, reader), return_when=asyncio.FIRST_COMPLETED)
    finally:
        for task in (sender, reader):
            task.cancel()
        # The sender fails when the client has gone; that is how streams end.
        await asyncio.gather(sender, reader, return_exceptions=True)
    if sender.done() and not sender.cancelled() \
            and isinstance(sender.exception(), SubscriptionClosedError):
        with contextlib.suppress(WebSocketDisconnect, OSError, RuntimeError):
            await websocket.close(code=WS_GOING_AWAY, reason="the daemon is stopping")


async def _forward(websocket: WebSocket, subscription: Subscription, first: Sequence[Message],
                   prepare: Callable[[Message], Message] | None,
                   heartbeat: tuple[float, Callable[[], Message]] | None) -> None:
    for message in first:
        await websocket.send_json(message)
    quiet_s, beat = heartbeat if heartbeat is not None else (None, None)
    # The wait for the next message goes on across heartbeats (a cancelled get could lose the
    # message it was handing over).
    pending: asyncio.Task[Message] | None = None
    try:
        while True:
            if pending is None:
                pending = asyncio.ensure_future(subscription.get())
            done, _ = await asyncio.wait((pending,), timeout=quiet_s)
            if not done and beat is not None:
                await websocket.send_json(beat())
                continue
            message, pending = pending.result(), None
            await websocket.send_json(message if prepare is None else prepare(message))
    finally:
        if pending is not None:
            pending.cancel()


async def _read_until_disconnect(websocket: WebSocket) -> None:
    while True:
        if (await websocket.receive())["type"] == "websocket.disconnect":
            return
