"""The rig file (``rig.json``): which devices exist and how they group into optical units.

See FORMATS.md, "Rig file". The rig says nothing about where devices stand; calibration finds
that out.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from eyeserver.errors import FormatError
from eyeserver.io._validate import (
    as_array,
    as_id,
    as_int,
    as_object,
    as_str,
    dump_json,
    join_field,
    load_json,
    require_key,
)
from eyeserver.io.atomic import atomic_write_text

__all__ = [
    "RIG_FORMAT",
    "CameraSpec",
    "ProjectorSpec",
    "RigSpec",
    "UnitSpec",
    "check_rig",
    "read_rig",
    "rig_from_dict",
    "write_rig",
]

RIG_FORMAT = "eyeserver.rig/1"
"""Value of the ``format`` key of a rig file."""


@dataclass(frozen=True)
class CameraSpec:
    """One camera of the rig.

    Attributes
    ----------
    id : str
        Camera id, unique among the rig's cameras.
    width, height : int
        Image size in pixels; every image the camera delivers has shape ``(height, width)``.
    """

    id: str
    width: int
    height: int


@dataclass(frozen=True)
class ProjectorSpec:
    """One fringe projector of the rig."""

    id: str


@dataclass(frozen=True)
class UnitSpec:
    """An optical unit: one projector and the cameras that see its fringes.

    Attributes
    ----------
    id : str
        Unit id, unique among the rig's units.
    projector : str
        Id of the unit's projector.
    cameras : tuple of str
        Ids of the unit's cameras, in file order.
    """

    id: str
    projector: str
    cameras: tuple[str, ...]


@dataclass(frozen=True)
class RigSpec:
    """The devices of a rig and their grouping into units.

    Build one with :func:`rig_from_dict` or :func:`read_rig` to get it validated; a ``RigSpec``
    built by hand is checked by :func:`check_rig` and by the writers.

    Attributes
    ----------
    cameras : tuple of CameraSpec
        In file order; a point cloud's ``camera`` field indexes this tuple.
    projectors : tuple of ProjectorSpec
        In file order.
    units : tuple of UnitSpec
        In file order.
    """

    cameras: tuple[CameraSpec, ...]
    projectors: tuple[ProjectorSpec, ...]
    units: tuple[UnitSpec, ...]

    @property
    def camera_ids(self) -> tuple[str, ...]:
        """Camera ids in file order."""
        return tuple(camera.id for camera in self.cameras)

    @property
    def projector_ids(self) -> tuple[str, ...]:
        """Projector ids in file order."""
        return tuple(projector.id for projector in self.projectors)

    @property
    def unit_ids(self) -> tuple[str, ...]:
        """Unit ids in file order."""
        return tuple(unit.id for unit in self.units)

    def camera(self, camera_id: str) -> CameraSpec:
        """The camera called ``camera_id``; KeyError when there is none."""
        for camera in self.cameras:
            if camera.id == camera_id:
                return camera
        raise KeyError(f"no camera {camera_id!r} in the rig")

    def camera_index(self, camera_id: str) -> int:
        """Position of ``camera_id`` in :attr:`cameras` (the PLY ``camera`` value); KeyError."""
        try:
            return self.camera_ids.index(camera_id)
        except ValueError:
            raise KeyError(f"no camera {camera_id!r} in the rig") from None

    def unit(self, unit_id: str) -> UnitSpec:
        """The unit called ``unit_id``; KeyError when there is none."""
        for unit in self.units:
            if unit.id == unit_id:
                return unit
        raise KeyError(f"no unit {unit_id!r} in the rig")

    def unit_of_camera(self, camera_id: str) -> UnitSpec:
        """The unit ``camera_id`` belongs to; KeyError when no unit holds it."""
        for unit in self.units:
            if camera_id in unit.cameras:
                return unit
        raise KeyError(f"camera {camera_id!r} belongs to no unit of the rig")

    def unit_of_projector(self, projector_id: str) -> UnitSpec:
        """The unit whose projector is ``projector_id``; KeyError when there is none."""
        for unit in self.units:
            if unit.projector == projector_id:
                return unit
        raise KeyError(f"projector {projector_id!r} belongs to no unit of the rig")

    def to_dict(self) -> dict[str, object]:
        """The rig file's content, ``format`` key included, ready for :func:`json.dumps`."""
        return {
            "format": RIG_FORMAT,
            "cameras": [
                {"id": camera.id, "width": camera.width, "height": camera.height}
                for camera in self.cameras
            ],
            "projectors": [{"id": projector.id} for projector in self.projectors],
            "units": [
                {"id": unit.id, "projector": unit.projector, "cameras": list(unit.cameras)}
                for unit in self.units
            ],
        }


def rig_from_dict(data: object, source: str | Path, field_prefix: str = "") -> RigSpec:
    """Validate a parsed rig document and build a :class:`RigSpec`.

    Parameters
    ----------
    data : object
        The parsed JSON (normally a dict). Keys this format does not define are ignored.
    source : str or Path
        The file the data came from, named in error messages.
    field_prefix : str, optional
        Prepended to field paths in error messages, e.g. ``"rig"`` for a rig held inline in a
        bundle so that errors read ``rig.units[1].cameras[0]``.

    Returns
    -------
    RigSpec

    Raises
    ------
    FormatError
        When the document breaks FORMATS.md: wrong ``format``, a missing or mistyped field, an
        illegal or duplicate id, a non-positive image size, a unit naming a device that does not
        exist, or a camera or projector that belongs to no unit or to more than one.
    """

    def at(name: str) -> str:
        return join_field(field_prefix, name)

    root = as_object(data, source, field_prefix or None)
    format_name = as_str(require_key(root, "format", source, field_prefix), source, at("format"))
    if format_name != RIG_FORMAT:
        raise FormatError(source, at("format"), f"expected {RIG_FORMAT!r}, got {format_name!r}")

    cameras: list[CameraSpec] = []
    camera_items = as_array(
        require_key(root, "cameras", source, field_prefix), source, at("cameras")
    )
    if not camera_items:
        raise FormatError(source, at("cameras"), "the rig needs at least one camera")
    for position, item in enumerate(camera_items):
        here = at(f"cameras[{position}]")
        entry = as_object(item, source, here)
        camera_id = as_id(require_key(entry, "id", source, here), source, f"{here}.id")
        if any(camera.id == camera_id for camera in cameras):
            raise FormatError(source, f"{here}.id", f"duplicate camera id {camera_id!r}")
        size: dict[str, int] = {}
        for key in ("width", "height"):
            value = as_int(require_key(entry, key, source, here), source, f"{here}.{key}")
            if value <= 0:
                raise FormatError(source, f"{here}.{key}", f"must be positive, got {value}")
            size[key] = value
        cameras.append(CameraSpec(camera_id, size["width"], size["height"]))

    projectors: list[ProjectorSpec] = []
    projector_items = as_array(
        require_key(root, "projectors", source, field_prefix), source, at("projectors")
    )
    for position, item in enumerate(projector_items):
        here = at(f"projectors[{position}]")
        entry = as_object(item, source, here)
        projector_id = as_id(require_key(entry, "id", source, here), source, f"{here}.id")
        if any(projector.id == projector_id for projector in projectors):
            raise FormatError(source, f"{here}.id", f"duplicate projector id {projector_id!r}")
        projectors.append(ProjectorSpec(projector_id))

    camera_ids = {camera.id for camera in cameras}
    projector_ids = {projector.id for projector in projectors}
    unit_of_camera: dict[str, str] = {}
    unit_of_projector: dict[str, str] = {}
    units: list[UnitSpec] = []
    unit_items = as_array(require_key(root, "units", source, field_prefix), source, at("units"))
    for position, item in enumerate(unit_items):
        here = at(f"units[{position}]")
        entry = as_object(item, source, here)
        unit_id = as_id(require_key(entry, "id", source, here), source, f"{here}.id")
        if any(unit.id == unit_id for unit in units):
            raise FormatError(source, f"{here}.id", f"duplicate unit id {unit_id!r}")

        projector_field = f"{here}.projector"
        projector_id = as_id(require_key(entry, "projector", source, here), source, projector_field)
        if projector_id not in projector_ids:
            raise FormatError(source, projector_field, f"no projector {projector_id!r} in the rig")
        if projector_id in unit_of_projector:
            raise FormatError(
                source,
                projector_field,
                f"projector {projector_id!r} already belongs to unit "
                f"{unit_of_projector[projector_id]!r}",
            )
        unit_of_projector[projector_id] = unit_id

        member_items = as_array(
            require_key(entry, "cameras", source, here), source, f"{here}.cameras"
        )
        if not member_items:
            raise FormatError(source, f"{here}.cameras", "a unit needs at least one camera")
        members: list[str] = []
        for member_position, member in enumerate(member_items):
            member_field = f"{here}.cameras[{member_position}]"
            camera_id = as_id(member, source, member_field)
            if camera_id not in camera_ids:
                raise FormatError(source, member_field, f"no camera {camera_id!r} in the rig")
            if camera_id in unit_of_camera:
                raise FormatError(
                    source,
                    member_field,
                    f"camera {camera_id!r} already belongs to unit {unit_of_camera[camera_id]!r}",
                )
            unit_of_camera[camera_id] = unit_id
            members.append(camera_id)
        units.append(UnitSpec(unit_id, projector_id, tuple(members)))

    for position, camera in enumerate(cameras):
        if camera.id not in unit_of_camera:
            raise FormatError(
                source, at(f"cameras[{position}]"), f"camera {camera.id!r} belongs to no unit"
            )
    for position, projector in enumerate(projectors):
        if projector.id not in unit_of_projector:
            raise FormatError(
                source,
                at(f"projectors[{position}]"),
                f"projector {projector.id!r} belongs to no unit",
            )
    return RigSpec(tuple(cameras), tuple(projectors), tuple(units))


def check_rig(rig: RigSpec) -> None:
    """Check a :class:`RigSpec` built in code against the rules :func:`rig_from_dict` applies.

    Parameters
    ----------
    rig : RigSpec

    Raises
    ------
    ValueError
        Naming the offending field, when a reader would reject the rig.
    """
    try:
        rig_from_dict(rig.to_dict(), "<rig>")
    except FormatError as exc:
        raise ValueError(f"invalid rig: field '{exc.field}': {exc.reason}") from exc


def read_rig(path: str | os.PathLike[str]) -> RigSpec:
    """Read and validate a rig file.

    Parameters
    ----------
    path : str or path-like
        The ``rig.json`` file.

    Returns
    -------
    RigSpec

    Raises
    ------
    FormatError
        When the file cannot be read, is not JSON, or breaks FORMATS.md.
    """
    return rig_from_dict(load_json(path), Path(path))


def write_rig(path: str | os.PathLike[str], rig: RigSpec) -> None:
    """Write a rig file atomically (see :func:`eyeserver.io.atomic_write_text`).

    Parameters
    ----------
    path : str or path-like
        The file to write; its directory must exist.
    rig : RigSpec
        The rig; it is validated first.

    Raises
    ------
    ValueError
        When the rig breaks FORMATS.md (nothing is written).
    """
    check_rig(rig)
    atomic_write_text(path, dump_json(rig.to_dict()))
