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

from eyeserver.core.types import F64
from eyeserver.hardware.sim.optics import rotation_x, rotation_y, rotation_z

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
    """A surface in local coordinates with a reflectance map and a label for ground truth.

    Optional optics beyond Lambert's (all None or 0 by default, the surface then renders as
    it always did): ``scatter`` gives per point the share of a projected fringe's modulation
    that light scattered inside a translucent surface washes out; ``specular`` is a wet
    surface's mirror reflectance at normal incidence (the tear film's), which shows each
    projector's aperture as a glint; ``bumps`` tilt the mirror's normals locally (tear-film
    irregularities, each a small facet of its own curvature that glints where its normal
    bisects the camera and the projector); ``clear_at`` marks per local point where the surface
    is clear (a transparent cornea): rays from the cameras pass there, and light passes there to
    surfaces that are ``reached_through_holes`` (an iris behind the cornea), while every other
    point's shadow test takes the surface as solid (light that enters the cornea goes into the
    eye). A clear surface still glints.
    """

    scatter: AlbedoFn | None = None
    specular: float = 0.0
    bumps: Bumps | None = None
    clear_at: Callable[[F64], npt.NDArray[np.bool_]] | None = None
    reached_through_holes: bool = False

    def __init__(self, albedo: AlbedoFn, label: str) -> None:
        self.albedo = albedo
        self.label = label

    @abc.abstractmethod
    def intersect(self, o: F64, d: F64) -> tuple[F64, F64]:
        """Distances ``(N,)`` along ``d`` to the first front hit and normals ``(N, 3)``."""

    @abc.abstractmethod
    def distance(self, points: F64) -> F64:
        """Unsigned distance of local points ``(N, 3)`` to the surface (for scoring)."""

    def hit(self, o: F64, d: F64, clear: bool = True) -> tuple[F64, F64]:
        """:meth:`intersect`, with ``clear`` no hit where the surface is clear (a
        closed solid's far side is not a surface that matters here: what lies behind a hole
        is reached through it)."""
        t, normals = self.intersect(o, d)
        return self.cleared(o, d, t, normals) if clear else (t, normals)

    def cleared(self, o: F64, d: F64, t: F64, normals: F64) -> tuple[F64, F64]:
        """:meth:`intersect`'s ``t`` and ``normals`` with no hit where the surface is clear
        (copies where any is)."""
        if self.clear_at is None:
            return t, normals
        hit = np.flatnonzero(np.isfinite(t))
        if not hit.size:
            return t, normals
        open_ = hit[self.clear_at(o + t[hit, None] * d[hit])]
        t, normals = t.copy(), normals.copy()
        t[open_] = np.inf
        normals[open_] = 0.0
        return t, normals


@dataclass(frozen=True)
class Bumps:
    """Small facets on a surface (local frame): where a point lies within ``radius`` of a
    facet's ``centre``, the mirror's normal is tilted by ``tilt`` (a tangential vector, tan of
    the angle) plus the facet's own curvature (``curvature_mm`` its radius)."""

    centre: F64
    radius: F64
    tilt: F64
    curvature_mm: F64

    def mirror_normals(self, points: F64, normals: F64) -> F64:
        """The normals of ``points`` ``(N, 3)`` (on the surface, local) as the tear film's
        mirror sees them."""
        out = normals.copy()
        for centre, radius, tilt, curvature in zip(self.centre, self.radius, self.tilt,
                                                   self.curvature_mm, strict=True):
            rel = points - centre
            inside = np.einsum("ij,ij->i", rel, rel) < radius**2
            if np.any(inside):
                n = normals[inside]
                offset = rel[inside] + tilt * curvature
                tangential = offset - np.einsum("ij,ij->i", offset, n)[:, None] * n
                bent = n + tangential / curvature
                out[inside] = bent / np.linalg.norm(bent, axis=1, keepdims=True)
        return out


def _basis_of(axis: F64) -> tuple[F64, F64]:
    """Two unit vectors completing the unit ``axis`` to an orthonormal frame."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(axis, e1)


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


class Ellipsoid(Surface):
    """An ellipsoid seen from outside, its semi-axes along the local axes about ``centre``
    (a spheroid with two equal semi-axes is the conic cap of an aspheric cornea)."""

    def __init__(self, centre: Sequence[float] | F64, semi_axes: Sequence[float] | F64,
                 albedo: AlbedoFn, label: str) -> None:
        super().__init__(albedo, label)
        self.centre = np.asarray(centre, dtype=np.float64)
        self.semi_axes = np.asarray(semi_axes, dtype=np.float64)

    def intersect(self, o: F64, d: F64) -> tuple[F64, F64]:
        n = d.shape[0]
        t = np.full(n, np.inf)
        normals = np.zeros((n, 3))
        # Only rays that meet the bounding sphere (an eye fills a tenth of an image).
        rel = self.centre - o
        along = d @ rel
        bound = float(self.semi_axes.max())
        near = np.flatnonzero(float(rel @ rel) - along**2 < bound**2)
        if not near.size:
            return t, normals
        # In coordinates scaled by the semi-axes the ellipsoid is the unit sphere.
        oc = -rel / self.semi_axes
        ds = d[near] / self.semi_axes
        a = np.einsum("ij,ij->i", ds, ds)
        b = ds @ oc
        c = float(oc @ oc) - 1.0
        disc = b * b - a * c
        hit = disc >= 0
        t_near = (-b - np.sqrt(np.where(hit, disc, 0.0))) / a
        hit &= t_near > _EPS
        near, t_near = near[hit], t_near[hit]
        t[near] = t_near
        points = o + t_near[:, None] * d[near]
        bent = (points - self.centre) / self.semi_axes**2
        normals[near] = bent / np.maximum(np.linalg.norm(bent, axis=1, keepdims=True), 1e-12)
        return t, normals

    def distance(self, points: F64) -> F64:
        # First order in the level set k = |(p − c)/axes|: (k − 1)/|∇k|, exact on a sphere and
        # within a few µm of the true distance within 0.1 mm of an eye's ellipsoids.
        rel = points - self.centre
        k = np.linalg.norm(rel / self.semi_axes, axis=1)
        grad = np.linalg.norm(rel / self.semi_axes**2, axis=1) / np.maximum(k, 1e-12)
        return np.asarray(np.abs(k - 1.0) / np.maximum(grad, 1e-12))


class Hairs(Surface):
    """Thin straight cylinders (lashes): segment ``starts`` → ``ends`` ``(K, 3)``, ``radius``.

    A ray hits a hair where it passes within ``radius`` of its axis between the ends; the
    entry point and normal are those of the infinite cylinder (exact for hairs far thinner
    than long)."""

    def __init__(self, starts: F64, ends: F64, radius: float, albedo: AlbedoFn,
                 label: str) -> None:
        super().__init__(albedo, label)
        self.starts = np.asarray(starts, dtype=np.float64)
        self.ends = np.asarray(ends, dtype=np.float64)
        self.radius = float(radius)
        self._centre = ((self.starts + self.ends) / 2).mean(axis=0) if len(self.starts) \
            else np.zeros(3)

    def intersect(self, o: F64, d: F64) -> tuple[F64, F64]:
        n = d.shape[0]
        best = np.full(n, np.inf)
        normals = np.zeros((n, 3))
        if not len(self.starts):
            return best, normals
        ray, hair = self._candidates(o, d)
        if not ray.size:
            return best, normals
        a = self.starts[hair]
        e = self.ends[hair] - a
        dn = d[ray]
        ee = np.einsum("ij,ij->i", e, e)
        w0 = o - a
        de = np.einsum("ij,ij->i", dn, e)
        dw = np.einsum("ij,ij->i", dn, w0)
        ew = np.einsum("ij,ij->i", e, w0)
        denom = np.maximum(ee - de * de, 1e-12)
        t = (de * ew - ee * dw) / denom
        s = (ew - de * dw) / denom
        gap = w0 + t[:, None] * dn - s[:, None] * e
        dist2 = np.einsum("ij,ij->i", gap, gap)
        t_in = t - np.sqrt(np.clip(self.radius**2 - dist2, 0.0, None) * ee / denom)
        ok = (dist2 < self.radius**2) & (s >= 0.0) & (s <= 1.0) & (t_in > _EPS)
        ray, t_in, a, e, ee, s, dn = ray[ok], t_in[ok], a[ok], e[ok], ee[ok], s[ok], dn[ok]
        np.minimum.at(best, ray, t_in)
        first = t_in <= best[ray]
        hit = o + t_in[first, None] * dn[first]
        radial = hit - (a[first] + s[first, None] * e[first])
        radial -= (np.einsum("ij,ij->i", radial, e[first]) / ee[first])[:, None] * e[first]
        normals[ray[first]] = radial / np.maximum(np.linalg.norm(radial, axis=1, keepdims=True),
                                                  1e-12)
        return best, normals

    def _candidates(self, o: F64, d: F64) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]]:
        """Ray–hair pairs ``(ray indices, hair indices)`` whose ray may meet the hair.

        All rays leave ``o``: in the gnomonic projection about the hairs' centre a hair is a
        segment, and a ray a point, so the rays sorted by one coordinate give each hair's
        candidates by bisection within its bounding box (a ray–sphere test of every ray against
        every hair cost more than the exact test of the pairs).
        """
        axis = self._centre - o
        axis /= np.linalg.norm(axis)
        e1, e2 = _basis_of(axis)
        ends = np.stack([self.starts, self.ends]) - o  # (2, K, 3)
        depth = ends @ axis
        if np.any(depth <= self.radius):  # a hair beside or behind o: test every ray
            k = len(self.starts)
            return (np.repeat(np.arange(d.shape[0]), k), np.tile(np.arange(k), d.shape[0]))
        du = ends @ e1 / depth
        dv = ends @ e2 / depth
        margin = 1.5 * self.radius / depth.min(axis=0)
        along = d @ axis
        ahead = np.flatnonzero(along > 1e-6)
        u = (d[ahead] @ e1) / along[ahead]
        v = (d[ahead] @ e2) / along[ahead]
        order = np.argsort(u)
        u_sorted = u[order]
        lo = np.searchsorted(u_sorted, du.min(axis=0) - margin)
        hi = np.searchsorted(u_sorted, du.max(axis=0) + margin, side="right")
        rays: list[npt.NDArray[np.intp]] = []
        hairs: list[npt.NDArray[np.intp]] = []
        for k in range(len(self.starts)):
            picked = order[lo[k]:hi[k]]
            inside = np.abs(v[picked] - 0.5 * (dv[0, k] + dv[1, k])) <= (
                0.5 * abs(dv[0, k] - dv[1, k]) + margin[k])
            picked = ahead[picked[inside]]
            rays.append(picked)
            hairs.append(np.full(picked.size, k, dtype=np.intp))
        return np.concatenate(rays), np.concatenate(hairs)

    def distance(self, points: F64) -> F64:
        best = np.full(points.shape[0], np.inf)
        for a, b in zip(self.starts, self.ends, strict=True):
            e = b - a
            s = np.clip(((points - a) @ e) / float(e @ e), 0.0, 1.0)
            gap = np.linalg.norm(points - (a + s[:, None] * e), axis=1) - self.radius
            np.minimum(best, np.abs(gap), out=best)
        return best


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
    scatter: F64 | None = None
    """Per ray, the share of a fringe's modulation lost in the surface (None: none hit
    scatters)."""
    specular: F64 | None = None
    """Per ray, the mirror reflectance of the first glossy surface met, clear or not, where it
    lies in front of the hit (None: nothing met is glossy)."""
    mirror_normals: F64 | None = None
    """Where ``specular`` is given: the normals the mirror reflects about (world frame)."""
    mirror_points: F64 | None = None
    """Where ``specular`` is given: the points the mirror reflects at (world frame)."""
    inner: npt.NDArray[np.bool_] | None = None
    """Per ray, whether the surface hit is reached through holes (its shadow test respects
    them); None: none is."""


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

    def first_hit_distance(self, o: F64, d: F64, clear: bool = False) -> F64:
        """Distance to the nearest surface along each ray (for shadow tests); ``clear``: light
        passes the surfaces' holes (towards what is reached through them)."""
        best = np.full(d.shape[0], np.inf)
        for body in self.bodies:
            o_local = body.to_local(o[None, :])[0]
            d_local = d @ body.R
            for surface in body.surfaces:
                t, _ = surface.hit(o_local, d_local, clear)
                np.minimum(best, t, out=best)
        return best

    def cast(self, o: F64, d: F64) -> RayHits:
        """Cast rays from ``o`` along unit directions ``d`` ``(N, 3)``."""
        n = d.shape[0]
        best = np.full(n, np.inf)
        normals = np.zeros((n, 3))
        owner = np.full(n, -1, dtype=np.int64)
        flat: list[tuple[Body, Surface]] = []
        # A glossy surface glints where it is clear too: its whole intersection is kept.
        wet: list[_Met] = []
        for body in self.bodies:
            o_local = body.to_local(o[None, :])[0]
            d_local = d @ body.R
            for surface in body.surfaces:
                t, nrm = surface.intersect(o_local, d_local)
                if surface.specular > 0:
                    wet.append(_Met(body, surface, o_local, d_local, t, nrm))
                t, nrm = surface.cleared(o_local, d_local, t, nrm)
                closer = t < best
                best = np.where(closer, t, best)
                normals[closer] = nrm[closer] @ body.R.T
                owner[closer] = len(flat)
                flat.append((body, surface))
        hit = np.isfinite(best)
        points = o + np.where(hit, best, 0.0)[:, None] * d
        albedo = np.full(n, self.background_albedo)
        label = np.full(n, -1, dtype=np.int16)
        scatter: F64 | None = None
        inner: npt.NDArray[np.bool_] | None = None
        for index, (body, surface) in enumerate(flat):
            sel = owner == index
            if not np.any(sel):
                continue
            local = body.to_local(points[sel])
            albedo[sel] = surface.albedo(local)
            label[sel] = self.labels.index(surface.label)
            if surface.scatter is not None:
                scatter = np.zeros(n) if scatter is None else scatter
                scatter[sel] = surface.scatter(local)
            if surface.reached_through_holes:
                inner = np.zeros(n, dtype=bool) if inner is None else inner
                inner[sel] = True
        specular, mirror, mirror_points = _glossy(wet, o, d, best)
        return RayHits(t=best, points=points, normals=normals, albedo=albedo, label=label,
                       scatter=scatter, specular=specular, mirror_normals=mirror,
                       mirror_points=mirror_points, inner=inner)

    def distance(self, points: F64) -> F64:
        """Distance of world points to the nearest surface of the scene (for scoring)."""
        best = np.full(points.shape[0], np.inf)
        for body in self.bodies:
            local = body.to_local(points)
            for surface in body.surfaces:
                np.minimum(best, surface.distance(local), out=best)
        return best


@dataclass(frozen=True)
class _Met:
    """A surface's intersection with a cast's rays, in its body's frame."""

    body: Body
    surface: Surface
    o: F64
    d: F64
    t: F64
    normals: F64


def _glossy(met: list[_Met], o: F64, d: F64, best: F64
            ) -> tuple[F64 | None, F64 | None, F64 | None]:
    """Of the glossy surfaces ``met``, the first along each ray, clear or not, where it lies in
    front of (or is) the hit at ``best``: reflectance, mirror normals and points (world), or
    Nones when none is glossy."""
    if not met:
        return None, None, None
    n = d.shape[0]
    nearest = np.full(n, np.inf)
    specular = np.zeros(n)
    mirror = np.zeros((n, 3))
    for m in met:
        front = np.flatnonzero((m.t < nearest) & (m.t <= best + 1e-6))
        if not front.size:
            continue
        nearest[front] = m.t[front]
        specular[front] = m.surface.specular
        local_normals = m.normals[front]
        if m.surface.bumps is not None:
            local_normals = m.surface.bumps.mirror_normals(
                m.o + m.t[front, None] * m.d[front], local_normals)
        mirror[front] = local_normals @ m.body.R.T
    reached = np.isfinite(nearest)
    points = o + np.where(reached, nearest, 0.0)[:, None] * d
    return specular, mirror, points
