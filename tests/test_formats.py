"""Round trips and validation rules of eyeserver.io (FORMATS.md)."""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from eyeserver.errors import FormatError
from eyeserver.io import (
    Bundle,
    BundleFrameData,
    BundleKind,
    ChessboardSpec,
    PointCloud,
    RigSpec,
    atomic_write_bytes,
    atomic_write_text,
    bundle_hash,
    check_rig,
    makedirs_synced,
    read_bundle,
    read_ply,
    read_rig,
    rig_from_dict,
    write_bundle,
    write_ply,
    write_rig,
)

WIDTH, HEIGHT = 12, 8

Document = dict[str, Any]
Mutation = Callable[[Document], object]


def rig_document() -> Document:
    """Two units lit in turn: P1 with S1, S2 and P2 with S3, S4."""
    return {
        "format": "eyeserver.rig/1",
        "cameras": [{"id": f"S{n}", "width": WIDTH, "height": HEIGHT} for n in range(1, 5)],
        "projectors": [{"id": "P1"}, {"id": "P2"}],
        "units": [
            {"id": "left", "projector": "P1", "cameras": ["S1", "S2"]},
            {"id": "right", "projector": "P2", "cameras": ["S3", "S4"]},
        ],
    }


@pytest.fixture
def rig() -> RigSpec:
    return rig_from_dict(rig_document(), "test")


def assert_names(error: FormatError, path: Path, field: str | None) -> None:
    """The message names the file and the field, as FORMATS.md asks."""
    message = str(error)
    assert str(path) in message
    assert error.field == field
    if field is not None:
        assert f"field '{field}'" in message


def test_format_error_names_file_and_field() -> None:
    error = FormatError(Path("/data/rig.json"), "units[1].cameras[0]", "no camera 'S9'")
    assert str(error) == "/data/rig.json: field 'units[1].cameras[0]': no camera 'S9'"


# --- atomic writes --------------------------------------------------------------------------


def test_atomic_write_replaces_and_leaves_no_temporary(tmp_path: Path) -> None:
    target = tmp_path / "state.bin"
    atomic_write_bytes(target, b"old")
    atomic_write_bytes(target, b"new content")
    assert target.read_bytes() == b"new content"
    atomic_write_text(tmp_path / "note.txt", "zürich\r\n")
    assert (tmp_path / "note.txt").read_bytes() == "zürich\r\n".encode()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["note.txt", "state.bin"]


def test_atomic_write_failure_keeps_old_content(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    target = tmp_path / "state.bin"
    atomic_write_bytes(target, b"old")

    def failing_replace(source: object, destination: object) -> None:
        raise OSError("disk gone")

    monkeypatch.setattr(os, "replace", failing_replace)
    with pytest.raises(OSError, match="disk gone"):
        atomic_write_bytes(target, b"new")
    assert target.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["state.bin"]


# --- rig file -------------------------------------------------------------------------------


def test_rig_round_trip(tmp_path: Path, rig: RigSpec) -> None:
    path = tmp_path / "rig.json"
    write_rig(path, rig)
    again = read_rig(path)
    assert again == rig
    assert json.loads(path.read_text()) == rig_document()
    assert again.to_dict() == rig_document()


def test_rig_helpers(rig: RigSpec) -> None:
    assert rig.camera_ids == ("S1", "S2", "S3", "S4")
    assert rig.projector_ids == ("P1", "P2")
    assert rig.camera("S3").width == WIDTH
    assert rig.camera_index("S3") == 2
    assert rig.unit_of_camera("S3").id == "right"
    assert rig.unit_of_projector("P1").cameras == ("S1", "S2")
    assert rig.unit("left").projector == "P1"
    for lookup in (rig.camera, rig.camera_index, rig.unit_of_camera, rig.unit_of_projector):
        with pytest.raises(KeyError):
            lookup("nope")


def test_rig_ignores_unknown_keys(tmp_path: Path, rig: RigSpec) -> None:
    document = rig_document()
    document["comment"] = "lab bench"
    document["cameras"][0]["serial"] = "1234"
    document["units"][0]["note"] = {"any": "thing"}
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(document))
    assert read_rig(path) == rig


def _set(path: list[str | int], value: object) -> Mutation:
    def mutate(document: Document) -> None:
        target: Any = document
        for key in path[:-1]:
            target = target[key]
        target[path[-1]] = value

    return mutate


def _delete(path: list[str | int]) -> Mutation:
    def mutate(document: Document) -> None:
        target: Any = document
        for key in path[:-1]:
            target = target[key]
        del target[path[-1]]

    return mutate


RIG_RULES: list[tuple[str, Mutation, str, str]] = [
    ("wrong format", _set(["format"], "eyeserver.rig/2"), "format", "eyeserver.rig/1"),
    ("missing format", _delete(["format"]), "format", "missing"),
    ("cameras not a list", _set(["cameras"], {"S1": {}}), "cameras", "array"),
    ("no cameras", _set(["cameras"], []), "cameras", "at least one camera"),
    ("camera not an object", _set(["cameras", 1], "S2"), "cameras[1]", "object"),
    ("illegal id", _set(["cameras", 0, "id"], "S 1"), "cameras[0].id", "legal id"),
    ("id too long", _set(["cameras", 0, "id"], "S" * 65), "cameras[0].id", "legal id"),
    ("id not a string", _set(["cameras", 0, "id"], 1), "cameras[0].id", "string"),
    ("duplicate camera", _set(["cameras", 1, "id"], "S1"), "cameras[1].id", "duplicate"),
    ("zero width", _set(["cameras", 0, "width"], 0), "cameras[0].width", "positive"),
    ("negative height", _set(["cameras", 2, "height"], -5), "cameras[2].height", "positive"),
    ("fractional width", _set(["cameras", 0, "width"], 640.0), "cameras[0].width", "integer"),
    ("boolean width", _set(["cameras", 0, "width"], True), "cameras[0].width", "integer"),
    ("missing height", _delete(["cameras", 3, "height"]), "cameras[3].height", "missing"),
    ("duplicate projector", _set(["projectors", 1, "id"], "P1"), "projectors[1].id", "duplicate"),
    ("duplicate unit", _set(["units", 1, "id"], "left"), "units[1].id", "duplicate"),
    ("unknown projector", _set(["units", 0, "projector"], "P9"), "units[0].projector", "P9"),
    ("projector twice", _set(["units", 1, "projector"], "P1"), "units[1].projector", "left"),
    ("unknown camera", _set(["units", 1, "cameras", 0], "S9"), "units[1].cameras[0]", "S9"),
    ("camera twice", _set(["units", 1, "cameras", 0], "S1"), "units[1].cameras[0]", "left"),
    ("unit without cameras", _set(["units", 0, "cameras"], []), "units[0].cameras", "at least"),
    ("unit cameras missing", _delete(["units", 0, "cameras"]), "units[0].cameras", "missing"),
    ("camera in no unit", _set(["units", 1, "cameras"], ["S3"]), "cameras[3]", "no unit"),
    (
        "projector in no unit",
        _set(["units"], [{"id": "all", "projector": "P1", "cameras": ["S1", "S2", "S3", "S4"]}]),
        "projectors[1]",
        "no unit",
    ),
]


@pytest.mark.parametrize(
    ("mutate", "field", "reason"),
    [rule[1:] for rule in RIG_RULES],
    ids=[rule[0] for rule in RIG_RULES],
)
def test_rig_rule(tmp_path: Path, mutate: Mutation, field: str, reason: str) -> None:
    document = rig_document()
    mutate(document)
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(document))
    with pytest.raises(FormatError, match=reason) as caught:
        read_rig(path)
    assert_names(caught.value, path, field)


@pytest.mark.parametrize(
    ("content", "reason"),
    [("[]", "must be an object"), ("{", "not valid JSON"), ('{"x": NaN}', "not valid JSON")],
)
def test_rig_file_not_an_object(tmp_path: Path, content: str, reason: str) -> None:
    path = tmp_path / "rig.json"
    path.write_text(content)
    with pytest.raises(FormatError, match=reason) as caught:
        read_rig(path)
    assert_names(caught.value, path, None)


def test_rig_file_missing(tmp_path: Path) -> None:
    with pytest.raises(FormatError, match="not found") as caught:
        read_rig(tmp_path / "absent.json")
    assert_names(caught.value, tmp_path / "absent.json", None)


def test_write_rig_refuses_invalid_rig(tmp_path: Path, rig: RigSpec) -> None:
    orphan = RigSpec(rig.cameras, rig.projectors, rig.units[:1])
    with pytest.raises(ValueError, match=r"cameras\[2\]"):
        check_rig(orphan)
    with pytest.raises(ValueError, match="belongs to no unit"):
        write_rig(tmp_path / "rig.json", orphan)
    assert not (tmp_path / "rig.json").exists()


# --- capture bundles ------------------------------------------------------------------------


def image(dtype: type[np.uint8] | type[np.uint16], seed: int, peak: int | None = None) -> Any:
    generator = np.random.default_rng(seed)
    high = peak if peak is not None else int(np.iinfo(dtype).max)
    return generator.integers(0, high, size=(HEIGHT, WIDTH), endpoint=True).astype(dtype)


def interleaved_frames(
    dtype: type[np.uint8] | type[np.uint16], z_mm: float | None = None
) -> list[BundleFrameData]:
    """Frame 0 lights P1 and holds S1, S2; frame 1 lights P2 and holds S3, S4 (FORMATS.md)."""
    return [
        BundleFrameData(
            images={"S1": image(dtype, 1), "S2": image(dtype, 2)},
            z_mm=z_mm,
            projectors_on=("P1",),
            t_ns=1_000,
        ),
        BundleFrameData(
            images={"S3": image(dtype, 3), "S4": image(dtype, 4)},
            z_mm=z_mm,
            projectors_on=("P2",),
            t_ns=2_000,
        ),
    ]


def make_bundle(directory: Path, rig: RigSpec, kind: BundleKind = "measurement") -> Bundle:
    z_mm = 3.0 if kind in ("plate", "reference") else None
    chessboard = ChessboardSpec(9, 6, 4.5, origin=True) if kind == "chessboard" else None
    frames = interleaved_frames(np.uint8, z_mm)
    if kind == "chessboard":
        frames = [BundleFrameData(images={"S1": image(np.uint8, 5), "S3": image(np.uint8, 6)})]
    return write_bundle(
        directory, kind, rig, frames, chessboard=chessboard, created="2026-11-23T10:00:00Z"
    )


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_bundle_round_trip(
    tmp_path: Path, rig: RigSpec, dtype: type[np.uint8] | type[np.uint16]
) -> None:
    frames = interleaved_frames(dtype, z_mm=3.0)
    written = write_bundle(
        tmp_path / "plate",
        "plate",
        rig,
        frames,
        created="2026-11-23T10:00:00Z",
        extra={"simulation": {"seed": 7, "truth": [1.0, 2.0]}},
    )
    bundle = read_bundle(tmp_path / "plate")
    assert bundle == written
    assert bundle.kind == "plate"
    assert bundle.rig == rig
    assert bundle.created == "2026-11-23T10:00:00Z"
    assert bundle.bit_depth is None
    assert bundle.extra == {"simulation": {"seed": 7, "truth": [1.0, 2.0]}}
    assert bundle.frame_indices == (0, 1)
    assert bundle.frame(1).images == {"S3": "S3_0001.png", "S4": "S4_0001.png"}
    assert bundle.frame(1).z_mm == 3.0
    assert bundle.frame(1).t_ns == 2_000
    assert bundle.frame(0).projectors_on == ("P1",)
    for position, frame in enumerate(frames):
        for camera_id, pixels in frame.images.items():
            loaded = bundle.load_image(position, camera_id)
            assert loaded.dtype == dtype
            np.testing.assert_array_equal(loaded, pixels)


def test_bundle_fringe_images_follow_each_cameras_own_unit(tmp_path: Path, rig: RigSpec) -> None:
    frames = [
        BundleFrameData(
            images={"S1": image(np.uint8, 1), "S3": image(np.uint8, 2)}, projectors_on=("P1",)
        ),
        BundleFrameData(
            images={"S2": image(np.uint8, 3), "S4": image(np.uint8, 4)}, projectors_on=("P1", "P2")
        ),
        BundleFrameData(images={"S1": image(np.uint8, 5)}),
    ]
    bundle = write_bundle(tmp_path / "m", "measurement", rig, frames)
    # S3 sees P1's light in frame 0 but P1 is not its unit's projector.
    assert bundle.fringe_images() == [(0, "S1"), (1, "S2"), (1, "S4")]
    assert bundle.is_fringe_image(0, "S1")
    assert not bundle.is_fringe_image(0, "S3")
    assert not bundle.is_fringe_image(2, "S1")
    assert bundle.cameras_in_frame(0) == ("S1", "S3")
    assert bundle.cameras_in_frame(2) == ("S1",)
    with pytest.raises(KeyError):
        bundle.cameras_in_frame(7)
    with pytest.raises(KeyError):
        bundle.load_image(2, "S2")


def test_chessboard_bundle_round_trip(tmp_path: Path, rig: RigSpec) -> None:
    bundle = make_bundle(tmp_path / "board", rig, "chessboard")
    assert read_bundle(tmp_path / "board").chessboard == ChessboardSpec(9, 6, 4.5, origin=True)
    assert bundle.fringe_images() == []
    assert "z_mm" not in json.loads((tmp_path / "board" / "bundle.json").read_text())["frames"][0]


def test_bundle_with_bit_depth_keeps_values_unshifted(tmp_path: Path, rig: RigSpec) -> None:
    pixels = image(np.uint16, 9, peak=4095)
    bundle = write_bundle(
        tmp_path / "b",
        "measurement",
        rig,
        [BundleFrameData(images={"S1": pixels}, projectors_on=("P1",))],
        bit_depth=12,
    )
    assert bundle.bit_depth == 12
    np.testing.assert_array_equal(bundle.load_image(0, "S1"), pixels)


def test_bundle_ignores_unknown_keys(tmp_path: Path, rig: RigSpec) -> None:
    directory = tmp_path / "b"
    make_bundle(directory, rig)
    edit_bundle_json(directory, _set(["frames", 0, "exposure_us"], 800))
    edit_bundle_json(directory, _set(["rig", "site"], "room 2"))
    bundle = read_bundle(directory)
    assert bundle.extra == {}
    assert bundle.rig == rig


def test_bundle_hash_is_stable_and_content_sensitive(tmp_path: Path, rig: RigSpec) -> None:
    first = make_bundle(tmp_path / "a", rig)
    make_bundle(tmp_path / "b", rig)
    digest = bundle_hash(first.path)
    assert len(digest) == 64
    assert bundle_hash(tmp_path / "b") == digest
    changed = image(np.uint8, 1)
    changed[0, 0] ^= 1
    cv2.imwrite(str(first.path / "S1_0000.png"), changed)
    assert bundle_hash(first.path) != digest


def test_write_bundle_refuses_to_overwrite(tmp_path: Path, rig: RigSpec) -> None:
    directory = tmp_path / "b"
    make_bundle(directory, rig)
    before = bundle_hash(directory)
    with pytest.raises(FileExistsError, match="overwrite=True"):
        make_bundle(directory, rig, "reference")
    assert bundle_hash(directory) == before
    replaced = write_bundle(
        directory, "reference", rig, interleaved_frames(np.uint16, z_mm=0.0), overwrite=True
    )
    assert replaced.kind == "reference"
    assert read_bundle(directory).kind == "reference"
    assert [p.name for p in tmp_path.iterdir()] == ["b"]


def test_write_bundle_fills_an_empty_directory(tmp_path: Path, rig: RigSpec) -> None:
    (tmp_path / "b").mkdir()
    assert make_bundle(tmp_path / "b", rig).kind == "measurement"
    (tmp_path / "file").write_text("x")
    with pytest.raises(FileExistsError, match="not a directory"):
        make_bundle(tmp_path / "file", rig)


def test_write_bundle_crash_leaves_nothing(
    tmp_path: Path, rig: RigSpec, monkeypatch: pytest.MonkeyPatch
) -> None:
    import eyeserver.io.bundle as bundle_module

    encode = bundle_module._encode_png
    calls = []

    def failing_encode(pixels: Any, name: str) -> bytes:
        calls.append(name)
        if len(calls) == 3:
            raise RuntimeError("power cut")
        return encode(pixels, name)

    monkeypatch.setattr(bundle_module, "_encode_png", failing_encode)
    with pytest.raises(RuntimeError, match="power cut"):
        make_bundle(tmp_path / "b", rig)
    assert list(tmp_path.iterdir()) == []


WRITER_RULES: list[tuple[str, BundleKind, Callable[[], list[BundleFrameData]], str]] = [
    ("no frames", "measurement", lambda: [], "at least one frame"),
    (
        "unknown camera",
        "measurement",
        lambda: [BundleFrameData(images={"S9": image(np.uint8, 0)})],
        "no camera 'S9'",
    ),
    (
        "wrong shape",
        "measurement",
        lambda: [BundleFrameData(images={"S1": np.zeros((HEIGHT, WIDTH + 1), np.uint8)})],
        "shape",
    ),
    (
        "colour image",
        "measurement",
        lambda: [BundleFrameData(images={"S1": np.zeros((HEIGHT, WIDTH, 3), np.uint8)})],
        "shape",
    ),
    (
        "float image",
        "measurement",
        lambda: [BundleFrameData(images={"S1": np.zeros((HEIGHT, WIDTH), np.float32)})],  # type: ignore[dict-item]
        "uint8 or uint16",
    ),
    (
        "unknown projector",
        "measurement",
        lambda: [BundleFrameData(images={}, projectors_on=("P7",))],
        "no projector 'P7'",
    ),
    ("plate without z", "plate", lambda: [BundleFrameData(images={})], "z_mm"),
    ("z in measurement", "measurement", lambda: [BundleFrameData(images={}, z_mm=1.0)], "z_mm"),
    ("nan z", "reference", lambda: [BundleFrameData(images={}, z_mm=float("nan"))], "finite"),
    ("board without chessboard", "chessboard", lambda: [BundleFrameData(images={})], "chessboard"),
]


@pytest.mark.parametrize(
    ("kind", "frames", "reason"),
    [rule[1:] for rule in WRITER_RULES],
    ids=[rule[0] for rule in WRITER_RULES],
)
def test_write_bundle_rejects_invalid_input(
    tmp_path: Path,
    rig: RigSpec,
    kind: BundleKind,
    frames: Callable[[], list[BundleFrameData]],
    reason: str,
) -> None:
    with pytest.raises(ValueError, match=reason):
        write_bundle(tmp_path / "b", kind, rig, frames())
    assert list(tmp_path.iterdir()) == []


def test_write_bundle_rejects_bad_options(tmp_path: Path, rig: RigSpec) -> None:
    frames = interleaved_frames(np.uint16)
    with pytest.raises(ValueError, match="bit_depth"):
        write_bundle(tmp_path / "b", "measurement", rig, frames, bit_depth=10)
    with pytest.raises(ValueError, match="bit_depth must be"):
        write_bundle(tmp_path / "b", "measurement", rig, frames, bit_depth=16)
    with pytest.raises(ValueError, match="needs a 16-bit PNG"):
        write_bundle(tmp_path / "b", "measurement", rig, interleaved_frames(np.uint8), bit_depth=10)
    with pytest.raises(ValueError, match=r"defined by FORMATS\.md"):
        write_bundle(tmp_path / "b", "measurement", rig, frames, extra={"kind": "plate"})
    with pytest.raises(ValueError, match="strict JSON"):
        write_bundle(tmp_path / "b", "measurement", rig, frames, extra={"x": object()})
    with pytest.raises(ValueError, match="ISO 8601"):
        write_bundle(tmp_path / "b", "measurement", rig, frames, created="last tuesday")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("cols", "rows", "square_mm", "reason"),
    [
        (1, 6, 4.5, "cols"),
        (9, 7, 4.5, "odd"),
        (8, 6, 4.5, "odd"),
        (9, 6, 0.0, "square_mm"),
        (9.0, 6, 4.5, "integer"),
        (9, 6, float("inf"), "square_mm"),
    ],
)
def test_chessboard_spec_rules(cols: Any, rows: Any, square_mm: Any, reason: str) -> None:
    with pytest.raises(ValueError, match=reason):
        ChessboardSpec(cols, rows, square_mm)


def edit_bundle_json(directory: Path, mutate: Mutation) -> None:
    path = directory / "bundle.json"
    document = json.loads(path.read_text())
    mutate(document)
    path.write_text(json.dumps(document))


BUNDLE_RULES: list[tuple[str, BundleKind, Mutation, str, str]] = [
    ("wrong format", "measurement", _set(["format"], "eyeserver.bundle/0"), "format", "bundle/1"),
    ("unknown kind", "measurement", _set(["kind"], "movie"), "kind", "movie"),
    ("missing kind", "measurement", _delete(["kind"]), "kind", "missing"),
    ("missing rig", "measurement", _delete(["rig"]), "rig", "missing"),
    (
        "invalid inline rig",
        "measurement",
        _set(["rig", "units", 1, "cameras", 0], "S9"),
        "rig.units[1].cameras[0]",
        "S9",
    ),
    ("inline rig format", "measurement", _delete(["rig", "format"]), "rig.format", "missing"),
    ("no frames", "measurement", _set(["frames"], []), "frames", "at least one"),
    ("frames not a list", "measurement", _set(["frames"], {}), "frames", "array"),
    ("duplicate index", "measurement", _set(["frames", 1, "index"], 0), "frames[1].index", "dup"),
    ("negative index", "measurement", _set(["frames", 0, "index"], -1), "frames[0].index", "neg"),
    (
        "absolute image path",
        "measurement",
        _set(["frames", 0, "images", "S1"], "/etc/passwd"),
        "frames[0].images.S1",
        "absolute",
    ),
    (
        "parent traversal",
        "measurement",
        _set(["frames", 0, "images", "S1"], "../outside.png"),
        "frames[0].images.S1",
        r"'\.\.'",
    ),
    (
        "nested traversal",
        "measurement",
        _set(["frames", 0, "images", "S2"], "sub/../../outside.png"),
        "frames[0].images.S2",
        r"'\.\.'",
    ),
    (
        "windows traversal",
        "measurement",
        _set(["frames", 0, "images", "S1"], "..\\outside.png"),
        "frames[0].images.S1",
        "backslash",
    ),
    (
        "windows drive",
        "measurement",
        _set(["frames", 0, "images", "S1"], "C:/outside.png"),
        "frames[0].images.S1",
        "absolute",
    ),
    (
        "empty image name",
        "measurement",
        _set(["frames", 0, "images", "S1"], ""),
        "frames[0].images.S1",
        "empty",
    ),
    (
        "image name not a string",
        "measurement",
        _set(["frames", 0, "images", "S1"], None),
        "frames[0].images.S1",
        "string",
    ),
    (
        "missing image file",
        "measurement",
        _set(["frames", 0, "images", "S1"], "S1_0099.png"),
        "frames[0].images.S1",
        "not found",
    ),
    (
        "unknown camera",
        "measurement",
        _set(["frames", 1, "images", "S9"], "S3_0001.png"),
        "frames[1].images.S9",
        "no camera 'S9'",
    ),
    (
        "unknown projector",
        "measurement",
        _set(["frames", 0, "projectors_on"], ["P1", "P3"]),
        "frames[0].projectors_on[1]",
        "no projector 'P3'",
    ),
    (
        "projector twice",
        "measurement",
        _set(["frames", 0, "projectors_on"], ["P1", "P1"]),
        "frames[0].projectors_on[1]",
        "twice",
    ),
    ("plate without z", "plate", _delete(["frames", 1, "z_mm"]), "frames[1].z_mm", "missing"),
    ("reference z text", "reference", _set(["frames", 0, "z_mm"], "3"), "frames[0].z_mm", "num"),
    ("plate z null", "plate", _set(["frames", 0, "z_mm"], None), "frames[0].z_mm", "number"),
    ("z in measurement", "measurement", _set(["frames", 0, "z_mm"], 1.0), "frames[0].z_mm", "abs"),
    ("fractional t_ns", "measurement", _set(["frames", 0, "t_ns"], 1.5), "frames[0].t_ns", "int"),
    ("board missing", "chessboard", _delete(["chessboard"]), "chessboard", "required"),
    ("board cols", "chessboard", _set(["chessboard", "cols"], 1), "chessboard.cols", "at least"),
    ("board parity", "chessboard", _set(["chessboard", "cols"], 8), "chessboard.rows", "odd"),
    (
        "board square",
        "chessboard",
        _set(["chessboard", "square_mm"], -4.5),
        "chessboard.square_mm",
        "positive",
    ),
    (
        "board rows missing",
        "chessboard",
        _delete(["chessboard", "rows"]),
        "chessboard.rows",
        "missing",
    ),
    (
        "board origin",
        "chessboard",
        _set(["chessboard", "origin"], "yes"),
        "chessboard.origin",
        "true or false",
    ),
    ("bit depth 16", "measurement", _set(["bit_depth"], 16), "bit_depth", "8, 10 or 12"),
    ("created text", "measurement", _set(["created"], "last tuesday"), "created", "ISO 8601"),
    ("created number", "measurement", _set(["created"], 20261123), "created", "string"),
    ("created missing", "measurement", _delete(["created"]), "created", "missing"),
]


@pytest.mark.parametrize(
    ("kind", "mutate", "field", "reason"),
    [rule[1:] for rule in BUNDLE_RULES],
    ids=[rule[0] for rule in BUNDLE_RULES],
)
def test_bundle_rule(
    tmp_path: Path, rig: RigSpec, kind: BundleKind, mutate: Mutation, field: str, reason: str
) -> None:
    directory = tmp_path / "bundle"
    make_bundle(directory, rig, kind)
    edit_bundle_json(directory, mutate)
    with pytest.raises(FormatError, match=reason) as caught:
        read_bundle(directory)
    assert_names(caught.value, directory / "bundle.json", field)


def test_bundle_rules_in_valid_variants(tmp_path: Path, rig: RigSpec) -> None:
    """What FORMATS.md allows: subsets of cameras, no projectors_on, no t_ns, a nested path."""
    directory = tmp_path / "bundle"
    make_bundle(directory, rig)
    (directory / "sub").mkdir()
    (directory / "S2_0000.png").rename(directory / "sub" / "S2.png")

    def mutate(document: Document) -> None:
        document["frames"][0]["images"]["S2"] = "./sub/S2.png"
        del document["frames"][0]["projectors_on"]
        del document["frames"][1]["t_ns"]
        document["created"] = "2026-11-23T10:00:00+01:00"

    edit_bundle_json(directory, mutate)
    bundle = read_bundle(directory)
    assert bundle.frame(0).projectors_on == ()
    assert bundle.frame(1).t_ns is None
    assert bundle.load_image(0, "S2").shape == (HEIGHT, WIDTH)


def test_bundle_not_a_directory(tmp_path: Path) -> None:
    with pytest.raises(FormatError, match="not a directory") as caught:
        read_bundle(tmp_path / "absent")
    assert_names(caught.value, tmp_path / "absent", None)
    (tmp_path / "empty").mkdir()
    with pytest.raises(FormatError, match="not found") as caught:
        read_bundle(tmp_path / "empty")
    assert_names(caught.value, tmp_path / "empty" / "bundle.json", None)


def test_bundle_symlink_escaping_the_directory(tmp_path: Path, rig: RigSpec) -> None:
    directory = tmp_path / "bundle"
    make_bundle(directory, rig)
    outside = tmp_path / "secret.png"
    (directory / "S1_0000.png").rename(outside)
    (directory / "S1_0000.png").symlink_to(outside)
    with pytest.raises(FormatError, match="outside the bundle") as caught:
        read_bundle(directory)
    assert_names(caught.value, directory / "bundle.json", "frames[0].images.S1")


def _replace_image(bundle: Bundle, name: str, pixels: Any) -> Path:
    path = bundle.path / name
    assert cv2.imwrite(str(path), pixels)
    return path


IMAGE_RULES: list[tuple[str, Callable[[], Any], str]] = [
    ("wrong size", lambda: np.zeros((HEIGHT, WIDTH * 2), np.uint8), "24×8 pixels"),
    ("transposed", lambda: np.zeros((WIDTH, HEIGHT), np.uint16), "delivers 12×8"),
]


@pytest.mark.parametrize(
    ("pixels", "reason"), [rule[1:] for rule in IMAGE_RULES], ids=[rule[0] for rule in IMAGE_RULES]
)
def test_load_image_rule(
    tmp_path: Path, rig: RigSpec, pixels: Callable[[], Any], reason: str
) -> None:
    bundle = make_bundle(tmp_path / "bundle", rig)
    path = _replace_image(bundle, "S2_0000.png", pixels())
    with pytest.raises(FormatError, match=reason) as caught:
        read_bundle(bundle.path).load_image(0, "S2")
    assert_names(caught.value, path, None)


@pytest.mark.parametrize("channels", [3, 4], ids=["colour", "colour with alpha"])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_a_colour_image_is_read_as_the_mean_of_its_colour_channels(
        tmp_path: Path, rig: RigSpec, channels: int, dtype: type[np.unsignedinteger[Any]]) -> None:
    bundle = make_bundle(tmp_path / "bundle", rig)
    rng = np.random.default_rng(channels)
    pixels = rng.integers(0, np.iinfo(dtype).max, (HEIGHT, WIDTH, channels), dtype=dtype)
    _replace_image(bundle, "S2_0000.png", pixels)

    loaded = read_bundle(bundle.path).load_image(0, "S2")

    assert loaded.dtype == dtype and loaded.shape == (HEIGHT, WIDTH)
    expected = pixels[..., :3].astype(np.float64).mean(axis=2)  # alpha plays no part
    assert np.abs(loaded - expected).max() <= 0.5 + 1e-9


def test_load_image_missing_or_not_png(tmp_path: Path, rig: RigSpec) -> None:
    bundle = make_bundle(tmp_path / "bundle", rig)
    (bundle.path / "S1_0000.png").unlink()
    with pytest.raises(FormatError, match=r"missing \(named by frames\[0\]\.images\.S1") as caught:
        bundle.load_image(0, "S1")
    assert_names(caught.value, bundle.path / "S1_0000.png", None)

    ok, jpeg = cv2.imencode(".jpg", image(np.uint8, 1))
    assert ok
    (bundle.path / "S2_0000.png").write_bytes(jpeg.tobytes())
    with pytest.raises(FormatError, match="not a PNG") as caught:
        bundle.load_image(0, "S2")
    assert_names(caught.value, bundle.path / "S2_0000.png", None)

    png = (bundle.path / "S3_0001.png").read_bytes()
    (bundle.path / "S3_0001.png").write_bytes(png[:40])
    with pytest.raises(FormatError, match="cannot decode") as caught:
        bundle.load_image(1, "S3")
    assert_names(caught.value, bundle.path / "S3_0001.png", None)


def test_load_image_checks_bit_depth(tmp_path: Path, rig: RigSpec) -> None:
    frames = [
        BundleFrameData(
            images={
                "S1": np.full((HEIGHT, WIDTH), 4096, np.uint16),
                "S2": np.full((HEIGHT, WIDTH), 7, np.uint8),
            }
        )
    ]
    bundle = write_bundle(tmp_path / "b", "measurement", rig, frames)
    edit_bundle_json(bundle.path, _set(["bit_depth"], 12))
    bundle = read_bundle(bundle.path)
    with pytest.raises(FormatError, match="4096, beyond bit_depth 12") as caught:
        bundle.load_image(0, "S1")
    assert_names(caught.value, bundle.path / "S1_0000.png", None)
    with pytest.raises(FormatError, match="needs a 16-bit PNG"):
        bundle.load_image(0, "S2")


# --- point clouds ---------------------------------------------------------------------------


def cloud(count: int, with_quality: bool, with_camera: bool) -> PointCloud:
    generator = np.random.default_rng(count)
    return PointCloud(
        points=generator.normal(0.0, 10.0, (count, 3)).astype(np.float32),
        quality=generator.random(count, dtype=np.float32) if with_quality else None,
        camera=generator.integers(0, 4, count).astype(np.uint8) if with_camera else None,
    )


@pytest.mark.parametrize("with_quality", [False, True])
@pytest.mark.parametrize("with_camera", [False, True])
@pytest.mark.parametrize("count", [0, 1, 1000])
def test_ply_round_trip(tmp_path: Path, count: int, with_quality: bool, with_camera: bool) -> None:
    original = cloud(count, with_quality, with_camera)
    path = tmp_path / "cloud.ply"
    write_ply(path, original)
    again = read_ply(path)
    assert again.points.dtype == np.float32
    np.testing.assert_array_equal(again.points, original.points)
    if with_quality:
        assert again.quality is not None and original.quality is not None
        assert again.quality.dtype == np.float32
        np.testing.assert_array_equal(again.quality, original.quality)
    else:
        assert again.quality is None
    if with_camera:
        assert again.camera is not None and original.camera is not None
        assert again.camera.dtype == np.uint8
        np.testing.assert_array_equal(again.camera, original.camera)
    else:
        assert again.camera is None
    record_size = 12 + 4 * with_quality + with_camera
    header_size = path.read_bytes().index(b"end_header\n") + len(b"end_header\n")
    assert path.stat().st_size == header_size + count * record_size


def test_ply_layout_is_exactly_as_documented(tmp_path: Path) -> None:
    points = np.array([[1.0, 2.0, 3.0], [-4.0, 5.5, 6.25]], np.float32)
    path = tmp_path / "cloud.ply"
    write_ply(
        path,
        PointCloud(points, np.array([0.5, 1.0], np.float32), np.array([0, 3], np.uint8)),
        comments=["bundle sha256 abc"],
    )
    expected_header = (
        b"ply\nformat binary_little_endian 1.0\ncomment bundle sha256 abc\n"
        b"element vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
        b"property float quality\nproperty uchar camera\nend_header\n"
    )
    data = path.read_bytes()
    assert data.startswith(expected_header)
    body = data[len(expected_header) :]
    assert body == (
        np.array([1, 2, 3, 0.5], "<f4").tobytes()
        + b"\x00"
        + np.array([-4, 5.5, 6.25, 1], "<f4").tobytes()
        + b"\x03"
    )


def _ply(header_lines: list[str], body: bytes) -> bytes:
    return ("\n".join(header_lines) + "\n").encode("ascii") + body


def test_ply_reads_double_coordinates_and_foreign_properties(tmp_path: Path) -> None:
    vertices = np.zeros(
        3,
        dtype=[
            ("x", "<f8"),
            ("y", "<f8"),
            ("z", "<f8"),
            ("nx", "<f4"),
            ("red", "u1"),
            ("camera", "<i4"),
        ],
    )
    vertices["x"], vertices["y"], vertices["z"] = [0.1, 0.2, 0.3], [1, 2, 3], [-1, -2, -3]
    vertices["camera"] = [0, 1, 255]
    header = [
        "ply",
        "format binary_little_endian 1.0",
        "obj_info made elsewhere",
        "element marker 2",
        "property int id",
        "element vertex 3",
        "property double x",
        "property double y",
        "property double z",
        "property float nx",
        "property uchar red",
        "property int camera",
        "element face 1",
        "property list uchar int vertex_indices",
        "end_header",
    ]
    markers = np.array([7, 8], "<i4").tobytes()
    face = b"\x03" + np.array([0, 1, 2], "<i4").tobytes()
    path = tmp_path / "foreign.ply"
    path.write_bytes(_ply(header, markers + vertices.tobytes() + face).replace(b"\n", b"\r\n", 2))
    result = read_ply(path)
    np.testing.assert_array_equal(
        result.points, np.stack([vertices["x"], vertices["y"], vertices["z"]], 1).astype(np.float32)
    )
    assert result.quality is None
    assert result.camera is not None and result.camera.tolist() == [0, 1, 255]


XYZ = ["property float x", "property float y", "property float z"]
ONE_POINT = np.array([1, 2, 3], "<f4").tobytes()


def _vertex_ply(
    properties: list[str], body: bytes, count: int = 1, layout: str = "binary_little_endian"
) -> bytes:
    return _ply(
        ["ply", f"format {layout} 1.0", f"element vertex {count}", *properties, "end_header"], body
    )


PLY_RULES: list[tuple[str, bytes, str | None, str]] = [
    ("not a ply", b"solid cube\n", None, "not a PLY"),
    ("ascii", _vertex_ply(XYZ, b"1 2 3\n", layout="ascii"), "format", "ascii PLY is not"),
    ("big endian", _vertex_ply(XYZ, ONE_POINT, layout="binary_big_endian"), "format", "big"),
    ("no format line", _ply(["ply", "element vertex 0", "end_header"], b""), "format", "no format"),
    ("no end_header", b"ply\nformat binary_little_endian 1.0\n", "header", "end_header"),
    ("truncated", _vertex_ply(XYZ, ONE_POINT, count=2), "data", "truncated"),
    ("trailing bytes", _vertex_ply(XYZ, ONE_POINT + b"\x00"), "data", "1 bytes after"),
    ("missing z", _vertex_ply(XYZ[:2], ONE_POINT[:8]), "property z", "no such property"),
    (
        "no vertex element",
        _ply(
            ["ply", "format binary_little_endian 1.0", "element point 1", *XYZ, "end_header"], b""
        ),
        "element vertex",
        "no vertex element",
    ),
    (
        "list in vertex",
        _vertex_ply([*XYZ, "property list uchar int tags"], ONE_POINT + b"\x00"),
        "element vertex",
        "list",
    ),
    (
        "unknown type",
        _vertex_ply([*XYZ, "property half w"], ONE_POINT + b"\x00\x00"),
        "element vertex",
        "unsupported property",
    ),
    (
        "camera out of range",
        _vertex_ply([*XYZ, "property int camera"], ONE_POINT + np.int32(300).tobytes()),
        "property camera",
        "0–255",
    ),
    (
        "float camera",
        _vertex_ply([*XYZ, "property float camera"], ONE_POINT + ONE_POINT[:4]),
        "property camera",
        "integer",
    ),
]


@pytest.mark.parametrize(
    ("content", "field", "reason"),
    [rule[1:] for rule in PLY_RULES],
    ids=[rule[0] for rule in PLY_RULES],
)
def test_ply_rule(tmp_path: Path, content: bytes, field: str | None, reason: str) -> None:
    path = tmp_path / "cloud.ply"
    path.write_bytes(content)
    with pytest.raises(FormatError, match=reason) as caught:
        read_ply(path)
    assert_names(caught.value, path, field)


def test_ply_missing_file(tmp_path: Path) -> None:
    with pytest.raises(FormatError, match="not found") as caught:
        read_ply(tmp_path / "absent.ply")
    assert_names(caught.value, tmp_path / "absent.ply", None)


def test_point_cloud_checks_and_converts() -> None:
    converted = PointCloud(np.zeros((2, 3)), [0.5, 1.0], np.array([1, 2], np.int64))  # type: ignore[arg-type]
    assert converted.points.dtype == np.float32
    assert converted.quality is not None and converted.quality.dtype == np.float32
    assert converted.camera is not None and converted.camera.dtype == np.uint8
    assert len(converted) == 2
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        PointCloud(np.zeros((2, 2), np.float32))
    with pytest.raises(ValueError, match="quality"):
        PointCloud(np.zeros((2, 3), np.float32), np.zeros(3, np.float32))
    with pytest.raises(ValueError, match="0–255"):
        PointCloud(np.zeros((1, 3), np.float32), camera=np.array([256]))
    with pytest.raises(ValueError, match="one line"):
        write_ply(Path("unused.ply"), converted, comments=["two\nlines"])


def test_makedirs_synced(tmp_path: Path) -> None:
    makedirs_synced(tmp_path / "a" / "b" / "c")
    assert (tmp_path / "a" / "b" / "c").is_dir()
    makedirs_synced(tmp_path / "a" / "b")
    (tmp_path / "file").write_text("x")
    with pytest.raises(FileExistsError):
        makedirs_synced(tmp_path / "file")
    bundle = make_bundle(tmp_path / "new" / "deeper" / "bundle", rig_from_dict(rig_document(), "x"))
    assert bundle.path.is_dir()
