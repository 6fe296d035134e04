"""The whole daemon on real drivers (issue 38): Aravis's fake GigE Vision cameras, an emulated
Gardasoft LED controller and an emulated Zaber stage (eyeserver.hardware.emulators.fakeroom),
named by a device room file; a capture through the API stores the fake cameras' images with the
controllers' settings applied.

Needs Aravis's fake camera and PyGObject (scripts/system-packages.sh, the genicam extra) and
root, to give the second fake camera its loopback address; skipped, saying which, without them.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from fastapi import FastAPI

from eyeserver.api.app import create_app
from eyeserver.errors import FormatError
from eyeserver.hardware.devices import load_device_room
from eyeserver.hardware.emulators.fakegv import find_fake_camera_program
from eyeserver.hardware.emulators.fakeroom import FakeRoom
from eyeserver.service.core import Service
from tests.apiclient import API, Client, serving, test_settings

try:
    import gi  # noqa: F401
    _GI = True
except ImportError:
    _GI = False

needs_fake_room = pytest.mark.skipif(
    find_fake_camera_program() is None or not _GI or os.geteuid() != 0,
    reason="the fake room needs aravis-tools and PyGObject (scripts/system-packages.sh, the "
           "genicam extra) and root (the second camera's loopback address)")


@pytest.fixture(scope="module")
def fake_room(tmp_path_factory: pytest.TempPathFactory) -> Iterator[FakeRoom]:
    with FakeRoom(tmp_path_factory.mktemp("fake-room")) as room:
        yield room


@pytest.fixture(scope="module")
def daemon(fake_room: FakeRoom, tmp_path_factory: pytest.TempPathFactory,
           ) -> Iterator[tuple[FastAPI, Client]]:
    settings = test_settings(tmp_path_factory.mktemp("fake-room-data") / "data",
                             room="devices", room_file=fake_room.room_file)
    app = create_app(settings)
    with serving(app) as client:
        yield app, client


@needs_fake_room
@pytest.mark.slow
def test_a_capture_on_the_fake_room_stores_the_fake_cameras_images(
        daemon: tuple[FastAPI, Client], fake_room: FakeRoom) -> None:
    app, client = daemon
    service = app.state.service
    assert isinstance(service, Service) and service.simulation is None

    status = client.get(f"{API}/status").json()
    assert status["state"] == "idle", status
    assert {d["id"]: d["health"] for d in status["devices"]} == {
        "P1": "ok", "S1": "ok", "S2": "ok", "T1": "ok"}, status
    response = client.post(f"{API}/captures", json={"unit": "all"})
    assert response.status_code == 201, response.text
    capture_id = response.json()["id"]

    directory = service.store.capture_path(capture_id)
    document: dict[str, Any] = json.loads((directory / "bundle.json").read_text())
    assert [c["id"] for c in document["rig"]["cameras"]] == ["S1", "S2"]
    images = document["frames"][0]["images"]
    assert set(images) == {"S1", "S2"}
    for camera_id, name in images.items():
        image = cv2.imread(str(directory / name), cv2.IMREAD_UNCHANGED)
        assert image is not None and image.shape == (512, 640) and image.dtype == np.uint8
        # The fake's diagonal ramp: each pixel one more than its left neighbour (mod 255),
        # whatever its frame id, scaled by exposure and gain (exactly 1 at 10 ms and 0 dB).
        assert np.array_equal((image[:, 1:].astype(int) - image[:, :-1]) % 255,
                              np.ones((512, 639), int)), camera_id

    # The LED controller got the projector's settings: a strobed pulse at full current.
    assert fake_room.led is not None
    channel = fake_room.led.channels[1]
    assert (channel.mode, channel.current_a, channel.pulse_us, channel.delay_us) == \
        ("pulse", 1.0, 8000.0, 10.0)
    devices = {d["id"]: d for d in client.get(f"{API}/devices").json()}
    assert devices["S1"]["driver"] == "GenicamCamera"
    assert devices["P1"]["driver"] == "GardasoftProjector"


@needs_fake_room
@pytest.mark.slow
def test_the_stage_of_the_fake_room_moves_the_plate(daemon: tuple[FastAPI, Client],
                                                   fake_room: FakeRoom) -> None:
    app, _ = daemon
    stage = app.state.service.stage
    assert stage is not None and stage.is_open
    stage.move_to(5.0)
    assert fake_room.stage is not None
    assert fake_room.stage.axis().position == round((5.0 + 15.0) / 0.000047625)


def test_a_device_room_file_names_the_file_and_field_of_a_mistake(tmp_path: Path) -> None:
    room = tmp_path / "room.toml"
    room.write_text('[[devices]]\nkind = "camera"\nid = "S1"\ndriver = "GenicamCamera"\n'
                    'options = { address = "10.0.0.2" }\n\n[trigger]\nid = "T1"\n'
                    'driver = "GenicamTrigger"\n\n[[units]]\nid = "left"\nprojector = "P1"\n'
                    'cameras = ["S1"]\n')
    with pytest.raises(FormatError, match=r"room\.toml.*unit 'left' names projector 'P1'"):
        load_device_room(room)
    room.write_text(room.read_text().replace('id = "T1"', 'id = "T1"\nrate = 25'))
    with pytest.raises(FormatError, match=r"room\.toml: field 'trigger\.rate': unknown key"):
        load_device_room(room)
    # The stage's id is a device id like the others: unique across the room.
    room.write_text(room.read_text().replace("rate = 25\n", "")
                    + '\n[[devices]]\nkind = "projector"\nid = "P1"\n'
                      'driver = "GardasoftProjector"\n\n[stage]\nid = "S1"\n'
                      'driver = "ZaberStage"\n')
    with pytest.raises(FormatError, match=r"room\.toml.*duplicate device id\(s\): S1"):
        load_device_room(room)
    room.write_text(room.read_text().replace('[stage]\nid = "S1"', '[stage]\nid = "Z1"'))
    assert load_device_room(room).device_ids() == ["S1", "P1", "T1", "Z1"]
