"""Coverage and accuracy of each fringe-order method on one room's scenes: the figures behind
``auto`` (eyeserver/reconstruction.py) and issue 37's coverage goals.

    .venv/bin/python scripts/coverage_by_method.py CALDIR [--room FILE]

Records plates at Z = 3 and 23 mm, a tilted plate, the pyramid, an eye phantom and the eye
(seed 7) in the room, reconstructs each with ``multi-view`` and ``spatial``, and prints the
least and largest of three coverages over the cameras: the share of the pixels that see the
scene (the truth's), of the pixels the unit's projector lights there (the truth's: issue 37's
goals count these) and of the pixels that see a fringe (the pipeline's own mask, the
reconstruction summary's ``coverage``).
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

from eyeserver.hardware.sim.config import load_room
from eyeserver.hardware.sim.scenes import SceneSpec
from eyeserver.hardware.sim.scoring import score_cloud
from eyeserver.hardware.sim.sessions import SimSession
from eyeserver.reconstruction import reconstruct_bundle

SCENES = {"plate at +3 mm": SceneSpec(kind="plate", position_mm=(0.0, 0.0, 3.0)),
          "plate at +23 mm": SceneSpec(kind="plate", position_mm=(0.0, 0.0, 23.0)),
          "tilted plate": SceneSpec(kind="plate", position_mm=(0.0, 0.0, 2.0),
                                    rotation_deg=(15.0, -10.0, 0.0)),
          "pyramid": SceneSpec(kind="pyramid", position_mm=(1.0, -1.0, -5.0)),
          "eye phantom 1": SceneSpec(kind="eye_phantom_1"),
          "eye": SceneSpec(kind="eye")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("calibration", type=Path, metavar="CALDIR")
    parser.add_argument("--room", type=Path, help="room file (default room)")
    args = parser.parse_args()
    config = load_room(args.room)
    work = Path(tempfile.mkdtemp(prefix="coverage-"))
    print("| scene | method | median (mm) | beyond 1 mm | of the scene seen | of the lit pixels "
          "| of the fringe seen |")
    print("|---|---|---|---|---|---|---|")
    for name, spec in SCENES.items():
        bundle = work / name.replace(" ", "_")
        with SimSession.open(config, seed=7) as session:
            session.record(spec, bundle)
        truth = json.loads((bundle / "truth.json").read_text())
        for method in ("multi-view", "spatial"):
            cloud, summary = reconstruct_bundle(args.calibration, bundle, method=method)
            score = score_cloud(truth, cloud, config)
            scene = [c["share"] for c in score["coverage"].values()]
            lit = [c["lit_share"] for c in score["coverage"].values()]
            fringe = [c["coverage"] for c in summary["cameras"].values()]
            print(f"| {name} | {method} | {score['median_mm']:.4f} | "
                  f"{score['beyond_1mm']:.4f} | {min(scene):.2f}–{max(scene):.2f} | "
                  f"{min(lit):.2f}–{max(lit):.2f} | {min(fringe):.2f}–{max(fringe):.2f} |")


if __name__ == "__main__":
    main()
