"""The simulated treatment room: its devices' optics, the scene in front of them, the room lights.

:class:`SimRoom` is what the simulated drivers render through (``render``) and what tests, benches
and the simulated-rig API place scenes in (``set_scene``). Ground truth lives in
:mod:`eyeserver.hardware.sim.truth`, never here on the path the pipeline sees.
"""

from __future__ import annotations

import threading
from collections.abc import Iterable, Mapping, Sequence

import numpy as np
import numpy.typing as npt

from eyeserver.core.clock import Clock, MonotonicClock
from eyeserver.hardware.sim.config import RoomConfig, load_room
from eyeserver.hardware.sim.render import Components, Renderer
from eyeserver.hardware.sim.scenes import SceneSpec, build_scene


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
        self._lock = threading.Lock()

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
        """Replace the scene. A moving eye's script starts now (the clock's current time)."""
        with self._lock:
            self._scene = spec
            self._scene_epoch_ns = self.clock.now_ns()

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
        if camera_id not in self.renderer.cameras:
            raise KeyError(f"no camera {camera_id!r} in this room")
        render = self.config.render
        if spec.moving:
            built = build_scene(spec, scene_t)
            if render.supersample_moving == 1 and built.static is not None:
                return self.renderer.components_moving(camera_id, built, projectors)
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
        renders with it too) or a still scene's light components."""
        self.components(camera_id, self.clock.now_ns() / 1e9, projectors)

    def render(self, camera_id: str, *, t_s: float, projectors: Mapping[str, float],
               exposure_us: float, gain_db: float, rng: np.random.Generator,
               ) -> npt.NDArray[np.uint8] | npt.NDArray[np.uint16]:
        """One noisy exposure of ``camera_id`` at clock time ``t_s`` (seconds).

        ``projectors`` maps each lit projector to its relative intensity (0…1).
        """
        unknown = set(projectors) - set(self.renderer.projectors)
        if unknown:
            raise KeyError(f"no projector {sorted(unknown)} in this room")
        components = self.components(camera_id, t_s, [p for p, i in projectors.items() if i > 0])
        lighting = self.config.lighting
        ambient = lighting.room_light_dn if self._room_lights else lighting.ambient_dn
        return self.renderer.expose(camera_id, components, ambient_dn=ambient,
                                    projectors=projectors, exposure_us=exposure_us,
                                    gain_db=gain_db, rng=rng)
