"""Reading the daemon's WebSocket streams, reconnecting and keeping the place by ``seq``.

Generated from ``_streams_async.py`` by ``scripts/unasync.py``: do not edit (edit that
file and run the script).
"""

from __future__ import annotations

import contextlib
import json
import logging
from collections import deque
from collections.abc import Callable
from typing import Any

from websockets.exceptions import ConnectionClosed, InvalidStatus, InvalidURI, WebSocketException

from eyeserver_client import _io_sync as io
from eyeserver_client._config import Connection
from eyeserver_client._sequence import Sequence
from eyeserver_client.errors import AuthError, ConnectionError, EyeserverError
from eyeserver_client.messages import Message

__all__ = ["MessageStream"]

_log = logging.getLogger("eyeserver_client")

WS_POLICY_VIOLATION = 1008
"""The daemon's close code for a stream opened without a valid token (the reason says so)."""


class MessageStream:
    """An iterator over one of the daemon's streams that survives a lost connection.

    It connects at the first read, or on entering it as a context manager (or at
    :meth:`connect`). When the connection is lost (closed by the daemon, broken, or silent for
    longer than ``silence_s`` seconds) it yields a
    :class:`~eyeserver_client.messages.Disconnected` at once, then connects again at the next
    read (waits growing from ``backoff_s`` to ``max_backoff_s`` seconds, at most
    ``max_attempts`` in a row, None: without end) and yields a
    :class:`~eyeserver_client.messages.Resumed` saying how many messages (by ``seq``) went by
    meanwhile and are lost, before the messages that follow. A stream the daemon replays
    (``replays``: the event stream) asks for what went by (``?after=seq``) and gets it again
    unless the daemon no longer keeps it. No message is yielded twice. With
    ``reconnect=False`` it ends after the :class:`~eyeserver_client.messages.Disconnected`
    instead.

    Raises :class:`~eyeserver_client.errors.AuthError` when the daemon refuses the token
    (close code 1008, with its reason; never retried), and
    :class:`~eyeserver_client.errors.ConnectionError` when ``max_attempts`` connections in a
    row failed. Close it (or use it as a context manager) to end it; the iteration then stops.
    """

    def __init__(self, connection: Connection, path: str,
                 parse: Callable[[dict[str, Any]], Message], *, reconnect: bool = True,
                 silence_s: float | None = None, open_timeout_s: float = 10.0,
                 backoff_s: float = 0.1, max_backoff_s: float = 5.0,
                 max_attempts: int | None = None, replays: bool = False) -> None:
        self.url = connection.websocket_root + path
        self._replays = replays
        self._headers = connection.headers()
        self._ssl = connection.ssl_context
        self._parse = parse
        self._reconnect = reconnect
        self._silence_s = silence_s
        self._open_timeout_s = open_timeout_s
        self._backoff_s = backoff_s
        self._max_backoff_s = max_backoff_s
        self._max_attempts = max_attempts
        self._sequence = Sequence()
        self._pending: deque[Message] = deque()
        self._websocket: io.WebSocket | None = None
        self._lost = False
        self._closed = False

    @property
    def last_seq(self) -> int | None:
        """The ``seq`` of the last numbered message yielded (or the ``hello``'s start)."""
        return self._sequence.last_seq

    def __iter__(self) -> MessageStream:
        return self

    def __next__(self) -> Message:
        while True:
            if self._pending:
                return self._pending.popleft()
            if self._closed or (self._lost and not self._reconnect):
                raise StopIteration
            if self._websocket is None:
                self.connect()
            websocket = self._websocket
            if websocket is None:  # closed meanwhile
                raise StopIteration
            try:
                raw = io.receive(websocket, self._silence_s)
            except TimeoutError:
                self._lose(f"nothing received for {self._silence_s:g} s")
                continue
            except ConnectionClosed as exc:
                if self._closed:
                    raise StopIteration from None
                close = exc.rcvd
                if close is not None and close.code == WS_POLICY_VIOLATION:
                    self._closed = True
                    raise AuthError(401, close.reason or "the daemon refused the token",
                                    method="GET", url=self.url) from None
                self._lose("closed by the daemon: " + (
                    f"{close.code} {close.reason}".strip() if close is not None
                    else "the connection broke"))
                continue
            self._pending.extend(self._sequence.receive(self._parse(_decode(raw))))

    def connect(self) -> None:
        """Connect now rather than at the first read (entering the context does this), so
        that nothing sent from now on is missed, e.g. before starting live tracking."""
        if self._websocket is None and not self._closed:
            self._websocket = self._connect()
            self._lost = False

    def _lose(self, reason: str) -> None:
        websocket, self._websocket = self._websocket, None
        if websocket is not None:
            with contextlib.suppress(OSError, WebSocketException):  # gone either way
                io.close(websocket)
        self._lost = True
        _log.warning("stream %s lost: %s", self.url, reason)
        self._pending.append(self._sequence.lost(reason))

    def _connect(self) -> io.WebSocket:
        attempt, wait_s = 0, self._backoff_s
        while True:
            attempt += 1
            try:
                return io.open_websocket(self._resuming_url(), self._headers, self._ssl,
                                         self._open_timeout_s)
            except InvalidURI as exc:
                raise EyeserverError(f"{self.url}: not a WebSocket URL ({exc})") from exc
            except InvalidStatus as exc:
                status = exc.response.status_code
                if status in (401, 403):
                    raise AuthError(status, "the daemon refused the stream's handshake",
                                    method="GET", url=self.url) from exc
                if status == 404:
                    raise EyeserverError(f"{self.url}: no such stream (404)") from exc
                failure: Exception = exc
            except (OSError, TimeoutError, WebSocketException) as exc:
                failure = exc
            if self._max_attempts is not None and attempt >= self._max_attempts:
                raise ConnectionError(f"{self.url}: could not connect after {attempt} "
                                      f"attempt(s) ({failure})") from failure
            _log.info("stream %s: connecting failed (%s); again in %.1f s", self.url,
                      failure, wait_s)
            io.sleep(wait_s)
            wait_s = min(wait_s * 2, self._max_backoff_s)

    def _resuming_url(self) -> str:
        """The stream's URL; for a stream the daemon replays (``replays``), once a message was
        numbered, with ``after=<the last seq>`` so that what went by meanwhile comes again."""
        last = self._sequence.last_seq
        if not self._replays or last is None:
            return self.url
        return f"{self.url}{'&' if '?' in self.url else '?'}after={last}"

    def close(self) -> None:
        """End the stream: the connection is closed and the iteration stops."""
        self._closed = True
        self._pending.clear()
        websocket, self._websocket = self._websocket, None
        if websocket is not None:
            with contextlib.suppress(OSError, WebSocketException):
                io.close(websocket)

    def __enter__(self) -> MessageStream:
        self.connect()
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


def _decode(raw: str | bytes) -> dict[str, Any]:
    try:
        data = json.loads(raw)
    except ValueError as exc:
        raise EyeserverError(f"the daemon sent a message that is not JSON: {raw!r:.200}"
                             ) from exc
    if not isinstance(data, dict):
        raise EyeserverError(f"the daemon sent a message that is not an object: {raw!r:.200}")
    return data
