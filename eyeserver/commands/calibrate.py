"""``eyeserver calibrate …``: calibrations made offline from capture bundles."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from eyeserver.commands import Subparsers
from eyeserver.commands import progress as _progress
from eyeserver.errors import EyeserverError

REPROJECTION_GOAL_PX = 0.15
REPROJECTION_PAPER_PX = 0.88
P2H_GOAL_MM = 0.03
P2H_PAPER_MM = 0.12


def add_parser(subparsers: Subparsers) -> None:
    """Register ``eyeserver calibrate stereo`` and ``eyeserver calibrate p2h``."""
    calibrate = subparsers.add_parser("calibrate", help="calibrate from capture bundles",
                                      description="Calibrate the rig offline from bundles.")
    commands = calibrate.add_subparsers(title="calibrations", dest="calibrate_command",
                                        metavar="COMMAND")
    commands.required = True
    stereo = commands.add_parser(
        "stereo", help="intrinsics, distortion and WCS poses from chessboard bundles",
        description="Detect the chessboard in every camera of every bundle, solve each camera's "
        "intrinsics and distortion from all its boards and its pose from the origin board, "
        "write CALDIR and print the reprojection errors.")
    stereo.add_argument("--out", type=Path, required=True, metavar="CALDIR")
    stereo.add_argument("--overwrite", action="store_true")
    stereo.add_argument("bundles", nargs="+", type=Path, metavar="BUNDLE")
    stereo.set_defaults(handler=_stereo)
    p2h = commands.add_parser(
        "p2h", help="phase-to-height models from the plate stack and the reference plane",
        description="Demodulate the plate stack against the reference plane, unwrap each pixel "
        "along Z over the whole range, fit each camera's Du & Wang model, add it to CALDIR and "
        "print the residuals and each unit's fringe-order margin.")
    p2h.add_argument("--calibration", type=Path, required=True, metavar="CALDIR")
    p2h.add_argument("plate", type=Path, metavar="PLATE_BUNDLE")
    p2h.add_argument("reference", type=Path, metavar="REFERENCE_BUNDLE")
    p2h.set_defaults(handler=_p2h)


def _stereo(args: argparse.Namespace) -> int:
    from eyeserver.calibration.artefact import stereo_document, write_calibration
    from eyeserver.calibration.stereo import calibrate_stereo

    result = calibrate_stereo(args.bundles, progress=_progress)
    document = stereo_document(result)
    try:
        write_calibration(args.out, document, overwrite=args.overwrite)
    except FileExistsError as exc:
        raise EyeserverError(f"{args.out} exists and is not empty (use --overwrite)") from exc
    print(f"stereo calibration of {len(result.cameras)} cameras from "
          f"{len(result.inputs)} chessboard bundles → {args.out}")
    print(f"reprojection error (px): goal ≤ {REPROJECTION_GOAL_PX}, paper "
          f"{REPROJECTION_PAPER_PX} median")
    print(f"  {'camera':<8}{'median':>8}{'IQR':>8}{'max':>8}{'boards':>8}")
    for cid, cam in result.cameras.items():
        q = cam.quality()
        print(f"  {cid:<8}{q['reprojection_median_px']:>8.3f}{q['reprojection_iqr_px']:>8.3f}"
              f"{q['reprojection_max_px']:>8.3f}{q['boards']:>8}")
    overall = document["quality"]
    print(f"  {'all':<8}{overall['reprojection_median_px']:>8.3f}"
          f"{overall['reprojection_iqr_px']:>8.3f}")
    for board, cameras in result.missed.items():
        print(f"  note: {board} was not found by {', '.join(cameras)}")
    return 0


def _p2h(args: argparse.Namespace) -> int:
    from eyeserver.calibration.artefact import load_calibration, write_calibration
    from eyeserver.calibration.phase_height import MARGIN_WARNING_RAD, calibrate_phase_height
    from eyeserver.io import bundle_hash

    document = load_calibration(args.calibration)
    arrays = document.pop("arrays")
    section, new_arrays = calibrate_phase_height(document, args.plate, args.reference,
                                                 progress=_progress)
    document["phase_to_height"] = section
    document["inputs"]["phase_to_height"] = [
        {"bundle": Path(p).name, "sha256": bundle_hash(p)} for p in (args.plate, args.reference)]
    write_calibration(args.calibration, document, {**arrays, **new_arrays}, overwrite=True)
    print(f"phase-to-height calibration → {args.calibration}")
    print(f"residual |Z_model − Z_nominal| (mm): goal ≤ {P2H_GOAL_MM} median, paper "
          f"{P2H_PAPER_MM} (IQR 0.15)")
    print(f"  {'camera':<8}{'median':>8}{'IQR':>8}{'RMSE':>8}  range")
    for cid, cam in section["cameras"].items():
        q = cam["quality"]
        low, high = cam["z_range_mm"]
        print(f"  {cid:<8}{q['median_abs_mm']:>8.4f}{q['iqr_mm']:>8.4f}{q['rmse_mm']:>8.4f}"
              f"  {low:+.0f}…{high:+.0f} mm (all of it usable)")
    print(f"fringe-order margin per unit (rad; the multi-view order needs ≥ {MARGIN_WARNING_RAD}):")
    for unit_id, unit in section["units"].items():
        if unit.get("margin_rad") is None:
            print(f"  {unit_id}: {unit['note']}")
            continue
        print(f"  {unit_id}: {unit['margin_rad']:.2f} over orders up to ±{unit['orders_checked']}"
              + (f" — {unit['note']}" if "note" in unit else ""))
    return 0


def add_reconstruct_parser(subparsers: Subparsers) -> None:
    """Register ``eyeserver reconstruct``."""
    parser = subparsers.add_parser(
        "reconstruct", help="the fused point cloud of a measurement bundle",
        description="Reconstruct the measurement in BUNDLE with the calibration in CALDIR and "
        "write the fused point cloud as binary PLY (x y z in WCS mm, quality, camera).")
    parser.add_argument("--calibration", type=Path, required=True, metavar="CALDIR")
    parser.add_argument("--out", type=Path, required=True, metavar="CLOUD.ply")
    parser.add_argument("--frames", metavar="I,J", help="frame indices to use (default: all)")
    parser.add_argument("--cameras", metavar="S1,S2", help="cameras to use (default: all)")
    parser.add_argument("bundle", type=Path, metavar="BUNDLE")
    parser.set_defaults(handler=_reconstruct)


def _reconstruct(args: argparse.Namespace) -> int:
    from eyeserver.io import write_ply
    from eyeserver.service.reconstruction import reconstruct_bundle

    frames = None
    if args.frames:
        try:
            frames = [int(f) for f in args.frames.split(",")]
        except ValueError:
            raise EyeserverError(f"--frames: not a list of frame numbers: {args.frames!r}") \
                from None
    cameras = args.cameras.split(",") if args.cameras else None
    started = time.perf_counter()
    cloud, summary = reconstruct_bundle(args.calibration, args.bundle, frames=frames,
                                        cameras=cameras, progress=_progress)
    write_ply(args.out, cloud)
    print(f"{summary['points']} points → {args.out} ({time.perf_counter() - started:.1f} s)")
    for cid, cam in summary["cameras"].items():
        print(f"  {cid}: {cam['points']} points (frame {cam['frame']}, fringe order "
              f"{cam['fringe_order']} with {cam['partner']})")
    return 0
