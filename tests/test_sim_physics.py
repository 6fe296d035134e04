"""Physics of the simulated room, checked through its own forward model.

Every test renders (or casts) a scene and compares what comes out with what the geometry and the
configured sensor say must come out, measured independently of the renderer's own formulas:
OpenCV's projection for the camera model, a fitted period for the grating, OpenCV's chessboard
detector for edges, a ray march for shadows, frame statistics for the noise. Each would fail if
the simulator got its physics wrong, not merely its shapes.

Renders of still scenes are cached per room, so rooms are module-scoped and shared.
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
import pytest
from scipy import ndimage, optimize

from eyeserver.calibration.chessboard import board_points, detect_chessboard
from eyeserver.core.clock import ManualClock
from eyeserver.core.types import F64
from eyeserver.hardware.sim import motion as motion_module
from eyeserver.hardware.sim.config import RoomConfig, room_from_dict
from eyeserver.hardware.sim.drivers import SimCamera, build_sim_rig
from eyeserver.hardware.sim.geometry import RayHits, pose_matrix
from eyeserver.hardware.sim.motion import EyeMotion, MotionSpec, ScriptEvent
from eyeserver.hardware.sim.optics import CameraModel
from eyeserver.hardware.sim.render import Components
from eyeserver.hardware.sim.room import SimRoom
from eyeserver.hardware.sim.scenes import (
    BOARD_BLACK,
    BOARD_WHITE,
    SCLERA,
    SKIN,
    EyeSpec,
    SceneSpec,
    _cap_bound,
    build_scene,
    scene_truth,
)
from eyeserver.hardware.sim.truth import device_truth

# A rig unlike the default one in every respect the camera model has: distance, azimuth,
# elevation, roll, a look-at point off the origin, strong radial and tangential distortion with
# k2 and k3, and an offset principal point.
ODD_RIG: dict[str, Any] = {"units": [{
    "id": "left",
    "projector": {"id": "P1", "distance_mm": 180.0, "azimuth_deg": 50.0, "elevation_deg": -5.0},
    "cameras": [{"id": "S1", "distance_mm": 300.0, "azimuth_deg": -35.0, "elevation_deg": 20.0,
                 "roll_deg": 15.0, "look_at_mm": (2.0, -1.0, 3.0),
                 "distortion": (-0.25, 0.12, 0.002, -0.0015, 0.02),
                 "principal_offset_px": (12.5, -8.0)}],
}]}


@pytest.fixture(scope="module")
def room() -> SimRoom:
    """The default room, shared so that its renders are cached across tests."""
    return SimRoom()


@pytest.fixture(scope="module")
def odd_room() -> SimRoom:
    return SimRoom(room_from_dict(ODD_RIG))


def _components(room: SimRoom, spec: SceneSpec, camera_id: str,
                projectors: tuple[str, ...] = ()) -> Components:
    room.set_scene(spec)
    return room.components(camera_id, projectors=projectors)


def _cast_image(room: SimRoom, spec: SceneSpec, camera_id: str) -> tuple[RayHits, list[str]]:
    """Every pixel centre's ray cast into ``spec`` (what the camera sees there)."""
    cam = room.renderer.cameras[camera_id]
    scene = build_scene(spec).scene
    return scene.cast(cam.centre, cam.rays().reshape(-1, 3)), scene.labels


def _expected_vignetting(cam: CameraModel) -> npt.NDArray[np.float64]:
    """docs/design.md §3's fall-off: 1 on the principal point, 1 − v at the farthest corner,
    quadratic."""
    h, w = cam.shape
    cx, cy = cam.K[0, 2], cam.K[1, 2]
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    r2 = (uu - cx) ** 2 + (vv - cy) ** 2
    corner2 = max((x - cx) ** 2 + (y - cy) ** 2 for x in (0.0, w - 1.0) for y in (0.0, h - 1.0))
    return np.asarray(1.0 - cam.config.vignetting * r2 / corner2)


# --- 1. camera rays against OpenCV's projection -----------------------------------------------


def _sample_pixels(h: int, w: int, n: int, seed: int) -> tuple[npt.NDArray[np.int64], ...]:
    rng = np.random.default_rng(seed)
    rows = np.r_[0, 0, h - 1, h - 1, h // 2, 0, h - 1, h // 2, h // 2, rng.integers(0, h, n)]
    cols = np.r_[0, w - 1, 0, w - 1, w // 2, w // 2, w // 2, 0, w - 1, rng.integers(0, w, n)]
    return rows, cols


RAY_SCENES = [
    # The calibration plate through the origin, normal to Z (only its 45 mm disc is hit).
    SceneSpec(kind="plate"),
    # The large reference plane, moved and tilted so that it fills every camera's view.
    SceneSpec(kind="reference", position_mm=(5.0, -3.0, 8.0), rotation_deg=(20.0, -15.0, 30.0)),
]


@pytest.mark.parametrize("spec", RAY_SCENES, ids=["plate", "tilted-reference"])
@pytest.mark.parametrize(("room_name", "camera_id"), [
    ("default", "S1"), ("default", "S2"), ("default", "S3"), ("default", "S4"), ("odd", "S1")])
def test_pixel_rays_meet_the_plate_where_opencv_projects(
        request: pytest.FixtureRequest, room_name: str, camera_id: str, spec: SceneSpec) -> None:
    sim = request.getfixturevalue("room" if room_name == "default" else "odd_room")
    cam = sim.renderer.cameras[camera_id]
    h, w = cam.shape
    rows, cols = _sample_pixels(h, w, 400, seed=0)
    built = build_scene(spec)
    hits = built.scene.cast(cam.centre, cam.rays()[rows, cols])
    hit = np.isfinite(hits.t)
    if spec.kind == "reference":
        assert hit.all(), "the reference plane must fill the image, corners included"
    else:
        assert hit.mean() > 0.5 and hit[4], "the plate must cover the image centre"
    # The hit points lie on the surface ...
    assert np.max(built.scene.distance(hits.points[hit])) < 1e-9
    # ... and OpenCV, with the camera's own K, distortion and [R|T], sends them back to the pixel.
    rvec, _ = cv2.Rodrigues(cam.R)
    uv, _ = cv2.projectPoints(hits.points[hit].reshape(-1, 1, 3), rvec, cam.T, cam.K, cam.dist)
    error = np.hypot(uv[:, 0, 0] - cols[hit], uv[:, 0, 1] - rows[hit])
    assert error.max() < 1e-6, f"worst round trip {error.max():.2e} px"


@pytest.mark.parametrize("room_name", ["default", "odd"])
def test_subpixel_rays_meet_the_plate_where_opencv_projects(
        request: pytest.FixtureRequest, room_name: str) -> None:
    """Sub-pixel rays (the supersampler's) land where OpenCV says, pixel borders included."""
    sim = request.getfixturevalue("room" if room_name == "default" else "odd_room")
    cam = sim.renderer.cameras["S1"]
    h, w = cam.shape
    rng = np.random.default_rng(7)
    # Every corner pixel and 500 others, each at its own corners and 12 random offsets.
    rows = np.r_[0, 0, h - 1, h - 1, rng.integers(0, h, 500)]
    cols = np.r_[0, w - 1, 0, w - 1, rng.integers(0, w, 500)]
    offsets = np.r_[[[-0.5, -0.5], [0.5, -0.5], [-0.5, 0.5], [0.5, 0.5]],
                    rng.uniform(-0.5, 0.5, (12, 2))]
    u = (cols[:, None] + offsets[None, :, 0]).ravel()
    v = (rows[:, None] + offsets[None, :, 1]).ravel()
    scene = build_scene(RAY_SCENES[1]).scene
    exact = cam.project(scene.cast(cam.centre, cam.rays_for_pixels(u, v)).points)
    assert np.max(np.hypot(exact[:, 0] - u, exact[:, 1] - v)) < 1e-6
    # The supersampler's expansion about each pixel: measured 5e-7 px at worst (a corner
    # pixel's corner); a first-order one is 1e-4 to 2.4e-4 px off. An edge within 1e-4 px is
    # exact for any detector; the bound is tighter, to catch a lost term.
    table = cam.project(scene.cast(cam.centre, cam.rays_at_subpixels(rows, cols, offsets)).points)
    assert np.max(np.hypot(table[:, 0] - u, table[:, 1] - v)) < 1e-5


# --- 2. the fringe period ---------------------------------------------------------------------


def _fit_period(s: F64, y: F64, lo: float, hi: float) -> float:
    """Period of the sinusoid (plus a linear trend) that fits ``y(s)`` best, least squares."""
    def rss(period: float) -> float:
        phase = 2 * math.pi * s / period
        design = np.stack([np.ones_like(s), s, np.cos(phase), np.sin(phase)], axis=1)
        coef, *_ = np.linalg.lstsq(design, y, rcond=None)
        residual = y - design @ coef
        return float(residual @ residual)
    candidates = np.linspace(lo, hi, 401)
    best = int(np.argmin([rss(p) for p in candidates]))
    step = candidates[1] - candidates[0]
    result = optimize.minimize_scalar(rss, bounds=(candidates[best] - step,
                                                   candidates[best] + step),
                                      method="bounded", options={"xatol": 1e-7})
    return float(result.x)


@pytest.fixture(scope="module")
def fine_room() -> SimRoom:
    return SimRoom(room_from_dict({"units": [{"id": "left",
                                               "projector": {"id": "P1", "period_mm": 1.5}}]}))


@pytest.mark.parametrize(("room_name", "projector_id", "camera_id", "period_mm"), [
    ("default", "P1", "S1", 2.0), ("default", "P2", "S4", 2.0), ("fine", "P1", "S1", 1.5)])
def test_fringe_period_on_the_plane_normal_to_the_projector_axis(
        request: pytest.FixtureRequest, room_name: str, projector_id: str, camera_id: str,
        period_mm: float) -> None:
    sim = request.getfixturevalue("room" if room_name == "default" else "fine_room")
    projector = device_truth(sim)["projectors"][projector_id]
    R_proj = np.asarray(projector["R"])
    centre = np.asarray(projector["centre_mm"])
    axis = R_proj[2]  # the projector's optical axis (its z), pointing at the look-at point
    # Turn the plate (local normal +z) to face the projector: n = Rz·Ry·Rx·ẑ with rz = 0.
    normal = -axis
    rotation = (-math.degrees(math.asin(normal[1])),
                math.degrees(math.atan2(normal[0], normal[2])), 0.0)
    spec = SceneSpec(kind="plate", position_mm=(0.0, 0.0, 0.0), rotation_deg=rotation)
    built = build_scene(spec)
    along_axis = built.scene.cast(centre, axis[None, :])
    assert along_axis.points[0] == pytest.approx([0.0, 0.0, 0.0], abs=1e-9)
    assert abs(float(along_axis.normals[0] @ axis)) == pytest.approx(1.0, abs=1e-12)

    fringe = _components(sim, spec, camera_id, (projector_id,)).fringe[projector_id]
    cam = sim.renderer.cameras[camera_id]
    h, w = cam.shape
    row, cols = h // 2, np.arange(w // 2 - 120, w // 2 + 120)
    hits = built.scene.cast(cam.centre, cam.rays()[row, cols])
    assert np.isfinite(hits.t).all()
    # Vertical grating lines: the phase runs along the projector's x axis, which lies in the
    # plane; that in-plane coordinate of each pixel's hit point is the abscissa of the profile.
    across = hits.points @ R_proj[0]
    measured = _fit_period(across, fringe[row, cols].astype(np.float64), 1.0, 3.0)
    assert measured == pytest.approx(period_mm, rel=0.01), f"period {measured:.4f} mm"


# --- 3. chessboard corners --------------------------------------------------------------------

BOARD_COLS, BOARD_ROWS, BOARD_SQUARE_MM = 9, 6, 4.5
BOARD_POSES = [
    ((0.0, 0.0, 0.0), (20.0, 0.0, 0.0)),
    ((0.0, 0.0, 0.0), (0.0, -20.0, 0.0)),  # 45° from S1's line of sight
    # Nearly upside down (corner 0 at the image's bottom right), tilted, off the origin.
    ((2.0, -3.0, 4.0), (-20.0, 0.0, 170.0)),
]


@pytest.fixture(scope="module")
def board_room() -> SimRoom:
    sim = SimRoom()
    sim.set_room_lights(True)  # chessboards are filmed under the room lights
    return sim


def _board_truth(cam: CameraModel, position: tuple[float, float, float],
                 rotation: tuple[float, float, float]) -> F64:
    local = board_points(BOARD_COLS, BOARD_ROWS, BOARD_SQUARE_MM)
    return cam.project(local @ pose_matrix(rotation).T + np.asarray(position))


@pytest.mark.parametrize(("position", "rotation"), BOARD_POSES,
                         ids=[f"rot{r[0]:g},{r[1]:g},{r[2]:g}" for _, r in BOARD_POSES])
def test_chessboard_corners_are_found_where_they_project(
        board_room: SimRoom, position: tuple[float, float, float],
        rotation: tuple[float, float, float]) -> None:
    spec = SceneSpec(kind="chessboard", position_mm=position, rotation_deg=rotation,
                     cols=BOARD_COLS, rows=BOARD_ROWS, square_mm=BOARD_SQUARE_MM)
    components = _components(board_room, spec, "S1")
    cam = board_room.renderer.cameras["S1"]
    truth = _board_truth(cam, position, rotation)
    cols, rows = BOARD_COLS, BOARD_ROWS

    # Noise-free: the room lights on a still board, quantised as the sensor would.
    light = board_room.config.lighting.room_light_dn
    clean = np.clip(np.rint(components.ambient * light), 0, 255).astype(np.uint8)
    corners = detect_chessboard(clean, cols, rows)
    assert corners is not None
    # Errors are hundredths of a pixel only if the order is FORMATS.md's (corner 0 at the
    # board's −X, +Y corner); any other order puts corners a square (≈ 40 px) away.
    error = np.hypot(*(corners - truth).T)
    assert error.max() <= 0.1, f"noise-free: worst corner {error.max():.3f} px"

    # With the sensor's noise, a few frames.
    noisy = []
    for seed in range(4):
        image = board_room.render("S1", t_s=0.0, projectors={}, exposure_us=10_000.0,
                                  gain_db=0.0, rng=np.random.default_rng([11, seed]))
        found = detect_chessboard(image, cols, rows)
        assert found is not None
        noisy.append(np.hypot(*(found - truth).T))
    noisy_error = np.concatenate(noisy)
    assert np.median(noisy_error) <= 0.05, f"noisy median {np.median(noisy_error):.3f} px"
    assert noisy_error.max() <= 0.15, f"noisy worst corner {noisy_error.max():.3f} px"


def test_chessboard_squares_have_their_albedo(board_room: SimRoom) -> None:
    """Square centres: room light × albedo × vignetting (the contrast a detector works with)."""
    position, rotation = BOARD_POSES[0]
    spec = SceneSpec(kind="chessboard", position_mm=position, rotation_deg=rotation,
                     cols=BOARD_COLS, rows=BOARD_ROWS, square_mm=BOARD_SQUARE_MM)
    ambient = _components(board_room, spec, "S1").ambient
    cam = board_room.renderer.cameras["S1"]
    cols, rows, s = BOARD_COLS, BOARD_ROWS, BOARD_SQUARE_MM
    a_grid, b_grid = np.meshgrid(np.arange(cols + 1), np.arange(rows + 1))
    a, b = a_grid.ravel(), b_grid.ravel()
    # Square (a, b) counted from the −X, +Y corner along +X and −Y; black when a + b is even.
    local = np.stack([(a + 0.5 - (cols + 1) / 2) * s, ((rows + 1) / 2 - b - 0.5) * s,
                      np.zeros(a.size)], axis=1)
    uv = cam.project(local @ pose_matrix(rotation).T + np.asarray(position))
    j, i = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
    albedo = np.where((a + b) % 2 == 0, BOARD_BLACK, BOARD_WHITE)
    expected = albedo * _expected_vignetting(cam)[i, j]
    np.testing.assert_allclose(ambient[i, j], expected, rtol=0.01)


# --- 4. shadows -------------------------------------------------------------------------------

WEDGE_HALF_WIDTH, WEDGE_HEIGHT, WEDGE_HALF_LENGTH = 10.0, 10.0, 15.0  # the wedge phantom, mm


@pytest.fixture(scope="module")
def flood_room() -> SimRoom:
    # P1 with a grating so coarse that the whole field lies on one bright fringe: dark then can
    # only mean shadow, not a dark fringe.
    return SimRoom(room_from_dict({"units": [
        {"id": "left", "projector": {"id": "P1", "period_mm": 1e4}}, {"id": "right"}]}))


def _in_wedge(q: F64) -> npt.NDArray[np.bool_]:
    """Strictly inside the wedge: on the base, under both sloping faces, between the ends."""
    return ((q[:, 2] > 1e-9) & (np.abs(q[:, 1]) < WEDGE_HALF_LENGTH)
            & (q[:, 2] < WEDGE_HEIGHT * (1 - np.abs(q[:, 0]) / WEDGE_HALF_WIDTH)))


def _marched_shadow(points_local: F64, light_local: F64, step: float = 0.02) -> npt.NDArray[
        np.bool_]:
    """Whether the segment from each point to the light passes through the wedge (ray march)."""
    to_light = light_local - points_local
    to_light /= np.linalg.norm(to_light, axis=1, keepdims=True)
    # Only the stretch below the ridge's height can be inside the wedge, and only points whose
    # stretch can reach the wedge's footprint need marching.
    reach = WEDGE_HEIGHT / np.maximum(to_light[:, 2], 1e-9)
    outside_x = np.maximum(np.abs(points_local[:, 0]) - WEDGE_HALF_WIDTH, 0.0)
    outside_y = np.maximum(np.abs(points_local[:, 1]) - WEDGE_HALF_LENGTH, 0.0)
    travel = reach * np.hypot(to_light[:, 0], to_light[:, 1])
    candidates = np.flatnonzero(np.hypot(outside_x, outside_y) <= travel + step)
    shadow = np.zeros(points_local.shape[0], dtype=bool)
    start, direction, limit = (points_local[candidates], to_light[candidates],
                               reach[candidates])
    hit = np.zeros(candidates.size, dtype=bool)
    for s in np.arange(step, float(limit.max(initial=0.0)) + step, step):
        live = np.flatnonzero((s <= limit) & ~hit)
        if not live.size:
            break
        hit[live] = _in_wedge(start[live] + s * direction[live])
    shadow[candidates] = hit
    return shadow


@pytest.mark.slow
@pytest.mark.parametrize("rotation", [(0.0, 0.0, 90.0), (10.0, -15.0, 60.0)])
def test_wedge_shadow_falls_where_geometry_says(flood_room: SimRoom,
                                                rotation: tuple[float, float, float]) -> None:
    spec = SceneSpec(kind="wedge", rotation_deg=rotation)
    camera_id = "S3"  # on the −X side, facing the shadow
    fringe = _components(flood_room, spec, camera_id, ("P1",)).fringe["P1"]
    h, w = fringe.shape
    hits, labels = _cast_image(flood_room, spec, camera_id)
    base = (hits.label == labels.index("base")).reshape(h, w)

    R, t = pose_matrix(rotation), np.asarray(spec.position)
    light = flood_room.renderer.projectors["P1"].centre
    on_base = base.ravel()
    geometric = np.zeros(h * w, dtype=bool)
    geometric[on_base] = _marched_shadow((hits.points[on_base] - t) @ R, (light - t) @ R)
    geometric = geometric.reshape(h, w)

    # Rendered dark: under a tenth of the plate's fringe amplitude per unit albedo (lit white
    # is ≈ 45–60 DN; the dark fiducial dots are lit too, hence per unit albedo).
    per_albedo = fringe / np.maximum(hits.albedo.reshape(h, w), 1e-6)
    rendered = per_albedo < 0.1 * flood_room.config.units[0].projector.fringe_pp_dn

    near_shadow_edge = (ndimage.binary_dilation(geometric, iterations=2)
                        & ndimage.binary_dilation(~geometric, iterations=2))
    judged = ndimage.binary_erosion(base, iterations=2) & ~near_shadow_edge
    agreement = float(np.mean(geometric[judged] == rendered[judged]))
    assert agreement >= 0.99, f"render and ray march agree on {agreement:.2%} of the base"
    shadow = judged & geometric
    assert shadow.sum() >= 2000, f"only {shadow.sum()} shadow pixels"
    # Each way, so that a small shadow cannot hide in the overall figure.
    assert np.mean(rendered[shadow]) >= 0.99
    assert np.mean(~rendered[judged & ~geometric]) >= 0.99
    # P1 stands at +X: the shadow falls beyond the wedge on the −X side.
    shadow_x = hits.points.reshape(h, w, 3)[judged & rendered][:, 0]
    assert np.all(shadow_x < float(t[0]))


# --- 5. noise and mean levels -----------------------------------------------------------------

FLAT = SceneSpec(kind="reference", position_mm=(0.0, 0.0, 0.0))  # white, fills the image


@pytest.fixture(scope="module")
def deep_room() -> SimRoom:
    return SimRoom(room_from_dict({"units": [{"id": "left",
                                               "cameras": [{"id": "S1", "bit_depth": 12}]}]}))


@pytest.mark.parametrize(("room_name", "gain_db"), [("8-bit", 0.0), ("8-bit", 6.0),
                                                    ("12-bit", 0.0)])
def test_temporal_noise_follows_the_sensor_model(request: pytest.FixtureRequest, room_name: str,
                                                 gain_db: float) -> None:
    sim = request.getfixturevalue("room" if room_name == "8-bit" else "deep_room")
    sim.set_room_lights(True)
    try:
        _components(sim, FLAT, "S1")
        cfg = sim.renderer.cameras["S1"].config
        h, w = cfg.height, cfg.width
        gain = 10 ** (gain_db / 20)
        max_dn = 2**cfg.bit_depth - 1
        patch = (slice(h // 2 - 100, h // 2 + 100), slice(w // 2 - 100, w // 2 + 100))
        means, variances = [], []
        # Exposures from ≈ 13 to ≈ 200 DN (8-bit scale), clear of the floor and the full well.
        for level, fraction in enumerate((0.08, 0.3, 0.6, 0.9, 1.2)):
            exposure = fraction * sim.config.lighting.exposure_ref_us / gain
            frames = np.stack([
                sim.render("S1", t_s=0.0, projectors={}, exposure_us=exposure, gain_db=gain_db,
                           rng=np.random.default_rng([5, level, k]))[patch]
                for k in range(16)]).astype(np.float64)
            means.append(frames.mean(axis=0).ravel())
            variances.append(frames.var(axis=0, ddof=1).ravel())
    finally:
        sim.set_room_lights(False)
    slope, intercept = np.polyfit(np.concatenate(means), np.concatenate(variances), 1)
    # Shot noise: var = mean · (DN per electron); read noise (1.2 DN on the 8-bit scale) and
    # the quantisation's 1/12 DN² add a floor.
    assert slope == pytest.approx(gain * max_dn / cfg.full_well_e, rel=0.05)
    expected_floor = (cfg.read_noise_dn * max_dn / 255) ** 2 + 1 / 12
    assert intercept == pytest.approx(expected_floor, rel=0.2)


@pytest.mark.parametrize("room_lights", [True, False])
def test_flat_field_level_is_light_times_albedo_times_vignetting(room: SimRoom,
                                                                 room_lights: bool) -> None:
    lighting = room.config.lighting
    light_dn = lighting.room_light_dn if room_lights else lighting.ambient_dn
    components = _components(room, FLAT, "S1")
    cam = room.renderer.cameras["S1"]
    expected = light_dn * 1.0 * _expected_vignetting(cam)  # the reference plane is white
    np.testing.assert_allclose(components.ambient * light_dn, expected, rtol=2e-3)
    room.set_room_lights(room_lights)
    try:
        frames = np.stack([room.render("S1", t_s=0.0, projectors={}, exposure_us=10_000.0,
                                       gain_db=0.0, rng=np.random.default_rng([9, k]))
                           for k in range(8)]).astype(np.float64)
    finally:
        room.set_room_lights(False)
    # Rounding and Gaussian noise are unbiased: the frame mean sits on the expected level, in
    # the centre and in the corners alike (blocks of 32 × 32 px, 8 frames: σ ≤ 0.035 DN).
    block_mean = frames.mean(axis=0).reshape(16, 32, 20, 32).mean(axis=(1, 3))
    block_expected = expected.reshape(16, 32, 20, 32).mean(axis=(1, 3))
    np.testing.assert_allclose(block_mean, block_expected, atol=0.15)


# --- 6. seeds ---------------------------------------------------------------------------------


def test_a_seed_reproduces_a_render(room: SimRoom) -> None:
    room.set_scene(SceneSpec(kind="plate"))

    def render(seed: int) -> npt.NDArray[Any]:
        return room.render("S1", t_s=0.0, projectors={"P1": 1.0}, exposure_us=10_000.0,
                           gain_db=0.0, rng=np.random.default_rng(seed))

    first, again, other = render(123), render(123), render(124)
    np.testing.assert_array_equal(first, again)
    assert not np.array_equal(first, other)
    # The two differ only by noise: about √2 times the per-pixel σ (≈ 2 DN here).
    assert 1.0 < np.std(first.astype(np.float64) - other) < 5.0


def _small_room(seed: int) -> RoomConfig:
    # A quarter of the resolution at four times the pixel pitch: the same view, rendered fast.
    cameras = [{"id": c, "width": 160, "height": 128, "pixel_um": 42.4} for c in ("S1", "S2")]
    return room_from_dict({"seed": seed, "units": [{"id": "left", "cameras": cameras}]})


def _acquire_images(seed: int) -> list[dict[str, npt.NDArray[Any]]]:
    sim = SimRoom(_small_room(seed))
    sim.set_scene(SceneSpec(kind="plate"))
    images = []
    with build_sim_rig(sim) as rig:
        for _ in range(2):
            (step,) = rig.acquire(["left"])
            images.append({c: f.image.copy() for c, f in step.frames.items()})
        images.append({c: f.image.copy() for c, f in rig.acquire_unlit().frames.items()})
    return images


def test_a_room_seed_reproduces_the_drivers_images() -> None:
    first, again, other = _acquire_images(3), _acquire_images(3), _acquire_images(4)
    for a, b, c in zip(first, again, other, strict=True):
        assert set(a) == {"S1", "S2"}
        for camera_id in a:
            np.testing.assert_array_equal(a[camera_id], b[camera_id])
            assert not np.array_equal(a[camera_id], c[camera_id])
    # Successive frames of one camera draw fresh noise.
    assert not np.array_equal(first[0]["S1"], first[1]["S1"])


# --- 7. vignetting and fringe contrast --------------------------------------------------------


def test_vignetting_is_a_quarter_at_the_corners(room: SimRoom) -> None:
    ambient = _components(room, FLAT, "S1").ambient
    h, w = ambient.shape
    centre = float(ambient[h // 2 - 1:h // 2 + 1, w // 2 - 1:w // 2 + 1].mean())
    assert centre == pytest.approx(1.0, abs=1e-3)
    for i, j in ((0, 0), (0, w - 1), (h - 1, 0), (h - 1, w - 1)):
        assert ambient[i, j] / centre == pytest.approx(0.75, abs=3e-3)


@pytest.mark.parametrize(("projector_id", "camera_id"), [("P1", "S1"), ("P2", "S4")])
def test_fringe_contrast_on_a_white_plate(room: SimRoom, projector_id: str,
                                          camera_id: str) -> None:
    components = _components(room, SceneSpec(kind="plate"), camera_id, (projector_id,))
    fringe = components.fringe[projector_id]
    h, w = fringe.shape
    window = fringe[h // 2 - 20:h // 2 + 21, w // 2 - 20:w // 2 + 21]  # two periods or more
    assert float(window.max() - window.min()) == pytest.approx(60.0, rel=0.1)
    background = components.ambient[h // 2, w // 2] * room.config.lighting.ambient_dn
    assert float(background) == pytest.approx(20.0, rel=0.05)


def test_fringe_contrast_on_the_sclera(room: SimRoom) -> None:
    """Sclera-like tissue swings ≈ 25 DN where a plate at the origin swings 60 (docs/design.md §3).

    On the eye the sclera is curved: where it turns towards the projector (45° off the Z axis)
    it catches more light than the plate does, where it turns away less (Lambert). The test
    measures the fringe on the sclera of the rendered eye and refers it back to the plate's
    illumination (incidence, distance and vignetting taken from the geometry of each pixel);
    it also checks that the raw swing follows Lambert on both sides of the globe.
    """
    spec = SceneSpec(kind="eye")
    fringe = _components(room, spec, "S1", ("P1",)).fringe["P1"].astype(np.float64)
    h, w = fringe.shape
    hits, labels = _cast_image(room, spec, "S1")
    sclera = (hits.label == labels.index("sclera")).reshape(h, w)
    assert sclera.sum() > 5000

    proj = room.renderer.projectors["P1"]
    points = hits.points.reshape(h, w, 3)
    to_proj = proj.centre - points
    distance = np.linalg.norm(to_proj, axis=2)
    normals = hits.normals.reshape(h, w, 3)
    cos_incidence = np.abs(np.einsum("ijk,ijk->ij", normals, to_proj)) / distance
    plate_cos = abs(float(proj.R[2, 2]))  # incidence of P1's axis on a plate normal to Z
    d0 = float(np.linalg.norm(proj.centre))
    gain = (cos_incidence / plate_cos) * (d0 / distance) ** 2 * _expected_vignetting(
        room.renderer.cameras["S1"])

    def local_swing(image: F64, where: npt.NDArray[np.bool_], size: int = 15) -> F64:
        high = ndimage.maximum_filter(np.where(where, image, -np.inf), size=size)
        low = ndimage.minimum_filter(np.where(where, image, np.inf), size=size)
        inside = ndimage.binary_erosion(where, structure=np.ones((size, size)))
        return np.asarray((high - low)[inside])

    # Referred to the plate's illumination (well-lit sclera only: grazing light amplifies blur).
    lit = sclera & (cos_incidence > 0.5)
    referred = np.median(local_swing(fringe / np.where(lit, gain, 1.0), lit))
    assert referred == pytest.approx(25.0, rel=0.25)
    # Raw: brighter on the side facing P1 (+X), nearly gone on the far side.
    facing = local_swing(fringe, sclera & (points[..., 0] > 0))
    away = local_swing(fringe, sclera & (points[..., 0] < 0), size=11)
    assert 25.0 < np.median(facing) < 25.0 / plate_cos * 1.05
    assert np.median(away) < 12.0


# --- 8. the eye -------------------------------------------------------------------------------


def test_corneal_apex_lies_near_z_plus_3_mm() -> None:
    spec = SceneSpec(kind="eye")
    built = build_scene(spec)
    # A ray down the beam axis meets the cornea first, at its apex.
    hits = built.scene.cast(np.array([0.0, 0.0, 100.0]), np.array([[0.0, 0.0, -1.0]]))
    assert built.scene.labels[hits.label[0]] == "cornea"
    apex = hits.points[0]
    assert apex[2] == pytest.approx(3.0, abs=0.5)
    # The truth's limbus plane and corneal radius put the apex at the same place.
    eye = scene_truth(spec)["eye"]
    half_limbus = spec.eye.limbus_diameter_mm / 2
    radius = eye["cornea_radius_mm"]
    sagitta = radius - math.sqrt(radius**2 - half_limbus**2)
    truth_apex = np.asarray(eye["limbus_centre_mm"]) + sagitta * np.asarray(eye["gaze"])
    np.testing.assert_allclose(apex, truth_apex, atol=1e-9)


@pytest.mark.parametrize("offset", [(0.0, 0.0), (0.4, -0.3)])
def test_a_decentred_limbus_is_drawn_where_its_truth_says(offset: tuple[float, float]) -> None:
    # A turned ellipsoidal eye, no lids: the clear cornea (rays along the gaze reach the iris)
    # ends at the limbus about the truth's limbus centre, which lies the offset's length off
    # the axis through the globe's centre along the gaze.
    eye = EyeSpec(limbus_offset_mm=offset, cornea_asphericity=-0.2, gaze_deg=(10.0, 5.0),
                  aperture_mm=(1000.0, 1000.0), globe_semi_axes_mm=(12.2, 11.8, 12.4))
    spec = SceneSpec(kind="eye", eye=eye)
    built = build_scene(spec)
    truth = scene_truth(spec)["eye"]
    limbus, gaze = np.asarray(truth["limbus_centre_mm"]), np.asarray(truth["gaze"])
    from_centre = limbus - np.asarray(truth["centre_mm"])
    across = from_centre - (from_centre @ gaze) * gaze
    assert np.linalg.norm(across) == pytest.approx(math.hypot(*offset), abs=1e-9)
    e1 = np.cross(gaze, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(gaze, e1)
    half = eye.limbus_diameter_mm / 2
    for radius, clear in ((half - 0.2, True), (half + 0.2, False)):
        for angle in np.linspace(0.0, 2 * math.pi, 12, endpoint=False):
            at = limbus + radius * (math.cos(angle) * e1 + math.sin(angle) * e2)
            hits = built.scene.cast(at + 50.0 * gaze, -gaze[None, :])
            assert (built.scene.labels[hits.label[0]] == "iris") == clear, (radius, angle)


def test_motion_state_depends_on_time_only() -> None:
    spec = MotionSpec(seed=11, saccade_rate_hz=2.0, blink_rate_hz=0.3, script=[
        ScriptEvent(t_s=3.0, kind="saccade", gaze_deg=(2.0, -1.0)),
        ScriptEvent(t_s=5.0, kind="shift", shift_mm=(0.5, 0.0, -0.3))])
    times = np.linspace(0.0, 35.0, 240)  # four of the motion's 10-second windows
    forward = [EyeMotion(spec).state(float(t)) for t in times]
    motion_module._window_events.cache_clear()
    shuffled_motion = EyeMotion(spec)
    order = np.random.default_rng(0).permutation(times.size)
    shuffled = {int(i): shuffled_motion.state(float(times[i])) for i in order}
    assert forward == [shuffled[i] for i in range(times.size)]
    # The eye does move (drift, saccades, blinks), and another seed moves it otherwise.
    yaw = np.array([s.gaze_offset_deg[0] for s in forward])
    assert np.ptp(yaw) > 0.1
    assert any(s.openness < 1.0 for s in forward)
    other = [EyeMotion(spec.model_copy(update={"seed": 12})).state(float(t)) for t in times]
    assert other != forward
    # The same through the scene's truth, asked backwards.
    eye_spec = SceneSpec(kind="eye", eye=EyeSpec(motion=spec))
    motion_module._window_events.cache_clear()
    backwards = [scene_truth(eye_spec, float(t))["eye"] for t in times[::-12]]
    assert backwards[::-1] == [scene_truth(eye_spec, float(t))["eye"] for t in times[::-12][::-1]]


def _eye_window(cam: CameraModel) -> tuple[slice, slice]:
    """The pixels that can see the default eye: its lid shell's bounding box, projected."""
    reach = 14.0  # the lid shell's radius (globe 12 mm + lid gap), with a margin
    corners = np.array([[x, y, z] for x in (-reach, reach) for y in (-reach, reach)
                        for z in (-10.0 - reach, -10.0 + reach)])
    uv = cam.project(corners)
    h, w = cam.shape
    j0, i0 = np.floor(uv.min(axis=0)).astype(int)
    j1, i1 = np.ceil(uv.max(axis=0)).astype(int) + 1
    return slice(max(i0, 0), min(i1, h)), slice(max(j0, 0), min(j1, w))


def test_a_blink_closes_the_lids() -> None:
    blink_start, duration = 1.0, 0.25
    spec = SceneSpec(kind="eye", eye=EyeSpec(motion=MotionSpec(
        drift_deg=0.0, saccade_rate_hz=0.0,
        script=[ScriptEvent(t_s=blink_start, kind="blink", duration_s=duration)])))
    mid_blink = blink_start + 0.375 * duration  # lids shut from 30 % to 45 % of the blink
    before = 0.5
    assert scene_truth(spec, before)["eye"]["openness"] == 1.0
    assert scene_truth(spec, mid_blink)["eye"]["openness"] == 0.0

    # Shut lids leave no slit: no camera sees the eye (a minimum slit once let a few rays in).
    sim = SimRoom(clock=ManualClock(0))
    shut = build_scene(spec, mid_blink).scene
    for camera_id, cam in sim.renderer.cameras.items():
        window = _eye_window(cam)
        seen = shut.cast(cam.centre, cam.rays()[window].reshape(-1, 3)).label
        for hidden in ("sclera", "cornea"):
            assert not np.any(seen == shut.labels.index(hidden)), f"{camera_id} sees {hidden}"

    # The render shows it: where S1 saw sclera before the blink, it images the lids' skin.
    cam = sim.renderer.cameras["S1"]
    window = _eye_window(cam)
    before_scene = build_scene(spec, before).scene
    was_sclera = (before_scene.cast(cam.centre, cam.rays()[window].reshape(-1, 3)).label
                  == before_scene.labels.index("sclera")).reshape(cam.rays()[window].shape[:2])
    assert was_sclera.sum() > 5000
    interior = ndimage.binary_erosion(was_sclera, iterations=3)
    vignetting = _expected_vignetting(cam)[window][interior]
    sim.set_scene(spec)  # at clock time 0, so clock time is scene time
    open_image = sim.components("S1", t_s=before).ambient[window][interior]
    shut_image = sim.components("S1", t_s=mid_blink).ambient[window][interior]
    np.testing.assert_allclose(open_image, SCLERA * vignetting, rtol=0.01)
    np.testing.assert_allclose(shut_image, SKIN * vignetting, rtol=0.01)


@pytest.mark.parametrize(("radius", "half_w", "half_h"), [(13.2, 11.0, 7.5), (13.2, 6.0, 9.0),
                                                        (10.0, 12.0, 7.5)])
def test_the_closing_lids_bound_holds_the_whole_cap_and_no_more(radius: float, half_w: float,
                                                                  half_h: float) -> None:
    # The closing lids lie on the lid sphere's front inside the wide opening; the moving
    # render re-tests only the rays that meet their bound, so it must hold every such point
    # (the moving-eye test below checks the light mid-blink), and it is the smallest ball that
    # does: its rim touches the cap's edge.
    centre = np.array([0.4, -0.3, 2.0])
    rng = np.random.default_rng(3)
    x, y = rng.uniform(-half_w, half_w, 200_000), rng.uniform(-half_h, half_h, 200_000)
    keep = ((x / half_w) ** 2 + (y / half_h) ** 2 < 1) & (x * x + y * y < radius**2)
    x, y = x[keep], y[keep]
    cap = centre + np.stack([x, y, np.sqrt(radius**2 - x * x - y * y)], axis=1)
    middle, reach = _cap_bound(centre, radius, max(half_w, half_h))
    distance = np.linalg.norm(cap - middle, axis=1)
    assert reach - 0.1 < distance.max() <= reach


@pytest.mark.slow
@pytest.mark.parametrize("t_s", [0.0, 0.33, 0.47, 0.52, 0.6, 0.9])
def test_a_moving_eye_renders_as_the_whole_scene_cast_afresh(room: SimRoom, odd_room: SimRoom,
                                                             t_s: float) -> None:
    # The moving-scene renderer re-casts only the pixels a moving part can change and tests
    # the static points near a moving part's shadow for that shadow alone, and shows the shut
    # lids' light, shaded once, where the closing lids are met; the light must be what a full
    # cast of the scene gives, with the eye turned, mid-saccade, and closing, shut and
    # opening in a blink.
    script = [ScriptEvent(t_s=0.3, kind="saccade", gaze_deg=(12.0, -6.0), duration_s=0.05),
              ScriptEvent(t_s=0.45, kind="blink", duration_s=0.2),
              ScriptEvent(t_s=0.8, kind="shift", shift_mm=(1.5, -1.0, 0.5), duration_s=0.2)]
    motion = MotionSpec(seed=4, drift_deg=0.05, saccade_rate_hz=0.0, script=script)
    spec = SceneSpec(kind="eye", eye=EyeSpec(gaze_deg=(5.0, 3.0), motion=motion))
    _renders_as_cast_afresh(spec, t_s, (room, odd_room))


@pytest.mark.slow
@pytest.mark.parametrize("t_s", [0.33, 0.52, 0.9])
def test_a_moving_patient_eye_renders_as_the_whole_scene_cast_afresh(room: SimRoom,
                                                                     t_s: float) -> None:
    # A patient's eye (docs/eye-model.md) turns its globe, soft limbus and iris behind a clear
    # cornea as moving parts; its lashes stay with the lids. Mid-saccade, mid-blink and after
    # a shift the moving render must be a full cast's.
    script = [ScriptEvent(t_s=0.3, kind="saccade", gaze_deg=(12.0, -6.0), duration_s=0.05),
              ScriptEvent(t_s=0.45, kind="blink", duration_s=0.2),
              ScriptEvent(t_s=0.8, kind="shift", shift_mm=(1.5, -1.0, 0.5), duration_s=0.2)]
    motion = MotionSpec(seed=4, drift_deg=0.05, saccade_rate_hz=0.0, script=script)
    eye = EyeSpec(gaze_deg=(5.0, 3.0), motion=motion, globe_semi_axes_mm=(12.3, 12.0, 11.7),
                  cornea_asphericity=-0.25, limbus_vertical_ratio=0.9, limbus_width_mm=0.8,
                  limbus_scatter=0.3, iris_albedo=0.15, tear_reflectance=0.02, tear_glints=3,
                  lashes=8, aperture_offset_mm=(0.3, -1.5), lid_gap_mm=0.6, features_seed=5)
    assert not eye.sharp
    _renders_as_cast_afresh(SceneSpec(kind="eye", eye=eye), t_s, (room,))


@pytest.mark.slow
@pytest.mark.parametrize("t_s", [0.47, 0.52])
@pytest.mark.parametrize("eye", [
    {"aperture_mm": (12.8, 8.0)},  # the lids' outer edge behind the face: the face in front
    {"cornea_radius_mm": 6.5},  # the cornea beyond the lids' sphere: no shut-lid light kept
])
def test_a_blink_renders_as_cast_afresh_where_the_face_or_the_cornea_reach_the_lids(
        room: SimRoom, eye: dict[str, Any], t_s: float) -> None:
    blink = ScriptEvent(t_s=0.45, kind="blink", duration_s=0.2)
    spec = SceneSpec(kind="eye", eye=EyeSpec(motion=MotionSpec(
        seed=4, drift_deg=0.05, saccade_rate_hz=0.0, script=[blink]), **eye))
    assert (build_scene(spec, t_s).closed is None) == ("cornea_radius_mm" in eye)
    _renders_as_cast_afresh(spec, t_s, (room,))


def _renders_as_cast_afresh(spec: SceneSpec, t_s: float, rooms: tuple[SimRoom, ...]) -> None:
    for some_room in rooms:
        renderer = some_room.renderer
        built = build_scene(spec, t_s)
        projectors = list(renderer.projectors)
        for camera_id in renderer.cameras:
            moving = renderer.components_moving(camera_id, built, projectors)
            whole = renderer.components(camera_id, built.scene, 1, projectors)
            np.testing.assert_allclose(moving.ambient, whole.ambient, atol=1e-4)
            for pid in projectors:
                np.testing.assert_allclose(moving.fringe[pid], whole.fringe[pid], atol=1e-4)
                assert np.abs(whole.fringe[pid]).max() > 1.0  # the fringes are there


@pytest.mark.slow
def test_preparing_a_camera_casts_a_moving_eyes_static_part_before_its_first_frame() -> None:
    # The first render of a moving scene casts its static part whole (≈ 1 s a camera); a
    # stream's cameras are prepared before the stream so that its first frames come on time.
    sim = SimRoom(clock=ManualClock(0))
    motion = MotionSpec(seed=2, drift_deg=0.05, saccade_rate_hz=0.0, blink_rate_hz=0.0)
    sim.set_scene(SceneSpec(kind="eye", eye=EyeSpec(motion=motion)))
    assert not sim.renderer._static
    sim.prepare("S1", ["P1"])
    (camera_id, _), part = next(iter(sim.renderer._static.items()))
    assert camera_id == "S1" and sorted(part.values) == ["P1", "ambient"]
    # With it, the shut lids' light a blink's frames show (none of it while the eye is open).
    assert part.closed_first is not None and part.closed_first.sum() > 5000
    assert sorted(part.closed_values) == ["P1", "ambient"]
    # What was prepared is what a frame then uses (the same light as without preparing).
    prepared = sim.components("S1", 0.2, ["P1"])
    assert len(sim.renderer._static) == 1
    fresh = SimRoom(clock=ManualClock(0))
    fresh.set_scene(sim.scene)
    np.testing.assert_array_equal(prepared.fringe["P1"], fresh.components("S1", 0.2, ["P1"])
                                  .fringe["P1"])


@pytest.mark.slow
def test_a_scripted_head_shift_is_cast_ahead_and_its_transit_is_not_kept() -> None:
    # Issue 35: after a scripted 1-mm shift live tracking had no frame for seconds; each
    # camera cast the head's static part for the positions in transit and again where it
    # ended. Preparing casts the end ahead; positions in transit are cast but not kept.
    sim = SimRoom(clock=ManualClock(0))
    shift = ScriptEvent(t_s=1.0, kind="shift", shift_mm=(1.0, 0.0, 0.0), duration_s=0.3)
    motion = MotionSpec(seed=2, drift_deg=0.0, saccade_rate_hz=0.0, blink_rate_hz=0.0,
                        script=[shift])
    sim.set_scene(SceneSpec(kind="eye", eye=EyeSpec(motion=motion)))
    sim.prepare("S1", ["P1"])
    prepared = list(sim.renderer._static)
    assert len(prepared) == 2  # where the head is now and where the shift leaves it
    for t_s in (1.1, 1.2, 1.6):  # twice in transit, once after
        sim.components("S1", t_s, ["P1"])
    assert set(sim.renderer._static) == set(prepared)  # nothing new cached
    # What was cast ahead is what a frame after the shift shows.
    fresh = SimRoom(clock=ManualClock(0))
    fresh.set_scene(sim.scene)
    np.testing.assert_array_equal(sim.components("S1", 1.6, ["P1"]).fringe["P1"],
                                  fresh.components("S1", 1.6, ["P1"]).fringe["P1"])


@pytest.mark.slow
def test_a_blink_renders_with_the_static_part_prepared_for_the_open_eye() -> None:
    # The lids stay in the static part with the opening wide; only the part that closes over
    # the opening moves. A blink's frames need no static part of their own (cast whole at the
    # blink's first frame, ≈ 1 s, it cost a live stream the blink's frames), and the rays that
    # meet the lid shell's bound but not the closing lids keep their static light.
    sim = SimRoom(clock=ManualClock(0))
    blink = ScriptEvent(t_s=0.1, kind="blink", duration_s=0.3)
    motion = MotionSpec(seed=2, drift_deg=0.05, saccade_rate_hz=0.0, script=[blink])
    sim.set_scene(SceneSpec(kind="eye", eye=EyeSpec(motion=motion)))
    sim.prepare("S1", ["P1"])
    assert len(sim.renderer._static) == 1
    for t_s in (0.1 + 0.3 * 0.2, 0.1 + 0.3 * 0.4):  # closing, then shut
        blinking = sim.components("S1", t_s, ["P1"])
        assert len(sim.renderer._static) == 1  # nothing cast anew
        fresh = SimRoom(clock=ManualClock(0))
        fresh.set_scene(sim.scene)
        built = build_scene(sim.scene, sim.scene_time(t_s))
        whole = fresh.renderer.components("S1", built.scene, 1, ["P1"])
        np.testing.assert_allclose(blinking.fringe["P1"], whole.fringe["P1"], atol=1e-4)
        np.testing.assert_allclose(blinking.ambient, whole.ambient, atol=1e-4)


def test_an_exposure_mid_saccade_is_the_mean_of_its_moments() -> None:
    # A camera integrates its exposure: mid-saccade the image is the mean of the light of
    # every moment of it (rendered as equal slices of the exposure, one per ≈ pixel of travel),
    # while an exposure of the eye at rest (drift only) is the single render at its middle.
    saccade = ScriptEvent(t_s=0.3, kind="saccade", gaze_deg=(6.0, 0.0), duration_s=0.03)
    motion = MotionSpec(seed=4, drift_deg=0.05, saccade_rate_hz=0.0, script=[saccade])
    eye_motion = EyeMotion(motion)
    assert eye_motion.sub_exposures(0.1, 0.01) == (0.1,)
    times = eye_motion.sub_exposures(0.315, 0.01)
    # 6° in 30 ms along a smoothstep: 13/27 of it within the 10 ms about the saccade's middle,
    # ≈ 0.65 mm at the cornea.
    travel = math.radians(6.0 * 13 / 27) * motion_module.SURFACE_LEVER_MM
    assert len(times) == math.ceil(travel / motion_module.BLUR_STEP_MM) == 14
    assert times[0] == pytest.approx(0.31 + 0.005 / len(times))
    assert times[-1] == pytest.approx(0.32 - 0.005 / len(times))
    # A 1-ms exposure of the same moment moves less: fewer slices.
    assert 1 < len(eye_motion.sub_exposures(0.315, 0.001)) < motion_module.MAX_SUBEXPOSURES

    sim = SimRoom(_small_room(5), clock=ManualClock(0))
    sim.set_scene(SceneSpec(kind="eye", eye=EyeSpec(motion=motion)))
    still = sim.render("S1", t_s=0.1, projectors={"P1": 1.0}, exposure_us=10_000.0,
                       gain_db=0.0, rng=np.random.default_rng(1))
    single = sim.renderer.expose("S1", sim.components("S1", 0.1, ["P1"]),
                                 ambient_dn=sim.config.lighting.ambient_dn,
                                 projectors={"P1": 1.0}, exposure_us=10_000.0, gain_db=0.0,
                                 rng=np.random.default_rng(1))
    np.testing.assert_array_equal(still, single)

    blurred = sim.render("S1", t_s=0.315, projectors={"P1": 1.0}, exposure_us=10_000.0,
                         gain_db=0.0, rng=np.random.default_rng(1))
    moments = [sim.components("S1", t, ["P1"]) for t in times]
    mean = Components(ambient=np.mean([m.ambient for m in moments], axis=0, dtype=np.float32),
                      fringe={"P1": np.mean([m.fringe["P1"] for m in moments], axis=0,
                                            dtype=np.float32)})
    expected = sim.renderer.expose("S1", mean, ambient_dn=sim.config.lighting.ambient_dn,
                                   projectors={"P1": 1.0}, exposure_us=10_000.0, gain_db=0.0,
                                   rng=np.random.default_rng(1))
    np.testing.assert_array_equal(blurred, expected)
    # The blur smears the limbus and the fringes on the turning eye (this small room's
    # pixels are 0.2 mm at the eye: the mean's edges lie up to 3 px from the middle's).
    smeared = np.abs(mean.fringe["P1"] - sim.components("S1", 0.315, ["P1"]).fringe["P1"])
    assert (smeared > 1.0).sum() > 20


# --- rendering ahead ----------------------------------------------------------------------------


def test_frames_rendered_ahead_are_what_the_room_renders_at_their_time() -> None:
    """A stream on whole camera periods takes the frames rendered ahead: bit for bit the room's
    render at that moment with the same noise draws; frames at other times or settings render
    at once, and a new scene forgets them."""
    period_ns, start_ns = 40_000_000, 7_000_000_000
    motion = MotionSpec(seed=2, drift_deg=0.5, saccade_rate_hz=0.0, blink_rate_hz=0.0)
    spec = SceneSpec(kind="eye", eye=EyeSpec(motion=motion))
    sim = SimRoom(_small_room(5), clock=ManualClock(start_ns))
    with build_sim_rig(sim) as rig:
        sim.set_scene(SceneSpec(kind="plate"))
        camera = rig.unit("left").cameras[0]
        assert isinstance(camera, SimCamera)
        with pytest.raises(ValueError, match="does not move"):
            camera.prerender(0.2, 25.0, ("P1",))
        sim.set_scene(spec)
        for each in rig.unit("left").cameras:
            assert isinstance(each, SimCamera)
            assert each.prerender(0.2, 25.0, ("P1",)) is sim.scene
        sim.clock.advance(3.0)  # rendering ahead took a while: the script restarts after it
        epoch_ns = start_ns + 3 * 1_000_000_000
        assert sim.restart_scene(spec, epoch_ns)
        assert sim.prerendered() == {c: {"left": 5, "used": 0, "live": 0} for c in ("S1", "S2")}
        steps = [rig.acquire(["left"], at_ns=epoch_ns + k * period_ns)[0] for k in range(3)]
        assert sim.prerendered()["S1"] == {"left": 2, "used": 3, "live": 0}
        # Off the periods (1 ms late): rendered at once; the frame it passed is forgotten.
        late = rig.acquire(["left"], at_ns=epoch_ns + 3 * period_ns + 1_000_000)[0]
        assert sim.prerendered()["S1"] == {"left": 1, "used": 3, "live": 1}

        # The same scene at the same times in a room of its own, with the noise drawn in the
        # same order from the generator rendering ahead drew from.
        twin = SimRoom(_small_room(5), clock=ManualClock(epoch_ns))
        twin.set_scene(spec)
        for index, camera_id in enumerate(("S1", "S2")):
            rng = np.random.default_rng([5, index, 1])
            for step in steps:
                meta = step.frames[camera_id].meta
                expected = twin.render(camera_id, t_s=meta.t_ns / 1e9, projectors={"P1": 1.0},
                                       exposure_us=meta.exposure_us, gain_db=meta.gain_db,
                                       rng=rng)
                np.testing.assert_array_equal(step.frames[camera_id].image, expected)
            assert not np.array_equal(late.frames[camera_id].image,
                                      steps[-1].frames[camera_id].image)
        # Other settings render at once; a new scene forgets what was rendered ahead.
        camera.set_exposure_us(camera.exposure_us / 2)
        rig.acquire(["left"], at_ns=epoch_ns + 4 * period_ns)
        assert sim.prerendered()["S1"] == {"left": 1, "used": 3, "live": 2}
        sim.set_scene(spec)
        assert sim.prerendered() == {}
        assert not sim.restart_scene(spec.model_copy(), epoch_ns)


@pytest.mark.slow
def test_a_wet_patient_eye_mirrors_each_projector_as_a_saturated_glint(room: SimRoom) -> None:
    # The tear film mirrors the projector's pupil (R·(d₀/r)² ≈ 32 times the white plate's light
    # for R = 0.02 and a 10-mm pupil at 200 mm): a few pixels far beyond the 8-bit range, where
    # the dry eye's brightest light is the sclera's fringe.
    renderer = room.renderer
    projectors = list(renderer.projectors)
    dry = EyeSpec(gaze_deg=(3.0, -2.0), limbus_width_mm=0.5, iris_albedo=0.2)
    wet = dry.model_copy(update={"tear_reflectance": 0.02})
    pid = projectors[0]
    for camera_id in ("S1", "S2"):
        lights = [renderer.components(camera_id, build_scene(SceneSpec(kind="eye", eye=e)).scene,
                                      2, [pid]).fringe[pid] for e in (dry, wet)]
        glint = lights[1] - lights[0]
        assert lights[0].max() < 100.0
        assert 1 <= int((glint > 255.0).sum()) <= 100, int((glint > 255.0).sum())
        assert glint.max() > 1000.0


def test_a_scene_changed_between_the_cameras_of_one_pulse_reaches_neither() -> None:
    # Live tracking goes on while the simulated eye is moved (PUT /sim/eye): an exposure timed
    # before the change (its pulse fired, one camera read after) still sees the old scene.
    clock = ManualClock(1_000_000_000)
    sim = SimRoom(_small_room(5), clock=clock)
    sim.set_scene(SceneSpec(kind="plate", position_mm=(0.0, 0.0, 0.0)))
    pulse_s = 1.9
    clock.advance(1.0)  # the pulse fired at 1.9 s; now 2 s

    def exposure(t_s: float) -> npt.NDArray[Any]:
        return np.asarray(sim.render("S1", t_s=t_s, projectors={"P1": 1.0}, exposure_us=10_000,
                                     gain_db=0.0, rng=np.random.default_rng(0)))

    before = exposure(pulse_s)
    sim.set_scene(SceneSpec(kind="plate", position_mm=(0.0, 0.0, 5.0)))
    np.testing.assert_array_equal(exposure(pulse_s), before)  # the old scene
    clock.advance(0.04)
    after = exposure(2.02)  # a pulse after the change
    # Long before it: a caller's "the scene as it is" (t = 0), the new scene at its start.
    np.testing.assert_array_equal(exposure(0.0), exposure(1.0))
    assert not np.array_equal(exposure(0.0), before)
    # The same noise draws (one seed): what differs is the plate, moved 5 mm (≈ 4 DN a pixel
    # on average as its fringes shift).
    assert np.abs(after.astype(np.float64) - before).mean() > 1.0
