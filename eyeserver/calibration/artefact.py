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
import zipfile
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from eyeserver.calibration.stereo import CameraCalibration, StereoResult
from eyeserver.errors import FormatError
from eyeserver.io import RigSpec, bundle_hash, fsync_dir, rig_from_dict
from eyeserver.io.atomic import atomic_write_bytes, atomic_write_text
from eyeserver.pipeline.phase_height import PhaseHeightModel

MAX_ARRAYS_BYTES = 1 << 30
"""The most ``arrays.npz`` may hold once unpacked, declared sizes summed (1 GiB; a rig's
reference phases take a few megabytes): a 7-MB upload of 2 GiB of zeros was loaded into
memory whole before (issue 35)."""

MAX_FOCAL_PX = 1e6
"""A camera's focal length beyond this many pixels is no lens (and K = 1e308 broke the
pipeline's arithmetic, issue 35)."""

MAX_TRANSLATION_MM = 1e5

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


def _no_constant(name: str) -> float:
    raise ValueError(f"{name} is not a number JSON allows")


def _camera(cam: dict[str, Any], source: Path, where: str) -> None:
    """Check one camera's intrinsics and pose in place (numpy arrays afterwards)."""
    K = cam["K"] = _matrix(cam.get("K"), (3, 3), source, f"{where}.K")
    R = cam["R"] = _matrix(cam.get("R"), (3, 3), source, f"{where}.R")
    T = cam["T"] = _matrix(cam.get("T"), (3,), source, f"{where}.T")
    try:
        dist = np.asarray(cam.get("dist"), dtype=np.float64)
    except (TypeError, ValueError):
        raise FormatError(source, f"{where}.dist", "must be an array of numbers") from None
    if dist.ndim != 1 or dist.size not in (4, 5, 8, 12, 14):
        raise FormatError(source, f"{where}.dist", "must be 4, 5, 8, 12 or 14 coefficients")
    if not np.all(np.isfinite(dist)) or np.any(np.abs(dist) > 1e4):
        raise FormatError(source, f"{where}.dist", "must be finite coefficients of a lens")
    cam["dist"] = dist
    if not (0 < K[0, 0] < MAX_FOCAL_PX and 0 < K[1, 1] < MAX_FOCAL_PX
            and np.allclose(K[2], (0.0, 0.0, 1.0)) and K[1, 0] == 0.0
            and abs(K[0, 2]) < MAX_FOCAL_PX and abs(K[1, 2]) < MAX_FOCAL_PX):
        raise FormatError(source, f"{where}.K", "is not a camera matrix (focal lengths "
                          f"positive and below {MAX_FOCAL_PX:g} px, last row 0 0 1)")
    if not (np.allclose(R @ R.T, np.eye(3), atol=1e-6)
            and math.isclose(float(np.linalg.det(R)), 1.0, abs_tol=1e-6)):
        raise FormatError(source, f"{where}.R", "is not a rotation")
    if float(np.linalg.norm(T)) > MAX_TRANSLATION_MM:
        raise FormatError(source, f"{where}.T", f"lies beyond {MAX_TRANSLATION_MM:g} mm")


def _phase_to_height(document: dict[str, Any], rig: RigSpec, source: Path) -> None:
    """Check the phase-to-height section, where there is one."""
    section = document.get("phase_to_height")
    if section is None:
        return
    cameras = section.get("cameras") if isinstance(section, dict) else None
    if not isinstance(cameras, dict) or set(cameras) != set(rig.camera_ids):
        raise FormatError(source, "phase_to_height.cameras", "must hold every camera of the rig")
    for camera_id, entry in cameras.items():
        where = f"phase_to_height.cameras.{camera_id}"
        if not isinstance(entry, dict):
            raise FormatError(source, where, "must be an object")
        _matrix(entry.get("carrier_cycles_per_px"), (2,), source, f"{where}.carrier_cycles_per_px")
        _matrix(entry.get("z_range_mm"), (2,), source, f"{where}.z_range_mm")
        try:
            PhaseHeightModel.from_dict(entry.get("model") or {})
        except (TypeError, ValueError) as exc:
            raise FormatError(source, f"{where}.model", str(exc)) from None


def _arrays(path: Path, rig: RigSpec, max_bytes: int) -> dict[str, np.ndarray]:
    """``arrays.npz``'s arrays, their sizes checked from the archive's headers before any is
    loaded; each camera's reference phase must be finite and of its image's shape."""
    try:
        with zipfile.ZipFile(path) as archive:
            declared = 0
            for info in archive.infolist():
                with archive.open(info) as member:
                    version = np.lib.format.read_magic(member)
                    shape, _, dtype = (np.lib.format.read_array_header_1_0(member)
                                       if version == (1, 0)
                                       else np.lib.format.read_array_header_2_0(member))
                # The larger of what the zip and the array's header declare.
                declared += max(info.file_size,
                                int(np.prod(shape, dtype=np.int64)) * dtype.itemsize)
                if declared > max_bytes or dtype.hasobject:
                    raise FormatError(path, info.filename, "declares more data than a "
                                      f"calibration holds (over {max_bytes >> 20} MiB) or "
                                      "Python objects")
        with np.load(path, allow_pickle=False) as stored:
            arrays = {name: stored[name] for name in stored.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise FormatError(path, None, f"unreadable arrays ({exc})") from exc
    sizes = {c.id: (c.height, c.width) for c in rig.cameras}
    for name, array in arrays.items():
        if name.startswith("reference_phase_"):
            camera_id = name.removeprefix("reference_phase_")
            if camera_id in sizes and (array.shape != sizes[camera_id]
                                       or array.dtype.kind != "f"
                                       or not np.all(np.isfinite(array))):
                raise FormatError(path, name, f"must be {sizes[camera_id]} finite numbers "
                                  "(the camera's image)")
    return arrays


def load_calibration(directory: str | Path, rig: RigSpec | None = None, *,
                     max_arrays_bytes: int = MAX_ARRAYS_BYTES) -> dict[str, Any]:
    """Read and check a calibration directory; with ``rig``, refuse one made for another rig.

    Every number is checked before anything is used: finite (JSON's NaN and Infinity are
    refused), of its shape, and physically possible (a camera matrix, a rotation, a lens's
    distortion, a finite phase-to-height model, reference phases of each camera's image size);
    ``arrays.npz`` by the sizes its members declare, at most ``max_arrays_bytes`` in all,
    before any is loaded.

    Returns the document with each camera's ``K``, ``dist``, ``R``, ``T`` as numpy arrays.

    Raises
    ------
    FormatError
        Naming the file and the field.
    """
    source = Path(directory) / CALIBRATION_FILE
    try:
        document = json.loads(source.read_text(encoding="utf-8"), parse_constant=_no_constant)
    except OSError as exc:
        raise FormatError(source, None, f"cannot read ({exc.strerror})") from exc
    except ValueError as exc:
        raise FormatError(source, None, f"not valid JSON: {exc}") from exc
    except RecursionError:
        raise FormatError(source, None, "not a calibration: nested too deep") from None
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
        if not isinstance(cam, dict):
            raise FormatError(source, f"cameras.{cid}", "must be an object")
        _camera(cam, source, f"cameras.{cid}")
    _phase_to_height(document, stored_rig, source)
    arrays_path = Path(directory) / ARRAYS_FILE
    document["arrays"] = (_arrays(arrays_path, stored_rig, max_arrays_bytes)
                          if arrays_path.exists() else {})
    return document
