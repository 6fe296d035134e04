"""Camera geometry of the pipeline against OpenCV's projection and the simulator's optics."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from eyeserver.hardware.sim.config import room_from_dict
from eyeserver.hardware.sim.room import SimRoom
from eyeserver.pipeline.geometry import (
    intersect_plane_z,
    pixel_grid_normalised,
    project,
    rays_from_normalised,
    undistorted_normalised,
)

STRONG = {"units": [{"id": "left", "cameras": [
    {"id": "S1", "distortion": [-0.2, 0.1, 0.002, -0.001, 0.0], "roll_deg": 7.0,
     "principal_offset_px": [12.0, -9.0]}, {"id": "S2"}]}]}


@pytest.mark.parametrize("room", [{}, STRONG], ids=["default", "strong-distortion"])
def test_pixel_ray_meets_plane_where_the_camera_projects_it(room: dict[str, object]) -> None:
    cam = SimRoom(room_from_dict(room)).renderer.cameras["S1"]
    rng = np.random.default_rng(1)
    u = rng.uniform(0, 639, 500)
    v = rng.uniform(0, 511, 500)
    x, y = undistorted_normalised(u, v, cam.K, cam.dist)
    for z in (-10.0, 0.0, 25.0):
        points = intersect_plane_z(cam.centre, rays_from_normalised(x, y, cam.R), z)
        assert np.allclose(points[:, 2], z)
        back = project(points, cam.K, cam.dist, cam.R, cam.T)
        assert np.max(np.hypot(back[:, 0] - u, back[:, 1] - v)) < 1e-6


def test_grid_matches_pointwise_and_rejects_bad_sizes() -> None:
    cam = SimRoom().renderer.cameras["S2"]
    x, y = pixel_grid_normalised(640, 512, cam.K, cam.dist)
    assert x.shape == (512, 640)
    xs, ys = undistorted_normalised(np.array([5.0, 600.0]), np.array([500.0, 3.0]), cam.K,
                                    cam.dist)
    assert np.allclose([x[500, 5], x[3, 600]], xs) and np.allclose([y[500, 5], y[3, 600]], ys)
    with pytest.raises(ValueError, match="image size"):
        pixel_grid_normalised(0, 10, cam.K, cam.dist)
    with pytest.raises(ValueError, match="u and v"):
        undistorted_normalised(np.zeros(3), np.zeros(4), cam.K, cam.dist)


@pytest.mark.parametrize("dist", [
    [-0.2, 0.1, 0.002, -0.001], [-0.2, 0.1, 0.002, -0.001, 0.05],
    [-0.2, 0.1, 0.002, -0.001, 0.05, 0.01, -0.02, 0.03],
    [-0.2, 0.1, 0.002, -0.001, 0.05, 0.01, -0.02, 0.03, 0.0, 0.0, 0.0, 0.0],
    [-0.2, 0.1, 0.002, -0.001, 0.05, 0.01, -0.02, 0.03, 0.001, -0.002, 0.0, 0.0]],
    ids=["4", "5", "8 rational", "12 thin prism zero", "12 thin prism"])
def test_project_is_opencvs_projection(dist: list[float]) -> None:
    rng = np.random.default_rng(3)
    R, _ = cv2.Rodrigues(np.array([0.1, -0.2, 0.05]))
    T = np.array([1.0, -2.0, 150.0])
    K = np.array([[1500.0, 0.0, 320.0], [0.0, 1480.0, 256.0], [0.0, 0.0, 1.0]])
    points = rng.uniform(-20.0, 20.0, (500, 3))
    expected, _ = cv2.projectPoints(points.reshape(-1, 1, 3), cv2.Rodrigues(R)[0], T, K,
                                    np.array(dist))
    uv = project(points, K, np.array(dist), R, T)
    assert uv.shape == (500, 2)
    assert np.max(np.abs(uv - expected.reshape(-1, 2))) < 1e-9


def test_a_calibrated_cameras_points_at_are_intersect_plane_zs() -> None:
    """``CalibratedCamera.points_at`` (the rays gathered from three contiguous rows) gives the
    numbers :func:`intersect_plane_z` gives from the (H·W, 3) rays, on a rolled, distorted
    camera, and its points lie on their planes."""
    from eyeserver.pipeline.demodulate import Carrier
    from eyeserver.pipeline.phase_height import PhaseHeightModel
    from eyeserver.pipeline.reconstruct import CalibratedCamera

    sim = SimRoom(room_from_dict(STRONG)).renderer.cameras["S1"]
    model = PhaseHeightModel((10.0, 1.0, 0, 0, 0, 0, 0, 0, 0, 0, 0),
                             0.0, 1.0, 0.0, 1.0, 0.0, 1.0, 0.0, 1.0, (-10.0, 25.0))
    camera = CalibratedCamera("S1", sim.K, sim.dist, sim.R, sim.T, model, Carrier((0.0, 0.1)),
                              np.zeros((512, 640), np.float32), border_px=10)
    rng = np.random.default_rng(3)
    pixels = rng.integers(0, 512 * 640, 2000).astype(np.intp)
    z = rng.uniform(-10.0, 25.0, pixels.size)
    points = camera.points_at(pixels, z)
    assert np.array_equal(points, intersect_plane_z(camera.centre, camera.rays[pixels], z))
    assert np.allclose(points[:, 2], z)
