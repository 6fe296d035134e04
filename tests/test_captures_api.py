"""Capture data through the REST API: bundle zips, single images, deletion, the kept
reconstruction summary with its options, list filters; and the store's filters below them.

One app serves the module. Fixtures order what must come first: ``uncalibrated_id`` is taken
before any calibration is active (``active_id`` depends on it).
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import sqlite3
import zipfile
from collections.abc import Callable, Iterator
from datetime import UTC, datetime, timedelta, timezone
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from fastapi import FastAPI

from eyeserver.io import BUNDLE_FILE, BundleFrameData, read_bundle, read_ply, rig_from_dict
from eyeserver.service.core import CLOUD_FILE, SUMMARY_FILE, Service
from eyeserver.service.storage import Store
from tests.apiclient import API, OPERATOR_TOKEN, Client, auth
from tests.test_service_calibration_api import ZIP, _calibration_members, _zip
from tests.test_storage import RIG_DOCUMENT, calibration_dir, frames

_NO_CAPTURE = "cap-20000101T000000000Z-0000"


@pytest.fixture(scope="module")
def caldir(calibrated_rooms: Callable[[str], tuple[Path, Path]]) -> Path:
    return calibrated_rooms("default")[1]


@pytest.fixture(scope="module")
def service(app: FastAPI, client: Client) -> Service:
    running = app.state.service
    assert isinstance(running, Service)
    return running


def _capture(client: Client, unit: str = "all") -> dict[str, Any]:
    response = client.post(f"{API}/captures", json={"unit": unit})
    assert response.status_code == 201, response.text
    created: dict[str, Any] = response.json()
    return created


@pytest.fixture(scope="module")
def uncalibrated_id(client: Client) -> str:
    return str(_capture(client)["id"])


@pytest.fixture(scope="module")
def calibration_zip(caldir: Path) -> bytes:
    return _zip(_calibration_members(caldir))


@pytest.fixture(scope="module")
def active_id(client: Client, uncalibrated_id: str, calibration_zip: bytes) -> str:
    imported = client.post(f"{API}/calibrations", content=calibration_zip, headers=ZIP)
    assert imported.status_code == 201, imported.text
    calibration_id = str(imported.json()["id"])
    activated = client.post(f"{API}/calibrations/{calibration_id}/activate")
    assert activated.status_code == 200, activated.text
    return calibration_id


@pytest.fixture(scope="module")
def reconstructed(client: Client, active_id: str) -> dict[str, Any]:
    """A capture reconstructed with the default options: its id and the POST's answer."""
    capture_id = _capture(client)["id"]
    before = client.get(f"{API}/captures/{capture_id}/reconstruction")
    assert before.status_code == 404
    assert "has not been reconstructed" in before.json()["detail"]
    response = client.post(f"{API}/captures/{capture_id}/reconstruction")
    assert response.status_code == 200, response.text
    return {"id": capture_id, "summary": response.json()}


def _stored_files(directory: Path) -> dict[str, bytes]:
    return {p.relative_to(directory).as_posix(): p.read_bytes()
            for p in sorted(directory.rglob("*")) if p.is_file()}


# --- the bundle as a zip, single images -----------------------------------------------------


@pytest.mark.slow
def test_the_bundle_zip_holds_the_bundle_byte_for_byte(client: Client, service: Service,
                                                       tmp_path: Path) -> None:
    capture_id = _capture(client)["id"]
    stored = _stored_files(service.store.capture_path(capture_id))

    response = client.get(f"{API}/captures/{capture_id}/bundle.zip")

    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "application/zip"
    assert f'filename="{capture_id}.zip"' in response.headers["content-disposition"]
    assert int(response.headers["content-length"]) == len(response.content)
    with zipfile.ZipFile(io.BytesIO(response.content)) as archive:
        assert archive.testzip() is None
        members = {info.filename: info for info in archive.infolist()}
        assert set(members) == {f"{capture_id}/{name}" for name in stored}
        for name, data in stored.items():
            assert archive.read(f"{capture_id}/{name}") == data, name
            if name.endswith(".png"):
                assert members[f"{capture_id}/{name}"].compress_type == zipfile.ZIP_STORED
        archive.extractall(tmp_path)
    unpacked = read_bundle(tmp_path / capture_id)  # unzipped, it is a bundle again
    assert len(unpacked.frames) == 2 and unpacked.kind == "measurement"


@pytest.mark.slow
def test_the_bundle_zip_leaves_out_the_cloud_and_its_summary(
        client: Client, reconstructed: dict[str, Any]) -> None:
    capture_id = reconstructed["id"]

    response = client.get(f"{API}/captures/{capture_id}/bundle.zip")

    with zipfile.ZipFile(io.BytesIO(response.content)) as archive:
        names = {name.split("/", 1)[1] for name in archive.namelist()}
    assert BUNDLE_FILE in names and CLOUD_FILE not in names and SUMMARY_FILE not in names


def test_every_image_is_served_as_stored_and_decodes_to_its_camera_size(
        client: Client, service: Service, uncalibrated_id: str) -> None:
    directory = service.store.capture_path(uncalibrated_id)
    document = json.loads((directory / BUNDLE_FILE).read_text())
    rig = rig_from_dict(document["rig"], "bundle.json")
    served = 0
    for frame in document["frames"]:
        for camera_id, name in frame["images"].items():
            response = client.get(
                f"{API}/captures/{uncalibrated_id}/frames/{frame['index']}/{camera_id}.png")

            assert response.status_code == 200, response.text
            assert response.headers["content-type"] == "image/png"
            assert response.content == (directory / name).read_bytes()
            image = cv2.imdecode(np.frombuffer(response.content, np.uint8),
                                 cv2.IMREAD_UNCHANGED)
            camera = rig.camera(camera_id)
            assert image is not None and image.shape == (camera.height, camera.width)
            served += 1
    assert served == 4  # two units interleaved, two cameras each


@pytest.mark.parametrize(("path", "reason"), [
    ("frames/7/S1.png", "has no frame 7 (its frames are 0, 1)"),
    ("frames/-1/S1.png", "has no frame -1"),
    ("frames/0/S9.png", "no image of camera 'S9' (not a camera of the rig"),
    ("frames/0/S3.png", "no image of camera 'S3' (a camera of the rig; the frame holds S1, S2)"),
])
def test_a_missing_frame_or_image_is_a_json_404_naming_it(
        client: Client, uncalibrated_id: str, path: str, reason: str) -> None:
    response = client.get(f"{API}/captures/{uncalibrated_id}/{path}")

    assert response.status_code == 404
    assert reason in response.json()["detail"]


@pytest.mark.parametrize("path", ["bundle.zip", "frames/0/S1.png", "reconstruction"])
def test_an_unknown_capture_is_a_json_404(client: Client, path: str) -> None:
    for capture_id in (_NO_CAPTURE, "not-an-id"):
        response = client.get(f"{API}/captures/{capture_id}/{path}")

        assert response.status_code == 404
        assert capture_id in response.json()["detail"]


# --- deletion -------------------------------------------------------------------------------


def test_an_operator_may_not_delete(client: Client, uncalibrated_id: str) -> None:
    response = client.delete(f"{API}/captures/{uncalibrated_id}",
                             params={"reason": "tidying up"}, headers=auth(OPERATOR_TOKEN))

    assert response.status_code == 403
    assert "physicist" in response.json()["detail"]
    assert client.get(f"{API}/captures/{uncalibrated_id}").status_code == 200


@pytest.mark.parametrize("params", [{}, {"reason": ""}, {"reason": "   "}],
                         ids=["none", "empty", "blank"])
def test_a_deletion_needs_a_reason(client: Client, uncalibrated_id: str,
                                   params: dict[str, str]) -> None:
    response = client.delete(f"{API}/captures/{uncalibrated_id}", params=params)

    assert response.status_code == 422
    assert response.json()["errors"][0]["loc"] == ["query", "reason"]
    assert response.json()["detail"].startswith("query.reason: ")
    assert client.get(f"{API}/captures/{uncalibrated_id}").status_code == 200


def test_a_deleted_capture_is_gone_audited_and_nothing_else_is(
        client: Client, service: Service, uncalibrated_id: str,
        reconstructed: dict[str, Any]) -> None:
    doomed = _capture(client)["id"]
    directory = service.store.capture_path(doomed)
    others = {item["id"] for item in client.get(f"{API}/captures",
                                                params={"limit": 1000}).json()["items"]}
    others.discard(doomed)
    kept_files = {capture_id: _stored_files(service.store.capture_path(capture_id))
                  for capture_id in (uncalibrated_id, reconstructed["id"])}

    response = client.delete(f"{API}/captures/{doomed}", params={"reason": "lens cap on"})

    assert response.status_code == 204 and response.content == b""
    for path in ("", "/bundle.zip", "/frames/0/S1.png", "/reconstruction", "/cloud.ply"):
        assert client.get(f"{API}/captures/{doomed}{path}").status_code == 404, path
    again = client.delete(f"{API}/captures/{doomed}", params={"reason": "twice"})
    assert again.status_code == 404
    assert not directory.exists()
    entry = next(e for e in service.store.audit_log() if e.action == "delete_capture")
    assert (entry.actor, entry.target) == ("physicist", doomed)
    assert entry.detail["reason"] == "lens cap on"
    listed = client.get(f"{API}/captures", params={"limit": 1000}).json()["items"]
    assert {item["id"] for item in listed} >= others
    assert doomed not in {item["id"] for item in listed}
    for capture_id, files in kept_files.items():
        assert _stored_files(service.store.capture_path(capture_id)) == files


# --- the reconstruction summary and its options ---------------------------------------------


def test_the_summary_is_kept_and_read_back(client: Client, service: Service,
                                           reconstructed: dict[str, Any],
                                           active_id: str) -> None:
    capture_id, summary = reconstructed["id"], reconstructed["summary"]

    response = client.get(f"{API}/captures/{capture_id}/reconstruction")

    assert response.status_code == 200
    assert response.json() == summary
    assert summary["calibration_id"] == active_id and summary["points"] > 100_000
    assert summary["options"] == {"method": "auto", "depth_prior_mm": None, "roi": None,
                                  "min_quality": 0.0}
    assert summary["method"] == "auto" and summary["duration_s"] > 0
    for camera in summary["cameras"].values():  # the default room's units discriminate orders
        assert camera["method"] == "spatial", camera
        assert camera["method_reason"].startswith("fringe-order margin 0.")
        assert 0.3 < camera["coverage"] <= 1.0
        assert camera["coverage"] == pytest.approx(camera["points"] / camera["fringe_pixels"],
                                                   abs=5e-5)  # rounded to 4 places
    assert summary["reconstructed"].endswith("Z")
    on_disk = json.loads((service.store.capture_path(capture_id) / SUMMARY_FILE).read_text())
    assert on_disk["points"] == summary["points"]


@pytest.mark.slow
def test_options_are_used_and_recorded(client: Client, service: Service,
                                       reconstructed: dict[str, Any], tmp_path: Path) -> None:
    capture_id, full = reconstructed["id"], reconstructed["summary"]
    low, high = full["extent_mm"]["min"], full["extent_mm"]["max"]
    middle_x = (low[0] + high[0]) / 2
    # The left half of the surface, with room to spare on every other side.
    roi = [low[0] - 1, low[1] - 1, low[2] - 1, middle_x, high[1] + 1, high[2] + 1]
    options = {"method": "spatial", "roi": roi, "min_quality": 0.05}

    response = client.post(f"{API}/captures/{capture_id}/reconstruction", json=options)

    assert response.status_code == 200, response.text
    summary = response.json()
    assert summary["method"] == "spatial"
    assert summary["options"] == {**options, "depth_prior_mm": None}
    assert 0 < summary["points"] < full["points"]
    assert summary["dropped"]["outside_region"] > 0
    assert summary["extent_mm"]["max"][0] <= middle_x
    assert client.get(f"{API}/captures/{capture_id}/reconstruction").json() == summary
    ply = client.get(f"{API}/captures/{capture_id}/cloud.ply")
    (tmp_path / "cloud.ply").write_bytes(ply.content)
    cloud = read_ply(tmp_path / "cloud.ply")
    assert len(cloud) == summary["points"]
    assert cloud.points[:, 0].max() <= middle_x
    assert cloud.quality is not None and cloud.quality.min() >= 0.05


def test_an_empty_scene_reconstructs_to_an_empty_cloud_with_its_reason(
        client: Client, active_id: str) -> None:
    # Issue 35: 500, and the stored summary (no extent_mm) made every later GET 500.
    before = client.get(f"{API}/sim/scene").json()
    assert client.put(f"{API}/sim/scene", json={"kind": "empty"}).status_code == 200
    try:
        capture_id = _capture(client)["id"]
    finally:
        assert client.put(f"{API}/sim/scene", json=before).status_code == 200

    made = client.post(f"{API}/captures/{capture_id}/reconstruction")
    again = client.get(f"{API}/captures/{capture_id}/reconstruction")

    assert made.status_code == 200, made.text
    assert made.json()["points"] == 0 and made.json()["extent_mm"] is None
    assert made.json()["empty_reason"].startswith("no surface was reconstructed")
    assert again.status_code == 200 and again.json() == made.json()


def test_offsets_beyond_what_the_store_holds_are_422(client: Client) -> None:
    huge = "99999999999999999999"
    answers = [client.get(f"{API}/captures", params={"offset": huge}),
               client.get(f"{API}/pose/measurements",
                          params={"patient_id": "P", "offset": "2785830935783066828800"}),
               client.get(f"{API}/patients/P/eye-models/"
                          "108528543049643317716051804321908523008")]

    assert [a.status_code for a in answers] == [422, 422, 422], [a.text for a in answers]
    assert client.get(f"{API}/captures", params={"offset": str(2**63 - 1)}).status_code == 200


@pytest.mark.parametrize(("body", "problem"), [
    ({"method": "fast"}, "method"),
    ({"roi": [0, 0, 0, 1, 1]}, "roi"),
    ({"roi": [1, 0, 0, 0, 1, 1]}, "low corner"),
    ({"min_quality": 1.5}, "min_quality"),
    ({"depth_prior_mm": "deep"}, "depth_prior_mm"),
    ({"frames": [0]}, "frames"),
    ('{"depth_prior_mm": NaN}', "depth_prior_mm"),
], ids=["method", "short roi", "inverted roi", "quality", "prior", "extra", "nan"])
def test_bad_options_are_a_422_with_reasons(client: Client, uncalibrated_id: str,
                                            body: dict[str, Any] | str, problem: str) -> None:
    if isinstance(body, str):
        response = client.post(f"{API}/captures/{uncalibrated_id}/reconstruction",
                               content=body, headers={"content-type": "application/json"})
    else:
        response = client.post(f"{API}/captures/{uncalibrated_id}/reconstruction", json=body)

    assert response.status_code == 422, response.text
    assert problem in json.dumps(response.json()["detail"])


# --- list filters ---------------------------------------------------------------------------


def _listed(client: Client, **params: str) -> tuple[list[str], int]:
    response = client.get(f"{API}/captures", params={"limit": "1000", **params})
    assert response.status_code == 200, response.text
    page = response.json()
    return [item["id"] for item in page["items"]], int(page["total"])


def test_captures_are_filtered_by_kind_calibration_unit_and_time(
        client: Client, uncalibrated_id: str, active_id: str) -> None:
    left = _capture(client, "left")
    everything, total = _listed(client)
    assert uncalibrated_id in everything and left["id"] in everything

    assert _listed(client, kind="measurement") == (everything, total)
    assert _listed(client, kind="chessboard") == ([], 0)
    calibrated, count = _listed(client, calibration_id=active_id)
    assert left["id"] in calibrated and uncalibrated_id not in calibrated
    assert count == len(calibrated) < total
    assert _listed(client, unit="left", calibration_id=active_id)[0] == [left["id"]]
    assert _listed(client, since=left["created"])[0] == [left["id"]]
    assert left["id"] not in _listed(client, until=left["created"])[0]
    since_first = _listed(client, since=client.get(
        f"{API}/captures/{uncalibrated_id}").json()["created"])[0]
    assert since_first[-1] == uncalibrated_id
    window, _ = _listed(client, since="2000-01-01T00:00:00Z", until=left["created"],
                        kind="measurement")
    assert window == everything[1:]  # all but the newest, the left capture
    # The same moment in another time zone is the same bound.
    east = datetime.fromisoformat(left["created"]).astimezone(timezone(timedelta(hours=2)))
    assert _listed(client, since=east.isoformat())[0] == [left["id"]]
    assert left["id"] not in _listed(client, until=east.isoformat())[0]
    assert datetime.fromisoformat(left["created"]).tzinfo == UTC


@pytest.mark.parametrize("params", [
    {"kind": "photo"},
    {"calibration_id": "cal-latest"},
    {"since": "yesterday"},
    {"since": "1700000000"},
    {"until": "2026-11-23T10:00:00"},  # no time zone
    {"since": "2026-11-23T10:00:00Z", "until": "2026-11-23T09:00:00Z"},
], ids=["kind", "calibration", "words", "unix time", "naive", "inverted"])
def test_malformed_filters_are_422(client: Client, params: dict[str, str]) -> None:
    response = client.get(f"{API}/captures", params=params)

    assert response.status_code == 422, response.text
    detail = json.dumps(response.json()["detail"])
    assert any(name in detail for name in params)


# --- calibrations uploaded through the API say where they came from -------------------------


def test_an_uploaded_calibration_records_who_and_what_not_a_temporary_directory(
        service: Service, active_id: str, calibration_zip: bytes) -> None:
    expected = f"upload by physicist, sha256:{hashlib.sha256(calibration_zip).hexdigest()}"

    record = service.store.get_calibration(active_id)

    assert record.source == expected
    entry = next(e for e in service.store.audit_log(1000) if e.action == "import_calibration"
                 and e.target == active_id)
    assert entry.detail == {"source": expected}


# --- the store's filters beneath the API ----------------------------------------------------


@pytest.fixture
def store(tmp_path: Path) -> Iterator[Store]:
    with Store.open(tmp_path / "data") as opened:
        yield opened


def test_store_filters_are_indexed_and_combine(store: Store, tmp_path: Path) -> None:
    rig = rig_from_dict(RIG_DOCUMENT, "test")
    calibration = store.import_calibration(calibration_dir(tmp_path / "cal"), actor="alice",
                                           source="made by hand")
    plain = store.add_capture("measurement", rig, frames(), unit="left", calibration_id=None)
    with_cal = store.add_capture("measurement", rig, frames(), unit="left",
                                 calibration_id=calibration.id)
    reference = store.add_capture("reference", rig, [
        BundleFrameData(images=f.images, z_mm=1.0, projectors_on=f.projectors_on)
        for f in frames()], unit="left", calibration_id=calibration.id)

    def ids(**filters: Any) -> list[str]:
        records, total = store.list_captures(**filters)
        assert total == len(records)
        return [r.id for r in records]

    assert calibration.source == "made by hand"
    assert ids(kind="reference") == [reference.id]
    assert ids(calibration_id=calibration.id) == [reference.id, with_cal.id]
    assert ids(kind="measurement", calibration_id=calibration.id) == [with_cal.id]
    created = datetime.fromisoformat(with_cal.created)
    assert ids(since=created, until=created + timedelta(milliseconds=1)) == [with_cal.id]
    # A bound between two milliseconds: created at .xyz is before .xyz + 0.5 ms and not after.
    half = timedelta(microseconds=500)
    assert ids(since=created - half, until=created + half) == [with_cal.id]
    assert with_cal.id not in ids(since=created + half)
    assert plain.id in ids(until=created)
    with pytest.raises(ValueError, match="until"):
        store.list_captures(until=datetime(2026, 1, 1))
    assert _query_plan(store.data_dir, "kind") == "captures_by_kind"
    assert _query_plan(store.data_dir, "calibration_id") == "captures_by_calibration"


def _query_plan(data_dir: Path, column: str) -> str:
    """The index SQLite uses for a filter on ``column`` (empty when it scans the table)."""
    with contextlib.closing(sqlite3.connect(data_dir / "index.sqlite3")) as db:
        plan = " ".join(str(row) for row in db.execute(
            f"EXPLAIN QUERY PLAN SELECT id FROM captures WHERE {column} = ? ORDER BY id DESC",
            ("x",)))
    for name in ("captures_by_kind", "captures_by_calibration"):
        if name in plan:
            return name
    return ""


def test_an_older_index_gains_the_filter_indexes(tmp_path: Path) -> None:
    Store.open(tmp_path / "data").close()
    with contextlib.closing(sqlite3.connect(tmp_path / "data" / "index.sqlite3")) as db:
        db.execute("DROP INDEX captures_by_kind")
        db.execute("DROP INDEX captures_by_calibration")
        db.commit()
    assert _query_plan(tmp_path / "data", "kind") == ""

    Store.open(tmp_path / "data").close()

    assert _query_plan(tmp_path / "data", "kind") == "captures_by_kind"
    assert _query_plan(tmp_path / "data", "calibration_id") == "captures_by_calibration"
