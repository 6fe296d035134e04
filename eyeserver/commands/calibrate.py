"""``eyeserver calibrate …``: calibrations made offline from capture bundles."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from eyeserver.bench.figures import FIGURES
from eyeserver.commands import Subparsers
from eyeserver.commands import progress as _progress
from eyeserver.errors import EyeserverError

REPROJECTION = FIGURES["reprojection_px"]
P2H = FIGURES["p2h_residual_mm"]


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
    print(f"reprojection error (px): goal ≤ {REPROJECTION.goal} median, paper "
          f"{REPROJECTION.paper}")
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
    from eyeserver.calibration.phase_height import MARGIN_WARNING_RAD, add_phase_height

    section = add_phase_height(args.calibration, args.plate, args.reference, progress=_progress)
    print(f"phase-to-height calibration → {args.calibration}")
    print(f"residual |Z_model − Z_nominal| (mm): goal ≤ {P2H.goal} median, paper "
          f"{P2H.paper}")
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
    parser.add_argument("--method", choices=("auto", "multi-view", "spatial"), default="auto",
                        help="fringe order: per pixel from the unit's other camera (multi-view: "
                        "fast, needs a unit whose calibration found a clear fringe-order "
                        "margin), spatial unwrapping with one order per region voted by the "
                        "other camera (spatial: slower, keeps more of what only one camera "
                        "sees), or, the default, auto: spatial for every unit whose "
                        "calibration found a fringe-order margin")
    parser.add_argument("--depth-prior", type=float, metavar="Z_MM",
                        help="height (mm) the surface lies near, within half a fringe's depth: "
                        "fixes the order of a camera alone in its unit and of spatial regions "
                        "the other camera cannot judge")
    parser.add_argument("--roi", type=float, nargs=6, metavar=("X0", "Y0", "Z0", "X1", "Y1", "Z1"),
                        help="keep only points inside this WCS box (mm)")
    parser.add_argument("--min-quality", type=float, default=0.0, metavar="Q",
                        help="drop points of quality below Q (0–1; default 0)")
    parser.add_argument("bundle", type=Path, metavar="BUNDLE")
    parser.set_defaults(handler=_reconstruct)


def _reconstruct(args: argparse.Namespace) -> int:
    from eyeserver.io import write_ply
    from eyeserver.pipeline.fusion import Region
    from eyeserver.reconstruction import reconstruct_bundle

    frames = None
    if args.frames:
        try:
            frames = [int(f) for f in args.frames.split(",")]
        except ValueError:
            raise EyeserverError(f"--frames: not a list of frame numbers: {args.frames!r}") \
                from None
    cameras = args.cameras.split(",") if args.cameras else None
    region = None
    if args.roi:
        try:
            region = Region(tuple(args.roi[:3]), tuple(args.roi[3:]))
        except ValueError as exc:
            raise EyeserverError(f"--roi: {exc}") from None
    if not 0.0 <= args.min_quality <= 1.0:
        raise EyeserverError(f"--min-quality must be between 0 and 1, not {args.min_quality}")
    started = time.perf_counter()
    cloud, summary = reconstruct_bundle(args.calibration, args.bundle, frames=frames,
                                        cameras=cameras, method=args.method,
                                        depth_prior_mm=args.depth_prior, region=region,
                                        min_quality=args.min_quality, progress=_progress)
    write_ply(args.out, cloud)
    print(f"{summary['points']} points → {args.out} ({time.perf_counter() - started:.1f} s)")
    for cid, cam in summary["cameras"].items():
        orders = ", ".join(f"{n} {name}" for name, n in cam["fringe_order"].items()) or "none"
        partner = f"orders fixed with {cam['partner']}" if cam["partner"] else "alone"
        print(f"  {cid}: {cam['points']} points, {cam['coverage']:.0%} of the "
              f"{cam['fringe_pixels']} pixels that see a fringe (frame {cam['frame']}, "
              f"{partner}; {cam['method']}: {cam['method_reason']}; fringe order from {orders})")
    dropped = {k: v for k, v in summary["dropped"].items() if v}
    if dropped:
        print("  dropped: " + ", ".join(f"{n} {k.replace('_', ' ')}" for k, n in dropped.items()))
    return 0
