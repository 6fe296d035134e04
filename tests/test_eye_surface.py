"""The patient eye's sclera: narrow patches between lids and limbus that eye pose fitting needs.

The visible sclera is a few hundred pixels per camera, more than a millimetre below the lids
around it, so the speckle filter alone dropped it (≈ 200 points left, 0.5 mm off); small
patches whose fringe order the partner camera confirms as a whole now stay
(``reconstruct._patch_confirmed``). Figures measured on the default room (seed 7): eye at rest
3555 sclera points, median 0.053 mm, none beyond 1 mm (scripts/eye_coverage.py prints more).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from eyeserver.hardware.sim.config import load_room
from eyeserver.hardware.sim.scenes import EyeSpec, SceneSpec
from eyeserver.hardware.sim.scoring import score_by_surface
from eyeserver.hardware.sim.sessions import SimSession
from eyeserver.io import PointCloud
from eyeserver.reconstruction import reconstruct_bundle

pytestmark = pytest.mark.slow  # every test here takes over a second

EYES = {
    "rest": SceneSpec(kind="eye"),
    "gaze": SceneSpec(kind="eye", eye=EyeSpec(gaze_deg=(10.0, 5.0))),
}


@pytest.mark.parametrize("name", list(EYES))
def test_sclera_is_reconstructed(calibrated_rooms: Any, name: str, tmp_path: Path) -> None:
    _, caldir = calibrated_rooms("default")
    bundle = tmp_path / name
    with SimSession.open(load_room(None), seed=7) as session:
        session.record(EYES[name], bundle)
    cloud, _ = reconstruct_bundle(caldir, bundle, method="multi-view")
    score = score_by_surface(json.loads((bundle / "truth.json").read_text()), cloud)
    sclera, skin = score["sclera"], score["skin"]
    # Measured 3555 and 3256 points, medians 0.053 and 0.045 mm, none beyond 1 mm.
    assert sclera["points"] > 2500, score
    assert sclera["median_mm"] < 0.075, score
    assert sclera["beyond_1mm"] < 0.005, score
    assert skin["median_mm"] < 0.01, score
    assert skin["beyond_1mm"] < 0.001, score


@pytest.mark.parametrize("seed", range(4))
def test_every_camera_keeps_the_sclera_of_a_turned_eye(calibrated_rooms: Any, seed: int,
                                                       tmp_path: Path) -> None:
    # Turned 8° towards +X, one unit sees its sclera as patches of 100–250 pixels: with only
    # patches of 200 pixels or more kept, the noise of one draw in four (seed 2) took a unit's
    # sclera away (measured 25 and 28 points against 213–266 in the other draws), and in a
    # draw where both units lost it the globe fit took the lids for the sclera (3.9 mm off).
    _, caldir = calibrated_rooms("default")
    bundle = tmp_path / "turned"
    with SimSession.open(load_room(None), seed=seed) as session:
        session.record(SceneSpec(kind="eye", eye=EyeSpec(gaze_deg=(8.0, 0.0))), bundle)
    cloud, _ = reconstruct_bundle(caldir, bundle, method="multi-view")
    truth = json.loads((bundle / "truth.json").read_text())
    for camera in np.unique(cloud.camera):
        mine = cloud.camera == camera
        sclera = score_by_surface(truth, PointCloud(cloud.points[mine], cloud.quality[mine],
                                                    cloud.camera[mine]))["sclera"]
        # Measured 241–440 points a camera over four draws, medians 0.03–0.16 mm.
        assert sclera["points"] > 150, (int(camera), sclera)
        assert sclera["median_mm"] < 0.25, (int(camera), sclera)
