"""Sending a bus subscription to a WebSocket client until it leaves (``/ws/events``,
``/ws/pose``).

The subscription's bounded queue is what keeps a slow client from holding anyone up; this
moves its messages to the socket, watches for the client leaving and says goodbye: 1001 when
the daemon closes the bus, :data:`WS_TOO_SLOW` to a client that accepted nothing for the
setting ``ws_stall_s`` (its socket's buffers full: it stopped reading), after a last
``dropped`` notice counting what it will never get. Both are written behind what the client
was already sent even though it does not read (:mod:`eyeserver.api.wsprotocol`), and the
subscription is let go at once.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

from fastapi import WebSocket, WebSocketDisconnect

from eyeserver.api.auth import websocket_caller
from eyeserver.api.wsprotocol import URGENT
from eyeserver.config import Settings
from eyeserver.service.events import Subscription, SubscriptionClosedError

__all__ = ["WS_TOO_SLOW", "WS_TRY_AGAIN_LATER", "opened", "stream"]

WS_GOING_AWAY = 1001
WS_TRY_AGAIN_LATER = 1013
"""Close code for a socket opened while the daemon is not running."""
WS_TOO_SLOW = 4008
"""Close code for a client that accepted nothing for the setting ``ws_stall_s`` (private-use
range; the reason says how long)."""

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


async def stream(websocket: WebSocket, subscription: Subscription, *, stall_s: float,
                 first: Sequence[Message] = (),
                 prepare: Callable[[Message], Message] | None = None,
                 heartbeat: tuple[float, Callable[[], Message]] | None = None) -> None:
    """Send ``first``, then every message of ``subscription`` (through ``prepare``, at the
    send) until the client disconnects, the bus closes or a send waits ``stall_s`` seconds.
    The socket must be accepted.

    ``heartbeat`` ``(seconds, message)``: when nothing was sent for that long, send
    ``message()``, so that a client can tell a quiet daemon from a dead link.
    """
    sender = asyncio.create_task(_forward(websocket, subscription, first, prepare, heartbeat,
                                          stall_s))
    reader = asyncio.create_task(_read_until_disconnect(websocket))
    try:
        await asyncio.wait((sender, reader), return_when=asyncio.FIRST_COMPLETED)
    finally:
        for task in (sender, reader):
            task.cancel()
        # The sender fails when the client has gone; that is how streams end.
        await asyncio.gather(sender, reader, return_exceptions=True)
    ended = sender.exception() if sender.done() and not sender.cancelled() else None
    with contextlib.suppress(WebSocketDisconnect, OSError, RuntimeError):
        if isinstance(ended, SubscriptionClosedError):
            await websocket.close(code=WS_GOING_AWAY, reason="the daemon is stopping")
        elif isinstance(ended, _StalledError):
            lost = subscription.abandon(**ended.lost)
            await websocket.send({"type": "websocket.send", URGENT: True,
                                  "text": json.dumps({"type": "dropped", "count": lost})})
            await websocket.close(code=WS_TOO_SLOW,
                                  reason=f"too slow: accepted nothing for {stall_s:g} s")


class _StalledError(Exception):
    """A send waited the stall time; :attr:`lost` (``unsent`` and ``untold``, as
    :meth:`Subscription.abandon` takes them) says what went with the message not sent."""

    def __init__(self, message: Message, from_subscription: bool) -> None:
        super().__init__("the client accepted nothing")
        if not from_subscription:  # a hello or a heartbeat: no event in it
            self.lost = {"unsent": 0, "untold": 0}
        elif message["type"] == "dropped":
            self.lost = {"unsent": 0, "untold": int(message["count"])}
        else:
            self.lost = {"unsent": 1, "untold": 0}


async def _send(websocket: WebSocket, message: Message, stall_s: float, *,
                from_subscription: bool) -> None:
    """Send ``message``, or raise :class:`_StalledError` when it waited ``stall_s`` seconds.
    A send that waits has written nothing yet (uvicorn waits for room before writing), so
    cancelling it loses the message whole, never half of it."""
    try:
        await asyncio.wait_for(websocket.send_json(message), stall_s)
    except TimeoutError:
        raise _StalledError(message, from_subscription) from None


async def _forward(websocket: WebSocket, subscription: Subscription, first: Sequence[Message],
                   prepare: Callable[[Message], Message] | None,
                   heartbeat: tuple[float, Callable[[], Message]] | None,
                   stall_s: float) -> None:
    for message in first:
        await _send(websocket, message, stall_s, from_subscription=False)
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
                await _send(websocket, beat(), stall_s, from_subscription=False)
                continue
            message, pending = pending.result(), None
            await _send(websocket, message if prepare is None else prepare(message), stall_s,
                        from_subscription=True)
    finally:
        if pending is not None:
            pending.cancel()


async def _read_until_disconnect(websocket: WebSocket) -> None:
    while True:
        if (await websocket.receive())["type"] == "websocket.disconnect":
            return
