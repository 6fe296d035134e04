"""Reconstruction of simulated scenes against their exact surfaces, on two rig geometries.

The pipeline sees only the bundles and the calibration the command line made from a simulated
calibration set; the scene's truth is used only to score the result.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from eyeserver.cli import main
from eyeserver.hardware.sim.config import load_room
from eyeserver.hardware.sim.scenes import SceneSpec
from eyeserver.hardware.sim.scoring import score_cloud
from eyeserver.hardware.sim.sessions import SimSession
from eyeserver.io import read_ply
from eyeserver.reconstruction import unit_method
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
    # Turned and shifted, its base plate's corners reach Z = −10.4 mm, just below the calibrated
    # range (at Z = −9 they reached −14 mm, beyond what any order can be checked for).
    "eye_phantom_2": SceneSpec(kind="eye_phantom_2", position_mm=(1.5, 0.5, -5.0),
                               rotation_deg=(8.0, -6.0, 0.0)),
    "eye": SceneSpec(kind="eye"),  # a patient's eye, lids and skin about it
}
CASES = [pytest.param("default", name) for name in SCENES] + [
    pytest.param("wide", "plate_+3"), pytest.param("wide", "pyramid"),
    pytest.param("wide", "eye_phantom_2"), pytest.param("wide", "eye"),
    # Horizontal fringes, one unit, 12-bit cameras: the pipeline assumes no fringe direction.
    pytest.param("horizontal", "plate_+3"), pytest.param("horizontal", "pyramid"),
    pytest.param("horizontal", "eye"),
    # Unbinned 1280×1024 10-bit cameras: twice the pixels per millimetre.
    pytest.param("single", "plate_+3"), pytest.param("single", "eye")]

PLANES = {"plate_0", "plate_-9", "plate_+3", "plate_+23", "tilted"}


def _measure(calibrated_rooms: Any, room: str, scene: str, tmp_path: Path,
             cameras: str | None = None, options: tuple[str, ...] = ()) -> dict[str, Any]:
    _, caldir = calibrated_rooms(room)
    config = load_room(ROOMS[room])
    bundle = tmp_path / scene
    if not bundle.exists():
        with SimSession.open(config, seed=7) as session:
            session.record(SCENES[scene], bundle)
    cloud_path = tmp_path / f"{scene}.ply"
    args = ["reconstruct", "--calibration", str(caldir), "--out", str(cloud_path), *options,
            str(bundle)]
    if cameras:
        args[1:1] = ["--cameras", cameras]
    assert main(args) == 0
    truth = json.loads((bundle / "truth.json").read_text())
    return score_cloud(truth, read_ply(cloud_path), config)


@pytest.mark.slow
@pytest.mark.parametrize(("room", "scene"), CASES,
                         ids=[f"{c.values[0]}-{c.values[1]}" for c in CASES])
def test_scene_matches_its_exact_surface(calibrated_rooms: Any, room: str, scene: str,
                                         tmp_path: Path) -> None:
    score = _measure(calibrated_rooms, room, scene, tmp_path)
    assert score["median_mm"] < 0.05, score  # docs/design.md §6: goal 0.15 mm, next 0.05
    assert score["rmse_mm"] < 0.15, score  # the goal of docs/design.md §6
    assert score["beyond_1mm"] < 0.001, score
    # Issue 37's goals: shares of the pixels the unit's projector lights (the truth's count).
    least = 0.8 if scene in PLANES else 0.6
    for camera_id, coverage in score["coverage"].items():
        assert coverage["lit_share"] >= least, (camera_id, score)


@pytest.mark.slow
def test_extremes_of_the_range_are_as_good_as_the_middle(calibrated_rooms: Any,
                                                          tmp_path: Path) -> None:
    middle = _measure(calibrated_rooms, "default", "plate_0", tmp_path)
    for scene in ("plate_-9", "plate_+23"):
        extreme = _measure(calibrated_rooms, "default", scene, tmp_path)
        assert extreme["median_mm"] < 2 * middle["median_mm"] + 0.005, (scene, extreme)
        assert extreme["rmse_mm"] < 0.1, (scene, extreme)


@pytest.mark.slow
def test_two_views_reconstruct_too(calibrated_rooms: Any, tmp_path: Path) -> None:
    score = _measure(calibrated_rooms, "default", "pyramid", tmp_path, cameras="S1,S2")
    assert set(score["coverage"]) == {"S1", "S2"}
    assert score["median_mm"] < 0.05


@pytest.mark.parametrize(("section", "asked", "for_tracking", "chosen", "why"), [
    ({"margin_rad": 0.69}, "auto", False, "spatial", "margin 0.69 rad: regions unwrapped"),
    ({"margin_rad": 0.69}, "auto", True, "multi-view", "margin 0.69 rad, at least 0.5"),
    ({"margin_rad": 0.5}, "auto", True, "multi-view", "at least 0.5"),
    ({"margin_rad": 0.2}, "auto", False, "spatial", "0.20 rad, below 0.5 rad: too blind"),
    ({"margin_rad": 0.2}, "auto", True, "spatial", "0.20 rad, below 0.5 rad: too blind"),
    ({"margin_rad": 0.0}, "auto", False, "blind", "cannot tell the fringe orders apart"),
    ({"margin_rad": 0.0}, "auto", True, "blind", "cannot tell the fringe orders apart"),
    ({"margin_rad": None, "note": "one camera"}, "auto", False, "spatial",
     "no fringe-order margin"),
    (None, "auto", True, "spatial", "no fringe-order margin"),
    ({"margin_rad": 0.0}, "multi-view", False, "multi-view", "asked for"),
    ({"margin_rad": 0.69}, "spatial", True, "spatial", "asked for"),
], ids=["clear", "clear, tracking", "at the line, tracking", "too blind", "too blind, tracking",
        "blind", "blind, tracking", "one camera", "no section", "asked multi-view",
        "asked spatial"])
def test_auto_picks_each_units_fringe_order_from_its_calibration(
        section: dict[str, Any] | None, asked: str, for_tracking: bool, chosen: str, why: str
) -> None:
    document = {"phase_to_height": {"units": {} if section is None else {"left": section}}}
    method, reason = unit_method(document, "left", asked, for_tracking=for_tracking)
    assert method == chosen
    assert why in reason


@pytest.mark.slow
@pytest.mark.parametrize("scene", ["plate_+3", "pyramid", "eye"])
def test_a_blind_unit_takes_its_fringe_order_from_the_other_unit(
        calibrated_rooms: Any, scene: str, tmp_path: Path) -> None:
    """examples/rooms/blind.toml: each unit's cameras at one azimuth, so neither tells the
    other's fringe order (every method that trusted it put a plate two fringes, 11.5 mm, off).
    With the default options the other unit's camera fixes each blind unit's orders: issue 37's
    coverage and accuracy goals, as on a sighted rig."""
    _, caldir = calibrated_rooms("blind")
    document = json.loads((caldir / "calibration.json").read_text())
    for unit in document["phase_to_height"]["units"].values():
        assert unit["margin_rad"] < 0.01 and "too blind" in unit["note"], unit

    score = _measure(calibrated_rooms, "blind", scene, tmp_path)

    assert score["median_mm"] < 0.05, score
    assert score["rmse_mm"] < 0.15, score
    assert score["beyond_1mm"] < 0.001, score
    least = 0.8 if scene in PLANES else 0.6
    for camera_id, coverage in score["coverage"].items():
        assert coverage["lit_share"] >= least, (camera_id, score)


@pytest.mark.slow
def test_a_blind_unit_alone_is_said_so_and_needs_a_depth_prior(
        calibrated_rooms: Any, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """One blind unit's images with no other unit's to fix its orders: refused with the reason
    unless given a depth prior, which then fixes each camera's orders alone."""
    with pytest.raises(AssertionError):
        _measure(calibrated_rooms, "blind", "plate_+3", tmp_path, cameras="S1,S2")
    error = capsys.readouterr().err
    assert "unit left is blind to the fringe order" in error, error
    assert "no other unit's camera" in error, error

    score = _measure(calibrated_rooms, "blind", "plate_+3", tmp_path, cameras="S1,S2",
                     options=("--depth-prior", "3"))
    assert score["median_mm"] < 0.05, score
    assert score["beyond_1mm"] < 0.001, score
    for camera_id, coverage in score["coverage"].items():  # 0.77: short of issue 37's 0.8
        assert coverage["share"] >= 0.75, (camera_id, score)


def test_a_colour_bundle_reconstructs_as_its_grey_one(calibrated_rooms: Any,
                                                      tmp_path: Path) -> None:
    """A colour camera's PNGs (channels of different strength, their mean the grey image) give
    the grey bundle's surface: docs/FORMATS.md reads them as the mean of their channels."""
    grey_score = _measure(calibrated_rooms, "default", "plate_+3", tmp_path)
    colour = tmp_path / "colour" / "plate_+3"
    shutil.copytree(tmp_path / "plate_+3", colour)
    for path in colour.glob("*.png"):
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(np.int32)
        assert image.ndim == 2
        spread = np.minimum(np.minimum(image, np.iinfo(np.uint8).max - image), 20)
        bgr = np.stack([image - spread, image, image + spread], axis=2)  # mean: the grey image
        assert cv2.imwrite(str(path), bgr.astype(np.uint8))

    colour_score = _measure(calibrated_rooms, "default", "plate_+3", tmp_path / "colour")

    assert colour_score["median_mm"] < 0.05, colour_score
    assert colour_score["beyond_1mm"] < 0.001, colour_score
    for camera_id, coverage in colour_score["coverage"].items():
        assert coverage["share"] == pytest.approx(grey_score["coverage"][camera_id]["share"],
                                                  abs=0.01)


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
    assert main(["reconstruct", "--calibration", str(caldir), "--roi", "0", "0", "0", "1", "1",
                 "-1", "--out", out, str(calset / "reference")]) == 2
    assert "--roi" in capsys.readouterr().err


SPATIAL = {"pyramid": 0.1, "eye_phantom_1": 0.03}
"""How much more of what each camera lit the default (``auto``: the spatial order, with what
only one camera sees kept where it continues confirmed points) keeps than the multi-view order
(measured 2026-12-05: pyramid 0.68–0.70 → 0.86–0.88, eye phantom 1 0.66 → 0.74)."""


@pytest.mark.slow
@pytest.mark.parametrize("scene", list(SPATIAL))
def test_the_default_order_covers_more_than_the_multi_view_one(calibrated_rooms: Any,
                                                               scene: str,
                                                               tmp_path: Path) -> None:
    fast = _measure(calibrated_rooms, "default", scene, tmp_path,
                    options=("--method", "multi-view"))
    default = _measure(calibrated_rooms, "default", scene, tmp_path)
    for score in (fast, default):
        assert score["median_mm"] < 0.05, score
        assert score["beyond_1mm"] < 0.001, score
    for camera_id, coverage in default["coverage"].items():
        assert (coverage["lit_share"]
                > fast["coverage"][camera_id]["lit_share"] + SPATIAL[scene]), (fast, default)


@pytest.mark.slow
def test_one_camera_alone_needs_and_uses_a_depth_prior(calibrated_rooms: Any, tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str],
                                                       ) -> None:
    calset, caldir = calibrated_rooms("default")
    out = str(tmp_path / "x.ply")
    assert main(["reconstruct", "--calibration", str(caldir), "--cameras", "S1", "--out", out,
                 str(calset / "reference")]) == 2
    assert "depth prior" in capsys.readouterr().err
    score = _measure(calibrated_rooms, "default", "plate_+3", tmp_path, cameras="S1",
                     options=("--depth-prior", "4.5"))
    assert "depth prior" in capsys.readouterr().out
    assert score["median_mm"] < 0.05, score
    assert score["beyond_1mm"] < 0.001, score
    # A prior more than half a fringe's depth off picks the neighbouring order: the prior is
    # what decides, so a wrong one gives a plate a fringe (≈ 5 mm) away.
    wrong = _measure(calibrated_rooms, "default", "plate_+3", tmp_path, cameras="S1",
                     options=("--depth-prior", "9"))
    assert wrong["median_mm"] > 3, wrong


@pytest.mark.slow
def test_region_of_interest_and_quality_crop(calibrated_rooms: Any, tmp_path: Path) -> None:
    whole = _measure(calibrated_rooms, "default", "pyramid", tmp_path)
    cropped = _measure(calibrated_rooms, "default", "pyramid", tmp_path,
                       options=("--roi", "-5", "-5", "-20", "5", "5", "30",
                                "--min-quality", "0.3"))
    points = read_ply(tmp_path / "pyramid.ply").points
    assert points.size and np.all(np.abs(points[:, :2]) <= 5.0 + 1e-4)
    assert cropped["points"] < whole["points"] / 3
    assert cropped["median_mm"] < 0.05


def test_a_cameras_pixel_rays_are_computed_when_first_needed_and_windows_slice_them() -> None:
    # Undistorting every pixel (≈ 40 ms a camera) is paid only by what reconstructs pixels:
    # the limbus search of a pose measurement projects points and never needs it.
    from eyeserver.pipeline.demodulate import Carrier
    from eyeserver.pipeline.geometry import pixel_grid_normalised, rays_from_normalised
    from eyeserver.pipeline.phase_height import PhaseHeightModel
    from eyeserver.pipeline.reconstruct import CalibratedCamera, cropped, decimated

    height, width = 120, 160
    K = np.array([[300.0, 0.0, 83.0], [0.0, 310.0, 57.0], [0.0, 0.0, 1.0]])
    dist = np.array([-0.2, 0.05, 0.001, -0.002, 0.0])
    R = np.array([[1.0, 0.0, 0.0], [0.0, 0.8, -0.6], [0.0, 0.6, 0.8]])
    model = PhaseHeightModel((10.0, 1.0, 0, 0, 0, 0, 0, 0, 0, 0, 0),
                             0.0, 1.0, 0.0, 1.0, 0.0, 1.0, 0.0, 1.0, (-10.0, 25.0))
    camera = CalibratedCamera("S1", K, dist, R, np.array([0.0, 5.0, 250.0]), model,
                              Carrier((0.0, 0.1)), np.zeros((height, width), np.float32),
                              border_px=10)
    assert "_xy" not in vars(camera) and "rays" not in vars(camera)
    x, y = pixel_grid_normalised(width, height, K, dist)
    np.testing.assert_array_equal(camera.x, x)
    np.testing.assert_array_equal(camera.y, y)
    np.testing.assert_array_equal(camera.rays, rays_from_normalised(x, y, R).reshape(-1, 3))
    assert camera.x.flags.c_contiguous and camera.y.flags.c_contiguous
    window = cropped(camera, 30, 20, 110, 90)
    np.testing.assert_array_equal(window.x, x[20:90, 30:110])
    np.testing.assert_array_equal(window.rays.reshape(70, 80, 3),
                                  camera.rays.reshape(height, width, 3)[20:90, 30:110])
    coarse = decimated(window, 2)
    np.testing.assert_array_equal(coarse.y, y[20:90:2, 30:110:2])


def test_a_region_too_small_for_the_sparse_vote_is_voted_on_the_full_grid(
        calibrated_rooms: Any) -> None:
    """``spatial_order`` votes each region's offset with multi-view picks on every ninth pixel
    first. A plate's phase masked into a large region and a 15 × 15-pixel island (above the
    200-pixel least region, one or two sparse picks, some 25 on the full grid) must give the
    island its order from the full grid, and every pixel the order the full grid's vote gives
    (the spatial path before the sparse vote)."""
    from eyeserver.calibration.artefact import load_calibration
    from eyeserver.io import rig_from_dict
    from eyeserver.pipeline.reconstruct import (
        COARSE_STRIDE,
        SPARSE_VOTE_STRIDE,
        Phase,
        camera_phase,
        grid_order,
        spatial_order,
    )
    from eyeserver.reconstruction import calibrated_cameras, z_range

    _, caldir = calibrated_rooms("default")
    with SimSession.open(load_room(None), seed=5) as session:
        session.room.set_scene(SceneSpec(kind="plate", position_mm=(0.0, 0.0, 3.0)))
        rig = rig_from_dict(session.rig.spec(), "<simulated rig>")
        step = session.rig.acquire([session.rig.units[0].id])[0]
    document = load_calibration(caldir, rig)
    cameras, limits = calibrated_cameras(document), z_range(document)
    id_a, id_b = list(step.frames)[:2]
    cam_a, cam_b = cameras[id_a], cameras[id_b]
    phase_a = camera_phase(cam_a, step.frames[id_a].image)
    phase_b = camera_phase(cam_b, step.frames[id_b].image)
    h, w = phase_a.valid.shape
    keep = np.zeros((h, w), bool)
    keep[:, : w // 2 - 20] = True  # the large region
    top, left = 257, w // 2 + 40  # the island: rows 257–271 hold one row of sparse picks
    keep[top:top + 15, left:left + 15] = True
    assert phase_a.valid[top:top + 15, left:left + 15].all()
    masked = Phase(phase_a.dphi, phase_a.modulation, phase_a.valid & keep)

    pixels, order, by_votes = spatial_order(cam_a, masked, cam_b, phase_b, limits, None)
    dense = grid_order(cam_a, masked, cam_b, phase_b, limits, stride=COARSE_STRIDE)
    d_pixels, d_order, _ = spatial_order(cam_a, masked, cam_b, phase_b, limits, None,
                                         grid=dense)
    island = (pixels // w >= top) & (pixels % w >= left)
    assert island.sum() >= 200 and by_votes[island].all()
    sparse = grid_order(cam_a, masked, cam_b, phase_b, limits, stride=SPARSE_VOTE_STRIDE)
    assert np.count_nonzero((sparse.pixels // w >= top) & (sparse.pixels % w >= left)) < 3
    assert np.array_equal(pixels, d_pixels) and np.array_equal(order, d_order)


def test_the_sampled_unwrapping_gives_each_part_of_a_region_its_own_vote() -> None:
    """``spatial_unwrap`` unwraps every second pixel: a one-pixel neck of the mask on an odd row
    joins two halves at full resolution but not among the samples, whose halves are unwrapped
    apart (each with its own offset). Each half must be a region of its own, its steps
    consistent with the true phase; a steep ramp (0.9 rad a pixel, 1.8 between samples) still
    unwraps."""
    from eyeserver.pipeline.reconstruct import Phase, spatial_unwrap

    rows, cols = np.mgrid[0:64, 0:96]
    truth = 0.9 * cols + 0.3 * rows
    valid = np.zeros(truth.shape, bool)
    valid[:, :40] = True
    valid[:, 51:] = True
    valid[31, 40:51] = True  # the neck: no sample lies on it
    wrapped = np.angle(np.exp(1j * truth)).astype(np.float32)
    unwrapped = spatial_unwrap(Phase(wrapped, np.ones_like(wrapped), valid))

    assert len(unwrapped.pixels) >= valid.sum() - 11  # at most the neck left out
    side = np.where(unwrapped.pixels % 96 < 45, 0, 1)
    regions = [set(unwrapped.region[side == s].tolist()) for s in (0, 1)]
    assert len(regions[0]) == 1 and len(regions[1]) == 1 and regions[0] != regions[1]
    true_steps = np.rint((truth.ravel() - wrapped.ravel()) / (2 * np.pi))[unwrapped.pixels]
    for region in np.unique(unwrapped.region):
        inside = unwrapped.region == region
        offsets = true_steps[inside] - unwrapped.steps[inside]
        assert np.unique(offsets).size == 1
