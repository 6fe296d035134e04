"""uvicorn's WebSocket protocol with one change: a goodbye is never held up by flow control.

uvicorn makes every ASGI send wait while the socket's write buffer is full, the close included;
so a client that stops reading could only be cut off by uvicorn's own keep-alive timeout (1011,
without a word of what it lost). With :class:`WebSocketProtocol` the daemon's last words to such
a client, a ``dropped`` notice marked :data:`URGENT` and the close frame, are written behind what
is already buffered at once: a client that reads again finds, in order, the messages it was
sent, the notice, and the documented close (:data:`eyeserver.api.streaming.WS_TOO_SLOW`).

Pass :data:`UVICORN_OPTIONS` to :func:`uvicorn.run` or :class:`uvicorn.Config`.
"""

from __future__ import annotations

from typing import Any

from uvicorn._types import ASGISendEvent
from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol

__all__ = ["URGENT", "UVICORN_OPTIONS", "WebSocketProtocol"]

URGENT = "eyeserver.urgent"
"""Key of an ASGI ``websocket.send`` message that must be written even while the client does
not read (a server that is not this one ignores it and sends the message as any other)."""


class WebSocketProtocol(WebSocketsSansIOProtocol):
    """uvicorn's websockets protocol, writing a close or an :data:`URGENT` message at once even
    while the transport is paused (its buffer full); everything else waits as before."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._paused = False

    def pause_writing(self) -> None:
        self._paused = True
        super().pause_writing()

    def resume_writing(self) -> None:
        self._paused = False
        super().resume_writing()

    async def send(self, message: ASGISendEvent) -> None:
        urgent = message["type"] == "websocket.close" or bool(message.get(URGENT))
        if not (urgent and self._paused):
            await super().send(message)
            return
        # uvicorn's send waits on ``writable`` and then writes without awaiting anything else:
        # opened for this one call, the message is written before any other task can run.
        self.writable.set()
        try:
            await super().send(message)
        finally:
            if self._paused:
                self.writable.clear()


UVICORN_OPTIONS: dict[str, Any] = {"ws": WebSocketProtocol, "http": "httptools"}
"""The keyword arguments of uvicorn the daemon runs with: WebSockets served by
:class:`WebSocketProtocol`, HTTP parsed by httptools (compiled; under 100 connections reading the
status it served about twice the requests per second of the pure-Python h11 and kept the p99
under 100 ms, docs/notes/hardening.md)."""
