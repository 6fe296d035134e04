"""Fiducial dots: find them in fringe images, pair them across cameras, triangulate them, and read
the fringe reconstruction's 3-D position at them (docs/design.md §6, "3-D accuracy at fiducials").

The paper validated its surfaces at small dark dots painted on the phantoms: each dot is located
in both cameras of a unit, triangulated, and compared with the position the fringe
reconstruction gives at the same dot. The four pure steps:

* :func:`detect_fiducials`: sub-pixel centres of dark round dots in one fringe image;
* :func:`match_stereo`: which dot of camera A is which of camera B (epipolar constraint);
* :func:`triangulate`: the WCS position of matched dots (``cv2.triangulatePoints``);
* :func:`surface_position`: where the camera's ray through a dot meets the surface the fringe
  reconstruction measured around it (on the dot itself the fringe is too dark).

A dot on fringes. A dot of albedo ``a`` shows ``a·I0(x)``, ``I0`` the image of the unmarked
surface; only its darkness relative to ``I0`` is symmetric about its centre (the raw darkness,
footprint times fringe, pulls a centroid towards the fringe's bright side), so ``I0`` is
estimated twice. For detection, a morphological closing with a line segment longer than a dot, in
twelve orientations, the smallest kept: every closing fills a dot, the orientation along a fringe
leaves it, and dark regions larger than a dot in some direction (an iris, shadows, edges) stay
dark. For the centre, the fringe is inpainted across the dot from both sides along its own path,
``I0(x) = ½·(I(x + L·t + b·n) + I(x − L·t + b·n))`` (``t`` the fringe's direction, ``n`` its normal,
``L`` just over the dot's diameter, ``b`` the bend of a curved fringe), which cancels a linear
change of brightness or phase along the path; ``t`` and ``b`` are fitted to a ring around the dot.
The centre is the centroid of ``1 − I/I0`` above 0.25 over the dot's core and a 2-px rim. A dot
is dropped rather than mislocated when the path predicts its ring poorly, its rim is dark too, the
fringe is not seen on both sides, its shape is wrong, or it does not stand out of the noise.
Measured accuracy: docs/notes/fiducials.md.

Conventions: pixels ``(u, v) = (column, row)``, integers at pixel centres, as OpenCV wants them;
cameras as in FORMATS.md and docs/design.md §2 (``x_cam = R·X_wcs + T``, ``K``, OpenCV distortion);
millimetres in the WCS.

References
----------
.. [1] Via et al., Phys. Imaging Radiat. Oncol. (2023), doi:10.1016/j.phro.2023.100517.
.. [2] R. Hartley and A. Zisserman, *Multiple View Geometry in Computer Vision*, 2nd ed.,
   Cambridge University Press (2004): §9.2 (fundamental matrix), §12.2 (linear triangulation).
.. [3] P. Soille, *Morphological Image Analysis*, 2nd ed., Springer (2003) (closings by lines).
.. [4] M. A. Fischler and R. C. Bolles, "Random sample consensus", Commun. ACM 24(6), 381–395
   (1981). doi:10.1145/358669.358692
"""

from __future__ import annotations

import math
import numbers
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from eyeserver.core.types import F32, F64, Bool
from eyeserver.pipeline.demodulate import checked_image
from eyeserver.pipeline.geometry import undistorted_normalised

__all__ = ["detect_fiducials", "match_stereo", "surface_position", "triangulate"]

# --- detection constants (the reasons are in the module docstring and at their use) -----------

# Noise smoothing (Gaussian σ, pixels) before detection: a dot of radius 2 px keeps a core
# darker than 0.35 of its surroundings on any fringe phase. The fringe's path around a dot is
# fitted on a smoother copy: its residual decides whether a dot is trusted.
_DETECTION_SMOOTHING_PX = 0.7
_PATH_SMOOTHING_PX = 1.0
# Orientations of the line closings (every 15°): a fringe at most 7.5° off a segment.
_LINE_ORIENTATIONS = 12
# A pixel is "dark" when it shows less than this fraction of the unmarked surface's brightness.
_DARK_RATIO = 0.5
# A dot's core must be at least this dark against the closings (a 2 px dot: ≤ 0.34).
_CORE_RATIO = 0.4
# The darkness of a dot, summed, must be at least this fraction of its core's area (the
# simulated paint: ≈ 0.6 after the floor below).
_MIN_DARKNESS_SHARE = 0.2
# Surfaces dimmer than this fraction of the image's bright level are not searched: their ratio
# is noise (the dark room behind the objects).
_BRIGHTNESS_FLOOR = 0.06
_BRIGHT_PERCENTILE = 99.5
# Tolerance on a dot's radius measured from its darkness, pixels; the fewest pixels of a dark
# core (a 2 px dot, blurred, keeps 4–10).
_SIZE_SLACK_PX = 0.5
_MIN_CORE_PX = 3
# A filled ellipse has the area 4π·sqrt(λ1·λ2) of its second moments; crescents, rings and
# L-shapes do not.
_FILL_RANGE = (0.75, 1.3)
# Margin of the dot region around the dark core, pixels: the dot's blurred rim. Its outermost
# pixels must be nearly as bright as the unmarked surface, or the dark core was only part of a
# larger dark feature (a dot above the size range, whose middle a closing left dark).
_RIM_PX = 2
_MAX_RIM_DARKNESS = 0.3
# Darkness below this is not counted in the centroid (noise on the surroundings, the faint
# rim); 0.05–0.35 measured, 0.25–0.35 best.
_DARKNESS_FLOOR = 0.25
# The fringe model must predict the ring around a dot within this RMS fraction of its
# brightness, or the dot's surroundings are no continuous fringe field (an edge, a shadow
# boundary, the iris) and its centre is not trusted.
_MAX_RING_RESIDUAL = 0.2
# The ring around a dot where the fringe's path is fitted: a narrow one (a sixth of a period,
# at least 4 px) describes the fringe where the dot is; a wider one reaches other features
# (the painted iris two millimetres away) and curvature the path does not follow.
_RING_WIDTH_PERIODS = 0.15
_RING_WIDTH_PX = 4.0
# Fringe directions tried around the structure tensor's (degrees), then bends (pixels), then
# finer directions.
_ANGLE_STEPS_DEG = np.arange(-12.0, 12.5, 2.0)
_BEND_STEPS_PX = np.arange(-4.0, 4.25, 0.5)
_FINE_ANGLE_STEPS_DEG = np.arange(-2.0, 2.25, 0.25)
# Two samples of I0 disagreeing by more than this ratio: one fell on another dark feature.
_SAMPLE_AGREEMENT = 0.6
# How far a dot's summed deficit must stand out of its noise (standard deviations): the
# simulated dots reach 13–200, dark clusters of noise (σ = 5 DN on a 10–70 DN fringe, or pure
# noise) at most 5.
_MIN_SIGNIFICANCE = 8.0

# --- surface fit constants ----------------------------------------------------------------------

# Rounds of trimming points of another surface from a ring; residuals below the floor (mm) are
# never trimmed (an exact surface has only rounding errors); the kept points must be most of
# the ring.
_TRIM_ROUNDS = 4
_TRIM_FLOOR_MM = 1e-3
_MIN_INLIER_SHARE = 0.7
_RANSAC_TRIALS = 64
_RANSAC_SEED = 20230517


# --- validation ---------------------------------------------------------------------------------


def _positive(value: object, name: str, minimum: float = 0.0) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"{name} must be a number, not {value!r}")
    number = float(value)
    if not (math.isfinite(number) and number > minimum):
        raise ValueError(f"{name} must be a finite number above {minimum:g}, not {value!r}")
    return number


def _checked_points(points: npt.ArrayLike, name: str) -> F64:
    array = np.asarray(points, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 2:
        raise ValueError(f"{name} must be an (N, 2) array of pixel positions (u, v), "
                         f"not of shape {array.shape}")
    if not np.isfinite(array).all():
        raise ValueError(f"{name} must be finite (no NaN or inf)")
    return array


def _checked_camera(K: npt.ArrayLike, dist: npt.ArrayLike, R: npt.ArrayLike, T: npt.ArrayLike,
                    suffix: str = "") -> tuple[F64, F64, F64, F64]:
    K_ = np.asarray(K, dtype=np.float64)
    if K_.shape != (3, 3) or not np.isfinite(K_).all():
        raise ValueError(f"K{suffix} must be a finite 3×3 camera matrix, not shape {K_.shape}")
    if not (K_[0, 0] > 0 and K_[1, 1] > 0):
        raise ValueError(f"K{suffix} must have positive focal lengths")
    dist_ = np.asarray(dist, dtype=np.float64).ravel()
    if dist_.size not in (4, 5, 8, 12, 14) or not np.isfinite(dist_).all():
        raise ValueError(f"dist{suffix} must hold 4, 5, 8, 12 or 14 finite OpenCV distortion "
                         f"coefficients, not {dist_.size}")
    R_ = np.asarray(R, dtype=np.float64)
    if R_.shape != (3, 3) or not np.isfinite(R_).all():
        raise ValueError(f"R{suffix} must be a finite 3×3 rotation matrix, not shape {R_.shape}")
    if not (np.allclose(R_ @ R_.T, np.eye(3), atol=1e-6) and np.linalg.det(R_) > 0):
        raise ValueError(f"R{suffix} must be a rotation matrix (orthonormal, determinant +1)")
    T_ = np.asarray(T, dtype=np.float64).ravel()
    if T_.shape != (3,) or not np.isfinite(T_).all():
        raise ValueError(f"T{suffix} must be a finite 3-vector, not shape "
                         f"{np.asarray(T).shape}")
    return K_, dist_, R_, T_


# --- detection ----------------------------------------------------------------------------------


def _line_kernel(length: int, angle_rad: float) -> npt.NDArray[np.uint8]:
    """A one-pixel-wide line segment of ``length`` pixels (odd) through the kernel's centre."""
    kernel = np.zeros((length, length), dtype=np.uint8)
    centre = length // 2
    dx = math.cos(angle_rad) * (length - 1) / 2
    dy = math.sin(angle_rad) * (length - 1) / 2
    cv2.line(kernel, (round(centre - dx), round(centre - dy)),
             (round(centre + dx), round(centre + dy)), 1, 1)
    return kernel


def _unmarked_brightness(smooth: F32, length: int) -> F32:
    """The image without its small dark features: the smallest of line closings (docstring)."""
    unmarked: F32 | None = None
    for k in range(_LINE_ORIENTATIONS):
        kernel = _line_kernel(length, math.pi * k / _LINE_ORIENTATIONS)
        # OpenCV's default border for morphology ignores the outside (−∞ for the dilation,
        # +∞ for the erosion), so a dot cut by the border is filled only from the inside.
        closed = np.asarray(cv2.morphologyEx(smooth, cv2.MORPH_CLOSE, kernel), dtype=np.float32)
        unmarked = closed if unmarked is None else np.minimum(unmarked, closed)
    assert unmarked is not None
    return unmarked


def _bilinear(image: F32, u: F64, v: F64) -> F64:
    """``image`` at sub-pixel positions (outside it: extrapolated from the border cells, for
    callers that mask those positions anyway)."""
    height, width = image.shape
    j0 = np.clip(np.floor(u).astype(np.intp), 0, width - 2)
    i0 = np.clip(np.floor(v).astype(np.intp), 0, height - 2)
    fu = u - j0
    fv = v - i0
    top = (1 - fu) * image[i0, j0] + fu * image[i0, j0 + 1]
    bottom = (1 - fu) * image[i0 + 1, j0] + fu * image[i0 + 1, j0 + 1]
    return np.asarray((1 - fv) * top + fv * bottom, dtype=np.float64)


def _inside(shape: tuple[int, ...], u: F64, v: F64) -> Bool:
    return np.asarray((u >= 0) & (u <= shape[1] - 1) & (v >= 0) & (v <= shape[0] - 1))


def _inpainted(image: F32, u: F64, v: F64, shift: F64, bend: F64) -> F64:
    """``I0`` at ``(u, v)`` from the samples at ``±shift + bend`` (module docstring).

    ``u`` and ``v`` are ``(..., N)``; ``shift`` and ``bend`` are ``(..., 2)`` offsets in pixels,
    one per leading index. ``bend`` follows a curved fringe: the points of a fringe of curvature
    κ at ``±L`` along its tangent both lie ``κ·L²/2`` off it on the same side. Where the two
    samples disagree strongly one of them fell on another dark feature (a neighbouring dot, the
    painted iris, a shadow), and the brighter one is the fringe.
    """
    ahead = _bilinear(image, u + (shift[..., 0] + bend[..., 0])[..., None],
                      v + (shift[..., 1] + bend[..., 1])[..., None])
    behind = _bilinear(image, u + (bend[..., 0] - shift[..., 0])[..., None],
                       v + (bend[..., 1] - shift[..., 1])[..., None])
    brighter = np.maximum(ahead, behind)
    agree = np.minimum(ahead, behind) >= _SAMPLE_AGREEMENT * brighter
    return np.asarray(np.where(agree, 0.5 * (ahead + behind), brighter), dtype=np.float64)


def _path_offsets(angles_rad: F64, length_px: float, bends_px: F64) -> tuple[F64, F64]:
    """``(shift, bend)``, each ``(P, 2)``, of paths along ``angles_rad`` bent by ``bends_px``."""
    along = np.stack([np.cos(angles_rad), np.sin(angles_rad)], axis=-1)
    across = np.stack([-along[:, 1], along[:, 0]], axis=-1)
    return length_px * along, bends_px[:, None] * across


class _Dot:
    """One dark component found by the detection pass."""

    def __init__(self, rows: npt.NDArray[np.intp], cols: npt.NDArray[np.intp]) -> None:
        self.rows = rows
        self.cols = cols
        self.centre = np.array([cols.mean(), rows.mean()])
        offsets = np.stack([cols - self.centre[0], rows - self.centre[1]])
        # Second moments of the pixel squares (a pixel adds 1/12 of its own width²).
        cov = offsets @ offsets.T / cols.size + np.eye(2) / 12.0
        self.eigenvalues = np.linalg.eigvalsh(cov)

    @property
    def semi_major_px(self) -> float:
        return 2.0 * math.sqrt(max(float(self.eigenvalues[1]), 0.0))

    @property
    def elongation(self) -> float:
        small, large = (max(float(e), 1e-12) for e in self.eigenvalues)
        return math.sqrt(large / small)

    @property
    def fill(self) -> float:
        small, large = (max(float(e), 0.0) for e in self.eigenvalues)
        return self.cols.size / max(4.0 * math.pi * math.sqrt(small * large), 1e-12)


def _refined_centre(values: F32, smooth: F32, gradients: tuple[F32, F32], dot: _Dot,
                    period_px: float, radius_range: tuple[float, float],
                    max_elongation: float) -> F64 | None:
    """Sub-pixel centre of ``dot`` from its darkness against the inpainted fringe, or None."""
    shape = values.shape
    cu, cv = dot.centre
    exclusion = dot.semi_major_px + _RIM_PX + 1.0
    length = 2.0 * exclusion + 1.0  # from anywhere on the dot to beyond it
    ring_out = exclusion + max(_RING_WIDTH_PERIODS * period_px, _RING_WIDTH_PX)

    # The dot's region: its dark pixels and their blurred rim.
    top, left = int(dot.rows.min()) - _RIM_PX, int(dot.cols.min()) - _RIM_PX
    box = np.zeros((int(dot.rows.max()) - top + _RIM_PX + 1,
                    int(dot.cols.max()) - left + _RIM_PX + 1), dtype=np.uint8)
    box[dot.rows - top, dot.cols - left] = 1
    grown = cv2.dilate(box, np.ones((3, 3), np.uint8), iterations=_RIM_PX)
    inner = cv2.dilate(box, np.ones((3, 3), np.uint8), iterations=_RIM_PX - 1)
    region_r, region_c = np.nonzero(grown)
    outermost = inner[region_r, region_c] == 0
    core = box[region_r, region_c] == 1
    region_u = (region_c + left).astype(np.float64)
    region_v = (region_r + top).astype(np.float64)
    if not _inside(shape, region_u, region_v).all():
        return None

    # The ring around it, where the fringe's path is found and checked.
    reach = math.ceil(ring_out)
    rr, cc = np.mgrid[math.floor(cv) - reach:math.floor(cv) + reach + 2,
                      math.floor(cu) - reach:math.floor(cu) + reach + 2]
    ring_u = cc.ravel().astype(np.float64)
    ring_v = rr.ravel().astype(np.float64)
    radius = np.hypot(ring_u - cu, ring_v - cv)
    keep = (radius >= exclusion) & (radius <= ring_out) & _inside(shape, ring_u, ring_v)
    ring_u, ring_v = ring_u[keep], ring_v[keep]
    if ring_u.size < 16:
        return None
    ring_i, ring_j = ring_v.astype(np.intp), ring_u.astype(np.intp)
    ring_values = smooth[ring_i, ring_j].astype(np.float64)
    ring_power = max(float(np.mean(ring_values**2)), 1e-12)

    def best_path(angles: F64, bends: F64) -> tuple[float, float, float]:
        """The ``(angle, bend, score)`` among paths that best predicts the ring: the relative
        mean square error of the prediction, on the noise-smoothed image."""
        shift, bend = _path_offsets(angles, length, bends)
        usable = np.ones((angles.size, ring_u.size), dtype=bool)
        for offset in (shift + bend, bend - shift):
            su = ring_u[None, :] + offset[:, 0:1]
            sv = ring_v[None, :] + offset[:, 1:2]
            usable &= _inside(shape, su, sv) & (np.hypot(su - cu, sv - cv) >= exclusion)
        error = np.where(usable, ring_values - _inpainted(smooth, ring_u, ring_v, shift, bend),
                         0.0)
        count = usable.sum(axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            scores = np.where(count >= 16, (error**2).sum(axis=1) / count / ring_power, np.inf)
        k = int(np.argmin(scores))
        return float(angles[k]), float(bends[k]), float(scores[k])

    # The fringe runs across the dominant gradient (structure tensor of the ring); then the
    # path that best predicts the ring itself: its direction, its bend, its direction again.
    gu, gv = gradients[0][ring_i, ring_j], gradients[1][ring_i, ring_j]
    juu, jvv, juv = float(gu @ gu), float(gv @ gv), float(gu @ gv)
    angle = 0.5 * math.atan2(2.0 * juv, juu - jvv) + 0.5 * math.pi
    angle, bend, score = best_path(angle + np.radians(_ANGLE_STEPS_DEG),
                                   np.zeros(_ANGLE_STEPS_DEG.size))
    angle, bend, score = best_path(np.full(_BEND_STEPS_PX.size, angle), _BEND_STEPS_PX)
    angle, bend, score = best_path(angle + np.radians(_FINE_ANGLE_STEPS_DEG),
                                   np.full(_FINE_ANGLE_STEPS_DEG.size, bend))
    if not score <= _MAX_RING_RESIDUAL**2:
        return None

    shift, bend_offset = _path_offsets(np.array([angle]), length, np.array([bend]))
    for offset in (shift[0] + bend_offset[0], bend_offset[0] - shift[0]):
        if not _inside(shape, region_u + offset[0], region_v + offset[1]).all():
            return None  # too near the border to see the fringe on both sides of the dot
    unmarked = _inpainted(values, region_u, region_v, shift, bend_offset)[0]
    observed = values[region_v.astype(np.intp), region_u.astype(np.intp)].astype(np.float64)
    # The dot must stand out of the noise: its summed deficit against the inpainted fringe,
    # over the noise of that deficit. The noise is the raw image's misfit to the same path on
    # the ring (model errors included); the inpainting averages two samples, so both the
    # misfit and the deficit of a pixel have the variance 1.5·σ².
    usable = np.ones(ring_u.size, dtype=bool)
    for offset in (shift[0] + bend_offset[0], bend_offset[0] - shift[0]):
        su, sv = ring_u + offset[0], ring_v + offset[1]
        usable &= _inside(shape, su, sv) & (np.hypot(su - cu, sv - cv) >= exclusion)
    misfit = (values[ring_i[usable], ring_j[usable]]
              - _inpainted(values, ring_u[usable], ring_v[usable], shift, bend_offset)[0])
    spread_dn = math.sqrt(max(float(np.mean(misfit**2)), 1e-12))
    significance = float(np.sum((unmarked - observed)[core])) / (spread_dn
                                                                 * math.sqrt(core.sum()))
    if significance < _MIN_SIGNIFICANCE:
        return None
    with np.errstate(divide="ignore", invalid="ignore"):
        darkness = np.where(unmarked > 0, 1.0 - observed / unmarked, 0.0)
    if float(np.mean(darkness[outermost])) > _MAX_RIM_DARKNESS:
        return None  # dark beyond the dot's rim: part of something larger
    weights = np.clip(darkness - _DARKNESS_FLOOR, 0.0, 1.0)
    total = float(weights.sum())
    # The weights must amount to a dark dot of about the detected size.
    if total < _MIN_DARKNESS_SHARE * dot.cols.size:
        return None
    centre = np.array([float(weights @ region_u) / total, float(weights @ region_v) / total])
    if np.hypot(*(centre - dot.centre)) > max(1.0, 0.5 * dot.semi_major_px):
        return None
    # The dot's radius in the image is its long semi-axis, twice the square root of the
    # largest second moment of the darkness (a uniform disc of radius r: r²/4); measured
    # 0.1–0.35 px short of the painted radius for 2.5–9 px dots, 0.05 px over at 2 px.
    offsets = np.stack([region_u - centre[0], region_v - centre[1]])
    spread = (offsets * weights) @ offsets.T / total
    small, large = (max(float(e), 1e-12) for e in np.linalg.eigvalsh(spread))
    radius = 2.0 * math.sqrt(large)
    if not radius_range[0] - _SIZE_SLACK_PX <= radius <= radius_range[1] + _SIZE_SLACK_PX:
        return None
    if math.sqrt(large / small) > max_elongation:
        return None
    return centre


def detect_fiducials(image: npt.ArrayLike, period_px: float, *, min_radius_px: float = 2.0,
                     max_radius_px: float = 8.0, max_elongation: float = 3.0) -> F64:
    """Sub-pixel centres of the dark round fiducial dots in a fringe image.

    A candidate is a compact region darker than half the brightness the unmarked surface would
    show there (line closings, module docstring), shaped like a filled ellipse. Its centre is
    the centroid of its darkness against the fringe inpainted across it along the fringe's own
    path; it is reported when that darkness has a long semi-axis between ``min_radius_px`` and
    ``max_radius_px`` (within half a pixel) and an elongation up to ``max_elongation``, and
    the fringe path describes its surroundings (module docstring). Shadows, edges, the dark
    room and large painted areas (an iris) are not dots; dots cut by the border or nearer to it
    along the fringes than about two dot diameters, beside a silhouette, or seen too obliquely
    are dropped, not mislocated.

    The centroid of a dot's image is the image of its centre only to first order: a disc on a
    surface tilted by θ appears as an ellipse whose centroid lies off the projected centre by
    about ``(r/Z)²·tan θ`` of the focal length, ≈ 0.01 px for a 0.5 mm dot at 250 mm.

    Parameters
    ----------
    image : array_like, shape (H, W)
        Fringe image, any real dtype (uint8, uint16, float), finite, at least 16×16 px; a
        camera's raw image (not undistorted).
    period_px : float
        Fringe period across the fringes, pixels (e.g. ``Carrier.period_px``), > 2. It sets
        the width of the ring around a dot where the fringe's path is fitted (0.15 of a period,
        at least 4 px); a rough value does (the simulated rooms: 23–30 px).
    min_radius_px, max_radius_px : float, optional
        Smallest and largest dot radius in the image, pixels (defaults 2 and 8: the simulated
        0.5 mm dots at 250 mm through 25 mm lenses are ≈ 4.7 px). ``0 < min < max``. Dots
        below ≈ 2 px lose too much contrast to the blur to be found reliably.
    max_elongation : float, optional
        Largest ratio of a dot's long to short axis, ≥ 1 (default 3: a disc seen up to ≈ 70°
        from its normal).

    Returns
    -------
    ndarray of float64, shape (N, 2)
        Centres ``(u, v)`` (column, row) in pixels, integer values at pixel centres, sorted by
        row then column. ``N`` may be 0.

    Raises
    ------
    ValueError
        If ``image``, ``period_px``, ``min_radius_px``, ``max_radius_px`` or
        ``max_elongation`` is invalid (named in the message).

    Examples
    --------
    A dot of radius 4.5 px centred at (60.3, 41.7) on fringes of a 20 px period, each pixel
    integrating 8 × 8 samples:

    >>> import numpy as np
    >>> v, u = (np.mgrid[0:96 * 8, 0:128 * 8] + 0.5) / 8 - 0.5
    >>> fringes = 40 + 30 * np.cos(2 * np.pi * u / 20)
    >>> paint = np.where(np.hypot(u - 60.3, v - 41.7) <= 4.5, 0.08, 1.0)
    >>> image = (paint * fringes).reshape(96, 8, 128, 8).mean(axis=(1, 3))
    >>> np.round(detect_fiducials(image, 20.0), 2)
    array([[60.29, 41.71]])
    """
    values = np.asarray(checked_image(image, min_size=16), dtype=np.float32)
    period = _positive(period_px, "period_px", 2.0)
    r_min = _positive(min_radius_px, "min_radius_px")
    r_max = _positive(max_radius_px, "max_radius_px")
    if r_max <= r_min:
        raise ValueError(f"max_radius_px ({r_max:g}) must exceed min_radius_px ({r_min:g})")
    elongation_max = _positive(max_elongation, "max_elongation")
    if elongation_max < 1.0:
        raise ValueError(f"max_elongation must be at least 1, not {max_elongation!r}")

    smooth = np.asarray(cv2.GaussianBlur(values, (0, 0), _DETECTION_SMOOTHING_PX),
                        dtype=np.float32)
    # Longer than the largest dot with its blurred rim, so that every closing fills a dot.
    length = 2 * math.ceil(r_max) + 5
    unmarked = _unmarked_brightness(smooth, length)
    bright = float(np.percentile(unmarked[::4, ::4], _BRIGHT_PERCENTILE))
    lit = unmarked > _BRIGHTNESS_FLOOR * bright
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(lit, smooth / np.where(lit, unmarked, 1.0), 1.0)
    dark = (ratio < _DARK_RATIO).astype(np.uint8)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(dark, connectivity=8)

    smoother = np.asarray(cv2.GaussianBlur(values, (0, 0), _PATH_SMOOTHING_PX),
                          dtype=np.float32)
    gradients = (np.asarray(cv2.Sobel(smoother, cv2.CV_32F, 1, 0, ksize=3), dtype=np.float32),
                 np.asarray(cv2.Sobel(smoother, cv2.CV_32F, 0, 1, ksize=3), dtype=np.float32))
    # The dark core is about the disc (smaller for a small, blurred dot); the dot's size is
    # checked on its darkness against the inpainted fringe, once it is refined.
    area_min = _MIN_CORE_PX
    area_max = math.pi * (r_max + 1.0) ** 2
    height, width = values.shape
    centres: list[F64] = []
    for label in range(1, count):
        left, top, box_w, box_h, area = (int(s) for s in stats[label])
        if not area_min <= area <= area_max:
            continue
        if left == 0 or top == 0 or left + box_w == width or top + box_h == height:
            continue  # cut by the border: its centroid would not be its centre
        window = labels[top:top + box_h, left:left + box_w] == label
        rows, cols = np.nonzero(window)
        dot = _Dot(rows + top, cols + left)
        if dot.elongation > elongation_max or not _FILL_RANGE[0] <= dot.fill <= _FILL_RANGE[1]:
            continue
        if dot.semi_major_px > r_max + 1.0:
            continue
        if float(ratio[dot.rows, dot.cols].min()) > _CORE_RATIO:
            continue  # shallow: noise on a dim fringe trough, not paint
        centre = _refined_centre(values, smoother, gradients, dot, period, (r_min, r_max),
                                 elongation_max)
        if centre is not None:
            centres.append(centre)
    if not centres:
        return np.zeros((0, 2), dtype=np.float64)
    found = np.array(centres, dtype=np.float64)
    return np.asarray(found[np.lexsort((found[:, 0], found[:, 1]))], dtype=np.float64)


# --- two views ----------------------------------------------------------------------------------


def _normalised(uv: F64, K: F64, dist: F64) -> F64:
    """Undistorted normalised coordinates ``(x, y)`` of raw pixel positions, ``(N, 2)``."""
    x, y = undistorted_normalised(uv[:, 0], uv[:, 1], K, dist)
    return np.stack([x, y], axis=1)


def _ideal_pixels(normalised: F64, K: F64) -> F64:
    """Where an ideal pinhole camera with the same ``K`` sees normalised points, ``(N, 2)``."""
    x, y = normalised[:, 0], normalised[:, 1]
    return np.stack([K[0, 0] * x + K[0, 1] * y + K[0, 2], K[1, 1] * y + K[1, 2]], axis=1)


def _skew(t: F64) -> F64:
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


def _fundamental_matrix(K_a: F64, R_a: F64, T_a: F64, K_b: F64, R_b: F64, T_b: F64) -> F64:
    """Fundamental matrix ``F`` with ``x_bᵀ·F·x_a = 0`` for undistorted homogeneous pixels.

    From the poses: camera B sees camera A's coordinates through ``R = R_b·R_aᵀ``,
    ``t = T_b − R·T_a``; the essential matrix is ``[t]ₓ·R`` and ``F = K_b⁻ᵀ·[t]ₓ·R·K_a⁻¹``
    (Hartley & Zisserman §9.2, ref. 2).
    """
    R = R_b @ R_a.T
    t = T_b - R @ T_a
    essential = _skew(t) @ R
    return np.asarray(np.linalg.inv(K_b).T @ essential @ np.linalg.inv(K_a), dtype=np.float64)


def _epipolar_distances(F: F64, pix_a: F64, pix_b: F64) -> F64:
    """``(Na, Nb)``: the larger of the two point-to-epipolar-line distances, pixels."""
    hom_a = np.column_stack([pix_a, np.ones(len(pix_a))])
    hom_b = np.column_stack([pix_b, np.ones(len(pix_b))])
    lines_b = hom_a @ F.T  # line in B of each point of A
    lines_a = hom_b @ F  # line in A of each point of B
    algebraic = hom_b @ F @ hom_a.T  # (Nb, Na): x_bᵀ F x_a
    to_b = np.abs(algebraic.T) / np.hypot(lines_b[:, 0], lines_b[:, 1])[:, None]
    to_a = np.abs(algebraic.T) / np.hypot(lines_a[:, 0], lines_a[:, 1])[None, :]
    return np.asarray(np.maximum(to_a, to_b), dtype=np.float64)


def _triangulated(norm_a: F64, norm_b: F64, R_a: F64, T_a: F64, R_b: F64, T_b: F64) -> F64:
    P_a = np.hstack([R_a, T_a[:, None]])
    P_b = np.hstack([R_b, T_b[:, None]])
    homogeneous = cv2.triangulatePoints(P_a, P_b, np.ascontiguousarray(norm_a.T),
                                        np.ascontiguousarray(norm_b.T))
    homogeneous = np.asarray(homogeneous, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        points = homogeneous[:3] / homogeneous[3]
    return np.asarray(points.T, dtype=np.float64)


def match_stereo(uv_a: npt.ArrayLike, uv_b: npt.ArrayLike, K_a: npt.ArrayLike,
                 dist_a: npt.ArrayLike, R_a: npt.ArrayLike, T_a: npt.ArrayLike,
                 K_b: npt.ArrayLike, dist_b: npt.ArrayLike, R_b: npt.ArrayLike,
                 T_b: npt.ArrayLike, *, max_epipolar_px: float = 1.5) -> npt.NDArray[np.intp]:
    """Pair the dots of two calibrated cameras by the epipolar constraint, one to one.

    Both point sets are undistorted (``cv2.undistortPoints``) to the pixels of ideal pinhole
    cameras with the same ``K``; the fundamental matrix of the two poses gives each dot its
    epipolar line in the other image. A pair is a candidate when both dots lie within
    ``max_epipolar_px`` of each other's line and the point they triangulate to stands in front
    of both cameras. A pair is kept only when it is the only candidate of both its dots: dots
    that could be either of two (several dots on one epipolar line) are dropped, not guessed.
    Two views cannot tell a dot whose partner is hidden in the other camera from a true pair
    when another dot happens to lie on its line; keep ``max_epipolar_px`` near the detection
    error.

    Parameters
    ----------
    uv_a, uv_b : array_like, shape (Na, 2) and (Nb, 2)
        Dot centres ``(u, v)`` in the raw (distorted) images of cameras A and B, pixels.
    K_a, K_b : array_like, shape (3, 3)
        Camera matrices.
    dist_a, dist_b : array_like
        OpenCV distortion coefficients ``(k1, k2, p1, p2[, k3, …])``.
    R_a, R_b : array_like, shape (3, 3)
        Rotations from the WCS to each camera: ``x_cam = R·X + T``.
    T_a, T_b : array_like, shape (3,)
        Translations, millimetres.
    max_epipolar_px : float, optional
        Largest distance of a dot from its partner's epipolar line, pixels of the undistorted
        images (default 1.5).

    Returns
    -------
    ndarray of intp, shape (M, 2)
        Index pairs ``(index in uv_a, index in uv_b)``, sorted by the first.

    Raises
    ------
    ValueError
        If any argument is invalid (named in the message), for example two cameras with the
        same centre (no baseline).
    """
    points_a = _checked_points(uv_a, "uv_a")
    points_b = _checked_points(uv_b, "uv_b")
    cam_a = _checked_camera(K_a, dist_a, R_a, T_a, "_a")
    cam_b = _checked_camera(K_b, dist_b, R_b, T_b, "_b")
    limit = _positive(max_epipolar_px, "max_epipolar_px")
    centre_a = -cam_a[2].T @ cam_a[3]
    centre_b = -cam_b[2].T @ cam_b[3]
    if np.linalg.norm(centre_a - centre_b) < 1e-9:
        raise ValueError("T_b must place camera B away from camera A (no stereo baseline)")
    if len(points_a) == 0 or len(points_b) == 0:
        return np.zeros((0, 2), dtype=np.intp)

    norm_a = _normalised(points_a, cam_a[0], cam_a[1])
    norm_b = _normalised(points_b, cam_b[0], cam_b[1])
    F = _fundamental_matrix(cam_a[0], cam_a[2], cam_a[3], cam_b[0], cam_b[2], cam_b[3])
    distances = _epipolar_distances(F, _ideal_pixels(norm_a, cam_a[0]),
                                    _ideal_pixels(norm_b, cam_b[0]))
    candidate = distances <= limit

    ia, ib = np.nonzero(candidate)
    if ia.size:
        # Cheirality: a true pair triangulates in front of both cameras.
        points = _triangulated(norm_a[ia], norm_b[ib], cam_a[2], cam_a[3], cam_b[2], cam_b[3])
        depth_a = points @ cam_a[2][2] + cam_a[3][2]
        depth_b = points @ cam_b[2][2] + cam_b[3][2]
        in_front = np.isfinite(points).all(axis=1) & (depth_a > 0) & (depth_b > 0)
        candidate[ia[~in_front], ib[~in_front]] = False

    unique = (candidate.sum(axis=1)[:, None] == 1) & (candidate.sum(axis=0)[None, :] == 1)
    pairs = np.argwhere(candidate & unique)
    return np.asarray(pairs, dtype=np.intp).reshape(-1, 2)


def triangulate(uv_a: npt.ArrayLike, uv_b: npt.ArrayLike, K_a: npt.ArrayLike,
                dist_a: npt.ArrayLike, R_a: npt.ArrayLike, T_a: npt.ArrayLike,
                K_b: npt.ArrayLike, dist_b: npt.ArrayLike, R_b: npt.ArrayLike,
                T_b: npt.ArrayLike) -> F64:
    """WCS positions of corresponding image points of two calibrated cameras.

    The points are undistorted to normalised coordinates (``cv2.undistortPoints`` with a tight
    iteration criterion) and triangulated linearly (``cv2.triangulatePoints``, Hartley &
    Zisserman §12.2, ref. 2) with the normalised projection matrices ``[R|T]``, so the result
    is in the WCS. With exact points the result is exact; with noisy ones the linear method
    on normalised coordinates stays within a few per cent of the optimal (reprojection)
    triangulation at these baselines.

    Parameters
    ----------
    uv_a, uv_b : array_like, shape (M, 2)
        Corresponding pixel positions ``(u, v)`` in the raw images of cameras A and B (row k of
        one is the same point as row k of the other; see :func:`match_stereo`).
    K_a, dist_a, R_a, T_a, K_b, dist_b, R_b, T_b : array_like
        The two cameras as in :func:`match_stereo` (``x_cam = R·X + T``, millimetres).

    Returns
    -------
    ndarray of float64, shape (M, 3)
        Points in the WCS, millimetres.

    Raises
    ------
    ValueError
        If any argument is invalid (named in the message), or ``uv_a`` and ``uv_b`` differ in
        length.

    Examples
    --------
    >>> import numpy as np
    >>> K = np.array([[2000.0, 0, 320], [0, 2000.0, 256], [0, 0, 1]])
    >>> no_lens = np.zeros(5)
    >>> R = np.eye(3)
    >>> T_a, T_b = np.array([0.0, 0, 250]), np.array([-50.0, 0, 250])
    >>> point = np.array([[1.0, 2.0, 3.0]])
    >>> uv = [K @ (R @ p + T) for p in point for T in (T_a, T_b)]
    >>> uv_a, uv_b = (np.array([q[:2] / q[2]]) for q in uv)
    >>> np.round(triangulate(uv_a, uv_b, K, no_lens, R, T_a, K, no_lens, R, T_b), 6)
    array([[1., 2., 3.]])
    """
    points_a = _checked_points(uv_a, "uv_a")
    points_b = _checked_points(uv_b, "uv_b")
    if len(points_a) != len(points_b):
        raise ValueError(f"uv_a and uv_b must hold the same number of points, not "
                         f"{len(points_a)} and {len(points_b)}")
    cam_a = _checked_camera(K_a, dist_a, R_a, T_a, "_a")
    cam_b = _checked_camera(K_b, dist_b, R_b, T_b, "_b")
    if len(points_a) == 0:
        return np.zeros((0, 3), dtype=np.float64)
    return _triangulated(_normalised(points_a, cam_a[0], cam_a[1]),
                         _normalised(points_b, cam_b[0], cam_b[1]), cam_a[2], cam_a[3],
                         cam_b[2], cam_b[3])


# --- one view and its fringe reconstruction -----------------------------------------------------


def _checked_ring(ring_px: Any) -> tuple[float, float]:
    try:
        inner, outer = (float(r) for r in ring_px)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"ring_px must be a pair (inner, outer) of radii in pixels, "
                         f"not {ring_px!r}") from exc
    if not (math.isfinite(inner) and math.isfinite(outer) and 0.0 <= inner < outer):
        raise ValueError(f"ring_px must satisfy 0 ≤ inner < outer (finite), not {ring_px!r}")
    return inner, outer


class _LocalSurface:
    """A plane, or a quadratic height over it, fitted by least squares to ``points``."""

    def __init__(self, points: F64, degree: int) -> None:
        self.mean = points.mean(axis=0)
        _, self.singular, self.axes = np.linalg.svd(points - self.mean, full_matrices=False)
        self.coef = np.zeros(6)
        if degree == 2:
            s, t, h = self._local(points)
            coef, *_ = np.linalg.lstsq(self._design(s, t), h, rcond=None)
            self.coef = np.asarray(coef, dtype=np.float64)

    def _local(self, points: F64) -> tuple[F64, F64, F64]:
        local = (points - self.mean) @ self.axes.T
        return local[:, 0], local[:, 1], local[:, 2]

    @staticmethod
    def _design(s: F64, t: F64) -> F64:
        return np.column_stack([np.ones_like(s), s, t, s * s, s * t, t * t])

    @property
    def degenerate(self) -> bool:
        """The points are (nearly) collinear: no plane through them."""
        return bool(self.singular[1] <= 1e-9 * max(float(self.singular[0]), 1e-300))

    def residuals(self, points: F64) -> F64:
        """Signed distances of ``points`` from the surface along the plane's normal, mm."""
        s, t, h = self._local(points)
        return np.asarray(h - self._design(s, t) @ self.coef, dtype=np.float64)

    def hit(self, centre: F64, direction: F64) -> F64 | None:
        """Where the ray ``centre + τ·direction`` meets the surface near the points, or None."""
        # In the plane's frame the ray is (s, t, h) = p + τ·q; solve h = quadratic(s, t).
        p = self.axes @ (centre - self.mean)
        q = self.axes @ direction
        if abs(float(q[2])) < 1e-9 * float(np.linalg.norm(q)):
            return None  # the ray runs along the plane
        plane_tau = -float(p[2]) / float(q[2])
        a0, a1, a2, a3, a4, a5 = (float(c) for c in self.coef)
        quad = a3 * q[0] ** 2 + a4 * q[0] * q[1] + a5 * q[1] ** 2
        lin = (a1 * q[0] + a2 * q[1] + 2 * a3 * p[0] * q[0] + a4 * (p[0] * q[1] + p[1] * q[0])
               + 2 * a5 * p[1] * q[1] - q[2])
        const = (a0 + a1 * p[0] + a2 * p[1] + a3 * p[0] ** 2 + a4 * p[0] * p[1]
                 + a5 * p[1] ** 2 - p[2])
        if abs(quad) <= 1e-12 * abs(lin):
            roots = np.array([-const / lin])
        else:
            roots = np.roots([quad, lin, const])
            roots = roots[np.abs(roots.imag) <= 1e-9 * np.maximum(np.abs(roots.real), 1.0)].real
        if roots.size == 0:
            return None
        # The root nearest the plane's intersection is the local surface (the other is far).
        tau = float(roots[np.argmin(np.abs(roots - plane_tau))])
        return np.asarray(centre + tau * direction, dtype=np.float64)


def _consensus(points: F64, band_mm: float) -> Bool:
    """The points within ``band_mm`` of the plane through three of them that most points lie
    near (ties: the smaller sum of squared distances), over a fixed set of random triples."""
    rng = np.random.default_rng(_RANSAC_SEED)
    triples = rng.integers(0, len(points), size=(_RANSAC_TRIALS, 3))
    first, second, third = points[triples[:, 0]], points[triples[:, 1]], points[triples[:, 2]]
    normals = np.cross(second - first, third - first)
    length = np.linalg.norm(normals, axis=1)
    usable = length > 1e-12 * max(float(np.abs(points).max()), 1.0) ** 2
    if not usable.any():
        return np.ones(len(points), dtype=bool)
    normals = normals[usable] / length[usable, None]
    distances = np.abs((points[None, :, :] - first[usable, None, :]) @ normals[..., None])[..., 0]
    near = distances <= band_mm
    count = near.sum(axis=1)
    spread = np.where(near, distances**2, 0.0).sum(axis=1)
    best = int(np.lexsort((spread, -count))[0])
    return np.asarray(near[best], dtype=bool)


def _surface_hit(points: F64, offsets: F64, centre: F64, direction: F64, degree: int,
                 min_points: int, max_rms_mm: float) -> F64:
    """Where the ray ``centre + τ·direction`` meets the surface fitted to ``points``, or NaN."""
    nan = np.full(3, np.nan)
    finite = np.isfinite(points).all(axis=1)
    points, offsets = points[finite], offsets[finite]
    if len(points) < min_points:
        return nan
    # Points of another surface in the ring (the plate seen past a phantom's silhouette, the
    # far side of a step) must not bend the fit. The plane through three of the points that
    # most points lie near (RANSAC, ref. 4, with a fixed seed: the result is reproducible)
    # picks the surface the ring mostly shows; then the fit of the wanted degree, trimmed of
    # points beyond three robust standard deviations (1.4826 × the median absolute residual),
    # is repeated a few times from there.
    inliers = _consensus(points, 3.0 * max_rms_mm)
    for _ in range(_TRIM_ROUNDS):
        if inliers.sum() < max(min_points, _MIN_INLIER_SHARE * len(points)):
            return nan  # no one surface holds most of the ring
        surface = _LocalSurface(points[inliers], degree)
        if surface.degenerate:
            return nan
        residuals = np.abs(surface.residuals(points))
        scale = 1.4826 * float(np.median(residuals[inliers]))
        kept = residuals <= max(3.0 * scale, _TRIM_FLOOR_MM)
        if (kept == inliers).all():
            break
        inliers = kept
    if inliers.sum() < max(min_points, _MIN_INLIER_SHARE * len(points)):
        return nan
    surface = _LocalSurface(points[inliers], degree)
    if surface.degenerate:
        return nan
    if math.sqrt(float(np.mean(surface.residuals(points[inliers]) ** 2))) > max_rms_mm:
        return nan  # not one smooth surface of this degree
    # The points must surround the dot (three quadrants at least) so that the surface is
    # interpolated under it, not extrapolated from one side.
    kept_offsets = offsets[inliers]
    quadrants = np.unique((kept_offsets[:, 0] >= 0).astype(int) * 2 + (kept_offsets[:, 1] >= 0))
    if quadrants.size < 3:
        return nan
    hit = surface.hit(centre, direction)
    return nan if hit is None else hit


def surface_position(uv: npt.ArrayLike, depth_points: npt.ArrayLike, K: npt.ArrayLike,
                     dist: npt.ArrayLike, R: npt.ArrayLike, T: npt.ArrayLike, *,
                     ring_px: tuple[float, float] = (8.0, 16.0), degree: int = 1,
                     min_points: int = 12, max_rms_mm: float = 0.1) -> F64:
    """The fringe reconstruction's 3-D position at each dot, from the surface around it.

    On the dark dot itself the fringe has too little light to be measured, so the surface is
    fitted to the camera's reconstructed points in a ring of pixels around the dot (least
    squares: the plane through their centroid along their smallest principal axis, with
    ``degree=2`` a quadratic height over that plane) and intersected with the camera's ray
    through the dot's centre (undistorted with ``cv2.undistortPoints``). A plane on a curved
    surface cuts under it: on a sphere of radius ρ a ring of radius r lies ≈ r²/(2ρ) below its
    middle (0.04 mm for r = 1 mm on a 12 mm eye); ``degree=2`` removes that.

    Parameters
    ----------
    uv : array_like, shape (N, 2)
        Dot centres ``(u, v)`` in the camera's raw image, pixels.
    depth_points : array_like, shape (H, W, 3)
        The camera's reconstructed WCS point (millimetres) at each pixel ``[row, column]``,
        NaN where it has none (build it from a camera cloud's points and pixel indices).
    K, dist, R, T : array_like
        The camera: matrix (3×3), OpenCV distortion coefficients, rotation (3×3) and
        translation (3, millimetres) with ``x_cam = R·X + T``.
    ring_px : (float, float), optional
        Inner and outer radius of the ring of pixels used, pixels from the dot's centre
        (``0 ≤ inner < outer``). The inner radius must clear the dot and the reconstruction's
        disturbed margin around it; default (8, 16).
    degree : {1, 2}, optional
        1 for a plane (default), 2 for a quadratic surface.
    min_points : int, optional
        Fewest reconstructed points in the ring, spread over at least three of its quadrants,
        for a position (default 12; at least 3 for a plane and 6 for a quadratic).
    max_rms_mm : float, optional
        Largest RMS distance of the ring's points from the fitted surface, millimetres
        (default 0.1): beyond it the ring does not lie on one smooth surface (it crosses an
        edge, a step or a silhouette) and the position is NaN. A plane on the simulated 12 mm
        eye phantom leaves ≈ 0.03 mm, the reconstruction's noise adds its own.

    Returns
    -------
    ndarray of float64, shape (N, 3)
        WCS points in millimetres; rows of NaN where the ring holds too few points, they do not
        surround the dot, they stray from the fitted surface by more than ``max_rms_mm``, or
        the ray runs along the fitted surface.

    Raises
    ------
    ValueError
        If any argument is invalid (named in the message).
    """
    points_uv = _checked_points(uv, "uv")
    cloud = np.asarray(depth_points, dtype=np.float64)
    if cloud.ndim != 3 or cloud.shape[2] != 3 or min(cloud.shape[:2]) < 1:
        raise ValueError(f"depth_points must be an (H, W, 3) array of WCS points, not of shape "
                         f"{cloud.shape}")
    K_, dist_, R_, T_ = _checked_camera(K, dist, R, T)
    inner, outer = _checked_ring(ring_px)
    rms_limit = _positive(max_rms_mm, "max_rms_mm")
    if isinstance(degree, bool) or degree not in (1, 2):
        raise ValueError(f"degree must be 1 (plane) or 2 (quadratic), not {degree!r}")
    fewest = 3 if degree == 1 else 6
    if isinstance(min_points, bool) or not isinstance(min_points, numbers.Integral) \
            or min_points < fewest:
        raise ValueError(f"min_points must be an integer of at least {fewest}, "
                         f"not {min_points!r}")
    result = np.full((len(points_uv), 3), np.nan)
    if len(points_uv) == 0:
        return result

    height, width = cloud.shape[:2]
    centre = -R_.T @ T_
    x, y = undistorted_normalised(points_uv[:, 0], points_uv[:, 1], K_, dist_)
    directions = np.stack([x, y, np.ones_like(x)], axis=1) @ R_
    reach = math.ceil(outer)
    dv, du = np.mgrid[-reach:reach + 1, -reach:reach + 1]
    for k, (u, v) in enumerate(points_uv):
        cols = np.rint(u).astype(np.intp) + du.ravel()
        rows = np.rint(v).astype(np.intp) + dv.ravel()
        offsets = np.stack([cols - u, rows - v], axis=1)
        radius = np.hypot(offsets[:, 0], offsets[:, 1])
        keep = ((radius >= inner) & (radius <= outer) & (cols >= 0) & (cols < width)
                & (rows >= 0) & (rows < height))
        result[k] = _surface_hit(cloud[rows[keep], cols[keep]], offsets[keep], centre,
                                 directions[k], degree, int(min_points), rms_limit)
    return result
