"""The room file: every parameter of the simulated treatment room, defaulting to the default room.

A room file is TOML (or JSON) that overrides any subset of :class:`RoomConfig`;
``docs/room-file.md`` documents each key and ``examples/rooms/`` holds other rigs. Units:
millimetres, degrees at this human-facing edge (radians inside), DN on the 8-bit scale.

Device placement uses spherical coordinates about the look-at point: a device at distance ``d``,
azimuth ``a`` (signed angle in the X–Z plane from +Z towards +X) and elevation ``e`` (towards +Y)
stands at ``look_at + d·(sin a cos e, sin e, cos a cos e)`` and looks at ``look_at`` with its image
rows running downwards (−Y) unless ``roll_deg`` turns it about its optical axis. ``position_mm``
overrides the spherical placement.

Default geometry (docs/design.md §3): projectors at 200 mm, ±45° azimuth, in the X–Z plane; cameras
at 250 mm, ±12° elevation, at azimuths 25° and 28°. The two cameras of a unit sit at *different*
azimuths because the multi-view fringe order discriminates only through the ratio of their depth
sensitivities s(a) = π·sin(45° − a)/cos(a) rad/mm (1.19 and 1.04 rad/mm here, ratio 0.877): a wrong
order k shifts the predicted phase by 2πk·0.877, at least 0.77 rad for every k up to 7, which covers
the 35 mm calibrated depth (6.6 fringes at 1.19 rad/mm). Equal azimuths would make it blind.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import Field, model_validator
from pydantic_core import PydanticCustomError

from eyeserver.core.frames import is_valid_id
from eyeserver.core.validation import StrictModel, read_table, validated

Vec3 = tuple[float, float, float]


def _room_error(field: str, message: str) -> PydanticCustomError:
    """A validation error about ``field`` (a dotted path) raised by a whole-room check."""
    return PydanticCustomError("room", "{message}", {"field": field, "message": message})


class PlacementConfig(StrictModel):
    """Where a device stands and where it looks."""

    distance_mm: Annotated[float, Field(gt=0, description="distance from look_at_mm")] = 250.0
    azimuth_deg: float = Field(0.0, description="signed angle in the X–Z plane from +Z to +X")
    elevation_deg: float = Field(0.0, description="angle above the X–Z plane (towards +Y)")
    roll_deg: float = Field(0.0, description="rotation about the optical axis")
    look_at_mm: Vec3 = Field((0.0, 0.0, 0.0), description="point on the optical axis")
    position_mm: Vec3 | None = Field(None, description="explicit centre; overrides the angles")


class CameraConfig(PlacementConfig):
    """A camera: placement, lens, sensor and noise."""

    id: str
    width: Annotated[int, Field(gt=0)] = 640
    height: Annotated[int, Field(gt=0)] = 512
    focal_mm: Annotated[float, Field(gt=0)] = 25.0
    pixel_um: Annotated[float, Field(gt=0, description="pixel pitch after binning")] = 10.6
    principal_offset_px: tuple[float, float] = Field(
        (0.0, 0.0), description="principal point offset from the image centre (u, v)")
    distortion: tuple[float, float, float, float, float] = Field(
        (-0.08, 0.0, 0.0, 0.0, 0.0), description="OpenCV (k1, k2, p1, p2, k3)")
    blur_px: Annotated[float, Field(ge=0, description="defocus/optics Gaussian sigma")] = 0.7
    vignetting: Annotated[float, Field(ge=0, lt=1, description="fall-off at the corners")] = 0.25
    full_well_e: Annotated[float, Field(gt=0)] = 6000.0
    read_noise_dn: Annotated[float, Field(ge=0, description="8-bit DN")] = 1.2
    bit_depth: Literal[8, 10, 12] = 8


class ProjectorConfig(PlacementConfig):
    """A Ronchi-grating projector modelled as a pinhole."""

    id: str
    distance_mm: Annotated[float, Field(gt=0)] = 200.0
    period_mm: Annotated[float, Field(gt=0, description=(
        "fringe period on a plane through look_at_mm normal to the projector axis"))] = 2.0
    fringe_angle_deg: float = Field(0.0, description=(
        "grating line direction in the projector image: 0 = vertical lines (phase varies along x)"))
    blur_periods: Annotated[float, Field(ge=0, description=(
        "Gaussian sigma of the projected square wave, in periods"))] = 0.15
    half_field_deg: Annotated[float, Field(gt=0, lt=89)] = 20.0
    fringe_pp_dn: Annotated[float, Field(ge=0, description=(
        "fringe peak-to-peak on a white plate through look_at_mm normal to Z, 8-bit DN, centre"
        " of the image, nominal exposure, 0 dB"))] = 60.0
    aperture_mm: Annotated[float, Field(gt=0, description=(
        "diameter of the projector lens's exit pupil: what a wet eye mirrors as a glint"))] = 10.0


class UnitConfig(StrictModel):
    """An optical unit: one projector and its cameras."""

    id: str
    projector: ProjectorConfig
    cameras: list[CameraConfig]


class LightingConfig(StrictModel):
    """Light that does not come from the projectors (8-bit DN on a white surface)."""

    ambient_dn: Annotated[float, Field(ge=0)] = 20.0
    room_light_dn: Annotated[float, Field(ge=0, description=(
        "with the room lights on, e.g. for chessboards"))] = 170.0
    exposure_ref_us: Annotated[float, Field(gt=0, description=(
        "exposure at which the DN figures hold; brightness scales linearly"))] = 10_000.0


class RenderConfig(StrictModel):
    """Numerical choices of the renderer."""

    supersample: Annotated[int, Field(ge=1, le=12, description=(
        "s: pixels straddling an edge integrate s² rays (still scenes)"))] = 4
    supersample_chessboard: Annotated[int, Field(ge=1, le=12, description=(
        "the same for chessboards, whose corners calibration locates to < 0.1 px"))] = 8
    supersample_moving: Annotated[int, Field(ge=1, le=4, description=(
        "the same for a moving eye (the live path: 1 = one ray per pixel)"))] = 1


class RoomConfig(StrictModel):
    """The whole simulated room."""

    seed: int = 0
    units: list[UnitConfig]
    lighting: LightingConfig = LightingConfig()
    render: RenderConfig = RenderConfig()

    @model_validator(mode="after")
    def _ids_unique_and_legal(self) -> RoomConfig:
        # Whole-room checks have no field of their own; the error's context names the one at
        # fault (``room_from_dict`` reports it), since a model validator's location is the root.
        seen: dict[str, str] = {}
        if not self.units:
            raise _room_error("units", "the room needs at least one unit")
        for i, unit in enumerate(self.units):
            named = [(f"units.{i}.id", unit.id), (f"units.{i}.projector.id", unit.projector.id),
                     *((f"units.{i}.cameras.{j}.id", c.id) for j, c in enumerate(unit.cameras))]
            for where, name in named:
                if not is_valid_id(name):
                    raise _room_error(where, f"id {name!r} must be letters, digits, '-' or '_'")
                if name in seen:
                    raise _room_error(where, f"id {name!r} is used twice (also at {seen[name]})")
                seen[name] = where
            if not unit.cameras:
                raise _room_error(f"units.{i}.cameras", f"unit {unit.id!r} has no camera")
        return self

    def cameras(self) -> list[CameraConfig]:
        """All cameras in unit order."""
        return [c for u in self.units for c in u.cameras]

    def projectors(self) -> list[ProjectorConfig]:
        """All projectors in unit order."""
        return [u.projector for u in self.units]


def _default_units() -> list[dict[str, Any]]:
    # Left unit on the patient's left (+X), right unit on the patient's right (−X); S1/S3 above the
    # projector plane, S2/S4 below, at different azimuths (see the module docstring).
    units = []
    for unit_id, sign, proj, cams in (("left", 1.0, "P1", ("S1", "S2")),
                                      ("right", -1.0, "P2", ("S3", "S4"))):
        units.append({
            "id": unit_id,
            "projector": {"id": proj, "azimuth_deg": 45.0 * sign},
            "cameras": [
                {"id": cams[0], "azimuth_deg": 25.0 * sign, "elevation_deg": 12.0},
                {"id": cams[1], "azimuth_deg": 28.0 * sign, "elevation_deg": -12.0},
            ],
        })
    return units


def _merge(base: Any, override: Any) -> Any:
    """Deep-merge ``override`` onto ``base``; lists of units/cameras merge by ``id``."""
    if isinstance(base, dict) and isinstance(override, dict):
        merged = dict(base)
        for key, value in override.items():
            merged[key] = _merge(base[key], value) if key in base else value
        return merged
    if (isinstance(base, list) and isinstance(override, list)
            and all(isinstance(x, dict) and isinstance(x.get("id"), str) for x in base + override)):
        by_id = {x["id"]: x for x in base}
        return [_merge(by_id[x["id"]], x) if x["id"] in by_id else x for x in override]
    return override


def default_room_dict() -> dict[str, Any]:
    """The default room as plain data (what an empty room file means)."""
    return {"seed": 0, "units": _default_units()}


def room_from_dict(data: dict[str, Any], source: str = "<room>") -> RoomConfig:
    """Build a room from overrides of the default room.

    A ``units`` list in ``data`` replaces the default units, except that entries whose ``id``
    matches a default unit (and cameras whose ``id`` matches) are merged onto it, so a room file
    can change one camera's lens without restating the rig.
    """
    merged = _merge(default_room_dict(), data)
    return validated(RoomConfig, merged, source, "docs/room-file.md")


def load_room(path: str | Path | None) -> RoomConfig:
    """Read a room file (TOML, or JSON by extension); ``None`` gives the default room."""
    if path is None:
        return room_from_dict({})
    return room_from_dict(read_table(path, "room file"), str(path))
