"""Calibrations and reconstructions through the REST API.

A calibration of the default simulated room (the session fixture) is uploaded as a zip,
activated, and used to reconstruct a fresh capture of the daemon's simulated eye. One app serves
the module; the tests run in file order, as the first needs a daemon with no active calibration.
"""

from __future__ import annotations

import io
import json
import math
import stat
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from fastapi import FastAPI

from eyeserver.calibration.artefact import ARRAYS_FILE, CALIBRATION_FILE
from eyeserver.io import read_ply
from eyeserver.service.core import Service
from eyeserver.service.uploads import UploadTooLargeError, unpack_calibration_zip
from tests.apiclient import API, Client

ZIP = {"content-type": "application/zip"}


def _zip(members: dict[str, bytes], symlinks: tuple[str, ...] = ()) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
        for name, data in members.items():
            info = zipfile.ZipInfo(name)
            if name in symlinks:
                info.external_attr = (stat.S_IFLNK | 0o777) << 16
            archive.writestr(info, data)
    return buffer.getvalue()


def _calibration_members(caldir: Path, folder: str = "") -> dict[str, bytes]:
    return {folder + name: (caldir / name).read_bytes()
            for name in (CALIBRATION_FILE, ARRAYS_FILE)}


@pytest.fixture(scope="module")
def caldir(calibrated_rooms: Callable[[str], tuple[Path, Path]]) -> Path:
    return calibrated_rooms("default")[1]


@pytest.fixture(scope="module")
def capture_id(client: Client) -> str:
    response = client.post(f"{API}/captures", json={"unit": "all"})
    assert response.status_code == 201, response.text
    return str(response.json()["id"])


@pytest.fixture(scope="module")
def imported_id(client: Client, caldir: Path) -> str:
    response = client.post(f"{API}/calibrations", content=_zip(_calibration_members(caldir)),
                           headers=ZIP)
    assert response.status_code == 201, response.text
    return str(response.json()["id"])


@pytest.fixture(scope="module")
def active_id(client: Client, imported_id: str) -> str:
    response = client.post(f"{API}/calibrations/{imported_id}/activate")
    assert response.status_code == 200, response.text
    return imported_id


@pytest.mark.slow
def test_reconstruction_without_an_active_calibration_is_409_with_the_reason(
        client: Client, capture_id: str) -> None:
    assert client.get(f"{API}/status").json()["active_calibration_id"] is None

    response = client.post(f"{API}/captures/{capture_id}/reconstruction")

    assert response.status_code == 409
    assert "no calibration is active" in response.json()["detail"]


@pytest.mark.parametrize("resource", ["cloud.ply", "preview.png"])
def test_cloud_and_preview_are_json_404_before_a_reconstruction(
        client: Client, capture_id: str, resource: str) -> None:
    response = client.get(f"{API}/captures/{capture_id}/{resource}")

    assert response.status_code == 404
    assert "has not been reconstructed" in response.json()["detail"]


@pytest.mark.parametrize("folder", ["", "cal/"], ids=["flat", "in-a-folder"])
def test_a_calibration_zip_is_imported_listed_and_found(client: Client, caldir: Path,
                                                        folder: str) -> None:
    response = client.post(f"{API}/calibrations",
                           content=_zip(_calibration_members(caldir, folder)), headers=ZIP)

    assert response.status_code == 201, response.text
    created = response.json()
    assert created["id"].startswith("cal-")
    assert created["active"] is False and created["status"] == "ok"
    expected_quality = json.loads((caldir / CALIBRATION_FILE).read_text())["quality"]
    assert created["quality"] == expected_quality and created["quality"]
    listed = client.get(f"{API}/calibrations").json()["items"]
    assert listed[0] == created  # newest first
    assert client.get(f"{API}/calibrations/{created['id']}").json() == created


def _bad_archives(caldir: Path) -> dict[str, tuple[bytes, str]]:
    good = _calibration_members(caldir)
    return {
        "parent": (_zip({**good, "../x": b"x"}), "'..'"),
        "absolute": (_zip({"/etc/calibration.json": good[CALIBRATION_FILE]}), "absolute"),
        "symlink": (_zip({**good, ARRAYS_FILE: b"/etc/passwd"}, symlinks=(ARRAYS_FILE,)),
                    "symbolic links"),
        "extra file": (_zip({**good, "notes.txt": b"hello"}), "only calibration.json"),
        "two folders": (_zip({"a/" + CALIBRATION_FILE: good[CALIBRATION_FILE],
                              "b/" + ARRAYS_FILE: good[ARRAYS_FILE]}), "one top-level folder"),
        "not a zip": (b"PK but not really", "not a zip file"),
        "no calibration.json": (_zip({ARRAYS_FILE: good[ARRAYS_FILE]}),
                                "holds no calibration.json"),
        "not a calibration": (_zip({CALIBRATION_FILE: b'{"format": "something-else"}'}),
                              "field 'format'"),
        "not JSON": (_zip({CALIBRATION_FILE: b"\x00\x01"}), "not valid JSON"),
        "evidence elsewhere": (_zip({"a/" + CALIBRATION_FILE: good[CALIBRATION_FILE],
                                     "b/inputs/cap-1/bundle.json": b"{}"}),
                               "one top-level folder"),
        "unsafe evidence": (_zip({**good, "inputs/../../x": b"x"}), "'..'"),
    }


@pytest.mark.parametrize("case", ["parent", "absolute", "symlink", "extra file", "two folders",
                                  "not a zip", "no calibration.json", "not a calibration",
                                  "not JSON", "evidence elsewhere", "unsafe evidence"])
def test_an_unsafe_or_invalid_archive_is_a_json_422_naming_the_problem(
        client: Client, caldir: Path, case: str) -> None:
    before = len(client.get(f"{API}/calibrations").json()["items"])
    archive, reason = _bad_archives(caldir)[case]

    response = client.post(f"{API}/calibrations", content=archive, headers=ZIP)

    assert response.status_code == 422, response.text
    assert reason in response.json()["detail"]
    assert len(client.get(f"{API}/calibrations").json()["items"]) == before


@pytest.mark.parametrize("folder", ["", "cal/"], ids=["flat", "in-a-folder"])
def test_a_downloaded_calibration_imports_without_its_evidence(tmp_path: Path, caldir: Path,
                                                               folder: str) -> None:
    # GET /calibrations/{id}/download carries the input bundles under <id>/inputs/.
    members = {**_calibration_members(caldir, folder),
               f"{folder}inputs/cap-1/bundle.json": b"{}",
               f"{folder}inputs/cap-1/S1_000.png": b"not looked at"}
    unpack_calibration_zip(_zip(members), tmp_path, max_unpacked_bytes=10**8)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([ARRAYS_FILE,
                                                                CALIBRATION_FILE])


def _document_with(caldir: Path, change: Callable[[dict[str, Any]], None]) -> bytes:
    document = json.loads((caldir / CALIBRATION_FILE).read_text())
    change(document)
    return json.dumps(document, allow_nan=True).encode()


def _arrays_with(caldir: Path, name: str, value: np.ndarray) -> bytes:
    with np.load(caldir / ARRAYS_FILE) as stored:
        arrays = {key: stored[key] for key in stored.files}
    arrays[name] = value
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return buffer.getvalue()


def _declares_two_gib() -> bytes:
    """An npz whose one member's header declares 2 GiB of float64, with almost no data."""
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<f8", "fortran_order": False,
                                                  "shape": (1 << 28,)})
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("zeros.npy", header.getvalue() + bytes(4096))
    return buffer.getvalue()


def _set(path: str, value: Any) -> Callable[[dict[str, Any]], None]:
    def change(document: dict[str, Any]) -> None:
        *parents, last = path.split(".")
        for key in parents:
            document = document[key]
        document[last] = value
    return change


@pytest.mark.parametrize(("member", "make", "field"), [
    (CALIBRATION_FILE, lambda c: _document_with(c, _set("cameras.S1.dist",
                                                          [math.nan, 0, 0, 0, 0])), "NaN"),
    (CALIBRATION_FILE, lambda c: _document_with(c, _set("cameras.S1.dist", "abc")),
     "cameras.S1.dist"),
    (CALIBRATION_FILE, lambda c: _document_with(c, _set("cameras.S2.K",
                                                          [[1e308, 0, 320], [0, 1e308, 256],
                                                           [0, 0, 1]])), "cameras.S2.K"),
    (CALIBRATION_FILE, lambda c: _document_with(c, _set("cameras.S2.K",
                                                          [[-2500, 0, 320], [0, 2500, 256],
                                                           [0, 0, 1]])), "cameras.S2.K"),
    (CALIBRATION_FILE, lambda c: _document_with(c, _set("cameras.S3.R",
                                                          [[1, 0.5, 0], [0, 1, 0], [0, 0, 1]])),
     "cameras.S3.R"),
    (CALIBRATION_FILE, lambda c: _document_with(c, _set("quality.reprojection_median_px",
                                                          math.inf)), "Infinity"),
    (CALIBRATION_FILE, lambda c: _document_with(
        c, _set("phase_to_height.cameras.S4.carrier_cycles_per_px", [0.04])),
     "phase_to_height.cameras.S4.carrier_cycles_per_px"),
    (CALIBRATION_FILE, lambda c: b"[" * 100_000 + b"]" * 100_000, "nested too deep"),
    (ARRAYS_FILE, lambda c: _arrays_with(c, "reference_phase_S1", np.zeros((10, 10))),
     "reference_phase_S1"),
    (ARRAYS_FILE, lambda c: _arrays_with(c, "reference_phase_S2",
                                         np.full((512, 640), np.nan)), "reference_phase_S2"),
    (ARRAYS_FILE, lambda c: _declares_two_gib(), "zeros.npy"),
], ids=["nan dist", "text dist", "huge K", "negative focal", "sheared R", "infinite quality",
        "short carrier", "deep", "small reference", "nan reference", "2 GiB declared"])
def test_a_calibration_with_an_impossible_number_is_422_naming_the_field(
        client: Client, caldir: Path, member: str, make: Callable[[Path], bytes],
        field: str) -> None:
    # Issue 35: these were accepted (201) and activatable, and using them gave 500.
    before = client.get(f"{API}/calibrations").json()
    members = _calibration_members(caldir)
    members[member] = make(caldir)

    response = client.post(f"{API}/calibrations", content=_zip(members), headers=ZIP)

    assert response.status_code == 422, response.text
    assert field in response.json()["detail"]
    assert "/tmp" not in response.json()["detail"]  # no server path in the answer
    assert client.get(f"{API}/calibrations").json() == before


def test_a_calibration_of_another_rig_is_refused(client: Client, caldir: Path) -> None:
    members = _calibration_members(caldir)
    document = json.loads(members[CALIBRATION_FILE])
    document["rig"]["cameras"][0]["width"] += 2
    members[CALIBRATION_FILE] = json.dumps(document).encode()

    response = client.post(f"{API}/calibrations", content=_zip(members), headers=ZIP)

    assert response.status_code == 422
    assert "made for another rig" in response.json()["detail"]


def test_an_upload_that_is_not_a_zip_body_is_415(client: Client, caldir: Path) -> None:
    response = client.post(f"{API}/calibrations", content=b"{}",
                           headers={"content-type": "application/json"})

    assert response.status_code == 415


def test_an_archive_that_unpacks_too_large_is_refused(tmp_path: Path) -> None:
    archive = _zip({CALIBRATION_FILE: b"0" * 10_000})

    with pytest.raises(UploadTooLargeError):
        unpack_calibration_zip(archive, tmp_path, max_unpacked_bytes=1000)


def test_activation_needs_an_idle_daemon_and_a_known_id(client: Client, app: FastAPI,
                                                        imported_id: str) -> None:
    calibration_id = imported_id
    service = app.state.service
    assert isinstance(service, Service)

    with service.operation("capturing"):
        busy = client.post(f"{API}/calibrations/{calibration_id}/activate")
    unknown = client.post(f"{API}/calibrations/cal-20000101T000000000Z-0000/activate")
    response = client.post(f"{API}/calibrations/{calibration_id}/activate")

    assert busy.status_code == 409 and "capturing" in busy.json()["detail"]
    assert unknown.status_code == 404
    assert response.status_code == 200, response.text
    assert response.json()["active"] is True
    assert client.get(f"{API}/status").json()["active_calibration_id"] == calibration_id
    assert [c["id"] for c in client.get(f"{API}/calibrations").json()["items"]
            if c["active"]] == [calibration_id]


def test_a_fresh_capture_is_reconstructed_stored_and_previewed(
        client: Client, caldir: Path, tmp_path: Path, active_id: str) -> None:
    active = active_id
    capture = client.post(f"{API}/captures", json={"unit": "all"}).json()

    response = client.post(f"{API}/captures/{capture['id']}/reconstruction")

    assert response.status_code == 200, response.text
    summary: dict[str, Any] = response.json()
    assert summary["capture_id"] == capture["id"] and summary["calibration_id"] == active
    assert summary["points"] > 100_000
    assert set(summary["cameras"]) == {"S1", "S2", "S3", "S4"}
    assert all(c["points"] > 0 for c in summary["cameras"].values())

    ply = client.get(f"{API}/captures/{capture['id']}/cloud.ply")
    assert ply.status_code == 200
    (tmp_path / "cloud.ply").write_bytes(ply.content)
    cloud = read_ply(tmp_path / "cloud.ply")
    assert len(cloud) == summary["points"]
    document = json.loads((caldir / CALIBRATION_FILE).read_text())
    z_low, z_high = next(iter(document["phase_to_height"]["cameras"].values()))["z_range_mm"]
    median_z = float(np.median(cloud.points[:, 2]))
    assert z_low < median_z < z_high
    assert np.allclose(cloud.points.min(axis=0), summary["extent_mm"]["min"], atol=1e-3)
    assert np.allclose(cloud.points.max(axis=0), summary["extent_mm"]["max"], atol=1e-3)

    preview = client.get(f"{API}/captures/{capture['id']}/preview.png")
    assert preview.status_code == 200
    assert preview.headers["content-type"] == "image/png"
    image = cv2.imdecode(np.frombuffer(preview.content, np.uint8), cv2.IMREAD_COLOR)
    assert image is not None and max(image.shape[:2]) == 512 and image.shape[2] == 3
    assert (image.reshape(-1, 3).any(axis=1)).mean() > 0.3  # the eye covers most of the map
