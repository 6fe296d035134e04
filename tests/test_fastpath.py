"""Health and status answered beside FastAPI (eyeserver.api.fastpath; issue 35, item 13): the
same answers as the routes, shared snapshots never older than the request, and every other
request handed on unchanged."""

from __future__ import annotations

import asyncio
import gc
import itertools
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from fastapi import FastAPI

import eyeserver
import eyeserver.api.fastpath as fastpath
import eyeserver.log
from eyeserver import cli
from eyeserver.api.fastpath import _SharedRead, status_response
from eyeserver.api.schemas import StatusResponse
from eyeserver.service.core import Service
from tests.apiclient import API, Client


class _SlowBuild:
    """A build that takes ``seconds`` on its thread and records when each one began."""

    def __init__(self, seconds: float, fail: bool = False) -> None:
        self.seconds, self.fail = seconds, fail
        self.started: list[float] = []
        self.lock = threading.Lock()

    def __call__(self) -> bytes:
        with self.lock:
            self.started.append(time.monotonic())
            number = len(self.started)
        time.sleep(self.seconds)
        if self.fail:
            raise OSError("the store is gone")
        return str(number).encode()


def test_concurrent_readers_share_builds_begun_after_they_asked() -> None:
    build = _SlowBuild(0.05)

    async def readers() -> list[tuple[float, bytes]]:
        shared = _SharedRead(build)

        async def read(delay_s: float) -> tuple[float, bytes]:
            await asyncio.sleep(delay_s)
            asked = time.monotonic()
            return asked, await shared.get()

        return await asyncio.gather(*(read(0.005 * i) for i in range(40)))

    answers = asyncio.run(readers())

    # 40 readers over 0.2 s, builds of 0.05 s: a handful of builds, never one at a time each.
    assert 2 <= len(build.started) <= 8
    for asked, body in answers:
        assert build.started[int(body) - 1] >= asked  # the answer was begun after the question
    starts = build.started
    assert all(later - earlier >= 0.05 for earlier, later in itertools.pairwise(starts))


def test_a_failed_build_reaches_every_waiter_and_the_next_read_builds_again() -> None:
    failing = _SlowBuild(0.02, fail=True)

    async def read_twice() -> tuple[list[Any], bytes]:
        shared = _SharedRead(failing)
        first = await asyncio.gather(*(shared.get() for _ in range(5)), return_exceptions=True)
        failing.fail = False
        return first, await shared.get()

    first, again = asyncio.run(read_twice())

    assert all(isinstance(e, OSError) for e in first)
    assert again == str(len(failing.started)).encode()


def test_a_reader_that_goes_away_does_not_cancel_the_others() -> None:
    build = _SlowBuild(0.05)

    async def one_leaves() -> tuple[bytes, bytes]:
        shared = _SharedRead(build)
        first = asyncio.ensure_future(shared.get())
        await asyncio.sleep(0.01)  # build 1 under way: the next two wait for build 2
        leaving = asyncio.ensure_future(shared.get())
        staying = asyncio.ensure_future(shared.get())
        await asyncio.sleep(0.01)
        leaving.cancel()
        return await first, await staying

    assert asyncio.run(one_leaves()) == (b"1", b"2")


def _counted(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Count the fast path's status builds."""
    calls: list[int] = []

    def counting(service: Service, tracking: object) -> StatusResponse:
        calls.append(1)
        return status_response(service, tracking)

    monkeypatch.setattr(fastpath, "status_response", counting)
    return calls


def test_the_status_read_is_the_routes_answer_without_the_route(
        app: FastAPI, client: Client, monkeypatch: pytest.MonkeyPatch) -> None:
    calls = _counted(monkeypatch)
    response = client.get(f"{API}/status")

    assert response.status_code == 200
    assert response.headers["content-type"] == "application/json"
    assert calls == [1]
    body = StatusResponse.model_validate(response.json()).model_dump()
    service = app.state.service
    assert isinstance(service, Service)
    expected = status_response(service, app.state.tracking).model_dump()
    assert body["uptime_s"] <= expected["uptime_s"]
    body.pop("uptime_s"), expected.pop("uptime_s")
    assert body == expected


def test_health_is_answered_as_the_route_would(client: Client) -> None:
    response = client.get(f"{API}/health", headers={"Authorization": ""})

    assert response.status_code == 200
    assert response.headers["content-type"] == "application/json"
    assert response.json() == {"status": "ok", "version": eyeserver.__version__}


@pytest.mark.parametrize("headers", [{"Authorization": ""}, {"Authorization": "Bearer nope"}],
                         ids=["no-token", "unknown-token"])
def test_a_read_without_a_valid_token_goes_to_the_application(
        client: Client, monkeypatch: pytest.MonkeyPatch, headers: dict[str, str]) -> None:
    calls = _counted(monkeypatch)
    response = client.get(f"{API}/status", headers=headers)

    assert response.status_code == 401
    assert response.headers["www-authenticate"] == "Bearer"
    assert calls == []


def test_a_failing_snapshot_is_answered_by_the_route(
        client: Client, monkeypatch: pytest.MonkeyPatch) -> None:
    def broken(service: Service, tracking: object) -> StatusResponse:
        raise OSError("disk I/O error")

    monkeypatch.setattr(fastpath, "status_response", broken)
    response = client.get(f"{API}/status")

    assert response.status_code == 200  # the route has its own reference and answers
    assert response.json()["state"] == "idle"


def test_the_daemon_runs_with_its_start_up_heap_out_of_the_collectors_full_passes(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Full passes of the cyclic collector over the start-up heap stopped every thread for
    40-90 ms under load; ``eyeserver serve`` freezes that heap before uvicorn runs."""
    import uvicorn

    seen: dict[str, Any] = {}

    def run(app: object, **options: Any) -> None:
        seen["frozen"] = gc.get_freeze_count()
        seen["http"] = options.get("http")

    monkeypatch.setattr(uvicorn, "run", run)
    monkeypatch.setattr(eyeserver.log, "configure_logging", lambda *_, **__: None)
    monkeypatch.setenv("EYESERVER_DATA_DIR", str(tmp_path / "data"))
    try:
        assert cli.main(["serve", "--port", "8765"]) == 0
    finally:
        gc.unfreeze()

    assert seen["frozen"] > 10_000  # FastAPI's, pydantic's and our modules at least
    assert seen["http"] == "httptools"
