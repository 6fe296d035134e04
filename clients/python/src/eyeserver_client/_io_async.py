"""The asyncio side of what differs between the two clients: sleeping and WebSockets.

``_io_sync`` is its blocking twin; ``scripts/unasync.py`` turns code written against this module
into code against that one.
"""

from __future__ import annotations

import asyncio
import ssl

from websockets.asyncio.client import ClientConnection, connect

__all__ = ["WebSocket", "close", "open_websocket", "receive", "sleep"]

WebSocket = ClientConnection


async def sleep(seconds: float) -> None:
    """Wait ``seconds``."""
    await asyncio.sleep(seconds)


async def open_websocket(url: str, headers: dict[str, str], context: ssl.SSLContext | None,
                         open_timeout_s: float) -> WebSocket:
    """Connect to ``url`` (``ws://`` or, with ``context``, ``wss://``)."""
    if context is None:
        return await connect(url, additional_headers=headers, open_timeout=open_timeout_s)
    return await connect(url, additional_headers=headers, open_timeout=open_timeout_s,
                         ssl=context)


async def receive(websocket: WebSocket, timeout_s: float | None) -> str | bytes:
    """The next message; :class:`TimeoutError` when none came within ``timeout_s``."""
    if timeout_s is None:
        return await websocket.recv()
    async with asyncio.timeout(timeout_s):
        return await websocket.recv()


async def close(websocket: WebSocket) -> None:
    """Close the connection (a close already under way or done is fine)."""
    await websocket.close()
