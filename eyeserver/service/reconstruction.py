"""Reconstruct a capture bundle with a calibration: the glue between files and the pipeline."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from eyeserver.calibration.artefact import load_calibration
from eyeserver.errors import EyeserverError
from eyeserver.io import PointCloud, read_bundle
from eyeserver.pipeline.demodulate import Carrier
from eyeserver.pipeline.phase_height import PhaseHeightModel
from eyeserver.pipeline.reconstruct import CalibratedCamera, unit_clouds

Progress = Callable[[str], None]


class ReconstructionError(EyeserverError):
    """A bundle cannot be reconstructed with the calibration given."""


def _quiet(_: str) -> None:
    pass


def calibrated_cameras(document: dict[str, Any]) -> dict[str, CalibratedCamera]:
    """The pipeline's view of every camera of a loaded calibration."""
    section = document.get("phase_to_height")
    if not section:
        raise ReconstructionError("the calibration has no phase-to-height models yet "
                                  "(run 'eyeserver calibrate p2h')")
    cameras = {}
    for camera_id, cam in document["cameras"].items():
        p2h = section["cameras"][camera_id]
        reference = document["arrays"].get(f"reference_phase_{camera_id}")
        if reference is None:
            raise ReconstructionError(f"the calibration lacks camera {camera_id}'s reference "
                                      "phase (arrays.npz)")
        carrier = Carrier(tuple(p2h["carrier_cycles_per_px"]))
        cameras[camera_id] = CalibratedCamera(
            camera_id=camera_id, K=cam["K"], dist=cam["dist"], R=cam["R"], T=cam["T"],
            model=PhaseHeightModel.from_dict(p2h["model"]), carrier=carrier,
            reference_phase=reference, border_px=math.ceil(carrier.period_px))
    return cameras


def reconstruct_bundle(calibration: str | Path, bundle_path: str | Path, *,
                       frames: Sequence[int] | None = None, cameras: Sequence[str] | None = None,
                       progress: Progress = _quiet) -> tuple[PointCloud, dict[str, Any]]:
    """The fused point cloud of a measurement bundle, and a summary per camera.

    ``frames`` and ``cameras`` restrict the views used (default: every fringe image). A camera's
    fringe order is fixed with its unit's other camera in the same frame, which must be there.
    """
    bundle = read_bundle(bundle_path)
    document = load_calibration(calibration, bundle.rig)
    calibrated = calibrated_cameras(document)
    rig = bundle.rig
    chosen_frames = set(frames) if frames is not None else set(bundle.frame_indices)
    unknown_frames = chosen_frames - set(bundle.frame_indices)
    if unknown_frames:
        raise ReconstructionError(f"{bundle.path}: no frame {sorted(unknown_frames)}")
    chosen_cameras = set(cameras) if cameras is not None else set(rig.camera_ids)
    unknown = chosen_cameras - set(rig.camera_ids)
    if unknown:
        raise ReconstructionError(f"{bundle.path}: no camera {sorted(unknown)} in the rig")
    z_range = tuple(document["phase_to_height"]["cameras"][rig.camera_ids[0]]["z_range_mm"])
    points, quality, camera_index = [], [], []
    summary: dict[str, Any] = {"cameras": {}}
    views = [(i, c) for i, c in bundle.fringe_images()
             if i in chosen_frames and c in chosen_cameras]
    if not views:
        raise ReconstructionError(f"{bundle.path}: no fringe image among the chosen frames and "
                                  "cameras (a camera's image counts only when its own unit's "
                                  "projector is lit)")
    done: dict[tuple[int, str], Any] = {}
    for index, camera_id in views:
        unit = rig.unit_of_camera(camera_id)
        partners = [c for c in unit.cameras if c != camera_id
                    and c in bundle.frame(index).images]
        if not partners:
            raise ReconstructionError(f"{bundle.path}: frame {index} has no other camera of "
                                      f"unit {unit.id} to fix camera {camera_id}'s fringe order")
        partner = partners[0]
        if (index, camera_id) not in done:
            progress(f"frame {index}: cameras {camera_id} and {partner} of unit {unit.id}")
            cloud_a, cloud_b = unit_clouds(
                calibrated[camera_id], bundle.load_image(index, camera_id),
                calibrated[partner], bundle.load_image(index, partner),
                (float(z_range[0]), float(z_range[1])))
            done[(index, camera_id)] = (cloud_a, partner)
            done[(index, partner)] = (cloud_b, camera_id)
        cloud, partner = done[(index, camera_id)]
        points.append(cloud.points)
        quality.append(cloud.quality)
        camera_index.append(np.full(len(cloud.points), rig.camera_index(camera_id), np.uint8))
        summary["cameras"][camera_id] = {"frame": index, "points": len(cloud.points),
                                         "fringe_order": cloud.method, "partner": partner}
    fused = PointCloud(np.concatenate(points).astype(np.float32),
                       np.concatenate(quality).astype(np.float32),
                       np.concatenate(camera_index))
    summary["points"] = len(fused)
    if len(fused):
        summary["extent_mm"] = {"min": fused.points.min(axis=0).tolist(),
                                "max": fused.points.max(axis=0).tolist()}
    return fused, summary
