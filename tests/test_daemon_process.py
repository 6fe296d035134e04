"""The daemon as a real process on loopback: the whole measurement through HTTP, and a
capture answered with 201 that survives ``kill -9``."""

from __future__ import annotations

import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import pytest

from eyeserver.bench.daemon import DaemonProcess, zip_directory
from eyeserver.hardware.sim.config import load_room
from eyeserver.hardware.sim.scoring import score_cloud
from eyeserver.io import read_bundle, read_ply

pytestmark = pytest.mark.slow  # every test here takes over a second

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


def test_a_measurement_end_to_end_through_a_real_daemon(
        tmp_path: Path, calibrated_rooms: Callable[[str], tuple[Path, Path]]) -> None:
    # Calibrated offline with the command line (the session fixture runs `eyeserver sim
    # calibration-set`, `eyeserver calibrate stereo` and `calibrate p2h`).
    _, caldir = calibrated_rooms("default")
    with DaemonProcess(tmp_path / "data", log=tmp_path / "serve.log") as daemon:
        client = daemon.client
        imported = client.post(f"{API}/calibrations", content=zip_directory(caldir),
                               headers={"content-type": "application/zip"})
        assert imported.status_code == 201, imported.text
        calibration_id = imported.json()["id"]
        assert client.post(f"{API}/calibrations/{calibration_id}/activate").status_code == 200

        placed = client.put(f"{API}/sim/scene",
                            json={"kind": "pyramid", "position_mm": [0.5, -0.8, -4.0],
                                  "rotation_deg": [4.0, -3.0, 20.0]})
        assert placed.status_code == 200, placed.text
        capture = _capture(client, "all")
        assert capture["calibration_id"] == calibration_id
        summary = client.post(f"{API}/captures/{capture['id']}/reconstruction")
        assert summary.status_code == 200, summary.text
        assert summary.json()["calibration_id"] == calibration_id
        ply = client.get(f"{API}/captures/{capture['id']}/cloud.ply")
        assert ply.status_code == 200
        truth = client.get(f"{API}/sim/truth").json()

        # An operator measures and reads, but may not calibrate.
        operator = {"Authorization": f"Bearer {daemon.operator_token}"}
        assert client.get(f"{API}/status", headers=operator).status_code == 200
        assert client.post(f"{API}/calibrations/{calibration_id}/activate",
                           headers=operator).status_code == 403
        assert httpx.get(f"{daemon.url}{API}/status").status_code == 401

    path = tmp_path / "downloaded.ply"
    path.write_bytes(ply.content)
    cloud = read_ply(path)
    assert len(cloud.points) == summary.json()["points"] > 100_000
    score = score_cloud(truth, cloud, load_room(None))
    assert score["scene"] == "pyramid"
    assert score["median_mm"] < 0.05, score
    assert score["rmse_mm"] < 0.15, score
    assert score["beyond_1mm"] < 1e-3, score
