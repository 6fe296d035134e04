"""Scoring a reconstruction against the simulated scene's exact surface (tests, benches, CLI)."""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from eyeserver.core.types import F64
from eyeserver.hardware.sim.config import RoomConfig
from eyeserver.hardware.sim.room import SimRoom
from eyeserver.hardware.sim.scenes import build_scene
from eyeserver.hardware.sim.truth import truth_scene
from eyeserver.io import PointCloud


def score_cloud(truth: dict[str, Any], cloud: PointCloud, room: RoomConfig,
                camera_ids: list[str] | None = None) -> dict[str, Any]:
    """Distances of ``cloud`` to the exact surface of ``truth``'s scene, and coverage per camera.

    Coverage of a camera is its points over the pixels whose ray meets the scene (``share``:
    the most it could reconstruct, before shadows and masks) and over the pixels its unit's
    projector lights there (``lit_share``: the pixels that can show a fringe, from the truth,
    not from the pipeline's mask; issue 37's coverage goals count these). ``camera_ids`` maps
    the cloud's camera indices to ids (default: the room's cameras in order, as the rig file
    lists them).
    """
    built = build_scene(truth_scene(truth), float(truth.get("t_s", 0.0)))
    points = cloud.points.astype(np.float64)
    distance = built.scene.distance(points) if len(points) else np.zeros(0)
    sim = SimRoom(room)
    ids = camera_ids if camera_ids is not None else sim.camera_ids()
    coverage: dict[str, Any] = {}
    projector_of = {camera: projector for _, projector, cameras in sim.units()
                    for camera in cameras}
    if cloud.camera is not None:
        for index in np.unique(cloud.camera):
            camera_id = ids[int(index)]
            seen_pixels, lit_pixels = sim.renderer.seen_and_lit(camera_id, built.scene,
                                                                projector_of[camera_id])
            seen, lit = int(seen_pixels.sum()), int(lit_pixels.sum())
            count = int(np.sum(cloud.camera == index))
            coverage[camera_id] = {"points": count, "share": count / max(seen, 1),
                                   "lit_pixels": lit, "lit_share": count / max(lit, 1)}
    return {
        "scene": built.scene.labels[0] if built.scene.labels else "empty",
        "points": len(points),
        "median_mm": float(np.median(distance)) if len(points) else float("nan"),
        "rmse_mm": float(np.sqrt(np.mean(distance**2))) if len(points) else float("nan"),
        "beyond_1mm": float(np.mean(distance > 1.0)) if len(points) else float("nan"),
        "coverage": coverage,
    }


def nearest_surfaces(truth: dict[str, Any], points: npt.ArrayLike
                     ) -> tuple[npt.NDArray[np.str_], F64, list[str]]:
    """Each point's nearest labelled surface of ``truth``'s scene (``sclera``, ``lids``,
    ``plate``, …), its distance to it (mm), and the scene's labels in its own order: what a
    point of a reconstruction most likely shows, for scoring by surface."""
    built = build_scene(truth_scene(truth), float(truth.get("t_s", 0.0)))
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    per_surface = [(body, surface) for body in built.scene.bodies for surface in body.surfaces]
    names = np.array([surface.label for _, surface in per_surface])
    order = list(dict.fromkeys(names.tolist()))
    if not len(pts) or not per_surface:
        return np.zeros(len(pts), dtype=names.dtype), np.full(len(pts), np.inf), order
    table = np.stack([surface.distance(body.to_local(pts)) for body, surface in per_surface])
    nearest = np.argmin(table, axis=0)
    return (names[nearest], np.asarray(table[nearest, np.arange(len(pts))], dtype=np.float64),
            order)


def score_by_surface(truth: dict[str, Any], cloud: PointCloud) -> dict[str, Any]:
    """Points, median |distance| and RMSE per labelled surface of the scene (each point counted
    on the surface nearest to it, :func:`nearest_surfaces`): a phantom's own body and its base
    plate apart, so a large flat base cannot hide how the curved part fares."""
    if not len(cloud.points):
        return {}
    label_of, distance, labels = nearest_surfaces(truth, cloud.points)
    out: dict[str, Any] = {}
    for label in labels:
        d = distance[label_of == label]
        if not d.size:
            continue
        out[label] = {"points": int(d.size), "median_mm": float(np.median(d)),
                      "rmse_mm": float(np.sqrt(np.mean(d**2))),
                      "beyond_1mm": float(np.mean(d > 1.0))}
    return out
