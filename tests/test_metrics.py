"""``GET /metrics``: the Prometheus text format, parsed back with prometheus_client's parser."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from fastapi import FastAPI
from prometheus_client.parser import text_string_to_metric_families

from eyeserver.api import create_app
from eyeserver.service.core import Service
from tests.apiclient import API, OPERATOR_TOKEN, Client, auth, serving, test_settings

Samples = dict[tuple[str, tuple[tuple[str, str], ...]], float]


@pytest.fixture
def app(tmp_path_factory: pytest.TempPathFactory) -> FastAPI:
    return create_app(test_settings(tmp_path_factory.mktemp("metrics") / "data"))


@pytest.fixture
def client(app: FastAPI) -> Iterator[Client]:
    with serving(app) as running:
        yield running


def _scrape(client: Client) -> tuple[dict[str, str], Samples]:
    response = client.get("/metrics", headers=auth(OPERATOR_TOKEN))
    assert response.status_code == 200, response.text
    assert response.headers["content-type"].startswith("text/plain; version=0.0.4")
    types: dict[str, str] = {}
    samples: Samples = {}
    for family in text_string_to_metric_families(response.text):
        types[family.name] = family.type
        for sample in family.samples:
            key = (sample.name, tuple(sorted(sample.labels.items())))
            assert key not in samples, f"{key} twice"
            samples[key] = sample.value
    return types, samples


def test_metrics_need_a_token_and_live_outside_the_api_prefix(client: Client) -> None:
    assert client.get("/metrics", headers={"Authorization": ""}).status_code == 401
    assert client.get(f"{API}/metrics").status_code == 404
    assert client.get("/metrics", headers=auth(OPERATOR_TOKEN)).status_code == 200


def test_a_fresh_daemon_lists_every_device_camera_and_queue(client: Client,
                                                            service: Service) -> None:
    types, samples = _scrape(client)

    assert types["eyeserver_frames_acquired"] == "counter"
    assert types["eyeserver_reconstruction_seconds"] == "histogram"
    assert samples[("eyeserver_state", (("state", "idle"),))] == 1
    assert samples[("eyeserver_state", (("state", "fault"),))] == 0
    for device in service.rig.devices:
        up = [v for (name, labels), v in samples.items()
              if name == "eyeserver_device_up" and ("device", device.id) in labels]
        assert up == [1]
    for camera in service.rig.cameras:
        assert samples[("eyeserver_frames_acquired_total", (("camera", camera.id),))] == 0
        assert samples[("eyeserver_frames_dropped_total", (("camera", camera.id),))] == 0
    for queue in ("acquisition", "reconstruction"):
        assert samples[("eyeserver_queue_waiting", (("queue", queue),))] == 0
        assert samples[("eyeserver_queue_capacity", (("queue", queue),))] > 0
    assert samples[("eyeserver_events_dropped_total", ())] == 0
    assert samples[("eyeserver_event_subscribers", ())] == 0
    assert samples[("eyeserver_reconstruction_seconds_count", ())] == 0
    # Live tracking is listed before its first session: nothing watches the eye, so held.
    assert samples[("eyeserver_tracking_running", ())] == 0
    assert samples[("eyeserver_tracking_beam_hold", ())] == 1
    for outcome in ("acquired", "processed", "dropped", "missed", "held"):
        assert samples[("eyeserver_tracking_frames_total", (("outcome", outcome),))] == 0
    assert samples[("eyeserver_tracking_stalls_total", ())] == 0
    assert types["eyeserver_tracking_latency_seconds"] == "histogram"
    assert samples[("eyeserver_tracking_latency_seconds_count", ())] == 0


@pytest.mark.slow
def test_a_calibration_sessions_frames_are_counted(client: Client, service: Service) -> None:
    service.hold_session("s-metrics")
    try:
        service.acquire_for_session("s-metrics", lit=True)
        service.acquire_for_session("s-metrics", lit=False)
    finally:
        service.release_session("s-metrics")

    _, samples = _scrape(client)

    for camera in service.rig.cameras:  # one lit frame, one under the room lights
        assert samples[("eyeserver_frames_acquired_total", (("camera", camera.id),))] == 2


@pytest.mark.slow
def test_captures_reconstructions_and_faults_are_counted(client: Client,
                                                         service: Service) -> None:
    unit = service.rig.units[0]
    assert client.post(f"{API}/captures", json={"unit": unit.id}).status_code == 201
    assert client.post(f"{API}/captures", json={"unit": "all"}).status_code == 201
    service.metrics.reconstruction_done(0.7)  # a real one needs a calibration; timing is all

    _, samples = _scrape(client)

    assert samples[("eyeserver_captures_total", (("unit", unit.id),))] == 1
    assert samples[("eyeserver_captures_total", (("unit", "all"),))] == 1
    for camera in service.rig.cameras:
        # A camera is exposed on its own unit's pulse: once per capture of its unit.
        expected = 2 if camera in unit.cameras else 1
        assert samples[("eyeserver_frames_acquired_total", (("camera", camera.id),))] == (
            expected)
    assert samples[("eyeserver_reconstruction_seconds_count", ())] == 1
    assert samples[("eyeserver_reconstruction_seconds_bucket", (("le", "0.5"),))] == 0
    assert samples[("eyeserver_reconstruction_seconds_bucket", (("le", "1.0"),))] == 1

    camera = unit.cameras[0].id
    unplugged = client.put(f"{API}/sim/devices/{camera}", json={"connected": False})
    assert unplugged.status_code == 200, unplugged.text
    assert client.post(f"{API}/captures", json={"unit": unit.id}).status_code >= 500

    _, samples = _scrape(client)
    assert samples[("eyeserver_state", (("state", "fault"),))] == 1
    (up,) = [v for (name, labels), v in samples.items()
             if name == "eyeserver_device_up" and ("device", camera) in labels]
    assert up == 0
