"""The room file: the default room, loading, merging by id, errors, and the example rigs.

``docs/room-file.md`` documents the format; ``examples/rooms/`` holds the rigs checked here.
"""

from __future__ import annotations

import functools
import json
import math
import tomllib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from eyeserver.core.types import F32
from eyeserver.errors import FormatError
from eyeserver.hardware.sim.config import (
    RoomConfig,
    default_room_dict,
    load_room,
    room_from_dict,
)
from eyeserver.hardware.sim.room import SimRoom
from eyeserver.hardware.sim.scenes import SceneSpec

REPO = Path(__file__).resolve().parents[1]
EXAMPLES_DIR = REPO / "examples" / "rooms"
EXAMPLES = sorted(EXAMPLES_DIR.glob("*.toml"))


def _write(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path


# --- the default room ---------------------------------------------------------------------------


def test_the_default_room_is_load_room_none() -> None:
    default = load_room(None)

    assert default == room_from_dict({})
    assert default == RoomConfig.model_validate(default_room_dict())


def test_the_default_room_is_the_documented_rig() -> None:
    room = load_room(None)

    assert [(u.id, u.projector.id, [c.id for c in u.cameras]) for u in room.units] == [
        ("left", "P1", ["S1", "S2"]), ("right", "P2", ["S3", "S4"])]
    for unit, sign in zip(room.units, (1.0, -1.0), strict=True):
        p = unit.projector
        assert (p.distance_mm, p.azimuth_deg, p.elevation_deg) == (200.0, 45.0 * sign, 0.0)
        assert (p.period_mm, p.fringe_angle_deg, p.blur_periods, p.fringe_pp_dn) == \
            (2.0, 0.0, 0.15, 60.0)
        upper, lower = unit.cameras
        assert (upper.distance_mm, upper.azimuth_deg, upper.elevation_deg) == \
            (250.0, 25.0 * sign, 12.0)
        assert (lower.distance_mm, lower.azimuth_deg, lower.elevation_deg) == \
            (250.0, 28.0 * sign, -12.0)
    for cam in room.cameras():  # the noise model of docs/design.md §3
        assert (cam.width, cam.height, cam.focal_mm, cam.pixel_um) == (640, 512, 25.0, 10.6)
        assert cam.distortion == (-0.08, 0.0, 0.0, 0.0, 0.0)
        assert (cam.blur_px, cam.vignetting, cam.full_well_e, cam.read_noise_dn,
                cam.bit_depth) == (0.7, 0.25, 6000.0, 1.2, 8)
    assert room.lighting.ambient_dn == 20.0


@pytest.mark.parametrize(("name", "text"), [("empty.toml", ""), ("empty.json", "{}")])
def test_an_empty_room_file_is_the_default_room(tmp_path: Path, name: str, text: str) -> None:
    assert load_room(_write(tmp_path / name, text)) == load_room(None)


# --- loading ------------------------------------------------------------------------------------


def test_there_are_example_rooms() -> None:
    assert {"wide.toml", "horizontal.toml"} <= {p.name for p in EXAMPLES}


@pytest.mark.parametrize("path", EXAMPLES, ids=lambda p: p.stem)
def test_every_example_room_loads(path: Path) -> None:
    room = load_room(path)

    assert room != load_room(None)
    assert room.cameras()
    SimRoom(room)  # the renderer accepts it (every device placed, every model built)


def test_the_example_rigs_are_what_their_files_say() -> None:
    wide = load_room(EXAMPLES_DIR / "wide.toml")
    assert [p.azimuth_deg for p in wide.projectors()] == [40.0, -40.0]
    assert {p.period_mm for p in wide.projectors()} == {2.4}
    assert {c.distance_mm for c in wide.cameras()} == {280.0}
    assert {abs(c.elevation_deg) for c in wide.cameras()} == {15.0}
    assert all(c.distortion[:2] == (-0.15, 0.05) and c.distortion[2:4] != (0.0, 0.0)
               and c.roll_deg != 0 and c.principal_offset_px != (0.0, 0.0)
               for c in wide.cameras())

    horizontal = load_room(EXAMPLES_DIR / "horizontal.toml")
    (unit,) = horizontal.units
    assert (unit.projector.azimuth_deg, unit.projector.elevation_deg,
            unit.projector.fringe_angle_deg) == (0.0, 40.0, 90.0)
    assert {c.bit_depth for c in unit.cameras} == {12}
    assert len({c.elevation_deg for c in unit.cameras}) == len(unit.cameras)


def _toml_text_of_overrides() -> str:
    return """
seed = 7

[lighting]
ambient_dn = 30.0

[[units]]
id = "left"
projector = { id = "P1", period_mm = 2.2 }

[[units.cameras]]
id = "S1"
bit_depth = 10
principal_offset_px = [3.0, -2.0]

[[units.cameras]]
id = "S2"
"""


def test_toml_and_json_load_alike(tmp_path: Path) -> None:
    text = _toml_text_of_overrides()
    from_toml = load_room(_write(tmp_path / "room.toml", text))
    from_json = load_room(_write(tmp_path / "room.json", json.dumps(tomllib.loads(text))))

    assert from_toml == from_json
    assert from_toml.seed == 7
    assert from_toml.lighting.ambient_dn == 30.0
    assert from_toml.units[0].projector.period_mm == 2.2
    assert from_toml.units[0].cameras[0].bit_depth == 10
    assert from_toml.units[0].cameras[0].principal_offset_px == (3.0, -2.0)


@pytest.mark.parametrize("path", EXAMPLES, ids=lambda p: p.stem)
def test_every_example_room_reads_the_same_as_json(path: Path, tmp_path: Path) -> None:
    as_json = _write(tmp_path / f"{path.stem}.json", json.dumps(tomllib.loads(path.read_text())))

    assert load_room(as_json) == load_room(path)


# --- merging onto the default room --------------------------------------------------------------


def test_a_partial_override_changes_one_camera_only(tmp_path: Path) -> None:
    # Every unit and camera that should stay is named by id; only S1's focal length changes.
    text = """
[[units]]
id = "left"
cameras = [{ id = "S1", focal_mm = 35.0 }, { id = "S2" }]

[[units]]
id = "right"
"""
    room = load_room(_write(tmp_path / "room.toml", text))

    expected = load_room(None).model_dump()
    expected["units"][0]["cameras"][0]["focal_mm"] = 35.0
    assert room.model_dump() == expected


def test_a_units_list_replaces_the_default_units(tmp_path: Path) -> None:
    one_unit = load_room(_write(tmp_path / "one.toml", '[[units]]\nid = "left"\n'))
    assert [u.id for u in one_unit.units] == ["left"]
    assert one_unit.units[0] == load_room(None).units[0]

    one_camera = load_room(_write(tmp_path / "cam.toml",
                                  '[[units]]\nid = "right"\ncameras = [{ id = "S4" }]\n'))
    assert [c.id for c in one_camera.cameras()] == ["S4"]
    assert one_camera.cameras()[0] == load_room(None).cameras()[3]


def test_a_unit_with_a_new_id_starts_from_the_schema_defaults() -> None:
    room = room_from_dict({"units": [{"id": "solo", "projector": {"id": "PX"},
                                      "cameras": [{"id": "CX", "azimuth_deg": 20.0}]}]})

    (unit,) = room.units
    assert (unit.projector.distance_mm, unit.projector.azimuth_deg) == (200.0, 0.0)
    assert (unit.cameras[0].distance_mm, unit.cameras[0].elevation_deg) == (250.0, 0.0)


def test_reordering_units_follows_the_room_file() -> None:
    room = room_from_dict({"units": [{"id": "right"}, {"id": "left"}]})

    assert [c.id for c in room.cameras()] == ["S3", "S4", "S1", "S2"]


# --- errors -------------------------------------------------------------------------------------

ERROR_CASES: list[Any] = [
    pytest.param("room.toml", "[lighting]\nambient = 3.0\n", "lighting.ambient", "unknown key",
                 id="unknown-key"),
    pytest.param("room.toml", '[[units]]\nid = "left"\ncameras = [{ id = "S1", focal = 35.0 }]\n',
                 "units.0.cameras.0.focal", "unknown key", id="unknown-camera-key"),
    pytest.param("room.toml", 'seed = "zero"\n', "seed", "integer", id="wrong-type"),
    pytest.param("room.toml",
                 '[[units]]\nid = "left"\ncameras = [{ id = "S1", focal_mm = "long" }]\n',
                 "units.0.cameras.0.focal_mm", "number", id="wrong-type-camera"),
    pytest.param("room.toml",
                 '[[units]]\nid = "left"\n[[units]]\nid = "right"\n'
                 'cameras = [{ id = "S1" }]\n',
                 "units.1.cameras.0.id", "'S1' is used twice", id="duplicate-id"),
    pytest.param("room.toml",
                 '[[units]]\nid = "left"\nprojector = { id = "P1", distance_mm = -200.0 }\n',
                 "units.0.projector.distance_mm", "greater than 0", id="negative-distance"),
    pytest.param("room.toml",
                 '[[units]]\nid = "left"\ncameras = [{ id = "S1", bit_depth = 9 }]\n',
                 "units.0.cameras.0.bit_depth", "8, 10 or 12", id="bad-bit-depth"),
    pytest.param("room.toml", "units = []\n", "units", "at least one unit", id="no-unit"),
    pytest.param("room.toml", '[[units]]\nid = "left"\ncameras = []\n', "units.0.cameras",
                 "no camera", id="no-camera"),
    pytest.param("room.toml", '[[units]]\nid = "left"\nprojector = { id = "P 1" }\n',
                 "units.0.projector.id", "letters, digits", id="illegal-id"),
    pytest.param("room.json", '{"lighting": {"ambient_dn": "bright"}}', "lighting.ambient_dn",
                 "number", id="json-wrong-type"),
]


@pytest.mark.parametrize(("name", "text", "field", "reason"), ERROR_CASES)
def test_a_bad_value_names_the_file_and_the_field(tmp_path: Path, name: str, text: str,
                                                  field: str, reason: str) -> None:
    path = _write(tmp_path / name, text)

    with pytest.raises(FormatError) as caught:
        load_room(path)

    error = caught.value
    assert error.path == str(path)
    assert error.field == field
    assert reason in error.reason
    assert str(path) in str(error)
    assert f"'{field}'" in str(error)


def _unreadable_cases(tmp_path: Path) -> Iterator[tuple[Path, str]]:
    yield tmp_path / "missing.toml", "cannot read"
    yield tmp_path, "cannot read"  # a directory
    yield _write(tmp_path / "bad.toml", "units = [\n"), "not valid toml"
    yield _write(tmp_path / "bad.json", '{"seed": 1,,}'), "not valid json"
    yield _write(tmp_path / "list.json", "[1, 2]"), "must hold a table"
    latin1 = tmp_path / "latin1.toml"
    latin1.write_bytes('# pièce\nseed = 1\n'.encode("latin-1"))
    yield latin1, "not valid toml"


def test_an_unreadable_or_malformed_file_is_a_format_error(tmp_path: Path) -> None:
    for path, reason in _unreadable_cases(tmp_path):
        with pytest.raises(FormatError) as caught:
            load_room(path)
        error = caught.value
        assert error.path == str(path), path
        assert error.field is None, path
        assert reason in error.reason.lower(), (path, error.reason)
        assert str(error).startswith(str(path)), path


# --- the example rigs render as their files say -------------------------------------------------


@functools.cache
def _plate_room(path: Path) -> SimRoom:
    """The example room with the flat calibration plate at Z = 0 (rendered once per camera)."""
    room = SimRoom(load_room(path))
    room.set_scene(SceneSpec(kind="plate"))
    return room


def _camera_cases() -> Iterator[Any]:
    for path in EXAMPLES:
        for unit in load_room(path).units:
            for camera in unit.cameras:
                yield pytest.param(path, unit.projector.id, camera.id,
                                   id=f"{path.stem}-{camera.id}")


def _dominant_frequency(image: F32, u0: float, v0: float) -> tuple[float, float]:
    """``(f_u, f_v)`` in cycles per pixel of the strongest non-DC peak of a Hann-windowed 2-D FFT
    of the square of side ``min(height, width) / 2`` centred (as far as it fits) on (u0, v0)."""
    height, width = image.shape
    side = min(height, width) // 2
    top = int(np.clip(round(v0) - side // 2, 0, height - side))
    left = int(np.clip(round(u0) - side // 2, 0, width - side))
    window = image[top:top + side, left:left + side].astype(np.float64)
    taper = np.hanning(side)
    window = (window - window.mean()) * np.outer(taper, taper)
    spectrum = np.abs(np.fft.rfft2(window))
    f_v = np.fft.fftfreq(side)[:, None]
    f_u = np.fft.rfftfreq(side)[None, :]
    spectrum[np.hypot(f_u, f_v) < 2.5 / side] = 0.0  # DC and the envelope's leakage
    i, j = np.unravel_index(int(np.argmax(spectrum)), spectrum.shape)
    return float(f_u[0, j]), float(f_v[i, 0])


@pytest.mark.slow
@pytest.mark.parametrize(("path", "projector_id", "camera_id"), list(_camera_cases()))
def test_the_plate_shows_fringes_as_the_room_file_says(path: Path, projector_id: str,
                                                       camera_id: str) -> None:
    room = _plate_room(path)
    projector = next(p for p in room.config.projectors() if p.id == projector_id)
    components = room.components(camera_id, projectors=[projector_id])
    fringe = components.fringe[projector_id]
    height, width = fringe.shape

    # The camera sees the lit plate at the origin.
    u0, v0 = room.renderer.cameras[camera_id].project(np.zeros((1, 3)))[0]
    assert 0 <= u0 < width and 0 <= v0 < height
    i0, j0 = round(v0), round(u0)
    assert components.ambient[i0, j0] > 0.5  # the white plate, not the black background
    assert fringe[i0 - 30:i0 + 31, j0 - 30:j0 + 31].max() > 20.0

    f_u, f_v = _dominant_frequency(fringe, u0, v0)
    period_px = 1.0 / math.hypot(f_u, f_v)
    assert 6.0 <= period_px <= 60.0

    # Vertical fringes (grating at 0°) vary along the columns u, horizontal ones (90°) along the
    # rows v; camera roll and perspective tilt them by a few degrees at most.
    across = math.degrees(math.atan2(abs(f_v), abs(f_u)))  # 0: along u, 90: along v
    grating = projector.fringe_angle_deg % 180.0
    if grating not in (0.0, 90.0):
        pytest.skip(f"only vertical or horizontal gratings are checked, not {grating}°")
    assert abs(across - grating) < 15.0, (f_u, f_v)
