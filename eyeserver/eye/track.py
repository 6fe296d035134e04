"""The eye followed from frame to frame: a warm-started fit and the image window the eye is in.

Live tracking (:mod:`eyeserver.service.tracking`) knows the last frame's pose. Between two
camera frames (40 ms) the globe's centre moves by the head's drift, hundredths of a millimetre,
and not at all when the eye turns (a globe turns about its own centre); its radius never
changes. So the global search of :func:`~eyeserver.eye.fit.fit_eye` (voxel means,
normals, the Hough vote, the shell search) is not needed again:

1. **Where to look** (:func:`eye_window`, :func:`pose_window`): the front of the globe and
   the lids around it (once the limbus is found in the images, the cap about the gaze that
   holds it), projected into a camera, padded for motion and the band-pass's reach, rounded out to
   :data:`WINDOW_QUANTUM_PX` so that cropped cameras can be cached per window
   (:func:`~eyeserver.pipeline.reconstruct.cropped`).
2. **With the images** (``views`` of :func:`track_eye`): the limbus found in them from the last
   pose (:func:`~eyeserver.eye.limbus.find_limbus`) and the sphere of the held radius
   through it that fits the sclera (:func:`~eyeserver.eye.limbus.globe_on_limbus`): the
   global fit's own steps with images, only the search for a first globe skipped, so the
   tracked pose is the one a reference captured with the global fit is compared with.
   Where the limbus is not found and the lids cover the front of the last globe
   (:func:`lids_closed`), the frame is a blink: the last globe and gaze are kept with the gaze
   source ``"none"`` (the beam is held; the next frame looks for the limbus from the last
   gaze again), because closed lids, a shell concentric with the globe about a millimetre
   outside it, are what step 3 and the global fit take for the sclera. Steps 3 and 4 are what
   is left when the limbus is not found otherwise.
3. **The globe** from the cloud alone: the points near the last sphere; the lid shell found
   about a millimetre outside it (the radial histogram around the last centre); a robust
   geometric fit of the sclera jointly with the concentric lid shell, the radius held at the
   last one. The sclera and the lids are told apart by which shell a point lies nearer
   (within half their gap), so the fit starts from a centre up to about half the gap off
   (≈ 0.6 mm in the simulated room); without lids, from up to :data:`WARM_FIT_BAND_MM`. Then
   the bands shrink as in :func:`~eyeserver.eye.fit.fit_eye`, whose refinement it shares.
4. **The gaze** from the cloud alone: as :func:`~eyeserver.eye.fit.fit_eye` finds
   it (the edge circle, the widest empty cone, a corneal cap), from the same start (the mean
   direction of what lies around the globe), not from the last gaze: the empty cone's score
   has several optima, and a search from the last gaze settled on another one than the global
   fit's. The cone search is this path's largest cost. Measured: docs/notes/tracking.md.

A cloud that leaves too few points near the last sphere raises
:class:`~eyeserver.eye.fit.PoseError`: the caller falls back on the global fit. The constants:
:mod:`eyeserver.eye.tunables`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from eyeserver.core.arrays import distances, rows_where
from eyeserver.core.types import F64
from eyeserver.eye.fit import (
    LIMBUS_FROM_IMAGES,
    CloudLike,
    EyeModel,
    EyePose,
    Gaze,
    PoseError,
    # Private helpers of fit_eye, shared rather than copied: the warm fit must give the same
    # globe as the global one.
    _radial_shells,
    _refine_globe,
    checked_cloud,
    cloud_gaze,
    pose_from_cloud,
    pose_on_limbus,
)
from eyeserver.eye.limbus import (
    LimbusView,
    _basis,  # the limbus circle's frame, shared, not copied
)
from eyeserver.eye.tunables import (
    FRONT_HALF_ANGLE_DEG,
    LID_REACH_MM,
    LIDS_COVER_SHARE,
    LIMBUS_HALF_ANGLE_DEG,
    MAX_LID_POINTS,
    MIN_SCLERA_POINTS,
    MOTION_MM,
    PAD_PERIODS,
    WARM_FIT_BAND_MM,
    WARM_FIT_COARSE_BANDS_MM,
    WARM_FIT_REFINE_BANDS_MM,
    WINDOW_QUANTUM_PX,
)
from eyeserver.pipeline.geometry import project
from eyeserver.pipeline.reconstruct import CalibratedCamera

__all__ = ["eye_window", "lids_closed", "pose_window", "track_eye"]


def eye_window(camera: CalibratedCamera, centre_mm: npt.ArrayLike, radius_mm: float, *,
               axis: npt.ArrayLike = (0.0, 0.0, 1.0),
               half_angle_deg: float = FRONT_HALF_ANGLE_DEG,
               motion_mm: float = MOTION_MM, pad_periods: float = PAD_PERIODS,
               quantum_px: int = WINDOW_QUANTUM_PX) -> tuple[int, int, int, int] | None:
    """The image window ``(x0, y0, x1, y1)`` that holds the eye of a globe seen by ``camera``.

    The cap of the lid shell (the globe's radius plus :data:`LID_REACH_MM` and ``motion_mm``)
    within ``half_angle_deg`` of ``axis`` is projected; its bounding box is padded by
    ``pad_periods`` fringe periods, rounded outwards to multiples of ``quantum_px`` and clipped
    to the image.

    Parameters
    ----------
    camera : CalibratedCamera
        The whole image's camera.
    centre_mm : array_like, shape (3,)
        The globe's centre, WCS mm.
    radius_mm : float
        The globe's radius, mm.
    axis : array_like, shape (3,)
        The cap's axis (WCS; default +Z, towards the cameras).
    half_angle_deg : float
        The cap's half angle (default :data:`FRONT_HALF_ANGLE_DEG`).
    motion_mm, pad_periods : float
        Allowance for motion (mm) and padding (fringe periods).
    quantum_px : int
        The window's corners are multiples of this (or the image's edges).

    Returns
    -------
    tuple of int or None
        Columns ``x0 ≤ j < x1`` and rows ``y0 ≤ i < y1``; None when the eye's front does not
        project into the image at all.

    Raises
    ------
    ValueError
        A centre that is not three finite numbers, a radius that is not positive, or a zero
        axis.
    """
    centre = np.asarray(centre_mm, dtype=np.float64)
    if centre.shape != (3,) or not np.isfinite(centre).all():
        raise ValueError(f"centre_mm must be three finite numbers, not {centre_mm!r}")
    if not radius_mm > 0:
        raise ValueError(f"radius_mm must be positive, not {radius_mm}")
    if quantum_px < 1:
        raise ValueError(f"quantum_px must be at least 1, not {quantum_px}")
    pole = np.asarray(axis, dtype=np.float64)
    if pole.shape != (3,) or not np.linalg.norm(pole) > 0:
        raise ValueError(f"axis must be a non-zero 3-vector, not {axis!r}")
    pole = pole / np.linalg.norm(pole)
    polar = np.radians(np.linspace(0.0, half_angle_deg, 6))
    azimuth = np.radians(np.arange(0.0, 360.0, 15.0))
    p, a = np.meshgrid(polar, azimuth)
    u, v = _basis(pole)
    directions = (np.sin(p)[..., None] * (np.cos(a)[..., None] * u + np.sin(a)[..., None] * v)
                  + np.cos(p)[..., None] * pole).reshape(-1, 3)
    reach = radius_mm + LID_REACH_MM + motion_mm
    points = centre + reach * directions
    uv = project(points, camera.K, camera.dist, camera.R, camera.T)
    uv = uv[np.isfinite(uv).all(axis=1)]
    height, width = camera.shape
    if not len(uv):
        return None
    pad = pad_periods * camera.carrier.period_px
    q = quantum_px
    x0 = max(0, math.floor((float(uv[:, 0].min()) - pad) / q) * q)
    y0 = max(0, math.floor((float(uv[:, 1].min()) - pad) / q) * q)
    x1 = min(width, math.ceil((float(uv[:, 0].max()) + pad) / q) * q)
    y1 = min(height, math.ceil((float(uv[:, 1].max()) + pad) / q) * q)
    if x1 - x0 < q or y1 - y0 < q:
        return None
    return x0, y0, x1, y1


def pose_window(camera: CalibratedCamera, pose: EyePose) -> tuple[int, int, int, int] | None:
    """The :func:`eye_window` to reconstruct the frame after ``pose``'s in: about its gaze
    (:data:`LIMBUS_HALF_ANGLE_DEG`) when its limbus came from the images, else the front of
    the globe and the lids about +Z that the cloud-only fit needs."""
    if pose.gaze_source == LIMBUS_FROM_IMAGES:
        return eye_window(camera, pose.centre_mm, pose.globe_radius_mm, axis=pose.gaze,
                          half_angle_deg=LIMBUS_HALF_ANGLE_DEG)
    return eye_window(camera, pose.centre_mm, pose.globe_radius_mm)


def _seen_shells(points: F64, centre: F64, radius: float) -> tuple[float, float]:
    """The sclera's and the lids' shells as seen from the last centre: the innermost shell of
    the radial histogram within :data:`WARM_FIT_BAND_MM` of the last radius (the lids rest on
    the globe, so the innermost is the sclera, as :func:`~eyeserver.eye.fit.fit_eye` reads it),
    and the strongest 0.6–3 mm outside that (NaN: no lids). A globe that moved shows its
    sclera a little off the last radius; the lids, about as far again outside."""
    shells = _radial_shells(points, np.ones(len(points)), centre,
                            (radius - WARM_FIT_BAND_MM, radius + WARM_FIT_BAND_MM))
    strongest = max((support for _, support in shells), default=0.0)
    inner = [r for r, support in shells if abs(r - radius) <= WARM_FIT_BAND_MM
             and support >= max(MIN_SCLERA_POINTS, 0.1 * strongest)]
    sclera = min(inner, default=radius)
    outer = [(support, r) for r, support in shells
             if sclera + 0.6 <= r <= sclera + LID_REACH_MM and support >= MIN_SCLERA_POINTS]
    return sclera, (max(outer)[1] if outer else math.nan)


def lids_closed(points: F64, centre: F64, radius: float, gaze: F64, limbus_radius: float,
                ) -> bool:
    """Whether the lids cover the front of the globe (``centre``, ``radius``) about ``gaze``.

    Inside the limbus (the disc within 4° of its edge about the gaze) an open eye leaves few
    points: the cornea is clear and the iris dark behind it, whatever the eye did since (the
    disc moves with the eye, and the sclera of a globe moved by a millimetre enters it on one
    side at most, nearer the old sphere than the lids). Shut lids cover it with their shell,
    0.6 mm to :data:`LID_REACH_MM` outside the globe, as densely as the ring of sclera or lids
    around it (2–12° outside the limbus): closed when that shell inside the disc holds at
    least :data:`LIDS_COVER_SHARE` of the ring's points and :data:`MIN_SCLERA_POINTS`.
    """
    rel = points - centre
    dist = distances(rel)
    angle = np.degrees(np.arccos(np.clip((rel @ gaze) / np.maximum(dist, 1e-9), -1.0, 1.0)))
    edge = math.degrees(math.asin(min(limbus_radius / radius, 1.0)))
    off = dist - radius
    covered = int(((angle < edge - 4.0) & (off > 0.6) & (off < LID_REACH_MM)).sum())
    ring = int(((angle > edge + 2.0) & (angle < edge + 12.0) & (off > -0.3)
                & (off < LID_REACH_MM)).sum())
    return covered >= MIN_SCLERA_POINTS and covered >= LIDS_COVER_SHARE * ring


def _shells(points: F64, centre: F64, radius: float, lid_radius: float, band: float,
            ) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.bool_]]:
    """The points within ``band`` of the sphere and of the lid shell, each point on the
    nearer shell only (the shells are less than two bands apart at first)."""
    dist = distances(points, centre)
    on_globe = np.abs(dist - radius) < band
    if not math.isfinite(lid_radius):
        return on_globe, np.zeros(len(points), dtype=bool)
    middle = 0.5 * (radius + lid_radius)
    on_lids = (np.abs(dist - lid_radius) < band) & (dist > middle)
    return on_globe & (dist <= middle), on_lids


def track_eye(cloud: CloudLike, model: EyeModel, previous: EyePose,
              views: Sequence[LimbusView] = ()) -> EyePose:
    """The eye's pose in ``cloud`` from the last frame's pose (see the module docstring).

    Parameters
    ----------
    cloud : CloudLike
        Points (N, 3) in WCS mm, with optional per-point quality in [0, 1] used as weights;
        the whole image's or a window's around the eye. A cloud with a ``pixels_per_point``
        (a decimated reconstruction's, :class:`~eyeserver.service.frame_pose.TrackedCloud`) has
        its sclera counted in image pixels for the confidence, as the whole images' fit counts
        it (``pixels_per_point`` of :func:`~eyeserver.eye.fit.pose_on_limbus`).
    model : EyeModel
        The patient's model: a fixed ``globe_radius_mm`` is held, and the limbus diameter
        places the limbus centre.
    previous : EyePose
        The last frame's pose: the fit starts at its centre and gaze and holds its radius
        (where the model leaves the radius free).
    views : sequence of LimbusView
        The fringe images the cloud came from (or their windows around the eye), with their
        cameras: the limbus is found in them from the last pose
        (:func:`~eyeserver.eye.limbus.find_limbus`) and sets the gaze and, with the
        sclera, the globe, as :func:`~eyeserver.eye.fit.fit_eye` does with images;
        where it is not found the cloud's own estimate stands.

    Returns
    -------
    EyePose
        As :func:`~eyeserver.eye.fit.fit_eye` gives it, the radius the previous one.

    Raises
    ------
    PoseError
        Too few points near the last sphere (the eye moved far or is lost): fit globally.
    ValueError
        ``cloud.points`` is not (N, 3) or holds non-finite values.
    """
    started = time.perf_counter()
    points, weights = checked_cloud(cloud)
    pixels_per_point = float(getattr(cloud, "pixels_per_point", 1.0))
    centre = np.asarray(previous.centre_mm, dtype=np.float64)
    radius = float(model.globe_radius_mm if model.globe_radius_mm is not None
                   else previous.globe_radius_mm)
    # Only what lies around the last globe matters from here on (sclera, lids, cornea).
    dist = distances(points, centre)
    near = ((dist > radius - WARM_FIT_BAND_MM)
            & (dist < radius + LID_REACH_MM + WARM_FIT_BAND_MM))
    points, weights, dist = rows_where(points, near), weights[near], dist[near]
    if len(points) < MIN_SCLERA_POINTS:
        raise PoseError(f"eye lost: only {len(points)} points near the last globe")
    if views:
        found = pose_on_limbus(points, views, model, centre,
                               np.asarray(previous.gaze, dtype=np.float64), radius, radius,
                               started, search=False, remeasure=False,
                               pixels_per_point=pixels_per_point)
        if found is not None:
            return found
        last_gaze = np.asarray(previous.gaze, dtype=np.float64)
        if lids_closed(points, centre, radius, last_gaze, model.limbus_diameter_mm / 2):
            # A blink: the last globe and gaze stand, the gaze unseen (beam held).
            off = dist - radius
            return pose_from_cloud(centre, np.asarray(previous.centre_sd_mm, dtype=np.float64),
                                   radius, Gaze(last_gaze, 90.0, "none"),
                                   float(np.median(np.abs(off))), 0, started,
                                   shape_sd_mm=model.shape_sd_mm)
    seen_radius, lid_radius = _seen_shells(points, centre, radius)
    cov = np.full((3, 3), np.inf)
    resid = np.zeros(0)
    inliers = np.zeros(0, dtype=bool)
    on_globe = np.zeros(len(points), dtype=bool)
    # The first pass takes the shells where they are seen from the last centre, the next ones
    # where the fit put them. Without lids the sclera alone is searched in wider bands; with
    # them, a wide band would take in the face around the lids and drag their shell outwards.
    with_lids = math.isfinite(lid_radius)
    bands = ((0.45, *WARM_FIT_REFINE_BANDS_MM) if with_lids
             else (*WARM_FIT_COARSE_BANDS_MM, *WARM_FIT_REFINE_BANDS_MM))
    for index, band in enumerate(bands):
        on_globe, on_lids = _shells(points, centre, seen_radius if index == 0 else radius,
                                    lid_radius, band)
        if on_globe.sum() < MIN_SCLERA_POINTS:
            raise PoseError(f"eye lost: only {int(on_globe.sum())} points on the last globe")
        # The lid shell only pins the depth: a fixed subsample of its points (weighted up)
        # does that as well; the sclera (a few thousand points) is always kept whole.
        stride = -(-int(on_lids.sum()) // MAX_LID_POINTS) or 1
        lid_index = np.flatnonzero(on_lids)[::stride]
        lid_scale = float(stride)
        centre, _, lid_radius, cov, resid, inliers = _refine_globe(
            points[on_globe], weights[on_globe], centre, radius, radius, points[lid_index],
            weights[lid_index] * lid_scale, lid_radius)
    sclera = points[on_globe][inliers]
    if len(sclera) < MIN_SCLERA_POINTS:
        raise PoseError(f"eye lost: only {len(sclera)} sclera points fit the last globe")
    surface_mad = float(np.median(np.abs(resid)))
    centre_sd = np.sqrt(np.clip(np.diag(cov)[:3], 0.0, None))
    # The gaze as fit_eye finds it, from the same start (what lies around the globe), not from
    # the last gaze (see the module docstring); the last gaze only where nothing lies around.
    gaze = cloud_gaze(points, sclera, centre, radius, centre_sd, model,
                      fallback=np.asarray(previous.gaze, dtype=np.float64))
    return pose_from_cloud(centre, centre_sd, radius, gaze, surface_mad, len(sclera), started,
                           pixels_per_point=pixels_per_point, shape_sd_mm=model.shape_sd_mm)
