"""``eyeserver bench accuracy``: the paper's validation on the simulated room.

The bench calibrates a simulated rig exactly as a physicist would (a calibration set recorded by
the room, ``calibrate stereo`` and ``calibrate p2h``), then records phantoms at several poses in
the calibrated volume, reconstructs each with all four views and with each unit's two views, and
scores every cloud against the scene's exact surface: the median |distance| and RMSE, and the
paper's "ICP RMSE after rigid registration" (the cloud registered point-to-plane onto a dense
sampling of the exact surface, then scored by its exact distance to it). The phantoms' dots,
found in the images, are located by the fringe surface around them and compared with their
stereo triangulation: the paper's headline figure.

Figures the bench does not measure yet are reported under ``pending`` with the reason, never
invented.
"""

from __future__ import annotations

import json
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from eyeserver.bench.figures import FIGURES
from eyeserver.bench.simcal import calibrate_room
from eyeserver.bench.speed import machine
from eyeserver.calibration.artefact import load_calibration
from eyeserver.hardware.sim.config import RoomConfig
from eyeserver.hardware.sim.room import SimRoom
from eyeserver.hardware.sim.scenes import SceneSpec, build_scene
from eyeserver.hardware.sim.scoring import score_cloud
from eyeserver.hardware.sim.sessions import SimSession
from eyeserver.hardware.sim.truth import truth_scene
from eyeserver.io import PointCloud, read_bundle
from eyeserver.pipeline.fiducials import (
    detect_fiducials,
    match_stereo,
    surface_position,
    triangulate,
)
from eyeserver.pipeline.reconstruct import unit_clouds
from eyeserver.pipeline.registration import icp_point_to_plane
from eyeserver.service.reconstruction import calibrated_cameras, reconstruct_bundle

Progress = Callable[[str], None]

PENDING = {
    "seam_error_mm": "the seam figure comes with the accuracy bench (issue 4)",
    "eye_model_distance_mm": "the eye model is issue 7",
    "static_noise_mm": "the repeatability figure comes with the accuracy bench (issue 4)",
    "ftm_phase_error_rad": "the public 4-step set is scored in the accuracy bench (issue 4)",
}
"""DESIGN §8 keys this bench does not measure yet, and why."""

ICP_SAMPLE = 5000
"""Cloud points each ICP iteration pairs (of a few hundred thousand)."""


def _quiet(_: str) -> None:
    pass


@dataclass(frozen=True)
class Case:
    """One phantom at one pose."""

    name: str
    spec: SceneSpec


PHANTOMS = ("pyramid", "wedge", "eye_phantom_1", "eye_phantom_2")


def cases(quick: bool, kinds: Sequence[str] = PHANTOMS) -> list[Case]:
    """The phantoms and poses measured: each phantom at the centre of the volume, and with the
    full run also shifted, turned and raised or lowered within it."""
    poses: list[tuple[tuple[float, float, float], tuple[float, float, float]]] = [
        ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))]
    if not quick:
        poses += [((2.0, -1.5, -4.0), (6.0, -4.0, 0.0)), ((-1.5, 2.0, 5.0), (-5.0, 5.0, 20.0)),
                  ((1.0, 1.0, 10.0), (3.0, 7.0, -15.0))]
    out = []
    for kind in kinds:
        for n, (position, rotation) in enumerate(poses):
            spec = SceneSpec(kind=kind, position_mm=position, rotation_deg=rotation)
            out.append(Case(f"{kind}#{n}", spec))
    return out


@contextmanager
def _workdir(out: Path | None) -> Iterator[Path]:
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        yield out
        return
    with tempfile.TemporaryDirectory(prefix="eyeserver-bench-") as tmp:
        yield Path(tmp)


def calibration_figures(caldir: Path) -> dict[str, Any]:
    """Reprojection error and phase-to-height residual per camera, from the artefact."""
    document = load_calibration(caldir)
    cameras = {cid: {"reprojection_median_px": cam["quality"]["reprojection_median_px"],
                     "reprojection_iqr_px": cam["quality"]["reprojection_iqr_px"]}
               for cid, cam in document["cameras"].items()}
    for cid, cam in document["phase_to_height"]["cameras"].items():
        cameras[cid]["p2h_residual_median_mm"] = cam["quality"]["median_abs_mm"]
        cameras[cid]["p2h_residual_iqr_mm"] = cam["quality"]["iqr_mm"]
    residuals = [c["p2h_residual_median_mm"] for c in cameras.values()]
    return {"reprojection_px": document["quality"]["reprojection_median_px"],
            "reprojection_iqr_px": document["quality"]["reprojection_iqr_px"],
            "p2h_residual_mm": float(np.median(residuals)),
            "margins_rad": {u: v.get("margin_rad")
                            for u, v in document["phase_to_height"]["units"].items()},
            "cameras": cameras}


def exact_surface(truth: dict[str, Any], room: SimRoom, camera_ids: Sequence[str],
                  ) -> np.ndarray:
    """Dense points of the exact surface: where the cameras' pixel rays meet it."""
    scene = build_scene(truth_scene(truth), float(truth.get("t_s", 0.0))).scene
    points = []
    for cid in camera_ids:
        cam = room.renderer.cameras[cid]
        rays = cam.rays().reshape(-1, 3)
        hit = scene.cast(cam.centre, rays)
        seen = np.isfinite(hit.t)
        points.append(cam.centre + hit.t[seen, None] * rays[seen])
    return np.concatenate(points)


def icp_rmse(truth: dict[str, Any], cloud: PointCloud, room: SimRoom,
             camera_ids: Sequence[str]) -> float:
    """The paper's figure: RMSE of the cloud after rigid registration onto the exact surface.

    ICP (point-to-plane) moves the cloud onto a dense sampling of the exact surface; the moved
    cloud is then scored by its exact distance to the surface (a nearest-sample distance would
    add the sampling's own spacing). The phantoms are nearly symmetric (a sphere on a plane
    turns about its vertical axis almost unseen), so ICP can slide far along such a motion to a
    pose no better than where it started: the measured pose is itself a rigid registration, and
    the better of the two is the figure.
    """
    scene = build_scene(truth_scene(truth), float(truth.get("t_s", 0.0))).scene
    target = exact_surface(truth, room, camera_ids)
    source = cloud.points.astype(np.float64)
    registration = icp_point_to_plane(source, target[::2], max_distance_mm=1.0,
                                      sample=ICP_SAMPLE, seed=0)
    registered = float(np.sqrt(np.mean(scene.distance(registration.apply(source)) ** 2)))
    as_measured = float(np.sqrt(np.mean(scene.distance(source) ** 2)))
    return min(registered, as_measured)


FIDUCIAL_RING_PERIODS = (0.8, 1.6)
"""Ring around a dot, in fringe periods, whose reconstructed surface locates it: the mask
erodes about a period around the dark dot, so the ring starts just beyond."""


def fiducial_errors(caldir: Path, bundle_path: Path) -> list[list[float]]:
    """Per dot seen by both cameras of a unit: fringe-derived position − stereo triangulation
    (x, y, z in mm). The dots are located in the images (never taken from the truth)."""
    bundle = read_bundle(bundle_path)
    document = load_calibration(caldir, bundle.rig)
    cameras = calibrated_cameras(document)
    z_range = tuple(document["phase_to_height"]["cameras"][bundle.rig.camera_ids[0]]
                    ["z_range_mm"])
    errors: list[list[float]] = []
    for index in bundle.frame_indices:
        ids = [c for i, c in bundle.fringe_images() if i == index]
        if len(ids) < 2:
            continue
        a, b = cameras[ids[0]], cameras[ids[1]]
        image_a, image_b = bundle.load_image(index, ids[0]), bundle.load_image(index, ids[1])
        cloud_a, _ = unit_clouds(a, image_a, b, image_b, (float(z_range[0]), float(z_range[1])))
        dots_a = detect_fiducials(image_a, a.carrier.period_px)
        dots_b = detect_fiducials(image_b, b.carrier.period_px)
        pairs = match_stereo(dots_a, dots_b, a.K, a.dist, a.R, a.T, b.K, b.dist, b.R, b.T)
        if not len(pairs):
            continue
        stereo = triangulate(dots_a[pairs[:, 0]], dots_b[pairs[:, 1]], a.K, a.dist, a.R, a.T,
                             b.K, b.dist, b.R, b.T)
        h, w = a.shape
        depth = np.full((h * w, 3), np.nan)
        depth[cloud_a.pixels] = cloud_a.points
        ring = (FIDUCIAL_RING_PERIODS[0] * a.carrier.period_px,
                FIDUCIAL_RING_PERIODS[1] * a.carrier.period_px)
        fringe = surface_position(dots_a[pairs[:, 0]], depth.reshape(h, w, 3), a.K, a.dist,
                                  a.R, a.T, ring_px=ring, degree=2)
        found = np.all(np.isfinite(fringe), axis=1)
        errors.extend((fringe[found] - stereo[found]).tolist())
    return errors


def _views(config: RoomConfig) -> list[tuple[str, list[str] | None, str]]:
    """(name, cameras, fringe-order method): 4 views (every camera) and each unit's 2 views with
    the fast path, and 4 views with the robust path for comparison."""
    views: list[tuple[str, list[str] | None, str]] = [("4view", None, "multi-view")]
    for unit in config.units:
        views.append((f"2view-{unit.id}", [c.id for c in unit.cameras], "multi-view"))
    views.append(("4view", None, "spatial"))
    return views


def run(config: RoomConfig, *, quick: bool = False, seed: int = 0, out: Path | None = None,
        calibration: Path | None = None, phantoms: Sequence[str] = PHANTOMS,
        progress: Progress = _quiet) -> dict[str, Any]:
    """The whole accuracy report as one JSON-able document."""
    started = time.perf_counter()
    room = SimRoom(config)
    with _workdir(out) as work:
        if calibration is None:
            progress("calibrating the simulated rig (calibration set, stereo, phase-to-height)")
            caldir = calibrate_room(config, work, seed, progress)
        else:
            caldir = calibration
        report: dict[str, Any] = {"format": "eyeserver.bench.accuracy/1",
                                  "machine": machine(), "seed": seed, "quick": quick,
                                  "noise_model": _noise_model(config)}
        calib = calibration_figures(caldir)
        report["calibration"] = calib
        report["reprojection_px"] = calib["reprojection_px"]
        report["p2h_residual_mm"] = calib["p2h_residual_mm"]
        measurements = []
        fiducials: list[dict[str, Any]] = []
        all_cases = cases(quick, phantoms)
        views = _views(config)
        with SimSession.open(config, seed=seed + 1) as session:
            for n, case in enumerate(all_cases):
                progress(f"{case.name} ({n + 1}/{len(all_cases)})")
                bundle = work / "scenes" / case.name.replace("#", "_")
                session.record(case.spec, bundle, overwrite=True)
                truth = json.loads((bundle / "truth.json").read_text())
                case_errors = fiducial_errors(caldir, bundle)
                fiducials.extend({"case": case.name, "error_mm": e} for e in case_errors)
                for view, cameras, method in views:
                    started_view = time.perf_counter()
                    cloud, _ = reconstruct_bundle(caldir, bundle, cameras=cameras, method=method)
                    seconds = time.perf_counter() - started_view
                    ids = cameras or [c.id for u in config.units for c in u.cameras]
                    score = score_cloud(truth, cloud, config)
                    coverage = [c["share"] for c in score["coverage"].values()]
                    measurements.append({
                        "case": case.name, "views": view, "method": method,
                        "points": score["points"], "median_mm": score["median_mm"],
                        "rmse_mm": score["rmse_mm"], "beyond_1mm": score["beyond_1mm"],
                        "coverage": float(np.mean(coverage)) if coverage else 0.0,
                        "reconstruct_s": seconds,
                        "icp_rmse_mm": icp_rmse(truth, cloud, room, ids) if len(cloud)
                        else float("nan")})
        report["measurements"] = measurements
    vectors = np.asarray([f["error_mm"] for f in fiducials], dtype=np.float64).reshape(-1, 3)
    distance = np.linalg.norm(vectors, axis=1)
    report["fiducials"] = {
        "measurements": len(distance),
        "sessions": len({f["case"] for f in fiducials}),
        "iqr_mm": float(np.subtract(*np.percentile(distance, [75, 25]))) if len(distance)
        else None,
        "per_axis_median_abs_mm": np.median(np.abs(vectors), axis=0).tolist() if len(distance)
        else None,
        "errors_mm": vectors.tolist()}
    report["fiducial_error_mm"] = float(np.median(distance)) if len(distance) else None
    for method, kind, prefix in (("multi-view", "4view", "4view"),
                                 ("multi-view", "2view", "2view"),
                                 ("spatial", "4view", "spatial_4view")):
        rows = [m for m in measurements if m["views"].startswith(kind) and m["method"] == method]
        for key, field in (("surface_median", "median_mm"), ("surface_rmse", "rmse_mm"),
                           ("icp_rmse", "icp_rmse_mm"), ("coverage", "coverage"),
                           ("beyond_1mm", "beyond_1mm")):
            values = np.asarray([m[field] for m in rows], dtype=np.float64)
            unit = "" if key in ("coverage", "beyond_1mm") else "_mm"
            name = f"{key}_{prefix}{unit}" if prefix != "spatial_4view" else \
                f"spatial_{key}_4view{unit}"
            report[name] = float(np.nanmedian(values)) if len(values) else None
            if unit:
                report[name.replace("_mm", "_iqr_mm")] = (
                    float(np.subtract(*np.nanpercentile(values, [75, 25]))) if len(values)
                    else None)
        report[f"{prefix}_measurements"] = len(rows)
    report["pending"] = dict(PENDING)
    for key in PENDING:
        report[key] = None
    report["duration_s"] = round(time.perf_counter() - started, 1)
    return report


def _noise_model(config: RoomConfig) -> dict[str, Any]:
    camera = config.units[0].cameras[0]
    return {"shot_noise_full_well_e": camera.full_well_e, "read_noise_dn": camera.read_noise_dn,
            "bit_depth": camera.bit_depth,
            "rig": {u.id: {"projector": u.projector.id, "cameras": [c.id for c in u.cameras]}
                    for u in config.units}}


def format_text(report: dict[str, Any]) -> str:
    """A table of the figures beside the paper's and the goal."""
    noise = report["noise_model"]
    lines = [f"eyeserver bench accuracy — simulated room, seed {report['seed']}, "
             f"{'quick' if report['quick'] else 'full'} run",
             f"noise model: shot noise (full well {noise['shot_noise_full_well_e']:.0f} e⁻), "
             f"read noise {noise['read_noise_dn']} DN, {noise['bit_depth']}-bit", "",
             f"{'figure':<54}{'paper':>21}{'goal':>8}{'eyeserver':>11}"]
    for key, figure in FIGURES.items():
        value = report.get(key)
        shown = "pending" if value is None else f"{value:.3f}"
        lines.append(f"{figure.label + ' (' + figure.unit + ')':<54}{figure.paper:>21}"
                     f"{'≤ ' + str(figure.goal):>8}{shown:>11}")
    lines.append("")
    fid = report["fiducials"]
    if fid["measurements"]:
        x, y, z = fid["per_axis_median_abs_mm"]
        lines.append(f"fiducials: {fid['measurements']} dots in {fid['sessions']} sessions, "
                     f"fringe − triangulation median {report['fiducial_error_mm']:.3f} mm "
                     f"(IQR {fid['iqr_mm']:.3f}; |x| {x:.3f}, |y| {y:.3f}, |z| {z:.3f})")
    lines.append("")
    lines.append("fringe order, multi-view (fast) against spatial (robust), 4 views, medians:")
    for label, fast, robust, scale, unit in (
            ("|distance| to exact surface", "surface_median_4view_mm",
             "spatial_surface_median_4view_mm", 1.0, " mm"),
            ("RMSE", "surface_rmse_4view_mm", "spatial_surface_rmse_4view_mm", 1.0, " mm"),
            ("share beyond 1 mm", "beyond_1mm_4view", "spatial_beyond_1mm_4view", 100.0, " %"),
            ("coverage of the pixels seeing the scene", "coverage_4view",
             "spatial_coverage_4view", 100.0, " %")):
        if report.get(fast) is not None and report.get(robust) is not None:
            lines.append(f"  {label:<42}{scale * report[fast]:>9.3f}{unit:<4}"
                         f"{scale * report[robust]:>9.3f}{unit}")
    lines.append("")
    lines.append(f"{report['4view_measurements']} 4-view and {report['2view_measurements']} "
                 "2-view reconstructions of the phantoms:")
    lines.append(f"  {'case':<18}{'views':<13}{'method':<11}{'points':>8}{'median':>8}"
                 f"{'RMSE':>8}{'ICP RMSE':>9}{'>1 mm':>7}{'cover':>7}{'s':>6}")
    for m in report["measurements"]:
        lines.append(f"  {m['case']:<18}{m['views']:<13}{m['method']:<11}{m['points']:>8}"
                     f"{m['median_mm']:>8.4f}{m['rmse_mm']:>8.4f}{m['icp_rmse_mm']:>9.4f}"
                     f"{100 * m['beyond_1mm']:>6.2f}%{100 * m['coverage']:>6.1f}%"
                     f"{m['reconstruct_s']:>6.2f}")
    for key, why in report["pending"].items():
        lines.append(f"pending {key}: {why}")
    lines.append(f"took {report['duration_s']} s")
    return "\n".join(lines)
