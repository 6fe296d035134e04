"""The sclera measured again from its own fringes, and the globe and gaze it carries with the
limbus (docs/design.md §4 step 8).

Why. The globe's depth behind the limbus is ill-conditioned: a radial error of the sclera is
amplified 3–8 times into the centre (:func:`~eyeserver.eye.limbus.globe_on_limbus`). The
band-limited Fourier demodulation blends each pixel's phase with its neighbours' over about a
fringe period, and the visible sclera is a band only a few periods wide between the dark
cornea and the lids, most of it within a period of where its fringe field ends: the
reconstructed sclera lies off the globe by a different offset in each camera and pose. The
fringes themselves are not off: fitted locally, with a smooth background and amplitude, they
give the true phase.

What. :func:`remeasured` takes, in every camera, the pixels that see a globe hypothesis (a
sphere; WCS, mm) where the cloud's sclera lies, predicts their phase from the sphere through the
calibration (:meth:`~eyeserver.pipeline.phase_height.PhaseHeightModel.phase` plus the reference
phase), and fits ``I = a + p·cos ψ + q·sin ψ`` over :data:`WINDOW_PX` squares of those pixels
only, never across the field's edge: ``δ = atan2(−q, p)`` (rad) is how far the pixel's phase lies
from the sphere's, ``Z`` follows from the phase ``Δφ̂ + δ``, and the point from the pixel's ray at
that height. A window is the only filter, and it holds nothing but sclera. Left out: pixels with
a lid in front of the sphere (:data:`IN_FRONT_MM`), unsure windows (:data:`MAX_PHASE_SD_RAD`),
pixels more than :data:`MAX_OFFSET_RAD` off, and, after :data:`ROUNDS` fits, pixels whose fringe
is fainter than most of the sclera's (:data:`MIN_AMPLITUDE`), whose windows read a biased phase.

The limbus found again. The band's fringe-free intensity ``I − B·cos φ`` blends ``B`` and ``φ``
across the limbus too, so each edge found in it moves with the fringe's phase there.
:func:`sharpened` divides each camera's image by the illumination ``a + p·cos ψ + q·sin ψ``,
``ψ`` the phase the globe hypothesis predicts, ``a, p, q`` fitted over :data:`WINDOW_PX` squares
of the sclera beyond the limbus (from :data:`LIMBUS_MARGIN_MM` behind its plane on, clear of the
edge's blur), each pixel up to and inside the limbus taking the nearest window's. What is left
is the albedo's step, whatever the fringe's phase at the edge; the limbus's last round runs again
in that image. Dividing needs no position of the edge, where subtracting a fringe cut off at the
edge would.

:func:`globe_and_gaze` then fits the globe to the remeasured points together with the limbus:
centre ``L' − h·g'`` with ``g'`` the limbus normal tilted and ``L'`` its centre shifted, each held
to the limbus's measurement within its uncertainty. The sclera counts as a whole, good to
:data:`REMEASURED_SCLERA_BIAS_MM`, so it moves the gaze only where it says so more precisely than
the limbus does. :func:`refit` runs :data:`PASSES` passes of the three, each about the last one's
globe. It costs ≈ 0.3 s a fit; live tracking (radius held) leaves it out. What each step gained,
how the windows and margins were chosen, and what is left: docs/notes/sclera.md. The constants:
:mod:`eyeserver.eye.tunables`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt
from scipy.ndimage import distance_transform_edt
from scipy.optimize import least_squares
from scipy.spatial import cKDTree

from eyeserver.core.arrays import distances
from eyeserver.core.types import F64
from eyeserver.eye.limbus import (
    Limbus,
    LimbusNotFoundError,
    LimbusView,
    Shade,
    circle_points,
    off_sphere_mm,
    refined,
)
from eyeserver.eye.tunables import (
    IN_FRONT_MM,
    LIMBUS_MARGIN_MM,
    MAX_OFFSET_RAD,
    MAX_PHASE_SD_RAD,
    MIN_AMPLITUDE,
    MIN_ILLUMINATION,
    MIN_REMEASURED_POINTS,
    MIN_SHARE,
    NEAR_MM,
    OUTSIDE_MM,
    PASSES,
    REMEASURED_SCLERA_BIAS_MM,
    ROBUST_MM,
    ROUNDS,
    WINDOW_PX,
)
from eyeserver.pipeline.geometry import project, rays_from_normalised, undistorted_normalised
from eyeserver.pipeline.reconstruct import CalibratedCamera

__all__ = ["GlobeFit", "globe_and_gaze", "refit", "remeasured", "sharpened"]


def remeasured(views: Sequence[LimbusView], centre: F64, radius: float, sclera: F64,
               cloud: F64 | None = None) -> F64:
    """The sclera's points measured again from each camera's fringes, about a sphere.

    ``centre`` and ``radius``: the globe hypothesis; ``sclera``: the cloud's sclera points,
    which say where on the sphere the sclera is seen (within :data:`NEAR_MM`); ``cloud``: what
    else was reconstructed (None: the sclera alone), which says what hides it from a camera
    (lids in front of the sphere along its ray, :data:`IN_FRONT_MM`). Returns (N, 3) points in
    the WCS, each camera's pixels one point each (empty where nothing is seen).
    """
    centre = np.asarray(centre, dtype=np.float64)
    return _remeasured(views, centre, radius, cKDTree(sclera), _occluders(cloud, centre, radius))


def _remeasured(views: Sequence[LimbusView], centre: F64, radius: float, tree: cKDTree,
                occluders: F64) -> F64:
    """:func:`remeasured` with the sclera's k-d tree and the occluders made."""
    parts = [_camera_points(view, centre, radius, tree, occluders) for view in views]
    return np.concatenate(parts) if parts else np.empty((0, 3))


def _occluders(cloud: F64 | None, centre: F64, radius: float) -> F64:
    """The cloud's points that can hide a sphere from a camera: what lies outside it (the lids,
    ≈ 1–3 mm outside); the sclera itself, however far the hypothesis is off, cannot."""
    occluders: F64 = np.empty((0, 3)) if cloud is None else np.asarray(cloud, dtype=np.float64)
    reach = distances(occluders, centre) - radius
    kept: F64 = occluders[(reach > OUTSIDE_MM) & (reach < 4.0)]
    return kept


def _camera_points(view: LimbusView, centre: F64, radius: float, tree: cKDTree,
                   occluders: F64) -> F64:
    """:func:`remeasured` in one camera, in the window about the sclera's projection."""
    cam = view.camera
    uv = project(np.asarray(tree.data, dtype=np.float64), cam.K, cam.dist, cam.R, cam.T)
    seen = np.all(np.isfinite(uv), axis=1)
    if seen.sum() < MIN_REMEASURED_POINTS:
        return np.empty((0, 3))
    window = _window_about(cam, uv[seen], WINDOW_PX)
    if window is None:
        return np.empty((0, 3))
    pixels = _SpherePixels(cam, window, centre, radius, occluders)
    near = np.zeros(pixels.seen.shape, dtype=bool)
    if pixels.seen.any():
        distance, _ = tree.query(pixels.on_sphere[pixels.seen], distance_upper_bound=NEAR_MM)
        near[pixels.seen] = np.isfinite(distance)
    if near.sum() < MIN_REMEASURED_POINTS:
        return np.empty((0, 3))
    dphi = np.where(near, pixels.dphi, 0.0)
    offset, mask = _offsets(pixels.crop(view.image), dphi + pixels.reference,
                            near & np.isfinite(dphi))
    if mask.sum() < MIN_REMEASURED_POINTS:
        return np.empty((0, 3))
    z = cam.model.height(pixels.x[mask], pixels.y[mask], dphi[mask] + offset[mask])
    ray = pixels.rays[mask]
    origin = cam.centre
    return np.asarray(origin + ((z - origin[2]) / ray[:, 2])[:, None] * ray, dtype=np.float64)


def _window_about(cam: CalibratedCamera, uv: F64, margin: int
                  ) -> tuple[int, int, int, int] | None:
    """The image window ``(x0, y0, x1, y1)`` holding ``uv`` and ``margin`` pixels about them,
    or None where too little of it lies in the image."""
    height, width = cam.shape
    x0, y0 = np.floor(uv.min(axis=0)).astype(int) - margin
    x1, y1 = np.ceil(uv.max(axis=0)).astype(int) + margin + 1
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, width), min(y1, height)
    if x1 - x0 < WINDOW_PX or y1 - y0 < WINDOW_PX:
        return None
    return int(x0), int(y0), int(x1), int(y1)


class _SpherePixels:
    """Where each pixel of a window ``(x0, y0, x1, y1)`` sees a sphere, and the phase the
    calibration predicts there."""

    def __init__(self, cam: CalibratedCamera, window: tuple[int, int, int, int], centre: F64,
                 radius: float, occluders: F64) -> None:
        self.window = window
        x0, y0, x1, y1 = window
        v, u = np.mgrid[y0:y1, x0:x1].astype(np.float64)
        self.x, self.y = undistorted_normalised(u, v, cam.K, cam.dist)
        self.rays = rays_from_normalised(self.x, self.y, cam.R)
        unit = self.rays / np.linalg.norm(self.rays, axis=-1, keepdims=True)
        # The ray's first meeting with the sphere.
        oc = cam.centre - centre
        b = unit @ oc
        disc = b * b - (oc @ oc - radius * radius)
        self.hit = disc > 0
        """The ray meets the sphere."""
        t = -b - np.sqrt(np.where(self.hit, disc, 0.0))
        self.seen = self.hit & (t < _nearest_along_rays(cam, occluders, window) + IN_FRONT_MM)
        """... and nothing of the cloud hides it there."""
        self.on_sphere = cam.centre + t[..., None] * unit
        self.dphi = np.where(self.hit, cam.model.phase(self.x, self.y, self.on_sphere[..., 2]),
                             np.nan)
        """The phase relative to the reference that the sphere gives (NaN off it)."""
        self.reference = self.crop(cam.reference_phase)

    def crop(self, image: npt.ArrayLike) -> F64:
        x0, y0, x1, y1 = self.window
        return np.asarray(np.asarray(image)[y0:y1, x0:x1], dtype=np.float64)


def sharpened(views: Sequence[LimbusView], limbus: Limbus, centre: F64, radius: float,
              cloud: F64 | None = None, cornea_radius: float | None = None) -> Limbus:
    """The limbus found again (its last round of edges, :func:`~eyeserver.eye.limbus.
    refined`) in images whose fringe is divided out: in each camera, ``I / (a + p·cos ψ +
    q·sin ψ)`` with ``ψ`` the phase the globe hypothesis (``centre``, ``radius``) predicts and
    ``a, p, q`` fitted over :data:`WINDOW_PX` squares of the sclera beyond the
    limbus (:data:`LIMBUS_MARGIN_MM`), carried to the limbus and the cornea from the nearest
    fit; ``cloud`` as for :func:`remeasured` (what may hide the sclera from a camera);
    ``cornea_radius`` (mm, the eye model's): the edges where the cornea shadows the sclera
    beyond the limbus from the camera's projector are left out (None: kept). ``limbus`` itself
    where no camera pair gives a circle."""
    centre = np.asarray(centre, dtype=np.float64)
    return _sharpened(views, limbus, centre, radius, _occluders(cloud, centre, radius),
                      cornea_radius)


def _sharpened(views: Sequence[LimbusView], limbus: Limbus, centre: F64, radius: float,
               occluders: F64, cornea_radius: float | None = None) -> Limbus:
    """:func:`sharpened` with the occluders made."""
    divided = [LimbusView(view.camera, view.image, flat) if (
        flat := _illumination_divided(view, limbus, centre, radius, occluders)) is not None
        else view for view in views]
    try:
        return refined(divided, limbus, None if cornea_radius is None
                       else Shade(centre, radius, cornea_radius))
    except LimbusNotFoundError:
        return limbus


def _illumination_divided(view: LimbusView, limbus: Limbus, centre: F64, radius: float,
                          occluders: F64) -> npt.NDArray[np.float32] | None:
    """:func:`sharpened`'s image for one camera, scaled to the sclera's median background (None
    where too little sclera is seen near the limbus)."""
    cam = view.camera
    on = circle_points(limbus, np.linspace(0.0, 2 * math.pi, 90, endpoint=False))
    uv = project(on, cam.K, cam.dist, cam.R, cam.T)
    if not np.all(np.isfinite(uv)):
        return None
    window = _window_about(cam, uv, 2 * WINDOW_PX)
    if window is None:
        return None
    pixels = _SpherePixels(cam, window, centre, radius, occluders)
    psi = pixels.dphi + pixels.reference
    along = np.where(pixels.hit, (pixels.on_sphere - limbus.centre) @ limbus.normal, np.inf)
    sclera = pixels.seen & (along < -LIMBUS_MARGIN_MM) & np.isfinite(psi)
    if sclera.sum() < WINDOW_PX**2:
        return None
    image = pixels.crop(view.image)
    # Fits are needed only near the limbus: the band of the sphere from a millimetre behind
    # the sclera's margin to half a millimetre in front of the limbus.
    near = (along > -LIMBUS_MARGIN_MM - 1.0) & (along < 0.5)
    fit = _window_fits(image, psi, sclera, WINDOW_PX, near)
    coefficients = np.zeros((*sclera.shape, 3))
    coefficients[fit.fitted] = fit.solution
    # Every pixel takes the nearest fit's background and fringe, at its own phase.
    _, (rows, cols) = distance_transform_edt(~fit.fitted, return_indices=True)
    a, p, q = np.moveaxis(coefficients[rows, cols], -1, 0)
    scale = float(np.median(a[sclera]))
    if not scale > 0:
        return None
    illumination = np.where(np.isfinite(psi), a + p * np.cos(psi) + q * np.sin(psi), a)
    out = np.array(view.image, dtype=np.float32)
    x0, y0, x1, y1 = window
    out[y0:y1, x0:x1] = scale * image / np.maximum(illumination, MIN_ILLUMINATION * scale)
    return out


def _nearest_along_rays(cam: CalibratedCamera, points: F64,
                        window: tuple[int, int, int, int]) -> F64:
    """Per pixel of ``window`` ``(x0, y0, x1, y1)``, the distance from the camera to the
    nearest of ``points`` seen there (a z-buffer; inf where none). Each point covers its pixel
    and, where the cloud is sparser than the pixels (another camera's points), its 3 × 3
    neighbours."""
    x0, y0, x1, y1 = window
    nearest = np.full((y1 - y0, x1 - x0), np.inf)
    if not len(points):
        return nearest
    uv = project(points, cam.K, cam.dist, cam.R, cam.T)
    col, row = np.round(uv[:, 0]).astype(int) - x0, np.round(uv[:, 1]).astype(int) - y0
    inside = (col >= 0) & (col < x1 - x0) & (row >= 0) & (row < y1 - y0)
    depth = distances(points[inside], cam.centre)
    np.minimum.at(nearest, (row[inside], col[inside]), depth)
    return np.asarray(cv2.erode(nearest, np.ones((3, 3), np.uint8),
                                borderType=cv2.BORDER_REPLICATE), dtype=np.float64)


def _offsets(image: F64, psi: F64, mask: npt.NDArray[np.bool_]
             ) -> tuple[F64, npt.NDArray[np.bool_]]:
    """How far each pixel's phase lies from ``psi`` (:func:`_local_offsets`, :data:`ROUNDS`
    times, each about the last one's phase), and which of the ``mask``'s pixels keep it: those
    whose phase is sure (:data:`MAX_PHASE_SD_RAD`), within :data:`MAX_OFFSET_RAD` and well lit
    (:data:`MIN_AMPLITUDE`)."""
    mask = mask.copy()
    offset = np.zeros(mask.shape)
    for _ in range(ROUNDS):
        delta, sd, _ = _local_offsets(image, psi + offset, mask)
        fitted = sd <= MAX_PHASE_SD_RAD
        offset = np.where(fitted, offset + delta, offset)
        mask &= fitted & (np.abs(offset) <= MAX_OFFSET_RAD)
    # The amplitude over the pixels kept (a window fit needs MIN_SHARE of them).
    _, _, amplitude = _local_offsets(image, psi + offset, mask)
    if mask.any():
        mask &= amplitude >= MIN_AMPLITUDE * np.median(amplitude[mask])
    return offset, mask


def _local_offsets(image: F64, psi: F64, mask: npt.NDArray[np.bool_]
                   ) -> tuple[F64, F64, F64]:
    """Per pixel, the phase offset ``δ`` of ``I = a + B·cos(ψ + δ)`` fitted by least squares
    over the mask's pixels in the :data:`WINDOW_PX` square about it, its standard deviation
    from the fit's residual (inf where no fit was made) and the amplitude ``B`` (0 there).

    Linear in ``(a, B cos δ, −B sin δ)`` (:func:`_window_fits`). ``a`` and ``B`` are held
    constant in a window: shading that changes the amplitude by 7 % across one reads as
    ≈ 0.013 rad of phase (synthetic fringes). Letting them vary linearly takes that out on
    noise-free fringes, but within less than a fringe period a linear amplitude is nearly a
    phase: on 36 rendered poses the globe centre came out 0.26 mm off (median, 15-px windows)
    against 0.056 mm.
    """
    fit = _window_fits(image, psi, mask, WINDOW_PX, mask)
    solution = fit.solution
    amplitude = np.hypot(solution[:, 1], solution[:, 2])
    sigma = np.sqrt(fit.residual / np.maximum(fit.count - 3.0, 1.0))
    delta = np.zeros(mask.shape)
    delta[fit.fitted] = np.arctan2(-solution[:, 2], solution[:, 1])
    sd = np.full(mask.shape, np.inf)
    # The phase's sd from the residual: σ / (B·√(n/2)).
    sd[fit.fitted] = np.where(fit.well & (amplitude > 0),
                              sigma / np.maximum(amplitude, 1e-12) / np.sqrt(fit.count / 2.0),
                              np.inf)
    amplitudes = np.zeros(mask.shape)
    amplitudes[fit.fitted] = amplitude
    return delta, sd, amplitudes


@dataclass(frozen=True)
class _WindowFits:
    fitted: npt.NDArray[np.bool_]
    """Where a fit was made."""
    solution: F64
    """``(a, p, q)`` of ``I = a + p·cos ψ + q·sin ψ`` at each fitted pixel (K, 3); zeros where
    the system is singular (not ``well``)."""
    well: npt.NDArray[np.bool_]
    count: F64
    """The mask's pixels in each fitted pixel's window."""
    residual: F64
    """Their sum of squared residuals."""


def _window_fits(image: F64, psi: F64, mask: npt.NDArray[np.bool_], size: int,
                 where: npt.NDArray[np.bool_]) -> _WindowFits:
    """``I = a + p·cos ψ + q·sin ψ`` fitted by least squares over the mask's pixels in the
    ``size`` square about each pixel of ``where`` that has at least :data:`MIN_SHARE` of its
    window in the mask. The sums of the normal equations (and ``ΣI²`` for the residual) are
    box filters of the masked products (OpenCV), the 3 × 3 systems solved together."""
    weight = mask.astype(np.float64)
    c, s = np.cos(np.where(mask, psi, 0.0)), np.sin(np.where(mask, psi, 0.0))
    values = np.where(mask, image, 0.0)

    def box(product: F64) -> F64:
        return np.asarray(cv2.boxFilter(product * weight, -1, (size, size), normalize=False,
                                        borderType=cv2.BORDER_CONSTANT), dtype=np.float64)

    n, sc, ss = box(np.ones_like(c)), box(c), box(s)
    scs = box(c * s)
    fitted = where & (n >= MIN_SHARE * size**2)
    normal = np.stack([np.stack([n, sc, ss], axis=-1), np.stack([sc, box(c * c), scs], axis=-1),
                       np.stack([ss, scs, box(s * s)], axis=-1)], axis=-2)[fitted]
    rhs = np.stack([box(values), box(values * c), box(values * s)], axis=-1)[fitted]
    # Well conditioned (det / trace³ bounds 1 / cond from below; np.linalg.cond's SVDs of the
    # many 3 × 3 systems cost ten times as much).
    well = np.linalg.det(normal) > 1e-10 * np.trace(normal, axis1=-2, axis2=-1) ** 3
    solution = np.zeros_like(rhs)
    solution[well] = np.linalg.solve(normal[well], rhs[well][..., None])[..., 0]
    # The residual's sum of squares from the normal equations: ΣI² − x·rhs.
    residual = np.maximum(box(values * values)[fitted]
                          - np.einsum("ij,ij->i", solution, rhs), 0.0)
    return _WindowFits(fitted, solution, well, n[fitted], residual)


@dataclass(frozen=True)
class GlobeFit:
    """The globe and gaze that the remeasured sclera and the limbus give together."""

    centre: F64
    radius: float
    gaze: F64
    limbus_centre: F64
    centre_cov: F64
    """3 × 3 covariance of ``centre`` (mm²)."""
    gaze_sd_deg: float
    limbus_sd_mm: float
    limbus: Limbus
    """The limbus it was fitted with."""


Surface = Callable[[F64, F64, F64], F64]
"""Distances (mm, + outside) of points from a held globe's surface given its centre and gaze:
an ellipsoidal globe's (:mod:`~eyeserver.eye.fit`), where a sphere's would not fit its sclera."""


def globe_and_gaze(points: F64, limbus: Limbus, depth: float, fixed_radius: float | None,
                   surface: Surface | None = None) -> GlobeFit:
    """The sphere through the limbus circle that fits ``points`` (remeasured sclera), the
    circle's tilt and centre free within the limbus's uncertainty.

    Parameters ``h`` (the depth, from ``depth``; held where ``fixed_radius`` is given), two
    tilts of the gaze and three shifts of the limbus centre. The points' distances
    to the sphere are soft-L1 robust at :data:`ROBUST_MM` (lids and speckle off the sphere
    count little) and weighed so that together they say what one measurement good to
    :data:`REMEASURED_SCLERA_BIAS_MM` says; the tilts and shifts are held to 0 by the limbus's
    per-axis uncertainties. ``surface``, with a ``fixed_radius``: the points' distances from the
    patient's own globe in place of the sphere's.
    """
    pts = np.asarray(points, dtype=np.float64)
    L, g, r = limbus.centre, limbus.normal, limbus.radius
    e1 = np.cross(g, [0.0, 1.0, 0.0])
    if np.linalg.norm(e1) < 1e-6:
        e1 = np.cross(g, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(g, e1)
    tilt_sd = max(math.radians(limbus.gaze_sd_deg) / math.sqrt(2.0), 1e-6)
    shift_sd = max(limbus.centre_sd_mm / math.sqrt(3.0), 1e-6)
    weight = 1.0 / (REMEASURED_SCLERA_BIAS_MM * math.sqrt(len(pts)))
    if fixed_radius is not None:
        depth = math.sqrt(max(fixed_radius**2 - r**2, 1.0))

    def unpack(x: F64) -> tuple[F64, F64, float]:
        h = depth if fixed_radius is not None else float(x[0])
        a1, a2, s1, s2, s3 = x[-5:]
        gaze = g + a1 * e1 + a2 * e2
        gaze /= np.linalg.norm(gaze)
        return L + s1 * e1 + s2 * e2 + s3 * g, gaze, h

    def residuals(x: F64) -> F64:
        centre_l, gaze, h = unpack(x)
        if surface is not None and fixed_radius is not None:
            distance = surface(pts, centre_l - h * gaze, gaze)
        else:
            distance = off_sphere_mm(pts, centre_l, gaze, r, h)
        # soft L1 as a residual (its square is the loss), so the priors stay quadratic.
        robust = np.sign(distance) * ROBUST_MM * np.sqrt(
            2.0 * (np.sqrt(1.0 + (distance / ROBUST_MM) ** 2) - 1.0))
        prior = x[-5:] / np.array([tilt_sd, tilt_sd, shift_sd, shift_sd, shift_sd])
        return np.concatenate([weight * robust, prior])

    start = np.zeros(5) if fixed_radius is not None else np.r_[depth, np.zeros(5)]
    fit = least_squares(residuals, start, x_scale="jac")
    centre_l, gaze, h = unpack(fit.x)
    centre = centre_l - h * gaze
    # Covariances from the Jacobian at the solution (the residuals are in units of their sd),
    # carried to the centre, the gaze and the limbus centre by central differences.
    cov = np.linalg.pinv(fit.jac.T @ fit.jac)

    def spread(f: Callable[[F64], F64]) -> F64:
        steps = 1e-6 * np.eye(len(fit.x))
        jac = np.stack([(f(fit.x + d) - f(fit.x - d)) / 2e-6 for d in steps], axis=1)
        return np.asarray(jac @ cov @ jac.T, dtype=np.float64)

    def centre_of(x: F64) -> F64:
        centre_l, gaze, h = unpack(x)
        return centre_l - h * gaze

    return GlobeFit(centre=centre, radius=math.hypot(h, r), gaze=gaze, limbus_centre=centre_l,
                    centre_cov=spread(centre_of),
                    gaze_sd_deg=math.degrees(math.sqrt(float(np.trace(
                        spread(lambda x: unpack(x)[1]))))),
                    limbus_sd_mm=math.sqrt(float(np.trace(spread(lambda x: unpack(x)[0])))),
                    limbus=limbus)


def refit(views: Sequence[LimbusView], limbus: Limbus, centre: F64, radius: float,
          sclera: F64, cloud: F64, fixed_radius: float | None,
          cornea_radius: float | None = None, surface: Surface | None = None
          ) -> GlobeFit | None:
    """The globe and gaze from the sclera remeasured about the globe ``centre``, ``radius``
    (:func:`~eyeserver.eye.limbus.globe_on_limbus`'s, whose ``sclera`` points say where
    it is seen; ``cloud`` what may hide it, see :func:`remeasured`) and the limbus found again
    about it (:func:`sharpened`, with the cornea's shadow where ``cornea_radius`` is given), in
    :data:`PASSES` passes; None where too little sclera is remeasured. ``surface`` as
    :func:`globe_and_gaze`."""
    fit = None
    tree = cKDTree(sclera)
    for _ in range(PASSES):
        # What hides the sphere depends on the sphere: made once a pass, for both steps.
        occluders = _occluders(cloud, centre, radius)
        points = _remeasured(views, centre, radius, tree, occluders)
        if len(points) < MIN_REMEASURED_POINTS:
            return fit
        limbus = _sharpened(views, limbus, centre, radius, occluders, cornea_radius)
        depth = math.sqrt(max(radius**2 - limbus.radius**2, 1.0))
        fit = globe_and_gaze(points, limbus, depth, fixed_radius, surface)
        centre, radius = fit.centre, fit.radius
    return fit
