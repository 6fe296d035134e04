"""From one unit's fringe images to a calibrated point cloud (docs/design.md §4 steps 2–7).

Per camera A of a unit: demodulate against the stored reference phase and mask what carries no
fringe (:func:`camera_phase`), fix the absolute fringe order of every pixel, then Z (WCS, mm) from
A's phase-to-height model and X, Y from A's ray (steps 5–6).

The fringe order comes by one of two paths, and the result says which (``CameraCloud.method``):

``"multi-view"`` (the fast path, docs/design.md §4 step 4)
    Every candidate order k of a pixel's phase gives, through A's model and ray, a 3-D point in
    the calibrated volume; the unit's other camera B, its model inverted at that point, predicts
    the phase B must see there; the candidate whose prediction matches B's measured phase wins.
    Evaluated for all pixels at once on a grid of every third pixel, ambiguous picks dropped and
    the rest cleaned by a median vote; each pixel takes the order that brings its phase nearest
    the interpolated absolute phase of its grid neighbours, then checked against B.
``"spatial"`` (the robust path)
    Quality-guided spatial unwrapping (Herráez et al. 2002, scikit-image) leaves one unknown
    order per connected region; the multi-view picks inside a region vote for it (on every
    ninth pixel, on every third of a region those do not settle). A region B
    cannot judge falls back on a depth prior (the offset that puts its median height nearest
    ``depth_prior_mm``), and says so. Slower (the unwrapping takes ≈ 16 ms a camera), but
    it keeps what the other camera does not see where it continues points B confirms
    (:func:`_checked`).

A camera with no partner in its unit can only use the depth prior, pixel by pixel (``"depth
prior"``): right only within half a fringe's depth (≈ ±2.5 mm on the default rig) of the prior.
A unit whose two cameras cannot tell the orders apart (both at one azimuth) can take its picks
from a camera of another unit instead (:func:`unit_clouds`'s ``order_partners``).

Finally each camera's points are kept only where the other camera's own reconstruction confirms
them, or (spatial, where B does not see them) does not contradict them (:func:`unit_clouds`), and
only in patches of continuous depth large enough not
to be a wrong order's island: :data:`SPECKLE_PX` pixels, or down to :data:`MIN_PATCH_PX` where
the other camera confirms the patch's order as a whole and no other order continues the points
around it better (:func:`_patch_confirmed`). The eye's visible sclera, a few hundred pixels
between the lids and the limbus and more than a millimetre below the lids, lives on the second
rule (measured with ``scripts/eye_coverage.py``: from ≈ 200 points 0.5 mm off to 3000–5000).

References
----------
Herráez, M. A., Burton, D. R., Lalor, M. J., Gdeisat, M. A. (2002). Fast two-dimensional
phase-unwrapping algorithm based on sorting by reliability following a noncontinuous path.
Applied Optics 41(35), 7437–7444.
Tao, T. et al. (2016). Real-time 3-D shape measurement with composite phase-shifting fringes and
multi-view system. Optics Express 24(18), 20253–20269.
"""

from __future__ import annotations

import math
from dataclasses import InitVar, dataclass, field
from functools import cached_property

import cv2
import numpy as np
import numpy.typing as npt
from scipy import ndimage
from skimage.restoration import unwrap_phase

from eyeserver.core.arrays import angle, rows_where, wrap
from eyeserver.core.types import F32, F64, Bool
from eyeserver.pipeline.demodulate import (
    Carrier,
    band_gain,
    border_mask,
    demodulate,
    phase_difference,
    with_bend_bias,
)
from eyeserver.pipeline.geometry import (
    pixel_grid_normalised,
    project,
    rays_from_normalised,
    undistorted_normalised,
)
from eyeserver.pipeline.phase_height import PhaseHeightModel

Int = npt.NDArray[np.int64]

TWO_PI = 2 * np.pi
MODULATION_FRACTION = 0.25
"""Pixels whose fringe amplitude is below this share of the image's strong fringes are masked
(low modulation: shadows, dark paint, the pupil, the background beyond the object)."""
SATURATION_FRACTION = 0.98
"""Pixels at or above this share of the camera's full scale are saturated."""
SATURATED_SHARE = 0.3
"""Pixels whose surrounding period is saturated over more than this share are masked."""
COARSE_STRIDE = 3
"""The multi-view candidates are evaluated on every third pixel in each direction (odd, so the
grid's pixel centres coincide with ``cv2.resize``'s sample positions); of a :func:`decimated`
camera's pixels, so its grid is as much coarser on the image."""
VOTE_SIZE = 3
"""Side of the median vote on the coarse grid's fringe orders (9 full-resolution pixels each)."""
AGREEMENT_MM = 0.3
"""Two cameras' reconstructions of the same surface point agree to a few hundredths of a mm;
a wrong fringe order is off by a fringe (≈ 5 mm)."""
MIN_SEPARATION_RAD = 0.3
"""The best fringe order must match the other camera this much better than the next best."""
MAX_MISMATCH_RAD = 0.35
"""A fringe-order pick whose phase in the other camera misses by more than this is dropped; it
lies well under half the default rig's 0.69 rad margin between right and wrong orders."""
BEYOND_RANGE_MM = 0.5
"""Heights this far outside the calibrated range are still candidates. Wider does not pay: each
extra candidate is one more chance for a wrong order to match the other camera (3 mm cost a
fifth of an eye phantom's points), and a surface beyond the range has no checked margin
anyway: it is outside the volume the rig was calibrated for (its points may be wrong)."""
EDGE_EROSION_PERIODS = 0.5
"""The mask is eroded by this share of a fringe period around every edge of the fringe field
(not at the image's frame, whose own margin is :data:`BORDER_PERIODS`)."""
BORDER_ACROSS_PERIODS = 0.5
"""The image's frame masked at the two sides the fringes run into, in fringe periods (the other
two, across which the carrier runs, keep :attr:`CalibratedCamera.border_px`, a whole period).
The demodulation continues the image beyond the frame along the fringes, exactly for straight
ones, and across them by whole periods, which bent fringes make an extrapolation
(:mod:`~eyeserver.pipeline.demodulate`): measured in docs/notes/fringe-order.md."""
SPECKLE_PX = 1000
"""Patches of continuous depth smaller than this (≈ 10 mm² on the default rig) are dropped: a
wrong fringe order that slipped through every check shows as an island a fringe's depth (≈ 5 mm)
away from its surroundings (the largest measured: 700 px along a tilted plate's edge whose true
points had left the other camera's view)."""
MIN_PATCH_PX = 100
"""Patches of continuous depth from this size up to :data:`SPECKLE_PX` stay only if the other
camera confirms their fringe order as a whole (:func:`_patch_confirmed`): the visible sclera
between the lids and the limbus is such a patch (a step of more than a millimetre away from the
lids around it), or several: where the partner camera sees only part of it, what it confirms
comes apart into patches of 100–250 pixels. Measured with 200 pixels here: on an eye turned 8°
one noise draw in four lost a unit's sclera, and the eye pose bench's globe centre came out
0.120 mm median, 0.29 mm p95, 3.9 mm at worst (lids taken for the sclera); with 100, 0.102,
0.26 and 0.37 mm (200 poses, seed 0; seed 1, 120 poses: 0.124 → 0.117, 0.34 → 0.29, 0.82 →
0.65 mm)."""
MIN_PATCH_POINTS = 50
"""A small patch needs this many points as well, on a decimated camera's grid (live tracking's
windows, every third pixel: 11 points for :data:`MIN_PATCH_PX`, so 450 pixels there): its
order is judged on medians over its points, and there the tracking holds the patient's radius,
so the sclera's smallest patches would only weigh in the fit's surface distance. Measured
(windows on every second pixel): 25-point patches cost a tracked frame 1.5 ms more (13.5 →
15 ms), all in confirming them."""
PATCH_MARGIN_RAD = 0.6
"""Over a small patch, every other fringe order must miss the other camera's phase by this much
more (median over the patch's pixels) than the patch's own order."""
PATCH_JUDGED_SHARE = 0.5
"""Share of a small patch's pixels the other camera must be able to judge under each of
:data:`PATCH_ORDERS` (within the calibrated volume): a patch whose neighbouring orders leave
the other camera's view cannot be told from a wrong-order island, and is dropped."""
PATCH_OWN_RAD = 0.1
"""A small patch's own order must match the other camera's phase this well (median). The true
order matches to the noise (the eye's sclera patches: 0.01–0.05 rad); a wrong order only as
well as the rig's margin between orders allows (≈ 0.3 rad at worst on the default rig): a
wrong-order island on a tilted plate measured 0.19–0.25 rad."""
PATCH_ORDERS = (-2, -1, 1, 2)
"""The neighbouring orders a small patch's own order must beat at the other camera. Orders
further out are not asked: where the cameras' sensitivities nearly repeat (about three orders
away on the default rig, docs/design.md §4 step 4) the other camera matches them almost as well, or
their points leave its view."""
PATCH_FAR_ORDERS = tuple(k for k in range(-8, 9) if k)
"""Orders a small patch is tested against for continuity with the points around it (all a
35 mm volume holds): a wrong-order island is typically three orders off, and its true order
continues the surface around it."""
PATCH_RING_PX = 6
"""Points of the cloud within this distance of a small patch are its surroundings."""
PATCH_RING_MIN_PX = 10
"""A small patch with surroundings on fewer of its pixels is isolated (not checked for
continuity)."""
SPECKLE_STEP_MM = 1.0
"""Neighbouring pixels whose heights differ by less than this belong to one patch."""
MIN_REGION_PX = 200
"""Spatially unwrapped regions smaller than this are noise islands and dropped."""
MIN_REGION_VOTES = 3
"""Multi-view picks a region needs before their majority fixes its order."""
SPARSE_VOTE_STRIDE = 9
"""The spatial order's regions are voted first by multi-view picks on every ninth pixel of each
axis (a ninth of :data:`COARSE_STRIDE`'s grid, and a subset of it: 9 // 2 lies on the grid):
an eye phantom's one region had 17,000 picks on the full grid, 97–99 % of them for one offset
(docs/notes/speed.md, twenty-second session)."""
SPARSE_MIN_VOTES = 100
"""Picks on the sparse grid that settle a region's offset (with :data:`SPARSE_MIN_SHARE`; a
region of some 8,000 pixels or more); other regions are voted on the full grid, as before."""
SPARSE_MIN_SHARE = 0.8
"""Share of a region's sparse picks that must agree to settle it: were the picks independent,
100 of a region whose full grid holds the least majority (0.6) would agree this well once in
60,000 (binomial); wrong picks come in patches, so the margin is wide."""
UNWRAP_STRIDE = 2
"""The spatial order unwraps every second pixel of each axis (a quarter of them); every pixel
then takes the 2π step that brings it nearest a sample within one pixel of it
(:func:`spatial_unwrap`). The samples' phases differ twice as much as neighbouring pixels';
on the eye phantom of five rigs the orders came out as with every pixel unwrapped
(docs/notes/speed.md)."""

METHODS = ("multi-view", "spatial")
"""The fringe-order paths :func:`unit_clouds` offers."""

LIGHT_STEPS_MM = (0.5, 3.0)
"""Steps of the central differences of the phase whose gradients give the iso-phase plane
through a point and the fringes' direction (:meth:`CalibratedCamera.light_direction`). Over the
short one the phase changes by less than π (a fringe period is ≈ 2.8 mm at the default rig's
eye); it unwraps the long one, whose gradients the reference phase's noise tilts less."""
LIGHT_CUBES_MM = (4.0, 20.0)
"""Half-sides of the cubes of points (7 and 11 a side) about the point asked whose gradients give
the plane through it (the short step's) and the fringes' direction (the long step's: the
direction the planes' normals vary least along, which a wider fan of planes fixes better).
Against the renderer's projectors (32 camera views of eight rendered eyes): 0.9° median, 2.0°
at most off, where the fringes' true direction gives 1.0° and 1.7° (the projector's offset
along its fringes, see the method); over a cube of 12 mm 1.2° and 3.3°, with the short step
alone 1.0° and 2.4°."""
LIGHT_OFF_PLANE_DEG = 8.0
"""Gradients further than this from their cube's median direction are left out (where the
reference phase wraps or is undefined between the two points of a difference)."""


@dataclass
class CalibratedCamera:
    """What the pipeline knows of one camera after calibration."""

    camera_id: str
    K: F64
    dist: F64
    R: F64
    T: F64
    model: PhaseHeightModel
    carrier: Carrier
    reference_phase: F32
    border_px: int
    """The image's frame masked across the carrier, pixels (a fringe period; along the fringes
    :data:`BORDER_ACROSS_PERIODS` of one)."""
    strong_modulation: float | None = None
    """The modulation of the image's strong fringes the mask's threshold is relative to
    (:data:`MODULATION_FRACTION`); None: each image's own 95th percentile. A window of an image
    (:func:`cropped`) takes the whole image's, so that it masks the same pixels."""
    spacing_px: int = 1
    """Image pixels between two neighbouring pixels of this camera: 1, or the factor of
    :func:`decimated`. The filters' sizes in pixels (:data:`SPECKLE_PX` and its kin) are
    given for spacing 1 and scaled by it, so that they keep their size on the object."""
    origin: tuple[int, int] = (0, 0)
    """Where this camera's pixel ``(0, 0)`` lies in the whole image, ``(column, row)``: a
    window's corner (:func:`cropped`), so that the demodulation's bend correction averages
    over the whole image's blocks (:func:`~eyeserver.pipeline.demodulate.with_bend_bias`)."""
    grid: InitVar[tuple[F64, F64] | None] = None
    """The undistorted normalised coordinates ``(x, y)`` of the pixels when known (a window or
    a decimation of another camera's: sliced, not computed again); None: computed when first
    needed."""
    _grid: tuple[F64, F64] | None = field(default=None, init=False, repr=False, compare=False)
    _pinhole_maps: tuple[F32, F32] | None = field(default=None, init=False, repr=False)
    _towards: dict[str, tuple[F64, F64]] = field(default_factory=dict, init=False, repr=False)
    _fringes: F64 | None = field(default=None, init=False, repr=False, compare=False)

    def __post_init__(self, grid: tuple[F64, F64] | None) -> None:
        self._grid = grid

    @cached_property
    def _xy(self) -> tuple[F64, F64]:
        # Undistorting every pixel costs ≈ 40 ms a 640 × 512 camera (cv2.undistortPoints):
        # not paid by a camera whose pixels are never reconstructed (the limbus search of a
        # pose measurement projects points through K and the distortion only).
        height, width = self.reference_phase.shape
        x, y = self._grid or pixel_grid_normalised(width, height, self.K, self.dist)
        self._grid = None
        # Contiguous, so that the many ``x.ravel()[pixels]`` look-ups index a view instead of
        # copying the whole grid each time (2.6 MB, ≈ 0.1 ms a copy).
        return np.ascontiguousarray(x), np.ascontiguousarray(y)

    @property
    def x(self) -> F64:
        """Undistorted normalised x of every pixel ``(height, width)``."""
        return self._xy[0]

    @property
    def y(self) -> F64:
        """Undistorted normalised y of every pixel ``(height, width)``."""
        return self._xy[1]

    @cached_property
    def rays(self) -> F64:
        """Each pixel's unit ray in the WCS ``(height · width, 3)``."""
        return rays_from_normalised(self.x, self.y, self.R).reshape(-1, 3)

    @cached_property
    def _ray_rows(self) -> F64:
        # (3, H·W): a pixel's ray gathered from three contiguous rows, not one row of an
        # (H·W, 3) array, as in :meth:`towards` (points_at on the eye phantom's pixels: 1.5 ms
        # where intersect_plane_z of the gathered rows took 4.2).
        return np.ascontiguousarray(self.rays.T)

    def points_at(self, pixels: npt.NDArray[np.intp], z: F64) -> F64:
        """WCS points ``(N, 3)`` where the rays of ``pixels`` (flat indices) meet the planes
        ``Z = z`` (mm), as :func:`~eyeserver.pipeline.geometry.intersect_plane_z` computes
        them (the same numbers); NaN for a ray parallel to the plane."""
        centre, rows = self.centre, self._ray_rows
        dz = rows[2].take(pixels)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (np.asarray(z, dtype=np.float64) - centre[2]) / dz
        t = np.where(np.abs(dz) > 1e-12, t, np.nan)
        points = np.empty((len(t), 3))
        for axis in range(3):
            np.multiply(t, rows[axis].take(pixels), out=points[:, axis])
            points[:, axis] += centre[axis]
        return points

    @property
    def shape(self) -> tuple[int, int]:
        """Image shape ``(height, width)``."""
        h, w = self.reference_phase.shape
        return int(h), int(w)

    @property
    def centre(self) -> F64:
        """Camera centre in the WCS."""
        return np.asarray(-self.R.T @ self.T, dtype=np.float64)

    def pinhole_maps(self) -> tuple[F32, F32]:
        """``cv2.remap`` maps that resample this camera's images onto its distortion-free
        pinhole image (same K), so a 3-D point's pixel there is just ``K·(R·X + T)``."""
        if self._pinhole_maps is None:
            h, w = self.shape
            map_x, map_y = cv2.initUndistortRectifyMap(self.K, self.dist, None, self.K, (w, h),
                                                       cv2.CV_32FC1)
            self._pinhole_maps = (np.asarray(map_x), np.asarray(map_y))
        return self._pinhole_maps

    def absolute_phase(self, points: F64) -> F64:
        """The phase this camera's projector throws onto WCS ``points`` ``(N, 3)``: the phase
        model's at each point's height plus the reference phase at its pixel (bilinear; NaN
        outside the image)."""
        pts = np.asarray(points, dtype=np.float64)
        uv = project(pts, self.K, self.dist, self.R, self.T)
        x, y = undistorted_normalised(uv[:, 0], uv[:, 1], self.K, self.dist)
        reference = cv2.remap(np.asarray(self.reference_phase, dtype=np.float32),
                              uv[:, :1].astype(np.float32), uv[:, 1:].astype(np.float32),
                              cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                              borderValue=float("nan"))[:, 0]
        return np.asarray(self.model.phase(x, y, pts[:, 2]) + reference, dtype=np.float64)

    def light_direction(self, at: npt.ArrayLike) -> F64 | None:
        """Unit direction from the WCS point ``at`` towards the projector whose fringes this
        camera measures, or None where the calibration does not say (too little of the cubes
        about ``at`` seen).

        Straight fringes make every surface of one phase a plane through a line through the
        projector, parallel to the fringes. The direction lies in the plane through ``at``
        (normal: the phase's gradient) and across the fringes (their direction: the one the
        planes' normals vary least along; :data:`LIGHT_CUBES_MM`): the projector is taken to
        lie level with ``at`` along its fringes, which it does where it is aimed at the eye (on
        the default rig the eye's offset from its axis puts it up to 1.7° off). Its side is the
        camera's: a unit's projector and cameras look at the eye from one side.
        """
        at = np.asarray(at, dtype=np.float64)
        plane = self._phase_normals(at, LIGHT_CUBES_MM[0], 7, LIGHT_STEPS_MM[0])
        if self._fringes is None:
            # The projector's own: found once, about the first point asked.
            across = self._phase_normals(at, LIGHT_CUBES_MM[1], 11, LIGHT_STEPS_MM[1])
            if across is not None:
                self._fringes = np.linalg.svd(across)[2][-1]
        if plane is None or self._fringes is None:
            return None
        direction = np.cross(plane.mean(axis=0), self._fringes)
        direction /= np.linalg.norm(direction)
        if direction @ (self.centre - at) < 0:
            direction = -direction
        return np.asarray(direction, dtype=np.float64)

    def _phase_normals(self, at: F64, half: float, side: int, step: float) -> F64 | None:
        """Unit gradients of :meth:`absolute_phase` over a cube of ``side``³ points and
        half-side ``half`` about ``at``, by central differences of ``step`` (unwrapped by the
        short step's where longer), all on one side, those off their median direction by more
        than :data:`LIGHT_OFF_PLANE_DEG` left out; None for fewer than 20."""
        steps = np.linspace(-half, half, side)
        cube = at + np.stack(np.meshgrid(steps, steps, steps), axis=-1).reshape(-1, 3)
        short = LIGHT_STEPS_MM[0]
        gradient = np.empty((len(cube), 3))
        for axis, e in enumerate(np.eye(3)):
            near = phase_difference(self.absolute_phase(cube + short * e),
                                    self.absolute_phase(cube - short * e)) * (step / short)
            if step > short:
                far = self.absolute_phase(cube + step * e) - self.absolute_phase(cube - step * e)
                near = near + phase_difference(far, near)
            gradient[:, axis] = near
        size = np.linalg.norm(gradient, axis=1)
        usable = np.isfinite(size) & (size > 0)
        if usable.sum() < 20:
            return None
        unit = gradient[usable] / size[usable, None]
        unit *= np.where(unit @ unit[0] < 0, -1.0, 1.0)[:, None]
        middle = np.median(unit, axis=0)
        middle /= np.linalg.norm(middle)
        kept = unit[unit @ middle > math.cos(math.radians(LIGHT_OFF_PLANE_DEG))]
        return kept if len(kept) >= 20 else None

    def towards(self, other: CalibratedCamera) -> tuple[F64, F64]:
        """Each pixel's ray in ``other``'s camera frame as ``p0 + Z·p1`` (Z the WCS height),
        each ``(3, H·W)``: a row per coordinate of B's frame, a column per pixel.

        A's ray point at height Z is ``C + (Z − C_z)/r_z · r``; in B's frame ``R_B·X + T_B`` it is
        affine in Z. Precomputed once per camera pair, it turns projecting every candidate of
        every pixel into B into a multiply-add and a division. Row by row so that the points'
        pixels are gathered from contiguous rows, several times faster than from an
        ``(H·W, 3)`` array (docs/notes/speed.md).
        """
        if other.camera_id not in self._towards:
            centre, rays = self.centre, self.rays
            rays_b = rays @ other.R.T
            p1 = rays_b / rays[:, 2:3]
            p0 = (other.R @ centre + other.T)[None, :] - centre[2] * p1
            self._towards[other.camera_id] = (np.ascontiguousarray(p0.T),
                                              np.ascontiguousarray(p1.T))
        return self._towards[other.camera_id]


def cropped(camera: CalibratedCamera, x0: int, y0: int, x1: int, y1: int, *,
            strong_modulation: float | None = None) -> CalibratedCamera:
    """The camera that sees only the window ``[y0:y1, x0:x1]`` of ``camera``'s images.

    The principal point moves by the window's origin, so every pixel keeps its undistorted
    normalised coordinates, its ray and (with the cropped reference phase) its phase-to-height
    model: where the window and the whole image both give a point at a pixel, it is the same
    (measured on the simulated eye: within 0.003 mm), except within the band-pass's reach of
    the window's border, which :func:`camera_phase` masks (``border_px``). Fringe phases are
    absolute (the demodulated phase includes the carrier ramp), so the crop needs no phase
    offset. The window keeps some points the whole image drops: a fringe order whose rival
    orders project outside the other camera's window has no rival left to be confused with.

    Parameters
    ----------
    camera : CalibratedCamera
        The whole image's camera.
    x0, y0, x1, y1 : int
        The window in pixels, columns ``x0 ≤ j < x1`` and rows ``y0 ≤ i < y1``, within the
        image.
    strong_modulation : float, optional
        The whole image's strong fringes' modulation (:func:`strong_modulation`), so the window
        masks what the whole image masks; None: the camera's own setting.

    Raises
    ------
    ValueError
        A window that is empty or leaves the image.
    """
    height, width = camera.shape
    if not (0 <= x0 < x1 <= width and 0 <= y0 < y1 <= height):
        raise ValueError(f"window ({x0}, {y0})–({x1}, {y1}) must be a non-empty part of the "
                         f"{width}×{height} image")
    K = camera.K.copy()
    K[0, 2] -= x0
    K[1, 2] -= y0
    return CalibratedCamera(camera.camera_id, K, camera.dist, camera.R, camera.T, camera.model,
                            camera.carrier,
                            np.ascontiguousarray(camera.reference_phase[y0:y1, x0:x1]),
                            camera.border_px,
                            camera.strong_modulation if strong_modulation is None
                            else strong_modulation, camera.spacing_px,
                            (camera.origin[0] + x0, camera.origin[1] + y0),
                            grid=(camera.x[y0:y1, x0:x1], camera.y[y0:y1, x0:x1]))


def decimated(camera: CalibratedCamera, factor: int) -> CalibratedCamera:
    """The camera of every ``factor``-th pixel of ``camera``'s images, in both directions.

    Pixel ``(i, j)`` of it is ``camera``'s pixel ``(factor·i, factor·j)``: K's rows scale by
    ``1/factor``, so every pixel keeps its undistorted normalised coordinates, its ray and its
    phase-to-height model, and a point reconstructed from it is the one ``camera`` gives at that
    pixel. Pair it with :meth:`Phase.decimated` of the full image's phase: demodulation needs
    the full image (the carrier is only a few pixels long), the orders and points do not.

    Raises
    ------
    ValueError
        A factor below 1.
    """
    if factor < 1:
        raise ValueError(f"factor must be at least 1, not {factor}")
    if factor == 1:
        return camera
    K = camera.K.copy()
    K[:2] /= factor
    return CalibratedCamera(camera.camera_id, K, camera.dist, camera.R, camera.T, camera.model,
                            camera.carrier,
                            np.ascontiguousarray(camera.reference_phase[::factor, ::factor]),
                            camera.border_px, camera.strong_modulation,
                            camera.spacing_px * factor,
                            grid=(camera.x[::factor, ::factor], camera.y[::factor, ::factor]))


def _area_px(camera: CalibratedCamera, pixels: int) -> int:
    """A pixel count given for image pixels, in ``camera``'s pixels (:attr:`spacing_px`)."""
    return max(1, round(pixels / camera.spacing_px**2))


def strong_modulation(camera: CalibratedCamera, image: npt.ArrayLike) -> float:
    """The modulation of ``image``'s strong fringes (:func:`fringe_strength`), what
    :func:`camera_phase` masks weak fringes against."""
    return fringe_strength(demodulate(np.asarray(image), camera.carrier,
                                      measure_bends=False).modulation)


def fringe_strength(modulation: npt.ArrayLike) -> float:
    """The strong fringes' modulation of a demodulated image: its 95th percentile."""
    return float(np.percentile(np.asarray(modulation), 95))


MIN_SEEN_DN = 5.0
"""Brightness (DN, the 95th percentile of the fringe-free image) below which a frame shows
nothing to judge its fringes on (the empty room: 0.6 DN)."""

MIN_FRINGE_CONTRAST = 0.1
"""A lit frame whose fringes' modulation is below this share of the light they ride on shows
no fringes: its projector lit nothing (a factor of 3 below a projector at 30 % drive on the
simulated scenes, 10 above a dark one: docs/notes/hardening.md)."""


@dataclass(frozen=True)
class FringeCheck:
    """Whether a lit frame shows its projector's fringes (:func:`fringe_check`)."""

    seen_dn: float
    """The fringe-free image's 95th percentile (DN): how much there is to see."""
    contrast: float
    """The median of ``B / A`` (the fringe's amplitude over the light it rides on) where the
    fringe-free light ``A`` is at least half :attr:`seen_dn`."""

    @property
    def judged(self) -> bool:
        """Whether the frame shows enough to judge (:data:`MIN_SEEN_DN`)."""
        return self.seen_dn >= MIN_SEEN_DN

    @property
    def dark(self) -> bool:
        """Whether the frame shows a scene but no fringes on it."""
        return self.judged and self.contrast < MIN_FRINGE_CONTRAST

    def to_dict(self) -> dict[str, object]:
        return {"seen_dn": self.seen_dn, "contrast": self.contrast, "judged": self.judged,
                "dark": self.dark}


def fringe_check(carrier: Carrier, image: npt.ArrayLike) -> FringeCheck:
    """How strongly a lit frame shows the fringes of the ``carrier`` it was calibrated with.

    Ambient light shows the scene whether the projector lights or not; the fringe rides on
    the projector's own light. So a frame with light but no fringe on it was not lit, whatever
    the projector's driver says (a dead LED, a drive level of 0). Relative to the light, not
    to the calibration's reference plane, so that a dark iris or a grey face is judged as
    fairly as the white plate.
    """
    pixels = np.asarray(image, dtype=np.float32)
    result = demodulate(pixels, carrier, measure_bends=False)
    light = cv2.GaussianBlur(pixels - result.modulation * np.cos(result.wrapped_phase),
                             (0, 0), 2.0)
    seen = float(np.percentile(light, 95))
    bright = light >= 0.5 * seen
    contrast = float(np.median(result.modulation[bright] / np.maximum(light[bright], 1e-3))) \
        if seen > 0 and bright.any() else 0.0
    return FringeCheck(seen, contrast)


@dataclass
class Phase:
    """A camera image demodulated against its reference: wrapped Δφ, modulation and mask."""

    dphi: F32
    modulation: F32
    valid: Bool
    bend_bias: F32 | None = None
    """The demodulation's :attr:`~eyeserver.pipeline.demodulate.Demodulated.bend_bias`, taken
    out of ``dphi`` (None: none)."""
    _pinhole: F32 | None = field(default=None, repr=False)

    def pinhole_view(self, camera: CalibratedCamera) -> F32:
        """cos Δφ, sin Δφ and the mask resampled onto the camera's pinhole image, (H, W, 3).

        The phase is resampled as a unit phasor so interpolation never straddles a wrap.
        """
        if self._pinhole is None:
            stack = np.dstack([np.cos(self.dphi), np.sin(self.dphi),
                               self.valid.astype(np.float32)]).astype(np.float32)
            map_x, map_y = camera.pinhole_maps()
            self._pinhole = np.asarray(cv2.remap(stack, map_x, map_y, cv2.INTER_LINEAR,
                                                 borderMode=cv2.BORDER_CONSTANT, borderValue=0))
        return self._pinhole

    def decimated(self, factor: int) -> Phase:
        """Every ``factor``-th pixel in both directions: the phase of :func:`decimated`'s
        camera (samples, not averages: a wrapped phase cannot be averaged)."""
        if factor == 1:
            return self
        pick = (slice(None, None, factor), slice(None, None, factor))
        return Phase(np.ascontiguousarray(self.dphi[pick]),
                     np.ascontiguousarray(self.modulation[pick]),
                     np.ascontiguousarray(self.valid[pick]),
                     None if self.bend_bias is None
                     else np.ascontiguousarray(self.bend_bias[pick]))


ORDER_SOURCES = ("multi-view", "spatial + multi-view", "spatial + depth prior", "depth prior")
"""What fixed a point's fringe order: ``CameraCloud.order_source`` indexes this tuple."""


@dataclass
class CameraCloud:
    """Points one camera contributes, with per-point quality and what fixed each fringe order."""

    camera_id: str
    points: F64
    quality: F32
    order_source: npt.NDArray[np.uint8] = field(repr=False)
    pixels: npt.NDArray[np.intp] = field(repr=False)

    @property
    def order_counts(self) -> dict[str, int]:
        """Points per fringe-order source (:data:`ORDER_SOURCES`), sources with none left out."""
        counts = np.bincount(self.order_source, minlength=len(ORDER_SOURCES))
        return {name: int(n) for name, n in zip(ORDER_SOURCES, counts, strict=False) if n}

    @property
    def method(self) -> str:
        """The source that fixed most points' orders (``"none"`` for an empty cloud)."""
        counts = self.order_counts
        return max(counts, key=counts.__getitem__) if counts else "none"

    def subset(self, keep: Bool) -> CameraCloud:
        """The points where ``keep`` holds."""
        return CameraCloud(self.camera_id, rows_where(self.points, keep), self.quality[keep],
                           self.order_source[keep], self.pixels[keep])

    def depth_image(self, shape: tuple[int, int]) -> F64:
        """Z of each pixel's point, NaN where the camera has none."""
        depth = np.full(shape, np.nan)
        depth.ravel()[self.pixels] = self.points[:, 2]
        return depth


def camera_phase(camera: CalibratedCamera, image: npt.ArrayLike,
                 saturation_dn: float | None = None, *, measure_bends: bool = True) -> Phase:
    """Demodulate ``image`` with the camera's carrier, relative to the reference, with its mask.

    ``dphi`` is the surface's phase, less the band's bias on bent fringes
    (:attr:`~eyeserver.pipeline.demodulate.Demodulated.bend_bias`) unless ``measure_bends`` is
    False (faster where the surface's shape does not matter to the result).

    Masked: low modulation (shadows, dark paint, the background), saturation (more than
    :data:`SATURATED_SHARE` of the period around a pixel at or above
    :data:`SATURATION_FRACTION` of ``saturation_dn``), the image border the band-pass
    corrupts, and half a fringe period around every edge of what remains.
    """
    pixels = np.asarray(image)
    result = demodulate(pixels, camera.carrier, measure_bends=False)
    strong = (fringe_strength(result.modulation) if camera.strong_modulation is None
              else camera.strong_modulation)
    if measure_bends:
        # A window's (cropped) bias is the whole image's: the same blocks, the same fringe field.
        result = with_bend_bias(result, camera.carrier, origin=camera.origin,
                                strong_modulation=strong)
    dphi = phase_difference(result.surface_phase(), camera.reference_phase)
    period = math.ceil(camera.carrier.period_px)
    valid = result.modulation > MODULATION_FRACTION * strong
    if saturation_dn is not None:
        saturated = (pixels >= SATURATION_FRACTION * saturation_dn).astype(np.float32)
        if saturated.any():
            # Clipping a fringe's crests keeps it symmetric about them, so its phase survives
            # light saturation; only where most of a period is clipped is the fringe lost.
            share = cv2.blur(saturated, (period, period))
            valid &= share < SATURATED_SHARE
    # The band-pass spreads every edge of the fringe field (an object's outline, a shadow, the
    # end of the plate) over about a period: erode the mask by half a period on each side. The
    # image's frame is no such edge (the image is continued beyond it): cv2.erode takes what
    # lies outside the image as valid, and the frame's own margin is cut after.
    half = max(1, round(EDGE_EROSION_PERIODS * period))
    eroded = cv2.erode(valid.astype(np.uint8), np.ones((2 * half + 1, 2 * half + 1), np.uint8))
    across = math.ceil(BORDER_ACROSS_PERIODS * camera.carrier.period_px)
    fy, fx = camera.carrier.frequency
    margins = (camera.border_px, across) if abs(fy) >= abs(fx) else (across, camera.border_px)
    valid = np.asarray(eroded, dtype=bool) & border_mask(dphi.shape, margins)
    return Phase(dphi=dphi, modulation=result.modulation, valid=valid,
                 bend_bias=result.bend_bias)


def _sample(image: F32, u: F64, v: F64) -> F32:
    """Bilinear samples of a (H, W, C) float32 image at pixel positions, shape (N, C); zero
    outside. ``cv2.remap`` does the interpolation (its maps are limited to 32767 per side)."""
    n = u.size
    cols = 1024
    rows = max(1, -(-n // cols))
    map_x = np.full(rows * cols, -10.0, np.float32)
    map_y = np.full(rows * cols, -10.0, np.float32)
    map_x[:n], map_y[:n] = u.ravel(), v.ravel()
    out = cv2.remap(image, map_x.reshape(rows, cols), map_y.reshape(rows, cols),
                    cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    samples: F32 = np.asarray(out, dtype=np.float32).reshape(rows * cols, -1)[:n]
    return samples


def _mismatch(cam_a: CalibratedCamera, cam_b: CalibratedCamera, view_b: F32,
              pixels: npt.NDArray[np.intp], z: F64) -> F64:
    """|phase B sees − phase B's model predicts| (rad) at A's pixels' points of height ``z``.

    ``z`` has shape (N,) or (N, K) for K candidates per pixel; the mismatch is π where B cannot
    judge (the point leaves B's view or B's fringes are masked there).
    """
    p0, p1 = cam_a.towards(cam_b)
    extra = (slice(None),) + (None,) * (z.ndim - 1)
    local = [p0[c].take(pixels)[extra] + z * p1[c].take(pixels)[extra] for c in range(3)]
    with np.errstate(divide="ignore", invalid="ignore"):
        xb, yb = local[0] / local[2], local[1] / local[2]
    K = cam_b.K
    u = K[0, 0] * xb + K[0, 1] * yb + K[0, 2]
    v = K[1, 1] * yb + K[1, 2]
    predicted = cam_b.model.phase(xb, yb, z)
    seen = _sample(view_b, u, v)
    cos_b, sin_b, valid_b = (seen[:, c].reshape(z.shape) for c in range(3))
    # The seen phase less the predicted one, wrapped: the same as the angle of the seen
    # (cos, sin) turned by −predicted, with one angle instead of a cos, a sin and an arctan2
    # (docs/notes/speed.md); wrapped below, so the angle's own range does not matter.
    mismatch = angle(sin_b, cos_b, centred=False).astype(np.float64) - predicted
    with np.errstate(invalid="ignore"):  # an infinite prediction: not judged, below
        wrap(mismatch)
    np.abs(mismatch, out=mismatch)
    judged = (valid_b > 0.99) & (local[2] > 0) & np.isfinite(predicted)
    return np.asarray(np.where(judged, mismatch, np.pi))


def _candidate_orders(camera: CalibratedCamera, x: F64, y: F64,
                      z_range: tuple[float, float]) -> Int:
    """Every fringe order whose height lies in the calibrated range somewhere among the pixels."""
    lo = camera.model.phase(x, y, np.full_like(x, z_range[0]))
    hi = camera.model.phase(x, y, np.full_like(x, z_range[1]))
    k_min = math.floor((np.nanmin(np.minimum(lo, hi)) - np.pi) / TWO_PI)
    k_max = math.ceil((np.nanmax(np.maximum(lo, hi)) + np.pi) / TWO_PI)
    return np.arange(k_min, k_max + 1, dtype=np.int64)


def _candidate_heights(camera: CalibratedCamera, pixels: npt.NDArray[np.intp], dphi: F64,
                       ks: Int, z_range: tuple[float, float]) -> F64:
    """Z (N, K) of every candidate order; NaN beyond the calibrated range (± BEYOND_RANGE_MM)."""
    x, y = camera.x.ravel()[pixels], camera.y.ravel()[pixels]
    z = camera.model.height(x[:, None], y[:, None], dphi[:, None] + TWO_PI * ks[None, :])
    inside = (z >= z_range[0] - BEYOND_RANGE_MM) & (z <= z_range[1] + BEYOND_RANGE_MM)
    return np.asarray(np.where(inside, z, np.nan))


@dataclass
class GridOrder:
    """Multi-view fringe orders on the coarse grid: pixels (flat full-resolution indices) with a
    confident pick, their order and the absolute phase it gives."""

    pixels: npt.NDArray[np.intp]
    order: Int
    absolute_phase: F64


def grid_order(cam_a: CalibratedCamera, phase_a: Phase, cam_b: CalibratedCamera,
               phase_b: Phase, z_range: tuple[float, float], *, stride: int = COARSE_STRIDE,
               within: Bool | None = None) -> GridOrder:
    """The multi-view fringe order on every ``stride``-th pixel of A's mask (and of ``within``,
    a mask of A's pixels, if given).

    All candidates of all grid pixels are evaluated at once; a pick is kept when it matches B
    within :data:`MAX_MISMATCH_RAD` and beats the runner-up by :data:`MIN_SEPARATION_RAD`, then
    a median over each grid pixel's neighbours cleans isolated wrong picks.
    """
    w = phase_a.dphi.shape[1]
    s, o = stride, stride // 2
    grid_valid = phase_a.valid[o::s, o::s]
    if within is not None:
        grid_valid = grid_valid & within[o::s, o::s]
    gi, gj = np.nonzero(grid_valid)
    pixels = ((gi * s + o) * w + gj * s + o).astype(np.intp)
    empty = GridOrder(pixels[:0], np.zeros(0, np.int64), np.zeros(0))
    if pixels.size == 0:
        return empty
    x, y = cam_a.x.ravel()[pixels], cam_a.y.ravel()[pixels]
    dphi = phase_a.dphi.ravel()[pixels].astype(np.float64)
    ks = _candidate_orders(cam_a, x, y, z_range)
    z = _candidate_heights(cam_a, pixels, dphi, ks, z_range)
    # Only the candidates inside the calibrated range are judged (on the eye phantom 72 % of
    # the pixels' candidates): the others cannot win.
    inside = np.isfinite(z)
    mismatch = np.full(z.shape, np.inf)
    mismatch[inside] = _mismatch(cam_a, cam_b, phase_b.pinhole_view(cam_b),
                                 np.broadcast_to(pixels[:, None], z.shape)[inside], z[inside])
    best = np.argmin(mismatch, axis=1)
    rows = np.arange(len(pixels))
    # The runner-up must lose clearly. Candidates whose point leaves B's field cannot be
    # judged and do not compete: counting them as possible matches left a fifth of an eye
    # phantom's points (far candidates leave a camera's field for most pixels near the top and
    # bottom of the image). The wrong orders this admits where the true point left B's view
    # form patches that the speckle filter and the cross-check remove.
    rival = mismatch.copy()
    rival[rows, best] = np.inf
    confident = ((mismatch[rows, best] < MAX_MISMATCH_RAD)
                 & (rival.min(axis=1) - mismatch[rows, best] >= MIN_SEPARATION_RAD))
    if not confident.any():
        return empty
    order = ks[best]
    # Median vote on the grid: orders as small integers, holes filled from their neighbours
    # first so the median at the mask's edge is not dragged towards zero.
    offset = int(order[confident].min()) - 1
    coded = np.zeros(grid_valid.shape, np.uint8)
    coded[gi[confident], gj[confident]] = (order[confident] - offset).astype(np.uint8)
    filled = np.where(coded > 0, coded, cv2.dilate(coded, np.ones((3, 3), np.uint8)))
    voted = cv2.medianBlur(filled, VOTE_SIZE)[gi, gj].astype(np.int64) + offset
    keep = confident & (voted == order)
    order = order[keep]
    return GridOrder(pixels[keep], order, dphi[keep] + TWO_PI * order)


def propagate_order(grid: GridOrder, phase_a: Phase) -> tuple[npt.NDArray[np.intp], Int]:
    """Full-resolution orders from the grid: each masked-in pixel takes the order that brings its
    wrapped phase nearest the absolute phase interpolated from its grid neighbours (a smooth
    surface moves far less than π between grid pixels; where it does not, the check against
    the other camera catches it)."""
    h, w = phase_a.dphi.shape
    s, o = COARSE_STRIDE, COARSE_STRIDE // 2
    gh, gw = len(range(o, h, s)), len(range(o, w, s))
    weight = np.zeros((gh, gw), np.float32)
    value = np.zeros((gh, gw), np.float32)
    gi, gj = np.divmod(grid.pixels, w)
    weight[gi // s, gj // s] = 1.0
    value[gi // s, gj // s] = grid.absolute_phase
    # cv2.resize by an odd factor samples grid pixel n exactly at full pixel s·n + s//2.
    # The last row or column of the image may lie beyond the grid's reach: repeat the edge.
    size, pad = (gw * s, gh * s), ((0, max(0, h - gh * s)), (0, max(0, w - gw * s)))
    weight_up = np.pad(cv2.resize(weight, size, interpolation=cv2.INTER_LINEAR), pad,
                       mode="edge")[:h, :w]
    value_up = np.pad(cv2.resize(value, size, interpolation=cv2.INTER_LINEAR), pad,
                      mode="edge")[:h, :w]
    pixels = np.flatnonzero(phase_a.valid & (weight_up > 0.2))
    estimate = value_up.ravel()[pixels] / weight_up.ravel()[pixels]
    order = np.rint((estimate - phase_a.dphi.ravel()[pixels]) / TWO_PI).astype(np.int64)
    return pixels.astype(np.intp), order


@dataclass(frozen=True)
class Unwrapped:
    """A camera's masked-in pixels unwrapped: their 2π steps from the wrapped phase, each
    consistent only within its region (:func:`spatial_unwrap`)."""

    pixels: npt.NDArray[np.intp]
    steps: Int
    region: Int
    """1 … ``count``: pixels of one region were unwrapped along paths through each other."""
    count: int


def spatial_unwrap(phase: Phase) -> Unwrapped:
    """The masked phase unwrapped by scikit-image's quality-guided (Herráez) unwrapper on every
    :data:`UNWRAP_STRIDE`-th pixel of each axis, each pixel stepped to the unwrapped phase of
    the nearest of the (up to four) samples within one pixel of it that lies in its own
    4-connected region. A region is a region of the full mask and of the samples' mask at once
    (a narrow neck of the mask may part the samples; each part is unwrapped on its own), so its
    steps come from one unwrapping. Pixels without such a sample (a few at the mask's edges)
    are left out.

    Why not the full image: the unwrapper took 45–52 ms a camera on the eye phantom, on the
    samples 9 ms, and the orders, checked against the multi-view picks, were as often right
    (docs/notes/speed.md, twenty-first session).
    """
    dphi, valid = phase.dphi, phase.valid
    w = valid.shape[1]
    s = UNWRAP_STRIDE
    sampled = valid[::s, ::s]
    pixels = np.flatnonzero(valid).astype(np.intp)
    if not sampled.any():
        return Unwrapped(pixels[:0], np.zeros(0, np.int64), np.zeros(0, np.int64), 0)
    coarse = np.ma.getdata(unwrap_phase(  # type: ignore[no-untyped-call]
        np.ma.masked_array(dphi[::s, ::s].astype(np.float64), mask=~sampled)))
    # OpenCV's labelling: 0.55 ms on a 640 × 512 mask where ndimage.label takes 1.2.
    full_labels = cv2.connectedComponents(valid.view(np.uint8), connectivity=4)[1]
    coarse_labels, coarse_count = ndimage.label(sampled)
    si, sj = np.nonzero(sampled)
    pair = full_labels[si * s, sj * s].astype(np.int64) * (coarse_count + 1) + coarse_labels[si, sj]
    pairs, sample_region = np.unique(pair, return_inverse=True)
    rows, cols = sampled.shape
    region_of = np.zeros(rows * cols, np.int64)
    region_of[si * cols + sj] = sample_region + 1
    label_of = np.zeros(rows * cols, np.int64)
    label_of[si * cols + sj] = full_labels[si * s, sj * s]
    i, j = np.divmod(pixels, w)
    own = full_labels.ravel()[pixels]
    # Nearest first: the sample at or just above and left of the pixel serves all but the
    # mask's edges, so the others are tried only where it did not.
    up, left = i // s, j // s
    sample = up * cols + left
    sample[(region_of[sample] == 0) | (label_of[sample] != own)] = -1
    down, right = np.minimum(-(-i // s), rows - 1), np.minimum(-(-j // s), cols - 1)
    for ci, cj in ((up, right), (down, left), (down, right)):
        open_ = np.flatnonzero(sample < 0)
        index = ci[open_] * cols + cj[open_]
        take = (region_of[index] > 0) & (label_of[index] == own[open_])
        sample[open_[take]] = index[take]
    found = sample >= 0
    pixels, sample = pixels[found], sample[found]
    region = region_of[sample]
    steps = np.rint((coarse.ravel()[sample] - dphi.ravel()[pixels]) / TWO_PI).astype(np.int64)
    return Unwrapped(pixels, steps, region, len(pairs))


def _region_votes(grid: GridOrder, step_at: Int, region_at: Int, count: int,
                  ) -> tuple[Int, Int, Int]:
    """Per region (0 … ``count``; 0 is no region) the offset most of the grid's picks in it
    vote for, their number and the number of all its picks (all zero without picks)."""
    if grid.pixels.size == 0:
        none = np.zeros(count + 1, np.int64)
        return none, none, none
    votes_region = region_at[grid.pixels]
    diff = grid.order - step_at[grid.pixels]
    low = int(diff.min())
    span = int(diff.max()) - low + 1
    table = np.bincount(votes_region * span + (diff - low),
                        minlength=(count + 1) * span).reshape(count + 1, span)
    table[0] = 0  # grid pixels left out of the unwrapping vote for nothing
    return table.argmax(axis=1) + low, table.max(axis=1), table.sum(axis=1)


def spatial_order(cam_a: CalibratedCamera, phase_a: Phase, cam_b: CalibratedCamera,
                  phase_b: Phase, z_range: tuple[float, float],
                  depth_prior_mm: float | None, *, grid: GridOrder | None = None,
                  ) -> tuple[npt.NDArray[np.intp], Int, npt.NDArray[np.bool_]]:
    """Orders from quality-guided spatial unwrapping (:func:`spatial_unwrap`), one offset per
    region, voted by B's multi-view picks (:func:`grid_order`): first on every
    :data:`SPARSE_VOTE_STRIDE`-th pixel, then, for a region those picks did not settle
    (:data:`SPARSE_MIN_VOTES`, :data:`SPARSE_MIN_SHARE`), on every :data:`COARSE_STRIDE`-th
    pixel of it. ``grid``: picks already made (on every pixel's grid); they vote alone.

    Returns the pixels, their orders and whether each pixel's region was fixed by multi-view
    votes (True) or by the depth prior (False). Regions with neither are dropped.
    """
    h, w = phase_a.dphi.shape
    unwrapped = spatial_unwrap(phase_a)
    count, pixels, steps, region = (unwrapped.count, unwrapped.pixels, unwrapped.steps,
                                    unwrapped.region)
    if count == 0:
        return np.zeros(0, np.intp), np.zeros(0, np.int64), np.zeros(0, bool)
    sizes = np.bincount(region, minlength=count + 1)
    min_region = _area_px(cam_a, MIN_REGION_PX)
    decided = np.zeros(count + 1, np.int8)  # 0 undecided, 1 multi-view, 2 depth prior
    step_at = np.zeros(h * w, np.int64)
    step_at[pixels] = steps
    region_at = np.zeros(h * w, np.int64)
    region_at[pixels] = region
    if grid is not None:
        offset, support, total = _region_votes(grid, step_at, region_at, count)
    else:
        offset, support, total = _region_votes(
            grid_order(cam_a, phase_a, cam_b, phase_b, z_range, stride=SPARSE_VOTE_STRIDE),
            step_at, region_at, count)
        settled = (total >= SPARSE_MIN_VOTES) & (support >= SPARSE_MIN_SHARE * total)
        unsettled = np.flatnonzero(~settled & (sizes >= min_region))
        unsettled = unsettled[unsettled > 0]
        if unsettled.size:
            mask = np.zeros(count + 1, bool)
            mask[unsettled] = True
            within = mask[region_at].reshape(h, w)
            dense = _region_votes(grid_order(cam_a, phase_a, cam_b, phase_b, z_range,
                                             within=within), step_at, region_at, count)
            for mine, theirs in zip((offset, support, total), dense, strict=True):
                mine[unsettled] = theirs[unsettled]
    majority = support >= np.maximum(MIN_REGION_VOTES, 0.6 * total)
    offset = np.where(majority, offset, 0)
    decided[majority] = 1
    undecided = np.flatnonzero((decided == 0) & (sizes >= min_region))
    undecided = undecided[undecided > 0]
    if depth_prior_mm is not None and undecided.size:
        # The offset that puts the region's median pixel nearest the prior height.
        level = phase_a.dphi.ravel()[pixels].astype(np.float64) + TWO_PI * steps
        medians = ndimage.median(level, region, undecided)
        labels_present, first = np.unique(region, return_index=True)
        index = first[np.searchsorted(labels_present, undecided)]
        x, y = cam_a.x.ravel()[pixels[index]], cam_a.y.ravel()[pixels[index]]
        ks = np.arange(-60, 61)  # far more orders than any calibrated volume holds
        z = cam_a.model.height(x[:, None], y[:, None],
                               np.asarray(medians)[:, None] + TWO_PI * ks[None, :])
        best = np.nanargmin(np.abs(np.where(np.isfinite(z), z, np.inf) - depth_prior_mm), axis=1)
        offset[undecided] = ks[best]
        decided[undecided] = 2
    keep = (decided[region] > 0) & (sizes[region] >= min_region)
    return (pixels[keep].astype(np.intp), steps[keep] + offset[region[keep]],
            decided[region[keep]] == 1)


def depth_prior_order(cam_a: CalibratedCamera, phase_a: Phase, z_range: tuple[float, float],
                      depth_prior_mm: float) -> tuple[npt.NDArray[np.intp], Int]:
    """Per pixel, the order whose height lies nearest ``depth_prior_mm`` (no other camera)."""
    pixels = np.flatnonzero(phase_a.valid).astype(np.intp)
    x, y = cam_a.x.ravel()[pixels], cam_a.y.ravel()[pixels]
    ks = _candidate_orders(cam_a, x, y, z_range)
    dphi = phase_a.dphi.ravel()[pixels].astype(np.float64)
    z = _candidate_heights(cam_a, pixels, dphi, ks, z_range)
    distance = np.where(np.isnan(z), np.inf, np.abs(z - depth_prior_mm))
    found = np.isfinite(distance).any(axis=1)
    best = np.argmin(distance, axis=1)
    return pixels[found], ks[best[found]]


def _points(camera: CalibratedCamera, phase: Phase, pixels: npt.NDArray[np.intp],
            order: Int) -> tuple[F64, F64]:
    """WCS points (N, 3) and their heights: Z from the model, X and Y from the pixel's ray."""
    x, y = camera.x.ravel()[pixels], camera.y.ravel()[pixels]
    z = camera.model.height(x, y, phase.dphi.ravel()[pixels] + TWO_PI * order)
    return camera.points_at(pixels, z), z


def _despeckle(pixels: npt.NDArray[np.intp], z: F64, shape: tuple[int, int],
               min_px: int | tuple[int, ...] = SPECKLE_PX, step_mm: float = SPECKLE_STEP_MM,
               ) -> Bool:
    """Which points lie in a patch of continuous depth (neighbours less than ``step_mm``
    apart) of at least ``min_px`` pixels (several sizes give an (N, sizes) array from one depth
    image).

    ``cv2.filterSpeckles`` (written for disparity maps) does the region growing; it takes 16-bit
    integers, so heights go in as hundredths of a millimetre.
    """
    invalid = np.int16(-32768)
    depth = np.full(shape, invalid, np.int16)
    finite = np.isfinite(z)
    depth.ravel()[pixels[finite]] = np.clip(np.rint(z[finite] * 100), -32000, 32000)
    sizes = (min_px,) if isinstance(min_px, int) else min_px
    kept = []
    for size in sizes:
        filtered = depth.copy() if len(sizes) > 1 else depth
        cv2.filterSpeckles(filtered, int(invalid), size, round(step_mm * 100))
        kept.append(finite & (filtered.ravel()[pixels] != invalid))
    return np.asarray(kept[0] if isinstance(min_px, int) else np.stack(kept, axis=1))


def _patch_confirmed(cloud: CameraCloud, candidate: Bool, cam: CalibratedCamera,
                     other: CalibratedCamera, phase_other: Phase,
                     z_range: tuple[float, float]) -> Bool:
    """Which ``candidate`` points lie in a small patch whose order the other camera confirms as
    a whole: over the patch, its own order matches the other camera's phase within
    :data:`PATCH_OWN_RAD`, each neighbouring order (:data:`PATCH_ORDERS`) either leaves the
    calibrated volume or misses by :data:`PATCH_MARGIN_RAD` more (medians), judged on
    :data:`PATCH_JUDGED_SHARE` of it, and no order continues the points around the patch
    better than its own (:func:`_fits_surroundings`).

    One pixel's order can match the other camera by chance; a patch of hundreds of pixels all
    matching with one order to the noise, and missing with the neighbouring ones, hardly can.
    The wrong-order island measured on a tilted plate (three orders off, isolated at the image
    border) matched only to 0.19–0.25 rad; the eye's sclera patches to 0.01–0.05 rad.
    Candidates are grouped by 4-connectivity (depth steps inside a group are rare: the speckle
    filter that selected them already splits at :data:`SPECKLE_STEP_MM`).
    """
    keep = np.zeros(len(cloud.pixels), bool)
    index = np.flatnonzero(candidate)
    if index.size == 0:
        return keep
    pixels = cloud.pixels[index]
    rows, cols = np.divmod(pixels, cam.shape[1])
    top, left = int(rows.min()), int(cols.min())
    image = np.zeros((int(rows.max()) - top + 1, int(cols.max()) - left + 1), np.uint8)
    image[rows - top, cols - left] = 1
    count, labels = cv2.connectedComponents(image, connectivity=4)
    patch = labels[rows - top, cols - left]
    x, y = cam.x.ravel()[pixels], cam.y.ravel()[pixels]
    z = cloud.points[index, 2]
    absolute = cam.model.phase(x, y, z)
    view = phase_other.pinhole_view(other)
    own = _mismatch(cam, other, view, pixels, z)
    z_near, inside = _shifted_heights(cam, x, y, absolute, PATCH_ORDERS, z_range)
    cost = _mismatch(cam, other, view, pixels, np.where(inside, z_near, z_range[0]))
    judged = (cost < np.pi) & inside
    around = np.full(len(cloud.pixels), np.nan)
    around[index] = _surroundings(cloud, candidate, cam.shape,
                                  max(1, round(PATCH_RING_PX / cam.spacing_px)))
    for label in range(1, count):
        members = patch == label
        own_median = float(np.median(own[members]))
        if own_median >= PATCH_OWN_RAD:
            continue
        confirmed = True
        for column in range(len(PATCH_ORDERS)):
            possible = inside[members, column]
            if possible.mean() < 0.5:
                continue  # that order puts the patch outside the calibrated volume
            if (judged[members, column].mean() < PATCH_JUDGED_SHARE
                    or float(np.median(cost[members, column][possible]))
                    < own_median + PATCH_MARGIN_RAD):
                confirmed = False
                break
        if confirmed and _fits_surroundings(cam, x[members], y[members], absolute[members],
                                            z[members], around[index[members]], z_range):
            keep[index[members]] = True
    return keep


def _shifted_heights(cam: CalibratedCamera, x: F64, y: F64, absolute: F64,
                     shifts: tuple[int, ...], z_range: tuple[float, float]) -> tuple[F64, Bool]:
    """Heights (N, len(shifts)) of pixels' absolute phases shifted by whole orders, and whether
    each lies in the calibrated volume."""
    turns = TWO_PI * np.asarray(shifts, np.float64)
    z = cam.model.height(x[:, None], y[:, None], absolute[:, None] + turns[None, :])
    inside = (z >= z_range[0] - BEYOND_RANGE_MM) & (z <= z_range[1] + BEYOND_RANGE_MM)
    return np.asarray(z), np.asarray(inside)


def _surroundings(cloud: CameraCloud, candidate: Bool, shape: tuple[int, int],
                  ring_px: int = PATCH_RING_PX) -> F64:
    """For each ``candidate`` point: the mean height of the cloud's other points (not
    ``candidate``) within ``ring_px`` of it (a square), NaN where there are none.

    A mean rather than a median (OpenCV has no masked median): the surroundings of a patch are
    one surface or two (the lids and the skin), a fringe's depth from a wrong order. Box sums
    over the candidates' bounding box only keep it to a fraction of a millisecond.
    """
    pixels = cloud.pixels[candidate]
    rows, cols = np.divmod(pixels, shape[1])
    r = ring_px
    top, left = max(0, int(rows.min()) - r), max(0, int(cols.min()) - r)
    bottom, right = min(shape[0], int(rows.max()) + r + 1), min(shape[1], int(cols.max()) + r + 1)
    full = np.full(shape, np.nan, np.float32)
    full.ravel()[cloud.pixels] = cloud.points[:, 2]
    full.ravel()[pixels] = np.nan
    depth = full[top:bottom, left:right]
    known = np.isfinite(depth).astype(np.float32)
    depth = np.nan_to_num(depth, nan=0.0)
    size = (2 * r + 1, 2 * r + 1)
    total = cv2.boxFilter(depth, -1, size, normalize=False, borderType=cv2.BORDER_CONSTANT)
    count = cv2.boxFilter(known, -1, size, normalize=False, borderType=cv2.BORDER_CONSTANT)
    total, count = total[rows - top, cols - left], count[rows - top, cols - left]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.asarray(np.where(count >= 0.5, total / count, np.nan), dtype=np.float64)


def _fits_surroundings(cam: CalibratedCamera, x: F64, y: F64, absolute: F64, z: F64,
                       around: F64, z_range: tuple[float, float]) -> bool:
    """Whether no other order (:data:`PATCH_FAR_ORDERS`) puts a patch nearer to the points
    around it than its own order does (median over the patch's pixels that have surroundings).

    A patch with surroundings on fewer than :data:`PATCH_RING_MIN_PX` pixels cannot be
    checked this way and passes: :data:`PATCH_OWN_RAD` alone guards it. (Requiring
    surroundings cost the eye 12 % of its sclera points, small patches whose lids around them
    were masked; the wrong-order island measured on a tilted plate was isolated too, at the
    image border with its true surroundings gone from the other camera's view.)
    """
    seen = np.isfinite(around)
    if seen.sum() < _area_px(cam, PATCH_RING_MIN_PX):
        return True
    z_far, inside = _shifted_heights(cam, x[seen], y[seen], absolute[seen], PATCH_FAR_ORDERS,
                                     z_range)
    own_gap = float(np.median(np.abs(z[seen] - around[seen])))
    gaps = np.where(inside, np.abs(z_far - around[seen][:, None]), np.inf)
    return not (np.isfinite(gaps).any() and float(np.min(np.median(gaps, axis=0))) < own_gap)


def _cloud(camera: CalibratedCamera, phase: Phase, pixels: npt.NDArray[np.intp], points: F64,
           z: F64, cost: F64, source: npt.NDArray[np.uint8], z_range: tuple[float, float],
           ) -> CameraCloud:
    """A camera's cloud from its pixels' points (:func:`_points`): their quality, and only the
    points within the calibrated range."""
    keep = np.isfinite(z) & (z >= z_range[0] - BEYOND_RANGE_MM) & (z <= z_range[1]
                                                                  + BEYOND_RANGE_MM)
    modulation = phase.modulation.ravel()[pixels]
    strong = float(np.percentile(modulation, 95)) if modulation.size else 1.0
    quality = np.clip(modulation / strong, 0, 1) * np.clip(1 - cost / np.pi, 0, 1)
    return CameraCloud(camera.camera_id, rows_where(points, keep), quality[keep].astype(np.float32),
                       source[keep], pixels[keep])


def camera_cloud(cam_a: CalibratedCamera, phase_a: Phase, cam_b: CalibratedCamera | None,
                 phase_b: Phase | None, z_range: tuple[float, float], *,
                 method: str = "multi-view", depth_prior_mm: float | None = None,
                 ) -> CameraCloud:
    """Camera A's points, its fringe order fixed with camera B of the same unit (see the module
    docstring for ``method``); without B only ``depth_prior_mm`` can fix it."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, not {method!r}")
    if cam_b is None or phase_b is None:
        if depth_prior_mm is None:
            raise ValueError("a camera without a partner needs depth_prior_mm")
        pixels, order = depth_prior_order(cam_a, phase_a, z_range, depth_prior_mm)
        source = np.full(pixels.size, ORDER_SOURCES.index("depth prior"), np.uint8)
        points, z = _points(cam_a, phase_a, pixels, order)
        return _cloud(cam_a, phase_a, pixels, points, z, np.zeros(pixels.size), source, z_range)
    if method == "multi-view":
        pixels, order = propagate_order(grid_order(cam_a, phase_a, cam_b, phase_b, z_range),
                                        phase_a)
        source = np.zeros(pixels.size, np.uint8)
    else:
        pixels, order, by_votes = spatial_order(cam_a, phase_a, cam_b, phase_b, z_range,
                                                depth_prior_mm)
        source = np.where(by_votes, 1, 2).astype(np.uint8)
    # Every pixel's final order checked against B: a multi-view pixel must match B's phase; a
    # spatially unwrapped one must not contradict it where B can judge.
    points, z = _points(cam_a, phase_a, pixels, order)
    cost = _mismatch(cam_a, cam_b, phase_b.pinhole_view(cam_b), pixels, np.nan_to_num(z))
    # A spatially unwrapped pixel is kept where B cannot judge it (its region's order came from
    # the votes or the depth prior; unit_clouds keeps a voted one only where it continues
    # points B confirms); every other pixel must match B. Spatial unwrapping that slipped by a
    # fringe inside a voted region (across a noisy patch) is caught here where B sees it.
    unwrapped = source != ORDER_SOURCES.index("multi-view")
    keep = (cost < MAX_MISMATCH_RAD) | (unwrapped & (cost == np.pi))
    cost = np.where(unwrapped & (cost == np.pi), 0.0, cost)
    return _cloud(cam_a, phase_a, pixels[keep], points[keep], z[keep], cost[keep], source[keep],
                  z_range)


def _contradicted(cloud: CameraCloud, cam: CalibratedCamera, other: CameraCloud,
                  cam_other: CalibratedCamera) -> tuple[Bool, Bool]:
    """For each point of ``cloud``: does the other camera's reconstruction exist where the point
    projects (confirmable), and does it disagree by more than :data:`AGREEMENT_MM`?"""
    depth = other.depth_image(cam_other.shape)
    map_x, map_y = cam_other.pinhole_maps()
    pinhole_depth = cv2.remap(depth.astype(np.float32), map_x, map_y, cv2.INTER_NEAREST,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
    p0, p1 = cam.towards(cam_other)
    z = cloud.points[:, 2]
    x_b, y_b, z_b = (p0[c].take(cloud.pixels) + z * p1[c].take(cloud.pixels) for c in range(3))
    K = cam_other.K
    with np.errstate(divide="ignore", invalid="ignore"):
        inverse = 1.0 / z_b
        u = np.rint((K[0, 0] * x_b + K[0, 1] * y_b) * inverse + K[0, 2])
        v = np.rint(K[1, 1] * y_b * inverse + K[1, 2])
    h, w = cam_other.shape
    with np.errstate(invalid="ignore"):  # NaN (behind the camera) compares False: outside
        inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    seen = np.full(len(z), np.nan)
    flat = (v[inside] * w + u[inside]).astype(np.int64)
    seen[inside] = pinhole_depth.ravel()[flat]
    known = np.isfinite(seen)
    with np.errstate(invalid="ignore"):
        return known, known & (np.abs(seen - z) >= AGREEMENT_MM)


def unit_clouds(cam_a: CalibratedCamera, image_a: npt.ArrayLike | None,
                cam_b: CalibratedCamera, image_b: npt.ArrayLike | None,
                z_range: tuple[float, float], *,
                method: str = "multi-view", depth_prior_mm: float | None = None,
                saturation_dn: float | None = None, phases: tuple[Phase, Phase] | None = None,
                order_partners: tuple[tuple[CalibratedCamera, Phase],
                                      tuple[CalibratedCamera, Phase]] | None = None,
                ) -> tuple[CameraCloud, CameraCloud]:
    """Both cameras' points of one unit, each order fixed with the other camera, and each point
    checked against the other camera's own reconstruction.

    ``phases``: the images' :func:`camera_phase` when the caller has them already (live
    tracking reuses them for the limbus, and reconstructs :func:`decimated` cameras from their
    :meth:`Phase.decimated`); the images are then not read (they may be None).

    ``order_partners``: the cameras (with their phases) whose fringes fix A's and B's orders
    when the unit's own cameras cannot fix each other's (a unit blind to the order: a camera of
    another unit, lit by its own projector). Any calibrated camera can judge a candidate point:
    its phase model predicts its own projector's phase there. The two cameras' clouds are
    still checked against each other, which needs no fringe.

    A wrong order that happens to match the other camera's phase (an occlusion, a far surface
    behind an edge) is a point the other camera does not reconstruct there. The multi-view path
    keeps only points the other camera confirms (measured on an eye phantom: from 2.2 % of
    points beyond 1 mm to a few in ten thousand), at the price of the parts only one camera
    sees; the spatial path drops only the points the other camera contradicts.
    """
    if phases is None:
        if image_a is None or image_b is None:
            raise ValueError("unit_clouds needs the images or their phases")
        phases = (camera_phase(cam_a, image_a, saturation_dn),
                  camera_phase(cam_b, image_b, saturation_dn))
    phase_a, phase_b = phases
    (judge_a, view_a), (judge_b, view_b) = order_partners or ((cam_b, phase_b), (cam_a, phase_a))
    cloud_a = camera_cloud(cam_a, phase_a, judge_a, view_a, z_range, method=method,
                           depth_prior_mm=depth_prior_mm)
    cloud_b = camera_cloud(cam_b, phase_b, judge_b, view_b, z_range, method=method,
                           depth_prior_mm=depth_prior_mm)
    known_a, wrong_a = _contradicted(cloud_a, cam_a, cloud_b, cam_b)
    known_b, wrong_b = _contradicted(cloud_b, cam_b, cloud_a, cam_a)
    checked_a = cloud_a.subset(_checked(cloud_a, known_a, wrong_a, cam_a, phase_a))
    checked_b = cloud_b.subset(_checked(cloud_b, known_b, wrong_b, cam_b, phase_b))
    return (_despeckled(checked_a, cam_a.shape, cam_a, judge_a, view_a, z_range),
            _despeckled(checked_b, cam_b.shape, cam_b, judge_b, view_b, z_range))


def _despeckled(cloud: CameraCloud, shape: tuple[int, int], cam: CalibratedCamera | None = None,
                other: CalibratedCamera | None = None, phase_other: Phase | None = None,
                z_range: tuple[float, float] | None = None) -> CameraCloud:
    """The points in patches of :data:`SPECKLE_PX` or more, and (given the other camera) those
    in smaller patches down to :data:`MIN_PATCH_PX` whose order it confirms as a whole."""
    z = cloud.points[:, 2]
    if cam is None or other is None or phase_other is None or z_range is None:
        return cloud.subset(_despeckle(cloud.pixels, z, shape))
    kept = _despeckle(cloud.pixels, z, shape, (_area_px(cam, SPECKLE_PX),
                                               max(_area_px(cam, MIN_PATCH_PX),
                                                   MIN_PATCH_POINTS)),
                      SPECKLE_STEP_MM * cam.spacing_px)
    large, small = kept[:, 0], kept[:, 1] & ~kept[:, 0]
    return cloud.subset(large | _patch_confirmed(cloud, small, cam, other, phase_other,
                                                 z_range))


def _checked(cloud: CameraCloud, known: Bool, wrong: Bool, cam: CalibratedCamera,
             phase: Phase) -> Bool:
    """Points the other camera confirms; a point whose region only the depth prior fixed needs
    only not to be contradicted (the other camera could not judge it); a spatially unwrapped
    point of a voted region that the other camera cannot judge (it does not see it) is kept
    where it continues confirmed points without a depth step (:data:`SPECKLE_STEP_MM`) and its
    fringe's local frequency lies where the pass band passes it unbiased
    (:data:`EXTENSION_MIN_GAIN`).

    Why: the multi-view order needs both cameras, so what only one camera sees (a band along
    the image's edge, a surface turned from the partner) was lost although the spatial
    unwrapping reaches it from the confirmed part. A slip of a fringe on the way is a depth
    step of a fringe's height (millimetres), which cuts the continuation there; the gain's
    condition keeps out steep flanks whose fringes the band passes biased (measured:
    docs/notes/fringe-order.md, "What only one camera sees")."""
    source = cloud.order_source
    by_prior = source == ORDER_SOURCES.index("spatial + depth prior")
    base = (known | by_prior) & ~wrong
    extension = (source == ORDER_SOURCES.index("spatial + multi-view")) & ~known & ~wrong
    if not extension.any():
        return np.asarray(base)
    at = np.flatnonzero(extension)  # only where it decides: 5–10 % of an eye's points
    extension[at] = _unbiased(cam, phase, cloud.pixels[at])
    return np.asarray(base | (extension & _continues(
        cloud, base | extension, base, cam.shape, SPECKLE_STEP_MM * cam.spacing_px)))


EXTENSION_MIN_GAIN = 0.99
"""The least pass-band gain (:func:`~eyeserver.pipeline.demodulate.band_gain`) at a pixel's
local fringe frequency for a point the other camera cannot check: on the flat top the phase is
unbiased; off it, the bend correction is the only defence, and the other camera's check no
longer backs it."""


def _unbiased(cam: CalibratedCamera, phase: Phase, pixels: npt.NDArray[np.intp]) -> Bool:
    """Whether each pixel's local fringe frequency (the carrier plus the surface phase's wrapped
    central differences, per image pixel) has a band gain of :data:`EXTENSION_MIN_GAIN`."""
    h, w = phase.dphi.shape
    rows, cols = np.divmod(pixels, w)
    up, down = np.minimum(rows + 1, h - 1), np.maximum(rows - 1, 0)
    right, left = np.minimum(cols + 1, w - 1), np.maximum(cols - 1, 0)
    dphi = phase.dphi
    step = 2.0 * cam.spacing_px * TWO_PI  # two samples, radians to cycles
    fy = wrap(dphi[up, cols].astype(np.float64) - dphi[down, cols]) / step
    fx = wrap(dphi[rows, right].astype(np.float64) - dphi[rows, left]) / step
    return np.asarray(band_gain(cam.carrier, fy, fx) >= EXTENSION_MIN_GAIN)


def _continues(cloud: CameraCloud, among: Bool, anchors: Bool, shape: tuple[int, int],
               step_mm: float) -> Bool:
    """Which points of ``among`` are 4-connected to an ``anchors`` point through pixels of
    ``among`` whose neighbours lie less than ``step_mm`` (mm) apart in depth; a pixel next to
    a larger step is a cut and continues nothing."""
    height, width = shape
    depth = np.full(height * width, np.nan)
    depth[cloud.pixels[among]] = cloud.points[among, 2]
    depth = depth.reshape(shape)
    cut = np.zeros(shape, bool)
    with np.errstate(invalid="ignore"):
        rows = np.abs(np.diff(depth, axis=0)) >= step_mm
        cols = np.abs(np.diff(depth, axis=1)) >= step_mm
    cut[:-1] |= rows
    cut[1:] |= rows
    cut[:, :-1] |= cols
    cut[:, 1:] |= cols
    labels, _ = ndimage.label(np.isfinite(depth) & ~cut)
    flat = labels.ravel()
    anchored = np.unique(flat[cloud.pixels[anchors & among]])
    anchored = anchored[anchored > 0]
    return np.asarray(np.isin(flat[cloud.pixels], anchored) & among)
