"""``/api/v1/asyncapi.json``: the WebSocket streams described as an AsyncAPI 3.0 document.

The OpenAPI document cannot describe a WebSocket's messages; this one, served beside it (with
the same rule: no token unless ``public_api_docs`` is off), names each stream's address, how to
authenticate, its close codes and every message it sends, the schemas generated from the
pydantic models of :mod:`eyeserver.api.messages`. tests/test_asyncapi.py checks that it lists
every WebSocket route of the app and that the messages a live daemon sends fit its models.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from fastapi import Depends, FastAPI
from fastapi.responses import JSONResponse
from pydantic import BaseModel
from pydantic.json_schema import models_json_schema

import eyeserver
from eyeserver.api.auth import require
from eyeserver.api.messages import EVENT_MESSAGES, POSE_MESSAGES

__all__ = ["ASYNCAPI_VERSION", "CHANNELS", "Channel", "asyncapi_document", "mount"]

ASYNCAPI_VERSION = "3.0.0"

_CLOSE_CODES = (
    "Close codes: 1008 (policy violation) with the reason when the token is missing or not "
    "valid, before any message; 1013 (try again later) while the daemon is not running; "
    "1001 (going away) when it shuts down; 4008 after a last `dropped` notice when the client "
    "accepted nothing for the setting `ws_stall_s` (it stopped reading). Messages the client "
    "sends are ignored.")


@dataclass(frozen=True)
class Channel:
    """One WebSocket route: its route name, path under the API prefix, what it is for and the
    models of the messages it sends."""

    name: str
    path: str
    description: str
    messages: tuple[type[BaseModel], ...]


CHANNELS: tuple[Channel, ...] = (
    Channel("events", "/ws/events",
            "The daemon's events: a `hello` snapshot first, then every event in order, `seq` "
            "increasing by one. A slow reader loses its oldest events (at most "
            "`event_queue_size` are kept for it) and gets a `dropped` notice before the next "
            "one. A client that reconnects with `?after=<its last seq>` gets the events since "
            "then again, after the `hello`, as long as the daemon keeps them (its newest "
            "1024; the `hello`'s `last_seq` says where they start).", EVENT_MESSAGES),
    Channel("pose", "/ws/pose",
            "Live tracking: a `heartbeat` at once (whether tracking runs, the beam held), then "
            "one `pose` message per processed frame (the beam-hold flag in "
            "each), a `hold` message when the daemon holds the beam without a frame, a "
            "`heartbeat` after a second with nothing else: a client that hears nothing for "
            "longer must take the link as dead and hold the beam. The stream outlives "
            "tracking sessions (heartbeats only between them).", POSE_MESSAGES),
)
"""The WebSocket routes and what they send."""


def asyncapi_document(prefix: str) -> dict[str, Any]:
    """The AsyncAPI 3.0 document of :data:`CHANNELS`, their paths under ``prefix``."""
    models = {model for channel in CHANNELS for model in channel.messages}
    _, schemas = models_json_schema(
        [(model, "serialization") for model in sorted(models, key=lambda m: m.__name__)],
        ref_template="#/components/schemas/{model}")
    messages: dict[str, Any] = {}
    for model in models:
        type_field = model.model_fields["type"].annotation
        messages[model.__name__] = {
            "name": model.__name__,
            "title": " or ".join(getattr(type_field, "__args__", ())),
            "summary": (model.__doc__ or "").strip().split("\n\n")[0].replace("\n", " "),
            "contentType": "application/json",
            "payload": {"$ref": f"#/components/schemas/{model.__name__}"},
        }
    channels: dict[str, Any] = {}
    operations: dict[str, Any] = {}
    for channel in CHANNELS:
        channels[channel.name] = {
            "address": f"{prefix}{channel.path}",
            "title": channel.path,
            "description": f"{channel.description}\n\n{_CLOSE_CODES}",
            "messages": {m.__name__: {"$ref": f"#/components/messages/{m.__name__}"}
                         for m in channel.messages},
            "bindings": {"ws": {"bindingVersion": "0.1.0", "method": "GET", "query": {
                "type": "object", "properties": {"token": {
                    "type": "string", "description": "The bearer token, for clients that "
                    "cannot set the Authorization header (browsers)."}}}}},
        }
        operations[f"send_{channel.name}"] = {
            "action": "send",  # the daemon sends; clients receive
            "channel": {"$ref": f"#/channels/{channel.name}"},
            "summary": f"The daemon sends on {channel.path}",
            "messages": [{"$ref": f"#/channels/{channel.name}/messages/{m.__name__}"}
                         for m in channel.messages],
        }
    return {
        "asyncapi": ASYNCAPI_VERSION,
        "info": {"title": "eyeserver streams", "version": eyeserver.__version__,
                 "description": "The daemon's WebSocket streams (JSON text messages). The "
                 "HTTP API is described by the OpenAPI document beside this one "
                 f"({prefix}/openapi.json)."},
        "defaultContentType": "application/json",
        "servers": {"daemon": {
            "host": "127.0.0.1:8000", "protocol": "ws",
            "description": "The daemon (wss with TLS); the host is wherever it listens.",
            "security": [{"$ref": "#/components/securitySchemes/bearer"},
                         {"$ref": "#/components/securitySchemes/query_token"}]}},
        "channels": channels,
        "operations": operations,
        "components": {
            "schemas": schemas.get("$defs", {}),
            "messages": dict(sorted(messages.items())),
            "securitySchemes": {
                "bearer": {"type": "http", "scheme": "bearer",
                           "description": "Authorization: Bearer <token> (any role)."},
                "query_token": {"type": "httpApiKey", "in": "query", "name": "token",
                                "description": "?token=<token> (any role)."}},
        },
    }


def mount(app: FastAPI, prefix: str, *, public: bool) -> None:
    """Serve :func:`asyncapi_document` at ``{prefix}/asyncapi.json``: to anyone when ``public``
    (as the OpenAPI document), else to an operator or physicist."""
    document = asyncapi_document(prefix)

    async def asyncapi_json() -> JSONResponse:
        return JSONResponse(document)

    app.add_api_route(f"{prefix}/asyncapi.json", asyncapi_json, include_in_schema=False,
                      dependencies=[] if public else [Depends(require("operator"))])
