"""Stereo calibration from simulated chessboard bundles, on the default rig and on another rig."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from eyeserver.calibration.artefact import load_calibration
from eyeserver.calibration.stereo import CalibrationError, calibrate_stereo
from eyeserver.cli import main
from eyeserver.errors import FormatError
from eyeserver.hardware.sim.config import RoomConfig, load_room
from eyeserver.hardware.sim.room import SimRoom
from eyeserver.hardware.sim.scenes import SceneSpec
from eyeserver.hardware.sim.sessions import SimSession, calibration_poses
from eyeserver.io import read_rig

pytestmark = pytest.mark.slow  # every test here takes over a second

ROOT = Path(__file__).resolve().parents[1]
ROOMS = {"default": None, "wide": ROOT / "examples" / "rooms" / "wide.toml"}


def _record_boards(config: RoomConfig, out: Path) -> list[Path]:
    paths = []
    with SimSession.open(config) as session:
        for n, (position, rotation) in enumerate(calibration_poses()):
            path = out / f"chessboard_{n:02d}"
            session.record(SceneSpec(kind="chessboard", position_mm=position,
                                     rotation_deg=rotation), path, origin=(n == 0))
            paths.append(path)
    return paths


@pytest.fixture(scope="module", params=sorted(ROOMS))
def boards(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory,
           ) -> tuple[RoomConfig, list[Path]]:
    config = load_room(ROOMS[request.param])
    return config, _record_boards(config, tmp_path_factory.mktemp(request.param))


def test_calibration_recovers_every_camera(boards: tuple[RoomConfig, list[Path]]) -> None:
    """Sub-0.1 px reprojection, and the calibrated cameras project any point of the calibrated
    volume where the true cameras do (what reconstruction needs), within 0.3 px."""
    config, paths = boards
    result = calibrate_stereo(paths)
    room = SimRoom(config)
    rng = np.random.default_rng(0)
    volume = rng.uniform([-12, -10, -10], [12, 10, 25], (2000, 3))
    assert set(result.cameras) == set(room.camera_ids())
    for camera_id, cam in result.cameras.items():
        quality = cam.quality()
        assert quality["reprojection_median_px"] < 0.1, camera_id
        assert quality["reprojection_max_px"] < 0.3, camera_id
        truth = room.renderer.cameras[camera_id]
        assert np.linalg.norm(cam.centre - truth.centre) < 0.6, camera_id
        angle = np.degrees(np.arccos(np.clip((np.trace(cam.R @ truth.R.T) - 1) / 2, -1, 1)))
        # Up to 0.157° on the wide rig's S1 with one noise draw of its boards (its centre and
        # rotation trade off; the projections below are what the reconstruction needs).
        assert angle < 0.2, camera_id
        rvec, _ = cv2.Rodrigues(cam.R)
        uv, _ = cv2.projectPoints(volume.reshape(-1, 1, 3), rvec, cam.T, cam.K, cam.dist)
        error = np.linalg.norm(uv.reshape(-1, 2) - truth.project(volume), axis=1)
        assert np.median(error) < 0.1, camera_id
        assert error.max() < 0.3, camera_id


def test_cli_writes_a_calibration_that_loads_for_its_rig_only(
        boards: tuple[RoomConfig, list[Path]], tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    _, paths = boards
    out = tmp_path / "cal"
    assert main(["calibrate", "stereo", "--out", str(out), *map(str, paths)]) == 0
    printed = capsys.readouterr().out
    assert "reprojection error" in printed and "goal" in printed
    document = load_calibration(out)
    assert len(document["inputs"]["stereo"]) == len(paths)
    assert all(len(entry["sha256"]) == 64 for entry in document["inputs"]["stereo"])
    rig_file = tmp_path / "rig.json"
    with SimSession.open(load_room(None)) as session:
        rig_file.write_text(json.dumps(session.rig.spec()))
    # A rig with one camera less is refused by name.
    data = json.loads(rig_file.read_text())
    data["cameras"] = data["cameras"][:2]
    data["units"] = data["units"][:1]
    data["projectors"] = data["projectors"][:1]
    rig_file.write_text(json.dumps(data))
    with pytest.raises(FormatError, match="another rig"):
        load_calibration(out, read_rig(rig_file))
    # Refuses to overwrite, says so in one line.
    assert main(["calibrate", "stereo", "--out", str(out), *map(str, paths)]) == 2
    assert "exists" in capsys.readouterr().err


def test_a_board_a_camera_cannot_see_is_reported_not_fatal(
        boards: tuple[RoomConfig, list[Path]], tmp_path: Path) -> None:
    config, paths = boards
    if config.units[0].id != "left" or len(config.units) < 2:
        pytest.skip("needs the two-unit default rig")
    with SimSession.open(config) as session:
        # Far to the patient's right: the left unit's cameras lose it.
        aside = tmp_path / "chessboard_aside"
        session.record(SceneSpec(kind="chessboard", position_mm=(-40.0, 0.0, 0.0)), aside)
    result = calibrate_stereo([*paths, aside])
    assert "chessboard_aside" in result.missed
    assert set(result.missed["chessboard_aside"]) & {"S1", "S2"}


def test_bad_inputs_are_named(boards: tuple[RoomConfig, list[Path]], tmp_path: Path) -> None:
    _, paths = boards
    with pytest.raises(CalibrationError, match="origin board"):
        calibrate_stereo(paths[1:])
    with pytest.raises(CalibrationError, match="at least"):
        calibrate_stereo(paths[:3])
    with pytest.raises(CalibrationError, match="second origin"):
        calibrate_stereo([paths[0], paths[0]])
    broken = tmp_path / "calibration.json"
    broken.write_text("{}")
    with pytest.raises(FormatError, match="format"):
        load_calibration(tmp_path)
