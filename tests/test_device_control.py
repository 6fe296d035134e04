"""``PATCH /api/v1/devices/{id}``: a physicist changes a projector's or a camera's settings.

One app serves the module (the simulated default room); each test sets back what it changed.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from eyeserver.hardware.sim.drivers import SimCamera
from eyeserver.io import read_bundle
from eyeserver.service.core import Service
from tests.apiclient import API, OPERATOR_TOKEN, Client, auth


def _patch(client: Client, device_id: str, body: dict[str, Any], **kwargs: Any) -> Any:
    return client.request("PATCH", f"{API}/devices/{device_id}", json=body, **kwargs)


def _details(client: Client, device_id: str) -> dict[str, Any]:
    response = client.get(f"{API}/devices/{device_id}")
    assert response.status_code == 200
    details: dict[str, Any] = response.json()["details"]
    return details


def test_camera_settings_are_set_read_back_and_audited(client: Client,
                                                       service: Service) -> None:
    response = _patch(client, "S1", {"exposure_us": 8000, "gain_db": 6.5})
    read_back = _details(client, "S1")
    audit = service.store.audit_log(limit=2)
    _patch(client, "S1", {"exposure_us": 10_000, "gain_db": 0})

    assert response.status_code == 200, response.text
    assert response.json()["id"] == "S1"
    assert response.json()["health"] == "ok"
    assert (response.json()["details"]["exposure_us"],
            response.json()["details"]["gain_db"]) == (8000.0, 6.5)
    assert (read_back["exposure_us"], read_back["gain_db"]) == (8000.0, 6.5)
    assert [(e.actor, e.action, e.target, dict(e.detail)) for e in reversed(audit)] == [
        ("physicist", "configure_device", "S1",
         {"setting": "exposure_us", "old": 10_000.0, "new": 8000.0}),
        ("physicist", "configure_device", "S1", {"setting": "gain_db", "old": 0.0, "new": 6.5}),
    ]


def test_projector_settings_are_set_and_read_back(client: Client, service: Service) -> None:
    response = _patch(client, "P2", {"enabled": False, "intensity": 0.25})
    read_back = _details(client, "P2")
    audit = service.store.audit_log(limit=2)
    untouched = _patch(client, "P2", {})  # nothing to change: the device as it is
    _patch(client, "P2", {"enabled": True, "intensity": 1.0})

    assert response.status_code == 200, response.text
    assert (read_back["enabled"], read_back["intensity"]) == (False, 0.25)
    assert {e.detail["setting"]: e.detail["new"] for e in audit} == {"enabled": False,
                                                                      "intensity": 0.25}
    assert untouched.status_code == 200
    assert untouched.json()["details"]["intensity"] == 0.25
    assert _details(client, "P2")["enabled"] is True


def _mean_level(service: Service, capture: Any, camera_id: str) -> float:
    assert capture.status_code == 201, capture.text
    bundle = read_bundle(service.store.get_capture(capture.json()["id"]).path)
    return float(np.asarray(bundle.load_image(bundle.frames[0].index, camera_id)).mean())


def test_a_capture_uses_the_new_settings(client: Client, service: Service) -> None:
    lit = client.post(f"{API}/captures", json={"unit": "right"})
    _patch(client, "P2", {"enabled": False})
    dark = client.post(f"{API}/captures", json={"unit": "right"})
    _patch(client, "P2", {"enabled": True})

    # Without its fringe projector the camera sees only the room's ambient light.
    assert _mean_level(service, dark, "S3") < 0.8 * _mean_level(service, lit, "S3")


@pytest.mark.parametrize(("device_id", "body", "detail"), [
    ("P1", {"exposure_us": 100},
     "P1: exposure_us does not apply to a projector (it takes enabled, intensity)"),
    ("S2", {"enabled": False, "intensity": 0.5},
     "S2: enabled, intensity do not apply to a camera (it takes exposure_us, gain_db)"),
    ("T1", {"gain_db": 1}, "T1: gain_db does not apply to a trigger (it takes none)"),
    ("S1", {"exposure_us": 1}, "S1: exposure_us=1.0 outside [10.0, 40000.0]"),
    ("P1", {"intensity": 1.5}, "P1: intensity=1.5 outside [0.0, 1.0]"),
])
def test_settings_that_do_not_apply_or_are_out_of_range_are_422(
    client: Client, device_id: str, body: dict[str, Any], detail: str
) -> None:
    before = _details(client, device_id)
    response = _patch(client, device_id, body)

    assert response.status_code == 422
    assert response.json() == {"detail": detail}
    assert _details(client, device_id) == before


def test_a_change_is_all_or_nothing(client: Client, service: Service) -> None:
    audited = len(service.store.audit_log(limit=1000))
    response = _patch(client, "S4", {"exposure_us": 9000, "gain_db": 99})

    assert response.status_code == 422
    assert response.json() == {"detail": "S4: gain_db=99.0 outside [0.0, 24.0]"}
    assert _details(client, "S4")["exposure_us"] == 10_000.0  # set back
    assert len(service.store.audit_log(limit=1000)) == audited


@pytest.mark.parametrize("body", [{"colour": "red"}, {"intensity": "bright"}, [1, 2]])
def test_a_malformed_body_is_422(client: Client, body: Any) -> None:
    response = _patch(client, "P1", body)

    assert response.status_code == 422
    assert "detail" in response.json()


def test_an_operator_may_not_change_settings(client: Client) -> None:
    response = _patch(client, "S1", {"gain_db": 3}, headers=auth(OPERATOR_TOKEN))

    assert response.status_code == 403
    assert response.json() == {
        "detail": "operator (operator) may not do this: it needs the physicist role"}
    assert _details(client, "S1")["gain_db"] == 0.0


def test_an_unknown_device_is_404(client: Client) -> None:
    response = _patch(client, "S9", {"gain_db": 3})

    assert response.status_code == 404
    assert response.json() == {"detail": "no device with id 'S9'"}


def test_a_failing_device_answers_503_and_faults_until_it_comes_back(
    client: Client, service: Service
) -> None:
    camera = service.rig.camera("S2")
    assert isinstance(camera, SimCamera)
    camera.inject_fault("disconnect")
    failed = _patch(client, "S2", {"gain_db": 2})
    status = client.get(f"{API}/status").json()
    camera.reconnect()
    recovered = _patch(client, "S2", {"gain_db": 0})  # reopens S2 first

    assert failed.status_code == 503
    assert failed.json() == {"detail": "S2: camera is not responding"}
    # The fault has just come: the background recovery tries S2 again in a second.
    assert failed.headers["Retry-After"] == "1"
    assert status["state"] == "fault"
    assert recovered.status_code == 200, recovered.text
    assert recovered.json()["health"] == "ok"
    assert client.get(f"{API}/status").json()["state"] == "idle"


def test_the_openapi_document_has_the_patch_route(client: Client) -> None:
    document = client.get(f"{API}/openapi.json").json()

    patch = document["paths"]["/api/v1/devices/{device_id}"]["patch"]
    assert {"200", "403", "404", "422", "503"} <= set(patch["responses"])
    body = document["components"]["schemas"]["DeviceSettingsRequest"]
    assert set(body["properties"]) == {"enabled", "intensity", "exposure_us", "gain_db"}
    assert body["additionalProperties"] is False
