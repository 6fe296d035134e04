"""Patients, eye models and reference poses through the REST API (``/api/v1/patients``).

One app serves the module; nothing here captures (verification: test_pose_verification.py).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import pytest

from eyeserver.api import create_app
from eyeserver.service.audit import SALT_FILE, hash_patient_id, load_salt
from tests.apiclient import API, OPERATOR_TOKEN, Client, auth, serving, test_settings

OPERATOR = auth(OPERATOR_TOKEN)


def _put_patient(client: Client, patient_id: str, **body: Any) -> Any:
    response = client.put(f"{API}/patients/{patient_id}", json={"eye": "right", **body})
    assert response.status_code in (200, 201), response.text
    return response.json()


def test_a_patient_is_created_then_updated(client: Client) -> None:
    created = client.put(f"{API}/patients/P-0001", json={"eye": "left"})
    updated = client.put(f"{API}/patients/P-0001",
                         json={"eye": "left", "tolerance_mm": 0.3, "tolerance_gaze_deg": 1.5,
                               "unit": "right"})
    read = client.get(f"{API}/patients/P-0001", headers=OPERATOR)

    assert created.status_code == 201, created.text
    assert created.json()["tolerance_mm"] == 0.2  # the defaults
    assert created.json()["tolerance_gaze_deg"] == 1.0
    assert created.json()["unit"] == "all"
    assert created.json()["eye_model_version"] is None
    assert updated.status_code == 200
    assert read.status_code == 200
    body = read.json()
    assert (body["eye"], body["unit"], body["tolerance_mm"], body["tolerance_gaze_deg"]) == \
        ("left", "right", 0.3, 1.5)
    assert body["key"] == created.json()["key"]
    assert body["key"].startswith("pat-")


def test_changing_patients_needs_a_physicist(client: Client) -> None:
    _put_patient(client, "P-0002")

    responses = [
        client.put(f"{API}/patients/P-0002", json={"eye": "right"}, headers=OPERATOR),
        client.post(f"{API}/patients/P-0002/eye-models", json={}, headers=OPERATOR),
        client.put(f"{API}/patients/P-0002/fractions/1/reference",
                   json={"centre_mm": [0, 0, -10], "gaze": [0, 0, 1]}, headers=OPERATOR),
    ]
    # The therapist at set-up captures the reference: an operator may (here no calibration is
    # active, so the daemon says that instead of 403).
    captured = client.post(f"{API}/patients/P-0002/fractions/1/reference/capture",
                           headers=OPERATOR)

    assert [r.status_code for r in responses] == [403] * 3
    assert captured.status_code == 409 and "no calibration is active" in captured.json()["detail"]
    assert client.get(f"{API}/patients/P-0002", headers={"Authorization": ""}).status_code == 401


@pytest.mark.parametrize(("path", "body"), [
    ("/patients/P-0003", {"eye": "middle"}),
    ("/patients/P-0003", {"eye": "right", "tolerance_mm": 0}),
    ("/patients/P-0003", {"eye": "right", "unit": "nowhere"}),
    ("/patients/P-0003", {"eye": "right", "colour": "blue"}),
    ("/patients/has%20space", {"eye": "right"}),
    ("/patients/" + "x" * 129, {"eye": "right"}),
])
def test_bad_patients_are_422(client: Client, path: str, body: dict[str, Any]) -> None:
    response = client.put(f"{API}{path}", json=body)

    assert response.status_code == 422, response.text
    assert client.get(f"{API}/patients/P-0003").status_code == 404


def test_an_unknown_patient_is_404_everywhere(client: Client) -> None:
    responses = [
        client.get(f"{API}/patients/P-nobody"),
        client.get(f"{API}/patients/P-nobody/eye-models"),
        client.post(f"{API}/patients/P-nobody/eye-models", json={}),
        client.put(f"{API}/patients/P-nobody/fractions/1/reference",
                   json={"centre_mm": [0, 0, -10], "gaze": [0, 0, 1]}),
        client.get(f"{API}/patients/P-nobody/fractions/1/reference"),
    ]

    assert [r.status_code for r in responses] == [404] * 5
    assert "no patient" in responses[0].json()["detail"]
    assert "P-nobody" not in responses[0].json()["detail"]  # it may reach the audit file


def test_eye_models_are_versioned_and_the_newest_is_used(client: Client) -> None:
    _put_patient(client, "P-0004")
    ellipsoid = {"ellipsoid": {"centre_mm": [1.0, 2.0, 3.0], "semi_axes_mm": [12.1, 11.9, 12.4],
                               "orientation": [[0, -1, 0], [1, 0, 0], [0, 0, 1]]},
                 "cornea_radius_mm": 7.6, "limbus_diameter_mm": 11.5, "source": "MRI 2026-11-02"}

    first = client.post(f"{API}/patients/P-0004/eye-models", json={})
    second = client.post(f"{API}/patients/P-0004/eye-models", json=ellipsoid)
    third = client.post(f"{API}/patients/P-0004/eye-models", json={"globe_radius_mm": 12.3})
    listed = client.get(f"{API}/patients/P-0004/eye-models", headers=OPERATOR)
    one = client.get(f"{API}/patients/P-0004/eye-models/2", headers=OPERATOR)
    missing = client.get(f"{API}/patients/P-0004/eye-models/9")
    patient = client.get(f"{API}/patients/P-0004").json()

    assert [r.status_code for r in (first, second, third)] == [201] * 3
    assert [first.json()["version"], second.json()["version"], third.json()["version"]] == \
        [1, 2, 3]
    assert first.json()["population"] is True
    assert first.json()["model"]["cornea_radius_mm"] == 7.8  # population defaults
    assert second.json()["population"] is False
    assert [m["version"] for m in listed.json()["items"]] == [1, 2, 3]
    assert one.json()["model"]["ellipsoid"]["semi_axes_mm"] == [12.1, 11.9, 12.4]
    assert one.json()["model"]["source"] == "MRI 2026-11-02"
    assert one.json()["actor"] == "physicist"
    assert missing.status_code == 404
    assert patient["eye_model_version"] == 3


@pytest.mark.parametrize("model", [
    {"globe_radius_mm": 12.0, "ellipsoid": {"semi_axes_mm": [12, 12, 12]}},
    {"limbus_diameter_mm": 15.9, "cornea_radius_mm": 7.0},
    {"ellipsoid": {"semi_axes_mm": [12, 12, 12], "orientation": [[1, 0, 0], [0, 1, 0],
                                                                 [0, 0, -1]]}},
    {"ellipsoid": {"semi_axes_mm": [12, 12, 12], "orientation": [[1, 0.2, 0], [0, 1, 0],
                                                                 [0, 0, 1]]}},
    {"ellipsoid": {"semi_axes_mm": [12, 12, 40]}},
    {"globe_radius_mm": 3},
    {"globe_sd_mm": 0.1},  # the error of no given globe
    {"globe_radius_mm": 12.0, "globe_sd_mm": -0.1},
    {"shape": "banana"},
])
def test_impossible_eye_models_are_422(client: Client, model: dict[str, Any]) -> None:
    _put_patient(client, "P-0005")

    response = client.post(f"{API}/patients/P-0005/eye-models", json=model)

    assert response.status_code == 422, response.text
    assert client.get(f"{API}/patients/P-0005").json()["eye_model_version"] is None


def test_reference_poses_are_versioned_per_fraction(client: Client) -> None:
    _put_patient(client, "P-0006")
    before = client.get(f"{API}/patients/P-0006/fractions/1/reference")

    first = client.put(f"{API}/patients/P-0006/fractions/1/reference",
                       json={"centre_mm": [0.5, -0.2, -10.0], "gaze": [0, 0, 2],
                             "plan": "plan 4 v2"})
    second = client.put(f"{API}/patients/P-0006/fractions/1/reference",
                        json={"centre_mm": [0.6, -0.2, -10.0], "gaze": [0, 0.1, 1],
                              "limbus_centre_mm": [0.6, 0.9, 0.9]})
    other = client.put(f"{API}/patients/P-0006/fractions/2/reference",
                       json={"centre_mm": [0, 0, -9.0], "gaze": [0, 0, 1]})
    current = client.get(f"{API}/patients/P-0006/fractions/1/reference", headers=OPERATOR)
    versions = client.get(f"{API}/patients/P-0006/fractions/1/references")

    assert before.status_code == 404
    assert "fraction 1 has no reference" in before.json()["detail"]
    assert [r.status_code for r in (first, second, other)] == [201] * 3
    assert first.json()["pose"]["gaze"] == [0.0, 0.0, 1.0]  # normalised
    assert first.json()["plan"] == "plan 4 v2"
    assert (first.json()["source"], first.json()["evidence"]) == ("plan", None)
    assert current.json()["version"] == 2
    assert current.json()["pose"]["centre_mm"] == [0.6, -0.2, -10.0]
    assert current.json()["pose"]["limbus_centre_mm"] == [0.6, 0.9, 0.9]
    assert [r["version"] for r in versions.json()["items"]] == [1, 2]
    assert other.json()["version"] == 1


@pytest.mark.parametrize("body", [
    {"centre_mm": [0, 0, -10], "gaze": [0, 0, 0]},
    {"centre_mm": [0, 0], "gaze": [0, 0, 1]},
    {"centre_mm": [0, 0, -10]},
])
def test_bad_reference_poses_are_422(client: Client, body: dict[str, Any]) -> None:
    _put_patient(client, "P-0007")

    response = client.put(f"{API}/patients/P-0007/fractions/1/reference", json=body)
    zero = client.put(f"{API}/patients/P-0007/fractions/0/reference",
                      json={"centre_mm": [0, 0, -10], "gaze": [0, 0, 1]})

    assert response.status_code == 422
    assert zero.status_code == 422


def test_the_audit_file_holds_patient_ids_only_hashed(client: Client, data_dir: Path) -> None:
    _put_patient(client, "P-SECRET-42")
    client.post(f"{API}/patients/P-SECRET-42/eye-models", json={})
    client.put(f"{API}/patients/P-SECRET-42/fractions/3/reference",
               json={"centre_mm": [0, 0, -10], "gaze": [0, 0, 1]})

    text = (data_dir / "audit.jsonl").read_text()
    expected = hash_patient_id("P-SECRET-42", load_salt(data_dir / SALT_FILE))
    lines = [json.loads(line) for line in text.splitlines()]
    mine = [line for line in lines if line["detail"].get("patient_id") == expected]

    assert "P-SECRET-42" not in text
    assert [line["action"] for line in mine] == ["create_patient", "add_eye_model",
                                                 "set_reference_pose"]
    assert all(line["target"].startswith("pat-") for line in mine)
    assert all(line["actor"] == "physicist" for line in mine)


def test_patients_survive_a_restart(data_dir: Path, client: Client) -> None:
    _put_patient(client, "P-0008", tolerance_mm=0.25)
    client.post(f"{API}/patients/P-0008/eye-models", json={"globe_radius_mm": 12.5})
    client.put(f"{API}/patients/P-0008/fractions/1/reference",
               json={"centre_mm": [0, 0, -10], "gaze": [0, 0, 1]})
    copy = data_dir.parent / "copy"
    # A second daemon cannot open a store that is open: restart on a copy of the directory.
    shutil.copytree(data_dir, copy, ignore=shutil.ignore_patterns("store.lock"))

    with serving(create_app(test_settings(copy))) as again:
        patient = again.get(f"{API}/patients/P-0008").json()
        model = again.get(f"{API}/patients/P-0008/eye-models/1").json()
        reference = again.get(f"{API}/patients/P-0008/fractions/1/reference").json()

    assert patient["tolerance_mm"] == 0.25
    assert patient["eye_model_version"] == 1
    assert model["model"]["globe_radius_mm"] == 12.5
    assert reference["pose"]["centre_mm"] == [0.0, 0.0, -10.0]
    assert list((copy / "patients" / patient["key"]).glob("*.json"))


def test_the_routes_are_documented(client: Client) -> None:
    paths = client.get(f"{API}/openapi.json").json()["paths"]

    assert {f"{API}/patients/{{patient_id}}", f"{API}/patients/{{patient_id}}/eye-models",
            f"{API}/patients/{{patient_id}}/eye-models/{{version}}",
            f"{API}/patients/{{patient_id}}/fractions/{{fraction}}/reference",
            f"{API}/patients/{{patient_id}}/fractions/{{fraction}}/reference/capture",
            f"{API}/pose/measure", f"{API}/pose/measurements",
            f"{API}/pose/measurements/{{measurement_id}}", f"{API}/sim/eye"} <= set(paths)


@pytest.mark.parametrize(("path", "body"), [
    ("/patients/P-BOOL", {"eye": "left", "min_confidence": False}),
    ("/patients/P-BOOL/fractions/1/reference",
     {"centre_mm": [0, 0, -10], "gaze": [0, 0, 1], "limbus_centre_mm": [0, 0, False]}),
])
def test_a_boolean_is_no_number_422(client: Client, path: str, body: dict[str, Any]) -> None:
    # The API fuzz (issue 35): pydantic read false as 0 and stored it.
    client.put(f"{API}/patients/P-BOOL", json={"eye": "left"})

    refused = client.put(f"{API}{path}", json=body)

    assert refused.status_code == 422, refused.text
    assert "a number is needed, not true or false" in refused.json()["detail"]
