"""How much of a simulated eye the pipeline reconstructs, and how well, surface by surface.

Renders the patient eye (at rest and at a few other gazes and positions), the two eye phantoms,
a tilted plate and the pyramid in the default simulated room (seed 7), reconstructs each bundle
with a calibration made from a simulated calibration set, and prints per labelled surface
(sclera, cornea, lids, skin, a phantom's body and base) the points kept, the median and 95th
percentile of their distance to the exact surface and the share beyond 0.5 mm, and the time the
reconstruction took. The pipeline sees only images and calibration; the scene's truth is used
only to score.

    .venv/bin/python scripts/eye_coverage.py --work /tmp/eyecov [--calibration CAL]
        [--cases eye,eye_phantom_2] [--method spatial] [--line-of-sight] [--json]

Without ``--calibration`` a calibration set is recorded and calibrated under ``--work`` first
(a few minutes); bundles are rendered once and reused from ``--work/bundles`` (delete them after
changing the simulator or :data:`CASES`). A point counts on the surface nearest to it, or with
``--line-of-sight`` on the surface its camera sees through it (stricter at the lids' margin,
where the fringe analysis smears lid and sclera into each other).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from eyeserver.cli import main as cli_main
from eyeserver.hardware.sim.config import load_room
from eyeserver.hardware.sim.room import SimRoom
from eyeserver.hardware.sim.scenes import EyeSpec, SceneSpec, build_scene
from eyeserver.hardware.sim.sessions import SimSession
from eyeserver.hardware.sim.truth import truth_scene
from eyeserver.io import PointCloud
from eyeserver.reconstruction import reconstruct_bundle

CASES: dict[str, SceneSpec] = {
    "eye": SceneSpec(kind="eye"),
    "eye_gaze_+10_+5": SceneSpec(kind="eye", eye=EyeSpec(gaze_deg=(10.0, 5.0))),
    "eye_moved_gaze_-8_-6": SceneSpec(kind="eye", position_mm=(3.0, -2.0, -7.0),
                                      eye=EyeSpec(gaze_deg=(-8.0, -6.0))),
    "eye_large_low": SceneSpec(kind="eye", position_mm=(-2.0, 1.5, -13.0),
                               eye=EyeSpec(globe_radius_mm=13.35, cornea_radius_mm=8.54)),
    "eye_phantom_1": SceneSpec(kind="eye_phantom_1"),
    "eye_phantom_2": SceneSpec(kind="eye_phantom_2", position_mm=(1.5, 0.5, -5.0),
                               rotation_deg=(8.0, -6.0, 0.0)),
    "tilted": SceneSpec(kind="plate", position_mm=(0.0, 0.0, 2.0), rotation_deg=(15.0, -10.0,
                                                                               0.0)),
    "pyramid": SceneSpec(kind="pyramid", position_mm=(1.0, -1.0, -5.0)),
}
"""The scenes measured: the patient eye four ways, the phantoms, and the tilted plate and the
pyramid whose wrong-order islands the speckle filter exists for (as tests/test_reconstruct.py
records them)."""

BEYOND_MM = 0.5


def surface_errors(truth: dict[str, Any], cloud: PointCloud, line_of_sight: bool = False,
                   ) -> dict[str, dict[str, float]]:
    """Per labelled surface: points, median and p95 distance (mm) to that surface and the share
    of points beyond :data:`BEYOND_MM`.

    A point counts on the surface nearest to it (as ``score_by_surface``), or with
    ``line_of_sight`` on the surface its camera sees along the line through it: a lid point
    smeared towards the sclera behind the lid's margin then counts as a (poor) lid point
    rather than as a sclera point 0.3–0.5 mm off.
    """
    built = build_scene(truth_scene(truth), float(truth.get("t_s", 0.0)))
    points = cloud.points.astype(np.float64)
    labels = built.scene.labels
    per_surface = [(body, surface) for body in built.scene.bodies for surface in body.surfaces]
    if not len(points):
        return {label: {"points": 0} for label in labels}
    table = np.stack([surface.distance(body.to_local(points)) for body, surface in per_surface])
    names = np.array([surface.label for _, surface in per_surface])
    if line_of_sight and cloud.camera is not None:
        sim = SimRoom(load_room(None))
        ids = sim.camera_ids()
        seen = np.full(len(points), "", dtype=object)
        for index in np.unique(cloud.camera):
            mine = cloud.camera == index
            centre = sim.renderer.cameras[ids[int(index)]].centre
            rays = points[mine] - centre
            rays /= np.linalg.norm(rays, axis=1, keepdims=True)
            hit = built.scene.cast(centre, rays).label
            seen[mine] = np.where(hit >= 0, np.array(labels, dtype=object)[hit], "")
        label_of = seen
        distance = np.full(len(points), np.inf)
        for n, name in enumerate(names):
            distance = np.where(label_of == name, np.minimum(distance, table[n]), distance)
    else:
        nearest = np.argmin(table, axis=0)
        label_of = names[nearest]
        distance = table[nearest, np.arange(len(points))]
    out: dict[str, dict[str, float]] = {}
    for label in labels:
        d = distance[label_of == label]
        out[label] = {"points": int(d.size)}
        if d.size:
            out[label].update(median_mm=float(np.median(d)),
                              p95_mm=float(np.percentile(d, 95)),
                              beyond=float(np.mean(d > BEYOND_MM)))
    return out


def calibrate(work: Path) -> Path:
    """A calibration of the default room under ``work`` (made once)."""
    calset, caldir = work / "calset", work / "cal"
    if (caldir / "calibration.json").exists():
        return caldir
    if not calset.exists():
        assert cli_main(["sim", "calibration-set", "--out", str(calset)]) == 0
    boards = sorted(str(p) for p in calset.glob("chessboard_*"))
    assert cli_main(["calibrate", "stereo", "--out", str(caldir), *boards]) == 0
    assert cli_main(["calibrate", "p2h", "--calibration", str(caldir), str(calset / "plate"),
                     str(calset / "reference")]) == 0
    return caldir


def measure(caldir: Path, work: Path, names: list[str], method: str,
            line_of_sight: bool = False) -> dict[str, dict[str, Any]]:
    """Render (once), reconstruct and score each named case."""
    config = load_room(None)
    results: dict[str, dict[str, Any]] = {}
    for name in names:
        bundle = work / "bundles" / name
        if not (bundle / "truth.json").exists():
            with SimSession.open(config, seed=7) as session:
                session.record(CASES[name], bundle)
        start = time.perf_counter()
        cloud, _ = reconstruct_bundle(caldir, bundle, method=method)
        seconds = time.perf_counter() - start
        truth = json.loads((bundle / "truth.json").read_text())
        results[name] = {"seconds": seconds,
                         "surfaces": surface_errors(truth, cloud, line_of_sight)}
    return results


def table(results: dict[str, dict[str, Any]]) -> str:
    """The results as a plain-text table."""
    lines = [f"{'case':22s} {'surface':8s} {'points':>8s} {'median':>8s} {'p95':>8s} "
             f"{'>0.5mm':>7s}"]
    for name, result in results.items():
        for label, s in result["surfaces"].items():
            if not s["points"]:
                lines.append(f"{name:22s} {label:8s} {0:8d}")
                continue
            lines.append(f"{name:22s} {label:8s} {s['points']:8d} {s['median_mm']:8.4f} "
                         f"{s['p95_mm']:8.4f} {100 * s['beyond']:6.2f}%")
        lines.append(f"{name:22s} ({result['seconds']:.2f} s)")
    return "\n".join(lines)


def run(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--work", type=Path, required=True,
                        help="directory for the calibration set and the bundles")
    parser.add_argument("--calibration", type=Path, help="an existing calibration directory")
    parser.add_argument("--cases", default=",".join(CASES),
                        help=f"comma-separated cases (default: all of {', '.join(CASES)})")
    parser.add_argument("--method", default="multi-view", choices=("multi-view", "spatial"))
    parser.add_argument("--line-of-sight", action="store_true",
                        help="count each point on the surface its camera sees through it, not "
                             "on the nearest surface")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    args = parser.parse_args(argv)
    names = [n for n in args.cases.split(",") if n]
    unknown = set(names) - set(CASES)
    if unknown:
        parser.error(f"unknown cases {sorted(unknown)}")
    args.work.mkdir(parents=True, exist_ok=True)
    caldir = args.calibration or calibrate(args.work)
    results = measure(caldir, args.work, names, args.method, args.line_of_sight)
    print(json.dumps(results, indent=1) if args.json else table(results))
    return 0


if __name__ == "__main__":
    sys.exit(run())
