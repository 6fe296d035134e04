"""Stereo (geometric) calibration from chessboard bundles (docs/design.md §5, FORMATS.md).

Every camera's intrinsics and lens distortion come from all the boards it saw; its pose ``[R|T]``
(WCS → camera) from the origin board, whose inner-corner grid defines the WCS (FORMATS.md). A board
a camera cannot see is reported, not fatal, as long as the camera saw enough boards and the
origin board.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from eyeserver.calibration.chessboard import board_points, detect_chessboard
from eyeserver.core.types import F64, Progress, quiet
from eyeserver.errors import EyeserverError
from eyeserver.io import Bundle, RigSpec, read_bundle

MIN_BOARDS = 4
"""Boards a camera must see for its intrinsics to be determined (OpenCV needs ≥ 3 views for
five distortion coefficients; one more keeps the fit from being exactly determined)."""


class CalibrationError(EyeserverError):
    """A calibration cannot be computed from the inputs given."""


@dataclass
class CameraCalibration:
    """One camera's calibrated pinhole model (OpenCV conventions, millimetres)."""

    camera_id: str
    width: int
    height: int
    K: F64
    dist: F64
    R: F64
    T: F64
    reprojection_px: F64 = field(repr=False)
    """Per-corner reprojection errors over every board the camera saw (pixels)."""
    boards_used: list[str] = field(default_factory=list)

    @property
    def centre(self) -> F64:
        """Camera centre in the WCS, ``C = −Rᵀ T``."""
        return np.asarray(-self.R.T @ self.T, dtype=np.float64)

    def quality(self) -> dict[str, float | int]:
        """Median and IQR of the reprojection error, and how many boards and corners."""
        err = self.reprojection_px
        q1, median, q3 = np.percentile(err, [25, 50, 75])
        return {"reprojection_median_px": float(median), "reprojection_iqr_px": float(q3 - q1),
                "reprojection_max_px": float(err.max()), "boards": len(self.boards_used),
                "corners": int(err.size)}


@dataclass
class StereoResult:
    """All cameras' calibrations plus what was seen where."""

    rig: RigSpec
    cameras: dict[str, CameraCalibration]
    missed: dict[str, list[str]]
    """Per board (bundle name), the cameras that did not find it."""
    inputs: list[Path]


def _board_observations(bundles: Sequence[Bundle], rig: RigSpec, progress: Progress,
                        ) -> tuple[dict[str, list[tuple[str, F64, F64]]], dict[str, list[str]],
                                   str]:
    """Per camera, ``(board name, object points, image points)`` of every board it found."""
    seen: dict[str, list[tuple[str, F64, F64]]] = {cid: [] for cid in rig.camera_ids}
    missed: dict[str, list[str]] = {}
    origin_name = ""
    for n, bundle in enumerate(bundles):
        name = bundle.path.name
        board = bundle.chessboard
        if bundle.kind != "chessboard" or board is None:
            raise CalibrationError(f"{bundle.path}: a stereo calibration takes chessboard "
                                   f"bundles, not '{bundle.kind}'")
        if board.origin:
            if origin_name:
                raise CalibrationError(f"{bundle.path}: a second origin board (the first was "
                                       f"{origin_name}); exactly one bundle defines the WCS")
            origin_name = name
        progress(f"detecting corners in {name} ({n + 1}/{len(bundles)})")
        objects = board_points(board.cols, board.rows, board.square_mm)
        frame = bundle.frames[0]
        for camera_id in rig.camera_ids:
            if camera_id not in frame.images:
                missed.setdefault(name, []).append(camera_id)
                continue
            corners = detect_chessboard(bundle.load_image(frame.index, camera_id),
                                        board.cols, board.rows)
            if corners is None:
                missed.setdefault(name, []).append(camera_id)
            else:
                seen[camera_id].append((name, objects, corners))
    if not origin_name:
        raise CalibrationError("no origin board: one chessboard bundle needs "
                               "\"origin\": true (FORMATS.md)")
    return seen, missed, origin_name


def calibrate_stereo(paths: Sequence[str | Path], progress: Progress = quiet) -> StereoResult:
    """Calibrate every camera of the rig from chessboard bundle directories.

    Raises :class:`CalibrationError` (naming the camera or bundle) when the bundles disagree on
    the rig, there is no (or more than one) origin board, or a camera saw too few boards or not
    the origin board.
    """
    if not paths:
        raise CalibrationError("no chessboard bundles given")
    bundles = [read_bundle(p) for p in paths]
    rig = bundles[0].rig
    for bundle in bundles[1:]:
        if bundle.rig.to_dict() != rig.to_dict():
            raise CalibrationError(f"{bundle.path}: its rig differs from {bundles[0].path}'s")
    seen, missed, origin = _board_observations(bundles, rig, progress)
    cameras: dict[str, CameraCalibration] = {}
    for camera_id in rig.camera_ids:
        views = seen[camera_id]
        spec = rig.camera(camera_id)
        if len(views) < MIN_BOARDS:
            raise CalibrationError(f"camera {camera_id} found the board in only {len(views)} "
                                   f"bundle(s); it needs at least {MIN_BOARDS}")
        names = [name for name, _, _ in views]
        if origin not in names:
            raise CalibrationError(f"camera {camera_id} did not find the origin board "
                                   f"({origin}), so its pose in the WCS is unknown")
        progress(f"solving camera {camera_id} from {len(views)} boards")
        object_points = [obj.astype(np.float32) for _, obj, _ in views]
        image_points = [img.astype(np.float32).reshape(-1, 1, 2) for _, _, img in views]
        criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
        # A 25 mm lens on a 6.8 mm sensor sees a narrow field (r ≤ 0.17 in normalised units),
        # where k3·r⁶ cannot be told from k1 and k2: left free it runs to hundreds and drags the
        # focal length and pose with it (measured: up to 2.4 px and 0.3 mm). Fix it at zero.
        _, K, dist, rvecs, tvecs = cv2.calibrateCamera(
            object_points, image_points, (spec.width, spec.height), None, None,
            flags=cv2.CALIB_FIX_K3, criteria=criteria)
        errors = []
        for obj, img, rvec, tvec in zip(object_points, image_points, rvecs, tvecs, strict=True):
            projected, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
            errors.append(np.linalg.norm(projected.reshape(-1, 2) - img.reshape(-1, 2), axis=1))
        # The origin board lies in the WCS exactly as its board frame (FORMATS.md), so its view's
        # extrinsics are the camera's WCS pose.
        k = names.index(origin)
        R, _ = cv2.Rodrigues(rvecs[k])
        cameras[camera_id] = CameraCalibration(
            camera_id=camera_id, width=spec.width, height=spec.height,
            K=np.asarray(K, dtype=np.float64), dist=np.asarray(dist, dtype=np.float64).ravel(),
            R=np.asarray(R, dtype=np.float64),
            T=np.asarray(tvecs[k], dtype=np.float64).ravel(),
            reprojection_px=np.concatenate(errors), boards_used=names)
    return StereoResult(rig=rig, cameras=cameras, missed=missed, inputs=[b.path for b in bundles])
