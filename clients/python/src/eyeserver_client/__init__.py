"""eyeserver-client: a typed Python client of the eyeserver daemon's API.

::

    from eyeserver_client import Client

    with Client("http://127.0.0.1:8000") as client:      # token: $EYESERVER_TOKEN
        print(client.status().state)
        result = client.measure_pose("P-0001", fraction=3)
        print(result.passed, result.deviation.length_mm)

:class:`Client` blocks, :class:`AsyncClient` is its asyncio twin (the same methods, awaited).
Answers are pydantic models (:mod:`eyeserver_client.models`, generated from the daemon's
OpenAPI document; :mod:`eyeserver_client.extras` for what the document leaves untyped); stream
messages are :mod:`eyeserver_client.messages`; errors are :mod:`eyeserver_client.errors`.
"""

from eyeserver_client._client_async import AsyncClient
from eyeserver_client._client_sync import Client
from eyeserver_client._streams_async import AsyncMessageStream
from eyeserver_client._streams_sync import MessageStream
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
from eyeserver_client.messages import (
    Disconnected,
    Dropped,
    Event,
    Heartbeat,
    Hello,
    HoldMessage,
    Message,
    PoseMessage,
    Resumed,
)

__version__ = "0.1.0"

__all__ = [
    "AsyncClient",
    "AsyncMessageStream",
    "AuthError",
    "Client",
    "Conflict",
    "ConnectionError",
    "Disconnected",
    "Dropped",
    "Event",
    "EyeserverError",
    "HTTPError",
    "Heartbeat",
    "Hello",
    "HoldMessage",
    "Invalid",
    "Message",
    "MessageStream",
    "NotFound",
    "PoseMessage",
    "RequestTimeoutError",
    "Resumed",
    "Unavailable",
    "UnexpectedResponseError",
    "__version__",
]
