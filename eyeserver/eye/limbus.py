"""The limbus found in the fringe images, and the globe that carries it (docs/design.md §4 step 8).

The cornea returns almost no projector light (transparent: what comes back is the dark iris
behind it) while the sclera around it is bright, so in each camera the limbus is the sharpest
dark-inside, bright-outside edge of the fringe-free intensity. A circle in space (centre ``L``,
unit normal ``g``, radius ``r``; WCS, mm) is fitted to those edges in every camera at once by its
reprojection error (pixels); its normal is the gaze and its centre the limbus centre. The
one-shot fit (``find_limbus(oval=True)``) fits an oval instead, its height ratio free: a
patient's visible limbus is ≈ 0.9 as high as wide, and the globe's depth needs the horizontal
half-width (the corneoscleral junction), not a radius between the two
(docs/notes/patient-eye.md). The cloud alone cannot give the limbus: its sclera ends about a
fringe period outside it, lopsided.

1. **Fringe-free intensity** ``I − B·cos φ`` from the FTM: sharp at the edge, where a box filter
   over a period would blur it.
2. **Start.** Circles tilted 0–30° about the rough gaze (the cloud fit's can be 10–25° off), and
   about the cornea's dark disc, scored by the mean outward intensity step along their
   projections; the best one starts. Live tracking starts from the last frame's limbus and
   scores tilted circles only when that fits poorly or turns the gaze by more than
   :data:`FOLLOWED_TURN_DEG` (a saccade).
3. **Edges.** Along the projected circle's outward normals (:data:`SAMPLES` per camera), the
   *innermost* rising edge at least :data:`EDGE_SHARE` as strong as the profile's strongest,
   sub-pixel from a parabola: outside the limbus lie other rising edges (a shadow's end, the
   lids' margins), inside it only the cornea.
4. **Circle.** Robust least squares (Cauchy loss: lid margins and shadow edges are outliers) of
   the edges' distances to the projected circle's tangents, the reach shrinking round by round
   (:data:`REACHES_PX`). Where both units' cloud gives the globe, the one-shot search holds the
   circle near its axis (:data:`LIMBUS_AXIS_SD_MM`): on a patient's eye, shadow and lid edges
   fit circles off it better than a faint limbus.
   Uncertainties from the Jacobian and a robust residual scale, each camera's edges counted
   once per fringe period (errors within a period are shared).
5. **Globe.** ``C = L − h·g``, ``R = √(h² + r²)`` (the limbus taken on the globe's axis): one
   number ``h``, which the cloud's sclera gives (:func:`globe_on_limbus`), clear of the lids
   and the limbus (the band blends surfaces across depth steps). Its systematic error,
   amplified 3–8 times into ``h``, sets the depth's stated uncertainty
   (:data:`CLOUD_SCLERA_BIAS_MM`).
6. **Again.** A pose measurement measures the sclera again from its own fringes and finds the
   limbus again (:func:`refined`) with the sclera's illumination divided out
   (:mod:`eyeserver.eye.sclera`), leaving out the edges where the cornea keeps the
   camera's projector's light off the sclera just beyond the limbus (:func:`in_cornea_shadow`:
   the edge found there moves outwards). Live tracking, its radius held, keeps step 5's globe.

Not modelled: a pupil or iris pattern inside the limbus (its edges would be taken for the limbus)
and corneal refraction. Measured, and the variants not used: docs/notes/limbus.md. The
constants: :mod:`eyeserver.eye.tunables`.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
from scipy.optimize import least_squares
from scipy.spatial import cKDTree

from eyeserver.core.arrays import distances
from eyeserver.core.types import F32, F64
from eyeserver.eye.tunables import (
    CIRCLE_ITERATIONS,
    CIRCLE_STEPS,
    CIRCLE_X_SCALE,
    CIRCLE_XTOL,
    CLOUD_SCLERA_BIAS_MM,
    DARK_SHARE,
    DEPTH_REFIT_LIMIT_MM,
    EDGE_SHARE,
    FOLLOWED_TURN_DEG,
    GLOBE_DEPTHS_MM,
    GOOD_RESIDUAL_PX,
    LID_CLEARANCE_MM,
    LID_GAP_MM,
    LID_SHELL_DOMINANCE,
    LIMBUS_AXIS_STRAY_SDS,
    LIMBUS_CLEARANCE_MM,
    LIMBUS_WINDOW_MARGIN_PX,
    MAX_RESIDUAL_PX,
    MIN_COVERAGE,
    MIN_EDGE_DN_PER_PX,
    MIN_SCLERA_POINTS,
    OVAL_CORNEA_MM,
    OVAL_RATIOS,
    REACHES_PX,
    SAMPLES,
    SHADOW_PROBE_MM,
    SHELL_SEARCH_MM,
    SHELL_TROUGH,
    START_TILTS_DEG,
)
from eyeserver.pipeline.demodulate import demodulate
from eyeserver.pipeline.geometry import project
from eyeserver.pipeline.reconstruct import CalibratedCamera, Phase

__all__ = ["Globe", "Limbus", "LimbusNotFoundError", "LimbusView", "Shade", "circle_points",
           "find_limbus", "fringe_free", "fringe_removed", "globe_on_limbus", "in_cornea_shadow",
           "refined"]


class LimbusNotFoundError(ValueError):
    """No limbus in the images (lids closed, eye outside the view, no contrast)."""


@dataclass(frozen=True)
class LimbusView:
    """One camera's fringe image with its calibration.

    ``flat``, where the reconstruction demodulated the image already: the image without its
    fringe, ``I − B·cos φ`` (:func:`fringe_free` computes it otherwise).
    """

    camera: CalibratedCamera
    image: npt.NDArray[Any]
    flat: npt.NDArray[np.float32] | None = None


@dataclass(frozen=True)
class Limbus:
    """The limbus circle in the WCS (mm) with its uncertainties."""

    centre: F64
    normal: F64
    """Unit normal pointing out of the eye (the gaze)."""
    radius: float
    centre_sd_mm: float
    gaze_sd_deg: float
    radius_sd_mm: float
    residual_px: float
    """Median distance of the edges kept to the fitted circle's projections."""
    coverage: dict[str, float]
    """Per camera, the share of the circle where an edge was found."""
    ratio: float = 1.0
    """The visible limbus's height over its width (an oval: the sclera overlaps the cornea
    above and below); ``radius`` is its horizontal half-width, the corneoscleral junction's
    radius, and ``centre`` the junction's centre. 1 where a circle was fitted."""


@dataclass(frozen=True)
class Globe:
    """A spherical globe carrying the limbus: ``centre = L − h·g``, ``radius = √(h² + r²)``."""

    centre: F64
    radius: float
    depth_sd_mm: float
    """Uncertainty of ``h`` (the centre's distance behind the limbus plane)."""
    points: int
    surface_mad_mm: float
    support: int
    """How many points place it: the sclera points whose own sphere through the limbus lies
    within 0.1 mm of ``h`` when the radius is fitted (the lids' votes spread over millimetres,
    so lids taken for the sclera, where almost no sclera is seen, have little support), the
    sclera points when the radius is held."""
    sclera: F64 = field(default_factory=lambda: np.empty((0, 3)), repr=False, compare=False)
    """The cloud's points taken for the sclera (clear of the lids and the limbus)."""
    two_shells: bool = False
    """The sclera's points held a second shell (lids close outside the globe) that their robust
    fit followed (:data:`~eyeserver.eye.tunables.DEPTH_REFIT_LIMIT_MM`): the depth is the votes'
    mode, its uncertainty includes the move, and measuring those points again in the images
    would follow the same shell."""


def fringe_free(camera: CalibratedCamera, image: npt.ArrayLike,
                window: tuple[int, int, int, int] | None = None) -> tuple[F32, tuple[int, int]]:
    """``I − B·cos φ`` (the image without its fringe), lightly smoothed (σ = 1 px).

    ``window`` ``(x0, y0, x1, y1)`` limits the work to a part of the image; returns the
    intensity and the window's origin.
    """
    pixels = np.asarray(image, dtype=np.float32)
    x0, y0 = 0, 0
    if window is not None:
        x0, y0, x1, y1 = window
        pixels = pixels[y0:y1, x0:x1]
    # The band's own fringe is what it takes out of the image: no bend bias needed.
    result = demodulate(pixels, camera.carrier, measure_bends=False)
    return _smoothed(pixels - result.modulation * np.cos(result.wrapped_phase)), (x0, y0)


def fringe_removed(camera: CalibratedCamera, image: npt.ArrayLike, phase: Phase) -> F32:
    """``I − B·cos φ`` from the reconstruction's :func:`~eyeserver.pipeline.reconstruct.
    camera_phase` of ``image`` (φ its phase relative to the reference, plus the reference's,
    plus the bend bias taken out of it: the fringe the band passed), for
    :attr:`LimbusView.flat`."""
    wrapped = phase.dphi + np.asarray(camera.reference_phase, dtype=np.float32)
    if phase.bend_bias is not None:
        wrapped += phase.bend_bias
    return np.asarray(np.asarray(image, dtype=np.float32) - phase.modulation * np.cos(wrapped),
                      dtype=np.float32)


def _smoothed(flat: npt.ArrayLike) -> F32:
    return np.asarray(cv2.GaussianBlur(np.asarray(flat, dtype=np.float32), (0, 0), 1.0),
                      dtype=np.float32)


def _cross(a: F64, b: F64) -> F64:
    """``np.cross`` of ``(..., 3)`` arrays, written out: np.cross's axis handling cost more
    than the products on the few-row arrays of the circle fit (measured: 17 of 120 ms)."""
    return np.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
                     a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                     a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], axis=-1)


def _basis(normals: F64) -> tuple[F64, F64]:
    """Two unit vectors completing each normal ``(..., 3)`` to an orthonormal frame."""
    helper = np.where(np.abs(normals[..., :1]) < 0.9, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    u = _cross(normals, helper)
    u /= np.linalg.norm(u, axis=-1, keepdims=True)
    return u, _cross(normals, u)


def _window(view: LimbusView, centre: F64, radius: float) -> tuple[int, int, int, int]:
    """The part of a view's image where a ball of ``radius`` about ``centre`` is seen."""
    camera = view.camera
    height, width = np.asarray(view.image).shape[:2]
    corners = centre + radius * np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1)
                                          for sz in (-1, 1)], dtype=np.float64)
    uv = project(corners, camera.K, camera.dist, camera.R, camera.T)
    x0, y0 = np.floor(uv.min(axis=0)).astype(int) - LIMBUS_WINDOW_MARGIN_PX
    x1, y1 = np.ceil(uv.max(axis=0)).astype(int) + LIMBUS_WINDOW_MARGIN_PX
    x0, y0, x1, y1 = max(0, x0), max(0, y0), min(width, x1), min(height, y1)
    if x1 - x0 < 32 or y1 - y0 < 32:
        raise LimbusNotFoundError(f"camera {camera.camera_id} does not see the eye")
    return int(x0), int(y0), int(x1), int(y1)


@dataclass(frozen=True)
class Shade:
    """What decides where the cornea shadows the sclera just beyond the limbus from a camera's
    projector, besides the limbus: the globe the sclera lies on and the cornea's radius (the
    eye model's; the cornea is the sphere of that radius through the limbus circle, in front of
    its plane)."""

    globe_centre: F64
    globe_radius: float
    cornea_radius: float


class _Image:
    """One camera's fringe-free intensity in a window, and projections into it."""

    def __init__(self, view: LimbusView, window: tuple[int, int, int, int] | None) -> None:
        self.camera = view.camera
        if view.flat is None:
            self.flat, origin = fringe_free(view.camera, view.image, window)
        else:
            x0, y0, x1, y1 = window or (0, 0, view.flat.shape[1], view.flat.shape[0])
            self.flat, origin = _smoothed(view.flat[y0:y1, x0:x1]), (x0, y0)
        self.origin = np.asarray(origin, dtype=np.float64)

    def project_full(self, points: F64) -> F64:
        cam = self.camera
        return project(points, cam.K, cam.dist, cam.R, cam.T)

    def profiles(self, uv: F64, outward: F64, offsets: F64) -> F32:
        """Intensity along ``uv + s·outward`` for every offset ``s`` (one row per point)."""
        local = uv - self.origin
        map_x = (local[:, None, 0] + offsets[None] * outward[:, None, 0]).astype(np.float32)
        map_y = (local[:, None, 1] + offsets[None] * outward[:, None, 1]).astype(np.float32)
        return np.asarray(cv2.remap(self.flat, map_x, map_y, cv2.INTER_LINEAR,
                                    borderMode=cv2.BORDER_REPLICATE), dtype=np.float32)

    def outline(self, centre: F64, normal: F64, radius: float, angles: F64,
                ratio: float = 1.0) -> tuple[F64, F64]:
        """Projected circle (or oval, :func:`_circles`) points and their outward image
        normals."""
        uv, outward = self.outlines(centre[None], normal[None], radius, angles, ratio)
        return uv[0], outward[0]

    def outlines(self, centres: F64, normals: F64, radius: float | F64, angles: F64,
                 ratio: float | F64 = 1.0) -> tuple[F64, F64]:
        """:meth:`outline` of many circles ``(H, 3)`` at once (one radius, or one each):
        ``(H, M, 2)`` each, in one projection (a call per circle cost more than the
        projecting)."""
        h, m = len(centres), len(angles)
        on, along = _circles(centres, normals, radius, angles, ratio)
        ahead = on + 1e-3 * along
        uv_all = self.project_full(np.concatenate([on, ahead, centres]))
        uv = uv_all[:h * m].reshape(h, m, 2)
        step = uv_all[h * m:2 * h * m].reshape(h, m, 2) - uv
        middle = uv_all[2 * h * m:]
        outward = np.stack([step[..., 1], -step[..., 0]], axis=-1)
        outward /= np.maximum(np.linalg.norm(outward, axis=-1, keepdims=True), 1e-12)
        facing = ((uv - middle[:, None, :]) * outward).sum(axis=-1) < 0
        outward *= np.where(facing, -1.0, 1.0)[..., None]
        return uv, outward


def _circles(centres: F64, normals: F64, radius: float | F64, angles: F64,
             ratio: float | F64 = 1.0) -> tuple[F64, F64]:
    """Points ``(H·M, 3)`` of circles ``(H, 3)`` (one radius, or one each) at ``angles``, and
    their tangents.

    With a ``ratio`` (one, or one each) other than 1, ovals: the half-width ``radius``
    horizontally, ``ratio`` times it along ``_basis``'s first vector (the room's vertical for
    a gaze near +Z; the visible limbus, whose top and bottom the sclera overlaps), each point
    lifted along the normal by the sagitta of a :data:`OVAL_CORNEA_MM` cornea between the
    junction's radius and its own (the oval's top and bottom lie on the cornea, in front of
    the junction's plane).
    """
    h = len(centres)
    u, v = _basis(normals)
    cos, sin = np.cos(angles)[None, :, None], np.sin(angles)[None, :, None]
    u, v = u[:, None, :], v[:, None, :]
    radii = np.broadcast_to(np.asarray(radius, dtype=np.float64), (h,))[:, None, None]
    ratios = np.broadcast_to(np.asarray(ratio, dtype=np.float64), (h,))[:, None, None]
    if np.all(ratios == 1.0):
        on = (centres[:, None, :] + radii * (cos * u + sin * v)).reshape(-1, 3)
        return on, (-sin * u + cos * v).reshape(-1, 3)
    across = radii * ratios * cos  # along u: the room's vertical for a gaze near +Z
    along = radii * sin
    rho = np.sqrt(across * across + along * along)
    lift = (np.sqrt(OVAL_CORNEA_MM**2 - np.minimum(rho, OVAL_CORNEA_MM) ** 2)
            - np.sqrt(OVAL_CORNEA_MM**2 - np.minimum(radii, OVAL_CORNEA_MM) ** 2))
    on = centres[:, None, :] + across * u + along * v + lift * normals[:, None, :]
    return on.reshape(-1, 3), (-ratios * sin * u + cos * v).reshape(-1, 3)


def _start(images: Sequence[_Image], pivot: F64, arm: float, gaze: F64, radius: float,
           tilts_deg: Sequence[float] = START_TILTS_DEG) -> tuple[float, F64]:
    """Among circles tilted by ``tilts_deg`` about ``gaze`` (centred at ``pivot + arm·g`` for a
    gaze ``g``), the one whose outline steps up most (the mean over the cameras of the median
    outward intensity step across it): ``(score, g)``."""
    u, v = _basis(gaze)
    candidates = [gaze]
    for tilt in tilts_deg[1:]:
        for azimuth in range(0, 360, 30):
            a, b = math.radians(tilt), math.radians(azimuth)
            candidates.append(math.cos(a) * gaze
                              + math.sin(a) * (math.cos(b) * u + math.sin(b) * v))
    normals = np.array(candidates)
    centres = pivot + arm * normals
    angles = np.linspace(0.0, 2 * math.pi, 90, endpoint=False)
    scores = np.zeros(len(normals))
    for image in images:
        uv, outward = image.outlines(centres, normals, radius, angles)
        across = image.profiles(uv.reshape(-1, 2), outward.reshape(-1, 2),
                                np.array([-1.5, 1.5])).reshape(len(normals), len(angles), 2)
        scores += np.median(across[..., 1] - across[..., 0], axis=1)
    best = int(np.argmax(scores))
    return float(scores[best]) / len(images), normals[best]


def _dark_blob_centre(images: Sequence[_Image], limbus_radius: float) -> F64 | None:
    """The limbus centre where the cameras' largest dark disc is seen (the cornea), or None.

    Shadows are dark too, but thin: the cornea is the dark region with the largest inscribed
    circle (``cv2.distanceTransform``). Rays through the discs' centres are intersected in
    the least-squares sense; None when fewer than two cameras see one or the rays miss each
    other by more than a limbus radius.
    """
    rays = []
    for image in images:
        flat = cv2.GaussianBlur(image.flat, (0, 0), 2.0)
        dark = (flat < DARK_SHARE * float(np.percentile(flat, 95))).astype(np.uint8)
        border = max(1, round(image.camera.carrier.period_px))
        dark[:border], dark[-border:], dark[:, :border], dark[:, -border:] = 0, 0, 0, 0
        inscribed = cv2.distanceTransform(dark, cv2.DIST_L2, 5)
        y, x = np.unravel_index(int(np.argmax(inscribed)), inscribed.shape)
        if inscribed[y, x] < 8.0:
            continue
        cam = image.camera
        pixel = (np.array([[x, y]], dtype=np.float64) + image.origin).reshape(-1, 1, 2)
        normalised = cv2.undistortPoints(pixel, cam.K, cam.dist).reshape(2)
        direction = cam.R.T @ np.array([normalised[0], normalised[1], 1.0])
        rays.append((cam.centre, direction / np.linalg.norm(direction)))
    if len(rays) < 2:
        return None
    # The point closest to all rays: Σ (I − d dᵀ)(X − C) = 0.
    lhs, rhs = np.zeros((3, 3)), np.zeros(3)
    for origin, direction in rays:
        across = np.eye(3) - np.outer(direction, direction)
        lhs += across
        rhs += across @ origin
    point = np.linalg.solve(lhs, rhs)
    misses = [np.linalg.norm((np.eye(3) - np.outer(d, d)) @ (point - c)) for c, d in rays]
    return np.asarray(point, dtype=np.float64) if max(misses) < limbus_radius else None


def _edges(image: _Image, centre: F64, normal: F64, radius: float, reach: float,
           shade: Shade | None = None, ratio: float = 1.0) -> tuple[F64, F64]:
    """``(angles, edge pixels)`` of the innermost strong rising edge near the projection; with
    ``shade``, none where the cornea shadows the sclera beyond the limbus from the camera's
    projector (:func:`in_cornea_shadow`; none left out where the calibration gives no
    direction to the projector)."""
    angles = np.linspace(0.0, 2 * math.pi, SAMPLES, endpoint=False)
    uv, outward = image.outline(centre, normal, radius, angles, ratio)
    offsets = np.arange(-reach, reach + 0.25, 0.5)
    rise = np.gradient(image.profiles(uv, outward, offsets), axis=1) / 0.5
    inner = rise[:, 1:-1]
    peak = (inner >= rise[:, :-2]) & (inner >= rise[:, 2:])
    strong = peak & (inner >= np.maximum(EDGE_SHARE * inner.max(axis=1, keepdims=True),
                                         MIN_EDGE_DN_PER_PX))
    found = strong.any(axis=1)
    light = None if shade is None else image.camera.light_direction(centre)
    if shade is not None and light is not None:
        found &= ~in_cornea_shadow(centre, normal, radius, angles, shade, light)
    k = np.argmax(strong, axis=1) + 1
    rows = np.arange(len(k))
    before, at, after = rise[rows, k - 1], rise[rows, k], rise[rows, k + 1]
    curvature = before - 2 * at + after
    curved = np.abs(curvature) > 1e-9
    shift = np.where(curved, 0.5 * (before - after) / np.where(curved, curvature, 1.0), 0.0)
    position = offsets[k] + 0.5 * np.clip(shift, -1.0, 1.0)
    edge = uv + position[:, None] * outward
    return angles[found], edge[found]


def _gaze(params: F64) -> F64:
    """The unit gaze of parameter rows ``(..., 6)``: X and Y given, Z > 0."""
    gx, gy = params[..., 3], params[..., 4]
    return np.stack([gx, gy, np.sqrt(np.maximum(1e-9, 1.0 - gx * gx - gy * gy))], axis=-1)


@dataclass(frozen=True)
class _Circle:
    """A fitted circle's parameters ``x`` (centre, gaze X and Y, radius), its residuals (px)
    and its Jacobian scaled by the loss as ``scipy.optimize.least_squares`` scales it (its
    ``JᵀJ`` the Gauss–Newton Hessian of the robust cost, for the covariance)."""

    x: F64
    fun: F64
    jac: F64



def _cauchy_cost(residuals: F64) -> float:
    return 0.5 * float(np.sum(np.log1p(residuals * residuals)))


def _circle_residuals(images: Sequence[_Image], edges: Sequence[tuple[F64, F64]],
                      centre: F64, normal: F64, radius: float, ratio: float = 1.0
                      ) -> Callable[[F64], F64]:
    """The edges' distances to the projected circle's tangents (pixels) as a function of
    parameter rows ``(H, 6)`` (centre, gaze X and Y, radius; ``(H, 7)``: and an oval's height
    ratio, else ``ratio``) → ``(H, N)``, all rows in one projection per camera; each edge is
    measured along the start outline's outward normal at the angle it was found at
    (:func:`_fit_circle`)."""
    seen = [(image, angles, found, image.outline(centre, normal, radius, angles, ratio)[1])
            for image, (angles, found) in zip(images, edges, strict=True) if len(angles)]
    # Every camera's angles in one _circles call (one per camera cost a tenth of a tracked
    # frame), cut apart again for each camera's projection.
    every_angle = np.concatenate([angles for _, angles, _, _ in seen]) if seen else np.zeros(0)
    cuts = np.cumsum([0] + [len(angles) for _, angles, _, _ in seen])

    def rows(params: F64) -> F64:
        out = []
        ratios = params[:, 6] if params.shape[1] > 6 else ratio
        on, _ = _circles(params[:, :3], _gaze(params), params[:, 5], every_angle, ratios)
        on = on.reshape(len(params), len(every_angle), 3)
        for (image, angles, found, outward), start, stop in zip(seen, cuts[:-1], cuts[1:],
                                                                strict=True):
            uv = image.project_full(on[:, start:stop].reshape(-1, 3))
            uv = uv.reshape(len(params), len(angles), 2)
            out.append(((found[None] - uv) * outward[None]).sum(axis=-1))
        return np.concatenate(out, axis=1)

    return rows


def _off_axis(params: F64, axis_point: F64) -> F64:
    """Rows ``(H, 3)``: each circle's centre's offset (mm) from the line through
    ``axis_point`` along its own normal (0 for a limbus concentric with a globe centred
    there)."""
    offset = params[:, :3] - axis_point
    g = _gaze(params)
    return np.asarray(offset - np.sum(offset * g, axis=1, keepdims=True) * g, dtype=np.float64)


def _fit_circle(images: Sequence[_Image], edges: Sequence[tuple[F64, F64]], centre: F64,
                normal: F64, radius: float, ratio: float = 1.0, fit_ratio: bool = False,
                axis: tuple[F64, float] | None = None) -> _Circle:
    """Robust least squares (Cauchy loss, scale 1 px) of the edges' distances to the projected
    circle's tangents (pixels).

    Each edge keeps the circle angle it was found at, and the outward normal of the start
    circle there: moving along the tangent costs nothing to first order, so the association
    holds within a round, and the circle moves by a pixel or less in the normals' directions
    within one (the round's search reach), which turns them by a fraction of a degree. The
    Jacobian is a forward difference taken in one batched projection per camera (the circle
    and its six nudged copies; SciPy's own differencing projects once per parameter).
    ``axis`` (a point and an sd, mm) adds three plain least-squares rows: the centre's offset
    from the line through the point along the circle's normal (:func:`_off_axis`), in sds; the
    returned residuals and Jacobian are the edges' alone.

    The minimisation is Levenberg–Marquardt on iteratively reweighted least squares, written
    here rather than ``scipy.optimize.least_squares``, whose bookkeeping around six parameters
    and a few hundred residuals cost more than the projections: each iteration evaluates the
    circle and its Jacobian in one batched projection. It finds SciPy's circles (tested); the
    timings: docs/notes/limbus.md.
    """
    rows = _circle_residuals(images, edges, centre, normal, radius, ratio)
    size = 7 if fit_ratio else 6
    steps, x_scale = CIRCLE_STEPS[:size], CIRCLE_X_SCALE[:size]

    count = sum(len(angles) for angles, _ in edges)  # the edges' rows; the axis's follow

    def evaluate(params: F64) -> tuple[F64, F64]:
        """Residuals ``(N,)`` at ``params`` and their forward-difference Jacobian ``(N, 6)``
        (7 with the oval's ratio); with the axis held, its three rows last."""
        batch = np.vstack([params, params + np.diag(steps)])
        values = rows(batch)
        if axis is not None:
            values = np.concatenate([values, _off_axis(batch, axis[0]) / axis[1]], axis=1)
        return values[0], ((values[1:] - values[0]) / steps[:, None]).T

    def total(values: F64) -> float:
        return _cauchy_cost(values[:count]) + 0.5 * float(np.sum(values[count:] ** 2))

    x = np.array([*centre, normal[0], normal[1], radius, ratio][:size])
    residuals, jac = evaluate(x)
    cost = total(residuals)
    damping = 1e-3
    for _ in range(CIRCLE_ITERATIONS):
        weights = 1.0 / (1.0 + residuals * residuals)
        weights[count:] = 1.0
        hessian = jac.T @ (weights[:, None] * jac)
        gradient = jac.T @ (weights * residuals)
        try:
            step = np.linalg.solve(hessian + damping * np.diag(np.maximum(np.diag(hessian),
                                                                          1e-12)), -gradient)
        except np.linalg.LinAlgError:
            break
        trial = x + step
        trial_residuals, trial_jac = evaluate(trial)
        trial_cost = total(trial_residuals)
        if trial_cost <= cost:
            x, residuals, jac, cost = trial, trial_residuals, trial_jac, trial_cost
            damping = max(damping / 10.0, 1e-9)
            if np.all(np.abs(step) < CIRCLE_XTOL * x_scale):
                break
        else:
            damping *= 10.0
            if damping > 1e8:
                break
    residuals, jac = residuals[:count], jac[:count]
    squared = residuals * residuals
    scale = np.maximum((1.0 - squared) / (1.0 + squared) ** 2, np.finfo(float).eps)
    return _Circle(x=x, fun=residuals, jac=jac * np.sqrt(scale)[:, None])


def _edges_per_period(image: _Image, centre: F64, normal: F64, radius: float,
                      ratio: float = 1.0) -> float:
    """How many of the circle's :data:`SAMPLES` fall within one fringe period of ``image``'s
    camera along its projection (at least 1)."""
    uv, _ = image.outline(centre, normal, radius,
                          np.linspace(0.0, 2 * math.pi, SAMPLES, endpoint=False), ratio)
    circumference = float(np.linalg.norm(np.diff(uv, axis=0, append=uv[:1]), axis=1).sum())
    period = image.camera.carrier.period_px / image.camera.spacing_px  # in its own pixels
    return max(1.0, period * SAMPLES / max(circumference, 1e-9))


def _refine(images: Sequence[_Image], centre: F64, normal: F64, radius: float,
            reaches: Sequence[float] = REACHES_PX, shade: Shade | None = None,
            ratio: float = 1.0, fit_ratio: bool = False,
            axis: tuple[F64, float] | None = None) -> Limbus:
    """Edges and circle, a round per search reach (module steps 3 and 4), from one start;
    with ``fit_ratio``, an oval whose height ``ratio`` is fitted too (:func:`_circles`)."""
    expected = radius
    for index, reach in enumerate(reaches):
        edges = [_edges(image, centre, normal, radius, reach, shade, ratio) for image in images]
        if sum(len(a) >= MIN_COVERAGE * SAMPLES for a, _ in edges) < 2:
            raise LimbusNotFoundError("no limbus edge in at least two cameras (lids closed?)")
        # The axis guides the rounds; the last is the edges' own unless it strays from it.
        last = index == len(reaches) - 1
        solution = _fit_circle(images, edges, centre, normal, radius, ratio, fit_ratio,
                               None if last else axis)
        if (last and axis is not None and float(np.linalg.norm(
                _off_axis(solution.x[None], axis[0]))) > LIMBUS_AXIS_STRAY_SDS * axis[1]):
            solution = _fit_circle(images, edges, centre, normal, radius, ratio, fit_ratio,
                                   axis)
        centre, normal, radius = solution.x[:3], _gaze(solution.x), float(solution.x[5])
        if fit_ratio:
            ratio = float(solution.x[6])
    residual = np.abs(solution.fun)
    if not 0.5 * expected < radius < 1.5 * expected:
        raise LimbusNotFoundError("the edges found fit no limbus circle")
    if not OVAL_RATIOS[0] < ratio < OVAL_RATIOS[1]:
        raise LimbusNotFoundError("the edges found fit no limbus oval")
    scale = 1.4826 * float(np.median(residual))
    # Edges within a fringe period of each other share their error (the fringe left in the
    # fringe-free intensity, the band's blur): each camera's information counts once per
    # period of its circle, not once per sample.
    rows = [(image, len(a)) for image, (a, _) in zip(images, edges, strict=True) if len(a)]
    per_period = np.repeat([_edges_per_period(image, centre, normal, radius, ratio)
                            for image, _ in rows], [n for _, n in rows])
    jac = solution.jac / np.sqrt(per_period)[:, None]
    try:
        cov = np.linalg.inv(jac.T @ jac) * max(scale, 0.05) ** 2
    except np.linalg.LinAlgError:
        cov = np.full((jac.shape[1],) * 2, np.inf)
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    return Limbus(centre=centre, normal=normal, radius=radius,
                  centre_sd_mm=float(np.linalg.norm(sd[:3])),
                  gaze_sd_deg=math.degrees(float(np.hypot(sd[3], sd[4]))),
                  radius_sd_mm=float(sd[5]), residual_px=float(np.median(residual)),
                  coverage={image.camera.camera_id: len(a) / SAMPLES
                            for image, (a, _) in zip(images, edges, strict=True)},
                  ratio=ratio)


def find_limbus(views: Sequence[LimbusView], globe_centre: npt.ArrayLike, gaze: npt.ArrayLike,
                globe_radius: float, limbus_radius: float, *, search: bool = True,
                oval: bool = False, axis_sd_mm: float | None = None) -> Limbus:
    """The limbus circle seen in ``views``, starting from a rough eye pose (see the module).

    The search starts about the rough pose, in a window of each image around it (and, with
    ``search`` and a rough gaze more than 6° from +Z, about +Z too, where the eye looks: one
    unit's cloud alone can put the gaze 40° off). When that ends in no limbus, or in edges
    further than :data:`GOOD_RESIDUAL_PX` from the circle, or the eye is in fewer than three
    cameras' views, and ``search`` is on, it starts again from the cornea's dark disc in the
    whole images (module step 2), and the closest fit wins. Without ``search``, the faster
    choice when the rough pose is good (live tracking starts from the previous frame), only the
    window is read.

    With ``axis_sd_mm``, the circles are held near the axis through ``globe_centre`` along
    their own normal (a prior of that sd, mm, on the centre's offset across it): the limbus is
    concentric with the globe, and on a patient's eye the edges of shadows and lids fit
    circles millimetres off it better than the faint limbus (docs/notes/patient-eye.md). The
    prior barely moves a limbus its edges place well (hundreds of edges against three rows);
    it decides where they do not. A search's last round is the edges' own fit, held only where
    that strays more than :data:`LIMBUS_AXIS_STRAY_SDS` sds from the axis.

    Raises
    ------
    LimbusNotFoundError
        Fewer than two cameras see enough of a limbus, or the edges fit no circle.
    """
    centre0 = np.asarray(globe_centre, dtype=np.float64)
    gaze0 = np.asarray(gaze, dtype=np.float64)
    gaze0 = gaze0 / np.linalg.norm(gaze0)
    if gaze0[2] <= 0:
        raise LimbusNotFoundError("the eye looks away from the cameras")
    depth = math.sqrt(max(globe_radius**2 - limbus_radius**2, 1.0))
    held = None if axis_sd_mm is None else (centre0, float(axis_sd_mm))
    found: list[Limbus] = []
    failure = LimbusNotFoundError("fewer than two cameras see the eye")
    images = []
    for view in views:
        with contextlib.suppress(LimbusNotFoundError):
            images.append(_Image(view, _window(view, centre0 + depth * gaze0,
                                               globe_radius * 0.6)))
    if len(images) >= 2 and not search:
        # Live tracking: the last frame's limbus is within a pixel or two of this one's but
        # for a saccade, and the last round alone (the rounds before it only bring a far start
        # closer) finds it from there; the tilted circles are scored only when that does not
        # fit well or turned the gaze by more than FOLLOWED_TURN_DEG (measured on a drifting
        # eye: the scoring took 1.9 ms of a 10–16 ms frame set, and chose the last gaze, whose
        # last round then ran the same). A limbus near the round's reach is half found: from a
        # last gaze 3.5° off, this round alone fitted a circle 0.63° from the eye's, 0.5 px
        # from its edges.
        try:
            limbus = _refine(images, centre0 + depth * gaze0, gaze0, limbus_radius,
                             REACHES_PX[-1:], fit_ratio=oval, axis=held)
        except LimbusNotFoundError as exc:
            failure = exc
        else:
            turn = math.degrees(math.acos(min(1.0, float(limbus.normal @ gaze0))))
            if limbus.residual_px <= GOOD_RESIDUAL_PX and turn <= FOLLOWED_TURN_DEG:
                return limbus
            found.append(limbus)
    if len(images) >= 2:
        # From the last frame's pose, the eye turned by a saccade at most.
        tilts = START_TILTS_DEG if search else START_TILTS_DEG[:3]
        starts = [gaze0]
        if search and gaze0[2] < math.cos(math.radians(START_TILTS_DEG[1])):
            # A rough gaze from the cloud alone can be 40° off (one unit's view of the eye):
            # the limbus is also looked for about the cameras' side, where the eye looks.
            starts.append(np.array([0.0, 0.0, 1.0]))
        for start in starts:
            _, normal = _start(images, centre0, depth, start, limbus_radius, tilts)
            # Live tracking comes here after a saccade's start, or when the last gaze's last
            # round failed: the rounds after the widest from the best-scoring circle.
            rounds: list[tuple[F64, Sequence[float], bool]] = [
                (normal, REACHES_PX if search else REACHES_PX[1:], False)]
            if not search and not np.array_equal(normal, start):
                # A tilted circle scored best but led nowhere: the eye may have turned by less
                # than the tilt's step, its limbus a few pixels from the last one, where no
                # circle scores well (measured: the frame after one caught mid-saccade, 2.4°
                # on, which the search from the last gaze with every reach finds, where the
                # global fit took 0.46 s). Only a good fit counts from that wide a search: from
                # a globe 4 mm off it fitted a circle 1.3 mm off, 0.8 px from its edges (the
                # limbus: 0.1–0.2 px).
                rounds.append((start, REACHES_PX, True))
            for axis, reaches, good_only in rounds:
                try:
                    limbus = _refine(images, centre0 + depth * axis, axis, limbus_radius,
                                     reaches, fit_ratio=oval, axis=held)
                except LimbusNotFoundError as exc:
                    failure = exc
                    continue
                if good_only and limbus.residual_px > GOOD_RESIDUAL_PX:
                    failure = LimbusNotFoundError("the edges found fit no limbus circle")
                    continue
                found.append(limbus)
                if limbus.residual_px <= GOOD_RESIDUAL_PX:
                    break
            if found and found[-1].residual_px <= GOOD_RESIDUAL_PX:
                break
    # One camera pair's circle depends on where its fit starts (one unit's cloud can start it
    # 50–90° off): a good fit (≤ GOOD_RESIDUAL_PX) from there was 2–5° off in 2 of 60 poses,
    # where the dark disc's start finds the limbus, so one pair always tries both. Measured on
    # `bench pose --unit left --held-radius` (60 poses): gaze 0.38° → 0.36° median, 0.96° →
    # 0.84° p95, centre at worst 1.3 → 0.22 mm, fit time unchanged (it mostly ran already);
    # with both units it changed nothing but cost 80–90 ms a fit (four whole images).
    if search and (not found or min(f.residual_px for f in found) > GOOD_RESIDUAL_PX
                   or len(images) < 3):
        whole = [_Image(view, None) for view in views]
        blob = _dark_blob_centre(whole, limbus_radius)
        if blob is not None:
            # The gaze towards the cameras (+Z) about the dark disc, tilted as it fits best.
            _, normal = _start(whole, blob, 0.0, np.array([0.0, 0.0, 1.0]), limbus_radius)
            try:
                found.append(_refine(whole, blob, normal, limbus_radius, fit_ratio=oval,
                                     axis=held))
            except LimbusNotFoundError as exc:
                failure = exc
    found = [limbus for limbus in found if limbus.residual_px <= MAX_RESIDUAL_PX]
    if not found:
        raise failure if str(failure) else LimbusNotFoundError("no limbus found")
    return min(found, key=lambda limbus: limbus.residual_px)


def refined(views: Sequence[LimbusView], limbus: Limbus, shade: Shade | None = None) -> Limbus:
    """The last round of edges and circle (module steps 3 and 4) again, from ``limbus``: for
    views whose :attr:`~LimbusView.flat` was made with a better fringe removal
    (:func:`~eyeserver.eye.sclera.sharpened`). With ``shade``, the edges where the cornea
    shadows the sclera beyond the limbus from the camera's projector are left out (module step
    6; cameras whose calibration gives no light direction keep theirs).

    Raises
    ------
    LimbusNotFoundError
        Fewer than two cameras see enough of it, or the edges fit no circle (or lie further than
        :data:`MAX_RESIDUAL_PX` from it, as :func:`find_limbus` requires).
    """
    images = []
    for view in views:
        with contextlib.suppress(LimbusNotFoundError):
            images.append(_Image(view, _window(view, limbus.centre, limbus.radius)))
    if len(images) < 2:
        raise LimbusNotFoundError("fewer than two cameras see the limbus")
    # Its edges are counted once per fringe period, as the band's are. Once per half period
    # (the fringe divided out, less of the error might be shared) made the stated sds hold the
    # errors as a normal error's would (bench pose: the centre's axes within one and two sds on
    # 78/97 %, the gaze 65/98 %, against 87/100 % and 88/100 %), but gave the limbus more
    # weight against the sclera and the poses were worse (gaze 0.065° → 0.074° median, centre
    # 0.098 → 0.105 mm p95): the wider sds stay.
    again = _refine(images, limbus.centre, limbus.normal, limbus.radius, REACHES_PX[-1:], shade,
                    limbus.ratio, fit_ratio=limbus.ratio != 1.0)
    if again.residual_px > MAX_RESIDUAL_PX:
        raise LimbusNotFoundError("the edges found fit no limbus circle")
    return again


def circle_points(limbus: Limbus, angles: F64) -> F64:
    """Points ``(M, 3)`` of the limbus circle at ``angles`` about its normal."""
    on, _ = _circles(limbus.centre[None], limbus.normal[None], limbus.radius, angles)
    return on


def in_cornea_shadow(centre: F64, normal: F64, radius: float, angles: F64, shade: Shade,
                     light: F64) -> npt.NDArray[np.bool_]:
    """Per angle about the limbus circle (``centre``, unit ``normal``, ``radius``), whether the
    cornea keeps the light coming from direction ``light`` off the sclera just beyond it
    (:data:`SHADOW_PROBE_MM` along ``shade``'s globe): the ray from there towards the light
    meets the cornea in front of the limbus's plane.

    Light entering a real cornea goes into the eye, not onto the sclera behind the limbus, so
    wherever the light comes from further off the gaze than the cornea's rim faces (90° less
    ``asin(radius / cornea radius)``: 41° for 5.85 and 7.8 mm) a band of sclera on the far side
    from it is dark, and the edge found there moves outwards with it (docs/notes/limbus.md)."""
    if shade.cornea_radius <= radius:
        return np.zeros(len(angles), dtype=bool)
    rim, _ = _circles(centre[None], normal[None], radius, angles)
    outward = rim - centre
    outward /= np.linalg.norm(outward, axis=1, keepdims=True)
    up = (rim - shade.globe_centre) / shade.globe_radius
    along = outward - (outward * up).sum(axis=1, keepdims=True) * up
    along /= np.linalg.norm(along, axis=1, keepdims=True)
    tilt = SHADOW_PROBE_MM / shade.globe_radius
    probe = shade.globe_centre + shade.globe_radius * (math.cos(tilt) * up + math.sin(tilt) * along)
    cornea = centre - math.sqrt(shade.cornea_radius**2 - radius**2) * normal
    rel = probe - cornea
    b = rel @ light
    disc = b * b - (np.einsum("ij,ij->i", rel, rel) - shade.cornea_radius**2)
    root = np.sqrt(np.where(disc > 0, disc, 0.0))
    shadowed = np.zeros(len(angles), dtype=bool)
    for t in (-b - root, -b + root):
        meets = probe + t[:, None] * light
        shadowed |= (disc > 0) & (t > 0) & ((meets - centre) @ normal > 0)
    return shadowed


def _votes(cloud: F64, limbus: Limbus, chosen: npt.NDArray[np.bool_]) -> tuple[F64, F64]:
    """Each chosen point's ``h`` and its weight (see :func:`globe_on_limbus`)."""
    L, g, r = limbus.centre, limbus.normal, limbus.radius
    rel = cloud[chosen] - L
    along = rel @ g
    return (r**2 - np.einsum("ij,ij->i", rel, rel)) / (2.0 * along), along**2


def _innermost_depth(votes: F64) -> float:
    """Where the votes for ``h`` gather first: the sclera, the innermost shell through the
    limbus.

    Nothing but noise lies inside the globe: from the first 0.3 mm window holding a fit's worth
    of votes, the strongest window within :data:`SHELL_SEARCH_MM` is the sclera's, unless a
    peak inside it holds at least half as many votes and a trough (below
    :data:`SHELL_TROUGH` of that peak) lies between them: then the strongest is a lid shell
    close to the globe (0.3–0.5 mm outside it, whose points outnumber the sclera's) and the
    inner peak is the sclera. Measured on 200 rendered poses, the first window alone sat on
    the noise inside the globe in one pose in ten (centre errors up to 2.3 mm); a longer search
    reaches the lids' votes on the `wide` rig, where they begin ≈ 2.8 mm beyond the sclera's
    and outnumber them a hundredfold. The inner peak: docs/notes/patient-eye.md.
    """
    edges = np.arange(GLOBE_DEPTHS_MM[0], GLOBE_DEPTHS_MM[1] + 0.1, 0.1)
    counts = np.convolve(np.histogram(votes, bins=edges)[0], np.ones(3), mode="same")
    enough = np.flatnonzero(counts >= MIN_SCLERA_POINTS)
    if not len(enough):
        raise LimbusNotFoundError("too little sclera beside the limbus to place the globe")
    first = int(enough[0])
    window = counts[first:first + round(SHELL_SEARCH_MM / 0.1)]
    chosen = int(np.argmax(window))
    for k in range(chosen):
        peak = (window[k] >= 0.5 * window[chosen] and (k == 0 or window[k - 1] <= window[k])
                and window[k + 1] <= window[k])
        if peak and _shells_apart(window, k, chosen):
            chosen = k
            break
    return float(edges[first + chosen] + 0.05)


def _shells_apart(counts: F64, inner: int, outer: int) -> bool:
    """Whether the histogram's peaks at ``inner`` and ``outer`` are two shells: the counts
    between them fall below :data:`SHELL_TROUGH` of the smaller peak's."""
    return bool(counts[inner:outer + 1].min() < SHELL_TROUGH * min(counts[inner], counts[outer]))


def _lid_gap(offset: F64) -> float:
    """Where the lids begin outside the sphere (mm of radial offset), from the points' offsets
    to it: the trough between the sclera's peak (about 0) and a lid shell's, where a second
    peak stands out (at least 0.3 of the sclera's, with a trough below :data:`SHELL_TROUGH`
    of the smaller); :data:`LID_GAP_MM` without one. A patient's lids may lie 0.3 mm outside
    the globe, the sclera's own flanks up to 0.3 mm (the band-limited FTM): a fixed clearance
    takes one for the other either way.

    The sclera's peak is the highest local maximum within 0.15 mm of the sphere (the highest
    count there can be the lid shell's rising flank). A lid shell closer than
    :data:`LID_GAP_MM` that holds :data:`LID_SHELL_DOMINANCE` times the sclera's count begins
    halfway between the two peaks, trough or not: with fringes parallel to the lid margins the
    demodulation blends the lids into the sclera across the fringes, and the blend fills the
    trough (docs/notes/patient-eye.md, twentieth session)."""
    step = 0.05
    edges = np.arange(-0.3, 1.6 + step / 2, step)
    counts = np.convolve(np.histogram(offset, bins=edges)[0], np.ones(3) / 3, mode="same")
    centres = edges[:-1] + step / 2
    near = np.flatnonzero(np.abs(centres) < 0.15)
    peaks = near[(counts[near] >= counts[near - 1]) & (counts[near] >= counts[near + 1])]
    if not len(peaks):
        peaks = near
    sclera = int(peaks[np.argmax(counts[peaks])])
    beyond = np.flatnonzero(centres > centres[sclera] + 0.2)
    if not len(beyond) or counts[sclera] <= 0:
        return LID_GAP_MM
    lid = int(beyond[np.argmax(counts[beyond])])
    if counts[lid] >= LID_SHELL_DOMINANCE * counts[sclera] and centres[lid] < LID_GAP_MM:
        return float(0.5 * (centres[sclera] + centres[lid]))
    if counts[lid] < 0.3 * counts[sclera] or not _shells_apart(counts, sclera, lid):
        return LID_GAP_MM
    trough = sclera + int(np.argmin(counts[sclera:lid + 1]))
    return float(np.clip(centres[trough], 0.1, LID_GAP_MM))


def _mean_shift(votes: F64, weights: F64, start: float, bandwidths: Sequence[float]) -> float:
    depth = start
    for bandwidth in bandwidths:
        for _ in range(5):
            near = np.abs(votes - depth) < bandwidth
            if near.sum() < 10:
                return depth
            depth = float(np.average(votes[near], weights=weights[near]))
    return depth


def off_sphere_mm(points: F64, centre: F64, normal: F64, radius: float, depth: float) -> F64:
    """Each point's distance (mm, + outside) from the sphere through the limbus circle
    (``centre``, unit ``normal``, ``radius``; WCS mm) whose centre lies ``depth`` behind it:
    the globe ``C = L − h·g``, ``R = √(h² + r²)``."""
    return distances(points, centre - depth * normal) - math.hypot(depth, radius)


def _fitted_depth(sclera: F64, limbus: Limbus, start: float) -> tuple[float, float]:
    """``h`` by robust least squares of the sclera's distances to the sphere through the
    limbus (soft L1, scale 0.05 mm, from ``start``), and its standard deviation.

    The distance's derivative along ``h`` is the point's depth behind the limbus plane over the
    radius, so this weighs each point's vote by its squared depth as the votes do, but takes
    all of the shell's points where the votes' mode takes those within 0.1 mm of it: a vote's
    own noise (the sclera's ≈ 0.06 mm, four times amplified) is wider than that.
    """
    L, g, r = limbus.centre, limbus.normal, limbus.radius

    def residuals(x: F64) -> F64:
        return off_sphere_mm(sclera, L, g, r, float(x[0]))

    def jacobian(x: F64) -> F64:
        rel = sclera - (L - x[0] * g)
        return np.asarray((rel @ g / distances(rel)
                           - x[0] / math.hypot(x[0], r))[:, None], dtype=np.float64)

    fit = least_squares(residuals, [start], jac=jacobian, loss="soft_l1", f_scale=0.05)
    sigma = 1.4826 * float(np.median(np.abs(fit.fun)))
    slope = jacobian(fit.x)[np.abs(fit.fun) < max(3.0 * sigma, 0.1), 0]
    information = float(slope @ slope)
    if information <= 0:
        return float(fit.x[0]), math.inf
    # The sclera shifted by b moves h by b·Σslope/Σslope² (the bias's gain, 3–8.5 on the
    # simulated eye); the points' own noise averages away, that bias does not.
    gain = abs(float(slope.sum())) / information
    return float(fit.x[0]), math.hypot(sigma / math.sqrt(information),
                                       gain * CLOUD_SCLERA_BIAS_MM)


def behind_limbus(points: F64, limbus: Limbus) -> npt.NDArray[np.bool_]:
    """Which ``points`` (WCS mm) lie behind the limbus's plane (by more than 0.5 mm) and more
    than :data:`LIMBUS_CLEARANCE_MM` from its circle: those that can carry the globe (sclera,
    lids), clear of the cornea and the limbus's own blur."""
    rel = points - limbus.centre
    along = rel @ limbus.normal
    across = distances(rel - along[:, None] * limbus.normal)
    return np.asarray((along < -0.5)
                      & (np.hypot(along, across - limbus.radius) > LIMBUS_CLEARANCE_MM))


def _holds_a_shell(points: F64, limbus: Limbus, inner: float, outer: float) -> bool:
    """Whether the sphere through the limbus at depth ``inner`` (mm) carries a shell of its own
    beside the one at ``outer``: at least half as many of ``points`` within 0.05 mm of it (the
    sclera's noise) as of the other, as :func:`_innermost_depth` asks of an inner peak. Of the
    points behind the limbus, the sclera with lids 0.3 mm outside it does (measured 9,465
    against the lids' 9,406); the noise inside the globe, where the votes' first window can
    start, does not (272 and 372 against the sclera's 1,063 and 1,313 on the `wide` rig)."""
    L, g, r = limbus.centre, limbus.normal, limbus.radius
    at_inner = np.count_nonzero(np.abs(off_sphere_mm(points, L, g, r, inner)) < 0.05)
    at_outer = np.count_nonzero(np.abs(off_sphere_mm(points, L, g, r, outer)) < 0.05)
    return bool(at_inner >= 0.5 * at_outer)


def _left_its_shell(points: F64, limbus: Limbus, start: float, moved: float) -> bool:
    """Whether a refinement of the depth from ``start`` to ``moved`` (mm) left the shell it
    started on for another: it moved more than :data:`DEPTH_REFIT_LIMIT_MM` and ``start``
    holds a shell of its own (:func:`_holds_a_shell`; ``points``: those behind the limbus)."""
    return (abs(moved - start) > DEPTH_REFIT_LIMIT_MM
            and _holds_a_shell(points, limbus, start, moved))


def globe_on_limbus(points: npt.ArrayLike, limbus: Limbus, fixed_radius: float | None = None
                    ) -> Globe:
    """The sphere through the limbus circle that the cloud's sclera lies on.

    A point ``p`` lies on the sphere through the circle with centre ``L − h·g`` when
    ``h = (r² − |p − L|²) / (2 (p − L)·g)``: every point behind the limbus plane (and more
    than :data:`LIMBUS_CLEARANCE_MM` from the limbus) votes for one ``h``, weighted by its
    squared depth behind the plane (the vote's error shrinks with it). The sclera votes sharply
    for its own ``h``; the lids, outside it and on no sphere through the limbus, vote for
    larger, scattered values — often many more of them — so the innermost shell is taken
    (:func:`_innermost_depth`) and refined by weighted mean shift (a shift that leaves it by
    more than :data:`DEPTH_REFIT_LIMIT_MM` where it holds a shell of its own has been drawn
    towards a lid shell, whose points lie further behind the limbus plane and weigh more: it
    starts again from the innermost with narrower windows); then again without the points
    within :data:`LID_CLEARANCE_MM` of the lids, which the band-limited FTM pulls towards them (a
    least-squares fit of the whole cloud's sclera followed those points outwards). The lids begin
    where the points' offsets from that sphere show a shell of their own (:func:`_lid_gap`), as
    close as 0.3 mm outside it, or else :data:`LID_GAP_MM` out. Last, ``h`` is
    fitted by robust least squares to the shell's points clear of the lids (:func:`_fitted_depth`):
    a vote's own noise is wider than the mean shift's last window, whose mode strays with it;
    a fit that leaves the mode by more than :data:`DEPTH_REFIT_LIMIT_MM` has followed a lid
    shell inside the band where the mode holds a shell of its own (:func:`_holds_a_shell`),
    and the mode stays, the move added to its uncertainty. A
    ``fixed_radius`` (the patient's model) sets ``h`` outright; the sclera then only measures how
    well the model fits, and a limbus with too little sclera beside it (one unit seeing the eye
    turned away) still places the globe, its surface distance that of what lies behind the limbus
    (lids), so that its confidence drops.

    The depth is ill-conditioned: a sclera point at polar angle θ from the gaze moves off the
    sphere by only (cos θ − cos θ_limbus) ≈ −0.2 per millimetre of ``h`` over the visible
    band (θ ≈ 40–65°), so a radial bias of the reconstructed sclera is amplified about four
    times into the radius, and about five times into the centre along the gaze. What is left
    of that bias, per pose, sets the depth's stated uncertainty
    (:data:`CLOUD_SCLERA_BIAS_MM`). The gaze's tilt is the limbus's, not fitted to the sclera,
    whose own bias would pull it further off than the limbus is. Measured:
    docs/notes/limbus.md.
    """
    cloud = np.asarray(points, dtype=np.float64)
    L, g, r = limbus.centre, limbus.normal, limbus.radius
    behind = behind_limbus(cloud, limbus)
    votes, weights = _votes(cloud, limbus, behind)
    clear = np.ones(len(cloud), dtype=bool)
    if fixed_radius is not None:
        depth = math.sqrt(max(fixed_radius**2 - r**2, 1.0))
    else:
        innermost = _innermost_depth(votes)
        depth = _mean_shift(votes, weights, innermost, (0.4, 0.25, 0.15, 0.1))
        if _left_its_shell(cloud[behind], limbus, innermost, depth):
            depth = _mean_shift(votes, weights, innermost, (0.15, 0.1))
    offset = off_sphere_mm(cloud, L, g, r, depth)
    gap = _lid_gap(offset[behind])
    band = min(gap, 0.3)  # the sclera's points: within this (mm) of the sphere
    # Only points that can be sclera are looked up (an eighth of the cloud or less), among the
    # lid points that can lie within the clearance of one (no further out than the two bands).
    candidate = behind & (np.abs(offset) < gap)
    lids = cloud[(offset > gap) & (offset < gap + LID_CLEARANCE_MM)]
    if len(lids) and candidate.any():
        distance, _ = cKDTree(lids).query(cloud[candidate],
                                          distance_upper_bound=LID_CLEARANCE_MM)
        far = np.zeros(len(cloud), dtype=bool)
        far[candidate] = ~np.isfinite(distance)
        if (far & (np.abs(offset) < band)).sum() >= MIN_SCLERA_POINTS:
            clear = far
            if fixed_radius is None:
                votes, weights = _votes(cloud, limbus, behind & clear)
                depth = _mean_shift(votes, weights, depth, (0.25, 0.15, 0.1))
    offset = off_sphere_mm(cloud, L, g, r, depth)
    sclera = behind & clear & (np.abs(offset) < band)
    fitted_sd = None
    two_shells = False
    if fixed_radius is None and sclera.sum() >= MIN_SCLERA_POINTS:
        mode = depth
        depth, fitted_sd = _fitted_depth(cloud[sclera], limbus, mode)
        two_shells = _left_its_shell(cloud[behind], limbus, mode, depth)
        if two_shells:  # not a refinement: another shell
            depth, fitted_sd = mode, math.hypot(fitted_sd, depth - mode)
        offset = off_sphere_mm(cloud, L, g, r, depth)
        sclera = behind & clear & (np.abs(offset) < band)
    if sclera.sum() < MIN_SCLERA_POINTS:
        if fixed_radius is None:
            raise LimbusNotFoundError("too little sclera beside the limbus to place the globe")
        # The model's radius places the globe on the limbus alone (one unit can see the limbus
        # whole and no sclera beside it: measured, 0.08 mm against 1.3 mm for the cloud-only
        # pose); what lies behind the limbus near that sphere (lids, mostly) says how little
        # carries it, which drops the pose's confidence.
        carrying = behind & (np.abs(offset) < 1.5)
        if not carrying.any():
            carrying = behind
        mad = float(np.median(np.abs(offset[carrying]))) if carrying.any() else 1.5
        points = int((behind & (np.abs(offset) < 0.3)).sum())
        return Globe(centre=L - depth * g, radius=math.hypot(depth, r), depth_sd_mm=0.0,
                     points=points, surface_mad_mm=mad, support=points)
    near = np.abs(votes - depth) < 0.1
    depth_sd = 0.0 if fitted_sd is None else fitted_sd
    return Globe(centre=L - depth * g, radius=math.hypot(depth, r), depth_sd_mm=depth_sd,
                 points=int(sclera.sum()),
                 surface_mad_mm=float(np.median(np.abs(offset[sclera]))),
                 support=int(sclera.sum()) if fixed_radius is not None else int(near.sum()),
                 sclera=cloud[sclera], two_shells=two_shells)
