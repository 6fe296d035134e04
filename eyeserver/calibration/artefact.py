"""The calibration artefact: a directory that holds everything the pipeline needs, with provenance.

::

    CALDIR/
      calibration.json    format, version, creation time, the rig, input bundles and their
                          hashes, each camera's K, distortion, R, T and quality figures, and
                          (after ``calibrate p2h``) each camera's carrier and phase-to-height
                          model with its residuals, and each unit's fringe-order margin
      arrays.npz          per-pixel maps (each camera's reference phase)

Loading validates the file and refuses a calibration made for another rig. Later stages (the
phase-to-height fit) add their own keys; the format string carries a version.
"""

from __future__ import annotations

import io
import json
import math
import os
import shutil
import tempfile
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from eyeserver.calibration.stereo import CameraCalibration, StereoResult
from eyeserver.errors import FormatError
from eyeserver.io import RigSpec, bundle_hash, fsync_dir, rig_from_dict
from eyeserver.io.atomic import atomic_write_bytes, atomic_write_text

CALIBRATION_FORMAT = "eyeserver.calibration/1"
CALIBRATION_FILE = "calibration.json"
ARRAYS_FILE = "arrays.npz"


def _camera_document(cam: CameraCalibration) -> dict[str, Any]:
    return {"width": cam.width, "height": cam.height, "K": cam.K.tolist(),
            "dist": cam.dist.tolist(), "R": cam.R.tolist(), "T": cam.T.tolist(),
            "centre_mm": cam.centre.tolist(), "boards": cam.boards_used,
            "quality": cam.quality()}


def stereo_document(result: StereoResult) -> dict[str, Any]:
    """The calibration document of a stereo calibration."""
    errors = np.concatenate([c.reprojection_px for c in result.cameras.values()])
    q1, median, q3 = np.percentile(errors, [25, 50, 75])
    return {
        "format": CALIBRATION_FORMAT,
        "version": 1,
        "created": datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "rig": result.rig.to_dict(),
        "inputs": {"stereo": [{"bundle": p.name, "sha256": bundle_hash(p)}
                              for p in result.inputs]},
        "cameras": {cid: _camera_document(c) for cid, c in result.cameras.items()},
        "quality": {"reprojection_median_px": float(median),
                    "reprojection_iqr_px": float(q3 - q1),
                    "boards_missed": result.missed},
    }


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    return value


def write_calibration(directory: str | Path, document: dict[str, Any],
                      arrays: dict[str, npt.NDArray[np.float32]] | None = None,
                      overwrite: bool = False) -> Path:
    """Write a calibration directory atomically (staged beside it, then renamed into place)."""
    target = Path(directory)
    if target.exists() and any(target.iterdir()) and not overwrite:
        raise FileExistsError(str(target))
    target.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{target.name}.", dir=target.parent))
    try:
        atomic_write_text(staging / CALIBRATION_FILE,
                          json.dumps(_jsonable(document), indent=1) + "\n")
        if arrays:
            buffer = io.BytesIO()
            np.savez_compressed(buffer, **arrays)  # type: ignore[arg-type]
            atomic_write_bytes(staging / ARRAYS_FILE, buffer.getvalue())
        if target.exists():
            # Replace the old directory with two renames, never leaving half of either.
            retired = Path(tempfile.mkdtemp(prefix=f".{target.name}.old.", dir=target.parent))
            os.replace(target, retired / target.name)
            os.replace(staging, target)
            shutil.rmtree(retired, ignore_errors=True)
        else:
            os.replace(staging, target)
        fsync_dir(target.parent)
    finally:
        if staging.exists():
            shutil.rmtree(staging, ignore_errors=True)
    return target


def _matrix(value: object, shape: tuple[int, ...], source: Path, field: str) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise FormatError(source, field, "must be an array of numbers") from None
    if array.shape != shape or not np.all(np.isfinite(array)):
        raise FormatError(source, field, f"must be {shape} finite numbers")
    return array


def load_calibration(directory: str | Path, rig: RigSpec | None = None) -> dict[str, Any]:
    """Read and check a calibration directory; with ``rig``, refuse one made for another rig.

    Returns the document with each camera's ``K``, ``dist``, ``R``, ``T`` as numpy arrays.
    """
    source = Path(directory) / CALIBRATION_FILE
    try:
        document = json.loads(source.read_text(encoding="utf-8"))
    except OSError as exc:
        raise FormatError(source, None, f"cannot read ({exc.strerror})") from exc
    except ValueError as exc:
        raise FormatError(source, None, f"not valid JSON: {exc}") from exc
    if not isinstance(document, dict) or document.get("format") != CALIBRATION_FORMAT:
        raise FormatError(source, "format", f"must be '{CALIBRATION_FORMAT}'")
    stored_rig = rig_from_dict(document.get("rig"), source, field_prefix="rig")
    if rig is not None and stored_rig.to_dict() != rig.to_dict():
        raise FormatError(source, "rig", "this calibration was made for another rig "
                          f"(cameras {', '.join(stored_rig.camera_ids)}; the rig has "
                          f"{', '.join(rig.camera_ids)})")
    cameras = document.get("cameras")
    if not isinstance(cameras, dict) or set(cameras) != set(stored_rig.camera_ids):
        raise FormatError(source, "cameras", "must hold every camera of the rig")
    for cid, cam in cameras.items():
        where = f"cameras.{cid}"
        if not isinstance(cam, dict):
            raise FormatError(source, where, "must be an object")
        cam["K"] = _matrix(cam.get("K"), (3, 3), source, f"{where}.K")
        cam["R"] = _matrix(cam.get("R"), (3, 3), source, f"{where}.R")
        cam["T"] = _matrix(cam.get("T"), (3,), source, f"{where}.T")
        dist = np.asarray(cam.get("dist"), dtype=np.float64)
        if dist.ndim != 1 or dist.size not in (4, 5, 8, 12, 14):
            raise FormatError(source, f"{where}.dist", "must be 4, 5, 8, 12 or 14 coefficients")
        cam["dist"] = dist
        if not math.isclose(abs(float(np.linalg.det(cam["R"]))), 1.0, abs_tol=1e-6):
            raise FormatError(source, f"{where}.R", "is not a rotation")
    arrays_path = Path(directory) / ARRAYS_FILE
    document["arrays"] = {}
    if arrays_path.exists():
        try:
            with np.load(arrays_path) as stored:
                document["arrays"] = {name: stored[name] for name in stored.files}
        except (OSError, ValueError) as exc:
            raise FormatError(arrays_path, None, f"unreadable arrays ({exc})") from exc
    return document
