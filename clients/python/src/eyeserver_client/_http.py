"""What both clients do around a request: URLs, errors, retries, reading answers.

Pure functions over httpx's requests and answers (no I/O), so the blocking and the asyncio
client behave the same.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Hashable, Mapping
from typing import Any, TypeVar, cast
from urllib.parse import quote

import httpx
from pydantic import TypeAdapter, ValidationError

from eyeserver_client._config import Connection
from eyeserver_client._operations import Operation
from eyeserver_client.errors import (
    AuthError,
    Conflict,
    ConnectionError,
    EyeserverError,
    HTTPError,
    Invalid,
    NotFound,
    RequestTimeoutError,
    Unavailable,
    UnexpectedResponseError,
)

__all__ = ["RetryPolicy", "error_for", "parse", "transport_error", "url_for"]

T = TypeVar("T")

_BY_STATUS: dict[int, type[HTTPError]] = {
    400: Invalid, 401: AuthError, 403: AuthError, 404: NotFound, 409: Conflict, 413: Invalid,
    422: Invalid, 503: Unavailable, 504: Unavailable,
}


def url_for(connection: Connection, operation: Operation,
            path: Mapping[str, object] | None = None) -> str:
    """The absolute URL of ``operation`` with its path parameters filled in.

    Each parameter is percent-encoded whole (``safe=""``): a patient id may hold ``?``, ``#``
    or ``%`` (printable ASCII without spaces, ``/`` and ``\\``), which must not cut the path.
    """
    template = operation.path
    for name, value in (path or {}).items():
        template = template.replace("{" + name + "}", quote(str(value), safe=""))
    if "{" in template:
        raise EyeserverError(f"{operation.path}: a path parameter is missing ({template})")
    return (connection.api if operation.under_api else connection.root) + template


def error_for(response: httpx.Response) -> HTTPError:
    """The exception that reports an error answer, with the daemon's reason."""
    reason = response.reason_phrase or f"HTTP {response.status_code}"
    errors: list[dict[str, Any]] | None = None
    try:
        body = response.json()
    except (json.JSONDecodeError, UnicodeDecodeError):
        body = None
    if isinstance(body, dict):
        detail = body.get("detail")
        if isinstance(detail, str):
            reason = detail
        elif detail is not None:  # a FastAPI default answer: its list of problems
            reason = json.dumps(detail)
        if isinstance(body.get("errors"), list):
            errors = body["errors"]
    elif response.text.strip():
        reason = response.text.strip()[:500]
    kind = _BY_STATUS.get(response.status_code, HTTPError)
    request = response.request
    return kind(response.status_code, reason, method=request.method, url=str(request.url),
                errors=errors, retry_after_s=_retry_after_s(response))


def _retry_after_s(response: httpx.Response) -> float | None:
    value = response.headers.get("Retry-After")
    if value is None:
        return None
    try:
        return max(0.0, float(value))
    except ValueError:  # an HTTP date: not something this daemon sends
        return None


def transport_error(exc: httpx.TransportError, method: str, url: str) -> ConnectionError:
    """The client's exception for a request that got no answer."""
    what = f"{method} {url}"
    if isinstance(exc, httpx.ConnectTimeout | httpx.ConnectError):
        return ConnectionError(f"{what}: cannot reach the daemon ({exc or type(exc).__name__})")
    if isinstance(exc, httpx.TimeoutException):
        return RequestTimeoutError(f"{what}: no answer in time ({type(exc).__name__}); the daemon "
                              "may still carry it out")
    return ConnectionError(f"{what}: the connection broke ({exc or type(exc).__name__})")


class RetryPolicy:
    """When to send a request again, and after how long.

    ``retries`` more attempts at most. A request that never reached the daemon (the
    connection could not be made) is repeated whatever it is; a request whose connection
    broke afterwards only when its operation is idempotent; an answer only when it is 503 with
    ``Retry-After`` and the operation is idempotent (waiting what the daemon asked, at most
    ``max_wait_s``). Timeouts are never repeated: the time allowed is spent. Waits between
    connection attempts grow from ``backoff_s``, doubling.
    """

    def __init__(self, retries: int = 2, backoff_s: float = 0.2, max_wait_s: float = 10.0
                 ) -> None:
        if retries < 0:
            raise ValueError(f"retries must be 0 or more, not {retries}")
        self.retries = retries
        self.backoff_s = backoff_s
        self.max_wait_s = max_wait_s

    def after_failure(self, operation: Operation, exc: httpx.TransportError, attempt: int
                      ) -> float | None:
        """Seconds to wait before attempt ``attempt + 1`` after ``exc``, or None: give up."""
        timed_out = isinstance(exc, httpx.TimeoutException) and not isinstance(
            exc, httpx.ConnectTimeout)
        if attempt >= self.retries or timed_out:
            return None
        never_sent = isinstance(exc, httpx.ConnectError | httpx.ConnectTimeout)
        if not (never_sent or operation.idempotent):
            return None
        return min(self.backoff_s * 2.0 ** attempt, self.max_wait_s)

    def after_answer(self, operation: Operation, error: HTTPError, attempt: int
                     ) -> float | None:
        """Seconds to wait before repeating a request answered with ``error``, or None."""
        if attempt >= self.retries or not operation.idempotent:
            return None
        if error.status == 503 and error.retry_after_s is not None:
            return min(error.retry_after_s, self.max_wait_s)
        return None


@functools.cache
def _adapter(kind: Hashable) -> TypeAdapter[Any]:
    adapter: TypeAdapter[Any] = TypeAdapter(cast(Any, kind))
    return adapter


def parse(response: httpx.Response, kind: type[T] | Any) -> T:
    """The answer's JSON body as ``kind`` (a model, or e.g. ``list[Model]``).

    Raises
    ------
    UnexpectedResponseError
        Not JSON, or not ``kind``: the daemon and this client disagree.
    """
    request = response.request
    try:
        value: T = _adapter(cast(Hashable, kind)).validate_json(response.content)
    except ValidationError as exc:
        problems = "; ".join(
            f"{'.'.join(str(p) for p in error['loc']) or '(body)'}: {error['msg']}"
            for error in exc.errors()[:5])
        raise UnexpectedResponseError(f"{request.method} {request.url}: the answer is not what "
                                 f"this client expects ({problems})") from exc
    return value
