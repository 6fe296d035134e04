"""The eye's pose from a reconstructed surface: globe centre, limbus centre and gaze (WCS, mm).

The fused cloud holds the skin around the orbit, the lids (or retractors), the sclera seen
through the palpebral opening and, where it carries fringe signal, the cornea. The globe is the
one convex sphere of radius ≈ 12 mm bulging towards the cameras (+Z) *behind* everything else
that is spherical: the lids are shells in front of it. So:

1. **Segmentation by shells about a common centre.** Voxel means (0.5 mm); the face's plane
   removed by MSAC; each voxel's normal votes for centres at globe-sized distances behind it
   (sclera, lids and retractors are near-concentric, so the votes agree), then mean shift.
   Around that centre the radial histogram shows the sclera (the innermost shell of a globe's
   size) and, 0.6–3 mm outside, the lids. Sequential LO-MSAC sphere search is the fallback.
2. **Globe.** Robust least squares of the sclera's geometric residual ``|p − c| − R`` jointly
   with a concentric lid shell (``R_lid`` free): the sclera alone (two small caps beside the
   cornea) trades depth for radius, the lids pin the depth (exact in the simulated room; a
   known limit). Radius free unless the model fixes it; covariance from the Jacobian.
3. **Rough gaze.** The sclera ends at the limbus, but the hole it leaves is lopsided and reaches
   well beyond it (the cornea's shadow, fringe erosion, the lids), so the circle fitted to the
   hole's edge gives the gaze only where it has the limbus's size, else the axis of the widest
   cone the sclera and lid shell leave empty does; a reconstructed corneal cap's axis is
   combined with it by inverse variance. The limbus centre lies on that axis at the model's
   limbus depth √(R² − (D/2)²). Gaze is +Z when the eye looks at the beam source
   (docs/design.md §2).
4. **The limbus in the images** (``views``): found by :mod:`eyeserver.eye.limbus` from the
   rough pose, it sets the gaze and the limbus centre; the globe is the sphere through it that
   the sclera lies on (:func:`pose_on_limbus`), the sclera measured again from its own fringes
   and the globe fitted with the limbus (:mod:`eyeserver.eye.sclera`). Its accuracy:
   docs/benchmarks.md ("Eye pose"). Without images, or where no limbus is found, the pose of
   steps 2–3 stands (``gaze_source`` says which; with images that showed no limbus, at a
   confidence scaled by :data:`UNSEEN_LIMBUS`).

Torsion is invisible to the surface of a sphere with a round limbus (docs/design.md §4 step 8):
reported as None. The cloud-only gaze's measured error: docs/notes/limbus.md. The constants:
:mod:`eyeserver.eye.tunables`.

References
----------
Via R. et al., "Feasibility of a light-based eye position verification for ocular proton
therapy", Physics and Imaging in Radiation Oncology (2023), doi:10.1016/j.phro.2023.100517.
Chum O., Matas J., Kittler J., "Locally optimized RANSAC", DAGM 2003.
Torr P., Zisserman A., "MLESAC", CVIU 78 (2000) (the truncated-quadratic MSAC score).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt
from scipy.optimize import least_squares
from scipy.spatial import cKDTree

from eyeserver.core.arrays import column_range, distances
from eyeserver.core.types import F64
from eyeserver.errors import EyeserverError
from eyeserver.eye.limbus import LimbusNotFoundError, LimbusView, find_limbus, globe_on_limbus
from eyeserver.eye.sclera import refit
from eyeserver.eye.tunables import (
    BOUNDARY_SECTORS,
    CONE_POINTS,
    EDGE_IS_LIMBUS_MM,
    IMPLAUSIBLE_RADIUS,
    LID_REACH_MM,
    LIMBUS_AXIS_SD_MM,
    MEASURED_GLOBE_SD_MM,
    MIN_SCLERA_POINTS,
    MODEL_ERROR_BELOW_CONFIDENCE,
    MODEL_ERROR_CENTRE_MM,
    MODEL_ERROR_GAZE_DEG,
    MODEL_ERROR_MIN_CONFIDENCE,
    MODEL_ERROR_POWER,
    MSAC_HYPOTHESES,
    MSAC_LOCAL_MM,
    NO_GLOBE_FACTOR,
    NORMAL_REACH_MM,
    OVAL_LIMBUS,
    SHAPE_SD_MM,
    SHELL_BAND_MM,
    UNSEEN_LIMBUS,
    VOTED_CENTRE_MM,
    VOXEL_MM,
    WELL_SEEN_LIMBUS_POINTS,
    WELL_SEEN_POINTS,
)

__all__ = ["CloudLike", "EyeModel", "EyePose", "Gaze", "PoseError", "checked_cloud", "cloud_gaze",
           "fit_eye", "fit_sphere", "model_error_sds", "pose_from_cloud", "pose_on_limbus",
           "radius_bounds", "with_model_error"]


class CloudLike(Protocol):
    """What :func:`fit_eye` reads of a cloud (:class:`eyeserver.io.PointCloud` qualifies)."""

    @property
    def points(self) -> npt.NDArray[Any]: ...

    @property
    def quality(self) -> npt.NDArray[Any] | None: ...


class PoseError(EyeserverError):
    """No eye could be fitted to the cloud; ``reason`` says why in words a user can act on."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


@dataclass(frozen=True)
class EyeModel:
    """A patient's eye model (MRI-derived or population defaults), mm.

    Attributes
    ----------
    globe_semi_axes_mm : (a, b, c) or None
        Semi-axes of the anterior-segment ellipsoid along ``orientation``'s columns; None with
        ``globe_radius_mm`` None fits a sphere whose radius is free.
    globe_radius_mm : float or None
        A spherical globe's radius; None fits it.
    orientation : 3×3 tuple or None
        Rotation from the model's axes to the WCS (columns: the semi-axes' directions).
    cornea_radius_mm, limbus_diameter_mm : float
        Anterior corneal radius and limbus diameter.
    globe_sd_mm : float
        The sd of the given radius or of each given semi-axis (their measurement's, an MRI's;
        default :data:`~eyeserver.eye.tunables.MEASURED_GLOBE_SD_MM`): it moves the centre
        along the gaze (:attr:`shape_sd_mm`).
    """

    globe_radius_mm: float | None = None
    globe_semi_axes_mm: tuple[float, float, float] | None = None
    orientation: tuple[tuple[float, float, float], ...] | None = None
    cornea_radius_mm: float = 7.8
    limbus_diameter_mm: float = 11.7
    globe_sd_mm: float = MEASURED_GLOBE_SD_MM

    @classmethod
    def population(cls) -> EyeModel:
        """Textbook defaults: globe ≈ 12 mm (fitted, not imposed), cornea 7.8 mm, limbus 11.7 mm."""
        return cls(globe_radius_mm=None, cornea_radius_mm=7.8, limbus_diameter_mm=11.7)

    def radius_through_limbus(self, limbus_radius_mm: float) -> float | None:
        """The radius (mm) of the sphere through a limbus circle of ``limbus_radius_mm`` whose
        centre is the globe's: the held radius of a spherical globe; for an ellipsoid, the
        sphere through the circle where the ellipsoid's cross-section has that mean radius;
        None where the radius is fitted.

        The ellipsoid's axial semi-axis ``c`` (:meth:`ellipsoid_frame`); its cross-section
        at ``z`` in front of the centre is an ellipse of semi-axes ``(a, b)·s``,
        ``s = √(1 − z²/c²)``, and the circle that best follows it has the radius
        ``s·(a + b)/2``. So the limbus lies ``z = c·√(1 − s²)`` in front of the centre with
        ``s = 2r/(a + b)``: the ellipsoid's own depth, not the mean radius's (a sphere of the
        mean radius puts the centre off by about 1.5 times the axial semi-axis's difference
        from the others, docs/notes/patient-eye.md).
        """
        if self.globe_radius_mm is not None:
            return self.globe_radius_mm
        if self.globe_semi_axes_mm is None:
            return None
        axes = np.asarray(self.globe_semi_axes_mm, dtype=np.float64)
        _, axial = self.ellipsoid_frame()
        across = np.delete(axes, axial)
        scale = 2.0 * limbus_radius_mm / float(across.sum())
        depth = float(axes[axial]) * math.sqrt(max(1.0 - scale * scale, 0.0))
        return math.hypot(depth, limbus_radius_mm)

    def ellipsoid_frame(self) -> tuple[F64, int]:
        """The ellipsoid's semi-axes' directions in the WCS (the columns of ``orientation``;
        the identity without one) and which of them is axial: the one nearest +Z (the eye
        looks towards the beam source at the planned pose, docs/design.md §2)."""
        frame = (np.eye(3) if self.orientation is None
                 else np.asarray(self.orientation, dtype=np.float64))
        return frame, int(np.argmax(np.abs(frame[2])))

    @property
    def shape_sd_mm(self) -> float:
        """The globe centre's sd along the gaze (mm) from what the model leaves uncertain of
        the globe's shape: its shape where the model does not give it (:data:`SHAPE_SD_MM`,
        none with the MRI's ellipsoid) and the error of the radius or semi-axes it gives
        (:attr:`globe_sd_mm`), which the fit turns into the centre's depth behind the limbus
        (:meth:`measured_depth_sd_mm`)."""
        unknown = 0.0 if self.globe_semi_axes_mm is not None else SHAPE_SD_MM
        return math.hypot(unknown, self.measured_depth_sd_mm())

    def measured_depth_sd_mm(self) -> float:
        """The sd (mm) of the centre's depth behind the limbus (of the model's diameter) that
        the given radius's or semi-axes' error (:attr:`globe_sd_mm`, each independent) makes;
        0 where the radius is fitted. A sphere's centre lies ``z = √(R² − r²)`` behind a limbus
        of radius ``r``, so ``∂z/∂R = R/z`` (1.15 for 12 mm); an ellipsoid's ``z = c·√(1 − s²)``
        with ``s = 2r/(a + b)`` (:meth:`radius_through_limbus`): ``∂z/∂c = √(1 − s²)``,
        ``∂z/∂a = ∂z/∂b = c·s²/((a + b)·√(1 − s²))`` (0.87 and 0.14 for 12 mm)."""
        r = self.limbus_diameter_mm / 2
        if self.globe_semi_axes_mm is not None:
            axes = np.asarray(self.globe_semi_axes_mm, dtype=np.float64)
            _, axial = self.ellipsoid_frame()
            c = float(axes[axial])
            across = float(np.delete(axes, axial).sum())
            s = min(2.0 * r / across, 0.999)
            root = math.sqrt(1.0 - s * s)
            gain = math.sqrt(root**2 + 2.0 * (c * s * s / (across * root)) ** 2)
        elif self.globe_radius_mm is not None:
            radius = self.globe_radius_mm
            gain = radius / math.sqrt(max(radius**2 - r**2, 1e-6))
        else:
            return 0.0
        return self.globe_sd_mm * gain

    @property
    def prior_radius_mm(self) -> float:
        """The radius used to seed the search: the given one, the semi-axes' mean, or 12 mm."""
        if self.globe_radius_mm is not None:
            return self.globe_radius_mm
        if self.globe_semi_axes_mm is not None:
            return float(np.mean(self.globe_semi_axes_mm))
        return 12.0


@dataclass(frozen=True)
class EyePose:
    """A fitted eye pose in the WCS (mm; gaze a unit vector, angles in degrees for humans)."""

    centre_mm: tuple[float, float, float]
    centre_sd_mm: tuple[float, float, float]
    """One standard deviation per WCS axis. Like ``limbus_sd_mm`` and ``gaze_sd_deg`` (a tilt's
    in two axes at once) it counts what no number of points averages away: edges and points
    within a fringe period share their error, and the sclera as a whole is trusted only to its
    systematic error from capture to capture (:data:`~eyeserver.eye.tunables.
    REMEASURED_SCLERA_BIAS_MM` for the sclera remeasured in the images,
    :data:`~eyeserver.eye.tunables.CLOUD_SCLERA_BIAS_MM` for the cloud's while tracking), which
    moves a fitted globe's depth (``eyeserver bench pose`` reports how often the errors lie
    within one and two). :func:`fit_eye` adds what the covariances cannot count, growing as the
    confidence falls (:func:`with_model_error`); live tracking's frame-to-frame poses do not."""
    globe_radius_mm: float
    limbus_centre_mm: tuple[float, float, float] | None
    limbus_sd_mm: float | None
    gaze: tuple[float, float, float]
    gaze_sd_deg: float
    torsion_deg: float | None
    surface_mad_mm: float
    sclera_points: int
    confidence: float
    gaze_source: str = "limbus"
    """Where the gaze came from: "limbus (images)" (the limbus found in the fringe images),
    or from the cloud alone: "limbus" (the hole the sclera leaves), "limbus+cornea", or "none"
    (not found)."""
    boundary_radius_mm: float | None = None
    """Radius of the limbus circle found in the images, or else of the sclera's inner boundary
    in the cloud (the valid region's edge, ≥ the true limbus)."""
    cornea_points: int = 0
    fit_ms: float = 0.0
    shape_sd_mm: float = 0.0
    """The centre's sd along the gaze (mm) from what the eye model leaves uncertain of the
    globe's shape (:attr:`EyeModel.shape_sd_mm`: no shape given, or the error of the one
    given), beside ``centre_sd_mm``'s measurement error: common to every fit of one eye with
    one model, so it cancels from a displacement from a reference captured with the same model
    (but for the gaze's turn between them), and counts in full against a planned pose."""

    def to_dict(self) -> dict[str, Any]:
        """JSON-able dictionary (lists for vectors)."""
        def vec(v: tuple[float, ...] | None) -> list[float] | None:
            return None if v is None else [float(x) for x in v]

        return {
            "centre_mm": vec(self.centre_mm),
            "centre_sd_mm": vec(self.centre_sd_mm),
            "globe_radius_mm": float(self.globe_radius_mm),
            "limbus_centre_mm": vec(self.limbus_centre_mm),
            "limbus_sd_mm": None if self.limbus_sd_mm is None else float(self.limbus_sd_mm),
            "gaze": vec(self.gaze),
            "gaze_sd_deg": float(self.gaze_sd_deg),
            "torsion_deg": None if self.torsion_deg is None else float(self.torsion_deg),
            "surface_mad_mm": float(self.surface_mad_mm),
            "sclera_points": int(self.sclera_points),
            "confidence": float(self.confidence),
            "gaze_source": self.gaze_source,
            "boundary_radius_mm": None if self.boundary_radius_mm is None
            else float(self.boundary_radius_mm),
            "cornea_points": int(self.cornea_points),
            "fit_ms": float(self.fit_ms),
            "shape_sd_mm": float(self.shape_sd_mm),
        }


LIMBUS_FROM_IMAGES = "limbus (images)"
"""The ``gaze_source`` of a pose whose limbus was found in the fringe images."""


def fit_sphere(points: npt.ArrayLike) -> tuple[F64, float]:
    """Algebraic (Kåsa) least-squares sphere through ``points`` (N ≥ 4, mm): ``(centre, radius)``.

    Linear in ``(c, R² − |c|²)``; about a millisecond for 50 k points. Biased towards small
    radii on a small noisy cap, so :func:`fit_eye` only seeds the geometric fit with it.

    >>> import numpy as np
    >>> u = np.random.default_rng(0).normal(size=(100, 3))
    >>> c, r = fit_sphere(5.0 * u / np.linalg.norm(u, axis=1, keepdims=True) + [1, 2, 3])
    >>> np.round(c, 6).tolist(), round(r, 6)
    ([1.0, 2.0, 3.0], 5.0)
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < 4:
        raise ValueError(f"points must have shape (N >= 4, 3), got {p.shape}")
    mean = p.mean(axis=0)
    q = p - mean  # centred: the normal equations stay well conditioned far from the origin
    a = np.column_stack([2.0 * q, np.ones(len(q))])
    b = np.einsum("ij,ij->i", q, q)
    sol, *_ = np.linalg.lstsq(a, b, rcond=None)
    centre = sol[:3]
    radius = math.sqrt(max(float(sol[3] + centre @ centre), 0.0))
    return centre + mean, radius


def _batch_spheres(groups: F64, valid: npt.NDArray[np.bool_]) -> tuple[F64, F64]:
    """Algebraic sphere fits of many small point groups at once: ``groups`` (H, K, 3) with
    ``valid`` (H, K) marking real members; centres (H, 3) and radii (H,) (NaN when degenerate)."""
    w = valid.astype(np.float64)
    count = np.maximum(w.sum(axis=1), 1.0)
    mean = (groups * w[..., None]).sum(axis=1) / count[:, None]
    q = (groups - mean[:, None, :]) * w[..., None]
    a = np.concatenate([2.0 * q, w[..., None]], axis=2)
    b = np.einsum("hkj,hkj->hk", q, q)
    ata = np.einsum("hki,hkj->hij", a, a)
    atb = np.einsum("hki,hk->hi", a, b)
    good = np.abs(np.linalg.det(ata)) > 1e-9
    ata[~good] = np.eye(4)
    sol = np.linalg.solve(ata, atb[..., None])[..., 0]
    centre = sol[:, :3] + mean
    r2 = sol[:, 3] + np.einsum("hi,hi->h", sol[:, :3], sol[:, :3])
    radius = np.sqrt(np.where(good & (r2 > 0), r2, np.nan))
    return centre, radius


def _voxel_means(points: F64, size: float) -> tuple[F64, F64, npt.NDArray[np.intp]]:
    """Mean point and count of every occupied ``size`` mm voxel: averaging ~50 points per voxel
    cuts the noise enough for curvature at a millimetre's scale."""
    key = np.floor(points / size).astype(np.int64)
    low, high = column_range(key)
    key -= low
    span = high - low + 1
    flat = (key[:, 0] * span[1] + key[:, 1]) * span[2] + key[:, 2]
    _, inverse, counts = np.unique(flat, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    means = np.stack([np.bincount(inverse, points[:, k]) for k in range(3)], axis=1)
    return means / counts[:, None], counts.astype(np.float64), inverse


def _shell_score(voxels: F64, counts: F64, centres: F64, radii: F64) -> F64:
    """Points (voxel counts) within the consensus band of each sphere hypothesis."""
    score = np.zeros(len(centres))
    for start in range(0, len(centres), 64):
        dist = np.abs(np.linalg.norm(voxels[None] - centres[start:start + 64, None], axis=2)
                      - radii[start:start + 64, None])
        score[start:start + 64] = (dist < SHELL_BAND_MM) @ counts
    return score


def _normals(voxels: F64) -> tuple[F64, npt.NDArray[np.bool_]]:
    """Unit normals facing +Z from a PCA of each voxel's 1.6 mm neighbourhood, and where valid.

    Batched: neighbour lists are padded to one length (the voxel itself repeated, weight 0),
    and all 3×3 scatter matrices go to one ``np.linalg.eigh`` call — a per-voxel loop took
    ≈ 1 s on a 20 k-voxel cloud.
    """
    tree = cKDTree(voxels)
    neighbours = tree.query_ball_point(voxels, NORMAL_REACH_MM, return_sorted=False)
    sizes = np.fromiter((len(m) for m in neighbours), dtype=np.intp, count=len(voxels))
    normals = np.zeros_like(voxels)
    valid = sizes >= 8
    if not valid.any():
        return normals, valid
    rows = np.flatnonzero(valid)
    width = int(sizes[rows].max())
    index = np.repeat(rows[:, None], width, axis=1)
    flat = np.concatenate([neighbours[k] for k in rows]).astype(np.intp)
    column = np.arange(len(flat)) - np.repeat(np.cumsum(sizes[rows]) - sizes[rows], sizes[rows])
    index[np.repeat(np.arange(len(rows)), sizes[rows]), column] = flat
    weight = (np.arange(width)[None, :] < sizes[rows, None]).astype(np.float64)
    members = voxels[index]
    mean = (members * weight[..., None]).sum(axis=1) / sizes[rows, None]
    q = (members - mean[:, None, :]) * weight[..., None]
    scatter = np.einsum("nki,nkj->nij", q, q)
    normal = np.linalg.eigh(scatter)[1][:, :, 0]
    normals[rows] = np.where(normal[:, 2:3] > 0, normal, -normal)
    return normals, valid


def _hough_centre(voxels: F64, counts: F64, normals: F64, r_lo: float, r_hi: float) -> F64 | None:
    """The point most normals pass through at a globe-sized distance behind the surface.

    Globe, lids and retractors resting on it are all near-concentric shells, so their normals
    agree on one centre even where their radii differ; a 1 mm accumulator over radius
    hypotheses finds it without knowing which points are sclera.
    """
    if len(voxels) < 8:
        return None
    radii = np.arange(r_lo, r_hi + 0.25, 0.25)
    votes = (voxels[:, None, :] - radii[None, :, None] * normals[:, None, :]).reshape(-1, 3)
    key = np.floor(votes).astype(np.int64)
    cells, inverse = np.unique(key, axis=0, return_inverse=True)
    weights = np.repeat(counts, len(radii))
    acc = np.bincount(inverse.ravel(), weights)
    centre = np.asarray(cells[int(np.argmax(acc))] + 0.5, dtype=np.float64)
    for reach in (1.5, 1.0, 0.75, 0.5):  # mean shift: the 1 mm cell alone leaves ±0.5 mm
        close = distances(votes, centre) < reach
        if not close.any():
            break
        centre = np.average(votes[close], axis=0, weights=weights[close])
    return centre


def _radial_shells(voxels: F64, counts: F64, centre: F64, r_bounds: tuple[float, float],
                   ) -> list[tuple[float, float]]:
    """``(radius, support)`` of the shells around ``centre``: peaks of the radial histogram."""
    dist = distances(voxels, centre)
    edges = np.arange(r_bounds[0] - 1.0, r_bounds[1] + 4.0, 0.1)
    hist, _ = np.histogram(dist, bins=edges, weights=counts)
    smooth = np.convolve(hist, np.ones(5), mode="same")  # 0.5 mm: a shell's noisy thickness
    peaks = [k for k in range(1, len(smooth) - 1)
             if smooth[k] >= smooth[k - 1] and smooth[k] > smooth[k + 1]]
    return [(float(edges[k] + 0.05), float(smooth[k])) for k in peaks]


def _globe_candidates(points: F64, r_bounds: tuple[float, float], fixed: float | None,
                      ) -> tuple[list[tuple[F64, float, float]], npt.NDArray[np.bool_]]:
    """``(centre, radius, support)`` of the globe: the innermost shell around the common centre.

    The plane of the face is removed first; normals of what is left vote for a centre
    (:func:`_hough_centre`); around it the radial histogram shows the sclera and, about a
    millimetre outside, the lids or retractors (both convex shells). The innermost shell of a
    globe's size with enough support is the sclera; "of a globe's size" allows for the voted
    centre's error (:data:`VOTED_CENTRE_MM`), which moves the sclera's peak by as much (a held
    radius of 12 mm ± 5 % missed the sclera's peak at 11.35 mm on 2 of 30 noise draws of an eye
    at rest, and on 4 of 60 draws of another noise generator; measured). Falls back to the
    LO-MSAC shell search.
    """
    voxels, counts, off_plane = _without_planes(points)
    if len(voxels) < 8:
        return [], off_plane
    normals, valid = _normals(voxels)
    centre = _hough_centre(voxels[valid], counts[valid], normals[valid], *r_bounds)
    if centre is not None:
        shells = _radial_shells(voxels, counts, centre, r_bounds)
        strongest = max((s for _, s in shells), default=0.0)
        for radius, support in shells:
            if (support >= max(MIN_SCLERA_POINTS, 0.1 * strongest)
                    and r_bounds[0] - VOTED_CENTRE_MM <= radius
                    <= r_bounds[1] + VOTED_CENTRE_MM):
                # The lids: the strongest shell 0.6–3 mm outside the sclera, if any.
                outer = [(s, r) for r, s in shells if radius + 0.6 <= r <= radius + LID_REACH_MM
                         and s >= MIN_SCLERA_POINTS]
                lid_radius = max(outer)[1] if outer else math.nan
                return [(centre, fixed if fixed is not None else radius, lid_radius)], off_plane
    return [(c, r, math.nan) for c, r, _ in _shell_search(voxels, counts, r_bounds, fixed)], \
        off_plane


def _without_planes(points: F64) -> tuple[F64, F64, npt.NDArray[np.bool_]]:
    """Voxel means and counts of ``points`` without the dominant plane(s) (MSAC), and which
    points are kept."""
    rng = np.random.default_rng(0)  # a fixed seed: the same cloud always gives the same pose
    voxels, counts, inverse = _voxel_means(points, VOXEL_MM)
    if len(voxels) < 4:
        return voxels, counts, np.ones(len(points), dtype=bool)
    keep = np.ones(len(voxels), dtype=bool)
    total = counts.sum()
    for _ in range(2):
        idx = np.flatnonzero(keep)
        if len(idx) < 3:
            break
        trip = voxels[idx[rng.integers(0, len(idx), size=(200, 3))]]
        normal = np.cross(trip[:, 1] - trip[:, 0], trip[:, 2] - trip[:, 0])
        norm = distances(normal)
        good = norm > 1e-6
        normal = normal[good] / norm[good, None]
        offset = np.einsum("ij,ij->i", normal, trip[good, 0])
        dist = np.abs(voxels[idx] @ normal.T - offset)
        support = (dist < 0.3).T @ counts[idx]
        best = int(np.argmax(support))
        if support[best] < 0.25 * total:
            break
        keep[idx[dist[:, best] < 0.6]] = False
    return voxels[keep], counts[keep], keep[inverse]


def _shell_search(voxels: F64, counts: F64, r_bounds: tuple[float, float], fixed: float | None,
                  ) -> list[tuple[F64, float, float]]:
    """Sequential LO-MSAC for up to three convex shells facing +Z, innermost first."""
    rng = np.random.default_rng(0)
    keep = np.ones(len(voxels), dtype=bool)
    shells: list[tuple[F64, float, float]] = []
    for _ in range(3):
        idx = np.flatnonzero(keep)
        if counts[idx].sum() < MIN_SCLERA_POINTS or len(idx) < 8:
            break
        sub = voxels[idx]
        tree = cKDTree(sub)
        seeds = rng.integers(0, len(sub), size=MSAC_HYPOTHESES)
        near = tree.query_ball_point(sub[seeds], MSAC_LOCAL_MM)
        groups = np.zeros((MSAC_HYPOTHESES, 4, 3))
        valid = np.zeros((MSAC_HYPOTHESES, 4), dtype=bool)
        for h, members in enumerate(near):
            if len(members) >= 4:
                groups[h] = sub[rng.choice(members, 4, replace=False)]
                valid[h] = True
        centres, radii = _batch_spheres(groups, valid)
        if fixed is not None:
            radii = np.where(np.isfinite(radii), fixed, np.nan)
        ok = (np.isfinite(radii) & (radii > r_bounds[0]) & (radii < r_bounds[1])
              & (sub[seeds, 2] - centres[:, 2] > 0.2 * np.nan_to_num(radii, nan=1.0)))
        if not ok.any():
            break
        centres, radii = centres[ok], radii[ok]
        score = _shell_score(sub, counts[idx], centres, radii)
        found = None
        for h in np.argsort(score)[::-1][:5]:
            centre, radius = centres[h], float(radii[h])
            for band in (0.6, 0.4, SHELL_BAND_MM):  # local optimisation on the hypothesis' inliers
                inl = np.abs(distances(sub, centre) - radius) < band
                if inl.sum() < 4:
                    break
                centre, radius = fit_sphere(sub[inl])
                if fixed is not None:
                    radius = fixed
            inl = np.abs(distances(sub, centre) - radius) < SHELL_BAND_MM
            support = float(counts[idx][inl].sum())
            if (r_bounds[0] <= radius <= r_bounds[1] and support >= MIN_SCLERA_POINTS
                    and np.median(sub[inl, 2]) > centre[2] + 0.2 * radius
                    and (found is None or support > found[2])):
                found = (centre, radius, support)
        if found is None:
            break
        shells.append(found)
        dist = distances(voxels, found[0])
        keep &= np.abs(dist - found[1]) > 2 * SHELL_BAND_MM
        keep &= dist < found[1] + 8.0
    if not shells:
        return []
    same = [s for s in shells if np.linalg.norm(s[0] - shells[0][0]) < 4.0]
    return sorted(same, key=lambda s: s[1])


def _refine_globe(points: F64, weights: F64, centre: F64, radius: float,
                  fixed_radius: float | None, lid_points: F64, lid_weights: F64,
                  lid_radius: float,
                  ) -> tuple[F64, float, float, F64, F64, npt.NDArray[np.bool_]]:
    """Geometric robust sphere fit of the sclera, jointly with a concentric lid shell when
    ``lid_points`` are given: centre, radius, lid radius, covariance (of centre and radius),
    the sclera's residuals and inliers.

    A few square millimetres of sclera on either side of the cornea are a small cap: alone
    they fix the centre across the line of sight but trade its depth against the radius
    (measured: 1.2 mm deeper and 1.2 mm larger on a clean 12 mm cap). The lids and retractors
    rest on the globe and cover a far wider angle, so a shell concentric with the sclera
    (its own radius free) pins the depth; the radius comes from the sclera alone.
    """
    sw = np.sqrt(weights)
    lw = np.sqrt(lid_weights)
    use_lids = len(lid_points) >= MIN_SCLERA_POINTS and math.isfinite(lid_radius)
    n_free = 3 if fixed_radius is not None else 4

    def residuals(x: F64) -> F64:
        r = fixed_radius if fixed_radius is not None else x[3]
        sclera = sw * (distances(points, x[:3]) - r)
        if not use_lids:
            return np.asarray(sclera, dtype=np.float64)
        lids = lw * (distances(lid_points, x[:3]) - x[n_free])
        return np.asarray(np.concatenate([sclera, lids]), dtype=np.float64)

    def jacobian(x: F64) -> F64:
        # Analytic: a finite-difference Jacobian cost 5 residual evaluations an iteration.
        blocks = [(points, sw, 0)] + ([(lid_points, lw, n_free)] if use_lids else [])
        rows = []
        for shell, root_w, column in blocks:
            rel = shell - x[:3]
            unit = rel / np.maximum(distances(rel), 1e-12)[:, None]
            block = np.zeros((len(shell), len(x)))
            block[:, :3] = -root_w[:, None] * unit
            if column:
                block[:, column] = -root_w
            elif fixed_radius is None:
                block[:, 3] = -root_w
            rows.append(block)
        return np.asarray(np.vstack(rows), dtype=np.float64)

    x0 = np.append(centre, radius) if fixed_radius is None else centre.copy()
    if use_lids:
        x0 = np.append(x0, lid_radius)
    fit = least_squares(residuals, x0, jac=jacobian, loss="soft_l1", f_scale=0.05, x_scale=1.0)
    x = fit.x
    r_fit = float(fixed_radius if fixed_radius is not None else x[3])
    lid_fit = float(x[n_free]) if use_lids else lid_radius
    resid = distances(points, x[:3]) - r_fit
    sigma = max(1.4826 * float(np.median(np.abs(resid))), 1e-4)
    inliers = np.abs(resid) < max(3.0 * sigma, 0.1)
    all_weights = np.concatenate([weights, lid_weights]) if use_lids else weights
    all_sw = np.sqrt(all_weights)
    keep = np.abs(fit.fun / np.maximum(all_sw, 1e-12)) < max(3.0 * sigma, 0.1)
    jac = fit.jac[keep] / np.maximum(all_sw[keep, None], 1e-12)
    jtj = jac.T @ (jac * all_weights[keep, None])
    try:
        cov = (np.linalg.inv(jtj) * sigma**2 * all_weights[keep].sum()
               / max(int(keep.sum()), 1))[:n_free, :n_free]
    except np.linalg.LinAlgError:
        cov = np.full((n_free, n_free), np.inf)
    return x[:3], r_fit, lid_fit, cov, resid, inliers


def _frame(axis: F64) -> tuple[F64, F64]:
    """Two unit vectors completing ``axis`` to an orthonormal frame."""
    helper = np.array([0.0, 1.0, 0.0]) if abs(axis[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(helper, axis)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(axis, e1)


def _limbus(directions: F64, start: F64 | None = None) -> tuple[F64, float, F64, int] | None:
    """Axis ``g`` and cos of the half-angle of the hole the sclera directions ring.

    Returns ``(g, cos_beta, covariance of the two tilt angles (rad²), boundary points)`` or
    None when the boundary is not seen on enough sides to fix a circle.
    """
    axis = directions.mean(axis=0) if start is None else start.copy()
    axis /= np.linalg.norm(axis)
    result = None
    for _ in range(5):
        e1, e2 = _frame(axis)
        azimuth = np.arctan2(directions @ e2, directions @ e1)
        sector = (((azimuth + math.pi) / (2 * math.pi) * BOUNDARY_SECTORS).astype(int)
                  % BOUNDARY_SECTORS)
        height = directions @ axis
        boundary = []
        for k in range(BOUNDARY_SECTORS):
            members = np.flatnonzero(sector == k)
            if len(members) < 3:
                continue
            top = members[np.argsort(height[members])[-2:]]  # the innermost two of the sector
            boundary.extend(top.tolist())
        sides = {int(sector[b] * 4 // BOUNDARY_SECTORS) for b in boundary}
        if len(boundary) < 8 or len(sides) < 2:
            return None
        b = directions[np.asarray(boundary)]
        angle = np.arccos(np.clip(b @ axis, -1.0, 1.0))
        if (np.ptp(azimuth[np.asarray(boundary)]) < math.pi / 2):
            return None
        start = np.array([0.0, 0.0, math.cos(float(np.median(angle)))])

        def residuals(x: F64, b: F64 = b, e1: F64 = e1, e2: F64 = e2, axis: F64 = axis) -> F64:
            g = axis + x[0] * e1 + x[1] * e2
            return np.asarray(b @ (g / np.linalg.norm(g)) - x[2], dtype=np.float64)

        fit = least_squares(residuals, start, loss="soft_l1", f_scale=0.01)
        g = axis + fit.x[0] * e1 + fit.x[1] * e2
        g /= np.linalg.norm(g)
        resid = fit.fun
        sigma = max(1.4826 * float(np.median(np.abs(resid))), 1e-5)
        try:
            cov = np.linalg.inv(fit.jac.T @ fit.jac)[:2, :2] * sigma**2
        except np.linalg.LinAlgError:
            cov = np.full((2, 2), np.inf)
        moved = float(np.linalg.norm(g - axis))
        axis = g
        result = (g, float(fit.x[2]), cov, len(boundary))
        if moved < 1e-5:
            break
    return result


def _empty_cone(directions: F64, axis: F64) -> F64:
    """Axis of the widest cone about the globe centre that the sclera and lid rim leave empty.

    The hole the cornea leaves in the cloud is wider than the limbus and lopsided (its shadow,
    fringe erosion, the lids), so a circle fitted to its edge points anywhere; the axis that
    keeps every edge furthest away (the 99.9th percentile of ``u·g`` smallest, a few stray
    points allowed) follows the hole's middle. Grids of tilts: ±25° by 1°, then ±1.5° by 0.1°.
    """
    if len(directions) > CONE_POINTS:  # a fixed subsample: the score is a high percentile
        directions = directions[np.linspace(0, len(directions) - 1, CONE_POINTS).astype(int)]
    best = axis / np.linalg.norm(axis)
    allowed = max(1, round(0.001 * len(directions)))
    for span, step in ((25.0, 1.0), (1.5, 0.1)):
        e1, e2 = _frame(best)
        tilts = np.tan(np.radians(np.arange(-span, span + 1e-9, step)))
        tx, ty = np.meshgrid(tilts, tilts)
        cand = best[None] + tx.ravel()[:, None] * e1 + ty.ravel()[:, None] * e2
        cand /= np.linalg.norm(cand, axis=1, keepdims=True)
        score = np.empty(len(cand))
        for start in range(0, len(cand), 256):
            dots = directions @ cand[start:start + 256].T
            score[start:start + 256] = -np.partition(-dots, allowed - 1, axis=0)[allowed - 1]
        best = cand[int(np.argmin(score))]
    return best


def _cornea(points: F64, centre: F64, radius: float, gaze: F64, cos_beta: float,
            ) -> tuple[F64, int, float] | None:
    """Centre of a corneal cap in front of the hole, its point count and centre SD, if seen."""
    rel = points - centre
    dist = distances(rel)
    inside = (rel @ gaze) > dist * (cos_beta - 0.05)
    candidates = points[inside & (dist > radius + 0.15) & (dist < radius + 3.5)]
    if len(candidates) < 60:
        return None
    c0, r0 = fit_sphere(candidates)
    if not 5.5 < r0 < 10.5:
        return None

    def residuals(x: F64) -> F64:
        return np.asarray(distances(candidates, x[:3]) - x[3], dtype=np.float64)

    fit = least_squares(residuals, np.append(c0, r0), loss="soft_l1", f_scale=0.05)
    resid = fit.fun
    sigma = max(1.4826 * float(np.median(np.abs(resid))), 1e-4)
    good = np.abs(resid) < 3 * sigma
    if good.sum() < 60 or not 5.5 < fit.x[3] < 10.5 or sigma > 0.2:
        return None
    try:
        cov = np.linalg.inv(fit.jac[good].T @ fit.jac[good]) * sigma**2
    except np.linalg.LinAlgError:
        return None
    return fit.x[:3], int(good.sum()), float(math.sqrt(np.trace(cov[:3, :3])))


def checked_cloud(cloud: CloudLike) -> tuple[F64, F64]:
    """A cloud's points (N, 3) and fit weights (its quality clipped to 0.05–1, or ones).

    Raises
    ------
    ValueError
        ``cloud.points`` is not (N, 3) or holds non-finite values.
    """
    points = np.asarray(cloud.points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"cloud.points must have shape (N, 3), got {points.shape}")
    if not np.isfinite(points).all():
        raise ValueError("cloud.points must be finite")
    quality = cloud.quality
    weights = (np.ones(len(points)) if quality is None
               else np.clip(np.asarray(quality, dtype=np.float64), 0.05, 1.0))
    return points, weights


def radius_bounds(model: EyeModel) -> tuple[float, float]:
    """The globe radii the model takes for an eye (mm): 0.7–1.45 times the prior radius when
    the radius is fitted, within 5 % of a held one."""
    fixed = model.globe_radius_mm
    if fixed is not None:
        return 0.95 * fixed, 1.05 * fixed
    return 0.7 * model.prior_radius_mm, 1.45 * model.prior_radius_mm


def _is_a_globe(radius: float, bounds: tuple[float, float]) -> bool:
    """Whether a fitted globe radius (mm) lies within :data:`NO_GLOBE_FACTOR` of ``bounds``."""
    return bounds[0] / NO_GLOBE_FACTOR <= radius <= bounds[1] * NO_GLOBE_FACTOR


def _refuse_no_globe(radius: float, bounds: tuple[float, float]) -> None:
    """:class:`PoseError` for a globe radius (mm) :data:`NO_GLOBE_FACTOR` beyond ``bounds``."""
    if not _is_a_globe(radius, bounds):
        raise PoseError(f"no eye found: the globe fitted has a radius of {radius:.3g} mm, far "
                        f"outside the model's {bounds[0]:.1f}–{bounds[1]:.1f} mm")


def fit_eye(cloud: CloudLike, model: EyeModel, views: Sequence[LimbusView] = ()) -> EyePose:
    """Fit the eye model to a fused cloud: globe centre and radius, limbus, gaze, confidence.

    Parameters
    ----------
    cloud : CloudLike
        Points (N, 3) in WCS mm, with optional per-point quality in [0, 1] used as weights.
    model : EyeModel
        The patient's model; a fixed ``globe_radius_mm`` is imposed, None fits the radius.
    views : sequence of LimbusView
        The fringe images the cloud came from, with their cameras. When given, the limbus is
        found in them (:mod:`eyeserver.eye.limbus`) and sets the gaze, the limbus centre
        and, with the sclera, the globe (``gaze_source`` ``"limbus (images)"``); when it is not
        found there (lids closed, too little contrast) the cloud-only estimate stands, its
        confidence scaled by :data:`UNSEEN_LIMBUS`.

    Returns
    -------
    EyePose
        Its sds include the error the fit's covariances do not count (:func:`with_model_error`).

    Raises
    ------
    PoseError
        No convex sphere of a globe's size is found, or too few points lie on it, or the globe
        fitted lies far outside the model's radii (:data:`NO_GLOBE_FACTOR`).
    ValueError
        ``cloud.points`` is not (N, 3) or holds non-finite values.
    """
    return with_model_error(_fit(cloud, model, views))


def with_model_error(pose: EyePose) -> EyePose:
    """``pose`` with the error its fit's covariances do not count added to its centre's and its
    gaze's sds (:func:`model_error_sds`): a pose whose evidence is weak says how little it
    knows. The confidence and the pose itself are unchanged."""
    centre, gaze = model_error_sds(pose.confidence)
    x, y, z = (math.hypot(sd, centre) for sd in pose.centre_sd_mm)
    return replace(pose, centre_sd_mm=(x, y, z), gaze_sd_deg=math.hypot(pose.gaze_sd_deg, gaze))


def model_error_sds(confidence: float) -> tuple[float, float]:
    """The unexplained error :func:`with_model_error` adds for ``confidence``: the sd per centre
    axis (mm) and the gaze's (degrees), zero at or above :data:`~eyeserver.eye.tunables.
    MODEL_ERROR_BELOW_CONFIDENCE` and growing as the confidence falls below it
    (:data:`~eyeserver.eye.tunables.MODEL_ERROR_CENTRE_MM`)."""
    c = min(max(confidence, MODEL_ERROR_MIN_CONFIDENCE), 1.0)
    weakness = (max(0.0, MODEL_ERROR_BELOW_CONFIDENCE - c) / c) ** MODEL_ERROR_POWER
    return MODEL_ERROR_CENTRE_MM * weakness, MODEL_ERROR_GAZE_DEG * weakness


def _fit(cloud: CloudLike, model: EyeModel, views: Sequence[LimbusView]) -> EyePose:
    """:func:`fit_eye` before :func:`with_model_error`."""
    started = time.perf_counter()
    points, weights = checked_cloud(cloud)
    if len(points) < MIN_SCLERA_POINTS:
        raise PoseError(f"no eye found: the cloud holds {len(points)} points")
    fixed = model.globe_radius_mm
    r_bounds = radius_bounds(model)
    candidates, off_plane = _globe_candidates(points, r_bounds, fixed)
    # The face's plane crosses every sphere about the eye in a ring of many points: its points
    # never take part in the globe's fit.
    points, weights = points[off_plane], weights[off_plane]
    if not candidates:
        raise PoseError("no eye found: no convex sphere of a globe's size (radius "
                        f"{r_bounds[0]:.1f}–{r_bounds[1]:.1f} mm) facing the cameras in "
                        f"{len(points)} points")
    # Lids and retractors lie in front of the globe: the innermost shell is the sclera.
    centre, radius, lid_radius = candidates[0]
    if fixed is not None:
        radius = fixed
    # The seed centre is good to ≈ 0.5 mm and the lids lie ≈ 1 mm outside: a band half that.
    band = 0.45
    for next_band in (0.3, SHELL_BAND_MM, 0.2):
        dist = distances(points, centre)
        near = np.abs(dist - radius) < band
        on_lids = (np.abs(dist - lid_radius) < band if math.isfinite(lid_radius)
                   else np.zeros(len(points), dtype=bool))
        if near.sum() < MIN_SCLERA_POINTS:
            raise PoseError(f"no eye found: only {int(near.sum())} points on the best globe")
        centre, radius, lid_radius, cov, resid, inliers = _refine_globe(
            points[near], weights[near], centre, radius, fixed, points[on_lids],
            weights[on_lids], lid_radius)
        band = next_band
    sclera = points[near][inliers]
    if len(sclera) < MIN_SCLERA_POINTS:
        raise PoseError(f"no eye found: only {len(sclera)} sclera points fit a globe")
    surface_mad = float(np.median(np.abs(resid)))
    centre_sd = np.sqrt(np.clip(np.diag(cov)[:3], 0.0, None))

    _refuse_no_globe(radius, r_bounds)
    gaze = cloud_gaze(points, sclera, centre, radius, centre_sd, model)
    plausible = 1.0 if r_bounds[0] <= radius <= r_bounds[1] else IMPLAUSIBLE_RADIUS
    if views:
        on_limbus = pose_on_limbus(points, views, model, centre, gaze.direction, radius, fixed,
                                   started)
        if on_limbus is not None:
            return on_limbus
        plausible *= UNSEEN_LIMBUS
    return pose_from_cloud(centre, centre_sd, radius, gaze, surface_mad, len(sclera), started,
                           plausible, shape_sd_mm=model.shape_sd_mm)


@dataclass(frozen=True)
class Gaze:
    """The gaze and what comes with it: the limbus, where it came from, how sure it is."""

    direction: F64
    sd_deg: float
    source: str
    limbus_centre: F64 | None = None
    limbus_sd_mm: float | None = None
    boundary_radius_mm: float | None = None
    cornea_points: int = 0


def cloud_gaze(points: F64, sclera: F64, centre: F64, radius: float, centre_sd: F64,
               model: EyeModel, fallback: F64 | None = None) -> Gaze:
    """The gaze from the cloud alone, about a fitted globe (module step 3).

    ``points`` is the cloud without the face's plane, ``sclera`` the points on the globe;
    ``fallback`` starts the search where nothing lies around the globe (None: no gaze then).
    """
    directions = sclera - centre
    directions /= distances(directions)[:, None]
    # The opening (sclera and the lids' inner rim together) is centred near the cornea; the
    # sclera alone, often more on one side, is not.
    dist_all = distances(points, centre)
    around = np.abs(dist_all - radius) < 3.0
    start = (points[around] - centre).mean(axis=0) if around.any() else fallback
    limbus = _limbus(directions, start)
    # The widest empty cone of the sclera and lid shell (R − 0.3 … R + 2 mm): measured on 24
    # rendered poses, gaze 4.8° median (p95 13°) against 7.7° (p95 43°) from the edge circle.
    shell = (dist_all > radius - 0.3) & (dist_all < radius + 2.0)
    opening = None
    if shell.sum() >= MIN_SCLERA_POINTS and start is not None:
        opening = _empty_cone((points[shell] - centre) / dist_all[shell, None], start)
    half = model.limbus_diameter_mm / 2
    depth = math.sqrt(max(radius**2 - half**2, 0.0))
    gaze = directions.mean(axis=0) if opening is None else opening
    if limbus is None:
        return Gaze(gaze / np.linalg.norm(gaze), 90.0, "none")
    g, cos_beta, tilt_cov, _ = limbus
    if g[2] < 0:  # the hole faces the cameras; a flip means the ring was misread
        g = -g
    edge_radius = radius * math.sqrt(max(1.0 - cos_beta**2, 0.0))
    if opening is not None and abs(edge_radius - half) > EDGE_IS_LIMBUS_MM:
        g = opening  # the hole is not the limbus: its edge circle would stray
    lateral = float(np.sqrt(np.sum(centre_sd**2 * (1.0 - g**2))))
    # Tilt of the fitted circle plus the globe centre's own lateral uncertainty seen from
    # the limbus plane.
    tilt_var = float(np.trace(tilt_cov)) + (lateral / max(depth, 1.0)) ** 2
    gaze, gaze_sd, source, cornea_points = g, math.degrees(math.sqrt(tilt_var)), "limbus", 0
    cornea = _cornea(points, centre, radius, g, cos_beta)
    if cornea is not None:
        c_centre, cornea_points, c_sd = cornea
        axis = c_centre - centre
        if np.linalg.norm(axis) > 1.0:
            axis /= np.linalg.norm(axis)
            var_c = (c_sd / max(float(np.linalg.norm(c_centre - centre)), 1.0)) ** 2
            var_l = math.radians(gaze_sd) ** 2
            blend = gaze / var_l + axis / var_c
            gaze = blend / np.linalg.norm(blend)
            gaze_sd = math.degrees(math.sqrt(1.0 / (1.0 / var_l + 1.0 / var_c)))
            source = "limbus+cornea"
    limbus_sd = float(math.sqrt(float(centre_sd @ centre_sd)
                                + (depth * math.radians(gaze_sd)) ** 2))
    return Gaze(gaze, gaze_sd, source, centre + depth * gaze, limbus_sd, edge_radius,
                cornea_points)


def pose_on_limbus(points: F64, views: Sequence[LimbusView], model: EyeModel, centre: F64,
                   rough_gaze: F64, radius: float, fixed_radius: float | None, started: float,
                   *, search: bool = True, remeasure: bool = True,
                   pixels_per_point: float = 1.0) -> EyePose | None:
    """The pose from the limbus found in ``views`` and the sclera of ``points`` that carries
    it (:mod:`eyeserver.eye.limbus`), from a rough globe and gaze; None where no limbus
    is found.

    ``fixed_radius`` holds the globe's radius (the patient's model, or the last frame's while
    tracking; None: the model's ellipsoid places the globe on the limbus, see
    :meth:`EyeModel.radius_through_limbus`, or else the sclera does); ``search`` as
    :func:`~eyeserver.eye.limbus.find_limbus`. ``started`` is
    the fit's start (``time.perf_counter()``) for ``fit_ms``. ``remeasure``: the globe and gaze
    from the sclera measured again in the images and the limbus found again there
    (:func:`~eyeserver.eye.sclera.refit`; live tracking, whose radius is held, leaves it
    out for time). ``pixels_per_point``: the image pixels each point stands for (a decimated
    reconstruction's, as live tracking's): the confidence counts the sclera's support in
    pixels, so that it does not depend on how densely the cloud was reconstructed.
    """
    try:
        # Both units' cloud places the globe's axis well enough to hold the search near it
        # (three cameras or more: a unit has two).
        held = LIMBUS_AXIS_SD_MM if search and len(views) >= 3 else None
        limbus = find_limbus(views, centre, rough_gaze, radius, model.limbus_diameter_mm / 2,
                             search=search, oval=search and OVAL_LIMBUS, axis_sd_mm=held)
        if fixed_radius is None:
            fixed_radius = model.radius_through_limbus(limbus.radius)
        globe = globe_on_limbus(points, limbus, fixed_radius)
    except LimbusNotFoundError:
        return None
    surface = None
    if model.globe_semi_axes_mm is not None and fixed_radius is not None:
        held = fixed_radius

        def surface(pts: F64, centre_at: F64, gaze_at: F64) -> F64:
            return _surface_distance(pts, centre_at, held, gaze_at, model)
    refitted = (refit(views, limbus, globe.centre, globe.radius, globe.sclera, points,
                      fixed_radius, model.cornea_radius_mm, surface)
                if remeasure and len(globe.sclera) >= MIN_SCLERA_POINTS and not globe.two_shells
                else None)
    if refitted is not None:
        limbus = refitted.limbus  # found again in the images with the fringe divided out
        centre_out, radius_out = refitted.centre, refitted.radius
        centre_sd = np.sqrt(np.clip(np.diag(refitted.centre_cov), 0.0, None))
        gaze = Gaze(refitted.gaze, refitted.gaze_sd_deg, LIMBUS_FROM_IMAGES,
                    refitted.limbus_centre, refitted.limbus_sd_mm, limbus.radius)
        surface_mad = float(np.median(np.abs(_surface_distance(
            globe.sclera, centre_out, radius_out, refitted.gaze, model))))
    else:
        g = limbus.normal
        depth = float((limbus.centre - globe.centre) @ g)
        # Per axis: the limbus centre's spread, the depth's along the gaze, and the tilt's
        # lever arm across it.
        lever = depth * math.radians(limbus.gaze_sd_deg)
        centre_sd = np.sqrt(limbus.centre_sd_mm**2 / 3.0 + (globe.depth_sd_mm * g) ** 2
                            + lever**2 * (1.0 - g**2))
        gaze = Gaze(g, limbus.gaze_sd_deg, LIMBUS_FROM_IMAGES, limbus.centre,
                    limbus.centre_sd_mm, limbus.radius)
        centre_out, radius_out, surface_mad = globe.centre, globe.radius, globe.surface_mad_mm
        if model.globe_semi_axes_mm is not None and len(globe.sclera):
            surface_mad = float(np.median(np.abs(_surface_distance(
                globe.sclera, centre_out, radius_out, g, model))))
    # The globe's support, not its sclera points: lids taken for the sclera of an eye that
    # shows almost none lie near the sphere in hundreds of points too (measured: 1 pose of 200,
    # 3.9 mm off with confidence 0.64: 43 points of support against 196–1,775 on 24 others;
    # its sclera had been lost to the speckle filter, see reconstruct.MIN_PATCH_PX).
    # How sharp the limbus itself is, not the gaze the sclera sharpened; and a radius beyond the
    # model's bounds is no eye's (one unit's sclera with the radius free: 5.1 and 6.9 mm off
    # with radii of 17.8 and 18.3 mm and confidences 0.58 and 0.35; `bench pose --unit left`).
    sharpness = replace(gaze, sd_deg=max(gaze.sd_deg, limbus.gaze_sd_deg))
    low, high = radius_bounds(model)
    if not _is_a_globe(radius_out, (low, high)):
        return None  # no globe carries this limbus: as if none were found
    plausible = 1.0 if low <= radius_out <= high else IMPLAUSIBLE_RADIUS
    confidence = plausible * _confidence(round(globe.support * pixels_per_point),
                                         WELL_SEEN_LIMBUS_POINTS, surface_mad, sharpness)
    return _pose(centre_out, centre_sd, radius_out, gaze, surface_mad, globe.points, confidence,
                 started, model.shape_sd_mm)


def _surface_distance(points: F64, centre: F64, radius: float, gaze: F64, model: EyeModel
                      ) -> F64:
    """Each point's distance (mm, + outside) from the globe: the sphere of ``radius`` about
    ``centre``, or the model's ellipsoid about it turned with the eye so that its axial
    semi-axis lies along ``gaze`` (radially: ``|q|·(1 − 1/‖q/axes‖)`` in the ellipsoid's
    frame, within a few micrometres of the true distance for a globe's few-percent
    ellipticity)."""
    rel = points - centre
    if model.globe_semi_axes_mm is None:
        return np.asarray(distances(rel) - radius, dtype=np.float64)
    axes = np.asarray(model.globe_semi_axes_mm, dtype=np.float64)
    frame, axial = model.ellipsoid_frame()
    planned = frame[:, axial] * math.copysign(1.0, frame[2, axial])
    # The smallest rotation taking the planned axial direction to the gaze (Rodrigues).
    axis = np.cross(planned, gaze)
    sin, cos = float(np.linalg.norm(axis)), float(planned @ gaze)
    turn = np.eye(3)
    if sin > 1e-12:
        k = axis / sin
        cross = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
        turn = np.eye(3) + sin * cross + (1.0 - cos) * cross @ cross
    local = rel @ (turn @ frame)
    length = distances(local)
    scaled = distances(local / axes)
    return np.asarray(length * (1.0 - 1.0 / np.maximum(scaled, 1e-12)), dtype=np.float64)


def pose_from_cloud(centre: F64, centre_sd: F64, radius: float, gaze: Gaze, surface_mad: float,
                    sclera_points: int, started: float, plausible: float = 1.0,
                    pixels_per_point: float = 1.0, *, shape_sd_mm: float = 0.0) -> EyePose:
    """The pose of a globe fitted to the cloud with its :func:`cloud_gaze`; ``plausible``
    scales the confidence (0.3 for a radius outside the model's bounds); ``pixels_per_point``
    as :func:`pose_on_limbus`; ``shape_sd_mm`` the model's (:attr:`EyePose.shape_sd_mm`)."""
    confidence = _confidence(round(sclera_points * pixels_per_point), WELL_SEEN_POINTS,
                             surface_mad, gaze) * plausible
    return _pose(centre, centre_sd, radius, gaze, surface_mad, sclera_points, confidence,
                 started, shape_sd_mm)


def _confidence(sclera_points: int, well_seen: int, surface_mad: float, gaze: Gaze) -> float:
    """Enough sclera, a surface that fits the model, a gaze that is found and sharp."""
    seen = 1.0 - math.exp(-sclera_points / well_seen)
    fits = 1.0 / (1.0 + (surface_mad / 0.15) ** 2)
    sharp = 0.0 if gaze.source == "none" else 1.0 / (1.0 + (gaze.sd_deg / 1.0) ** 2)
    return seen * fits * (0.25 + 0.75 * sharp)


def _pose(centre: F64, centre_sd: F64, radius: float, gaze: Gaze, surface_mad: float,
          sclera_points: int, confidence: float, started: float, shape_sd_mm: float = 0.0
          ) -> EyePose:
    def triple(v: F64) -> tuple[float, float, float]:
        return float(v[0]), float(v[1]), float(v[2])

    return EyePose(
        centre_mm=triple(centre), centre_sd_mm=triple(centre_sd), globe_radius_mm=float(radius),
        limbus_centre_mm=None if gaze.limbus_centre is None else triple(gaze.limbus_centre),
        limbus_sd_mm=gaze.limbus_sd_mm, gaze=triple(gaze.direction),
        gaze_sd_deg=float(gaze.sd_deg), torsion_deg=None, surface_mad_mm=float(surface_mad),
        sclera_points=int(sclera_points), confidence=float(min(max(confidence, 0.0), 1.0)),
        gaze_source=gaze.source, boundary_radius_mm=gaze.boundary_radius_mm,
        cornea_points=gaze.cornea_points, fit_ms=1000.0 * (time.perf_counter() - started),
        shape_sd_mm=float(shape_sd_mm))
