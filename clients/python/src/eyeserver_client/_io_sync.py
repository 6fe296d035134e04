"""The blocking side of what differs between the two clients: sleeping and WebSockets.

The twin of ``_io_async``, with the same names.
"""

from __future__ import annotations

import ssl
import time

from websockets.sync.client import ClientConnection, connect

__all__ = ["WebSocket", "close", "open_websocket", "receive", "sleep"]

WebSocket = ClientConnection


def sleep(seconds: float) -> None:
    """Wait ``seconds``."""
    time.sleep(seconds)


def open_websocket(url: str, headers: dict[str, str], context: ssl.SSLContext | None,
                   open_timeout_s: float) -> WebSocket:
    """Connect to ``url`` (``ws://`` or, with ``context``, ``wss://``)."""
    websocket = connect(url, additional_headers=headers, open_timeout=open_timeout_s,
                        ssl=context)
    if not isinstance(websocket, ClientConnection):  # websockets' auto-reconnecting variant
        raise TypeError(f"unexpected connection type {type(websocket).__name__}")
    # Entered as its context manager would be (websockets 17.1 warns about a connection used
    # otherwise); :func:`close` is the exit.
    return websocket.__enter__()


def receive(websocket: WebSocket, timeout_s: float | None) -> str | bytes:
    """The next message; :class:`TimeoutError` when none came within ``timeout_s``."""
    return websocket.recv(timeout=timeout_s)


def close(websocket: WebSocket) -> None:
    """Close the connection (a close already under way or done is fine)."""
    websocket.close()
