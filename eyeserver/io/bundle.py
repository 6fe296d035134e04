"""Capture bundles: a directory with ``bundle.json`` and the PNG images of one acquisition.

See FORMATS.md, "Capture bundle". :func:`read_bundle` validates the metadata and checks that
every image file exists; pixels are read lazily by :meth:`Bundle.load_image`, which checks them
against the rig. :func:`write_bundle` publishes a bundle with a single directory rename, so a
crash never leaves a half-written bundle under its final name.
"""

from __future__ import annotations

import contextlib
import hashlib
import math
import os
import secrets
import shutil
import zipfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path, PurePosixPath, PureWindowsPath
from typing import IO, Literal, TypeAlias, cast, get_args

import cv2
import numpy as np
import numpy.typing as npt

from eyeserver.core.frames import grey
from eyeserver.core.types import Image
from eyeserver.errors import FormatError
from eyeserver.io._validate import (
    as_array,
    as_bool,
    as_finite_number,
    as_id,
    as_int,
    as_object,
    as_str,
    dump_json,
    load_json,
    require_key,
    type_name,
)
from eyeserver.io.atomic import fsync_dir, makedirs_synced, write_synced
from eyeserver.io.rig_file import RigSpec, check_rig, rig_from_dict

__all__ = [
    "BIT_DEPTHS",
    "BUNDLE_FILE",
    "BUNDLE_FORMAT",
    "BUNDLE_KINDS",
    "Bundle",
    "BundleFrame",
    "BundleFrameData",
    "BundleKind",
    "ChessboardSpec",
    "bundle_hash",
    "read_bundle",
    "write_bundle",
    "write_bundle_zip",
]

BUNDLE_FORMAT = "eyeserver.bundle/1"
"""Value of the ``format`` key of ``bundle.json``."""

BUNDLE_FILE = "bundle.json"
"""Name of the metadata file inside a bundle directory."""

BundleKind: TypeAlias = Literal["measurement", "chessboard", "plate", "reference"]
BUNDLE_KINDS: tuple[BundleKind, ...] = get_args(BundleKind)
"""The four kinds of bundle, in FORMATS.md order."""

BIT_DEPTHS = (8, 10, 12)
"""Legal values of the optional top-level ``bit_depth``."""

_Z_KINDS: tuple[BundleKind, ...] = ("plate", "reference")
_KNOWN_KEYS = frozenset({"format", "kind", "rig", "created", "frames", "chessboard", "bit_depth"})
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _chessboard_problem(cols: object, rows: object, square_mm: object) -> tuple[str, str] | None:
    """The first rule the board breaks as ``(field, reason)``, or None when it is valid."""
    for name, value in (("cols", cols), ("rows", rows)):
        if isinstance(value, bool) or not isinstance(value, int):
            return name, f"must be an integer, got {type_name(value)}"
        if value < 2:
            return name, f"must be at least 2 inner corners, got {value}"
    assert isinstance(cols, int) and isinstance(rows, int)
    # One odd and one even count make the board look different after a half turn, which is how
    # a detector reads its orientation (FORMATS.md, "The origin board defines the WCS").
    if cols % 2 == rows % 2:
        return "rows", f"exactly one of cols ({cols}) and rows ({rows}) must be odd"
    if isinstance(square_mm, bool) or not isinstance(square_mm, int | float):
        return "square_mm", f"must be a number, got {type_name(square_mm)}"
    if not (math.isfinite(square_mm) and square_mm > 0):
        return "square_mm", f"must be a positive finite number, got {square_mm!r}"
    return None


@dataclass(frozen=True)
class ChessboardSpec:
    """The calibration board seen in a chessboard bundle.

    Attributes
    ----------
    cols : int
        Inner corners per row, at least 2.
    rows : int
        Inner corners per column, at least 2; exactly one of ``cols`` and ``rows`` is odd.
    square_mm : float
        Side of one square, mm, positive.
    origin : bool
        True for the bundle whose board defines the world coordinate system.

    Raises
    ------
    ValueError
        When a rule above is broken.
    """

    cols: int
    rows: int
    square_mm: float
    origin: bool = False

    def __post_init__(self) -> None:
        problem = _chessboard_problem(self.cols, self.rows, self.square_mm)
        if problem is not None:
            raise ValueError(f"chessboard {problem[0]}: {problem[1]}")

    def to_dict(self) -> dict[str, object]:
        """The ``chessboard`` object of ``bundle.json``."""
        return {
            "cols": self.cols,
            "rows": self.rows,
            "square_mm": self.square_mm,
            "origin": self.origin,
        }


@dataclass(frozen=True)
class BundleFrame:
    """One frame of a bundle as described in ``bundle.json``.

    Attributes
    ----------
    index : int
        The frame's ``index``, unique within the bundle.
    images : Mapping of str to str
        Camera id to image file name, relative to the bundle directory. Holds any subset of the
        rig's cameras.
    z_mm : float or None
        Nominal Z of the flat surface (plate and reference bundles only).
    projectors_on : tuple of str
        Projectors lit during the frame.
    t_ns : int or None
        Acquisition time in nanoseconds on a monotonic clock, when known.
    """

    index: int
    images: Mapping[str, str]
    z_mm: float | None = None
    projectors_on: tuple[str, ...] = ()
    t_ns: int | None = None


@dataclass(frozen=True)
class Bundle:
    """A capture bundle read from disk by :func:`read_bundle`.

    Attributes
    ----------
    path : Path
        The bundle directory.
    kind : {"measurement", "chessboard", "plate", "reference"}
    rig : RigSpec
        The rig held inline.
    created : str
        Creation time, ISO 8601, as written in the file.
    frames : tuple of BundleFrame
        In file order.
    chessboard : ChessboardSpec or None
        Always present for chessboard bundles.
    bit_depth : int or None
        Sensor depth (8, 10 or 12) when the file states it; otherwise the PNG's own depth counts.
    extra : Mapping of str to object
        Top-level keys FORMATS.md does not define (for instance a simulator's ground truth),
        as parsed from the JSON.
    """

    path: Path
    kind: BundleKind
    rig: RigSpec
    created: str
    frames: tuple[BundleFrame, ...]
    chessboard: ChessboardSpec | None = None
    bit_depth: int | None = None
    extra: Mapping[str, object] = field(default_factory=dict)

    @property
    def frame_indices(self) -> tuple[int, ...]:
        """The frames' ``index`` values in file order."""
        return tuple(frame.index for frame in self.frames)

    def frame(self, frame_index: int) -> BundleFrame:
        """The frame whose ``index`` is ``frame_index``; KeyError when there is none."""
        return self.frames[self._position(frame_index)]

    def cameras_in_frame(self, frame_index: int) -> tuple[str, ...]:
        """Ids of the cameras with an image in the frame, in rig order; KeyError."""
        images = self.frame(frame_index).images
        return tuple(camera_id for camera_id in self.rig.camera_ids if camera_id in images)

    def is_fringe_image(self, frame_index: int, camera_id: str) -> bool:
        """True when the camera's own unit's projector is lit in the frame (FORMATS.md)."""
        frame = self.frame(frame_index)
        if camera_id not in frame.images:
            return False
        return self.rig.unit_of_camera(camera_id).projector in frame.projectors_on

    def fringe_images(self) -> list[tuple[int, str]]:
        """Every ``(frame_index, camera_id)`` whose image shows its own unit's fringes.

        Frames come in file order and cameras in rig order. An image taken while only another
        unit's projector is lit is not a fringe image.
        """
        return [
            (frame.index, camera_id)
            for frame in self.frames
            for camera_id in self.cameras_in_frame(frame.index)
            if self.rig.unit_of_camera(camera_id).projector in frame.projectors_on
        ]

    def image_path(self, frame_index: int, camera_id: str) -> Path:
        """Where the image of ``camera_id`` in the frame lies; KeyError when the frame lacks it."""
        frame = self.frame(frame_index)
        try:
            name = frame.images[camera_id]
        except KeyError:
            raise KeyError(f"frame {frame_index} holds no image of camera {camera_id!r}") from None
        return self.path / name

    def image_bytes(self, frame_index: int, camera_id: str) -> bytes:
        """One image file's content as stored (the PNG, not checked against the rig).

        Raises
        ------
        KeyError
            When the bundle has no such frame or the frame no image of that camera.
        FormatError
            Naming the image file, when it resolves outside the bundle directory.
        OSError
            When it cannot be read (``FileNotFoundError`` when it is gone).
        """
        path = self.image_path(frame_index, camera_id)
        if not _stays_inside(self.path, path):
            raise FormatError(path, None, "resolves outside the bundle directory")
        return path.read_bytes()

    def load_image(self, frame_index: int, camera_id: str) -> Image:
        """Read one image and check it against the rig.

        Parameters
        ----------
        frame_index : int
            The frame's ``index`` (not its position in the file).
        camera_id : str
            A camera with an image in that frame.

        Returns
        -------
        ndarray of uint8 or uint16, shape (height, width)
            Pixel values as stored (10- and 12-bit data are not shifted); a colour image's the
            mean of its colour channels, rounded.

        Raises
        ------
        KeyError
            When the bundle has no such frame or the frame no image of that camera.
        FormatError
            Naming the image file, when it is missing, not a PNG, not 8- or 16-bit, neither
            single-channel nor colour (3 or 4 channels, read as their mean), not the camera's
            size, or holds values beyond ``bit_depth``.
        """
        position = self._position(frame_index)
        path = self.image_path(frame_index, camera_id)
        where = f"frames[{position}].images.{camera_id} in {self.path / BUNDLE_FILE}"
        if not _stays_inside(self.path, path):
            raise FormatError(path, None, f"resolves outside the bundle directory ({where})")
        try:
            data = path.read_bytes()
        except FileNotFoundError as exc:
            raise FormatError(path, None, f"image file missing (named by {where})") from exc
        except OSError as exc:
            raise FormatError(path, None, f"cannot read the image: {exc}") from exc
        if not data.startswith(_PNG_SIGNATURE):
            raise FormatError(path, None, "not a PNG file")
        # imdecode rather than imread: it reads what we already hold and is not tripped up by
        # non-ASCII paths on Windows. IMREAD_UNCHANGED keeps 16-bit data and the channel count.
        decoded = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
        if decoded is None:
            raise FormatError(path, None, "cannot decode the PNG")
        image = np.asarray(decoded)
        if image.dtype not in (np.uint8, np.uint16):
            raise FormatError(path, None, f"must be an 8- or 16-bit PNG, got {image.dtype}")
        if image.ndim == 3 and image.shape[2] in (3, 4):
            # A colour PNG: the mean of its colour channels (docs/FORMATS.md), in its own type.
            image = np.rint(grey(image)).astype(image.dtype)
        elif image.ndim != 2:
            channels = image.shape[2] if image.ndim == 3 else image.ndim
            raise FormatError(path, None, f"must be single-channel or colour (3 or 4 "
                              f"channels), got {channels} channels")
        camera = self.rig.camera(camera_id)
        height, width = image.shape
        if (height, width) != (camera.height, camera.width):
            raise FormatError(
                path,
                None,
                f"is {width}×{height} pixels but camera {camera_id!r} delivers "
                f"{camera.width}×{camera.height}",
            )
        if self.bit_depth is not None:
            problem = _bit_depth_problem(image, self.bit_depth)
            if problem is not None:
                raise FormatError(path, None, problem)
        return cast(Image, image)

    def _position(self, frame_index: int) -> int:
        for position, frame in enumerate(self.frames):
            if frame.index == frame_index:
                return position
        raise KeyError(f"no frame with index {frame_index} in bundle {self.path}")


@dataclass(frozen=True)
class BundleFrameData:
    """One frame to be written by :func:`write_bundle`.

    Attributes
    ----------
    images : Mapping of str to ndarray
        Camera id to image (uint8 or uint16, shape ``(height, width)`` of that camera).
    z_mm : float or None
        Nominal Z of the flat surface; required for plate and reference bundles only.
    projectors_on : tuple of str
        Projectors lit during the frame.
    t_ns : int or None
        Acquisition time in nanoseconds on a monotonic clock.
    """

    images: Mapping[str, Image]
    z_mm: float | None = None
    projectors_on: tuple[str, ...] = ()
    t_ns: int | None = None


def _bit_depth_problem(image: npt.NDArray[np.generic], bit_depth: int) -> str | None:
    if bit_depth > 8 and image.dtype == np.uint8:
        return f"bit_depth is {bit_depth} but the image is 8-bit (needs a 16-bit PNG)"
    peak = int(image.max())
    if peak >= 1 << bit_depth:
        largest = (1 << bit_depth) - 1
        return f"holds the value {peak}, beyond bit_depth {bit_depth} (largest {largest})"
    return None


def _relative_name_problem(name: str) -> str | None:
    """Why ``name`` is not a safe file name relative to the bundle directory, or None."""
    if not name:
        return "must not be empty"
    if "\x00" in name:
        return "must not contain NUL characters"
    # A backslash is a separator on Windows: refusing it keeps '..\\x' from escaping there.
    if "\\" in name:
        return "must use '/' as separator (backslashes are not allowed)"
    if PurePosixPath(name).is_absolute() or PureWindowsPath(name).drive:
        return f"{name!r} must be relative to the bundle directory, not absolute"
    if ".." in PurePosixPath(name).parts:
        return f"{name!r} must stay inside the bundle directory ('..' is not allowed)"
    return None


def _stays_inside(root: Path, path: Path) -> bool:
    """True when ``path`` resolves (symbolic links followed) to a place under ``root``."""
    return path.resolve().is_relative_to(root.resolve())


def _check_created(text: str) -> str | None:
    try:
        datetime.fromisoformat(text)
    except ValueError:
        return f"must be an ISO 8601 date and time such as '2026-11-23T10:00:00Z', got {text!r}"
    return None


def read_bundle(directory: str | os.PathLike[str]) -> Bundle:
    """Read and validate a capture bundle.

    Parameters
    ----------
    directory : str or path-like
        The bundle directory (holding ``bundle.json``).

    Returns
    -------
    Bundle
        With the metadata checked and every image file found; pixels are checked when
        :meth:`Bundle.load_image` reads them.

    Raises
    ------
    FormatError
        Naming ``bundle.json`` and the field, when the bundle breaks FORMATS.md: wrong
        ``format`` or ``kind``, an invalid inline rig, no frames, duplicate frame indices, an
        image name that is absolute or leaves the bundle, an image file that does not exist, a
        camera or projector id the rig lacks, ``z_mm`` missing from a plate or reference bundle
        or present in another, a missing or invalid ``chessboard`` in a chessboard bundle, a
        ``bit_depth`` other than 8, 10 or 12, or a ``created`` that is not ISO 8601.
    """
    root = Path(directory)
    source = root / BUNDLE_FILE
    if not root.is_dir():
        raise FormatError(root, None, "not a directory (a bundle is a directory with bundle.json)")
    document = as_object(load_json(source), source, None)

    format_name = as_str(require_key(document, "format", source), source, "format")
    if format_name != BUNDLE_FORMAT:
        raise FormatError(source, "format", f"expected {BUNDLE_FORMAT!r}, got {format_name!r}")

    kind_text = as_str(require_key(document, "kind", source), source, "kind")
    if kind_text not in BUNDLE_KINDS:
        allowed = ", ".join(repr(kind) for kind in BUNDLE_KINDS)
        raise FormatError(source, "kind", f"must be one of {allowed}, got {kind_text!r}")
    kind: BundleKind = kind_text

    rig = rig_from_dict(require_key(document, "rig", source), source, field_prefix="rig")

    created = as_str(require_key(document, "created", source), source, "created")
    problem = _check_created(created)
    if problem is not None:
        raise FormatError(source, "created", problem)

    bit_depth: int | None = None
    if "bit_depth" in document:
        bit_depth = as_int(document["bit_depth"], source, "bit_depth")
        if bit_depth not in BIT_DEPTHS:
            raise FormatError(source, "bit_depth", f"must be 8, 10 or 12, got {bit_depth}")

    chessboard: ChessboardSpec | None = None
    if "chessboard" in document:
        chessboard = _read_chessboard(document["chessboard"], source)
    elif kind == "chessboard":
        raise FormatError(source, "chessboard", "required for a chessboard bundle but missing")

    frame_items = as_array(require_key(document, "frames", source), source, "frames")
    if not frame_items:
        raise FormatError(source, "frames", "a bundle needs at least one frame")
    frames: list[BundleFrame] = []
    position_of_index: dict[int, int] = {}
    for position, item in enumerate(frame_items):
        frame = _read_frame(item, position, kind, rig, root, source)
        if frame.index in position_of_index:
            raise FormatError(
                source,
                f"frames[{position}].index",
                f"duplicate frame index {frame.index} "
                f"(also at frames[{position_of_index[frame.index]}])",
            )
        position_of_index[frame.index] = position
        frames.append(frame)

    extra = {key: value for key, value in document.items() if key not in _KNOWN_KEYS}
    return Bundle(
        path=root,
        kind=kind,
        rig=rig,
        created=created,
        frames=tuple(frames),
        chessboard=chessboard,
        bit_depth=bit_depth,
        extra=extra,
    )


def _read_chessboard(value: object, source: Path) -> ChessboardSpec:
    board = as_object(value, source, "chessboard")
    cols = require_key(board, "cols", source, "chessboard")
    rows = require_key(board, "rows", source, "chessboard")
    square_mm = require_key(board, "square_mm", source, "chessboard")
    problem = _chessboard_problem(cols, rows, square_mm)
    if problem is not None:
        raise FormatError(source, f"chessboard.{problem[0]}", problem[1])
    origin = as_bool(board.get("origin", False), source, "chessboard.origin")
    return ChessboardSpec(
        cols=cast(int, cols),
        rows=cast(int, rows),
        square_mm=float(cast(float, square_mm)),
        origin=origin,
    )


def _read_frame(
    item: object, position: int, kind: BundleKind, rig: RigSpec, root: Path, source: Path
) -> BundleFrame:
    here = f"frames[{position}]"
    entry = as_object(item, source, here)

    index = as_int(require_key(entry, "index", source, here), source, f"{here}.index")
    if index < 0:
        raise FormatError(source, f"{here}.index", f"must not be negative, got {index}")

    images: dict[str, str] = {}
    image_map = as_object(require_key(entry, "images", source, here), source, f"{here}.images")
    for camera_id, name_value in image_map.items():
        image_field = f"{here}.images.{camera_id}"
        if camera_id not in rig.camera_ids:
            raise FormatError(source, image_field, f"no camera {camera_id!r} in the rig")
        name = as_str(name_value, source, image_field)
        problem = _relative_name_problem(name)
        if problem is not None:
            raise FormatError(source, image_field, problem)
        path = root / name
        if not _stays_inside(root, path):
            raise FormatError(
                source, image_field, f"{name!r} resolves outside the bundle directory"
            )
        if not path.is_file():
            raise FormatError(source, image_field, f"image file {name!r} not found in the bundle")
        images[camera_id] = name

    z_mm: float | None = None
    if kind in _Z_KINDS:
        z_mm = as_finite_number(require_key(entry, "z_mm", source, here), source, f"{here}.z_mm")
    elif "z_mm" in entry:
        raise FormatError(
            source,
            f"{here}.z_mm",
            f"must be absent in a {kind} bundle (only plate and reference bundles have z_mm)",
        )

    projectors_on: list[str] = []
    if "projectors_on" in entry:
        lit = as_array(entry["projectors_on"], source, f"{here}.projectors_on")
        for lit_position, lit_value in enumerate(lit):
            lit_field = f"{here}.projectors_on[{lit_position}]"
            projector_id = as_id(lit_value, source, lit_field)
            if projector_id not in rig.projector_ids:
                raise FormatError(source, lit_field, f"no projector {projector_id!r} in the rig")
            if projector_id in projectors_on:
                raise FormatError(source, lit_field, f"projector {projector_id!r} listed twice")
            projectors_on.append(projector_id)

    t_ns: int | None = None
    if "t_ns" in entry:
        t_ns = as_int(entry["t_ns"], source, f"{here}.t_ns")

    return BundleFrame(
        index=index, images=images, z_mm=z_mm, projectors_on=tuple(projectors_on), t_ns=t_ns
    )


def _frame_document(
    position: int,
    frame: BundleFrameData,
    kind: BundleKind,
    rig: RigSpec,
    bit_depth: int | None,
) -> dict[str, object]:
    """Check one frame to be written (ValueError) and build its ``bundle.json`` entry."""
    here = f"frames[{position}]"
    images: dict[str, str] = {}
    for camera_id in frame.images:
        if camera_id not in rig.camera_ids:
            raise ValueError(f"{here}.images: no camera {camera_id!r} in the rig")
    for camera in rig.cameras:
        if camera.id not in frame.images:
            continue
        image = frame.images[camera.id]
        image_field = f"{here}.images[{camera.id!r}]"
        if not isinstance(image, np.ndarray):
            raise ValueError(f"{image_field}: must be a numpy array, got {type(image).__name__}")
        if image.dtype not in (np.uint8, np.uint16):
            raise ValueError(f"{image_field}: must be uint8 or uint16, got {image.dtype}")
        if image.shape != (camera.height, camera.width):
            raise ValueError(
                f"{image_field}: shape must be (height, width) = "
                f"{(camera.height, camera.width)}, got {image.shape}"
            )
        if bit_depth is not None:
            problem = _bit_depth_problem(image, bit_depth)
            if problem is not None:
                raise ValueError(f"{image_field}: {problem}")
        images[camera.id] = f"{camera.id}_{position:04d}.png"

    entry: dict[str, object] = {"index": position, "images": images}
    if kind in _Z_KINDS:
        if frame.z_mm is None:
            raise ValueError(f"{here}.z_mm: required for a {kind} bundle")
        if isinstance(frame.z_mm, bool) or not math.isfinite(frame.z_mm):
            raise ValueError(f"{here}.z_mm: must be a finite number, got {frame.z_mm!r}")
        entry["z_mm"] = float(frame.z_mm)
    elif frame.z_mm is not None:
        raise ValueError(f"{here}.z_mm: must be None in a {kind} bundle")

    lit = tuple(frame.projectors_on)
    for projector_id in lit:
        if projector_id not in rig.projector_ids:
            raise ValueError(f"{here}.projectors_on: no projector {projector_id!r} in the rig")
    if len(set(lit)) != len(lit):
        raise ValueError(f"{here}.projectors_on: a projector is listed twice in {lit}")
    entry["projectors_on"] = list(lit)

    if frame.t_ns is not None:
        if isinstance(frame.t_ns, bool) or not isinstance(frame.t_ns, int | np.integer):
            raise ValueError(f"{here}.t_ns: must be an integer, got {frame.t_ns!r}")
        entry["t_ns"] = int(frame.t_ns)
    return entry


def _created_text(created: str | datetime | None) -> str:
    if created is None:
        created = datetime.now(UTC)
    if isinstance(created, datetime):
        if created.tzinfo is None:
            raise ValueError("created: a datetime needs a time zone (naive times are ambiguous)")
        return created.isoformat(timespec="milliseconds").replace("+00:00", "Z")
    problem = _check_created(created)
    if problem is not None:
        raise ValueError(f"created: {problem}")
    return created


def _encode_png(image: Image, name: str) -> bytes:
    ok, encoded = cv2.imencode(".png", np.ascontiguousarray(image))
    if not ok:
        raise ValueError(f"OpenCV could not encode {name} as PNG")
    return bytes(np.asarray(encoded).tobytes())


def _fresh_sibling(target: Path, suffix: str) -> Path:
    """A hidden, unused name next to ``target`` (same file system, so a rename is atomic)."""
    while True:
        candidate = target.with_name(f".{target.name}.{secrets.token_hex(6)}{suffix}")
        if not os.path.lexists(candidate):
            return candidate


def _refuse_target(target: Path, overwrite: bool) -> bool:
    """Raise when ``target`` may not be replaced; True when it exists and is not empty."""
    if not os.path.lexists(target):
        return False
    if target.is_symlink() or not target.is_dir():
        raise FileExistsError(f"{target} exists and is not a directory")
    occupied = any(target.iterdir())
    if occupied and not overwrite:
        raise FileExistsError(
            f"{target} exists and is not empty (pass overwrite=True to replace it)"
        )
    return occupied


def _publish(staging: Path, target: Path, overwrite: bool) -> None:
    """Move the finished ``staging`` directory to ``target`` with directory renames."""
    parent = target.parent
    if _refuse_target(target, overwrite):
        # Two renames: a crash between them leaves no bundle under the final name (the old one
        # survives under a hidden name), never a mixture of old and new files.
        retired = _fresh_sibling(target, ".old")
        os.rename(target, retired)
        os.rename(staging, target)
        fsync_dir(parent)
        # The new bundle is in place and durable; a leftover of the old one is only clutter.
        shutil.rmtree(retired, ignore_errors=True)
        return
    try:
        # POSIX rename replaces an empty directory and refuses a non-empty one, so a bundle
        # that appeared since the check above is never clobbered.
        os.replace(staging, target)
    except OSError as exc:
        if os.path.isdir(target) and any(Path(target).iterdir()):
            raise FileExistsError(f"{target} appeared while the bundle was written") from exc
        raise
    fsync_dir(parent)


def write_bundle(
    directory: str | os.PathLike[str],
    kind: BundleKind,
    rig: RigSpec,
    frames: Sequence[BundleFrameData],
    *,
    chessboard: ChessboardSpec | None = None,
    bit_depth: int | None = None,
    created: str | datetime | None = None,
    extra: Mapping[str, object] | None = None,
    overwrite: bool = False,
) -> Bundle:
    """Write a capture bundle atomically.

    Frame ``i`` of ``frames`` gets ``index`` ``i`` and its images are written as
    ``{camera}_{i:04d}.png``. Everything goes to a hidden sibling directory first, is fsynced, and
    is then renamed to ``directory``; a crash never leaves a half-written bundle under that name.

    Parameters
    ----------
    directory : str or path-like
        The bundle directory to create. Missing parent directories are created.
    kind : {"measurement", "chessboard", "plate", "reference"}
    rig : RigSpec
        The rig, stored inline.
    frames : sequence of BundleFrameData
        At least one frame.
    chessboard : ChessboardSpec, optional
        Required for chessboard bundles.
    bit_depth : {8, 10, 12}, optional
        Sensor depth of the data in 16-bit images; pixel values must fit in it.
    created : str or datetime, optional
        Creation time: an ISO 8601 string or a time-zone aware datetime; now (UTC) by default.
    extra : Mapping of str to object, optional
        Further top-level keys (JSON-serialisable, none of FORMATS.md's own); readers that do
        not know them ignore them, :attr:`Bundle.extra` returns them.
    overwrite : bool, optional
        Replace an existing non-empty ``directory``. An empty directory is always replaced.

    Returns
    -------
    Bundle
        The bundle as :func:`read_bundle` reads it back.

    Raises
    ------
    ValueError
        When the arguments would make a bundle that breaks FORMATS.md (nothing is written).
    FileExistsError
        When ``directory`` exists and is not empty and ``overwrite`` is false, or is not a
        directory.
    """
    target = Path(directory)
    if kind not in BUNDLE_KINDS:
        raise ValueError(f"kind must be one of {BUNDLE_KINDS}, got {kind!r}")
    check_rig(rig)
    if not frames:
        raise ValueError("frames: a bundle needs at least one frame")
    if bit_depth is not None and (isinstance(bit_depth, bool) or bit_depth not in BIT_DEPTHS):
        raise ValueError(f"bit_depth must be 8, 10 or 12, got {bit_depth!r}")
    if chessboard is None and kind == "chessboard":
        raise ValueError("chessboard: required for a chessboard bundle")
    extra = dict(extra or {})
    clashing = sorted(_KNOWN_KEYS.intersection(extra))
    if clashing:
        raise ValueError(
            f"extra: keys {clashing} are defined by FORMATS.md; pass them as arguments"
        )

    document: dict[str, object] = {
        "format": BUNDLE_FORMAT,
        "kind": kind,
        "rig": rig.to_dict(),
        "created": _created_text(created),
        "frames": [
            _frame_document(position, frame, kind, rig, bit_depth)
            for position, frame in enumerate(frames)
        ],
    }
    if chessboard is not None:
        document["chessboard"] = chessboard.to_dict()
    if bit_depth is not None:
        document["bit_depth"] = bit_depth
    document.update(extra)
    try:
        metadata = dump_json(document).encode("utf-8")
    except (TypeError, ValueError) as exc:
        raise ValueError(f"extra: not serialisable as strict JSON: {exc}") from exc

    makedirs_synced(target.parent)
    _refuse_target(target, overwrite)  # fail before encoding any image
    staging = _fresh_sibling(target, ".partial")
    staging.mkdir()
    try:
        for position, frame in enumerate(frames):
            for camera_id, image in frame.images.items():
                name = f"{camera_id}_{position:04d}.png"
                write_synced(staging / name, _encode_png(image, name))
        write_synced(staging / BUNDLE_FILE, metadata)
        fsync_dir(staging)
        _publish(staging, target, overwrite)
    except BaseException:
        with contextlib.suppress(OSError):
            shutil.rmtree(staging)
        raise
    return read_bundle(target)


def bundle_hash(directory: str | os.PathLike[str]) -> str:
    """SHA-256 of a bundle's content, for provenance.

    The bundle is validated with :func:`read_bundle` first. The digest covers ``bundle.json``
    and every image file it names, taken once each in sorted order of their names as written in
    ``bundle.json``; each file contributes its UTF-8 name and its content, each preceded by its
    length in bytes as an 8-byte little-endian integer, so no two different bundles share a
    byte stream.

    Parameters
    ----------
    directory : str or path-like
        The bundle directory.

    Returns
    -------
    str
        64 lowercase hexadecimal digits.

    Raises
    ------
    FormatError
        When the bundle is invalid or a file cannot be read.
    """
    bundle = read_bundle(directory)
    names = {BUNDLE_FILE}
    for frame in bundle.frames:
        names.update(frame.images.values())
    digest = hashlib.sha256()
    for name in sorted(names):
        encoded_name = name.encode("utf-8")
        path = bundle.path / name
        digest.update(len(encoded_name).to_bytes(8, "little"))
        digest.update(encoded_name)
        try:
            with path.open("rb") as stream:
                digest.update(os.fstat(stream.fileno()).st_size.to_bytes(8, "little"))
                while chunk := stream.read(1 << 20):
                    digest.update(chunk)
        except OSError as exc:
            raise FormatError(path, None, f"cannot read the file: {exc}") from exc
    return digest.hexdigest()


def write_bundle_zip(bundle: Bundle, stream: IO[bytes], *, folder: str | None = None
                     ) -> list[str]:
    """Write a bundle's files, byte for byte, into a zip archive.

    The archive holds ``bundle.json`` and the image files it names (each once, in frame then
    rig order), nothing else found in the directory. Images are stored as they are: PNG is
    compressed already, so deflating it again would cost time and save nothing;
    ``bundle.json`` is deflated.

    Parameters
    ----------
    bundle : Bundle
        A bundle from :func:`read_bundle`.
    stream : binary file
        Writable (and, for :mod:`zipfile`'s headers, preferably seekable); left open.
    folder : str, optional
        A top-level folder for the members (``<folder>/bundle.json``), so that unpacking the
        archive gives a bundle directory; without it the members are at the top.

    Returns
    -------
    list of str
        The member names, in archive order.

    Raises
    ------
    FormatError
        When an image resolves outside the bundle directory.
    OSError
        When a file cannot be read (for instance deleted meanwhile).
    """
    if folder is not None and _relative_name_problem(folder) is not None:
        raise ValueError(f"folder: {_relative_name_problem(folder)}")
    prefix = "" if folder is None else PurePosixPath(folder).as_posix() + "/"
    names = [BUNDLE_FILE]
    for frame in bundle.frames:
        for camera_id in bundle.cameras_in_frame(frame.index):
            name = PurePosixPath(frame.images[camera_id]).as_posix()
            if name not in names:
                names.append(name)
    members = []
    # strict_timestamps=False: a file time before 1980 (a clock never set) is clamped, not fatal.
    with zipfile.ZipFile(stream, "w", strict_timestamps=False) as archive:
        for name in names:
            path = bundle.path / name
            if not _stays_inside(bundle.path, path):
                raise FormatError(path, None, "resolves outside the bundle directory")
            compression = zipfile.ZIP_DEFLATED if name == BUNDLE_FILE else zipfile.ZIP_STORED
            archive.write(path, prefix + name, compress_type=compression)
            members.append(prefix + name)
    return members
