"""Running the app in process for tests: settings with known tokens and a blocking client.

(Starlette's TestClient wants a package this project does not use.) :func:`serving` runs the
app's lifespan on an event loop in a thread; :class:`Client` calls it from any thread, so tests
can run requests side by side as a real server would. Requests carry the physicist's token
unless a test passes ``headers=`` (or :func:`auth` of another token).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import httpx
import pytest
from anyio.from_thread import start_blocking_portal
from fastapi import FastAPI

from eyeserver.config import Settings

API = "/api/v1"
OPERATOR_TOKEN = "operator-token-0123456789"
PHYSICIST_TOKEN = "physicist-token-0123456789"
TOKENS = f"operator:{OPERATOR_TOKEN},physicist:{PHYSICIST_TOKEN}"


def auth(token: str) -> dict[str, str]:
    """The header that presents ``token``."""
    return {"Authorization": f"Bearer {token}"}


def test_settings(data_dir: Path, **overrides: Any) -> Settings:
    """Settings for ``data_dir`` with the test tokens, ignoring the developer's environment.

    The daily QA's lockout (``qa.required``, on by default as in a treatment room) is off
    unless a test passes ``qa=``: the tests of verification and tracking test those, not the
    morning routine, which tests/test_qa.py tests with the lockout on (docs/qa.md)."""
    overrides.setdefault("qa", {"required": False})
    with pytest.MonkeyPatch.context() as patch:
        for name in list(os.environ):
            if name.upper().startswith("EYESERVER_"):
                patch.delenv(name)
        patch.setenv("EYESERVER_TOKENS", TOKENS)
        return Settings.load(data_dir=data_dir, **overrides)


test_settings.__test__ = False  # type: ignore[attr-defined]  # not a test for pytest


class Client:
    """A blocking client of an app running with its lifespan on an event loop in a thread."""

    def __init__(self, portal: Any, client: httpx.AsyncClient) -> None:
        self.portal = portal
        self._client = client

    def request(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        kwargs["headers"] = {**auth(PHYSICIST_TOKEN), **kwargs.get("headers", {})}
        response: httpx.Response = self.portal.call(
            lambda: self._client.request(method, path, **kwargs))
        return response

    def get(self, path: str, **kwargs: Any) -> httpx.Response:
        return self.request("GET", path, **kwargs)

    def post(self, path: str, **kwargs: Any) -> httpx.Response:
        return self.request("POST", path, **kwargs)

    def put(self, path: str, **kwargs: Any) -> httpx.Response:
        return self.request("PUT", path, **kwargs)

    def delete(self, path: str, **kwargs: Any) -> httpx.Response:
        return self.request("DELETE", path, **kwargs)


@contextmanager
def serving(app: FastAPI) -> Iterator[Client]:
    """Run ``app``'s lifespan, answer requests through the yielded client, then shut down."""
    with ExitStack() as stack:
        portal = stack.enter_context(start_blocking_portal())
        stack.enter_context(portal.wrap_async_context_manager(app.router.lifespan_context(app)))
        # raise_app_exceptions=False: a crashing route gives its 500 answer, as over a socket.
        transport = httpx.ASGITransport(app=app, raise_app_exceptions=False)
        client = stack.enter_context(portal.wrap_async_context_manager(
            httpx.AsyncClient(transport=transport, base_url="http://test")))
        yield Client(portal, client)
