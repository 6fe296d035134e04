"""The simulated treatment room: its devices' optics, the scene in front of them, the room lights.

:class:`SimRoom` is what the simulated drivers render through (``render``) and what tests, benches
and the simulated-rig API place scenes in (``set_scene``). Ground truth lives in
:mod:`eyeserver.hardware.sim.truth`, never here on the path the pipeline sees.

A moving scene can be rendered ahead (:meth:`SimRoom.prerender`): a camera's exposures at the
times a stream will take them, kept until a frame asks for one. Real cameras cost the host no
CPU; the simulated ones render on the host's cores, beside the pipeline they feed. A stream of
pre-rendered frames measures what the daemon itself adds (``eyeserver bench tracking
--prerendered``).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Iterable, Mapping, Sequence

import numpy as np

from eyeserver.core.clock import Clock, MonotonicClock
from eyeserver.core.types import Image
from eyeserver.hardware.sim.config import RoomConfig, load_room
from eyeserver.hardware.sim.motion import EyeMotion
from eyeserver.hardware.sim.render import Components, Renderer
from eyeserver.hardware.sim.scenes import SceneSpec, build_scene

_RecordKey = tuple[int, tuple[tuple[str, float], ...], float, float]


def _record_key(offset_us: int, projectors: Mapping[str, float], exposure_us: float,
                gain_db: float) -> _RecordKey:
    """What a pre-rendered exposure must match: its scene time (µs), lit projectors and
    intensities, exposure and gain."""
    return (offset_us, tuple(sorted(projectors.items())), float(exposure_us), float(gain_db))


class _Recording:
    """A camera's exposures of one scene rendered ahead, in time order, and what became of the
    frames asked for since."""

    def __init__(self, spec: SceneSpec, room_lights: bool) -> None:
        self.spec = spec
        self.room_lights = room_lights
        self.frames: dict[_RecordKey, Image] = {}
        self.used = 0
        self.live = 0

    def take(self, key: _RecordKey) -> Image | None:
        """The exposure for ``key``, forgetting it and any earlier one (a stream never goes
        back); None when there is none."""
        image = self.frames.pop(key, None)
        while self.frames:
            first = next(iter(self.frames))
            if first[0] >= key[0]:
                break
            del self.frames[first]
        if image is None:
            self.live += 1
        else:
            self.used += 1
        return image


PREPARED_SHIFTS = 2
"""Scripted head shifts whose end positions :meth:`SimRoom.prepare` casts ahead (each one
static part per camera, kept among
:data:`~eyeserver.hardware.sim.render.STATIC_PARTS_PER_CAMERA`)."""

TRANSIT_PROBE_S = 1e-3
"""How far apart two moments are compared to tell a head in transit (seconds)."""


def _head_in_transit(spec: SceneSpec, scene_t: float) -> bool:
    """Whether the head moves at scene time ``scene_t`` (a scripted shift under way)."""
    if spec.eye is None or spec.eye.motion is None:
        return False
    motion = EyeMotion(spec.eye.motion)
    return (motion.state(scene_t).head_offset_mm
            != motion.state(scene_t + TRANSIT_PROBE_S).head_offset_mm)


BEFORE_CHANGE_S = 0.2
"""How long before a scene change an exposure may be timed and still see the scene before it
(seconds): a few frames at 25 Hz, for the cameras of a pulse fired just before the change. A
time further back is a caller's "the scene as it is" (renders at t = 0), not a frame in flight."""


class SimRoom:
    """A room described by a :class:`RoomConfig`, with one scene at a time."""

    def __init__(self, config: RoomConfig | None = None, clock: Clock | None = None) -> None:
        self.config = config if config is not None else load_room(None)
        self.clock: Clock = clock if clock is not None else MonotonicClock()
        self.seed = self.config.seed
        self.renderer = Renderer(self.config)
        self._scene = SceneSpec()
        self._room_lights = False
        self._scene_epoch_ns = 0
        # The scene before the last change and its epoch: exposures timed before the change
        # still see it (render), so that the cameras of one trigger pulse never see two scenes.
        self._before: tuple[SceneSpec, int] | None = None
        self._lock = threading.Lock()
        self._recordings: dict[str, _Recording] = {}

    # --- the rig as the drivers see it -----------------------------------------------------

    def camera_ids(self) -> list[str]:
        """Camera ids in unit order."""
        return [c.id for c in self.config.cameras()]

    def projector_ids(self) -> list[str]:
        """Projector ids in unit order."""
        return [p.id for p in self.config.projectors()]

    def units(self) -> list[tuple[str, str, list[str]]]:
        """``(unit id, projector id, camera ids)`` for every unit."""
        return [(u.id, u.projector.id, [c.id for c in u.cameras]) for u in self.config.units]

    def camera_format(self, camera_id: str) -> tuple[int, int, int]:
        """``(width, height, bit_depth)`` of a camera."""
        cfg = self.renderer.cameras[camera_id].config
        return cfg.width, cfg.height, cfg.bit_depth

    # --- what stands in the room ----------------------------------------------------------

    @property
    def scene(self) -> SceneSpec:
        """The scene in front of the cameras."""
        return self._scene

    def set_scene(self, spec: SceneSpec) -> None:
        """Replace the scene. A moving eye's script starts now (the clock's current time);
        an exposure timed up to :data:`BEFORE_CHANGE_S` before now (a trigger pulse fired
        before the change, one of whose cameras is read after it) is still rendered with the
        scene it was taken of. Earlier times see the new scene at its start, as before."""
        with self._lock:
            self._before = (self._scene, self._scene_epoch_ns)
            self._scene = spec
            self._scene_epoch_ns = self.clock.now_ns()
            self._recordings.clear()

    def scene_time(self, t_s: float) -> float:
        """Seconds since the scene was set, for a clock time ``t_s``."""
        return max(0.0, t_s - self._scene_epoch_ns / 1e9)

    @property
    def room_lights(self) -> bool:
        """Whether the room lights are on (chessboards are filmed under them)."""
        return self._room_lights

    def set_room_lights(self, on: bool) -> None:
        """Switch the room lights."""
        self._room_lights = bool(on)

    # --- rendering -------------------------------------------------------------------------

    def components(self, camera_id: str, t_s: float = 0.0, projectors: Iterable[str] = (),
                   ) -> Components:
        """Noise-free light components of a camera at clock time ``t_s``.

        ``projectors`` names the projector components wanted besides the ambient one.
        """
        with self._lock:
            spec = self._scene
            scene_t = self.scene_time(t_s)
        return self._components(camera_id, spec, scene_t, projectors)

    def _components(self, camera_id: str, spec: SceneSpec, scene_t: float,
                    projectors: Iterable[str]) -> Components:
        if camera_id not in self.renderer.cameras:
            raise KeyError(f"no camera {camera_id!r} in this room")
        render = self.config.render
        if spec.moving:
            built = build_scene(spec, scene_t)
            if render.supersample_moving == 1 and built.static is not None:
                return self.renderer.components_moving(
                    camera_id, built, projectors, keep=not _head_in_transit(spec, scene_t))
            return self.renderer.components(camera_id, built.scene, render.supersample_moving,
                                            projectors)
        built = build_scene(spec, 0.0)
        supersample = (render.supersample_chessboard if spec.kind == "chessboard"
                       else render.supersample)
        return self.renderer.components(camera_id, built.scene, supersample, projectors,
                                        cache_key=spec.model_dump_json())

    def prepare(self, camera_id: str, projectors: Sequence[str]) -> None:
        """Fill the render caches for ``camera_id`` lit by ``projectors`` with the scene in
        front of it now: a moving scene's static part (cast whole, ≈ 1 s a camera; a blink
        renders with it too) or a still scene's light components; and the static parts where
        the next :data:`PREPARED_SHIFTS` head shifts of the script end, so that the frames
        after a shift do not wait for that cast (live tracking had no frame for seconds after
        a scripted 1-mm shift, issue 35)."""
        now = self.clock.now_ns() / 1e9
        self.components(camera_id, now, projectors)
        with self._lock:
            spec, scene_t = self._scene, self.scene_time(now)
        if spec.moving and spec.eye is not None and spec.eye.motion is not None:
            ends = sorted(e.t_s + e.duration_s for e in spec.eye.motion.script
                          if e.kind == "shift" and e.t_s + e.duration_s > scene_t)
            for end in ends[:PREPARED_SHIFTS]:
                self._components(camera_id, spec, end, projectors)

    def render(self, camera_id: str, *, t_s: float, projectors: Mapping[str, float],
               exposure_us: float, gain_db: float, rng: np.random.Generator) -> Image:
        """One noisy exposure of ``camera_id`` at clock time ``t_s`` (seconds).

        ``projectors`` maps each lit projector to its relative intensity (0…1). An exposure
        rendered ahead for this moment and these settings (:meth:`prerender`) is taken instead
        (``rng`` is then not drawn from).
        """
        unknown = set(projectors) - set(self.renderer.projectors)
        if unknown:
            raise KeyError(f"no projector {sorted(unknown)} in this room")
        with self._lock:
            spec, epoch_ns = self._scene, self._scene_epoch_ns
            if (self._before is not None
                    and epoch_ns - BEFORE_CHANGE_S * 1e9 <= t_s * 1e9 < epoch_ns):
                spec, epoch_ns = self._before
            recording = self._recordings.get(camera_id)
            if (recording is not None and recording.spec is spec
                    and recording.room_lights == self._room_lights):
                offset_us = round((t_s * 1e9 - epoch_ns) / 1e3)
                image = recording.take(_record_key(offset_us, projectors, exposure_us, gain_db))
                if image is not None:
                    return image
        return self._expose(camera_id, spec, max(0.0, t_s - epoch_ns / 1e9), projectors,
                            exposure_us, gain_db, rng)

    def _expose(self, camera_id: str, spec: SceneSpec, scene_t: float,
                projectors: Mapping[str, float], exposure_us: float, gain_db: float,
                rng: np.random.Generator) -> Image:
        lit = [p for p, i in projectors.items() if i > 0]
        motion = spec.eye.motion if spec.moving else None
        times = ((scene_t,) if motion is None
                 else EyeMotion(motion).sub_exposures(scene_t, exposure_us / 1e6))
        components = self._components(camera_id, spec, max(0.0, times[0]), lit)
        if len(times) > 1:
            # Motion blur: the exposure integrates the light of every moment of it.
            parts = [components] + [self._components(camera_id, spec, max(0.0, t), lit)
                                    for t in times[1:]]
            components = Components(
                ambient=np.mean([c.ambient for c in parts], axis=0, dtype=np.float32),
                fringe={p: np.mean([c.fringe[p] for c in parts], axis=0, dtype=np.float32)
                        for p in components.fringe})
        lighting = self.config.lighting
        ambient = lighting.room_light_dn if self._room_lights else lighting.ambient_dn
        return self.renderer.expose(camera_id, components, ambient_dn=ambient,
                                    projectors=projectors, exposure_us=exposure_us,
                                    gain_db=gain_db, rng=rng)

    # --- rendering ahead -------------------------------------------------------------------

    def prerender(self, camera_id: str, *, seconds: float, rate_hz: float,
                  projectors: Mapping[str, float], exposure_us: float, gain_db: float,
                  rng: np.random.Generator, progress: Callable[[float], None] | None = None,
                  ) -> SceneSpec:
        """Render ``camera_id``'s exposures of the scene in front of it now, ahead, for the
        first ``seconds`` of its script: one at every ``1 / rate_hz`` from the script's start
        (pulses at whole periods after it, mid-exposure half ``exposure_us`` later), with these
        settings and noise from ``rng``. They replace the camera's earlier ones and are kept
        until a frame of the same scene asks for one (:meth:`render`) or the scene changes.

        Frames are taken by scene time: :meth:`restart_scene` restarts the script at a moment
        when the stream's pulses will fall at those times. ``progress`` gets the share done
        (0–1) every few percent. Returns the scene rendered. A moving scene only: a still one
        is rendered once and reused anyway.

        Raises
        ------
        ValueError
            The scene does not move, or ``seconds`` or ``rate_hz`` is not positive.
        """
        if not (seconds > 0 and rate_hz > 0):
            raise ValueError(f"seconds and rate_hz must be positive, not {seconds}, {rate_hz}")
        with self._lock:
            spec = self._scene
        if not spec.moving:
            raise ValueError(f"the scene ({spec.kind}) does not move: nothing to render ahead")
        period_us = round(1e6 / rate_hz)
        count = math.ceil(seconds * rate_hz)
        recording = _Recording(spec, self._room_lights)
        for k in range(count):
            offset_us = k * period_us + round(exposure_us / 2)
            recording.frames[_record_key(offset_us, projectors, exposure_us, gain_db)] = \
                self._expose(camera_id, spec, offset_us / 1e6, projectors, exposure_us,
                             gain_db, rng)
            if progress is not None and (k + 1) % max(1, count // 20) == 0:
                progress((k + 1) / count)
        with self._lock:
            if self._scene is spec:
                self._recordings[camera_id] = recording
        return spec

    def restart_scene(self, spec: SceneSpec, epoch_ns: int) -> bool:
        """Restart ``spec``'s script at clock time ``epoch_ns``, keeping what was rendered
        ahead of it; False (nothing changed) when the scene in front of the cameras is no
        longer ``spec``."""
        with self._lock:
            if self._scene is not spec:
                return False
            self._scene_epoch_ns = int(epoch_ns)
            return True

    def prerendered(self) -> dict[str, dict[str, int]]:
        """Per camera with exposures rendered ahead of the current scene: ``left`` (not yet
        asked for), ``used`` (frames that took one) and ``live`` (frames rendered at once,
        none matching)."""
        with self._lock:
            return {camera_id: {"left": len(r.frames), "used": r.used, "live": r.live}
                    for camera_id, r in self._recordings.items() if r.spec is self._scene}
