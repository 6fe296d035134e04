"""Rigid registration of a measured surface onto a reference surface (docs/design.md §4, §6).

The paper scores a measured eye-phantom surface by its "ICP RMSE after rigid registration"
against the phantom's reference surface; the eye pose work registers surfaces the same way.
This module holds the three pieces:

* :func:`estimate_normals`: unit normals of a point cloud by principal component analysis of
  each point's nearest neighbours (Hoppe et al. 1992), batched over all points;
* :func:`icp_point_to_plane`: iterative closest point with the point-to-plane error (Chen &
  Medioni 1992) linearised for small angles (Low 2004), returning a :class:`Registration`;
* :func:`nearest_distances`: each point's distance to the nearest point of another cloud, the
  score behind :attr:`Registration.rmse_mm`.

Why point-to-plane
------------------
An eye is nearly a sphere. Point-to-point ICP pulls every source point towards one discrete target
point, so on a smooth, weakly featured surface the pairs resist sliding along it and the solution
stalls with degree-level rotation errors (≈ 2° measured, docs/notes/design-measurements.md). The
point-to-plane error only penalises the offset along the target's normal: the surface may slide over
itself, the small shape features that fix the pose decide it, and the residual falls to ≈ 0.01°. No
surface method sees a rotation about a sphere's centre, nor the torsion of an eye symmetric about
its axis: exactly unobservable motions are left out of each step, but noise in the estimated normals
makes them look faintly observable and they drift by tenths of a degree from iteration to iteration.
Only the observable part of such a result (the globe's centre, the direction of the eye's axis)
means anything.

Conventions
-----------
Points are rows ``(x, y, z)`` in millimetres. A rigid transform maps a point ``p`` to
``R @ p + t``; as a 4×4 homogeneous matrix it is ``[[R, t], [0, 0, 0, 1]]``.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from eyeserver.core.types import F64

__all__ = ["Registration", "estimate_normals", "icp_point_to_plane", "nearest_distances"]

# Three points fix a rigid transform in principle; six pairs are the fewest for which the 6×6
# point-to-plane system can be of full rank.
_MIN_POINTS = 6
# Eigenvalues of the scaled 6×6 normal matrix below this fraction of the largest are treated as
# unobservable motions (a rotation about a sphere's centre, a slide along a plane) and left out
# of the step instead of being amplified into noise. The matrix squares the Jacobian's
# condition, so this keeps directions down to a 10⁻⁶ relative sensitivity.
_RELATIVE_EIGENVALUE_FLOOR = 1e-12
# Neighbourhood size of the target normals ICP estimates itself (see estimate_normals).
_ICP_NEIGHBOURS = 12
# How far from orthonormal the rotation of an ``initial`` transform may be.
_ROTATION_TOLERANCE = 1e-6


@dataclass(frozen=True, eq=False)
class Registration:
    """The result of a rigid registration: the transform mapping source onto target, and scores.

    Attributes
    ----------
    rotation : ndarray, shape (3, 3), float64
        Proper rotation ``R`` (orthonormal, determinant +1). Read-only.
    translation : ndarray, shape (3,), float64
        Translation ``t`` in mm. Read-only. A source point ``p`` maps to ``R @ p + t``.
    rmse_mm : float
        Root mean square distance, mm, of every source point (not only the ICP sample), after the
        transform, to its nearest target point; only the inliers count when a
        ``max_distance_mm`` was given. NaN if no point is an inlier. A distance to the nearest
        *point* includes the target's sampling: a source lying exactly on the surface between
        target points 0.14 mm apart scores ≈ 0.09 mm, so a reference must be sampled much
        more densely than the accuracy to be shown.
    inlier_fraction : float
        Fraction of all source points within ``max_distance_mm`` of the target after the
        transform; 1.0 when no ``max_distance_mm`` was given.
    iterations : int
        Number of ICP iterations run (correspondence search and least-squares step each).
    converged : bool
        Whether the last step moved every sampled point by less than the tolerance, or the
        pairs of source and target points repeated those of an earlier iteration (a cycle the
        iteration would only go round again). False when the iteration budget ran out or fewer
        than 6 pairs were left.
    """

    rotation: F64
    translation: F64
    rmse_mm: float
    inlier_fraction: float
    iterations: int
    converged: bool

    def __post_init__(self) -> None:
        rotation = np.array(self.rotation, dtype=np.float64)
        translation = np.array(self.translation, dtype=np.float64)
        if rotation.shape != (3, 3):
            raise ValueError(f"rotation: expected shape (3, 3), not {rotation.shape}")
        if translation.shape != (3,):
            raise ValueError(f"translation: expected shape (3,), not {translation.shape}")
        rotation.setflags(write=False)
        translation.setflags(write=False)
        object.__setattr__(self, "rotation", rotation)
        object.__setattr__(self, "translation", translation)

    @property
    def matrix(self) -> F64:
        """The transform as a 4×4 homogeneous matrix ``[[R, t], [0, 0, 0, 1]]`` (a new array)."""
        matrix = np.eye(4)
        matrix[:3, :3] = self.rotation
        matrix[:3, 3] = self.translation
        return matrix

    def apply(self, points: npt.ArrayLike) -> F64:
        """Transform ``points``, shape (N, 3) or (3,), in mm; returns a new float64 array.

        Raises
        ------
        ValueError
            If ``points`` does not end in an axis of length 3.
        """
        array = np.asarray(points, dtype=np.float64)
        if array.ndim not in (1, 2) or array.shape[-1] != 3:
            raise ValueError(f"points: expected shape (N, 3) or (3,), not {array.shape}")
        return np.asarray(array @ self.rotation.T + self.translation, dtype=np.float64)


def estimate_normals(points: npt.ArrayLike, neighbours: int = 12, *,
                     towards: npt.ArrayLike | None = None) -> F64:
    """Unit surface normals of a point cloud from the principal axes of local neighbourhoods.

    The normal at a point is the eigenvector of the smallest eigenvalue of the covariance of its
    ``neighbours`` nearest points (itself included): the direction in which the neighbourhood is
    thinnest. All covariances are formed and decomposed in one batch.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Finite points in mm, ``N >= neighbours``.
    neighbours : int, optional
        Size of each neighbourhood, at least 3. A dozen points average the noise of a measured
        surface; many more blur its curvature (the neighbourhood's radius grows with √k).
    towards : array_like, shape (3,), optional
        Viewpoint in mm (e.g. a camera centre). If given, each normal is flipped to point towards
        it; otherwise its sign is arbitrary (but reproducible).

    Returns
    -------
    normals : ndarray, shape (N, 3), float64
        Unit normals. Where a neighbourhood is degenerate (collinear or coincident points) the
        direction is arbitrary within the degenerate subspace.

    Notes
    -----
    The plane fitted to a neighbourhood passes through its centroid, so on a curved surface the
    estimate is the normal there, not at the point itself: where the neighbours lie lopsided
    around the point by δ, the normal tilts by about δ/R on a surface of radius R (measured on a
    globe of radius 12 mm sampled every 0.3 mm, 12 neighbours: median 0.2°, worst 0.6°).

    Raises
    ------
    ValueError
        If ``points`` is not (N, 3), holds non-finite values or fewer than ``neighbours`` points,
        ``neighbours`` is not an integer of at least 3, or ``towards`` is not a finite (3,)
        vector; the message names the parameter.

    References
    ----------
    .. [1] H. Hoppe, T. DeRose, T. Duchamp, J. McDonald and W. Stuetzle, "Surface
       reconstruction from unorganized points", Computer Graphics (SIGGRAPH '92) 26(2), 71–78
       (1992). doi:10.1145/142920.134011

    Examples
    --------
    >>> xy = np.stack(np.meshgrid(np.arange(5.0), np.arange(5.0)), axis=-1).reshape(-1, 2)
    >>> plane = np.column_stack([xy, np.zeros(len(xy))])
    >>> normals = estimate_normals(plane, 8, towards=[0.0, 0.0, 10.0])
    >>> np.allclose(normals, [0.0, 0.0, 1.0])
    True
    """
    cloud = _as_points(points, "points", minimum=3)
    k = _as_int(neighbours, "neighbours", minimum=3)
    if cloud.shape[0] < k:
        raise ValueError(f"points: {cloud.shape[0]} points are fewer than neighbours={k}")
    viewpoint = None if towards is None else _as_vector(towards, "towards")
    _, index = cKDTree(cloud).query(cloud, k=k)
    normals = _principal_normals(cloud[np.asarray(index, dtype=np.intp)])
    if viewpoint is not None:
        facing = np.einsum("ij,ij->i", normals, viewpoint - cloud)
        normals[facing < 0.0] *= -1.0
    return normals


def nearest_distances(source: npt.ArrayLike, target: npt.ArrayLike) -> F64:
    """Distance, mm, from each source point to its nearest target point.

    Parameters
    ----------
    source : array_like, shape (N, 3)
        Finite points in mm, at least one.
    target : array_like, shape (M, 3)
        Finite points in mm, at least one.

    Returns
    -------
    distances : ndarray, shape (N,), float64
        Euclidean distances in mm.

    Raises
    ------
    ValueError
        If either array is not (N, 3), empty or holds non-finite values; the message names it.

    Examples
    --------
    >>> nearest_distances([[0.0, 0.0, 3.0], [1.0, 0.0, 0.0]], [[0.0, 0.0, 0.0]])
    array([3., 1.])
    """
    source_points = _as_points(source, "source", minimum=1)
    target_points = _as_points(target, "target", minimum=1)
    distances, _ = cKDTree(target_points).query(source_points, k=1)
    return np.asarray(distances, dtype=np.float64)


def icp_point_to_plane(
    source: npt.ArrayLike,
    target: npt.ArrayLike,
    *,
    target_normals: npt.ArrayLike | None = None,
    initial: npt.ArrayLike | None = None,
    max_iterations: int = 50,
    tolerance_mm: float = 1e-6,
    max_distance_mm: float | None = None,
    trim_factor: float | None = 3.0,
    sample: int | None = 5000,
    seed: int = 0,
) -> Registration:
    """Rigidly register ``source`` onto ``target`` by point-to-plane iterative closest point.

    Each iteration pairs every sampled source point (moved by the current transform) with its
    nearest target point, drops doubtful pairs, and solves the linearised point-to-plane least
    squares problem for a small rotation and translation, which is composed onto the transform.

    Parameters
    ----------
    source : array_like, shape (N, 3)
        The surface to move (e.g. the measured one), finite, mm, ``N >= 6``.
    target : array_like, shape (M, 3)
        The surface to move onto (e.g. the reference), finite, mm, ``M >= 6``.
    target_normals : array_like, shape (M, 3), optional
        Normals of ``target`` (any non-zero length, any sign). If not given they are
        estimated as by :func:`estimate_normals` (12 neighbours), and only at the target points
        that some sampled source point pairs with.
    initial : array_like, shape (4, 4), optional
        Starting rigid transform of the source (homogeneous, rotation orthonormal to 10⁻⁶);
        identity if not given. The result includes it.
    max_iterations : int, optional
        Iteration budget, at least 1.
    tolerance_mm : float, optional
        Convergence threshold, mm: the iteration stops once a step moves every sampled point by
        less than this (bounded by ``|Δt| + |Δω|·r_max`` about the sample's centroid), or once
        the pairs repeat an earlier iteration's (see :attr:`Registration.converged`).
    max_distance_mm : float, optional
        Pairs farther apart than this (mm) are rejected in every iteration, and the final
        scores count only source points within it. Set it to a few times the expected
        misalignment plus noise when the source may hold outliers or lie partly off the target.
    trim_factor : float, optional
        Robust trim: pairs farther apart than ``trim_factor`` times the median pair distance of
        the iteration are rejected too (after ``max_distance_mm``). ``None`` disables it. The
        default 3 keeps nearly all pairs of a noisy but aligned surface while dropping points
        that fell off the target's edge or far off its surface. When about half of the source or
        more lies off the target, the median is itself an off-target distance and the trim no
        longer helps (measured: a third off registers exactly, half off fails by 2°): set
        ``max_distance_mm``.
    sample : int, optional
        Number of source points used by the iterations, drawn once without replacement (all
        points if ``None`` or if the source has no more). At least 6.
    seed : int, optional
        Seed of the sample; the same seed gives the same result.

    Returns
    -------
    Registration
        The transform mapping ``source`` onto ``target`` and its scores: ``rmse_mm`` and
        ``inlier_fraction`` are evaluated on all source points, not only the sample.

    Raises
    ------
    ValueError
        On a wrong shape, non-finite values, fewer than 6 points, zero-length normals, a
        non-rigid ``initial``, or an out-of-range option; the message names the parameter.

    Notes
    -----
    For a pair of a moved source point ``p``, target point ``q`` with unit normal ``n``, a small
    rotation ``ω`` about the sample's centroid ``c`` and translation ``δ`` change the residual
    ``(p − q)·n`` by ``ω·((p − c) × n) + δ·n``. Stacking the rows ``[(p − c) × n, n]`` gives a
    Jacobian ``J`` (N×6) whose normal equations ``JᵀJ x = −Jᵀr`` are solved after scaling
    the rotational columns by the sample's RMS radius, so both halves are in mm. Motions the
    surface cannot see (eigenvalues below 10⁻¹² of the largest) are left out of the step. The
    step's rotation is applied exactly (Rodrigues), so the transform stays rigid. Pivoting
    about the centroid decouples rotation from translation, which keeps the system well
    conditioned far from the origin.

    The sample is drawn once, not per iteration: the same points in every iteration let the
    step shrink steadily to zero, so the tolerance is a meaningful stopping rule.

    References
    ----------
    .. [1] P. J. Besl and N. D. McKay, "A method for registration of 3-D shapes", IEEE Trans.
       Pattern Anal. Mach. Intell. 14(2), 239–256 (1992). doi:10.1109/34.121791
    .. [2] Y. Chen and G. Medioni, "Object modelling by registration of multiple range images",
       Image and Vision Computing 10(3), 145–155 (1992). doi:10.1016/0262-8856(92)90066-C
    .. [3] K.-L. Low, "Linear least-squares optimization for point-to-plane ICP surface
       registration", Technical Report TR04-004, University of North Carolina at Chapel Hill
       (2004).
    .. [4] S. Rusinkiewicz and M. Levoy, "Efficient variants of the ICP algorithm", Proc. 3rd
       Int. Conf. on 3-D Digital Imaging and Modeling, 145–152 (2001).
       doi:10.1109/IM.2001.924423
    .. [5] E. Via et al., Physics and Imaging in Radiation Oncology (2023),
       doi:10.1016/j.phro.2023.100517 (ICP RMSE as the surface accuracy figure).

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> xy = rng.uniform(-5.0, 5.0, (2000, 2))
    >>> surface = np.column_stack([xy, 0.05 * xy[:, 0] ** 2 + 0.02 * xy[:, 0] * xy[:, 1] ** 2])
    >>> moved = surface + [0.2, -0.1, 0.3]
    >>> result = icp_point_to_plane(moved, surface)
    >>> np.round(result.translation, 6) + 0.0
    array([-0.2,  0.1, -0.3])
    """
    source_points = _as_points(source, "source", minimum=_MIN_POINTS)
    target_points = _as_points(target, "target", minimum=_MIN_POINTS)
    iterations_budget = _as_int(max_iterations, "max_iterations", minimum=1)
    tolerance = _as_float(tolerance_mm, "tolerance_mm", positive=False)
    max_distance = (None if max_distance_mm is None
                    else _as_float(max_distance_mm, "max_distance_mm", positive=True))
    trim = None if trim_factor is None else _as_float(trim_factor, "trim_factor", positive=True)
    if trim is not None and trim < 1.0:
        # Below 1 the trim would drop half the pairs or more in every iteration.
        raise ValueError(f"trim_factor: must be at least 1 or None, not {trim}")
    sample_size = (source_points.shape[0] if sample is None
                   else _as_int(sample, "sample", minimum=_MIN_POINTS))
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral):
        raise ValueError(f"seed: expected an integer, not {type(seed).__name__}")
    rotation, translation = _as_rigid(initial)

    tree = cKDTree(target_points)
    normals: F64 | _LazyNormals
    if target_normals is None:
        normals = _LazyNormals(tree, target_points, min(_ICP_NEIGHBOURS, target_points.shape[0]))
    else:
        normals = _as_points(target_normals, "target_normals", minimum=1)
        if normals.shape != target_points.shape:
            raise ValueError(f"target_normals: shape {normals.shape} differs from target's "
                             f"{target_points.shape}")
        lengths = np.linalg.norm(normals, axis=1)
        if np.any(lengths == 0.0):
            raise ValueError("target_normals: holds zero-length normals")
        normals = normals / lengths[:, None]

    n_source = source_points.shape[0]
    if sample_size < n_source:
        rng = np.random.default_rng(int(seed))
        chosen = np.sort(rng.choice(n_source, size=sample_size, replace=False))
        sampled = source_points[chosen]
    else:
        sampled = source_points

    converged = False
    iterations = 0
    previous_pairs = b""
    earlier_pairs: set[bytes] = set()
    while iterations < iterations_budget:
        iterations += 1
        moved = sampled @ rotation.T + translation
        distances, index = _query(tree, moved, max_distance)
        keep = np.isfinite(distances)
        if trim is not None and np.count_nonzero(keep) >= _MIN_POINTS:
            # A floor keeps pairs that are all exact (zero distance) from being trimmed away.
            limit = max(trim * float(np.median(distances[keep])), 1e-12)
            keep &= distances <= limit
        if np.count_nonzero(keep) < _MIN_POINTS:
            break
        pairs = np.where(keep, index, -1).tobytes()
        if pairs in earlier_pairs:
            # The same pairs as two or more iterations ago: the least-squares solution of a set
            # of pairs hardly depends on where it is linearised, so the iteration has entered a
            # cycle among a few discrete pairings and would only go round it again. Noise makes
            # points midway between two target points switch partners back and forth (measured
            # steps of 3·10⁻⁴ mm for ever, 0.02 mm noise on a nearly spherical patch), and an
            # invisible torsion drifts until the pairings close a loop (20–50 iterations).
            converged = True
            break
        earlier_pairs.add(previous_pairs)
        previous_pairs = pairs
        step_rotation, step_translation, step_mm = _point_to_plane_step(
            moved[keep], target_points[index[keep]], normals[index[keep]])
        rotation = step_rotation @ rotation
        translation = step_rotation @ translation + step_translation
        if step_mm < tolerance:
            converged = True
            break

    final_distances, _ = _query(tree, source_points @ rotation.T + translation, max_distance)
    inliers = np.isfinite(final_distances)
    n_inliers = int(np.count_nonzero(inliers))
    rmse = (math.sqrt(float(np.mean(final_distances[inliers] ** 2))) if n_inliers
            else math.nan)
    return Registration(rotation=rotation, translation=translation, rmse_mm=rmse,
                        inlier_fraction=n_inliers / n_source, iterations=iterations,
                        converged=converged)


def _point_to_plane_step(moved: F64, matched: F64, normals: F64) -> tuple[F64, F64, float]:
    """One linearised point-to-plane step: ``(R, t)`` to compose, and its largest move in mm."""
    centre = moved.mean(axis=0)
    arms = moved - centre
    # Scale the rotational unknowns by the sample's RMS radius so that all six are in mm and the
    # normal matrix is balanced whatever the patch size.
    radius = math.sqrt(float(np.mean(np.einsum("ij,ij->i", arms, arms))))
    radius = radius if radius > 0.0 else 1.0
    jacobian = np.concatenate([np.cross(arms, normals) / radius, normals], axis=1)
    residuals = np.einsum("ij,ij->i", moved - matched, normals)
    normal_matrix = jacobian.T @ jacobian
    rhs = -(jacobian.T @ residuals)
    eigenvalues, eigenvectors = np.linalg.eigh(normal_matrix)
    floor = _RELATIVE_EIGENVALUE_FLOOR * float(eigenvalues[-1])
    visible = eigenvalues > floor
    solution = eigenvectors[:, visible] @ ((eigenvectors[:, visible].T @ rhs)
                                           / eigenvalues[visible])
    omega = solution[:3] / radius
    delta = solution[3:]
    step_rotation = _rotation_from_vector(omega)
    # The rotation turns about the centroid: p → c + R(p − c) + δ = R p + (c − R c + δ).
    step_translation = centre - step_rotation @ centre + delta
    reach = float(np.max(np.linalg.norm(arms, axis=1)))
    step_mm = float(np.linalg.norm(delta)) + float(np.linalg.norm(omega)) * reach
    return step_rotation, step_translation, step_mm


def _rotation_from_vector(omega: F64) -> F64:
    """Rotation matrix of the rotation vector ``omega`` (axis × angle in rad), Rodrigues."""
    angle = float(np.linalg.norm(omega))
    if angle < 1e-300:
        return np.eye(3)
    axis = omega / angle
    cross = np.array([[0.0, -axis[2], axis[1]],
                      [axis[2], 0.0, -axis[0]],
                      [-axis[1], axis[0], 0.0]])
    return np.asarray(np.eye(3) + math.sin(angle) * cross
                      + (1.0 - math.cos(angle)) * (cross @ cross), dtype=np.float64)


def _query(tree: Any, points: F64, max_distance: float | None) -> tuple[F64, npt.NDArray[np.intp]]:
    """Nearest-neighbour distances (inf beyond ``max_distance``) and indices into the tree."""
    # The bound also prunes the tree search, which makes outlier-heavy queries cheaper. cKDTree
    # excludes a neighbour exactly at the bound; the next float up keeps it, as documented.
    bound = np.inf if max_distance is None else np.nextafter(max_distance, np.inf)
    distances, index = tree.query(points, k=1, distance_upper_bound=bound)
    return np.asarray(distances, dtype=np.float64), np.asarray(index, dtype=np.intp)


def _principal_normals(neighbourhoods: F64) -> F64:
    """Unit direction of least spread of each neighbourhood, shape (N, k, 3) -> (N, 3)."""
    centred = neighbourhoods - neighbourhoods.mean(axis=1, keepdims=True)
    # A batched matmul forms the 3×3 scatter matrices ≈ 3× faster than the equivalent einsum.
    covariances = np.swapaxes(centred, 1, 2) @ centred
    # eigh sorts the eigenvalues ascending: column 0 is the thinnest direction.
    _, eigenvectors = np.linalg.eigh(covariances)
    return np.ascontiguousarray(eigenvectors[:, :, 0], dtype=np.float64)


class _LazyNormals:
    """Normals of a target cloud estimated on first use, point by point.

    ICP only ever looks at the target points that some sampled source point pairs with, a few
    thousand of a cloud that may hold 50 000: estimating just those saves most of the cost
    (the k-nearest-neighbour search and the eigen-decompositions dominate a registration).
    """

    def __init__(self, tree: Any, points: F64, neighbours: int) -> None:
        self._tree = tree
        self._points = points
        self._neighbours = neighbours
        self._normals = np.zeros_like(points)
        self._known = np.zeros(points.shape[0], dtype=bool)

    def __getitem__(self, index: npt.NDArray[np.intp]) -> F64:
        missing = np.unique(index[~self._known[index]])
        if missing.size:
            _, neighbours = self._tree.query(self._points[missing], k=self._neighbours)
            self._normals[missing] = _principal_normals(
                self._points[np.asarray(neighbours, dtype=np.intp)])
            self._known[missing] = True
        return self._normals[index]


def _as_points(value: npt.ArrayLike, name: str, *, minimum: int) -> F64:
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: expected an (N, 3) array of numbers") from exc
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f"{name}: expected shape (N, 3), not {array.shape}")
    if array.shape[0] < minimum:
        raise ValueError(f"{name}: needs at least {minimum} points, not {array.shape[0]}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name}: holds non-finite values (NaN or inf)")
    return array


def _as_vector(value: npt.ArrayLike, name: str) -> F64:
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: expected a vector of 3 numbers") from exc
    if array.shape != (3,):
        raise ValueError(f"{name}: expected shape (3,), not {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name}: holds non-finite values (NaN or inf)")
    return array


def _as_int(value: object, name: str, *, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ValueError(f"{name}: expected an integer, not {type(value).__name__}")
    if int(value) < minimum:
        raise ValueError(f"{name}: must be at least {minimum}, not {value}")
    return int(value)


def _as_float(value: object, name: str, *, positive: bool) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"{name}: expected a number, not {type(value).__name__}")
    number = float(value)
    if not math.isfinite(number) or number < 0.0 or (positive and number == 0.0):
        kind = "positive" if positive else "non-negative"
        raise ValueError(f"{name}: must be a finite {kind} number, not {number}")
    return number


def _as_rigid(initial: npt.ArrayLike | None) -> tuple[F64, F64]:
    """Rotation and translation of a 4×4 rigid transform (identity for ``None``), validated."""
    if initial is None:
        return np.eye(3), np.zeros(3)
    try:
        matrix = np.asarray(initial, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError("initial: expected a 4×4 array of numbers") from exc
    if matrix.shape != (4, 4):
        raise ValueError(f"initial: expected shape (4, 4), not {matrix.shape}")
    if not np.all(np.isfinite(matrix)):
        raise ValueError("initial: holds non-finite values (NaN or inf)")
    if not np.allclose(matrix[3], [0.0, 0.0, 0.0, 1.0], rtol=0.0, atol=_ROTATION_TOLERANCE):
        raise ValueError(f"initial: last row must be [0, 0, 0, 1], not {matrix[3].tolist()}")
    rotation = matrix[:3, :3].copy()
    if (not np.allclose(rotation.T @ rotation, np.eye(3), rtol=0.0, atol=_ROTATION_TOLERANCE)
            or np.linalg.det(rotation) <= 0.0):
        raise ValueError("initial: the upper-left 3×3 block is not a proper rotation")
    return rotation, matrix[:3, 3].copy()
