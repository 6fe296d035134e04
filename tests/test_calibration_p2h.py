"""Phase-to-height calibration on simulated calibration sets, on the default rig and another."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from eyeserver.calibration.artefact import load_calibration
from eyeserver.calibration.phase_height import fringe_order_margin
from eyeserver.calibration.stereo import CalibrationError
from eyeserver.cli import main
from eyeserver.hardware.sim.config import room_from_dict
from eyeserver.hardware.sim.room import SimRoom
from eyeserver.pipeline.phase_height import fit_phase_height


@pytest.fixture(scope="module", params=["default", "wide"])
def calibrated(request: pytest.FixtureRequest, calibrated_rooms) -> tuple[Path, Path]:  # type: ignore[no-untyped-def]
    """A simulated calibration set and the calibration made from it with the command line."""
    result: tuple[Path, Path] = calibrated_rooms(request.param)
    return result


@pytest.mark.slow
def test_models_fit_the_whole_range(calibrated: tuple[Path, Path]) -> None:
    _, caldir = calibrated
    document = load_calibration(caldir)
    section = document["phase_to_height"]
    for camera_id, cam in section["cameras"].items():
        quality = cam["quality"]
        assert quality["median_abs_mm"] < 0.03, camera_id  # the goal of docs/design.md §6
        assert cam["z_range_mm"] == [-10.0, 25.0], camera_id  # all 35 mm, not just 15
        # Every plane fits, the extremes as well as the middle: no slip anywhere.
        assert max(z["median_abs_mm"] for z in quality["per_z"]) < 0.03, camera_id
        assert f"reference_phase_{camera_id}" in document["arrays"]
    for unit_id, unit in section["units"].items():
        assert unit["margin_rad"] >= 0.5, unit_id
        assert unit["orders_checked"] >= 5, unit_id
    assert len(document["inputs"]["phase_to_height"]) == 2


@pytest.mark.slow
def test_a_mislabelled_plane_is_named(calibrated: tuple[Path, Path], tmp_path: Path) -> None:
    calset, caldir = calibrated
    bad = tmp_path / "plate"
    bad.mkdir()
    for item in (calset / "plate").iterdir():
        (bad / item.name).write_bytes(item.read_bytes())
    bundle = json.loads((bad / "bundle.json").read_text())
    for frame in bundle["frames"]:
        if frame["z_mm"] == 20.0:
            frame["z_mm"] = 23.5  # the stage was not where the bundle says
    (bad / "bundle.json").write_text(json.dumps(bundle))
    document = load_calibration(caldir)
    document.pop("arrays")
    from eyeserver.calibration.phase_height import calibrate_phase_height

    with pytest.raises(CalibrationError, match=r"Z = \+2"):
        calibrate_phase_height(document, bad, calset / "reference")


def test_p2h_needs_the_right_bundles(calibrated: tuple[Path, Path],
                                     capsys: pytest.CaptureFixture[str]) -> None:
    calset, caldir = calibrated
    assert main(["calibrate", "p2h", "--calibration", str(caldir), str(calset / "reference"),
                 str(calset / "plate")]) == 2
    assert "expected a 'plate' bundle" in capsys.readouterr().err


def _exact_model(room: SimRoom, camera_id: str, projector_id: str):  # type: ignore[no-untyped-def]
    cam = room.renderer.cameras[camera_id]
    proj = room.renderer.projectors[projector_id]
    v, u = np.mgrid[20:500:24, 20:620:24].astype(np.float64)
    x, y = cam.normalised_for_pixels(u, v)
    rays = cam.rays_for_pixels(u, v)
    reference = None
    xs, ys, dphis, zs = [], [], [], []
    for z in [10.0, *np.arange(-10.0, 26.0)]:
        t = (z - cam.centre[2]) / rays[..., 2]
        phase, _, _ = proj.phase_at(cam.centre + t[..., None] * rays)
        if reference is None:
            reference = phase
            continue
        xs.append(x.ravel())
        ys.append(y.ravel())
        dphis.append((phase - reference).ravel())
        zs.append(np.full(x.size, z))
    return fit_phase_height(np.concatenate(xs), np.concatenate(ys), np.concatenate(dphis),
                            np.concatenate(zs)).model


def _camera(room: SimRoom, camera_id: str) -> dict[str, np.ndarray]:
    cam = room.renderer.cameras[camera_id]
    return {"R": cam.R, "T": cam.T}


def test_margin_tells_a_sighted_rig_from_a_blind_one() -> None:
    """Two cameras at the same azimuth (a purely vertical baseline under vertical fringes) are
    blind to the fringe order at every k; the default rig's 25°/28° split is not."""
    default = SimRoom()
    sighted = fringe_order_margin(_exact_model(default, "S1", "P1"),
                                  _exact_model(default, "S2", "P1"),
                                  _camera(default, "S1"), _camera(default, "S2"), (-10.0, 25.0))
    assert sighted["margin_rad"] > 0.5
    blind_room = SimRoom(room_from_dict({"units": [{"id": "left", "cameras": [
        {"id": "S1"}, {"id": "S2", "azimuth_deg": 25.0}]}]}))
    blind = fringe_order_margin(_exact_model(blind_room, "S1", "P1"),
                                _exact_model(blind_room, "S2", "P1"),
                                _camera(blind_room, "S1"), _camera(blind_room, "S2"),
                                (-10.0, 25.0))
    assert blind["margin_rad"] < 0.1 < math.pi


def test_a_range_with_no_wrong_order_in_it_has_the_largest_margin() -> None:
    """Plates over a range shallower than a fringe's depth leave no wrong order inside it: the
    margin is π (a wrapped gap's most), a number a calibration file can hold, not infinity."""
    default = SimRoom()
    shallow = fringe_order_margin(_exact_model(default, "S1", "P1"),
                                  _exact_model(default, "S2", "P1"),
                                  _camera(default, "S1"), _camera(default, "S2"), (-0.5, 0.5))
    assert shallow == {"margin_rad": math.pi, "orders_checked": 0}
