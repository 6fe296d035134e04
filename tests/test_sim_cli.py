"""``eyeserver sim …`` end to end: bundles on disk whose images carry the physics of the room."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from eyeserver.cli import main
from eyeserver.hardware.sim.optics import blurred_square_wave
from eyeserver.hardware.sim.room import SimRoom
from eyeserver.hardware.sim.scenes import SKIN, build_scene
from eyeserver.hardware.sim.truth import truth_scene
from eyeserver.io import read_bundle, read_rig

PATCH = 48


@pytest.fixture(scope="module")
def eye_bundle(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("eye") / "bundle"
    assert main(["sim", "render", "--scene", "eye", "--out", str(out)]) == 0
    return out


def _skin_patch(labels: np.ndarray, skin: int, image: np.ndarray) -> tuple[int, int]:
    """Top-left corner of the brightest PATCH×PATCH window that lies entirely on lit skin."""
    best, where = -1.0, (0, 0)
    h, w = labels.shape
    for i in range(16, h - PATCH - 16, 16):
        for j in range(16, w - PATCH - 16, 16):
            if np.all(labels[i:i + PATCH, j:j + PATCH] == skin):
                mean = float(image[i:i + PATCH, j:j + PATCH].mean())
                if mean > best:
                    best, where = mean, (i, j)
    assert best > 0, "no patch of skin found"
    return where


@pytest.mark.slow
def test_eye_render_is_four_fringe_images_interleaved(eye_bundle: Path) -> None:
    bundle = read_bundle(eye_bundle)
    assert bundle.kind == "measurement"
    assert [f.projectors_on for f in bundle.frames] == [("P1",), ("P2",)]
    assert [sorted(f.images) for f in bundle.frames] == [["S1", "S2"], ["S3", "S4"]]
    assert sorted(bundle.fringe_images()) == [(0, "S1"), (0, "S2"), (1, "S3"), (1, "S4")]
    for index, camera in bundle.fringe_images():
        image = bundle.load_image(index, camera)
        assert image.shape == (512, 640) and image.dtype == np.uint8
    truth = json.loads((eye_bundle / "truth.json").read_text())
    assert truth["eye"]["centre_mm"] == pytest.approx([0.0, 0.0, -10.0])


def test_eye_render_carrier_and_contrast_match_the_geometry(eye_bundle: Path) -> None:
    """On a patch of skin, the fringe's frequency and amplitude are what the optics predict.

    Prediction from geometry alone: the projector phase at the surface points the pixels see
    gives the carrier (radians per pixel along the image rows); the projector's calibrated
    irradiance with the incidence angle, the inverse-square fall-off, the skin's albedo, the
    vignetting and the camera's blur gives the fundamental's amplitude.
    """
    bundle = read_bundle(eye_bundle)
    truth = json.loads((eye_bundle / "truth.json").read_text())
    room = SimRoom()
    built = build_scene(truth_scene(truth), truth["t_s"])
    skin = built.scene.labels.index("skin")
    for index, camera_id in bundle.fringe_images():
        projector_id = bundle.frame(index).projectors_on[0]
        image = bundle.load_image(index, camera_id).astype(np.float64)
        cam = room.renderer.cameras[camera_id]
        proj = room.renderer.projectors[projector_id]
        hits = built.scene.cast(cam.centre, cam.rays().reshape(-1, 3))
        labels = hits.label.reshape(cam.shape)
        i0, j0 = _skin_patch(labels, skin, image)
        rows = slice(i0, i0 + PATCH)
        cols = slice(j0, j0 + PATCH)
        points = hits.points.reshape(*cam.shape, 3)[rows, cols]
        phase, distance, _ = proj.phase_at(points)
        carrier = float(np.median(np.abs(np.diff(phase, axis=1))))  # rad per pixel along u

        # Measured: the strongest frequency along the rows of the patch (zero-padded FFT).
        patch = image[rows, cols]
        patch = patch - patch.mean(axis=1, keepdims=True)
        window = np.hanning(PATCH)
        spectrum = np.abs(np.fft.rfft(patch * window, n=4096, axis=1)).mean(axis=0)
        freqs = np.fft.rfftfreq(4096) * 2 * math.pi
        measured = float(freqs[np.argmax(spectrum[8:]) + 8])
        assert measured == pytest.approx(carrier, rel=0.05), camera_id

        # Amplitude of the fundamental, demodulated at the measured carrier.
        normals = np.zeros_like(points)
        normals[..., 2] = 1.0  # the face plane faces +Z (the scene is not rotated)
        to_proj = (proj.centre - points) / distance[..., None]
        cos_inc = np.sum(normals * to_proj, axis=-1)
        swing = (SKIN * proj.power_dn * cos_inc * (proj.working_distance / distance) ** 2
                 * room.renderer._vignetting[camera_id][rows, cols])
        fundamental = 0.5 * (blurred_square_wave(np.array([0.0]), proj.config.blur_periods)[0]
                             - blurred_square_wave(np.array([math.pi]),
                                                   proj.config.blur_periods)[0])
        blur = math.exp(-0.5 * (cam.config.blur_px * carrier) ** 2)
        expected = float(np.median(swing)) * fundamental * blur
        u = np.arange(PATCH)
        lock_in = (patch * np.exp(-1j * measured * u)[None, :]).mean(axis=1)
        amplitude = float(np.median(2 * np.abs(lock_in)))
        assert amplitude == pytest.approx(expected, rel=0.15), camera_id


@pytest.mark.slow
def test_calibration_set_layout(tmp_path: Path) -> None:
    out = tmp_path / "calset"
    room = tmp_path / "coarse.toml"  # layout only: coarse pixel integration keeps it quick
    room.write_text("[render]\nsupersample = 1\nsupersample_chessboard = 1\n")
    code = main(["sim", "calibration-set", "--room", str(room), "--out", str(out),
                 "--z-min", "-1", "--z-max", "1", "--z-step", "1"])
    assert code == 0
    rig = read_rig(out / "rig.json")
    assert [u.id for u in rig.units] == ["left", "right"]
    boards = sorted(p.name for p in out.glob("chessboard_*"))
    assert boards[0] == "chessboard_00" and len(boards) >= 8
    origin = read_bundle(out / "chessboard_00")
    assert origin.kind == "chessboard" and origin.chessboard is not None
    assert origin.chessboard.origin
    assert not read_bundle(out / boards[1]).chessboard.origin  # type: ignore[union-attr]
    assert origin.frames[0].projectors_on == ()
    plate = read_bundle(out / "plate")
    # Each Z once per projector, in order: -1 (P1, P2), 0 (P1, P2), +1 (P1, P2).
    assert [(f.z_mm, f.projectors_on) for f in plate.frames] == [
        (z, (p,)) for z in (-1.0, 0.0, 1.0) for p in ("P1", "P2")]
    reference = read_bundle(out / "reference")
    assert {f.z_mm for f in reference.frames} == {10.0}


@pytest.mark.slow
def test_render_refuses_to_overwrite_and_names_bad_options(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "plate"
    assert main(["sim", "render", "--scene", "plate", "--position", "0", "0", "3",
                 "--out", str(out)]) == 0
    assert read_bundle(out).frames[0].z_mm == 3.0
    assert main(["sim", "render", "--scene", "plate", "--out", str(out)]) == 2
    assert "exists" in capsys.readouterr().err
    assert main(["sim", "render", "--scene", "wedge", "--gaze", "1", "2",
                 "--out", str(tmp_path / "w")]) == 2
    assert "--gaze" in capsys.readouterr().err
    assert main(["sim", "render", "--scene", "eye", "--units", "middle",
                 "--out", str(tmp_path / "e")]) == 2
    assert "middle" in capsys.readouterr().err
    bad_room = tmp_path / "room.toml"
    bad_room.write_text("seed = 'x'\n")
    assert main(["sim", "render", "--scene", "plate", "--room", str(bad_room),
                 "--out", str(tmp_path / "p2")]) == 2
    err = capsys.readouterr().err
    assert str(bad_room) in err and "seed" in err
