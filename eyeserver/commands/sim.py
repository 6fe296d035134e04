"""``eyeserver sim …``: record scenes and calibration sets in the simulated room."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from eyeserver.commands import Subparsers
from eyeserver.commands import progress as _progress
from eyeserver.errors import EyeserverError, FormatError

SCENES = ("chessboard", "plate", "reference", "pyramid", "wedge", "eye_phantom_1",
          "eye_phantom_2", "eye")


def add_parser(subparsers: Subparsers) -> None:
    """Register ``eyeserver sim render`` and ``eyeserver sim calibration-set``."""
    sim = subparsers.add_parser("sim", help="the simulated treatment room",
                                description="Record bundles in the simulated treatment room.")
    commands = sim.add_subparsers(title="sim commands", dest="sim_command", metavar="COMMAND")
    commands.required = True

    render = commands.add_parser(
        "render", help="capture one scene as a bundle (with its truth.json)",
        description="Capture a scene with every camera, each unit lit in turn (chessboards under "
        "room light), and write a capture bundle with the scene's ground truth as truth.json.")
    render.add_argument("--scene", required=True, choices=SCENES)
    render.add_argument("--position", type=float, nargs=3, metavar=("X", "Y", "Z"),
                        help="scene position in mm (default: the scene's own, e.g. the eye's "
                        "globe centre at 0 0 -10, the reference plane at Z=+10)")
    render.add_argument("--rotation", type=float, nargs=3, metavar=("RX", "RY", "RZ"),
                        default=(0.0, 0.0, 0.0), help="rotation in degrees (Rz·Ry·Rx)")
    render.add_argument("--gaze", type=float, nargs=2, metavar=("YAW", "PITCH"),
                        help="eye only: gaze yaw (towards +X) and pitch (up) in degrees")
    render.add_argument("--globe-radius", type=float, metavar="MM", help="eye only")
    render.add_argument("--cornea-radius", type=float, metavar="MM", help="eye only")
    render.add_argument("--motion-seed", type=int, metavar="N",
                        help="eye only: let the eye move (drift, micro-saccades, blinks) with "
                        "this seed")
    render.add_argument("--time", type=float, default=0.0, metavar="S",
                        help="seconds the scene runs before the capture (a moving eye)")
    render.add_argument("--scene-file", type=Path, metavar="FILE",
                        help="a JSON scene spec (SceneSpec) instead of the options above")
    render.add_argument("--units", metavar="IDS", help="comma-separated units to light "
                        "(default: all, in rig order)")
    render.add_argument("--room", type=Path, metavar="FILE", help="room file (default room)")
    render.add_argument("--seed", type=int, help="noise seed (default: the room file's)")
    render.add_argument("--out", type=Path, required=True, metavar="DIR")
    render.add_argument("--overwrite", action="store_true",
                        help="replace an existing bundle at --out")
    render.set_defaults(handler=_render)

    calib = commands.add_parser(
        "calibration-set", help="write a full calibration set",
        description="Write DIR/rig.json, DIR/chessboard_NN (00 is the origin board), DIR/plate "
        "(Z from --z-min to --z-max in --z-step) and DIR/reference, ready for calibration.")
    calib.add_argument("--room", type=Path, metavar="FILE", help="room file (default room)")
    calib.add_argument("--seed", type=int, help="noise seed (default: the room file's)")
    calib.add_argument("--z-min", type=float, default=-10.0, metavar="MM")
    calib.add_argument("--z-max", type=float, default=25.0, metavar="MM")
    calib.add_argument("--z-step", type=float, default=1.0, metavar="MM")
    calib.add_argument("--reference-z", type=float, default=10.0, metavar="MM")
    calib.add_argument("--out", type=Path, required=True, metavar="DIR")
    calib.add_argument("--overwrite", action="store_true")
    calib.set_defaults(handler=_calibration_set)

    score = commands.add_parser(
        "score", help="compare a point cloud with a scene's exact surface",
        description="Distance of every point of CLOUD.ply to the exact surface of the scene in "
        "a bundle's truth.json: median and RMSE, share beyond 1 mm, and coverage (points per "
        "camera over the pixels of that camera that see the scene).")
    score.add_argument("--truth", type=Path, required=True, metavar="FILE")
    score.add_argument("--room", type=Path, metavar="FILE",
                       help="room file the bundle was rendered in (for coverage)")
    score.add_argument("--json", action="store_true", help="one JSON document on stdout")
    score.add_argument("cloud", type=Path, metavar="CLOUD.ply")
    score.set_defaults(handler=_score)


def _scene_spec(args: argparse.Namespace) -> object:
    from pydantic import ValidationError

    from eyeserver.hardware.sim.motion import MotionSpec
    from eyeserver.hardware.sim.scenes import EyeSpec, SceneSpec

    if args.scene_file is not None:
        try:
            data = json.loads(args.scene_file.read_text(encoding="utf-8"))
            return SceneSpec.model_validate({**data, "kind": args.scene})
        except OSError as exc:
            raise FormatError(args.scene_file, None, f"cannot read ({exc.strerror})") from exc
        except ValueError as exc:
            raise FormatError(args.scene_file, None, str(exc).splitlines()[0]) from exc
    eye: dict[str, object] = {}
    if args.gaze is not None:
        eye["gaze_deg"] = tuple(args.gaze)
    if args.globe_radius is not None:
        eye["globe_radius_mm"] = args.globe_radius
    if args.cornea_radius is not None:
        eye["cornea_radius_mm"] = args.cornea_radius
    if args.motion_seed is not None:
        eye["motion"] = MotionSpec(seed=args.motion_seed, blink_rate_hz=0.2)
    if eye and args.scene != "eye":
        raise EyeserverError("--gaze, --globe-radius, --cornea-radius and --motion-seed apply "
                             "to --scene eye")
    try:
        return SceneSpec(kind=args.scene,
                         position_mm=tuple(args.position) if args.position else None,
                         rotation_deg=tuple(args.rotation), eye=EyeSpec(**eye))
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        raise EyeserverError(f"bad scene option {where}: {first['msg']}") from exc


def _render(args: argparse.Namespace) -> int:
    from eyeserver.hardware.sim.config import load_room
    from eyeserver.hardware.sim.scenes import SceneSpec
    from eyeserver.hardware.sim.sessions import SimSession

    spec = _scene_spec(args)
    assert isinstance(spec, SceneSpec)
    room = load_room(args.room)
    if args.time < 0:
        raise EyeserverError(f"--time must not be negative ({args.time})")
    units = args.units.split(",") if args.units else None
    known = [u.id for u in room.units]
    if units is not None and (unknown := [u for u in units if u not in known]):
        raise EyeserverError(f"--units: no unit {', '.join(unknown)} in the room "
                             f"(it has {', '.join(known)})")
    _progress(f"rendering {spec.kind} with {len(room.cameras())} cameras")
    started = time.perf_counter()
    with SimSession.open(room, args.seed) as session:
        try:
            session.record(spec, args.out, units=units, origin=spec.kind == "chessboard",
                           overwrite=args.overwrite, scene_time_s=args.time)
        except FileExistsError as exc:
            raise EyeserverError(f"{args.out} exists and is not empty (use --overwrite)") \
                from exc
    _progress(f"wrote {args.out} in {time.perf_counter() - started:.1f} s")
    return 0


def _calibration_set(args: argparse.Namespace) -> int:
    from eyeserver.hardware.sim.config import load_room
    from eyeserver.hardware.sim.sessions import SimSession, plate_heights, write_calibration_set

    room = load_room(args.room)
    try:
        z_values = plate_heights(args.z_min, args.z_max, args.z_step)
    except ValueError as exc:
        raise EyeserverError(f"--z-min/--z-max/--z-step: {exc}") from exc
    started = time.perf_counter()
    with SimSession.open(room, args.seed) as session:
        try:
            summary = write_calibration_set(session, args.out, z_values=z_values,
                                            reference_z=args.reference_z,
                                            overwrite=args.overwrite, progress=_progress)
        except FileExistsError as exc:
            raise EyeserverError(f"{exc.filename or args.out} exists and is not empty "
                                 "(use --overwrite)") from exc
    _progress(f"wrote {args.out} ({summary['chessboards']} chessboards, "
              f"{summary['plate_heights']} plate heights) in "
              f"{time.perf_counter() - started:.0f} s")
    return 0


def _score(args: argparse.Namespace) -> int:
    from eyeserver.hardware.sim.config import load_room
    from eyeserver.hardware.sim.scoring import score_cloud
    from eyeserver.io import read_ply

    try:
        truth = json.loads(args.truth.read_text(encoding="utf-8"))
    except OSError as exc:
        raise FormatError(args.truth, None, f"cannot read ({exc.strerror})") from exc
    except ValueError as exc:
        raise FormatError(args.truth, None, f"not valid JSON: {exc}") from exc
    if isinstance(truth, list):  # a plate stack's truth: one entry per height
        raise EyeserverError(f"{args.truth}: holds several scenes; score one scene's bundle")
    result = score_cloud(truth, read_ply(args.cloud), load_room(args.room))
    if args.json:
        print(json.dumps(result, indent=1))
        return 0
    print(f"{args.cloud} against the exact {result['scene']} ({result['points']} points)")
    print(f"  median |distance| {result['median_mm']:.4f} mm, RMSE {result['rmse_mm']:.4f} mm "
          f"(goal ≤ 0.15 mm), beyond 1 mm {100 * result['beyond_1mm']:.3f} %")
    for cid, cov in result["coverage"].items():
        print(f"  {cid}: {cov['points']} points, coverage {100 * cov['share']:.1f} %")
    return 0
