"""The AsyncAPI document of the WebSocket streams (``GET /api/v1/asyncapi.json``): it lists every
WebSocket route the app has, and the messages a live daemon sends fit the models its schemas
are generated from (which forbid fields they do not name)."""

from __future__ import annotations

import json
import re
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from fastapi import FastAPI
from fastapi.routing import APIWebSocketRoute
from pydantic import BaseModel, ValidationError
from starlette.routing import WebSocketRoute
from websockets.sync.client import connect

from eyeserver.api import create_app
from eyeserver.api.asyncapi import CHANNELS, asyncapi_document
from eyeserver.api.messages import Dropped, PoseMessage
from tests.apiclient import API, OPERATOR_TOKEN, PHYSICIST_TOKEN, auth, test_settings
from tests.liveserver import live_server
from tests.test_tracking import scripted_tracking

TIMEOUT_S = 120.0  # a loaded machine renders a capture slowly


@pytest.fixture(scope="module")
def app(tmp_path_factory: pytest.TempPathFactory) -> FastAPI:
    return create_app(test_settings(tmp_path_factory.mktemp("asyncapi") / "data"))


@pytest.fixture(scope="module")
def base_url(app: FastAPI) -> Iterator[str]:
    with live_server(app) as url:
        yield url


def _document(base_url: str) -> dict[str, Any]:
    answer = httpx.get(f"{base_url}{API}/asyncapi.json", timeout=TIMEOUT_S)
    assert answer.status_code == 200, answer.text
    document: dict[str, Any] = answer.json()
    return document


def _models_by_type() -> dict[str, dict[str, type[BaseModel]]]:
    """For each channel, the model of each message ``type``."""
    found: dict[str, dict[str, type[BaseModel]]] = {}
    for channel in CHANNELS:
        for model in channel.messages:
            for kind in model.model_fields["type"].annotation.__args__:  # type: ignore[union-attr]
                found.setdefault(channel.name, {})[kind] = model
    return found


def _websocket_paths(routes: list[Any], prefix: str = "") -> set[str]:
    """The paths of every WebSocket route, in included routers too (FastAPI 0.165 keeps an
    included router as one route holding the original router and the prefix)."""
    found: set[str] = set()
    for route in routes:
        if isinstance(route, APIWebSocketRoute | WebSocketRoute):
            found.add(prefix + route.path)
        elif hasattr(route, "original_router"):
            found |= _websocket_paths(route.original_router.routes,
                                      prefix + route.include_context.prefix)
    return found


def test_the_document_lists_every_websocket_route_and_its_messages(
        app: FastAPI, base_url: str) -> None:
    document = _document(base_url)
    routes = _websocket_paths(app.routes)

    assert document["asyncapi"] == "3.0.0"
    assert {c["address"] for c in document["channels"].values()} == routes
    assert routes == {f"{API}/ws/events", f"{API}/ws/pose"}
    assert document == json.loads(json.dumps(asyncapi_document(API)))
    schemas = document["components"]["schemas"]
    for name, channel in document["channels"].items():
        operation = document["operations"][f"send_{name}"]
        assert operation["action"] == "send"
        assert operation["channel"] == {"$ref": f"#/channels/{name}"}
        assert len(operation["messages"]) == len(channel["messages"]) > 0
        for message in channel["messages"].values():
            target = message["$ref"].removeprefix("#/components/messages/")
            payload = document["components"]["messages"][target]["payload"]["$ref"]
            assert payload.removeprefix("#/components/schemas/") in schemas
    # Every $ref in the document resolves.
    text = json.dumps(document)
    for ref in {part.split('"')[0] for part in text.split('"$ref": "#/')[1:]}:
        node: Any = document
        for key in ref.split("/"):
            node = node[key]
    pose = schemas["PoseMessage"]
    assert pose["additionalProperties"] is False
    assert {"beam_hold", "deviation", "latency_ms", "seq"} <= set(pose["required"])


def test_every_event_the_daemon_publishes_is_documented_and_typed_in_the_client() -> None:
    """Each ``events.publish("<type>", …)`` in the daemon's code has its model in the AsyncAPI
    document (the live test below cannot provoke every one: the QA's need a phantom run and a
    physicist), and the Python client parses each documented event into its own model."""
    from eyeserver_client import messages as client_messages

    source = Path(__file__).resolve().parents[1] / "eyeserver"
    published = {kind for path in source.rglob("*.py")
                 for kind in re.findall(r"""\.publish\(\s*["']([a-z_.]+)["']""", path.read_text())}
    models = _models_by_type()
    assert {"qa.run", "qa.override", "qa.override_withdrawn", "pose", "hold"} <= published
    assert published - set(models["events"]) - set(models["pose"]) == set()
    client_types = set(client_messages._EVENT_TYPES)
    assert set(models["events"]) == client_types, set(models["events"]) ^ client_types


def test_the_documents_are_refused_without_a_token_when_not_public(
        tmp_path_factory: pytest.TempPathFactory) -> None:
    settings = test_settings(tmp_path_factory.mktemp("private") / "data")
    private = create_app(settings.model_copy(update={"public_api_docs": False}))
    with live_server(private) as url:
        assert httpx.get(f"{url}{API}/asyncapi.json").status_code == 401
        assert httpx.get(f"{url}{API}/asyncapi.json",
                         headers=auth(OPERATOR_TOKEN)).status_code == 200


def test_the_models_refuse_a_message_that_drifted() -> None:
    sent = {"type": "dropped", "count": 3}
    assert Dropped.model_validate(sent).count == 3
    with pytest.raises(ValidationError):
        Dropped.model_validate({**sent, "lost": 3})  # a field the document does not name
    with pytest.raises(ValidationError):
        PoseMessage.model_validate({"type": "pose", "seq": 1, "time": "x"})  # fields missing


@pytest.mark.slow
def test_every_message_a_live_daemon_sends_fits_its_schema(app: FastAPI, base_url: str) -> None:
    # Scripted tracking (as tests/test_tracking.py): the pose stream's messages without the
    # pipeline's cost.
    scripted_tracking(app, base_url)
    received: dict[str, list[dict[str, Any]]] = {"events": [], "pose": []}
    stop = threading.Event()

    def listen(channel: str) -> None:
        url = base_url.replace("http://", "ws://", 1) + f"{API}/ws/{channel}?token={OPERATOR_TOKEN}"
        with connect(url, open_timeout=TIMEOUT_S, ping_interval=None) as ws:
            while not stop.is_set():
                try:
                    received[channel].append(json.loads(ws.recv(timeout=0.2)))
                except TimeoutError:
                    continue

    threads = [threading.Thread(target=listen, args=(c,), daemon=True) for c in received]
    for thread in threads:
        thread.start()
    physicist, operator = auth(PHYSICIST_TOKEN), auth(OPERATOR_TOKEN)
    deadline = time.monotonic() + TIMEOUT_S
    while not (received["events"] and received["pose"]):  # hello, and a heartbeat
        assert time.monotonic() < deadline, received
        time.sleep(0.05)
    with httpx.Client(base_url=f"{base_url}{API}", timeout=TIMEOUT_S) as http:
        for method, path, body, headers in [
                ("POST", "/captures", {"unit": "left"}, operator),
                ("POST", "/calibration-sessions", {"kind": "stereo"}, physicist),
                ("POST", "/tracking/start", {"patient_id": "P-T1", "fraction": 1}, operator)]:
            answer = http.request(method, path, json=body, headers=headers)
            assert answer.status_code in (200, 201), answer.text
            if path == "/calibration-sessions":
                closed = http.delete(f"/calibration-sessions/{answer.json()['id']}",
                                     headers=physicist)
                assert closed.status_code == 200, closed.text
        while sum(m["type"] == "pose" for m in received["pose"]) < 5:
            assert time.monotonic() < deadline, "no pose messages"
            time.sleep(0.02)
        assert http.post("/tracking/stop", headers=operator).status_code == 200
    while not any(m["type"] == "tracking.stopped" for m in received["events"]):
        assert time.monotonic() < deadline, "no tracking.stopped"
        time.sleep(0.02)
    time.sleep(1.2)  # a heartbeat after the session
    stop.set()
    for thread in threads:
        thread.join(TIMEOUT_S)

    models = _models_by_type()
    seen: dict[str, set[str]] = {}
    for channel, messages in received.items():
        for message in messages:
            model = models[channel].get(message["type"])
            assert model is not None, f"{channel}: {message['type']} is not in the document"
            model.model_validate(message)  # raises, naming the field, when it drifted
            seen.setdefault(channel, set()).add(message["type"])
    assert seen["events"] >= {"hello", "state", "capture.stored", "calibration_session.opened",
                              "tracking.started", "tracking.stopped"}
    assert seen["pose"] >= {"heartbeat", "pose", "hold"}
