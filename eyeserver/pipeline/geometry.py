"""Camera geometry of the pipeline: undistorted pixel coordinates and the transversal mapping.

docs/design.md §4 step 6: the calibrated pinhole model (lens distortion removed) gives the ray
from the camera centre ``C = −Rᵀ T`` through pixel (i, j); where it meets the plane Z gives X and
Y.
"""

from __future__ import annotations

import functools

import cv2
import numpy as np

from eyeserver.core.types import F64


def undistorted_normalised(u: F64, v: F64, K: F64, dist: F64) -> tuple[F64, F64]:
    """Undistorted normalised coordinates ``(x, y)`` of pixel positions ``(u, v)`` (any shape).

    Uses ``cv2.undistortPoints`` with a tight iteration criterion: the default stops after five
    iterations, which leaves up to 0.01 px at the corners of a lens with k1 = −0.08.

    Parameters
    ----------
    u, v : ndarray
        Column and row positions in pixels, same shape.
    K : ndarray, shape (3, 3)
        Camera matrix.
    dist : ndarray
        OpenCV distortion coefficients.
    """
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    if u.shape != v.shape:
        raise ValueError(f"u and v must have the same shape, not {u.shape} and {v.shape}")
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"K must be 3×3, not {K.shape}")
    points = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
    xy = cv2.undistortPoints(points, K, np.asarray(dist, dtype=np.float64), None, None,
                             criteria=criteria).reshape(-1, 2)
    x = np.asarray(xy[:, 0], dtype=np.float64).reshape(u.shape)
    y = np.asarray(xy[:, 1], dtype=np.float64).reshape(u.shape)
    return x, y


def pixel_grid_normalised(width: int, height: int, K: F64, dist: F64) -> tuple[F64, F64]:
    """:func:`undistorted_normalised` of every pixel centre, arrays of shape ``(height, width)``,
    C-contiguous and read-only.

    Kept for the process (the 16 latest lenses): undistorting every pixel costs ≈ 40 ms a
    640 × 512 camera, and a bench or a test loads the same calibration many times.
    """
    if width <= 0 or height <= 0:
        raise ValueError(f"image size must be positive, not {width}×{height}")
    K_ = np.asarray(K, dtype=np.float64)
    if K_.shape != (3, 3):
        raise ValueError(f"K must be 3×3, not {K_.shape}")
    dist_ = np.asarray(dist, dtype=np.float64).ravel()
    return _pixel_grid(int(width), int(height), K_.tobytes(), dist_.tobytes())


@functools.lru_cache(maxsize=16)
def _pixel_grid(width: int, height: int, K: bytes, dist: bytes) -> tuple[F64, F64]:
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    x, y = undistorted_normalised(u, v, np.frombuffer(K).reshape(3, 3), np.frombuffer(dist))
    x, y = np.ascontiguousarray(x), np.ascontiguousarray(y)
    x.flags.writeable = y.flags.writeable = False
    return x, y


def rays_from_normalised(x: F64, y: F64, R: F64) -> F64:
    """World directions (not normalised; camera-z component 1) of the rays through ``(x, y)``."""
    cam = np.stack([x, y, np.ones_like(x)], axis=-1)
    return np.asarray(cam @ np.asarray(R, dtype=np.float64), dtype=np.float64)


def intersect_plane_z(centre: F64, directions: F64, z: F64) -> F64:
    """Points where rays from ``centre`` along ``directions`` (…, 3) meet the planes ``Z = z``.

    ``z`` broadcasts against the rays' leading shape; rays parallel to the plane give NaN.
    """
    directions = np.asarray(directions, dtype=np.float64)
    dz = directions[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (np.asarray(z, dtype=np.float64) - centre[2]) / dz
    t = np.where(np.abs(dz) > 1e-12, t, np.nan)
    return np.asarray(centre + t[..., None] * directions, dtype=np.float64)


_NUMPY_DISTORTION = 8
"""Distortion models up to this many coefficients (k1, k2, p1, p2[, k3[, k4, k5, k6]]) are
projected in NumPy; longer ones (thin prism, tilted sensor) by ``cv2.projectPoints``."""


def project(points: F64, K: F64, dist: F64, R: F64, T: F64) -> F64:
    """Pixel ``(u, v)`` of world points ``(N, 3)`` through a calibrated camera.

    OpenCV's pinhole and distortion model (K's skew ignored, as OpenCV does), written out in
    NumPy for models of up to :data:`_NUMPY_DISTORTION` coefficients: for 2,500 points (the
    limbus fit's batched circles, ≈ 30 calls a tracked frame) ``cv2.projectPoints`` with its
    ``cv2.Rodrigues`` took 0.5 ms on one thread (1 ms with OpenCV's thread pool), NumPy
    0.17 ms; the two agree to 1e-9 px (tests). Points behind the camera are projected as
    OpenCV does (through the centre), not masked.
    """
    coefficients = np.asarray(dist, dtype=np.float64).ravel()
    if coefficients.size > _NUMPY_DISTORTION and np.any(coefficients[_NUMPY_DISTORTION:]):
        return _project_cv2(points, K, coefficients, R, T)
    k = np.zeros(_NUMPY_DISTORTION)
    k[:min(coefficients.size, _NUMPY_DISTORTION)] = coefficients[:_NUMPY_DISTORTION]
    k1, k2, p1, p2, k3, k4, k5, k6 = k
    K = np.asarray(K, dtype=np.float64)
    # The camera's coordinates as three contiguous rows (3, N): the passes below then run on
    # contiguous arrays, not on an (N, 3) array's strided columns (a quarter faster).
    local = np.asarray(R, dtype=np.float64) @ np.asarray(points, dtype=np.float64).reshape(-1, 3).T
    local += np.asarray(T, dtype=np.float64).reshape(3, 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        inverse = np.where(local[2] != 0, 1.0 / local[2], 1.0)
        x, y = local[0] * inverse, local[1] * inverse
        r2 = x * x + y * y
        radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
        xy = x * y
        xd = x * radial + 2 * p1 * xy + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * xy
    uv = np.empty((x.size, 2))
    uv[:, 0] = K[0, 0] * xd + K[0, 2]
    uv[:, 1] = K[1, 1] * yd + K[1, 2]
    return uv


def _project_cv2(points: F64, K: F64, dist: F64, R: F64, T: F64) -> F64:
    rvec, _ = cv2.Rodrigues(np.asarray(R, dtype=np.float64))
    uv, _ = cv2.projectPoints(np.asarray(points, dtype=np.float64).reshape(-1, 1, 3), rvec,
                              np.asarray(T, dtype=np.float64), np.asarray(K, dtype=np.float64),
                              np.asarray(dist, dtype=np.float64))
    return np.asarray(uv.reshape(-1, 2), dtype=np.float64)
