"""Analytic surfaces for ray casting, in their own local frames, and rigid bodies that place them.

Every ray bundle shares one origin (a camera or projector centre), so intersections take an origin
``o`` of shape ``(3,)`` and directions ``d`` of shape ``(N, 3)`` and return per-ray distances
``t`` (``inf`` where the ray misses) and unit normals. All work is vectorised over rays.
"""

from __future__ import annotations

import abc
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from eyeserver.hardware.sim.optics import rotation_x, rotation_y, rotation_z

F64 = npt.NDArray[np.float64]
AlbedoFn = Callable[[F64], F64]

_EPS = 1e-9


def pose_matrix(rotation_deg: Sequence[float]) -> F64:
    """Rotation ``Rz·Ry·Rx`` from angles ``(rx, ry, rz)`` in degrees (local → world)."""
    rx, ry, rz = (math.radians(float(a)) for a in rotation_deg)
    return rotation_z(rz) @ rotation_y(ry) @ rotation_x(rx)


def constant_albedo(value: float) -> AlbedoFn:
    """A uniform surface of reflectance ``value`` (1 = the white calibration plate)."""
    def albedo(points: F64) -> F64:
        return np.full(points.shape[0], value, dtype=np.float64)
    return albedo


class Surface(abc.ABC):
    """A surface in local coordinates with a reflectance map and a label for ground truth."""

    def __init__(self, albedo: AlbedoFn, label: str) -> None:
        self.albedo = albedo
        self.label = label

    @abc.abstractmethod
    def intersect(self, o: F64, d: F64) -> tuple[F64, F64]:
        """Distances ``(N,)`` along ``d`` to the first front hit and normals ``(N, 3)``."""

    @abc.abstractmethod
    def distance(self, points: F64) -> F64:
        """Unsigned distance of local points ``(N, 3)`` to the surface (for scoring)."""


def _no_hit(n: int) -> tuple[F64, F64]:
    return np.full(n, np.inf), np.zeros((n, 3))


class Sphere(Surface):
    """A sphere seen from outside (unions of spheres, such as globe and cornea, need nothing more:
    the nearest entry point of a union of convex solids is the nearest of their entry points)."""

    def __init__(self, centre: Sequence[float] | F64, radius: float, albedo: AlbedoFn,
                 label: str) -> None:
        super().__init__(albedo, label)
        self.centre = np.asarray(centre, dtype=np.float64)
        self.radius = float(radius)

    def intersect(self, o: F64, d: F64) -> tuple[F64, F64]:
        oc = o - self.centre
        b = d @ oc
        c = float(oc @ oc) - self.radius**2
        disc = b * b - c
        hit = disc >= 0
        root = np.sqrt(np.where(hit, disc, 0.0))
        t = -b - root
        # From inside the sphere only the far root is in front; we never look from inside.
        t = np.where(hit & (t > _EPS), t, np.inf)
        points = o + t[:, None] * d
        normals = (points - self.centre) / self.radius
        normals[~np.isfinite(t)] = 0.0
        return t, normals

    def distance(self, points: F64) -> F64:
        return np.asarray(np.abs(np.linalg.norm(points - self.centre, axis=1) - self.radius))


class Plane(Surface):
    """The plane local z = 0, bounded by a rectangle ``half_size`` or a disc ``radius``.

    ``hole`` = (x, y, radius) cuts a circular hole; ``ellipse_hole`` = (x, y, a, b) an elliptical
    one. Both faces are visible; the normal returned is +z.
    """

    def __init__(self, albedo: AlbedoFn, label: str, *, half_size: tuple[float, float] | None
                 = None, radius: float | None = None, hole: tuple[float, float, float] | None
                 = None) -> None:
        super().__init__(albedo, label)
        self.half_size = half_size
        self.radius = radius
        self.hole = hole

    def _inside(self, x: F64, y: F64) -> npt.NDArray[np.bool_]:
        inside = np.ones(x.shape, dtype=bool)
        if self.half_size is not None:
            inside &= (np.abs(x) <= self.half_size[0]) & (np.abs(y) <= self.half_size[1])
        if self.radius is not None:
            inside &= x * x + y * y <= self.radius**2
        if self.hole is not None:
            hx, hy, hr = self.hole
            inside &= (x - hx) ** 2 + (y - hy) ** 2 > hr**2
        return inside

    def intersect(self, o: F64, d: F64) -> tuple[F64, F64]:
        dz = d[:, 2]
        safe = np.where(np.abs(dz) > 1e-12, dz, 1e-12)
        t = -o[2] / safe
        x = o[0] + t * d[:, 0]
        y = o[1] + t * d[:, 1]
        ok = (t > _EPS) & (np.abs(dz) > 1e-12) & self._inside(x, y)
        t = np.where(ok, t, np.inf)
        normals = np.zeros((d.shape[0], 3))
        normals[:, 2] = 1.0
        return t, normals

    def distance(self, points: F64) -> F64:
        return np.asarray(np.abs(points[:, 2]))


class Cone(Surface):
    """Lateral surface of a circular cone on z = 0: base ``radius``, apex at z = ``height``."""

    def __init__(self, radius: float, height: float, albedo: AlbedoFn, label: str) -> None:
        super().__init__(albedo, label)
        self.radius = float(radius)
        self.height = float(height)

    def intersect(self, o: F64, d: F64) -> tuple[F64, F64]:
        k2 = (self.radius / self.height) ** 2
        h = self.height
        hz = h - o[2]
        a = d[:, 0] ** 2 + d[:, 1] ** 2 - k2 * d[:, 2] ** 2
        b = 2 * (o[0] * d[:, 0] + o[1] * d[:, 1] + k2 * hz * d[:, 2])
        c = o[0] ** 2 + o[1] ** 2 - k2 * hz**2
        disc = b * b - 4 * a * c
        real = disc >= 0
        root = np.sqrt(np.where(real, disc, 0.0))
        safe_a = np.where(np.abs(a) > 1e-15, a, 1e-15)
        t_best = np.full(d.shape[0], np.inf)
        for t in ((-b - root) / (2 * safe_a), (-b + root) / (2 * safe_a)):
            z = o[2] + t * d[:, 2]
            ok = real & (t > _EPS) & (z >= 0) & (z <= h)
            t_best = np.where(ok & (t < t_best), t, t_best)
        points = o + np.where(np.isfinite(t_best), t_best, 0.0)[:, None] * d
        normals = np.stack([points[:, 0], points[:, 1], k2 * (h - points[:, 2])], axis=1)
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        normals[~np.isfinite(t_best)] = 0.0
        return t_best, normals

    def distance(self, points: F64) -> F64:
        # Distance in the meridian half-plane to the generatrix segment from (R, 0) to (0, h).
        rho = np.hypot(points[:, 0], points[:, 1])
        p = np.stack([rho, points[:, 2]], axis=1)
        a = np.array([self.radius, 0.0])
        ab = np.array([-self.radius, self.height])
        s = np.clip(((p - a) @ ab) / (ab @ ab), 0.0, 1.0)
        return np.asarray(np.linalg.norm(p - (a + s[:, None] * ab), axis=1))


class ConvexPolyhedron(Surface):
    """A convex solid ``{x : n_i·x ≤ d_i}`` given by outward unit normals and offsets."""

    def __init__(self, normals: F64, offsets: F64, albedo: AlbedoFn, label: str) -> None:
        super().__init__(albedo, label)
        norms = np.linalg.norm(normals, axis=1, keepdims=True)
        self.normals = normals / norms
        self.offsets = offsets / norms[:, 0]

    def intersect(self, o: F64, d: F64) -> tuple[F64, F64]:
        n_rays = d.shape[0]
        t_enter = np.full(n_rays, -np.inf)
        t_exit = np.full(n_rays, np.inf)
        face = np.zeros(n_rays, dtype=np.int64)
        ok = np.ones(n_rays, dtype=bool)
        for i, (normal, offset) in enumerate(zip(self.normals, self.offsets, strict=True)):
            denom = d @ normal
            num = offset - float(normal @ o)
            parallel = np.abs(denom) < 1e-12
            ok &= ~(parallel & (num < 0))
            t = num / np.where(parallel, 1.0, denom)
            entering = (denom < 0) & ~parallel
            exiting = (denom > 0) & ~parallel
            better = entering & (t > t_enter)
            face = np.where(better, i, face)
            t_enter = np.where(better, t, t_enter)
            t_exit = np.where(exiting & (t < t_exit), t, t_exit)
        hit = ok & (t_enter <= t_exit) & (t_enter > _EPS)
        t = np.where(hit, t_enter, np.inf)
        normals = self.normals[face]
        normals[~hit] = 0.0
        return t, normals

    def distance(self, points: F64) -> F64:
        # Exact for points on or near the boundary away from edges: the distance to the nearest
        # face plane among those the point is outside of (or the least-inside one).
        signed = points @ self.normals.T - self.offsets
        return np.asarray(np.abs(np.max(signed, axis=1)))


@dataclass
class Body:
    """Surfaces sharing a rigid pose: ``x_world = R x_local + t``."""

    surfaces: list[Surface]
    R: F64 = field(default_factory=lambda: np.eye(3))
    t: F64 = field(default_factory=lambda: np.zeros(3))

    def to_local(self, points: F64) -> F64:
        """World points ``(N, 3)`` into this body's frame."""
        return np.asarray((points - self.t) @ self.R)

    def to_world(self, points: F64) -> F64:
        """Local points ``(N, 3)`` into the world frame."""
        return np.asarray(points @ self.R.T + self.t)


@dataclass
class RayHits:
    """Result of casting rays into a scene (world frame)."""

    t: F64
    points: F64
    normals: F64
    albedo: F64
    label: npt.NDArray[np.int16]
    """Index into the scene's ``labels`` (−1 where nothing was hit)."""


class Scene:
    """A set of bodies; the nearest hit along each ray wins."""

    def __init__(self, bodies: list[Body], background_albedo: float = 0.0) -> None:
        self.bodies = bodies
        self.background_albedo = background_albedo
        self.labels: list[str] = []
        for body in bodies:
            for surface in body.surfaces:
                if surface.label not in self.labels:
                    self.labels.append(surface.label)

    def first_hit_distance(self, o: F64, d: F64) -> F64:
        """Distance to the nearest surface along each ray (for shadow tests)."""
        best = np.full(d.shape[0], np.inf)
        for body in self.bodies:
            o_local = body.to_local(o[None, :])[0]
            d_local = d @ body.R
            for surface in body.surfaces:
                t, _ = surface.intersect(o_local, d_local)
                np.minimum(best, t, out=best)
        return best

    def cast(self, o: F64, d: F64) -> RayHits:
        """Cast rays from ``o`` along unit directions ``d`` ``(N, 3)``."""
        n = d.shape[0]
        best = np.full(n, np.inf)
        normals = np.zeros((n, 3))
        owner = np.full(n, -1, dtype=np.int64)
        flat: list[tuple[Body, Surface]] = []
        for body in self.bodies:
            o_local = body.to_local(o[None, :])[0]
            d_local = d @ body.R
            for surface in body.surfaces:
                t, nrm = surface.intersect(o_local, d_local)
                closer = t < best
                best = np.where(closer, t, best)
                normals[closer] = nrm[closer] @ body.R.T
                owner[closer] = len(flat)
                flat.append((body, surface))
        hit = np.isfinite(best)
        points = o + np.where(hit, best, 0.0)[:, None] * d
        albedo = np.full(n, self.background_albedo)
        label = np.full(n, -1, dtype=np.int16)
        for index, (body, surface) in enumerate(flat):
            sel = owner == index
            if np.any(sel):
                albedo[sel] = surface.albedo(body.to_local(points[sel]))
                label[sel] = self.labels.index(surface.label)
        return RayHits(t=best, points=points, normals=normals, albedo=albedo, label=label)

    def distance(self, points: F64) -> F64:
        """Distance of world points to the nearest surface of the scene (for scoring)."""
        best = np.full(points.shape[0], np.inf)
        for body in self.bodies:
            local = body.to_local(points)
            for surface in body.surfaces:
                np.minimum(best, surface.distance(local), out=best)
        return best
