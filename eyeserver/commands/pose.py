"""``eyeserver pose``: the eye pose of a measurement bundle, as JSON."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from eyeserver.commands import Subparsers
from eyeserver.commands import progress as _progress


def add_parser(subparsers: Subparsers) -> None:
    """Register ``eyeserver pose --calibration CALDIR BUNDLE``."""
    parser = subparsers.add_parser(
        "pose", help="the eye pose of a measurement bundle (JSON)",
        description="Reconstruct the measurement in BUNDLE with the calibration in CALDIR, fit "
        "the eye model (population defaults, globe radius fitted) with the limbus found in the "
        "fringe images, and print the pose as JSON: "
        "centre_mm (globe centre) and gaze (unit vector) in the WCS, with uncertainties, the "
        "surface-to-model distance and a confidence. Exit status 2 when no eye is found.")
    parser.add_argument("--calibration", type=Path, required=True, metavar="CALDIR")
    parser.add_argument("bundle", type=Path, metavar="BUNDLE")
    parser.set_defaults(handler=_pose)


def _pose(args: argparse.Namespace) -> int:
    from eyeserver.pipeline.eyepose import EyeModel, fit_eye
    from eyeserver.service.reconstruction import limbus_views, reconstruct_bundle

    cloud, _ = reconstruct_bundle(args.calibration, args.bundle, progress=_progress)
    views = limbus_views(args.calibration, args.bundle)
    # PoseError → "eyeserver: error: …", exit 2
    pose = fit_eye(cloud, EyeModel.population(), views)
    print(json.dumps(pose.to_dict(), indent=1))
    return 0
