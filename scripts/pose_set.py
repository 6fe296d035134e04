"""Render a fixed set of simulated eyes once, then fit them with any checkout: an A/B of the pose
fit on the same images (the bench renders anew on every run).

    .venv/bin/python scripts/pose_set.py render --eyes patient --count 16 --seed 11 SETDIR
    .venv/bin/python scripts/pose_set.py fit --calibration CALDIR SETDIR
    .venv/bin/python scripts/pose_set.py fit --stages --method multi-view \
        --calibration CALDIR SETDIR
    .venv/bin/python scripts/pose_set.py oracle --calibration CALDIR SETDIR
    .venv/bin/python scripts/pose_set.py cloud --calibration CALDIR SETDIR
    .venv/bin/python scripts/pose_set.py ablate --seed 6 --calibration CALDIR SETDIR
    .venv/bin/python scripts/pose_set.py lids [--room ROOM] --calibration CALDIR SETDIR
    .venv/bin/python scripts/pose_set.py limbus [--room ROOM] [--widths MM ...] \
        --calibration CALDIR SETDIR
    .venv/bin/python scripts/pose_set.py orientation --calibration CALDIR SETDIR
    .venv/bin/python scripts/pose_set.py sclera --calibration CALDIR SETDIR
    PYTHONPATH=/path/to/other/checkout .venv/bin/python scripts/pose_set.py fit ... SETDIR

Eyes are drawn as ``eyeserver.hardware.sim.population.draw`` draws them and placed within ±5 mm
and ±10° as the pose bench places them; each bundle keeps its ``truth.json``, which only the fit
step's scoring reads, after the fit (``--stages``: also the cloud-only pose and the limbus the
free search finds from it (an oval, no axis held), each against the truth, and how far the true
and the found limbus centres lie from the cloud globe's axis). ``oracle`` is a diagnostic, not a fit: it hands the globe's
stages the true limbus circle (the corneoscleral junction: the scene's horizontal limbus
radius), to see what the rest of the fit makes of a perfectly found limbus. A calibration
comes from ``eyeserver bench accuracy --out`` or the benches' ``calibrate_room``.

``ablate`` renders one drawn patient eye at rest (centred at (0, 0, −10) mm, gaze 0, as a
reference capture sees it) with each group of its properties in turn set to the sharp eye's
(``-group``) and the sharp eye given only that group of the patient's (``+group``), and fits
each: which property alone breaks the fit. ``lids`` renders the sharp eye with lids 0.3–0.8 mm
outside the globe (the population's range reaches 0.3) and two lid openings, and fits each:
are lids close to the globe told from the sclera. ``limbus`` renders ``tests/test_limbus.py``'s
looking eye with limbus transitions of 0.2 and 0.5 mm (``--widths``) before a dark and a light
iris, and fits each: is the limbus found across widths and contrasts (with its stated sd beside
the errors).
``orientation`` is a diagnostic of any rendered set: the limbus edges each camera finds about
the true junction, their offsets from it binned by how the limbus runs to the camera's fringes.
``sclera`` is another (any set, ``lids``'s too): the cloud's points behind the true limbus by
the true surface each lies nearest, the sclera's offset from the true globe by its distance
from the lids, and the globe placed on the true limbus circle.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
from pathlib import Path
from typing import Any

import numpy as np


def render(args: argparse.Namespace) -> None:
    from eyeserver.hardware.sim import population
    from eyeserver.hardware.sim.config import load_room
    from eyeserver.hardware.sim.scenes import SceneSpec
    from eyeserver.hardware.sim.sessions import SimSession

    rng = np.random.default_rng(args.seed)
    with SimSession.open(load_room(args.room), seed=args.seed + 1) as session:
        for k in range(args.count):
            eye = population.draw(rng, args.eyes)
            position = np.array([0.0, 0.0, -10.0]) + rng.uniform(-5.0, 5.0, 3)
            gaze = rng.uniform(-10.0, 10.0, 2)
            eye = eye.model_copy(update={"gaze_deg": (float(gaze[0]), float(gaze[1]))})
            spec = SceneSpec(kind="eye", position_mm=tuple(float(v) for v in position), eye=eye)
            session.record(spec, args.setdir / f"eye_{k:03d}", overwrite=True)
            print(f"rendered eye_{k:03d}", flush=True)


def off(pose_centre: Any, pose_gaze: Any, eye: dict[str, Any], key: str = "centre_mm") -> str:
    """How far a pose (or limbus, ``key``) lies from the truth's: centre in mm, gaze in °."""
    centre = float(np.linalg.norm(np.subtract(pose_centre, eye[key])))
    cos = float(np.asarray(pose_gaze) @ np.asarray(eye["gaze"]))
    return f"centre {centre:.3f} mm gaze {math.degrees(math.acos(min(1.0, cos))):.2f}°"


def across_axis(point: Any, direction: Any, through: Any) -> float:
    """How far (mm) ``point`` lies from the line through ``through`` along unit ``direction``:
    a limbus centre's offset from a globe's axis."""
    offset = np.subtract(point, through)
    g = np.asarray(direction, dtype=np.float64)
    return float(np.linalg.norm(offset - (offset @ g) * g))


def fit(args: argparse.Namespace) -> None:
    from eyeserver.errors import EyeserverError
    from eyeserver.eye.fit import EyeModel, fit_eye
    from eyeserver.eye.limbus import LimbusNotFoundError, find_limbus
    from eyeserver.reconstruction import limbus_views, reconstruct_bundle

    for bundle in sorted(args.setdir.glob("eye_*")):
        truth = json.loads((bundle / "truth.json").read_text())
        eye, spec = truth["eye"], truth["scene"]["eye"]
        model = EyeModel.population()
        try:
            cloud, _ = reconstruct_bundle(args.calibration, bundle, method=args.method)
            views = limbus_views(args.calibration, bundle)
            if args.stages:
                rough = fit_eye(cloud, model)
                stages = f"  cloud alone: {off(rough.centre_mm, rough.gaze, eye)}, radius " \
                    f"{rough.globe_radius_mm:.2f} for {eye['globe_radius_mm']:.2f} mm"
                true_off = across_axis(eye["limbus_centre_mm"], eye["gaze"], rough.centre_mm)
                stages += f"; the true limbus {true_off:.2f} mm off its axis"
                try:
                    # The free search (no axis held), as the fit ran before the twenty-third
                    # session and still runs for one unit.
                    limbus = find_limbus(views, rough.centre_mm, rough.gaze,
                                         rough.globe_radius_mm, model.limbus_diameter_mm / 2,
                                         oval=True)
                    found = off(limbus.centre, limbus.normal, eye, "limbus_centre_mm")
                    stages += f"; limbus from it: {found} (its centre), radius " \
                        f"{limbus.radius:.2f} mm, " \
                        f"{across_axis(limbus.centre, limbus.normal, rough.centre_mm):.2f} mm " \
                        "off the cloud globe's axis"
                except (EyeserverError, LimbusNotFoundError) as exc:
                    stages += f"; no limbus from it: {exc}"
            pose = fit_eye(cloud, model, views)
        except EyeserverError as exc:
            print(f"{bundle.name} refused: {exc}", flush=True)
            continue
        print(f"{bundle.name} {off(pose.centre_mm, pose.gaze, eye)} confidence "
              f"{pose.confidence:.2f} ({pose.gaze_source}); limbus width "
              f"{spec['limbus_width_mm']:.2f} mm, ratio {spec['limbus_vertical_ratio']:.2f}, "
              f"iris {spec['iris_albedo']:.2f}, sclera {spec['sclera_albedo']:.2f}, "
              f"ellipsoid {spec['globe_semi_axes_mm'] is not None}", flush=True)
        if args.stages:
            print(stages, flush=True)


def oracle(args: argparse.Namespace) -> None:
    from eyeserver.errors import EyeserverError
    from eyeserver.eye.fit import checked_cloud
    from eyeserver.eye.limbus import Limbus, globe_on_limbus
    from eyeserver.eye.sclera import refit
    from eyeserver.reconstruction import limbus_views, reconstruct_bundle

    for bundle in sorted(args.setdir.glob("eye_*")):
        truth = json.loads((bundle / "truth.json").read_text())
        eye, spec = truth["eye"], truth["scene"]["eye"]
        centre, gaze = np.asarray(eye["centre_mm"]), np.asarray(eye["gaze"])
        limbus = Limbus(centre=np.asarray(eye["limbus_centre_mm"]), normal=gaze,
                        radius=spec["limbus_diameter_mm"] / 2, centre_sd_mm=0.01,
                        gaze_sd_deg=0.1, radius_sd_mm=0.01, residual_px=0.2, coverage={})
        try:
            cloud, _ = reconstruct_bundle(args.calibration, bundle, method=args.method)
            points, _ = checked_cloud(cloud)
            globe = globe_on_limbus(points, limbus)
            again = refit(limbus_views(args.calibration, bundle), limbus, globe.centre,
                          globe.radius, globe.sclera, points, None, 7.8)
        except EyeserverError as exc:
            print(f"{bundle.name} no globe: {exc}", flush=True)
            continue
        line = (f"{bundle.name} on the true limbus: centre "
                f"{np.linalg.norm(globe.centre - centre):.3f} mm, radius {globe.radius:.2f} "
                f"for {eye['globe_radius_mm']:.2f} mm")
        if again is not None:
            cos = float(again.gaze @ gaze)
            line += (f"; remeasured: centre {np.linalg.norm(again.centre - centre):.3f} mm, gaze "
                     f"{math.degrees(math.acos(min(1.0, cos))):.2f}°")
        print(f"{line} (ellipsoid {spec['globe_semi_axes_mm'] is not None}, limbus width "
              f"{spec['limbus_width_mm']:.2f} mm)", flush=True)


ABLATION_GROUPS = {
    "shape": ("globe_radius_mm", "globe_semi_axes_mm"),
    "cornea": ("cornea_radius_mm", "cornea_asphericity"),
    "limbus_size": ("limbus_diameter_mm", "limbus_vertical_ratio"),
    "limbus_edge": ("limbus_width_mm", "limbus_scatter"),
    "albedo": ("sclera_albedo", "iris_albedo"),
    "iris": ("iris_depth_mm", "pupil_diameter_mm"),
    "tear": ("tear_reflectance", "tear_glints"),
    "lids": ("aperture_mm", "aperture_offset_mm", "lid_gap_mm"),
    "lashes": ("lashes",),
}
"""The drawn eye's properties (``EyeSpec`` fields), grouped as ``ablate`` swaps them."""


def ablate(args: argparse.Namespace) -> None:
    from eyeserver.hardware.sim import population
    from eyeserver.hardware.sim.config import load_room
    from eyeserver.hardware.sim.scenes import SceneSpec
    from eyeserver.hardware.sim.sessions import SimSession

    patient = population.draw(np.random.default_rng(args.seed), "patient")
    sharp = population.draw(np.random.default_rng(args.seed), "sharp")
    variants = {"patient": patient, "sharp": sharp}
    for name, keys in ABLATION_GROUPS.items():
        variants[f"-{name}"] = patient.model_copy(update={k: getattr(sharp, k) for k in keys})
        variants[f"+{name}"] = sharp.model_copy(update={k: getattr(patient, k) for k in keys})
    with SimSession.open(load_room(args.room), seed=3) as session:
        for name, eye in variants.items():
            bundle = args.setdir / f"seed{args.seed}{name}"
            session.record(SceneSpec(kind="eye", position_mm=(0.0, 0.0, -10.0), eye=eye),
                           bundle, overwrite=True)
            print(f"{name:14s} {scored(args.calibration, bundle)}", flush=True)


def scored(calibration: Path, bundle: Path) -> str:
    """``bundle`` reconstructed and fitted with the population's model (radius fitted): how
    far the pose lies from the truth, its confidence and radius, or why it was refused."""
    from eyeserver.errors import EyeserverError
    from eyeserver.eye.fit import EyeModel, fit_eye
    from eyeserver.reconstruction import limbus_views, reconstruct_bundle

    truth = json.loads((bundle / "truth.json").read_text())["eye"]
    try:
        made, _ = reconstruct_bundle(calibration, bundle)
        pose = fit_eye(made, EyeModel.population(), limbus_views(calibration, bundle))
    except EyeserverError as exc:
        return f"refused: {exc}"
    return (f"{off(pose.centre_mm, pose.gaze, truth)} confidence {pose.confidence:.2f} "
            f"radius {pose.globe_radius_mm:.2f} mm")


LID_GAPS_MM = (0.3, 0.45, 0.6, 0.8)
"""The lid shells' distances from the globe that ``lids`` renders (mm)."""

LID_OPENINGS = (((10.2, 7.5), (-0.1, -0.6)), ((11.0, 6.5), (0.0, -0.3)))
"""Its lid openings: half-width and half-height, centre from the globe's axis (mm)."""


def lids(args: argparse.Namespace) -> None:
    from eyeserver.hardware.sim.config import load_room
    from eyeserver.hardware.sim.scenes import EyeSpec, SceneSpec
    from eyeserver.hardware.sim.sessions import SimSession

    with SimSession.open(load_room(args.room), seed=3) as session:
        for gap in LID_GAPS_MM:
            for aperture, offset in LID_OPENINGS:
                bundle = args.setdir / f"lids{gap:g}_open{aperture[1]:g}"
                eye = EyeSpec(gaze_deg=(3.0, -2.0), globe_radius_mm=12.0, aperture_mm=aperture,
                              aperture_offset_mm=offset, lid_gap_mm=gap)
                session.record(SceneSpec(kind="eye", position_mm=(0.5, -0.5, -10.5), eye=eye),
                               bundle, overwrite=True)
                print(f"{bundle.name:18s} {scored(args.calibration, bundle)}",
                      flush=True)


LIMBUS_IRISES = {"dark": 0.06, "light": 0.25}
"""``limbus``'s irises: their albedo in near-infrared (the sclera's 0.42)."""


def limbus(args: argparse.Namespace) -> None:
    from eyeserver.errors import EyeserverError
    from eyeserver.eye.fit import EyeModel, fit_eye
    from eyeserver.hardware.sim.config import load_room
    from eyeserver.hardware.sim.scenes import EyeSpec, SceneSpec
    from eyeserver.hardware.sim.sessions import SimSession
    from eyeserver.reconstruction import limbus_views, reconstruct_bundle

    with SimSession.open(load_room(args.room), seed=3) as session:
        for width, (shade, iris) in itertools.product(args.widths, LIMBUS_IRISES.items()):
            name = f"{width:g} mm, {shade} iris"
            bundle = args.setdir / f"limbus{width:g}_iris{iris:g}"
            eye = EyeSpec(gaze_deg=(7.0, -4.0), globe_radius_mm=12.5, limbus_width_mm=width,
                          iris_albedo=iris, sclera_albedo=0.42)
            session.record(SceneSpec(kind="eye", position_mm=(1.5, -1.0, -11.0), eye=eye),
                           bundle, overwrite=True)
            truth = json.loads((bundle / "truth.json").read_text())["eye"]
            try:
                made, _ = reconstruct_bundle(args.calibration, bundle)
                pose = fit_eye(made, EyeModel.population(),
                               limbus_views(args.calibration, bundle))
            except EyeserverError as exc:
                print(f"{name:20s} refused: {exc}", flush=True)
                continue
            found = ("no limbus" if pose.limbus_centre_mm is None else
                     off(pose.limbus_centre_mm, pose.gaze, truth, "limbus_centre_mm")
                     + f" (its radius {pose.boundary_radius_mm or math.nan:.2f} mm)")
            sd = ", ".join(f"{v:.3f}" for v in pose.centre_sd_mm)
            globe = float(np.linalg.norm(np.subtract(pose.centre_mm, truth["centre_mm"])))
            print(f"{name:20s} limbus {found}; globe centre {globe:.3f} mm, stated sd "
                  f"({sd}) mm, shape sd {pose.shape_sd_mm:.2f} mm, confidence "
                  f"{pose.confidence:.2f}", flush=True)


ORIENTATION_BINS = ((0.0, 0.5), (0.5, 0.8), (0.8, 0.95), (0.95, 1.01))
"""``orientation``'s bins of |cos| between an edge's outward normal and the camera's carrier (1:
the limbus runs along the fringes there)."""


def orientation(args: argparse.Namespace) -> None:
    from eyeserver.eye import limbus as limbus_module
    from eyeserver.reconstruction import limbus_views

    print("median offset of the edges from the true junction, mm (outwards +), and their count, "
          "per |cos| bin " + ", ".join(f"{lo:g}-{min(hi, 1):g}" for lo, hi in ORIENTATION_BINS))
    for bundle in sorted(p for p in args.setdir.iterdir() if (p / "truth.json").exists()):
        truth = json.loads((bundle / "truth.json").read_text())
        eye, spec = truth["eye"], truth["scene"]["eye"]
        centre, gaze = np.asarray(eye["limbus_centre_mm"]), np.asarray(eye["gaze"])
        radius, ratio = spec["limbus_diameter_mm"] / 2, spec["limbus_vertical_ratio"]
        cells = []
        for view in limbus_views(args.calibration, bundle):
            image = limbus_module._Image(view, None)
            angles, edges = limbus_module._edges(image, centre, gaze, radius, 8.0, ratio=ratio)
            on, outward = image.outline(centre, gaze, radius, angles, ratio)
            beyond, _ = image.outline(centre, gaze, radius + 0.1, angles, ratio)
            offset = ((edges - on) * outward).sum(axis=1) / (
                np.linalg.norm(beyond - on, axis=1) / 0.1)
            fy, fx = view.camera.carrier.frequency
            along = np.abs(outward @ np.array([fx, fy])) / math.hypot(fx, fy)
            bins = [offset[(along >= lo) & (along < hi)] for lo, hi in ORIENTATION_BINS]
            cells.append(view.camera.camera_id + " " + " ".join(
                f"{np.median(b):+.2f}({len(b)})" if len(b) else "-" for b in bins))
        print(f"{bundle.name:20s} " + " | ".join(cells), flush=True)


def cloud(args: argparse.Namespace) -> None:
    """Each eye's cloud against the exact scene (globe, cornea, iris, lids, lashes, skin): is
    the reconstruction right before any fit, and what share of the globe's neighbourhood is
    lid rather than sclera."""
    from eyeserver.hardware.sim.config import load_room
    from eyeserver.hardware.sim.scoring import score_by_surface, score_cloud
    from eyeserver.reconstruction import reconstruct_bundle

    config = load_room(args.room)
    for bundle in sorted(args.setdir.glob("eye_*")):
        truth = json.loads((bundle / "truth.json").read_text())
        made, _ = reconstruct_bundle(args.calibration, bundle, method=args.method)
        score = score_cloud(truth, made, config)
        lit = [c["lit_share"] for c in score["coverage"].values()]
        surfaces = score_by_surface(truth, made)
        near = ", ".join(f"{name} {v['points']}" for name, v in surfaces.items()
                         if name in ("sclera", "lids", "iris", "lashes"))
        print(f"{bundle.name}: median {score['median_mm']:.4f} mm, beyond 1 mm "
              f"{score['beyond_1mm']:.4f}, lit share {min(lit):.2f}-{max(lit):.2f}; points on "
              f"{near}", flush=True)


SCLERA_FROM_LIDS_MM = (0.0, 0.5, 1.0, 1.5, 2.0, 3.0, math.inf)
"""``sclera``'s bins of the distance from the nearest lid point (mm)."""


def sclera(args: argparse.Namespace) -> None:
    """Each render's cloud behind the true limbus, by the true surface each point lies nearest
    (a diagnostic, ground truth only): how many points are sclera and how many lids, how far
    the sclera lies off the true globe by its distance from the lids (the band-limited
    demodulation blends the two near the lid margin), and the globe that
    ``limbus.globe_on_limbus`` places on the true limbus circle."""
    from scipy.spatial import cKDTree

    from eyeserver.eye.limbus import Limbus, behind_limbus, globe_on_limbus
    from eyeserver.hardware.sim.scoring import nearest_surfaces
    from eyeserver.reconstruction import reconstruct_bundle

    for bundle in sorted(p.parent for p in args.setdir.glob("*/truth.json")):
        truth = json.loads((bundle / "truth.json").read_text())
        eye = truth["eye"]
        made, _ = reconstruct_bundle(args.calibration, bundle)
        points = made.points.astype(np.float64)
        label, _, _ = nearest_surfaces(truth, points)
        centre, gaze = np.asarray(eye["centre_mm"]), np.asarray(eye["gaze"])
        junction = np.asarray(eye["limbus_centre_mm"])
        depth = float((junction - centre) @ gaze)
        radius = math.sqrt(eye["globe_radius_mm"] ** 2 - depth**2)
        true = Limbus(centre=junction, normal=gaze, radius=radius, centre_sd_mm=0.0,
                      gaze_sd_deg=0.0, radius_sd_mm=0.0, residual_px=0.0, coverage={})
        behind = behind_limbus(points, true)
        counts = ", ".join(f"{name} {int(np.sum(behind & (label == name)))}"
                           for name in ("sclera", "lids"))
        try:
            globe = globe_on_limbus(points, true)
            placed = (f"globe on the true limbus {np.linalg.norm(globe.centre - centre):.3f} mm "
                      f"off, radius {globe.radius:.2f} for {eye['globe_radius_mm']:.2f} mm")
        except ValueError as exc:
            placed = f"no globe on the true limbus: {exc}"
        print(f"{bundle.name}: behind the limbus {counts}; {placed}", flush=True)
        on_sclera, on_lids = behind & (label == "sclera"), label == "lids"
        if not on_sclera.any() or not on_lids.any():
            continue
        off = np.linalg.norm(points[on_sclera] - centre, axis=1) - eye["globe_radius_mm"]
        from_lids, _ = cKDTree(points[on_lids]).query(points[on_sclera])
        for lo, hi in itertools.pairwise(SCLERA_FROM_LIDS_MM):
            mine = (from_lids >= lo) & (from_lids < hi)
            if mine.any():
                print(f"    sclera {lo:g}-{hi:g} mm from the lids: {int(mine.sum()):5d} points, "
                      f"off the globe median {np.median(off[mine]):+.3f} mm, "
                      f"p90 {np.percentile(off[mine], 90):+.3f} mm", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    steps = parser.add_subparsers(required=True)
    make = steps.add_parser("render", help="render a set of eyes into SETDIR")
    make.add_argument("--eyes", default="patient", choices=("patient", "sharp"))
    make.add_argument("--count", type=int, default=16)
    make.add_argument("--seed", type=int, default=0)
    make.add_argument("--room", type=Path, default=None, help="room file (default room)")
    make.add_argument("setdir", type=Path)
    make.set_defaults(step=render)
    score = steps.add_parser("fit", help="fit every eye of SETDIR and score it")
    score.add_argument("--calibration", type=Path, required=True, metavar="CALDIR")
    score.add_argument("--method", default="auto", choices=("auto", "multi-view", "spatial"),
                       help="the reconstruction's fringe order (default: as `eyeserver pose`)")
    score.add_argument("--stages", action="store_true",
                       help="also score the cloud-only pose and the limbus found from it")
    score.add_argument("setdir", type=Path)
    score.set_defaults(step=fit)
    bound = steps.add_parser("oracle", help="the globe's stages from the true limbus (a "
                             "diagnostic: what a perfectly found limbus would give)")
    bound.add_argument("--calibration", type=Path, required=True, metavar="CALDIR")
    bound.add_argument("--method", default="auto", choices=("auto", "multi-view", "spatial"))
    bound.add_argument("setdir", type=Path)
    bound.set_defaults(step=oracle)
    swap = steps.add_parser("ablate", help="one patient eye at rest with each group of its "
                            "properties swapped for the sharp eye's, fitted")
    swap.add_argument("--calibration", type=Path, required=True, metavar="CALDIR")
    swap.add_argument("--seed", type=int, default=6, help="the population draw's seed")
    swap.add_argument("--room", type=Path, default=None, help="room file (default room)")
    swap.add_argument("setdir", type=Path)
    swap.set_defaults(step=ablate)
    shells = steps.add_parser("lids", help="the sharp eye with lids close to the globe, fitted")
    shells.add_argument("--calibration", type=Path, required=True, metavar="CALDIR")
    shells.add_argument("--room", type=Path, default=None, help="room file (default room)")
    shells.add_argument("setdir", type=Path)
    shells.set_defaults(step=lids)
    edges = steps.add_parser("limbus", help="limbus transitions and contrasts, fitted")
    edges.add_argument("--calibration", type=Path, required=True, metavar="CALDIR")
    edges.add_argument("--room", type=Path, default=None, help="room file (default room)")
    edges.add_argument("--widths", type=float, nargs="+", default=[0.2, 0.5], metavar="MM",
                       help="the transitions' 10–90 %% widths (default 0.2 0.5)")
    edges.add_argument("setdir", type=Path)
    edges.set_defaults(step=limbus)
    turned = steps.add_parser("orientation", help="the limbus edges about the true junction, "
                              "by how the limbus runs to the fringes (a diagnostic)")
    turned.add_argument("--calibration", type=Path, required=True, metavar="CALDIR")
    turned.add_argument("setdir", type=Path)
    turned.set_defaults(step=orientation)
    by_surface = steps.add_parser("cloud", help="each eye's cloud against the exact scene")
    by_surface.add_argument("--calibration", type=Path, required=True, metavar="CALDIR")
    by_surface.add_argument("--method", default="auto", choices=("auto", "multi-view", "spatial"))
    by_surface.add_argument("--room", type=Path, default=None, help="room file (default room)")
    by_surface.add_argument("setdir", type=Path)
    by_surface.set_defaults(step=cloud)
    shell = steps.add_parser("sclera", help="the cloud's sclera and lids behind the true "
                             "limbus, and the globe on it (a diagnostic)")
    shell.add_argument("--calibration", type=Path, required=True, metavar="CALDIR")
    shell.add_argument("setdir", type=Path)
    shell.set_defaults(step=sclera)
    args = parser.parse_args()
    args.step(args)


if __name__ == "__main__":
    main()
