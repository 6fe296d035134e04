"""Guided phase-to-height calibration through the API with the plate on a Zaber stage: the
daemon moves the room's stage device (:class:`~eyeserver.hardware.drivers.zaber.ZaberStage`
over the Zaber ASCII emulator on a pty) in place of the simulated stage.

The room is the simulated one with its stage swapped for the Zaber driver, and the emulated
stage carries the simulated plate: whenever its axis stands still, the simulated room's plate is
put where the axis is (``zero_mm + position × microstep_mm``). So the plate is where the driver
really drove the stage, not where the daemon asked for it, and a wrong conversion, a move that
never settled or the simulated stage used instead would show in the plate's height and in the
calibration's residual.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi import FastAPI

from eyeserver.api.app import create_app
from eyeserver.hardware.drivers.zaber import ZaberStage
from eyeserver.hardware.emulators.zaber import ZaberEmulator
from eyeserver.hardware.registry import DriverContext
from eyeserver.hardware.room import RoomHardware
from eyeserver.hardware.sim.hardware import simulated_room
from eyeserver.hardware.sim.room import SimRoom
from eyeserver.hardware.sim.scenes import SceneSpec
from eyeserver.service.core import Service
from tests.apiclient import API, Client, serving, test_settings

MICROSTEP_MM = 0.000047625
"""A Zaber X-LSM's travel per microstep, mm."""
ZERO_MM = -15.0
"""The plate's Z at stage position 0, mm: the stage's travel is −15 … +30 mm."""
PLATE_HEIGHTS = [round(-10.0 + 35.0 * n / 26, 3) for n in range(27)]
"""−10 … +25 mm in 27 planes, 1.35 mm apart: the session asks for no gap over 1.4 mm."""
REFERENCE_Z = 10.0


class PlateCarryingZaber(ZaberEmulator):
    """The Zaber emulator whose axis carries the simulated room's plate."""

    def __init__(self, **options: Any) -> None:
        super().__init__(**options)
        self.room: SimRoom | None = None
        self.placed_mm: list[float] = []

    def reply(self, command: str) -> bytes | None:
        answer = super().reply(command)
        axis = self.axis()
        axis.update(time.monotonic())
        if self.room is not None and not axis.busy:
            z_mm = ZERO_MM + axis.position * MICROSTEP_MM
            if not self.placed_mm or self.placed_mm[-1] != z_mm:
                self.room.set_scene(SceneSpec(kind="plate", position_mm=(0.0, 0.0, z_mm)))
                self.placed_mm.append(z_mm)
        return answer


@pytest.fixture
def stage(tmp_path: Path) -> Iterator[PlateCarryingZaber]:
    with PlateCarryingZaber(homed=True, link_dir=tmp_path, name="stage") as emulator:
        axis = emulator.axis()
        axis.limit_max = round(45.0 / MICROSTEP_MM)
        axis.speed = 2_000_000.0  # 95 mm/s: BUSY for a few polls on a 2 mm step
        yield emulator


@pytest.fixture
def daemon(stage: PlateCarryingZaber, tmp_path: Path,
           monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[FastAPI, Client]]:
    def room_with_a_zaber_stage(name: str, room_file: Path | None) -> RoomHardware:
        hardware = simulated_room(room_file)
        assert isinstance(hardware.simulation, SimRoom)
        stage.room = hardware.simulation
        zaber = ZaberStage("Z1", context=DriverContext(), port=stage.port,
                           microstep_mm=MICROSTEP_MM, zero_mm=ZERO_MM, poll_interval_s=0.005,
                           settle_timeout_s=5.0)
        return dataclasses.replace(hardware, stage=zaber)

    monkeypatch.setattr("eyeserver.service.core.room_hardware", room_with_a_zaber_stage)
    app = create_app(test_settings(tmp_path / "data"))
    with serving(app) as client:
        yield app, client


def _ok(response: Any, status: int = 200) -> Any:
    assert response.status_code == status, response.text
    return response.json()


def _wait_job(client: Client, job_id: str, timeout_s: float = 300) -> dict[str, Any]:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        job: dict[str, Any] = _ok(client.get(f"{API}/jobs/{job_id}"))
        if job["state"] in ("succeeded", "failed", "cancelled"):
            return job
        time.sleep(0.2)
    raise AssertionError(f"job {job_id} did not finish in {timeout_s} s")


@pytest.mark.slow
def test_guided_phase_to_height_on_the_zaber_stage(
        daemon: tuple[FastAPI, Client], stage: PlateCarryingZaber,
        calibrated_rooms: Any) -> None:
    app, client = daemon
    service = app.state.service
    assert isinstance(service, Service) and isinstance(service.stage, ZaberStage)
    _, caldir = calibrated_rooms("default")
    parent = service.store.import_calibration(caldir, actor="physicist")

    session = _ok(client.post(f"{API}/calibration-sessions",
                              json={"kind": "phase-height", "calibration_id": parent.id}), 201)
    pid = session["id"]
    for z_mm in PLATE_HEIGHTS:
        step = _ok(client.post(f"{API}/calibration-sessions/{pid}/plates",
                               json={"z_mm": z_mm, "move_stage": True}), 201)
        assert step["moved_by_stage"]
        # The stage went there over its serial line, and the plate with it.
        target = round((z_mm - ZERO_MM) / MICROSTEP_MM)
        assert f"/1 1 move abs {target}" in stage.received
        assert stage.axis().position == target
        assert _ok(client.get(f"{API}/sim/scene"))["position_mm"][2] == pytest.approx(
            z_mm, abs=MICROSTEP_MM)
    assert service.stage.position_mm == PLATE_HEIGHTS[-1]

    # Beyond the stage's travel: refused before anything moves (422), the session goes on.
    moves = sum(c.startswith("/1 1 move") for c in stage.received)
    refused = client.post(f"{API}/calibration-sessions/{pid}/plates",
                          json={"z_mm": 31.0, "move_stage": True})
    assert refused.status_code == 422, refused.text
    assert sum(c.startswith("/1 1 move") for c in stage.received) == moves

    _ok(client.put(f"{API}/sim/scene", json={"kind": "reference",
                                             "position_mm": [0, 0, REFERENCE_Z]}))
    _ok(client.post(f"{API}/calibration-sessions/{pid}/reference",
                    json={"z_mm": REFERENCE_Z}), 201)
    job = _ok(client.post(f"{API}/calibration-sessions/{pid}/solve"), 202)
    p2h = _wait_job(client, job["id"])
    assert p2h["state"] == "succeeded", p2h["error"]
    calibration = _ok(client.get(f"{API}/calibrations/{p2h['result']['calibration_id']}"))
    assert calibration["parent_id"] == parent.id
    assert calibration["quality"]["p2h_residual_median_mm"] < 0.03


def test_a_stage_fault_fails_the_plate_and_nothing_is_stored(
        daemon: tuple[FastAPI, Client], stage: PlateCarryingZaber,
        calibrated_rooms: Any) -> None:
    app, client = daemon
    service = app.state.service
    _, caldir = calibrated_rooms("default")
    parent = service.store.import_calibration(caldir, actor="physicist")
    session = _ok(client.post(f"{API}/calibration-sessions",
                              json={"kind": "phase-height", "calibration_id": parent.id}), 201)
    pid = session["id"]
    captures = len(_ok(client.get(f"{API}/captures"))["items"])
    with stage.lock:
        stage.axis().stall_at = round((2.0 - ZERO_MM) / MICROSTEP_MM)  # the carriage jams
    failed = client.post(f"{API}/calibration-sessions/{pid}/plates",
                         json={"z_mm": 5.0, "move_stage": True})
    assert failed.status_code >= 500 or failed.status_code == 409, failed.text
    assert "Z1" in failed.text and "stalled" in failed.text
    assert len(_ok(client.get(f"{API}/captures"))["items"]) == captures
    assert _ok(client.get(f"{API}/calibration-sessions/{pid}"))["plates"] == []
