"""How far two calibrations of one rig differ: the drift a physicist checks before trusting one.

Per camera: the rotation (degrees) and the shift of the camera centre (mm) between the two WCS
poses, the change of the intrinsics (focal lengths and principal point, pixels) and, when both
have phase-to-height models, the change of height: sample pixels across the image, at heights
over the calibrated volume, are turned into the phase calibration A expects there and back into
a height with calibration B; the differences |Z_B − Z_A| are summarised in millimetres.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from eyeserver.core.types import F64
from eyeserver.pipeline.geometry import undistorted_normalised
from eyeserver.pipeline.phase_height import PhaseHeightModel

__all__ = ["SAMPLE_GRID", "compare_calibrations"]


SAMPLE_GRID = 7
"""Sample pixels per image axis (inside a 10 % margin), and heights over the calibrated range."""


def _rotation_deg(r_a: F64, r_b: F64) -> float:
    # atan2 of sine and cosine, not acos of the cosine alone: acos loses half the digits near
    # zero, where drift is measured (rounding in the trace alone reads as micro-degrees).
    relative = r_b @ r_a.T
    sine = float(np.linalg.norm([relative[2, 1] - relative[1, 2], relative[0, 2] - relative[2, 0],
                                 relative[1, 0] - relative[0, 1]])) / 2.0
    cosine = (float(np.trace(relative)) - 1.0) / 2.0
    return math.degrees(math.atan2(sine, cosine))


def _height_change(cam_a: dict[str, Any], cam_b: dict[str, Any], p2h_a: dict[str, Any],
                   p2h_b: dict[str, Any], ref_a: F64 | None, ref_b: F64 | None,
                   ) -> dict[str, Any]:
    model_a = PhaseHeightModel.from_dict(p2h_a["model"])
    model_b = PhaseHeightModel.from_dict(p2h_b["model"])
    low = max(p2h_a["z_range_mm"][0], p2h_b["z_range_mm"][0])
    high = min(p2h_a["z_range_mm"][1], p2h_b["z_range_mm"][1])
    width, height = int(cam_a["width"]), int(cam_a["height"])
    us = np.linspace(0.1 * width, 0.9 * width, SAMPLE_GRID)
    vs = np.linspace(0.1 * height, 0.9 * height, SAMPLE_GRID)
    grid_u, grid_v = np.meshgrid(us, vs)
    u, v = grid_u.ravel(), grid_v.ravel()
    xa, ya = undistorted_normalised(u, v, cam_a["K"], cam_a["dist"])
    xb, yb = undistorted_normalised(u, v, cam_b["K"], cam_b["dist"])
    # Phases are relative to each calibration's reference image; a pixel's observed phase is
    # the same for both, so B's phase differs from A's by the change of the reference phase.
    shift = np.zeros_like(u)
    if ref_a is not None and ref_b is not None and ref_a.shape == ref_b.shape:
        iu, iv = u.astype(int), v.astype(int)
        shift = np.angle(np.exp(1j * (ref_a[iv, iu] - ref_b[iv, iu])))
    changes = []
    for z in np.linspace(low, high, SAMPLE_GRID):
        dphi_a = model_a.phase(xa, ya, np.full_like(xa, z))
        changes.append(model_b.height(xb, yb, dphi_a + shift) - z)
    difference = np.abs(np.concatenate(changes))
    return {"z_range_mm": [float(low), float(high)], "samples": int(difference.size),
            "median_abs_mm": float(np.median(difference)),
            "max_abs_mm": float(np.max(difference))}


def compare_calibrations(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
    """Compare two loaded calibrations (:func:`~eyeserver.calibration.artefact.
    load_calibration`) camera by camera; see the module docstring.

    Returns
    -------
    dict
        ``cameras``: per camera ``rotation_deg``, ``centre_shift_mm`` (vector and norm as
        ``centre_shift_norm_mm``), ``focal_change_px`` ([fx, fy]), ``principal_point_change_px``
        ([cx, cy]) and ``phase_to_height`` (None unless both have it); plus ``summary`` with
        the largest rotation, shift and height change.
    """
    cameras: dict[str, Any] = {}
    p2h_a = a.get("phase_to_height", {}).get("cameras", {})
    p2h_b = b.get("phase_to_height", {}).get("cameras", {})
    arrays_a, arrays_b = a.get("arrays", {}), b.get("arrays", {})
    for camera_id in sorted(set(a["cameras"]) & set(b["cameras"])):
        cam_a, cam_b = a["cameras"][camera_id], b["cameras"][camera_id]
        centre_a = -cam_a["R"].T @ cam_a["T"]
        centre_b = -cam_b["R"].T @ cam_b["T"]
        shift = centre_b - centre_a
        k_a, k_b = cam_a["K"], cam_b["K"]
        entry: dict[str, Any] = {
            "rotation_deg": _rotation_deg(cam_a["R"], cam_b["R"]),
            "centre_shift_mm": shift.tolist(),
            "centre_shift_norm_mm": float(np.linalg.norm(shift)),
            "focal_change_px": [float(k_b[0, 0] - k_a[0, 0]), float(k_b[1, 1] - k_a[1, 1])],
            "principal_point_change_px": [float(k_b[0, 2] - k_a[0, 2]),
                                          float(k_b[1, 2] - k_a[1, 2])],
            "phase_to_height": None,
        }
        if camera_id in p2h_a and camera_id in p2h_b:
            key = f"reference_phase_{camera_id}"
            entry["phase_to_height"] = _height_change(
                cam_a, cam_b, p2h_a[camera_id], p2h_b[camera_id],
                None if key not in arrays_a else np.asarray(arrays_a[key], np.float64),
                None if key not in arrays_b else np.asarray(arrays_b[key], np.float64))
        cameras[camera_id] = entry
    heights = [c["phase_to_height"]["max_abs_mm"] for c in cameras.values()
               if c["phase_to_height"] is not None]
    return {"cameras": cameras, "summary": {
        "max_rotation_deg": max((c["rotation_deg"] for c in cameras.values()), default=0.0),
        "max_centre_shift_mm": max((c["centre_shift_norm_mm"] for c in cameras.values()),
                                   default=0.0),
        "max_height_change_mm": max(heights) if heights else None}}
