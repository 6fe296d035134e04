"""Ground truth of the simulated room, for tests, benches and demonstrations only.

Nothing on the measurement path (``eyeserver.pipeline``, ``eyeserver.calibration``) may import this
module or use what it returns; import-linter checks that in CI. What it offers: the exact scene
(surfaces, fiducial centres, the eye's pose at a time) and the exact optics of every device.
"""

from __future__ import annotations

from typing import Any

from eyeserver.hardware.sim.room import SimRoom
from eyeserver.hardware.sim.scenes import SceneSpec, build_scene, scene_truth


def device_truth(room: SimRoom) -> dict[str, Any]:
    """True intrinsics, distortion and ``[R|T]`` of every camera, and every projector's pose."""
    cameras = {
        cid: {"K": cam.K.tolist(), "dist": cam.dist.tolist(), "R": cam.R.tolist(),
              "T": cam.T.tolist(), "centre_mm": cam.centre.tolist(),
              "width": cam.config.width, "height": cam.config.height}
        for cid, cam in room.renderer.cameras.items()
    }
    projectors = {
        pid: {"R": proj.R.tolist(), "centre_mm": proj.centre.tolist(),
              "period_mm": proj.config.period_mm,
              "period_normalised": proj.period_normalised}
        for pid, proj in room.renderer.projectors.items()
    }
    return {"cameras": cameras, "projectors": projectors}


def room_truth(room: SimRoom, t_s: float | None = None) -> dict[str, Any]:
    """The scene's truth at clock time ``t_s`` (default: now), plus the devices' optics."""
    if t_s is None:
        t_s = room.clock.now_ns() / 1e9
    truth = scene_truth(room.scene, room.scene_time(t_s))
    truth["devices"] = device_truth(room)
    return truth


def truth_scene(truth: dict[str, Any]) -> SceneSpec:
    """The :class:`SceneSpec` stored in a truth document (e.g. a bundle's ``truth.json``)."""
    return SceneSpec.model_validate(truth["scene"])


__all__ = ["build_scene", "device_truth", "room_truth", "scene_truth", "truth_scene"]
