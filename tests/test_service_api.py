"""The daemon's service through its REST API: status, devices, captures, the state machine.

The app runs in process with its lifespan (the simulated default room, an eye in the scene).
Rendering a room's first frames takes seconds, so one app serves most tests of this module;
each test leaves it idle and healthy.
"""

from __future__ import annotations

import contextlib
import errno
import functools
import io
import json
import re
import socket
import sqlite3
import threading
import time
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import eyeserver
import eyeserver.api.app as app_module
from eyeserver.api import create_app
from eyeserver.hardware.sim.drivers import SimCamera
from eyeserver.io import read_bundle
from eyeserver.service.core import Service
from eyeserver.service.storage import StorageError
from tests.apiclient import API, OPERATOR_TOKEN, Client, serving, test_settings
from tests.liveserver import live_server


def _camera(service: Service, camera_id: str) -> SimCamera:
    camera = service.rig.camera(camera_id)
    assert isinstance(camera, SimCamera)
    return camera


def _wait_until(condition: Callable[[], bool], timeout_s: float = 10) -> bool:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def _capture(client: Client, unit: str) -> Any:
    response = client.post(f"{API}/captures", json={"unit": unit})
    assert response.status_code == 201, response.text
    return response.json()


def test_status_reports_state_devices_units_and_version(client: Client) -> None:
    response = client.get(f"{API}/status")

    assert response.status_code == 200
    body = response.json()
    assert body["state"] == "idle"
    assert body["version"] == eyeserver.__version__
    assert body["active_calibration_id"] is None
    assert body["uptime_s"] >= 0
    assert [d["id"] for d in body["devices"]] == ["P1", "P2", "S1", "S2", "S3", "S4", "T1"]
    assert all(d["health"] == "ok" and d["reason"] is None and d["open"]
               for d in body["devices"])
    assert body["units"] == [
        {"id": "left", "projector": "P1", "cameras": ["S1", "S2"], "health": "ok",
         "reason": None},
        {"id": "right", "projector": "P2", "cameras": ["S3", "S4"], "health": "ok",
         "reason": None},
    ]


def test_devices_are_listed_and_found_by_id(client: Client) -> None:
    listed = client.get(f"{API}/devices").json()
    camera = client.get(f"{API}/devices/S3")
    missing = client.get(f"{API}/devices/S9")

    assert {d["kind"] for d in listed} == {"camera", "projector", "trigger"}
    assert camera.status_code == 200
    assert camera.json()["unit"] == "right"
    assert camera.json()["driver"] == "SimCamera"
    assert camera.json()["details"]["width"] > 0
    assert next(d for d in listed if d["id"] == "T1")["unit"] is None
    assert missing.status_code == 404
    assert missing.json() == {"detail": "no device with id 'S9'"}


@pytest.mark.parametrize(("unit", "cameras"), [("left", [["S1", "S2"]]),
                                              ("all", [["S1", "S2"], ["S3", "S4"]])])
def test_a_capture_is_acknowledged_with_its_bundle_on_disk(
    client: Client, data_dir: Path, unit: str, cameras: list[list[str]]
) -> None:
    created = _capture(client, unit)

    assert created["id"].startswith("cap-")
    assert created["unit"] == unit
    assert created["kind"] == "measurement"
    assert created["frame_count"] == len(cameras)
    bundle = read_bundle(data_dir / "captures" / created["id"])
    # "all" interleaves the units: one pulse (frame) per unit, lit by that unit's projector only.
    assert [sorted(f.images) for f in bundle.frames] == cameras
    assert [f.projectors_on for f in bundle.frames] == [("P1",), ("P2",)][:len(cameras)]
    for frame, camera_ids in zip(bundle.frames, cameras, strict=True):
        for camera_id in camera_ids:
            image = np.asarray(bundle.load_image(frame.index, camera_id))
            assert image.ndim == 2 and image.size > 0
            assert image.std() > 1  # the fringes on the eye, not a blank frame
    assert client.get(f"{API}/captures/{created['id']}").json() == created


def test_captures_are_listed_newest_first_in_pages_and_by_unit(client: Client) -> None:
    taken = [_capture(client, "right")["id"] for _ in range(3)]

    first = client.get(f"{API}/captures", params={"limit": 2}).json()
    second = client.get(f"{API}/captures", params={"limit": 2, "offset": 2}).json()
    right = client.get(f"{API}/captures", params={"unit": "right"}).json()
    bad_page = client.get(f"{API}/captures", params={"limit": 0})

    assert [c["id"] for c in first["items"]] == taken[::-1][:2]
    assert second["items"][0]["id"] == taken[0]
    assert first["total"] == second["total"] >= 3
    assert (first["limit"], second["offset"]) == (2, 2)
    assert [c["id"] for c in right["items"]] == taken[::-1]
    assert right["total"] == 3
    assert bad_page.status_code == 422


@pytest.mark.parametrize("capture_id", ["cap-20200101T000000000Z-0000", "not-an-id"])
def test_an_unknown_capture_is_a_json_404(client: Client, capture_id: str) -> None:
    response = client.get(f"{API}/captures/{capture_id}")

    assert response.status_code == 404
    assert response.json() == {"detail": f"no capture with id {capture_id!r}"}


def test_an_unknown_unit_is_a_json_422_with_the_reason(client: Client) -> None:
    response = client.post(f"{API}/captures", json={"unit": "middle"})
    malformed = client.post(f"{API}/captures", json={"units": "all"})

    assert response.status_code == 422
    assert response.json() == {
        "detail": "unknown unit 'middle'; the rig has left, right (or 'all')"}
    assert malformed.status_code == 422
    assert "detail" in malformed.json()


def test_a_busy_daemon_answers_409_naming_its_state(client: Client,
                                                    service: Service) -> None:
    with service.operation("calibrating"):
        state = client.get(f"{API}/status").json()["state"]
        response = client.post(f"{API}/captures", json={"unit": "left"})

    assert state == "calibrating"
    assert response.status_code == 409
    assert response.json() == {"detail": "cannot start a capture: the daemon is calibrating"}
    assert client.get(f"{API}/status").json()["state"] == "idle"


@pytest.mark.slow
def test_a_capture_in_progress_blocks_another(client: Client, service: Service) -> None:
    # A lost transfer makes S1's read wait out its time-out (2 s): the capture stays running.
    # A second capture asked for meanwhile is not refused: it waits its turn on the
    # acquisition worker (a triggered capture is never dropped) and runs after the first.
    _camera(service, "S1").inject_fault("timeout")
    responses: dict[str, Any] = {}

    def post(name: str, unit: str) -> threading.Thread:
        runner = threading.Thread(target=lambda: responses.update(
            {name: client.post(f"{API}/captures", json={"unit": unit})}))
        runner.start()
        return runner

    slow = post("slow", "left")
    assert _wait_until(lambda: service.state == "capturing")
    queued = post("queued", "right")
    assert _wait_until(lambda: service.acquisition_worker.waiting == 1)
    state_while_queued = service.state
    slow.join(timeout=30)
    queued.join(timeout=30)

    assert state_while_queued == "capturing"
    assert responses["slow"].status_code == 504
    assert responses["slow"].json()["detail"].startswith("S1: frame lost in transfer")
    assert responses["queued"].status_code == 201, responses["queued"].text
    assert responses["queued"].json()["unit"] == "right"
    # The time-out put S1 in fault; the next capture (or the background retry) reopens it.
    _capture(client, "left")
    assert client.get(f"{API}/status").json()["state"] == "idle"


def test_a_full_acquisition_queue_answers_503_naming_it(client: Client,
                                                        service: Service) -> None:
    worker = service.acquisition_worker
    running, release = threading.Event(), threading.Event()
    blocker = worker.submit(lambda: running.set() or release.wait(30))
    assert running.wait(10)
    fillers = [worker.submit(lambda: None) for _ in range(worker.capacity)]
    try:
        capture = client.post(f"{API}/captures", json={"unit": "left"})
        setting = client.request("PATCH", f"{API}/devices/S1", json={"gain_db": 1.0})
    finally:
        release.set()
    blocker.result(timeout=10)
    for filler in fillers:
        filler.result(timeout=10)

    expected = {"detail": "the acquisition queue is full (8 jobs waiting); try again later"}
    assert (capture.status_code, capture.json()) == (503, expected)
    assert (setting.status_code, setting.json()) == (503, expected)
    # A full queue clears in a moment: the answer says when to try again.
    assert capture.headers["retry-after"] == setting.headers["retry-after"] == "1"
    assert client.get(f"{API}/devices/S1").json()["details"]["gain_db"] == 0.0
    _capture(client, "left")  # nothing was lost: the queue works again


def test_a_disconnected_camera_faults_its_unit_until_it_comes_back(
    client: Client, service: Service
) -> None:
    camera = _camera(service, "S3")
    camera.inject_fault("disconnect")

    failed = client.post(f"{API}/captures", json={"unit": "right"})
    status = client.get(f"{API}/status").json()
    still_failing = client.post(f"{API}/captures", json={"unit": "all"})
    other_unit = client.post(f"{API}/captures", json={"unit": "left"})
    status_during = client.get(f"{API}/status").json()["state"]
    camera.reconnect()
    recovered = client.post(f"{API}/captures", json={"unit": "right"})
    after = client.get(f"{API}/status").json()

    assert failed.status_code == 503
    assert failed.json() == {"detail": "S3: camera is not responding"}
    assert status["state"] == "fault"
    units = {u["id"]: u for u in status["units"]}
    assert units["right"]["health"] == "fault"
    assert units["right"]["reason"] == "S3: camera is not responding"
    assert units["left"]["health"] == "ok"
    s3 = next(d for d in status["devices"] if d["id"] == "S3")
    assert (s3["health"], s3["reason"]) == ("fault", "camera is not responding")
    assert still_failing.status_code == 503
    assert other_unit.status_code == 201  # the healthy unit keeps working
    assert status_during == "fault"
    assert recovered.status_code == 201
    assert after["state"] == "idle"
    assert all(d["health"] == "ok" for d in after["devices"])
    assert all(u["health"] == "ok" for u in after["units"])


class SteppedWaits:
    """The background recovery's wait, stepped by the test instead of the clock.

    Records every delay asked for; the ``n``-th wait returns once :meth:`release` was called
    ``n`` times (or the service stops).
    """

    def __init__(self) -> None:
        self.delays: list[float] = []
        self._released = 0
        self._changed = threading.Condition()

    def __call__(self, delay_s: float, stop: threading.Event) -> bool:
        with self._changed:
            self.delays.append(delay_s)
            turn = len(self.delays)
            self._changed.notify_all()
            while self._released < turn and not stop.is_set():
                self._changed.wait(0.05)
        return stop.is_set()

    def release(self) -> None:
        with self._changed:
            self._released += 1
            self._changed.notify_all()

    def wait_for(self, count: int, timeout_s: float = 30) -> list[float]:
        """The delays once ``count`` waits were asked for (the attempt before them is done)."""
        with self._changed:
            assert self._changed.wait_for(lambda: len(self.delays) >= count, timeout_s), \
                f"the recovery asked for {len(self.delays)} waits, not {count}"
            return list(self.delays)


def test_a_failed_device_recovers_in_the_background_with_back_off(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    waits = SteppedWaits()
    monkeypatch.setattr(app_module, "Service", functools.partial(Service, retry_wait=waits))
    app = create_app(test_settings(tmp_path / "data"))
    with serving(app) as client:
        service = app.state.service
        camera = _camera(service, "S3")
        camera.inject_fault("disconnect")

        failed = client.post(f"{API}/captures", json={"unit": "right"})
        status = client.get(f"{API}/status").json()
        first = waits.wait_for(1)
        for attempt in range(1, 7):  # S3 is still unplugged: each retry fails, the wait grows
            waits.release()
            waits.wait_for(attempt + 1)
        still_failing = client.get(f"{API}/status").json()
        # The recovery's next attempt is 30 s away: a refused client is told to wait that long.
        refused = client.post(f"{API}/captures", json={"unit": "right"})
        camera.reconnect()
        waits.release()  # the seventh retry reopens S3: no capture is needed for that
        recovered = _wait_until(lambda: service.state == "idle")
        after = client.get(f"{API}/status").json()
        camera.inject_fault("disconnect")  # a new fault starts the schedule again
        again = client.post(f"{API}/captures", json={"unit": "right"})
        schedule = waits.wait_for(8)
        camera.reconnect()
        waits.release()
        assert _wait_until(lambda: service.state == "idle")

    assert failed.status_code == 503
    assert failed.json() == {"detail": "S3: camera is not responding"}
    assert failed.headers["Retry-After"] == "1"
    assert status["state"] == "fault"
    assert first == [1.0]
    assert refused.status_code == 503
    assert 20 < int(refused.headers["Retry-After"]) <= 30
    assert still_failing["state"] == "fault"
    assert next(u for u in still_failing["units"] if u["id"] == "right")["reason"] == \
        "S3: camera is not responding"
    assert recovered
    assert after["state"] == "idle"
    assert all(d["health"] == "ok" and d["open"] for d in after["devices"])
    assert again.status_code == 503
    assert schedule == [1.0, 2.0, 4.0, 8.0, 16.0, 30.0, 30.0, 1.0]


@pytest.mark.slow
def test_a_capture_is_found_again_after_a_restart(tmp_path: Path) -> None:
    settings = test_settings(tmp_path / "data")
    with serving(create_app(settings)) as first:
        created = _capture(first, "left")

    with serving(create_app(settings)) as second:
        found = second.get(f"{API}/captures/{created['id']}")
        listed = second.get(f"{API}/captures").json()

    assert found.status_code == 200
    assert found.json() == created
    assert [c["id"] for c in listed["items"]] == [created["id"]]


def test_the_openapi_document_has_the_routes_and_examples(client: Client) -> None:
    document = client.get(f"{API}/openapi.json").json()

    assert {"/api/v1/status", "/api/v1/devices", "/api/v1/devices/{device_id}",
            "/api/v1/captures", "/api/v1/captures/{capture_id}"} <= set(document["paths"])
    request = document["components"]["schemas"]["CaptureRequest"]
    assert request["properties"]["unit"]["examples"] == ["all", "left"]
    assert "201" in document["paths"]["/api/v1/captures"]["post"]["responses"]


def test_a_bugs_500_leaves_the_keep_alive_connection_usable(tmp_path: Path) -> None:
    # Issue 35: after any 500 the next request on the same connection was reset.
    app = create_app(test_settings(tmp_path / "data"))

    async def boom() -> None:
        raise RuntimeError("a bug")

    app.add_api_route("/api/v1/boom-for-test", boom)
    with live_server(app) as url:
        host, port = url.removeprefix("http://").split(":")
        request = (f"GET /api/v1/boom-for-test HTTP/1.1\r\nHost: {host}\r\n"
                   f"Authorization: Bearer {OPERATOR_TOKEN}\r\n\r\n").encode()
        health = f"GET /api/v1/health HTTP/1.1\r\nHost: {host}\r\n\r\n".encode()
        with socket.create_connection((host, int(port)), timeout=30) as sock:
            stream = sock.makefile("rb")
            sock.sendall(request)
            first = _read_response(stream)
            sock.sendall(health)
            second = _read_response(stream)

    assert first[0] == 500 and json.loads(first[1]) == {"detail": "internal server error"}
    assert second[0] == 200 and json.loads(second[1])["status"] == "ok"


def _read_response(stream: Any) -> tuple[int, bytes]:
    status = int(stream.readline().split()[1])
    length = 0
    while (line := stream.readline()) not in (b"\r\n", b""):
        name, _, value = line.decode().partition(":")
        if name.lower() == "content-length":
            length = int(value)
    return status, stream.read(length)


def test_uploads_unpack_in_the_data_directory_and_leftovers_go_at_start(tmp_path: Path) -> None:
    # Issue 35: uploads unpacked into the system's temporary directory, were left there by a
    # kill -9, and error messages named them.
    data_dir = tmp_path / "data"
    leftover = data_dir / "uploads" / "calibration-killed"
    leftover.mkdir(parents=True)
    (leftover / "arrays.npz").write_bytes(bytes(1024))
    app = create_app(test_settings(data_dir))
    with serving(app) as client:
        assert not leftover.exists()
        bad = io.BytesIO()
        with zipfile.ZipFile(bad, "w") as archive:
            archive.writestr("calibration.json", "{not json")
            archive.writestr("arrays.npz", b"")
        answer = client.post(f"{API}/calibrations", content=bad.getvalue(),
                             headers={"content-type": "application/zip"})

    assert answer.status_code == 422
    assert answer.json()["detail"].startswith("upload:calibration.json: not valid JSON")
    assert list((data_dir / "uploads").iterdir()) == []


def test_a_full_disk_is_507_with_the_reason_everywhere(tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    # Issue 35: SQLite's "database or disk is full" gave 500 on patient creation or deletion.
    app = create_app(test_settings(tmp_path / "data"))
    with serving(app) as client:
        store = app.state.service.store

        @contextlib.contextmanager
        def full() -> Iterator[None]:
            raise sqlite3.OperationalError("database or disk is full")
            yield

        monkeypatch.setattr(store, "transaction", full)
        patient = client.put(f"{API}/patients/P-1", json={"eye": "left"})
        monkeypatch.undo()

        def no_space(*args: Any, **kwargs: Any) -> None:
            raise StorageError("capture x: cannot write the bundle") from OSError(
                errno.ENOSPC, "No space left on device")

        monkeypatch.setattr(store, "add_capture", no_space)
        capture = client.post(f"{API}/captures", json={"unit": "left"})

    for answer in (patient, capture):
        assert answer.status_code == 507, answer.text
        assert answer.json()["detail"].startswith("the data directory's disk is full") or \
            "cannot write the bundle" in answer.json()["detail"]


@pytest.mark.parametrize("public", [True, False])
def test_the_api_documents_are_open_or_need_a_token_as_configured(tmp_path: Path,
                                                                  public: bool) -> None:
    settings = test_settings(tmp_path / "data").model_copy(update={"public_api_docs": public})
    with serving(create_app(settings)) as client:
        anonymous = client.get(f"{API}/openapi.json", headers={"Authorization": ""})
        with_token = client.get(f"{API}/openapi.json")
        docs = client.get(f"{API}/docs", headers={"Authorization": ""})
        assets = {url: client.get(url, headers={"Authorization": ""})
                  for url in re.findall(r'(?:src|href)="([^"]+)"', docs.text)}

    assert anonymous.status_code == (200 if public else 401)
    assert with_token.status_code == 200 and "/api/v1/status" in with_token.json()["paths"]
    assert docs.status_code == (200 if public else 404)
    if public:
        # Every asset of the page comes from the daemon (a room PC has no internet).
        assert set(assets) == {f"{API}/docs/assets/swagger-ui.css",
                               f"{API}/docs/assets/swagger-ui-bundle.js",
                               f"{API}/docs/assets/favicon-32x32.png"}
        assert all(answer.status_code == 200 for answer in assets.values())
        assert "SwaggerUIBundle" in assets[f"{API}/docs/assets/swagger-ui-bundle.js"].text
        assert "://" not in docs.text.replace("http://www.w3.org", "")


def test_the_document_describes_every_answer_and_errors_have_one_shape(client: Client) -> None:
    document = client.get(f"{API}/openapi.json").json()
    schemas = document["components"]["schemas"]

    for path, methods in document["paths"].items():
        for method, operation in methods.items():
            assert {"500", "507"} <= set(operation["responses"]), (method, path)
            if "requestBody" in operation:
                assert "400" in operation["responses"], (method, path)
    assert schemas["HTTPValidationError"]["properties"]["detail"]["type"] == "string"
    invalid = client.post(f"{API}/captures", json={"unit": 7, "extra": True})
    assert invalid.status_code == 422
    assert isinstance(invalid.json()["detail"], str) and "body.unit" in invalid.json()["detail"]
    assert [e["loc"][-1] for e in invalid.json()["errors"]] == ["unit", "extra"]
    assert client.get(f"{API}/captures/nope").json().keys() == {"detail"}
