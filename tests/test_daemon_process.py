"""The daemon as a real process on loopback: the whole measurement through HTTP, and a
capture answered with 201 that survives ``kill -9``."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import httpx

from eyeserver.bench.daemon import DaemonProcess
from eyeserver.io import read_bundle

API = "/api/v1"


def _capture(client: httpx.Client, unit: str) -> dict[str, Any]:
    response = client.post(f"{API}/captures", json={"unit": unit})
    assert response.status_code == 201, response.text
    body: dict[str, Any] = response.json()
    return body


def test_an_acknowledged_capture_survives_kill_9(tmp_path: Path) -> None:
    data_dir = tmp_path / "data"
    daemon = DaemonProcess(data_dir, log=tmp_path / "serve.log")
    daemon.start()
    try:
        acknowledged = [_capture(daemon.client, unit) for unit in ("left", "all", "right")]
        # One more capture is under way when the daemon dies: it may or may not have been
        # acknowledged, but it must not leave anything broken behind.
        in_flight: dict[str, Any] = {}
        url, token = daemon.url, daemon.physicist_token

        def late() -> None:
            try:
                in_flight["response"] = httpx.post(
                    f"{url}{API}/captures", json={"unit": "all"}, timeout=30,
                    headers={"Authorization": f"Bearer {token}"})
            except httpx.TransportError as exc:
                in_flight["error"] = exc

        runner = threading.Thread(target=late)
        runner.start()
        threading.Event().wait(0.3)
    finally:
        daemon.kill()
    runner.join(timeout=30)

    with daemon:
        for created in acknowledged:
            found = daemon.client.get(f"{API}/captures/{created['id']}")
            assert found.status_code == 200, found.text
            assert found.json() == created
        listed = daemon.client.get(f"{API}/captures", params={"limit": 100}).json()
        ids = {c["id"] for c in listed["items"]}
        assert {c["id"] for c in acknowledged} <= ids
        if "response" in in_flight and in_flight["response"].status_code == 201:
            assert in_flight["response"].json()["id"] in ids
        for item in listed["items"]:  # everything indexed is complete on disk
            assert item["status"] == "ok"
            bundle = read_bundle(data_dir / "captures" / item["id"])
            assert len(bundle.frames) == item["frame_count"]
        assert daemon.client.get(f"{API}/status").json()["state"] == "idle"
