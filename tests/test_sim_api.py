"""The simulated room through the REST API (``/api/v1/sim/…``): scenes, stage, chessboard, truth,
device cables, the state machine, and a daemon on real hardware that has no simulated room.

One app in the default simulated room serves the module (each new scene renders for a few
seconds on first capture); every test places the scene it needs and leaves the daemon idle.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from anyio.from_thread import start_blocking_portal

from eyeserver.api import create_app
from eyeserver.api.auth import TokenTable
from eyeserver.api.routers.sim import NO_SIM_ROOM
from eyeserver.hardware.sim.drivers import build_sim_rig
from eyeserver.hardware.sim.room import SimRoom
from eyeserver.hardware.sim.scenes import SceneSpec, scene_truth
from eyeserver.io import read_bundle
from eyeserver.service.core import Service
from eyeserver.service.simroom import STAGE_TRAVEL_MM
from tests.apiclient import API, OPERATOR_TOKEN, Client, auth, test_settings

SIM_ROUTES: list[tuple[str, str, dict[str, Any] | None]] = [
    ("GET", "/sim/scene", None),
    ("PUT", "/sim/scene", {"kind": "pyramid"}),
    ("PUT", "/sim/stage", {"z_mm": 0.0}),
    ("PUT", "/sim/chessboard", {"position_mm": [0, 0, 0], "rotation_deg": [0, 0, 0]}),
    ("GET", "/sim/truth", None),
    ("PUT", "/sim/devices/S1", {"connected": True}),
]


def _capture_images(client: Client, data_dir: Path, unit: str) -> dict[str, np.ndarray]:
    response = client.post(f"{API}/captures", json={"unit": unit})
    assert response.status_code == 201, response.text
    bundle = read_bundle(data_dir / "captures" / response.json()["id"])
    frame = bundle.frames[0]
    return {c: np.asarray(bundle.load_image(frame.index, c), dtype=np.float64)
            for c in frame.images}


def test_a_placed_scene_is_read_back(client: Client) -> None:
    spec = {"kind": "pyramid", "position_mm": [1.0, -2.0, -6.0], "rotation_deg": [0.0, 10.0, 5.0]}

    placed = client.put(f"{API}/sim/scene", json=spec, headers=auth(OPERATOR_TOKEN))
    read = client.get(f"{API}/sim/scene", headers=auth(OPERATOR_TOKEN))

    assert placed.status_code == 200, placed.text
    expected = SceneSpec.model_validate(spec).model_dump(mode="json")
    assert placed.json() == expected
    assert read.status_code == 200
    assert read.json() == expected


def test_the_truth_is_the_placed_scenes(client: Client, service: Service) -> None:
    spec = SceneSpec(kind="eye", position_mm=(1.0, 0.5, -9.0), rotation_deg=(0.0, 5.0, 0.0),
                     eye={"gaze_deg": (6.0, -3.0), "globe_radius_mm": 12.4})
    assert client.put(f"{API}/sim/scene", json=spec.model_dump(mode="json")).status_code == 200

    truth = client.get(f"{API}/sim/truth")

    assert truth.status_code == 200
    body = truth.json()
    expected = json.loads(json.dumps(scene_truth(spec)))
    # A still scene's truth does not depend on the time since it was placed.
    assert {k: v for k, v in body.items() if k not in ("t_s", "devices")} == \
        {k: v for k, v in expected.items() if k != "t_s"}
    assert body["t_s"] >= 0
    assert body["eye"]["globe_radius_mm"] == 12.4
    room = service.simulation
    assert isinstance(room, SimRoom)
    assert set(body["devices"]["cameras"]) == set(room.camera_ids())
    assert set(body["devices"]["projectors"]) == set(room.projector_ids())


def test_the_stage_moves_the_plate_and_captures_show_it(client: Client, data_dir: Path) -> None:
    low = client.put(f"{API}/sim/stage", json={"z_mm": -5.0}, headers=auth(OPERATOR_TOKEN))
    low_truth = client.get(f"{API}/sim/truth").json()
    low_images = _capture_images(client, data_dir, "left")
    high = client.put(f"{API}/sim/stage", json={"z_mm": 15.0}, headers=auth(OPERATOR_TOKEN))
    high_truth = client.get(f"{API}/sim/truth").json()
    high_images = _capture_images(client, data_dir, "left")

    assert low.status_code == high.status_code == 200
    assert low.json()["kind"] == "plate"
    assert low.json()["position_mm"] == [0.0, 0.0, -5.0]
    assert (low_truth["scene"]["kind"], low_truth["surfaces"]) == ("plate", ["plate"])
    assert low_truth["scene"]["position_mm"][2] == -5.0
    assert high_truth["scene"]["position_mm"][2] == 15.0
    # 20 mm of depth moves the fringes by many periods: far more than the noise (≈ 1–3 DN).
    for camera_id, image in low_images.items():
        assert np.abs(image - high_images[camera_id]).mean() > 5, camera_id


def test_the_chessboard_is_placed_in_its_pose(client: Client) -> None:
    pose = {"position_mm": [2.0, -1.0, 5.0], "rotation_deg": [20.0, 0.0, 15.0]}

    placed = client.put(f"{API}/sim/chessboard", json=pose, headers=auth(OPERATOR_TOKEN))
    truth = client.get(f"{API}/sim/truth").json()

    assert placed.status_code == 200, placed.text
    assert placed.json() == SceneSpec(kind="chessboard", position_mm=(2.0, -1.0, 5.0),
                                      rotation_deg=(20.0, 0.0, 15.0)).model_dump(mode="json")
    assert truth["surfaces"] == ["chessboard"]
    assert truth["scene"]["rotation_deg"] == [20.0, 0.0, 15.0]


@pytest.mark.parametrize(("path", "body", "reason"), [
    ("/sim/scene", {"kind": "unicorn"}, "kind"),
    ("/sim/scene", {"kind": "eye", "colour": "blue"}, "colour"),
    ("/sim/scene", {"kind": "eye", "eye": {"limbus_diameter_mm": 15.5,
                                           "cornea_radius_mm": 7.0}}, "limbus"),
    ("/sim/scene", {"kind": "chessboard", "cols": 8, "rows": 6}, "odd"),
    ("/sim/stage", {"z_mm": STAGE_TRAVEL_MM[1] + 0.5}, "less than or equal"),
    ("/sim/stage", {"z_mm": STAGE_TRAVEL_MM[0] - 0.5}, "greater than or equal"),
    ("/sim/stage", {"z_mm": 1.0, "speed_mm_s": 2.0}, "speed_mm_s"),
    ("/sim/stage", {}, "z_mm"),
    ("/sim/chessboard", {"position_mm": [0.0, 0.0]}, "position_mm"),
    ("/sim/chessboard", {"square_mm": 4.0}, "square_mm"),
    ("/sim/devices/S1", {"connected": "maybe"}, "connected"),
], ids=["unknown-kind", "extra-field", "limbus-too-wide", "board-unorientable",
        "stage-too-high", "stage-too-low", "stage-extra-field", "stage-no-z", "board-2d",
        "board-extra-field", "cable-not-bool"])
def test_bad_bodies_are_422_with_the_reason(client: Client, path: str, body: dict[str, Any],
                                            reason: str) -> None:
    before = client.get(f"{API}/sim/scene").json()

    response = client.put(f"{API}{path}", json=body)

    assert response.status_code == 422
    assert reason in json.dumps(response.json()["detail"])
    assert client.get(f"{API}/sim/scene").json() == before


def test_scene_changes_wait_for_no_capture_409(client: Client, service: Service) -> None:
    before = client.get(f"{API}/sim/scene").json()
    with service.operation("capturing"):
        answers = [client.put(f"{API}/sim/scene", json={"kind": "wedge"}),
                   client.put(f"{API}/sim/stage", json={"z_mm": 3.0}),
                   client.put(f"{API}/sim/chessboard", json={})]
        read = client.get(f"{API}/sim/scene")
        truth = client.get(f"{API}/sim/truth")

    assert [a.status_code for a in answers] == [409, 409, 409]
    assert all(a.json() == {"detail": "cannot place a scene: the daemon is capturing"}
               for a in answers)
    assert (read.status_code, truth.status_code) == (200, 200)  # reading never conflicts
    assert client.get(f"{API}/sim/scene").json() == before
    assert client.get(f"{API}/status").json()["state"] == "idle"


def test_an_unplugged_camera_faults_its_unit_until_replugged(client: Client) -> None:
    client.put(f"{API}/sim/stage", json={"z_mm": 15.0})  # a scene already rendered

    unplugged = client.put(f"{API}/sim/devices/S1", json={"connected": False})
    failed = client.post(f"{API}/captures", json={"unit": "left"})
    status = client.get(f"{API}/status").json()
    replugged = client.put(f"{API}/sim/devices/S1", json={"connected": True})
    recovered = client.post(f"{API}/captures", json={"unit": "left"})
    after = client.get(f"{API}/status").json()

    assert unplugged.status_code == 200
    assert unplugged.json() == {"id": "S1", "kind": "camera", "connected": False}
    assert failed.status_code == 503
    assert failed.json() == {"detail": "S1: camera is not responding"}
    assert status["state"] == "fault"
    s1 = next(d for d in status["devices"] if d["id"] == "S1")
    assert (s1["health"], s1["reason"]) == ("fault", "camera is not responding")
    assert next(u for u in status["units"] if u["id"] == "left")["health"] == "fault"
    assert replugged.json() == {"id": "S1", "kind": "camera", "connected": True}
    assert recovered.status_code == 201, recovered.text
    assert after["state"] == "idle"
    assert all(d["health"] == "ok" for d in after["devices"])


@pytest.mark.slow
def test_an_unplugged_projector_fails_the_capture_and_recovers_on_replug_alone(
        client: Client) -> None:
    # Issue 35: a dark projector used to give 201 "ok" with fringe-less images.
    client.put(f"{API}/sim/stage", json={"z_mm": 15.0})
    before = client.get(f"{API}/captures").json()["total"]

    unplugged = client.put(f"{API}/sim/devices/P1", json={"connected": False})
    failed = client.post(f"{API}/captures", json={"unit": "left"})
    status = client.get(f"{API}/status").json()
    replugged = client.put(f"{API}/sim/devices/P1", json={"connected": True})
    # Nobody touches the device or captures: the daemon's own recovery reopens it.
    deadline = time.monotonic() + 30.0
    while client.get(f"{API}/status").json()["state"] != "idle" \
            and time.monotonic() < deadline:
        time.sleep(0.1)
    after = client.get(f"{API}/status").json()
    recovered = client.post(f"{API}/captures", json={"unit": "left"})

    assert unplugged.json() == {"id": "P1", "kind": "projector", "connected": False}
    assert failed.status_code == 503
    assert failed.json() == {"detail": "P1: projector is not responding"}
    assert client.get(f"{API}/captures").json()["total"] == before + 1  # the recovered one only
    assert status["state"] == "fault"
    p1 = next(d for d in status["devices"] if d["id"] == "P1")
    assert (p1["health"], p1["reason"]) == ("fault", "projector is not responding")
    assert next(u for u in status["units"] if u["id"] == "left")["health"] == "fault"
    assert replugged.status_code == 200
    assert after["state"] == "idle" and all(d["health"] == "ok" for d in after["devices"])
    assert recovered.status_code == 201, recovered.text


@pytest.mark.parametrize(("path", "body"), [
    ("/sim/scene", {"kind": "eye", "rotation_deg": [0, math.inf, 0]}),
    ("/sim/scene", {"kind": "eye", "position_mm": [0, 0, math.nan]}),
    ("/sim/scene", {"kind": "eye", "position_mm": [1e308, 0, 0]}),
    ("/sim/scene", {"kind": "chessboard", "square_mm": math.inf}),
    ("/sim/scene", {"kind": "eye", "eye": {"gaze_deg": [1e308, 0]}}),
    ("/sim/scene", {"kind": "eye", "eye": {"aperture_mm": [math.inf, 7.5]}}),
    ("/sim/chessboard", {"position_mm": [0, -math.inf, 0]}),
    ("/sim/chessboard", {"rotation_deg": [1e308, 0, 0]}),
    ("/sim/eye", {"gaze_deg": [math.nan, 0]}),
    ("/sim/eye", {"position_mm": [0, 0, 1e308]}),
    ("/sim/eye", {"motion": {"saccade_rate_hz": 1e5}}),
    ("/sim/eye", {"motion": {"drift_deg": math.inf}}),
    ("/sim/eye", {"motion": {"script": [{"t_s": 1e308, "kind": "blink"}]}}),
    ("/sim/eye", {"motion": {"script": [{"t_s": 1, "kind": "shift",
                                         "shift_mm": [math.nan, 0, 0]}]}}),
    ("/sim/scene", {"kind": "eye", "rotation_deg": [0, 0, False]}),
    ("/sim/stage", {"z_mm": False}),
    ("/sim/eye", {"motion": {"script": [{"t_s": 1, "kind": "shift",
                                         "shift_mm": [0, 0, True]}]}}),
])
def test_every_number_of_a_scene_is_finite_and_bounded_422(client: Client, path: str,
                                                             body: dict[str, Any]) -> None:
    # Issue 35: an infinite rotation was accepted (200), then every capture, GET /sim/eye and
    # /sim/truth answered 500 until the scene was replaced.
    client.put(f"{API}/sim/scene", json={"kind": "eye"})
    before = client.get(f"{API}/sim/scene").json()

    refused = client.put(f"{API}{path}", content=json.dumps(body, allow_nan=True),
                         headers={"content-type": "application/json"})

    assert refused.status_code == 422, refused.text
    assert client.get(f"{API}/sim/scene").json() == before
    assert client.get(f"{API}/sim/eye").status_code == 200
    assert client.get(f"{API}/sim/truth").status_code == 200


def test_device_cables_need_a_known_device_and_a_physicist(client: Client) -> None:
    unknown = client.put(f"{API}/sim/devices/S9", json={"connected": False})
    operator = client.put(f"{API}/sim/devices/S1", json={"connected": False},
                          headers=auth(OPERATOR_TOKEN))

    assert unknown.status_code == 404
    assert unknown.json() == {"detail": "no simulated device with id 'S9'"}
    assert operator.status_code == 403
    assert client.get(f"{API}/status").json()["state"] == "idle"


@pytest.mark.parametrize(("method", "path", "body"), SIM_ROUTES)
def test_every_sim_route_needs_a_token(client: Client, method: str, path: str,
                                       body: dict[str, Any] | None) -> None:
    response = client.request(method, f"{API}{path}", json=body, headers={"Authorization": ""})

    assert response.status_code == 401
    assert "token" in response.json()["detail"]


def test_the_sim_routes_are_documented(client: Client) -> None:
    paths = client.get(f"{API}/openapi.json").json()["paths"]

    assert {f"{API}/sim/scene", f"{API}/sim/stage", f"{API}/sim/chessboard", f"{API}/sim/truth",
            f"{API}/sim/devices/{{device_id}}"} <= set(paths)
    stage = paths[f"{API}/sim/stage"]["put"]
    assert {"401", "404", "409", "422"} <= set(stage["responses"])


# --- a daemon on real hardware --------------------------------------------------------------


@pytest.fixture(scope="module")
def real_client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Client]:
    """A daemon whose service drives a rig it did not build from a simulated room.

    (The rig's drivers happen to be simulated ones, but the service was handed the rig as it
    would be a real one, so it knows of no room: what matters here.) The app's state is set up
    by hand instead of by its lifespan, which would build the simulated room.
    """
    settings = test_settings(tmp_path_factory.mktemp("real") / "data")
    app = create_app(settings)
    service = Service(settings, rig=build_sim_rig(SimRoom()))
    with service:
        app.state.tokens = TokenTable.for_settings(settings)
        app.state.service = service
        with start_blocking_portal() as portal, \
                portal.wrap_async_context_manager(httpx.AsyncClient(
                    transport=httpx.ASGITransport(app=app), base_url="http://test")) as http:
            yield Client(portal, http)


@pytest.mark.parametrize(("method", "path", "body"), SIM_ROUTES)
def test_a_daemon_on_real_hardware_answers_404_on_every_sim_route(
    real_client: Client, method: str, path: str, body: dict[str, Any] | None
) -> None:
    response = real_client.request(method, f"{API}{path}", json=body)

    assert response.status_code == 404
    assert response.json() == {"detail": NO_SIM_ROOM}


def test_a_daemon_on_real_hardware_still_serves_its_other_routes(real_client: Client) -> None:
    assert real_client.get(f"{API}/status").json()["state"] == "idle"
