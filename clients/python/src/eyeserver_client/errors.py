"""The client's one exception tree.

::

    EyeserverError                 anything this client raises on purpose
    ├── HTTPError                  the daemon answered with an error status: .status, .reason
    │   ├── AuthError              401 no valid token, 403 the token's role may not do this
    │   ├── NotFound               404 no such capture, patient, reference, session, …
    │   ├── Conflict               409 the request conflicts with the daemon's state (busy,
    │   │                          no active calibration, not tracking, evidence kept)
    │   ├── Invalid                400 unreadable body, 413 upload too large, 422 bad input
    │   │                          or no eye could be fitted (.errors: each problem)
    │   └── Unavailable            503 a device failed or a queue is full, 504 a device timed out
    ├── ConnectionError            the daemon could not be reached or the link broke
    │   └── RequestTimeoutError         no answer within the client's timeout
    └── UnexpectedResponseError         an answer this client cannot read (not JSON, not the model):
                                   the daemon and the client have drifted apart

Other statuses (500 a bug in the daemon, 501 not built, 507 its disk is full) are plain
:class:`HTTPError`. Every :class:`HTTPError` carries the daemon's own words: the body of each
of its errors is ``{"detail": "<reason>"}`` (with ``errors`` for a 422), so ``.reason`` is what
to show a person.
"""

from __future__ import annotations

import builtins
from typing import Any

__all__ = [
    "AuthError",
    "Conflict",
    "ConnectionError",
    "EyeserverError",
    "HTTPError",
    "Invalid",
    "NotFound",
    "RequestTimeoutError",
    "Unavailable",
    "UnexpectedResponseError",
]


class EyeserverError(Exception):
    """Base of every error this client raises on purpose."""


class HTTPError(EyeserverError):
    """The daemon answered with an error status.

    Attributes
    ----------
    status : int
        The HTTP status code.
    reason : str
        The daemon's reason (``detail`` of its JSON body), meant for a person; the status line
        when the body has none.
    detail : str
        The same as :attr:`reason` (the name the daemon's body uses).
    errors : list of dict or None
        For a request that failed validation (422): each problem with its ``loc``, ``msg`` and
        ``type``, as the daemon reports them; None otherwise.
    method, url : str
        The request that failed.
    retry_after_s : float or None
        The daemon's ``Retry-After`` (seconds), when it sent one.
    """

    def __init__(self, status: int, reason: str, *, method: str = "", url: str = "",
                 errors: list[dict[str, Any]] | None = None,
                 retry_after_s: float | None = None) -> None:
        super().__init__(f"{status} {method} {url}: {reason}" if method else
                         f"{status}: {reason}")
        self.status = status
        self.reason = reason
        self.errors = errors
        self.method = method
        self.url = url
        self.retry_after_s = retry_after_s

    @property
    def detail(self) -> str:
        """The daemon's reason, under the name its JSON body gives it."""
        return self.reason


class AuthError(HTTPError):
    """401: no valid bearer token; 403: the token's role may not do this (a physicist's
    route called with an operator's token). Also a stream closed with 1008."""


class NotFound(HTTPError):  # noqa: N818 (the HTTP status's name, as the brief and httpx do)
    """404: the thing asked for does not exist (the reason names it)."""


class Conflict(HTTPError):  # noqa: N818
    """409: the request conflicts with the daemon's state: it is busy (capturing,
    calibrating, tracking), no calibration is active, nothing is tracking, or a capture is kept
    as evidence. Retrying the same request later may succeed; retrying at once will not."""


class Invalid(HTTPError):  # noqa: N818
    """400, 413 or 422: the request itself is wrong (bad body, value out of range, unknown
    unit, an upload too large) or no eye could be fitted; :attr:`errors` lists each problem
    of a validation failure."""


class Unavailable(HTTPError):  # noqa: N818
    """503: a device failed or a queue of the daemon is full (nothing was done); 504: a device
    timed out. The reason names the device or the queue."""


class ConnectionError(EyeserverError, builtins.ConnectionError):
    """The daemon could not be reached, or the link broke before an answer came.

    Also a :class:`builtins.ConnectionError`, so code that catches the standard one catches
    this too. Whether a request that broke off was carried out is unknown, unless the
    connection was never made (then nothing was sent)."""


class RequestTimeoutError(ConnectionError):
    """No answer within the client's timeout. The daemon may still carry the request out
    (a pose measurement takes seconds): read the result back before repeating it."""


class UnexpectedResponseError(EyeserverError):
    """An answer this client cannot read: not JSON, or not the model the client expects. The
    daemon and the client have drifted apart; the message says where."""
