"""Point clouds as binary little-endian PLY (FORMATS.md, "Point clouds").

We write float32 ``x y z`` in WCS millimetres, then, where known, float32 ``quality`` (0–1) and
uint8 ``camera`` (index into the rig's camera list). We read what we write and what other tools
commonly write for a point cloud: a ``vertex`` element of scalar properties (any PLY scalar
type, ``double`` coordinates included), other elements of scalar properties before it, and any
elements after it.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from eyeserver.errors import FormatError
from eyeserver.io.atomic import atomic_write_bytes

__all__ = ["PointCloud", "read_ply", "write_ply"]

_SCALAR_TYPES: dict[str, str] = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "<i2",
    "int16": "<i2",
    "ushort": "<u2",
    "uint16": "<u2",
    "int": "<i4",
    "int32": "<i4",
    "uint": "<u4",
    "uint32": "<u4",
    "float": "<f4",
    "float32": "<f4",
    "double": "<f8",
    "float64": "<f8",
}


@dataclass(frozen=True, eq=False)
class PointCloud:
    """Points in WCS millimetres with optional per-point quality and source camera.

    The constructor converts ``points`` and ``quality`` to float32 and ``camera`` to uint8.

    Attributes
    ----------
    points : ndarray of float32, shape (N, 3)
        x, y, z in mm.
    quality : ndarray of float32, shape (N,), or None
        Confidence in [0, 1]; not enforced, as a reader must take what a file holds.
    camera : ndarray of uint8, shape (N,), or None
        Index into the rig's camera list (:attr:`eyeserver.io.RigSpec.cameras`).

    Raises
    ------
    ValueError
        When the shapes disagree or ``camera`` holds values outside 0–255 or non-integers.
    """

    points: npt.NDArray[np.float32]
    quality: npt.NDArray[np.float32] | None = None
    camera: npt.NDArray[np.uint8] | None = None

    def __post_init__(self) -> None:
        points = np.asarray(self.points)
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"points must have shape (N, 3), got {points.shape}")
        count = points.shape[0]
        object.__setattr__(self, "points", points.astype(np.float32, copy=False))
        if self.quality is not None:
            quality = np.asarray(self.quality)
            if quality.shape != (count,):
                raise ValueError(f"quality must have shape ({count},), got {quality.shape}")
            object.__setattr__(self, "quality", quality.astype(np.float32, copy=False))
        if self.camera is not None:
            camera = np.asarray(self.camera)
            if camera.shape != (count,):
                raise ValueError(f"camera must have shape ({count},), got {camera.shape}")
            if camera.dtype != np.uint8:
                if not np.issubdtype(camera.dtype, np.integer):
                    raise ValueError(f"camera must hold integers, got {camera.dtype}")
                if count and (camera.min() < 0 or camera.max() > 255):
                    raise ValueError("camera values must lie in 0–255")
                camera = camera.astype(np.uint8)
            object.__setattr__(self, "camera", camera)

    def __len__(self) -> int:
        return int(self.points.shape[0])


def _vertex_dtype(cloud: PointCloud) -> np.dtype[np.void]:
    fields: list[tuple[str, str]] = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if cloud.quality is not None:
        fields.append(("quality", "<f4"))
    if cloud.camera is not None:
        fields.append(("camera", "u1"))
    return np.dtype(fields)  # packed: PLY has no padding between properties


def write_ply(
    path: str | os.PathLike[str], cloud: PointCloud, comments: Sequence[str] = ()
) -> None:
    """Write a point cloud as binary little-endian PLY, atomically.

    The ``vertex`` element holds ``float x``, ``float y``, ``float z``, then ``float quality``
    and ``uchar camera`` when the cloud has them.

    Parameters
    ----------
    path : str or path-like
        The file to write; its directory must exist.
    cloud : PointCloud
        The points.
    comments : sequence of str, optional
        Header comment lines (provenance such as a bundle hash); one line each.

    Raises
    ------
    ValueError
        When a comment holds a line break or non-ASCII text.
    """
    header = ["ply", "format binary_little_endian 1.0"]
    for comment in comments:
        if "\n" in comment or "\r" in comment or not comment.isascii():
            raise ValueError(f"PLY comments must be one line of ASCII, got {comment!r}")
        header.append(f"comment {comment}".rstrip())
    header.append(f"element vertex {len(cloud)}")
    header += ["property float x", "property float y", "property float z"]
    if cloud.quality is not None:
        header.append("property float quality")
    if cloud.camera is not None:
        header.append("property uchar camera")
    header.append("end_header")

    vertices = np.empty(len(cloud), dtype=_vertex_dtype(cloud))
    vertices["x"] = cloud.points[:, 0]
    vertices["y"] = cloud.points[:, 1]
    vertices["z"] = cloud.points[:, 2]
    if cloud.quality is not None:
        vertices["quality"] = cloud.quality
    if cloud.camera is not None:
        vertices["camera"] = cloud.camera
    atomic_write_bytes(path, ("\n".join(header) + "\n").encode("ascii") + vertices.tobytes())


@dataclass
class _Element:
    name: str
    count: int
    properties: list[tuple[str, str]]  # (name, numpy type code)
    has_list: bool = False


def _parse_header(data: bytes, source: Path) -> tuple[list[_Element], int]:
    """The header's elements and the offset of the first data byte."""
    if not data.startswith(b"ply"):
        raise FormatError(source, None, "not a PLY file (it does not start with 'ply')")
    elements: list[_Element] = []
    format_seen = False
    offset = 0
    line_number = 0
    while True:
        end = data.find(b"\n", offset)
        if end < 0:
            raise FormatError(source, "header", "no 'end_header' line")
        raw = data[offset:end]
        offset = end + 1
        line_number += 1
        try:
            line = raw.decode("ascii").rstrip("\r")
        except UnicodeDecodeError:
            raise FormatError(source, "header", f"line {line_number} is not ASCII") from None
        words = line.split()
        if line_number == 1:
            if words != ["ply"]:
                raise FormatError(source, None, "not a PLY file (first line is not 'ply')")
            continue
        if not words or words[0] in ("comment", "obj_info"):
            continue
        keyword = words[0]
        if keyword == "end_header":
            break
        if keyword == "format":
            if len(words) != 3 or words[2] != "1.0":
                raise FormatError(source, "format", f"unsupported format line {line!r}")
            if words[1] != "binary_little_endian":
                raise FormatError(
                    source,
                    "format",
                    f"{words[1]} PLY is not supported; only binary_little_endian",
                )
            format_seen = True
        elif keyword == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise FormatError(source, "header", f"bad element line {line!r}")
            elements.append(_Element(words[1], int(words[2]), []))
        elif keyword == "property":
            if not elements:
                raise FormatError(source, "header", f"property before any element: {line!r}")
            element = elements[-1]
            if len(words) >= 2 and words[1] == "list":
                element.has_list = True
                continue
            if len(words) != 3 or words[1] not in _SCALAR_TYPES:
                raise FormatError(
                    source, f"element {element.name}", f"unsupported property line {line!r}"
                )
            name = words[2]
            if any(name == existing for existing, _ in element.properties):
                raise FormatError(
                    source, f"element {element.name}", f"property {name!r} declared twice"
                )
            element.properties.append((name, _SCALAR_TYPES[words[1]]))
        else:
            raise FormatError(source, "header", f"unknown header line {line!r}")
    if not format_seen:
        raise FormatError(source, "format", "the header has no format line")
    return elements, offset


def read_ply(path: str | os.PathLike[str]) -> PointCloud:
    """Read a binary little-endian PLY point cloud.

    Parameters
    ----------
    path : str or path-like
        The file.

    Returns
    -------
    PointCloud
        ``x y z`` converted to float32 (double coordinates lose precision beyond float32's),
        ``quality`` to float32 and ``camera`` to uint8 when the file has them.

    Raises
    ------
    FormatError
        Naming the file and the field, when the file is not a PLY, is ASCII or big-endian,
        has no ``vertex`` element or no ``x``, ``y`` or ``z``, has list properties in or before
        the vertex element, has ``camera`` values outside 0–255, or is truncated.
    """
    source = Path(path)
    try:
        data = source.read_bytes()
    except FileNotFoundError as exc:
        raise FormatError(source, None, "file not found") from exc
    except OSError as exc:
        raise FormatError(source, None, f"cannot read the file: {exc}") from exc
    elements, offset = _parse_header(data, source)

    vertex: _Element | None = None
    is_last = False
    for position, element in enumerate(elements):
        if element.name == "vertex":
            vertex = element
            is_last = position == len(elements) - 1
            break
        if element.has_list:
            # A list's length is stored per item, so the data after it cannot be located
            # without parsing every item.
            raise FormatError(
                source,
                f"element {element.name}",
                "list properties before the vertex element are not supported",
            )
        offset += element.count * np.dtype(element.properties).itemsize
    if vertex is None:
        raise FormatError(source, "element vertex", "the file has no vertex element")
    if vertex.has_list:
        raise FormatError(source, "element vertex", "list properties are not supported")
    names = [name for name, _ in vertex.properties]
    for axis in ("x", "y", "z"):
        if axis not in names:
            raise FormatError(source, f"property {axis}", "the vertex element has no such property")

    record = np.dtype(vertex.properties)
    needed = vertex.count * record.itemsize
    available = len(data) - offset
    if available < needed:
        raise FormatError(
            source,
            "data",
            f"truncated: {vertex.count} vertices need {needed} bytes, {max(available, 0)} present",
        )
    if is_last and available > needed:
        raise FormatError(
            source,
            "data",
            f"{available - needed} bytes after the last of the {vertex.count} declared vertices",
        )
    vertices = np.frombuffer(data, dtype=record, count=vertex.count, offset=offset)

    points = np.empty((vertex.count, 3), dtype=np.float32)
    for column, axis in enumerate(("x", "y", "z")):
        points[:, column] = vertices[axis]
    quality: npt.NDArray[np.float32] | None = None
    if "quality" in names:
        quality = vertices["quality"].astype(np.float32)
    camera: npt.NDArray[np.uint8] | None = None
    if "camera" in names:
        raw_camera = vertices["camera"]
        if not np.issubdtype(raw_camera.dtype, np.integer):
            raise FormatError(
                source, "property camera", f"must be an integer type, not {raw_camera.dtype}"
            )
        if vertex.count and (raw_camera.min() < 0 or raw_camera.max() > 255):
            raise FormatError(source, "property camera", "values must lie in 0–255")
        camera = raw_camera.astype(np.uint8)
    return PointCloud(points, quality, camera)
