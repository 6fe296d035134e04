"""How clearly each simulated frame shows its fringe carrier: the figures behind
``MIN_CARRIER_STRENGTH`` and ``MIN_CARRIER_DOMINANCE`` (eyeserver/pipeline/demodulate.py).

    .venv/bin/python scripts/carrier_quality.py [--room FILE]

For one camera of each unit of the room, a plate lit at 100, 30 and 5 %, a dark projector, the
eye, the pyramid and the empty room: the spectral peak over the spectrum's median, over the
strongest other component (outside its main lobe and harmonics: ``carrier_ratios``, the
pipeline's own judgement), and what measure_carrier says.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from eyeserver.hardware.sim.config import load_room
from eyeserver.hardware.sim.room import SimRoom
from eyeserver.hardware.sim.scenes import SceneSpec
from eyeserver.pipeline.demodulate import carrier_ratios, measure_carrier


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--room", type=Path, help="room file (default room)")
    room = SimRoom(load_room(parser.parse_args().room))
    rng = np.random.default_rng(0)
    plate = SceneSpec(kind="plate", position_mm=(0.0, 0.0, 0.0))
    cases = [("plate", plate, 1.0), ("plate at 30 %", plate, 0.3), ("plate at 5 %", plate, 0.05),
             ("plate, projector dark", plate, 0.0), ("eye", SceneSpec(kind="eye"), 1.0),
             ("pyramid", SceneSpec(kind="pyramid"), 1.0), ("empty", SceneSpec(kind="empty"), 1.0)]
    print("| unit | camera | scene | peak / median | peak / next | measure_carrier |")
    print("|---|---|---|---|---|---|")
    for unit, projector, cameras in room.units():
        camera = cameras[0]
        for name, scene, level in cases:
            room.set_scene(scene)
            image = room.render(camera, t_s=0.0, projectors={projector: level} if level else {},
                                exposure_us=10_000, gain_db=0.0, rng=rng)
            strength, dominance = carrier_ratios(image)
            try:
                said = f"{measure_carrier(image).period_px:.2f} px"
            except ValueError as exc:
                said = f"refused: {str(exc).split(':')[0]}"
            print(f"| {unit} | {camera} | {name} | {strength:.1f} | {dominance:.2f} | {said} |")


if __name__ == "__main__":
    main()
