"""The audit file: one fsynced JSON line per audited action, append-only, with the caller's
name and role, patient ids hashed; ``GET /api/v1/audit`` for physicists."""

from __future__ import annotations

import io
import itertools
import json
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi import FastAPI

from eyeserver.api import create_app
from eyeserver.calibration.artefact import write_calibration
from eyeserver.service.audit import (
    AUDIT_FILE,
    SALT_FILE,
    AuditTrail,
    hash_patient_id,
    load_salt,
    pseudonymise,
)
from eyeserver.service.core import Service
from eyeserver.service.storage import AuditEntry
from tests.apiclient import API, OPERATOR_TOKEN, Client, auth, serving, test_settings

ZIP = {"content-type": "application/zip"}


def _calibration_zip(service: Service, directory: Path) -> bytes:
    """A minimal calibration of the daemon's own rig (load_calibration accepts it)."""
    camera = {"K": [[20.0, 0.0, 8.0], [0.0, 20.0, 6.0], [0.0, 0.0, 1.0]],
              "dist": [0.0] * 5, "R": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
              "T": [0.0, 0.0, 300.0]}
    document = {"format": "eyeserver.calibration/1", "version": 1,
                "created": "2026-11-23T10:00:00Z", "rig": service.rig.spec(),
                "cameras": {c.id: {"width": c.width, "height": c.height, **camera}
                            for c in service.rig.cameras},
                "quality": {}}
    write_calibration(directory, document, {})
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for path in sorted(directory.iterdir()):
            archive.write(path, path.name)
    return buffer.getvalue()


def _lines(path: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines()]


@pytest.fixture
def app(tmp_path: Path) -> FastAPI:
    return create_app(test_settings(tmp_path / "data"))


@pytest.fixture
def client(app: FastAPI) -> Iterator[Client]:
    with serving(app) as running:
        yield running


@pytest.fixture
def service(app: FastAPI, client: Client) -> Service:
    running = app.state.service
    assert isinstance(running, Service)
    return running


@pytest.mark.slow
def test_import_activation_and_deletion_are_audited_with_the_callers_name(
        client: Client, service: Service, tmp_path: Path) -> None:
    audit_file = tmp_path / "data" / AUDIT_FILE
    archive = _calibration_zip(service, tmp_path / "cal")
    seen: list[bytes] = [audit_file.read_bytes()]

    imported = client.post(f"{API}/calibrations", content=archive, headers=ZIP)
    assert imported.status_code == 201, imported.text
    calibration_id = imported.json()["id"]
    seen.append(audit_file.read_bytes())
    activated = client.post(f"{API}/calibrations/{calibration_id}/activate")
    assert activated.status_code == 200, activated.text
    seen.append(audit_file.read_bytes())
    capture = client.post(f"{API}/captures", json={"unit": "all"},
                          headers=auth(OPERATOR_TOKEN))
    assert capture.status_code == 201, capture.text
    capture_id = capture.json()["id"]
    deleted = client.delete(f"{API}/captures/{capture_id}", params={"reason": "lens cap on"})
    assert deleted.status_code == 204, deleted.text
    seen.append(audit_file.read_bytes())

    # Append-only: every later state of the file starts with the earlier one.
    for earlier, later in itertools.pairwise(seen):
        assert later.startswith(earlier) and len(later) > len(earlier)
    lines = _lines(audit_file)  # every line parses on its own
    by_action = {line["action"]: line for line in lines}
    assert by_action["import_calibration"]["target"] == calibration_id
    assert by_action["activate_calibration"]["target"] == calibration_id
    assert by_action["delete_capture"]["target"] == capture_id
    assert by_action["delete_capture"]["detail"]["reason"] == "lens cap on"
    for action in ("import_calibration", "activate_calibration", "delete_capture"):
        line = by_action[action]
        assert (line["actor"], line["role"], line["outcome"]) == ("physicist", "physicist", "ok")
        assert set(line) == {"time", "seq", "actor", "role", "action", "target", "detail",
                             "outcome"}
    # The same rows as the store's audit table, nothing more and nothing twice.
    stored = [(e.seq, e.actor, e.action, e.target) for e in reversed(service.store.audit_log())]
    assert [(line["seq"], line["actor"], line["action"], line["target"]) for line in lines
            ] == stored

    listed = client.get(f"{API}/audit", params={"limit": 2})
    assert listed.status_code == 200, listed.text
    entries = listed.json()["items"]
    assert [e["action"] for e in entries] == ["delete_capture", "activate_calibration"]
    assert entries[0]["actor"] == "physicist"


def test_device_settings_are_audited_and_failures_too(client: Client, service: Service,
                                                      tmp_path: Path) -> None:
    camera = service.rig.cameras[0].id
    changed = client.request("PATCH", f"{API}/devices/{camera}", json={"gain_db": 3.0})
    assert changed.status_code == 200, changed.text
    missing = "cap-20000101T000000000Z-0000"
    assert client.delete(f"{API}/captures/{missing}",
                         params={"reason": "typo"}).status_code == 404

    lines = _lines(tmp_path / "data" / AUDIT_FILE)
    configured = next(line for line in lines if line["action"] == "configure_device")
    assert configured["target"] == camera and configured["detail"]["setting"] == "gain_db"
    failed = lines[-1]
    assert (failed["action"], failed["target"], failed["outcome"], failed["seq"]) == (
        "delete_capture", missing, "error", None)
    assert missing in failed["detail"]["error"]


def test_only_physicists_read_the_audit(client: Client) -> None:
    assert client.get(f"{API}/audit", headers=auth(OPERATOR_TOKEN)).status_code == 403
    assert client.get(f"{API}/audit", headers={"Authorization": ""}).status_code == 401


def test_a_request_the_role_may_not_make_is_audited_as_denied(client: Client,
                                                             service: Service) -> None:
    denied = client.post(f"{API}/patients/P-SECRET-7/eye-models", json={},
                         headers=auth(OPERATOR_TOKEN))

    assert denied.status_code == 403
    last = _lines(service.audit.path)[-1]
    assert (last["actor"], last["role"], last["action"], last["outcome"]) == (
        "operator", "operator", "denied", "denied")
    assert last["target"] == "POST /api/v1/patients/{patient_id}/eye-models"
    assert last["detail"] == {"needs": "physicist"}
    assert "P-SECRET-7" not in service.audit.path.read_text()
    physicist = client.get(f"{API}/audit").json()
    assert physicist["items"][0]["outcome"] == "denied"


# --- the pieces -----------------------------------------------------------------------------


def test_patient_ids_are_hashed_with_the_installations_salt(tmp_path: Path) -> None:
    salt = load_salt(tmp_path / SALT_FILE)
    assert load_salt(tmp_path / SALT_FILE) == salt  # kept, not drawn again
    assert (tmp_path / SALT_FILE).stat().st_mode & 0o777 == 0o600
    other = b"x" * 32  # another installation's salt

    hashed = hash_patient_id("P-0001", salt)
    assert hashed.startswith("hmac-sha256:") and "P-0001" not in hashed
    assert hashed == hash_patient_id("P-0001", salt) != hash_patient_id("P-0002", salt)
    assert hash_patient_id("P-0001", other) != hashed
    detail = {"patient_id": "P-0001", "session": {"patient_id": "P-0001", "n": 2},
              "list": [{"patient_id": "P-0001"}], "note": "P-0001 is fine here"}
    assert pseudonymise(detail, salt) == {
        "patient_id": hashed, "session": {"patient_id": hashed, "n": 2},
        "list": [{"patient_id": hashed}], "note": "P-0001 is fine here"}


def test_the_file_never_holds_a_patient_id_in_clear(tmp_path: Path) -> None:
    trail = AuditTrail(tmp_path / "audit.jsonl", tmp_path / SALT_FILE)
    trail.open()
    trail.set_roles({"dr.weber": "physicist"})
    try:
        trail.record_stored(AuditEntry(7, "2026-11-23T10:00:00.000Z", "dr.weber",
                                       "start_session", "ses-1", {"patient_id": "P-0042"}))
    finally:
        trail.close()
    text = (tmp_path / "audit.jsonl").read_text()
    assert "P-0042" not in text
    (line,) = _lines(tmp_path / "audit.jsonl")
    assert line["detail"]["patient_id"] == hash_patient_id("P-0042",
                                                           load_salt(tmp_path / SALT_FILE))
    assert (line["seq"], line["role"], line["time"]) == (7, "physicist",
                                                         "2026-11-23T10:00:00.000Z")


def test_a_torn_last_line_is_closed_and_skipped(tmp_path: Path) -> None:
    path = tmp_path / "audit.jsonl"
    path.write_text('{"time": "t", "actor": "a", "action": "x", "target": "y"}\n{"time": "t", "ac')
    before = path.read_bytes()
    trail = AuditTrail(path, tmp_path / SALT_FILE)
    trail.open()
    try:
        trail.record("retention", "delete_capture", "cap-1", {"reason": "old"})
    finally:
        trail.close()
    assert path.read_bytes().startswith(before)
    entries = trail.entries(10)
    assert [e["action"] for e in entries] == ["delete_capture", "x"]
    assert entries[0]["role"] == "system"
