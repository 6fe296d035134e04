"""The physics of the simulated room: ray casting, projection, shading and the camera's sensor.

A render has two halves. :meth:`Renderer.components` casts every camera pixel's ray into the
scene (``s²`` rays where the pixel straddles an edge: a pixel integrates light over its area),
asks each projector which grating phase lands on the hit point and whether the point sees it
(shadows), and shades it (Lambert, albedo, inverse-square fall-off), then applies vignetting
and the optics' blur. The result is noise-free and linear in each light source, so it is
cached per scene and reused for every frame of a still scene. :meth:`Renderer.expose` then
mixes the light sources for one exposure and adds the sensor: shot noise from the full well,
read noise and quantisation.
"""

from __future__ import annotations

import functools
import math
import threading
from collections import OrderedDict
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
import numpy.typing as npt

from eyeserver.core.types import F32, F64, Image
from eyeserver.hardware.sim.config import CameraConfig, RoomConfig
from eyeserver.hardware.sim.geometry import Scene
from eyeserver.hardware.sim.optics import CameraModel, ProjectorModel, blurred_square_wave
from eyeserver.hardware.sim.scenes import BuiltScene

AMBIENT = "ambient"
"""Name of the diffuse (room or ambient) light source in :class:`Components`."""


@dataclass(frozen=True)
class Components:
    """Noise-free irradiance of one camera image, per light source, in 8-bit DN per unit light.

    ``ambient`` is the image under a uniform diffuse light of 1 DN on white; ``fringe[p]`` the
    image with projector ``p`` alone at full intensity (its fringe contrast calibrated by the
    room file). Both include vignetting and blur. Only the projectors asked for are present.
    """

    ambient: F32
    fringe: dict[str, F32]


@dataclass(frozen=True)
class _Shading:
    values: F64
    albedo: F64
    label: npt.NDArray[np.int16]
    lit: npt.NDArray[np.bool_]
    normals: F64
    glossy: npt.NDArray[np.bool_] | None = None
    """Rays that meet a glint or come near one (their pixels are integrated like edges')."""


@dataclass
class _StaticPart:
    """The static part of a moving scene seen by one camera.

    Raw (pre-blur) values per source, and finished (:meth:`Renderer._finish`); the pixels
    whose rays meet the moving parts' envelope (flat indices and rays); and, per projector,
    the pixels whose static point's ray to the projector passes through the envelope (with
    those segments), i.e. that could fall in a moving part's shadow.
    """

    values: dict[str, F64]
    finished: dict[str, F32]
    view_idx: npt.NDArray[np.intp]
    view_rays: F64
    hit_idx: npt.NDArray[np.intp]
    hit_points: F64
    shadow_idx: dict[str, npt.NDArray[np.intp]] = field(default_factory=dict)
    shadow_seg: dict[str, F64] = field(default_factory=dict)
    shadow_len2: dict[str, F64] = field(default_factory=dict)
    closed_first: npt.NDArray[np.bool_] | None = None
    """Per pixel: the scene's ``closed`` body at its fullest is the first hit (the shut lids)."""
    closed_values: dict[str, F64] = field(default_factory=dict)
    """Per source, the raw values of those pixels with that body at its fullest."""


ALBEDO_STEP = 1e-3
"""Neighbouring pixels whose albedo differs by more than this are integrated over their area:
every painted edge (steps of 0.02 and more), not the smooth reflectance of a soft limbus far
from its band, whose pixel centres stand for their pixels (a 1e-6 threshold integrated every
pixel of a patient's eye, 16 rays each, for nothing)."""


def _edge_pixels(shading: _Shading, height: int, width: int) -> npt.NDArray[np.bool_]:
    """Pixels whose centre differs from a 4-neighbour's in albedo, object, light or normal."""
    albedo = shading.albedo.reshape(height, width)
    label = shading.label.reshape(height, width)
    lit = shading.lit.reshape(height, width)
    normals = shading.normals.reshape(height, width, 3)
    edge = np.zeros((height, width), dtype=bool)
    for ta, tb in (((slice(1, None), slice(None)), (slice(None, -1), slice(None))),
                   ((slice(None), slice(1, None)), (slice(None), slice(None, -1)))):
        # Normals only compare where both rays hit something (a miss has a zero normal).
        bent = ((np.einsum("ijk,ijk->ij", normals[ta], normals[tb]) < 0.9995)
                & (label[ta] >= 0) & (label[tb] >= 0))
        diff = ((np.abs(albedo[ta] - albedo[tb]) > ALBEDO_STEP) | (label[ta] != label[tb])
                | (lit[ta] != lit[tb]) | bent)
        edge[ta] |= diff
        edge[tb] |= diff
    if shading.glossy is not None:
        glossy = shading.glossy.reshape(height, width)
        edge |= glossy
        edge[1:] |= glossy[:-1]
        edge[:-1] |= glossy[1:]
        edge[:, 1:] |= glossy[:, :-1]
        edge[:, :-1] |= glossy[:, 1:]
    return edge


GLINT_REACH = 3.0
"""Rays whose mirror reflection passes within this many aperture radii of a projector's pupil
are integrated over their pixel's area: a glint is smaller than a pixel."""


def _glints(hits_specular: F64, mirror: F64, rays: F64, points: F64, proj: ProjectorModel
            ) -> tuple[F64, npt.NDArray[np.bool_]]:
    """Mirror images of ``proj``'s exit pupil on a wet surface, in the units of
    :meth:`Renderer._shade_sources`'s values, and the rays near one.

    A mirror of reflectance ``R`` shows the pupil's radiance ``R·L``; a white diffuser at the
    working distance ``d₀`` under the same projector shows ``L·Ω/π`` with ``Ω = π r²/d₀²`` the
    pupil's solid angle, so the glint is ``R·(d₀/r)²`` times the white plate's light (≈ 32×
    for 2 % and a 10-mm pupil at 200 mm: saturated), at the grating's mean transmission (the
    pupil is lit through all of it), where the reflected ray meets the pupil.
    """
    outward = mirror * np.sign(np.einsum("ij,ij->i", mirror, -rays))[:, None]
    reflected = rays - 2.0 * np.einsum("ij,ij->i", rays, outward)[:, None] * outward
    to_proj = proj.centre - points
    distance = np.linalg.norm(to_proj, axis=1)
    cos_gap = np.einsum("ij,ij->i", reflected, to_proj) / np.maximum(distance, 1e-9)
    gap = np.arccos(np.clip(cos_gap, -1.0, 1.0))
    pupil = proj.config.aperture_mm / 2
    half = np.arctan(pupil / distance)
    # A soft rim a tenth of the pupil wide keeps the image free of single-sample aliasing.
    inside = np.clip((half - gap) / (0.1 * half) + 0.5, 0.0, 1.0)
    gain = hits_specular * (proj.working_distance / pupil) ** 2
    return gain * proj.power_dn * 0.5 * inside, gap < GLINT_REACH * half


def _radical_inverse_base2(k: npt.NDArray[np.int64]) -> F64:
    out = np.zeros(k.shape)
    scale = 0.5
    k = k.copy()
    while np.any(k):
        out += (k & 1) * scale
        k >>= 1
        scale *= 0.5
    return out


def pixel_samples(n: int) -> F64:
    """``n`` sample offsets within a pixel (Hammersley set, in −0.5…0.5).

    Every sample has its own column and its own row, so a straight edge in any direction,
    axis-aligned ones included, is resolved in ``n`` coverage steps rather than the ``√n`` of a
    regular grid: with 64 samples chessboard corners land within 0.09 px; a 3×3 grid left 0.26 px.
    """
    k = np.arange(n, dtype=np.int64)
    return np.stack([(k + 0.5) / n - 0.5, _radical_inverse_base2(k) + 0.5 / n - 0.5], axis=1)


def _f32(array: object) -> F32:
    """An OpenCV result as the float32 array it is (OpenCV's stubs type it loosely)."""
    return np.asarray(array, dtype=np.float32)


def _union(parts: Sequence[npt.NDArray[np.intp]], size: int) -> npt.NDArray[np.bool_]:
    """A mask of ``size`` set at every index of ``parts`` (several times faster than np.unique
    of their concatenation)."""
    mask = np.zeros(size, dtype=bool)
    for part in parts:
        mask[part] = True
    return mask


STATIC_PARTS_PER_CAMERA = 4
"""Static parts of moving scenes cached per camera (the last head positions, and those a
script's head shifts will end at, cast ahead by :meth:`SimRoom.prepare`)."""


@functools.lru_cache(maxsize=16)
def _camera_model(config_json: str) -> CameraModel:
    """The camera model of a camera's configuration (as JSON), shared by every renderer of it:
    its pixel grid and rays (the lens undone at every pixel, ≈ 0.2 s a 640 × 512 camera) are
    computed once a process, not once a room (the benches and tests open many rooms of the
    same cameras)."""
    return CameraModel(CameraConfig.model_validate_json(config_json))


class Renderer:
    """Renders images of a room's cameras; thread-safe, with a small cache of still scenes."""

    def __init__(self, room: RoomConfig, cache_size: int = 64) -> None:
        self.room = room
        self.cameras = {c.id: _camera_model(c.model_dump_json()) for c in room.cameras()}
        self.projectors = {p.id: ProjectorModel(p) for p in room.projectors()}
        self._vignetting = {cid: cam.vignetting for cid, cam in self.cameras.items()}
        self._cache: OrderedDict[tuple[str, str, str], F32] = OrderedDict()
        self._cache_size = cache_size
        self._static: OrderedDict[tuple[str, str], _StaticPart] = OrderedDict()
        self._lock = threading.Lock()

    def components(self, camera_id: str, scene: Scene, supersample: int,
                   projectors: Iterable[str] = (), cache_key: str | None = None) -> Components:
        """Noise-free light components of ``camera_id`` viewing ``scene``.

        ``projectors`` names the projector components wanted (the ambient one always comes).
        ``cache_key`` identifies a still scene: its components are computed once and reused.
        """
        sources = [AMBIENT, *projectors]
        keys = {source: (camera_id, source, f"{cache_key}|{supersample}")
                for source in sources} if cache_key is not None else {}
        images: dict[str, F32] = {}
        with self._lock:
            for source, key in keys.items():
                if (cached := self._cache.get(key)) is not None:
                    self._cache.move_to_end(key)
                    images[source] = cached
        missing = [source for source in sources if source not in images]
        if missing:
            computed = self._compute(camera_id, scene, supersample, missing)
            images.update(computed)
            if keys:
                with self._lock:
                    for source in missing:
                        self._cache[keys[source]] = computed[source]
                    while len(self._cache) > self._cache_size:
                        self._cache.popitem(last=False)
        return Components(ambient=images[AMBIENT],
                          fringe={pid: images[pid] for pid in sources[1:]})

    def seen_and_lit(self, camera_id: str, scene: Scene, projector_id: str,
                     ) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.bool_]]:
        """Per pixel ``(height, width)``, whether the ray through its centre meets ``scene``
        (seen), and whether it meets it where projector ``projector_id`` lights it (inside its
        field, not shadowed, facing it: lit): the pixels that can show that projector's
        fringe, the truth's denominator of a reconstruction's coverage, whatever the pipeline's
        own fringe mask decides. One ray cast for both (each takes ≈ 0.5 s a camera)."""
        cam = self.cameras[camera_id]
        shading = self._shade(cam, scene, cam.rays().reshape(-1, 3), projector_id)
        shape = (cam.config.height, cam.config.width)
        return (shading.label >= 0).reshape(shape), shading.lit.reshape(shape)

    def _shade(self, cam: CameraModel, scene: Scene, rays: F64, source: str) -> _Shading:
        """Light reaching the camera along ``rays`` from one source, per unit source strength."""
        return self._shade_sources(cam, scene, rays, [source])[source]

    def _shade_sources(self, cam: CameraModel, scene: Scene, rays: F64,
                       sources: Sequence[str]) -> dict[str, _Shading]:
        """:meth:`_shade` for several sources from one ray cast."""
        hits = scene.cast(cam.centre, rays)
        hit = np.isfinite(hits.t)
        # Lambertian surfaces look equally bright from every side: only the side facing the
        # camera can be lit, so orient normals towards the camera.
        facing = np.einsum("ij,ij->i", hits.normals, rays) > 0
        normals = np.where(facing[:, None], -hits.normals, hits.normals)
        albedo = np.where(hit, hits.albedo, scene.background_albedo)
        idx = np.flatnonzero(hit)
        points = hits.points[idx]
        out: dict[str, _Shading] = {}
        for source in sources:
            lit = np.zeros(rays.shape[0], dtype=bool)
            if source == AMBIENT:
                out[source] = _Shading(values=albedo, albedo=albedo, label=hits.label, lit=lit,
                                       normals=normals)
                continue
            proj = self.projectors[source]
            values = np.zeros(rays.shape[0])
            glossy: npt.NDArray[np.bool_] | None = None
            if idx.size:
                phase, distance, inside = proj.phase_at(points)
                to_proj = (proj.centre - points) / distance[:, None]
                cos_inc = np.einsum("ij,ij->i", normals[idx], to_proj)
                # Shadows: the projector's ray to the point must not meet the scene first
                # (through the holes of clear surfaces where the point lies behind them).
                blocker = scene.first_hit_distance(proj.centre, -to_proj)
                if hits.inner is not None:
                    behind = np.flatnonzero(hits.inner[idx])
                    if behind.size:
                        blocker[behind] = scene.first_hit_distance(
                            proj.centre, -to_proj[behind], clear=True)
                visible = blocker >= distance - (1e-3 + 1e-6 * distance)
                lit_here = inside & visible & (cos_inc > 0)
                transmission = blurred_square_wave(phase, proj.config.blur_periods)
                if hits.scatter is not None:
                    # Light scattered within a translucent surface leaves it as the grating's
                    # mean (0.5), not where the fringe put it.
                    share = hits.scatter[idx]
                    transmission = (1.0 - share) * transmission + 0.5 * share
                values[idx] = np.where(
                    lit_here, albedo[idx] * proj.power_dn * cos_inc
                    * (proj.working_distance / distance) ** 2 * transmission, 0.0)
                lit[idx] = lit_here
                if (hits.specular is not None and hits.mirror_normals is not None
                        and hits.mirror_points is not None):
                    # A glint is the pupil's image on the eye's convex front, which the
                    # projector sees: no shadow test.
                    wet = np.flatnonzero(hits.specular > 0)
                    if wet.size:
                        glint, near = _glints(hits.specular[wet], hits.mirror_normals[wet],
                                              rays[wet], hits.mirror_points[wet], proj)
                        values[wet] += glint
                        glossy = np.zeros(rays.shape[0], dtype=bool)
                        glossy[wet] = near
            out[source] = _Shading(values=values, albedo=albedo, label=hits.label, lit=lit,
                                   normals=normals, glossy=glossy)
        return out

    def components_moving(self, camera_id: str, built: BuiltScene,
                          projectors: Iterable[str] = (), *, keep: bool = True) -> Components:
        """Components of a moving scene at one instant, re-casting only what moved.

        The static part (``built.static``) is rendered once and cached. Each frame re-casts,
        through the whole scene, only the pixels whose camera ray meets a moving part (tested
        where the ray meets the part's bounding sphere). A static point whose ray to a
        projector passes through the sphere can only fall into a moving part's shadow: there
        the moving parts alone are tested for blocking that ray, and its static value kept or
        darkened (half the re-cast rays on the simulated eye, measured). Everywhere else the
        moving parts cannot change the light. Both tests run only over the pixels that meet
        ``built.envelope``, found once per static part. Measured on one camera: a frame of the
        drifting eye 6.6 ms (7.6 re-casting every ray that meets a bound), of the shut lids
        18.5 (23 with the whole lid shell a moving part); with the closing lids bounded by their
        own cap instead of the lid sphere, 9 % less again (20 against 22 ms, another day); and
        where the scene gives a body that stands for a moving one at its fullest
        (``built.closed``: the shut lids), the rays that meet the moving one where the full one
        is the first hit take its light, shaded once (:meth:`_closed_layer`), about half a
        shut-lid frame's time.
        """
        if built.static is None or built.static_key is None or built.envelope is None:
            raise ValueError("the scene has no static part to cache")
        cam = self.cameras[camera_id]
        sources = [AMBIENT, *projectors]
        static = self._static_part(camera_id, built, sources, keep=keep)
        rays = cam.rays().reshape(-1, 3)
        moving = Scene([body for body in built.scene.bodies
                        if not any(body is other for other in built.static.bodies)])
        seen: list[npt.NDArray[np.intp]] = []
        shaded: dict[str, list[npt.NDArray[np.intp]]] = {source: [] for source in sources[1:]}
        for centre, radius in built.moving_bounds:
            along = static.view_rays @ (centre - cam.centre)
            rel = centre - cam.centre
            near = (along > 0) & (float(rel @ rel) - along**2 < radius**2)
            seen.append(static.view_idx[near])
            for source in sources[1:]:
                # Closest approach of the bound's centre to each segment projector → point.
                seg = static.shadow_seg[source]
                rel = centre - self.projectors[source].centre
                frac = np.clip((seg @ rel) / static.shadow_len2[source], 0.0, 1.0)
                gap = rel - frac[:, None] * seg
                shaded[source].append(np.flatnonzero(np.einsum("ij,ij->i", gap, gap)
                                                      < radius**2))
        # Of the rays that meet a bound, only those that meet a moving part can change: the
        # others keep the static part's first hit (its light changes only by a moving part's
        # shadow, below). Testing the moving parts alone is cheap against re-casting the whole
        # scene: a blink's bound is the whole lid shell, its closing lids a part of it.
        idx = np.flatnonzero(_union(seen, rays.shape[0]))
        meets = [np.isfinite(Scene([body]).first_hit_distance(cam.centre, rays[idx]))
                 for body in moving.bodies]
        hit = np.logical_or.reduce(meets) if meets else np.zeros(idx.size, dtype=bool)
        # Of those, the rays that meet the closing lids where the shut lids are the first hit
        # show the shut lids' light there, shaded once (_closed_layer): a blink's frames
        # re-cast only the opening.
        covered = np.zeros(0, dtype=np.intp)
        if built.closed is not None and built.closed[0] is not None:
            first = static.closed_first  # cast with the static part (_static_part)
            assert first is not None
            lids = next(m for body, m in zip(moving.bodies, meets, strict=True)
                        if body is built.scene.bodies[built.closed[0]])
            cover = first[idx] & lids
            covered, hit = idx[cover], hit & ~cover
        idx = idx[hit]
        changed = np.zeros(rays.shape[0], dtype=bool)
        changed[idx] = changed[covered] = True
        fresh = self._shade_sources(cam, built.scene, rays[idx], sources) if idx.size else {}
        images: dict[str, F32] = {}
        for source in sources:
            pixels = np.concatenate([idx, covered])
            values = np.concatenate([fresh[source].values if idx.size else np.zeros(0),
                                     static.closed_values[source][covered] if covered.size
                                     else np.zeros(0)])
            if source != AMBIENT and shaded[source]:
                dark = self._shadowed(static, source, moving, shaded[source], changed)
                pixels, values = np.concatenate([pixels, dark]), np.concatenate(
                    [values, np.zeros(dark.size)])
            images[source] = self._finish_change(camera_id, static, source, pixels, values)
        return Components(ambient=images[AMBIENT],
                          fringe={pid: images[pid] for pid in sources[1:]})

    def _finish_change(self, camera_id: str, static: _StaticPart, source: str,
                       pixels: npt.NDArray[np.intp], values: F64) -> F32:
        """:meth:`_finish` of the static part's values with ``pixels`` (flat indices) set to
        ``values``, from the static part's finished image: vignetting and blur are linear, so
        only the change is blurred, in the box around it that the blur reaches (bit for bit
        the whole image's blur but for float rounding: the box's content is zero within a
        kernel's reach of its inner edges, and its edges on the image's border reflect as the
        whole image's do). Measured: 0.06 against 0.6 ms a source for the eye's change."""
        cam = self.cameras[camera_id]
        height, width = cam.shape
        image = static.finished[source].copy()
        if not pixels.size:
            return image
        rows, cols = np.divmod(pixels, width)
        change = ((values - static.values[source][pixels])
                  * self._vignetting[camera_id].ravel()[pixels]).astype(np.float32)
        sigma = cam.config.blur_px
        if sigma <= 0:
            image.ravel()[pixels] += change
            return image
        reach = math.ceil(4.0 * sigma) + 2  # OpenCV's float kernel: radius ≈ 4σ
        y0, y1 = max(0, int(rows.min()) - reach), min(height, int(rows.max()) + reach + 1)
        x0, x1 = max(0, int(cols.min()) - reach), min(width, int(cols.max()) + reach + 1)
        box = np.zeros((y1 - y0, x1 - x0), dtype=np.float32)
        box[rows - y0, cols - x0] = change
        image[y0:y1, x0:x1] += _f32(cv2.GaussianBlur(box, (0, 0), sigma,
                                                     borderType=cv2.BORDER_REFLECT))
        return image

    def _shadowed(self, static: _StaticPart, source: str, moving: Scene,
                  near: list[npt.NDArray[np.intp]], recast: npt.NDArray[np.bool_],
                  ) -> npt.NDArray[np.intp]:
        """The static points (pixel indices) that a moving part hides from ``source``, among
        those whose ray to it passes ``near`` the moving parts (positions in the static part's
        shadow lists) and that are not ``recast`` anyway."""
        rows = np.flatnonzero(_union(near, len(static.shadow_idx[source])))
        pixels = static.shadow_idx[source][rows]
        keep = ~recast[pixels]
        rows, pixels = rows[keep], pixels[keep]
        seg = static.shadow_seg[source][rows]
        distance = np.sqrt(static.shadow_len2[source][rows])
        blocker = moving.first_hit_distance(self.projectors[source].centre,
                                            seg / distance[:, None])
        # The same margin as the full shadow test of _shade_sources.
        return pixels[blocker < distance - (1e-3 + 1e-6 * distance)]

    def _closed_layer(self, camera_id: str, built: BuiltScene, static: _StaticPart,
                      sources: Sequence[str]) -> None:
        """Fill in ``static`` which pixels (of those that meet the envelope) first meet
        ``built.closed``'s body at its fullest in front of the static part, and their light
        from ``sources`` (≈ 20 ms a camera: a stream's cameras cast them when they are
        prepared, and a blink's first frame would take ≈ 30 ms, as every shut-lid frame did
        without them).
        Measured on one camera in one sitting: a shut-lid frame 16–18 ms, half shut 22, against
        32–36 and 32 re-casting every ray that meets the closing lids (an open eye's 13–15).
        """
        assert built.closed is not None and built.static is not None
        cam = self.cameras[camera_id]
        scene = Scene([*built.static.bodies, built.closed[1]])
        if static.closed_first is None:
            full = Scene([built.closed[1]]).first_hit_distance(cam.centre, static.view_rays)
            nearest = scene.first_hit_distance(cam.centre, static.view_rays)
            first = np.zeros(cam.shape[0] * cam.shape[1], dtype=bool)
            first[static.view_idx[np.isfinite(full) & (full <= nearest)]] = True
            static.closed_first = first
        missing = [source for source in sources if source not in static.closed_values]
        if missing:
            pixels = np.flatnonzero(static.closed_first)
            shaded = self._shade_sources(cam, scene, cam.rays().reshape(-1, 3)[pixels], missing)
            for source in missing:
                values = np.zeros(len(static.closed_first))
                values[pixels] = shaded[source].values
                static.closed_values[source] = values

    def _static_part(self, camera_id: str, built: BuiltScene, sources: Sequence[str], *,
                     keep: bool = True) -> _StaticPart:
        """The static part of ``built`` for ``camera_id`` with ``sources`` shaded, from the
        cache or cast now; ``keep`` False leaves one cast now out of the cache (a head in
        transit: its position never comes again, and it would push out those that do)."""
        assert built.static is not None and built.static_key is not None
        assert built.envelope is not None
        key = (camera_id, built.static_key)
        cam = self.cameras[camera_id]
        rays = cam.rays().reshape(-1, 3)
        with self._lock:
            part = self._static.get(key)
        if part is None:
            centre, radius = built.envelope
            rel = centre - cam.centre
            along = rays @ rel
            view = np.flatnonzero((along > 0) & (float(rel @ rel) - along**2 < radius**2))
            hits = built.static.cast(cam.centre, rays)
            part = _StaticPart(values={}, finished={}, view_idx=view, view_rays=rays[view],
                               hit_idx=np.flatnonzero(np.isfinite(hits.t)),
                               hit_points=hits.points[np.isfinite(hits.t)])
        missing = [src for src in sources if src not in part.values]
        if missing:
            shaded = self._shade_sources(cam, built.static, rays, missing)
            centre, radius = built.envelope
            for src in missing:
                part.values[src] = shaded[src].values
                part.finished[src] = self._finish(camera_id, shaded[src].values)
                if src == AMBIENT:
                    continue
                seg = part.hit_points - self.projectors[src].centre
                rel = centre - self.projectors[src].centre
                len2 = np.maximum(np.einsum("ij,ij->i", seg, seg), 1e-12)
                frac = np.clip((seg @ rel) / len2, 0.0, 1.0)
                gap = rel - frac[:, None] * seg
                near = np.einsum("ij,ij->i", gap, gap) < radius**2
                part.shadow_idx[src] = part.hit_idx[near]
                part.shadow_seg[src] = seg[near]
                part.shadow_len2[src] = len2[near]
        if built.closed is not None:
            self._closed_layer(camera_id, built, part, sources)
        with self._lock:
            if keep or key in self._static:
                self._static[key] = part
                self._static.move_to_end(key)
            while len(self._static) > STATIC_PARTS_PER_CAMERA * len(self.cameras):
                self._static.popitem(last=False)
        return part

    def _finish(self, camera_id: str, values: F64) -> F32:
        """Vignetting and the optics' blur on per-pixel values (a flat array)."""
        cam = self.cameras[camera_id]
        height, width = cam.shape
        image = values.reshape(height, width).astype(np.float32) * self._vignetting[camera_id]
        if cam.config.blur_px > 0:
            return np.asarray(cv2.GaussianBlur(image, (0, 0), cam.config.blur_px,
                                               borderType=cv2.BORDER_REFLECT), dtype=np.float32)
        return image

    def _compute(self, camera_id: str, scene: Scene, s: int, sources: Sequence[str],
                 ) -> dict[str, F32]:
        """The finished images of ``sources``, from one ray cast for all of them (a camera's
        cast took half of a still plate's render per source)."""
        cam = self.cameras[camera_id]
        height, width = cam.shape
        shadings = self._shade_sources(cam, scene, cam.rays().reshape(-1, 3), sources)
        values = {source: shading.values.copy() for source, shading in shadings.items()}
        if s > 1:
            # Pixel integration where it matters: a pixel integrates light over its area, which
            # differs from its centre's value only where something changes within it (an edge
            # in albedo, object, shadow or surface orientation). Those pixels get s² rays; the
            # smooth rest keeps one (a 19-px fringe loses 0.05 % of its contrast to that).
            # Each source's own edges: a shadow's edge is no edge of the ambient light.
            edges = {source: _edge_pixels(shading, height, width)
                     for source, shading in shadings.items()}
            rows, cols = np.nonzero(np.logical_or.reduce(list(edges.values())))
            offsets = pixel_samples(s * s)
            # In chunks of ~64 k rays: arrays that stay in cache run several times faster.
            chunk = max(1, 65536 // (s * s))
            for start in range(0, rows.size, chunk):
                r, c = rows[start:start + chunk], cols[start:start + chunk]
                subs = self._shade_sources(cam, scene, cam.rays_at_subpixels(r, c, offsets),
                                           sources)
                for source, sub in subs.items():
                    own = edges[source][r, c]
                    values[source][r[own] * width + c[own]] = (
                        sub.values.reshape(-1, s * s)[own].mean(axis=1))
        return {source: self._finish(camera_id, value) for source, value in values.items()}

    def expose(self, camera_id: str, components: Components, *, ambient_dn: float,
               projectors: Mapping[str, float], exposure_us: float, gain_db: float,
               rng: np.random.Generator) -> Image:
        """Turn light components into one noisy, quantised exposure.

        Shot noise is drawn as a Gaussian with the Poisson variance of the collected electrons
        (exact in mean and variance; indistinguishable from Poisson above a few tens of electrons,
        i.e. everywhere above 1 DN here) because it is several times faster than
        ``rng.poisson`` and the live simulator has a frame budget. For the same reason the
        standard normal deviates come from OpenCV's generator (``cv2.randn``, seeded from
        ``rng`` for each exposure, on the calling thread's own generator, so a seed still
        reproduces every image) and the arithmetic from OpenCV's vectorised operations:
        1.6 ms a 640×512 exposure against 4.2 ms with NumPy's generator and operations
        (measured on one core; the deviates alone 0.85 against 3.0 ms).
        """
        cfg = self.cameras[camera_id].config
        scale = exposure_us / self.room.lighting.exposure_ref_us
        signal_dn8: F32 = components.ambient * np.float32(ambient_dn * scale)
        for pid, intensity in projectors.items():
            if intensity > 0:
                signal_dn8 = _f32(cv2.scaleAdd(components.fringe[pid], float(intensity * scale),
                                               signal_dn8))
        max_dn = float(2**cfg.bit_depth - 1)
        dn_per_e = 10 ** (gain_db / 20) * max_dn / cfg.full_well_e
        read_noise = cfg.read_noise_dn * max_dn / 255.0
        electrons = signal_dn8 * np.float32(cfg.full_well_e / 255.0)
        np.minimum(electrons, np.float32(cfg.full_well_e), out=electrons)
        variance = _f32(cv2.scaleAdd(electrons, float(dn_per_e**2),
                                     np.full_like(electrons, read_noise**2)))
        noise = np.empty_like(electrons)
        cv2.setRNGSeed(int(rng.integers(2**31)))
        cv2.randn(noise, np.zeros(1), np.ones(1))
        image = _f32(cv2.scaleAdd(electrons, float(dn_per_e),
                                  _f32(cv2.multiply(_f32(cv2.sqrt(variance)), noise))))
        np.clip(np.rint(image, out=image), 0.0, max_dn, out=image)
        if cfg.bit_depth == 8:
            return image.astype(np.uint8)
        return image.astype(np.uint16)
