"""Fiducial dots through a forward model (STYLE rule 4): the simulated room renders phantoms with
painted dots, and what eyeserver.pipeline.fiducials finds is compared with the scene's truth.

The truth comes from the bundle's ``truth.json`` (the dots' centres and the true cameras) and
from ray casting the exact scene (which dots a camera sees whole, the exact surface behind each
pixel). Synthetic images and analytic surfaces check the parts the scenes cannot isolate: the
sub-pixel centre on every fringe phase and on curved fringes, dots cut by the border, dark
features and noise that are no dots, the size range, exact geometry.

Why the projected centre is the reference for the image centroid: a dot is painted on the
surface, so its true centre lies on the surface and projects through the camera model exactly
(``cv2.projectPoints``, which the simulator's rays follow). The centroid of the dot's image is
that projection only to first order: perspective shifts the centroid of a disc on a surface
tilted by θ by about (r/Z)²·tan θ focal lengths, ≈ 0.01 px for these 0.5 mm dots at 250 mm
even at 70°, far inside the tolerances below.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
import pytest

from eyeserver.core.types import F64
from eyeserver.hardware.sim.config import load_room
from eyeserver.hardware.sim.room import SimRoom
from eyeserver.hardware.sim.scenes import (
    FIDUCIAL_PAINT,
    FIDUCIAL_RADIUS_MM,
    SceneSpec,
    build_scene,
)
from eyeserver.hardware.sim.sessions import SimSession
from eyeserver.hardware.sim.truth import truth_scene
from eyeserver.io import read_bundle
from eyeserver.pipeline.fiducials import (
    detect_fiducials,
    match_stereo,
    surface_position,
    triangulate,
)
from tests.conftest import ROOMS

PERIOD_PX = 24.0  # the simulated rooms' fringe period in the image (23–30 px)

# Every detection must be this near the projected centre of a dot (dots stand ≥ 20 px apart,
# so anything farther is a false detection or a broken centre).
MATCH_PX = 0.6
MEDIAN_PX = 0.15  # brief: < 0.2 px; measured 0.05–0.09 px per scene
MAX_PX = 0.5  # measured ≤ 0.34 px
# A dot counts as clearly visible when the camera sees all of it at most 60° from its normal
# (cos ≥ 0.5); dots seen more obliquely may be found or dropped (their rings of fringe are
# too curved to trust), but never mislocated.
CLEAR_COS = 0.5
RECALL = 0.85  # measured 0.89–1.0 of the clearly visible dots, per scene
TRIANGULATION_MEDIAN_MM = 0.05  # measured 0.009–0.016 mm with the true cameras
# Measured ≤ 0.09 mm: the cameras of a unit stand ≈ 24° apart, so a 0.3 px error across the
# baseline moves the point ≈ 2.5 times as far in depth as across the ray.
TRIANGULATION_MAX_MM = 0.15

SCENES: dict[str, SceneSpec] = {
    "eye_phantom_1": SceneSpec(kind="eye_phantom_1"),
    # Turned and shifted, with a corneal cap: dots on a sphere seen from every side.
    "eye_phantom_2": SceneSpec(kind="eye_phantom_2", position_mm=(1.5, 0.5, -9.0),
                               rotation_deg=(8.0, -6.0, 0.0)),
    "pyramid": SceneSpec(kind="pyramid", position_mm=(1.0, -1.0, -5.0)),
    "wedge": SceneSpec(kind="wedge"),
}
CASES = [("default", "eye_phantom_1"), ("default", "eye_phantom_2"), ("default", "pyramid"),
         ("default", "wedge"), ("wide", "eye_phantom_1"), ("wide", "pyramid"),
         # Horizontal fringes, 12-bit cameras, one unit.
         ("horizontal", "eye_phantom_2")]
CASE_IDS = [f"{room}-{scene}" for room, scene in CASES]


# --- the simulated scenes -----------------------------------------------------------------------


@dataclass
class View:
    """One camera's fringe image of a scene, its true camera and what the detector found."""

    camera_id: str
    image: npt.NDArray[Any]
    K: F64
    dist: F64
    R: F64
    T: F64
    centre: F64
    projected: F64
    """Every fiducial's true centre projected into the image, (F, 2)."""
    whole: npt.NDArray[np.bool_]
    """Whether the camera sees the whole dot (centre and rim unoccluded)."""
    centre_seen: npt.NDArray[np.bool_]
    cos_view: F64
    detected: F64 = field(init=False)
    nearest: npt.NDArray[np.intp] = field(init=False)
    error_px: F64 = field(init=False)

    def __post_init__(self) -> None:
        self.detected = detect_fiducials(self.image, PERIOD_PX)
        distance = np.linalg.norm(self.detected[:, None, :] - self.projected[None], axis=2)
        self.nearest = np.argmin(distance, axis=1) if len(self.detected) else \
            np.zeros(0, dtype=np.intp)
        self.error_px = distance[np.arange(len(self.detected)), self.nearest]

    @property
    def camera(self) -> tuple[F64, F64, F64, F64]:
        return self.K, self.dist, self.R, self.T

    @property
    def clear(self) -> npt.NDArray[np.bool_]:
        return self.whole & (self.cos_view >= CLEAR_COS)


@dataclass
class Scene:
    room: SimRoom
    truth: dict[str, Any]
    fiducials: F64
    views: dict[str, View]
    units: list[tuple[str, str]]


def _visibility(truth: dict[str, Any], centre: F64) -> tuple[npt.NDArray[np.bool_],
                                                              npt.NDArray[np.bool_], F64]:
    """Per fiducial: whole dot seen, centre seen, cosine of the view to the surface normal."""
    scene = build_scene(truth_scene(truth)).scene
    fiducials = np.asarray(truth["fiducials_mm"], dtype=np.float64)
    to_dot = fiducials - centre
    distance = np.linalg.norm(to_dot, axis=1)
    hits = scene.cast(centre, to_dot / distance[:, None])
    centre_seen = np.abs(hits.t - distance) < 1e-3
    normals = hits.normals / np.linalg.norm(hits.normals, axis=1, keepdims=True)
    cos_view = np.abs(np.einsum("ij,ij->i", normals, to_dot / distance[:, None]))
    # Twelve points of each dot's rim, in the surface's tangent plane.
    helper = np.where(np.abs(normals[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    first = np.cross(normals, helper)
    first /= np.linalg.norm(first, axis=1, keepdims=True)
    second = np.cross(normals, first)
    angles = np.linspace(0.0, 2 * math.pi, 12, endpoint=False)
    rim = (fiducials[:, None, :] + FIDUCIAL_RADIUS_MM
           * (np.cos(angles)[None, :, None] * first[:, None, :]
              + np.sin(angles)[None, :, None] * second[:, None, :])).reshape(-1, 3)
    to_rim = rim - centre
    rim_distance = np.linalg.norm(to_rim, axis=1)
    rim_hits = scene.cast(centre, to_rim / rim_distance[:, None])
    rim_seen = (np.abs(rim_hits.t - rim_distance) < 0.05).reshape(len(fiducials), -1)
    whole = centre_seen & rim_seen.all(axis=1)
    return whole, centre_seen, np.where(centre_seen, cos_view, 0.0)


def _record(room_name: str, scene_name: str, out: Path) -> Scene:
    config = load_room(ROOMS[room_name])
    with SimSession.open(config, seed=7) as session:
        session.record(SCENES[scene_name], out)
        room = session.room
    bundle = read_bundle(out)
    truth = json.loads((out / "truth.json").read_text())
    fiducials = np.asarray(truth["fiducials_mm"], dtype=np.float64)
    views: dict[str, View] = {}
    for frame_index, camera_id in bundle.fringe_images():
        cam = truth["devices"]["cameras"][camera_id]
        K, dist, R, T, centre = (np.asarray(cam[k], dtype=np.float64)
                                 for k in ("K", "dist", "R", "T", "centre_mm"))
        rvec, _ = cv2.Rodrigues(R)
        projected, _ = cv2.projectPoints(fiducials.reshape(-1, 1, 3), rvec, T, K, dist)
        whole, centre_seen, cos_view = _visibility(truth, centre)
        views[camera_id] = View(camera_id, bundle.load_image(frame_index, camera_id), K, dist,
                                R, T, centre,
                                np.asarray(projected, dtype=np.float64).reshape(-1, 2), whole,
                                centre_seen, cos_view)
    units = [(unit.cameras[0], unit.cameras[1]) for unit in bundle.rig.units]
    return Scene(room, truth, fiducials, views, units)


_SCENES: dict[tuple[str, str], Scene] = {}


@pytest.fixture(scope="module")
def scenes(tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    """``get(room, scene) -> Scene``, recorded on first use (≈ 1–1.5 s each)."""
    def get(room_name: str, scene_name: str) -> Scene:
        key = (room_name, scene_name)
        if key not in _SCENES:
            out = tmp_path_factory.mktemp(f"{room_name}-{scene_name}") / "bundle"
            _SCENES[key] = _record(room_name, scene_name, out)
        return _SCENES[key]
    return get


# --- detection in the simulated room ------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize(("room", "scene"), CASES, ids=CASE_IDS)
def test_every_detection_is_a_dot_at_its_true_centre(scenes: Any, room: str,
                                                     scene: str) -> None:
    errors: list[float] = []
    for view in scenes(room, scene).views.values():
        # No false detections: every detection sits on a dot the camera sees...
        stray = view.error_px > MATCH_PX
        assert not stray.any(), (view.camera_id, view.detected[stray], view.error_px[stray])
        assert view.centre_seen[view.nearest].all(), (view.camera_id, view.nearest)
        # ...and no dot is reported twice.
        assert len(set(view.nearest.tolist())) == len(view.nearest), view.camera_id
        errors.extend(view.error_px.tolist())
    assert len(errors) >= 10, errors
    assert float(np.median(errors)) < MEDIAN_PX, errors
    assert max(errors) < MAX_PX, errors


@pytest.mark.parametrize(("room", "scene"), CASES, ids=CASE_IDS)
def test_clearly_visible_dots_are_found(scenes: Any, room: str, scene: str) -> None:
    clear = found = 0
    for view in scenes(room, scene).views.values():
        wanted = np.flatnonzero(view.clear & _inside_image(view, margin=20.0))
        clear += wanted.size
        found += np.isin(wanted, view.nearest).sum()
    assert clear >= 10, clear
    assert found >= RECALL * clear, (found, clear)


def _inside_image(view: View, margin: float) -> npt.NDArray[np.bool_]:
    height, width = view.image.shape
    u, v = view.projected[:, 0], view.projected[:, 1]
    return np.asarray((u >= margin) & (u <= width - 1 - margin) & (v >= margin)
                      & (v <= height - 1 - margin))


# --- two views: matching and triangulation -------------------------------------------------------


@pytest.mark.parametrize(("room", "scene"), CASES, ids=CASE_IDS)
def test_stereo_pairs_are_true_and_triangulate_onto_the_dots(scenes: Any, room: str,
                                                             scene: str) -> None:
    recorded = scenes(room, scene)
    errors: list[float] = []
    for camera_a, camera_b in recorded.units:
        a, b = recorded.views[camera_a], recorded.views[camera_b]
        pairs = match_stereo(a.detected, b.detected, *a.camera, *b.camera)
        assert pairs.dtype.kind == "i" and pairs.shape[1] == 2
        dots_a, dots_b = a.nearest[pairs[:, 0]], b.nearest[pairs[:, 1]]
        assert (dots_a == dots_b).all(), (camera_a, camera_b, dots_a, dots_b)
        # Dots seen by both are dropped only when another dot lies on the same epipolar line.
        common = np.intersect1d(a.nearest, b.nearest).size
        assert len(pairs) >= 0.75 * common, (camera_a, camera_b, len(pairs), common)
        points = triangulate(a.detected[pairs[:, 0]], b.detected[pairs[:, 1]], *a.camera,
                             *b.camera)
        errors.extend(np.linalg.norm(points - recorded.fiducials[dots_a], axis=1).tolist())
    assert len(errors) >= 8, errors
    assert float(np.median(errors)) <= TRIANGULATION_MEDIAN_MM, errors
    assert max(errors) <= TRIANGULATION_MAX_MM, errors


# --- one view and the surface around the dot ----------------------------------------------------


def _true_depth_points(recorded: Scene, view: View) -> F64:
    """The exact surface point behind every pixel, NaN on the dots and a pixel around them
    (where the fringe reconstruction has no points either) and where no surface is."""
    camera = recorded.room.renderer.cameras[view.camera_id]
    height, width = camera.shape
    hits = build_scene(truth_scene(recorded.truth)).scene.cast(camera.centre,
                                                               camera.rays().reshape(-1, 3))
    points = hits.points.reshape(height, width, 3).copy()
    on_dot = (np.abs(hits.albedo - FIDUCIAL_PAINT) < 1e-9).reshape(height, width)
    masked = cv2.dilate(on_dot.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    points[masked | ~np.isfinite(hits.t).reshape(height, width)] = np.nan
    return points


@pytest.mark.parametrize(("room", "scene"), [("default", "eye_phantom_1"), ("wide", "pyramid"),
                                             ("horizontal", "eye_phantom_2")],
                         ids=["default-eye_phantom_1", "wide-pyramid", "horizontal-eye_phantom_2"])
def test_surface_position_at_detected_dots_on_the_exact_surface(scenes: Any, room: str,
                                                                 scene: str) -> None:
    recorded = scenes(room, scene)
    view = recorded.views[recorded.units[0][0]]
    depth_points = _true_depth_points(recorded, view)
    truth = recorded.fiducials[view.nearest]
    quadratic = surface_position(view.detected, depth_points, *view.camera, degree=2)
    plane = surface_position(view.detected, depth_points, *view.camera)
    known = np.isfinite(quadratic).all(axis=1)
    assert known.sum() >= 0.8 * known.size, quadratic
    quadratic_error = np.linalg.norm(quadratic[known] - truth[known], axis=1)
    # What is left is the detection's error carried along the ray onto the surface.
    assert float(np.median(quadratic_error)) < 0.03, quadratic_error
    assert float(np.max(quadratic_error)) < 0.08, quadratic_error
    # A plane cuts under a curved surface by about r²/2ρ (ring radius r ≈ 1–2 mm on a 12 mm
    # sphere or the pyramid's cone): a bias of up to a few tenths of a millimetre, never more.
    plane_known = np.isfinite(plane).all(axis=1)
    plane_error = np.linalg.norm(plane[plane_known] - truth[plane_known], axis=1)
    assert plane_known.sum() >= 0.6 * plane_known.size, plane
    assert float(np.max(plane_error)) < 0.4, plane_error


def _camera(name: str = "S1") -> tuple[F64, F64, F64, F64, F64]:
    """A true camera of the default room: K, dist, R, T and its centre."""
    cam = SimRoom(load_room(None)).renderer.cameras[name]
    return cam.K, cam.dist, cam.R, cam.T, cam.centre


def _rays(name: str = "S1") -> F64:
    return np.asarray(SimRoom(load_room(None)).renderer.cameras[name].rays(), dtype=np.float64)


def _project(points: F64, K: F64, dist: F64, R: F64, T: F64) -> F64:
    rvec, _ = cv2.Rodrigues(R)
    uv, _ = cv2.projectPoints(points.reshape(-1, 1, 3), rvec, T, K, dist)
    return np.asarray(uv.reshape(-1, 2), dtype=np.float64)


def test_surface_position_is_exact_on_a_tilted_plane() -> None:
    K, dist, R, T, centre = _camera()
    rays = _rays()
    # A plane through (1, −2, 3) mm tilted about 30° and 20°, every pixel's ray cut by it.
    normal = np.array([math.sin(math.radians(20)), math.sin(math.radians(30)), 1.0])
    normal /= np.linalg.norm(normal)
    anchor = np.array([1.0, -2.0, 3.0])
    depth = (normal @ (anchor - centre)) / (rays @ normal)
    depth_points = centre + depth[..., None] * rays
    # Dots anywhere on the plane, also at sub-pixel positions and near the lens' edge.
    rng = np.random.default_rng(3)
    in_plane = np.linalg.svd(normal[None, :])[2][1:]
    dots = anchor + rng.uniform(-12.0, 12.0, (25, 2)) @ in_plane
    uv = _project(dots, K, dist, R, T)
    assert (uv[:, 0] > 20).all() and (uv[:, 0] < 620).all()
    for degree in (1, 2):
        found = surface_position(uv, depth_points, K, dist, R, T, degree=degree)
        assert np.abs(found - dots).max() < 1e-6, (degree, np.abs(found - dots).max())


def test_quadratic_surface_removes_the_plane_bias_on_a_sphere() -> None:
    K, dist, R, T, centre = _camera()
    rays = _rays()
    sphere_centre, radius = np.array([0.0, 0.0, -10.0]), 12.0
    # Nearest intersection of every ray with the sphere.
    offset = centre - sphere_centre
    b = rays @ offset
    disc = b**2 - (offset @ offset - radius**2)
    depth = -b - np.sqrt(np.where(disc >= 0, disc, np.nan))
    depth_points = centre + depth[..., None] * rays
    # Dots facing S1 (the first), then further round the sphere (cos of the view 0.52–0.99).
    polar = np.radians([27.0, 0.0, 20.0, 45.0, 30.0, 35.0, 35.0])
    azimuth = np.radians([27.0, 0.0, 40.0, 20.0, 90.0, 290.0, 160.0])
    dots = sphere_centre + radius * np.stack([np.sin(polar) * np.cos(azimuth),
                                              np.sin(polar) * np.sin(azimuth),
                                              np.cos(polar)], axis=1)
    uv = _project(dots, K, dist, R, T)
    plane = surface_position(uv, depth_points, K, dist, R, T)
    quadratic = surface_position(uv, depth_points, K, dist, R, T, degree=2)
    assert np.isfinite(quadratic).all(), quadratic
    assert np.linalg.norm(quadratic - dots, axis=1).max() < 0.005, quadratic - dots
    # Face on, the ring of 8–16 px (0.85–1.7 mm at 0.106 mm/px) lies ⟨r²⟩/2ρ below the cap:
    # the plane through it cuts the ray that much short. Obliquely the ring stretches on the
    # surface and the bias grows, until the plane no longer fits the ring (NaN).
    mm_per_px = float(np.linalg.norm(centre - dots[0])) / K[0, 0]
    mean_r2 = 0.5 * ((8.0 * mm_per_px) ** 2 + (16.0 * mm_per_px) ** 2)
    plane_error = np.linalg.norm(plane - dots, axis=1)
    assert plane_error[0] == pytest.approx(mean_r2 / (2 * radius), rel=0.1), plane_error
    known = np.isfinite(plane_error)
    assert known.sum() >= 5 and (plane_error[known] >= 0.9 * plane_error[0]).all(), plane_error


def test_surface_position_is_nan_where_the_ring_does_not_describe_the_surface() -> None:
    K, dist, R, T, centre = _camera()
    rays = _rays()
    depth = (0.0 - centre[2]) / rays[..., 2]
    depth_points = centre + depth[..., None] * rays
    uv = np.array([[200.0, 150.0], [400.0, 150.0], [320.0, 350.0], [100.5, 400.25]])
    cut = depth_points.copy()
    cut[120:180, 200:230] = np.nan  # the first dot sees points on its left only
    cut[140:161, 390:411] = np.nan  # the second's ring is intact beyond 10 px
    step = cut.copy()
    step[350:, :] += np.array([0.0, 0.0, 1.0])  # a 1 mm step across the third dot
    found = surface_position(uv, step, K, dist, R, T)
    assert np.isnan(found[0]).all()  # one side only: not interpolated
    assert np.isfinite(found[1]).all()
    assert np.isnan(found[2]).all()  # two surfaces in one ring
    assert np.isfinite(found[3]).all()
    assert np.isnan(surface_position(uv[3:], cut, K, dist, R, T, ring_px=(0.0, 1.0),
                                     min_points=5)).all()  # too few points
    assert surface_position(np.zeros((0, 2)), cut, K, dist, R, T).shape == (0, 3)


# --- synthetic images: what the scenes cannot isolate ---------------------------------------------


def _synthetic(dots: list[tuple[float, float, float]], *, shape: tuple[int, int] = (160, 200),
               period: float = 22.0, angle_deg: float = 0.0, phase: float = 0.0,
               paint: Callable[[F64, F64], F64] | None = None, noise: float = 0.8,
               seed: int = 0, fringe_centre: tuple[float, float] | None = None) -> F64:
    """Fringes ``40 + 30·cos`` with dots ``(u, v, radius)`` of albedo 0.08, each pixel the mean
    of 8 × 8 samples, blurred (σ 0.7 px) and noisy like the simulated camera. The fringes are
    straight along ``angle_deg``, or circles about ``fringe_centre``."""
    s = 8
    v, u = (np.mgrid[0:shape[0] * s, 0:shape[1] * s] + 0.5) / s - 0.5
    angle = math.radians(angle_deg)
    if fringe_centre is None:
        across = u * math.cos(angle) + v * math.sin(angle)
    else:
        across = np.hypot(u - fringe_centre[0], v - fringe_centre[1])
    light = 40.0 + 30.0 * np.cos(2 * math.pi * across / period + phase)
    albedo = np.ones_like(u) if paint is None else paint(u, v)
    for du, dv, radius in dots:
        albedo = np.where(np.hypot(u - du, v - dv) <= radius, 0.08 * albedo, albedo)
    image = (albedo * light).reshape(shape[0], s, shape[1], s).mean(axis=(1, 3))
    image = cv2.GaussianBlur(image, (0, 0), 0.7)
    return np.asarray(image + np.random.default_rng(seed).normal(0.0, noise, shape))


@pytest.mark.parametrize("angle_deg", [0.0, 35.0, 90.0])
def test_the_centre_does_not_follow_the_fringe_phase(angle_deg: float) -> None:
    # A plain centroid of the darkness (even against the exact unmarked image) moves by up to
    # 1.2 px with the fringe's phase under the dot (measured); against the inpainted fringe
    # what is left (≤ 0.12 px measured, noise-free alike) is the camera blur mixing the dot's
    # edge with the fringe's slope.
    errors = []
    for k in range(8):
        centre = (97.0 + 0.37 * k, 78.0 + 0.21 * k)
        image = _synthetic([(*centre, 4.7)], angle_deg=angle_deg, phase=k * math.pi / 4, seed=k)
        found = detect_fiducials(image, 22.0)
        assert found.shape == (1, 2), (k, found)
        errors.append(float(np.hypot(*(found[0] - centre))))
    assert max(errors) < 0.15, errors


def test_the_inpainted_fringe_follows_a_curved_fringe() -> None:
    # Circular fringes of radius 90 px (four periods): along a straight chord of ±16 px the
    # fringe falls away by 1.4 px, 0.4 rad of phase; the path's bend follows it. Measured
    # ≤ 0.15 px; a straight path leaves up to 0.8 px or drops dots.
    errors = []
    for k in range(6):
        centre = (100.0 + 0.3 * k, 80.0 + 0.17 * k)
        image = _synthetic([(*centre, 4.7)], fringe_centre=(centre[0] - 90.0, centre[1]),
                           phase=k * math.pi / 3, seed=k)
        found = detect_fiducials(image, 22.0)
        assert found.shape == (1, 2), (k, found)
        errors.append(float(np.hypot(*(found[0] - centre))))
    assert max(errors) < 0.2, errors


def test_dots_cut_by_the_border_are_not_reported() -> None:
    # Vertical fringes: the fringe is inpainted along the columns. Dots cut by each border,
    # one too near the top to see the fringe above it, and one wholly inside.
    dots = [(2.0, 80.0, 4.7), (197.5, 60.0, 4.7), (100.0, 1.5, 4.7), (60.0, 158.0, 4.7),
            (150.0, 9.0, 4.7), (100.0, 90.0, 4.7)]
    found = detect_fiducials(_synthetic(dots), 22.0)
    assert found.shape == (1, 2), found
    assert np.hypot(*(found[0] - (100.0, 90.0))) < 0.1, found


def test_dark_features_that_are_no_dots_are_not_reported() -> None:
    def paint(u: F64, v: F64) -> F64:
        albedo = np.ones_like(u)
        albedo[np.hypot(u - 60.0, v - 60.0) <= 30.0] = 0.15  # a painted iris
        albedo[(u > 150) & (np.abs(v - 40.0) < 0.12 * (u - 150))] = 0.05  # a shadow's tip
        albedo[v > 130] = 0.0  # the dark room below an edge
        albedo[(np.abs(u - 120.0) < 3.0) & (v > 60) & (v < 120)] = 0.1  # a thin dark line
        return albedo

    found = detect_fiducials(_synthetic([(170.0, 100.0, 4.7)], paint=paint), 22.0)
    assert found.shape == (1, 2), found
    assert np.hypot(*(found[0] - (170.0, 100.0))) < 0.1, found
    assert detect_fiducials(_synthetic([]), 22.0).shape == (0, 2)


@pytest.mark.slow
def test_noise_makes_no_dots() -> None:
    # σ = 5 DN on fringes of 10–70 DN (the simulated camera: ≈ 1.3–2 DN): clusters of dark
    # noise pass the closings but not the significance test; the dot still does.
    for seed in range(4):
        found = detect_fiducials(_synthetic([(100.0, 80.0, 4.7)], noise=5.0, seed=seed,
                                            shape=(200, 260)), 22.0)
        assert found.shape == (1, 2), (seed, found)
        assert np.hypot(*(found[0] - (100.0, 80.0))) < 0.6, found
    noise = np.random.default_rng(1).integers(0, 4096, (512, 640)).astype(np.uint16)
    assert detect_fiducials(noise, 24.0).shape == (0, 2)


def test_dots_outside_the_size_range_are_not_reported() -> None:
    image = _synthetic([(50.0, 50.0, 1.0), (100.0, 80.0, 4.7), (150.0, 100.0, 11.0)])
    found = detect_fiducials(image, 22.0, min_radius_px=2.0, max_radius_px=8.0)
    assert found.shape == (1, 2) and np.hypot(*(found[0] - (100.0, 80.0))) < 0.1, found


# --- synthetic cameras: exact geometry -----------------------------------------------------------


def _stereo_pair() -> tuple[tuple[F64, F64, F64, F64], tuple[F64, F64, F64, F64]]:
    """Two cameras of the default room (S1 above, S2 below the left projector), true values."""
    room = SimRoom(load_room(None))
    a, b = room.renderer.cameras["S1"], room.renderer.cameras["S2"]
    return (a.K, a.dist, a.R, a.T), (b.K, b.dist, b.R, b.T)


def test_triangulation_is_exact_on_exact_points() -> None:
    cam_a, cam_b = _stereo_pair()
    points = np.random.default_rng(5).uniform([-20, -15, -10], [20, 15, 25], (40, 3))
    found = triangulate(_project(points, *cam_a), _project(points, *cam_b), *cam_a, *cam_b)
    assert found.shape == (40, 3)
    assert np.abs(found - points).max() < 1e-6, np.abs(found - points).max()
    assert triangulate(np.zeros((0, 2)), np.zeros((0, 2)), *cam_a, *cam_b).shape == (0, 3)


def test_matching_pairs_true_partners_and_drops_ambiguous_ones() -> None:
    cam_a, cam_b = _stereo_pair()
    rng = np.random.default_rng(11)
    points = rng.uniform([-20, -15, -10], [20, 15, 15], (12, 3))
    uv_a = _project(points, *cam_a)
    uv_b = _project(points, *cam_b)
    # B lists its dots in another order, and sees one more that A does not: a point further
    # along A's ray through dot 0, which lands on dot 0's epipolar line in B.
    order = rng.permutation(len(points))
    centre_a = -cam_a[2].T @ cam_a[3]
    hidden = centre_a + 1.05 * (points[0] - centre_a)
    uv_b = np.vstack([uv_b[order], _project(hidden[None], *cam_b)])
    # A sees one dot whose partner B misses.
    uv_a = np.vstack([uv_a, _project(np.array([[5.0, 25.0, 0.0]]), *cam_a)])
    pairs = match_stereo(uv_a, uv_b, *cam_a, *cam_b)
    expected = {(int(order[j]), j) for j in range(len(order)) if order[j] != 0}
    assert {tuple(p) for p in pairs.tolist()} == expected
    assert (np.diff(pairs[:, 0]) > 0).all()
    # Exact points lie on their lines: a far tighter bound keeps every pair.
    assert len(match_stereo(uv_a, uv_b, *cam_a, *cam_b, max_epipolar_px=0.01)) == len(expected)
    assert match_stereo(np.zeros((0, 2)), uv_b, *cam_a, *cam_b).shape == (0, 2)


# --- validation -----------------------------------------------------------------------------------


def test_bad_detection_arguments_are_named() -> None:
    image = _synthetic([])
    cases: list[tuple[dict[str, Any], str]] = [
        ({"image": image[0]}, "image"),
        ({"image": np.full((40, 40), np.nan)}, "image"),
        ({"image": np.zeros((40, 40), dtype=bool)}, "image"),
        ({"period_px": 1.5}, "period_px"),
        ({"period_px": float("nan")}, "period_px"),
        ({"min_radius_px": 0.0}, "min_radius_px"),
        ({"max_radius_px": 1.0}, "max_radius_px"),
        ({"max_elongation": 0.5}, "max_elongation"),
    ]
    for change, name in cases:
        arguments: dict[str, Any] = {"image": image, "period_px": 22.0, **change}
        with pytest.raises(ValueError, match=name):
            detect_fiducials(**arguments)


def test_bad_geometry_arguments_are_named() -> None:
    cam_a, cam_b = _stereo_pair()
    uv = np.array([[320.0, 256.0]])
    with pytest.raises(ValueError, match="uv_a"):
        triangulate(uv[0], uv, *cam_a, *cam_b)
    with pytest.raises(ValueError, match="uv_a and uv_b"):
        triangulate(np.vstack([uv, uv]), uv, *cam_a, *cam_b)
    with pytest.raises(ValueError, match="K_b"):
        triangulate(uv, uv, *cam_a, np.eye(2), *cam_b[1:])
    with pytest.raises(ValueError, match="R_a"):
        match_stereo(uv, uv, cam_a[0], cam_a[1], 2 * cam_a[2], cam_a[3], *cam_b)
    with pytest.raises(ValueError, match="dist_a"):
        match_stereo(uv, uv, cam_a[0], np.zeros(3), *cam_a[2:], *cam_b)
    with pytest.raises(ValueError, match="max_epipolar_px"):
        match_stereo(uv, uv, *cam_a, *cam_b, max_epipolar_px=-1.0)
    with pytest.raises(ValueError, match="baseline"):
        match_stereo(uv, uv, *cam_a, *cam_a)
    depth_points = np.zeros((512, 640, 3))
    bad_surface_arguments: list[tuple[dict[str, Any], str]] = [
        ({"depth_points": np.zeros((512, 640))}, "depth_points"),
        ({"ring_px": (5.0, 3.0)}, "ring_px"),
        ({"ring_px": 5.0}, "ring_px"),
        ({"degree": 3}, "degree"),
        ({"min_points": 2}, "min_points"),
        ({"max_rms_mm": 0.0}, "max_rms_mm"),
        ({"T": np.zeros(2)}, "^T must"),
    ]
    for change, name in bad_surface_arguments:
        arguments: dict[str, Any] = {"uv": uv, "depth_points": depth_points, "K": cam_a[0],
                                     "dist": cam_a[1], "R": cam_a[2], "T": cam_a[3], **change}
        with pytest.raises(ValueError, match=name):
            surface_position(**arguments)
