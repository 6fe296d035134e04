"""Reconstruction of simulated scenes against their exact surfaces, on two rig geometries.

The pipeline sees only the bundles and the calibration the command line made from a simulated
calibration set; the scene's truth is used only to score the result.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from eyeserver.cli import main
from eyeserver.hardware.sim.config import load_room
from eyeserver.hardware.sim.scenes import SceneSpec
from eyeserver.hardware.sim.scoring import score_cloud
from eyeserver.hardware.sim.sessions import SimSession
from eyeserver.io import read_ply
from tests.conftest import ROOMS

SCENES: dict[str, SceneSpec] = {
    "plate_0": SceneSpec(kind="plate", position_mm=(0.0, 0.0, 0.0)),
    "plate_-9": SceneSpec(kind="plate", position_mm=(0.0, 0.0, -9.0)),
    "plate_+3": SceneSpec(kind="plate", position_mm=(0.0, 0.0, 3.0)),
    "plate_+23": SceneSpec(kind="plate", position_mm=(0.0, 0.0, 23.0)),
    "tilted": SceneSpec(kind="plate", position_mm=(0.0, 0.0, 2.0), rotation_deg=(15.0, -10.0,
                                                                                0.0)),
    "wedge": SceneSpec(kind="wedge"),
    "pyramid": SceneSpec(kind="pyramid", position_mm=(1.0, -1.0, -5.0)),
    "eye_phantom_1": SceneSpec(kind="eye_phantom_1"),
    "eye_phantom_2": SceneSpec(kind="eye_phantom_2", position_mm=(1.5, 0.5, -9.0),
                               rotation_deg=(8.0, -6.0, 0.0)),
}
KNOWN_GAP = pytest.mark.xfail(strict=True, reason=(
    "eye phantom 2 (corneal cap, turned and shifted): ~10 % of points beyond 1 mm, not yet "
    "understood; median still 0.024 mm (issue 3 stays open)"))
CASES = [pytest.param("default", name, marks=KNOWN_GAP if name == "eye_phantom_2" else ())
         for name in SCENES] + [
    pytest.param("wide", "plate_+3"), pytest.param("wide", "pyramid"),
    pytest.param("wide", "eye_phantom_2", marks=KNOWN_GAP),
    # Horizontal fringes, one unit, 12-bit cameras: the pipeline assumes no fringe direction.
    pytest.param("horizontal", "plate_+3"), pytest.param("horizontal", "pyramid")]


def _measure(calibrated_rooms: Any, room: str, scene: str, tmp_path: Path,
             cameras: str | None = None) -> dict[str, Any]:
    _, caldir = calibrated_rooms(room)
    config = load_room(ROOMS[room])
    bundle = tmp_path / scene
    with SimSession.open(config, seed=7) as session:
        session.record(SCENES[scene], bundle)
    cloud_path = tmp_path / f"{scene}.ply"
    args = ["reconstruct", "--calibration", str(caldir), "--out", str(cloud_path), str(bundle)]
    if cameras:
        args[1:1] = ["--cameras", cameras]
    assert main(args) == 0
    truth = json.loads((bundle / "truth.json").read_text())
    return score_cloud(truth, read_ply(cloud_path), config)


@pytest.mark.parametrize(("room", "scene"), CASES,
                         ids=[f"{c.values[0]}-{c.values[1]}" for c in CASES])
def test_scene_matches_its_exact_surface(calibrated_rooms: Any, room: str, scene: str,
                                         tmp_path: Path) -> None:
    score = _measure(calibrated_rooms, room, scene, tmp_path)
    assert score["median_mm"] < 0.05, score  # goal of DESIGN §6: 0.15 mm
    assert score["beyond_1mm"] < 0.005, score
    for camera_id, coverage in score["coverage"].items():
        assert coverage["share"] > 0.4, (camera_id, score)


def test_extremes_of_the_range_are_as_good_as_the_middle(calibrated_rooms: Any,
                                                          tmp_path: Path) -> None:
    middle = _measure(calibrated_rooms, "default", "plate_0", tmp_path)
    for scene in ("plate_-9", "plate_+23"):
        extreme = _measure(calibrated_rooms, "default", scene, tmp_path)
        assert extreme["median_mm"] < 2 * middle["median_mm"] + 0.005, (scene, extreme)
        assert extreme["rmse_mm"] < 0.1, (scene, extreme)


def test_two_views_reconstruct_too(calibrated_rooms: Any, tmp_path: Path) -> None:
    score = _measure(calibrated_rooms, "default", "pyramid", tmp_path, cameras="S1,S2")
    assert set(score["coverage"]) == {"S1", "S2"}
    assert score["median_mm"] < 0.05


def test_bad_requests_are_explained(calibrated_rooms: Any, tmp_path: Path,
                                    capsys: pytest.CaptureFixture[str]) -> None:
    calset, caldir = calibrated_rooms("default")
    out = str(tmp_path / "x.ply")
    assert main(["reconstruct", "--calibration", str(caldir), "--out", out,
                 str(calset / "chessboard_00")]) == 2
    assert "no fringe image" in capsys.readouterr().err
    assert main(["reconstruct", "--calibration", str(caldir), "--cameras", "S9", "--out", out,
                 str(calset / "reference")]) == 2
    assert "S9" in capsys.readouterr().err
    assert main(["reconstruct", "--calibration", str(tmp_path), "--out", out,
                 str(calset / "reference")]) == 2
    assert "calibration.json" in capsys.readouterr().err
