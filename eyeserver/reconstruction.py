"""Reconstruct a capture bundle with a calibration: the glue between files and the pipeline.

The command line, the benches and the daemon share it, so it sits below the daemon
(:mod:`eyeserver.service`) and above what it joins (calibration, io, pipeline, the eye); like
them it never imports the simulator (an import contract in ``pyproject.toml``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from eyeserver.calibration.artefact import load_calibration
from eyeserver.calibration.phase_height import MARGIN_WARNING_RAD
from eyeserver.core.arrays import column_range
from eyeserver.core.types import Progress, quiet
from eyeserver.errors import EyeserverError
from eyeserver.eye import LimbusView
from eyeserver.io import Bundle, PointCloud, RigSpec, read_bundle
from eyeserver.pipeline.demodulate import Carrier
from eyeserver.pipeline.fusion import Part, Region, fuse
from eyeserver.pipeline.phase_height import PhaseHeightModel
from eyeserver.pipeline.reconstruct import (
    METHODS,
    CalibratedCamera,
    CameraCloud,
    Phase,
    camera_cloud,
    camera_phase,
    unit_clouds,
)


class ReconstructionError(EyeserverError):
    """A bundle cannot be reconstructed with the calibration given."""


RECONSTRUCTION_METHODS = ("auto", *METHODS)
"""The fringe-order methods a reconstruction may be asked for: ``auto`` (the default) picks one
per unit with :func:`unit_method`."""

BLIND_MARGIN_RAD = 0.01
"""A unit whose calibrated fringe-order margin is below this (rad) gets no evidence of the order
from its other camera at all, below the phase's own noise: its cameras at one azimuth
(examples/rooms/blind.toml, 6e-8 rad) picked orders two fringes off with every method that
trusts that camera, so ``auto`` takes the orders from another unit's camera
(:func:`order_judge`) or, without one, asks for a depth prior."""


def unit_method(document: dict[str, Any], unit_id: str, method: str, *,
                for_tracking: bool = False) -> tuple[str, str]:
    """The fringe-order method a unit is reconstructed with, and why.

    ``auto`` takes the spatial order (one order per region, voted by the multi-view picks of
    its pixels) wherever the calibration found the unit's two cameras discriminate fringe orders
    at all: it keeps what only one of them sees, which the multi-view order cannot
    (docs/notes/fringe-order.md), and the eye pose is fitted to it (the sclera beside steep lids:
    docs/notes/patient-eye.md, nineteenth session). With ``for_tracking`` (live tracking, whose
    frames must be posed within the frame period, its globe's radius held) it takes the
    multi-view order where the margin is at least ``MARGIN_WARNING_RAD``: about half the
    spatial order's time (``eyeserver bench speed``'s stage table). Below
    :data:`BLIND_MARGIN_RAD` it gives ``"blind"``: another unit's camera (:func:`order_judge`)
    or a depth prior must fix that unit's orders. Any other method is kept.
    """
    if method != "auto":
        return method, "asked for"
    units = (document.get("phase_to_height") or {}).get("units") or {}
    section = units.get(unit_id)
    margin = section.get("margin_rad") if isinstance(section, dict) else None
    if not isinstance(margin, (int, float)):
        return "spatial", "the calibration gives no fringe-order margin for this unit"
    if margin >= MARGIN_WARNING_RAD:
        if for_tracking:
            return "multi-view", (f"fringe-order margin {margin:.2f} rad, at least "
                                  f"{MARGIN_WARNING_RAD} rad")
        return "spatial", (f"fringe-order margin {margin:.2f} rad: regions unwrapped, each "
                           "order voted by the other camera, what only one camera sees kept")
    if margin >= BLIND_MARGIN_RAD:
        return "spatial", (f"fringe-order margin {margin:.2f} rad, below {MARGIN_WARNING_RAD} "
                           "rad: too blind for the multi-view order")
    return "blind", (f"fringe-order margin {margin:.3f} rad: its other camera cannot tell the "
                     "fringe orders apart (its cameras see the same depth per fringe)")


def blind_units(document: dict[str, Any]) -> dict[str, str]:
    """The units of a loaded calibration blind to the fringe order (:func:`unit_method`'s
    ``"blind"``), each with the reason: another unit's images must fix their orders."""
    units = (document.get("phase_to_height") or {}).get("units") or {}
    chosen = {unit_id: unit_method(document, unit_id, "auto") for unit_id in units}
    return {unit_id: why for unit_id, (method, why) in chosen.items() if method == "blind"}


@dataclass(frozen=True)
class ReconstructionOptions:
    """The choices of a reconstruction, as ``eyeserver reconstruct`` offers them.

    Attributes
    ----------
    method : {"auto", "multi-view", "spatial"}
        How fringe orders are fixed (see :mod:`eyeserver.pipeline.reconstruct`); ``auto`` per
        unit from its calibration (:func:`unit_method`).
    depth_prior_mm : float or None
        Height (mm) the surface lies near, within half a fringe's depth.
    roi : tuple of 6 floats or None
        ``(x0, y0, z0, x1, y1, z1)``: keep only points inside this WCS box (mm).
    min_quality : float
        Drop points of quality below this (0 to 1).

    Raises
    ------
    ReconstructionError
        For an unknown method, a value that is not finite, a box with a corner not below the
        other or a quality outside 0 to 1 (the message names the option).
    """

    method: str = "auto"
    depth_prior_mm: float | None = None
    roi: tuple[float, ...] | None = None
    min_quality: float = 0.0

    def __post_init__(self) -> None:
        if self.method not in RECONSTRUCTION_METHODS:
            raise ReconstructionError(f"method: unknown fringe-order method {self.method!r} "
                                      f"(one of {', '.join(RECONSTRUCTION_METHODS)})")
        if self.depth_prior_mm is not None and not math.isfinite(self.depth_prior_mm):
            raise ReconstructionError(f"depth_prior_mm must be finite, not {self.depth_prior_mm}")
        if self.roi is not None:
            self.region()
        if not 0.0 <= self.min_quality <= 1.0:
            raise ReconstructionError(f"min_quality must be between 0 and 1, not "
                                      f"{self.min_quality}")

    def region(self) -> Region | None:
        """The ``roi`` as the fusion step's box (None without one)."""
        if self.roi is None:
            return None
        if len(self.roi) != 6:
            raise ReconstructionError(f"roi must be [x0, y0, z0, x1, y1, z1], got {self.roi!r}")
        x0, y0, z0, x1, y1, z1 = (float(value) for value in self.roi)
        try:
            return Region((x0, y0, z0), (x1, y1, z1))
        except ValueError as exc:
            raise ReconstructionError(f"roi: {exc}") from None

    def to_dict(self) -> dict[str, object]:
        """The options as JSON values (``roi`` a list), for a reconstruction's summary."""
        return {"method": self.method, "depth_prior_mm": self.depth_prior_mm,
                "roi": None if self.roi is None else list(self.roi),
                "min_quality": self.min_quality}


def camera_carriers(document: dict[str, Any]) -> dict[str, Carrier]:
    """Each camera's fringe carrier in a loaded calibration (none before its phase-to-height
    models)."""
    section = document.get("phase_to_height") or {}
    return {camera_id: Carrier(tuple(entry["carrier_cycles_per_px"]))
            for camera_id, entry in section.get("cameras", {}).items()}


def calibrated_cameras(document: dict[str, Any]) -> dict[str, CalibratedCamera]:
    """The pipeline's view of every camera of a loaded calibration."""
    section = document.get("phase_to_height")
    if not section:
        raise ReconstructionError("the calibration has no phase-to-height models yet "
                                  "(run 'eyeserver calibrate p2h')")
    carrier_of = camera_carriers(document)
    cameras = {}
    for camera_id, cam in document["cameras"].items():
        p2h = section["cameras"][camera_id]
        reference = document["arrays"].get(f"reference_phase_{camera_id}")
        if reference is None:
            raise ReconstructionError(f"the calibration lacks camera {camera_id}'s reference "
                                      "phase (arrays.npz)")
        carrier = carrier_of[camera_id]
        cameras[camera_id] = CalibratedCamera(
            camera_id=camera_id, K=cam["K"], dist=cam["dist"], R=cam["R"], T=cam["T"],
            model=PhaseHeightModel.from_dict(p2h["model"]), carrier=carrier,
            reference_phase=reference, border_px=math.ceil(carrier.period_px))
    return cameras


def z_range(document: dict[str, Any]) -> tuple[float, float]:
    """The calibrated height range (mm) of a loaded calibration with phase-to-height models."""
    cameras = document["phase_to_height"]["cameras"]
    low, high = cameras[next(iter(cameras))]["z_range_mm"]
    return float(low), float(high)


def saturation_dn(bundle: Bundle) -> float | None:
    """The full scale of the bundle's images when it states its bit depth."""
    return float(2 ** bundle.bit_depth - 1) if bundle.bit_depth else None


def unit_pairs(bundle: Bundle) -> list[tuple[int, str, str]]:
    """``(frame, camera, partner)``: in each frame, the first two fringe cameras of each unit
    (the pair whose fringe order fixes the other's)."""
    by_unit: dict[tuple[int, str], list[str]] = {}
    for index, camera_id in bundle.fringe_images():
        by_unit.setdefault((index, bundle.rig.unit_of_camera(camera_id).id), []).append(camera_id)
    return [(index, ids[0], ids[1]) for (index, _), ids in by_unit.items() if len(ids) >= 2]


def order_judge(views: Sequence[tuple[int, str]], rig: RigSpec, unit_id: str,
                index: int) -> tuple[int, str] | None:
    """The view ``(frame, camera)`` of another unit nearest in time to frame ``index``, whose
    fringes fix the orders of unit ``unit_id`` when its own cameras cannot (a blind unit), or
    None when no other unit's image is among ``views``.

    Any calibrated camera judges a candidate point by its own projector's phase there; across
    units the wrong orders' points fall on unrelated phases, so the picks are right wherever
    both units see the surface (measured on examples/rooms/blind.toml: docs/notes/
    fringe-order.md). The calibration's margin cannot say so: it is a minimum over the volume,
    and across units the gap sweeps through zero somewhere, where the picks are not confident
    and do not vote."""
    others = [view for view in views if rig.unit_of_camera(view[1]).id != unit_id]
    return min(others, key=lambda view: (abs(view[0] - index), view), default=None)


EMPTY_REASON = ("no surface was reconstructed: nothing in the cameras' view carried its "
                "projector's fringes (an empty room, a dark projector)")
"""Why a reconstruction's cloud is empty: a valid answer, stated in its summary."""


def limbus_views(calibration: str | Path, bundle_path: str | Path) -> list[LimbusView]:
    """Each camera's first fringe image in a bundle, with its calibration: where the eye fit
    looks for the limbus (:func:`~eyeserver.eye.fit.fit_eye`)."""
    bundle = read_bundle(bundle_path)
    cameras = calibrated_cameras(load_calibration(calibration, bundle.rig))
    first: dict[str, int] = {}
    for index, camera_id in bundle.fringe_images():
        first.setdefault(camera_id, index)
    return [LimbusView(cameras[camera_id], bundle.load_image(index, camera_id))
            for camera_id, index in first.items()]


def reconstruct_bundle(calibration: str | Path, bundle_path: str | Path, *,
                       frames: Sequence[int] | None = None, cameras: Sequence[str] | None = None,
                       method: str = "auto", depth_prior_mm: float | None = None,
                       region: Region | None = None, min_quality: float = 0.0,
                       progress: Progress = quiet) -> tuple[PointCloud, dict[str, Any]]:
    """The fused point cloud of a measurement bundle, and a summary per camera.

    ``frames`` and ``cameras`` restrict the views used (default: every fringe image). A camera's
    fringe order is fixed with its unit's other camera in the same frame (``method``: see
    :mod:`eyeserver.pipeline.reconstruct`, ``auto`` chosen per unit by :func:`unit_method`), a
    blind unit's with another unit's camera (:func:`order_judge`); a camera alone in its frame
    needs ``depth_prior_mm``. ``region`` and ``min_quality`` crop the
    fused cloud. Each camera's summary says the method its unit used and why, the pixels that
    saw a fringe (``fringe_pixels``) and the share of them that gave a point (``coverage``).
    """
    if method not in RECONSTRUCTION_METHODS:
        raise ReconstructionError(f"unknown fringe-order method {method!r} (one of "
                                  f"{', '.join(RECONSTRUCTION_METHODS)})")
    bundle = read_bundle(bundle_path)
    document = load_calibration(calibration, bundle.rig)
    calibrated = calibrated_cameras(document)
    rig = bundle.rig
    chosen_frames = set(frames) if frames is not None else set(bundle.frame_indices)
    unknown_frames = chosen_frames - set(bundle.frame_indices)
    if unknown_frames:
        raise ReconstructionError(f"{bundle.path}: no frame {sorted(unknown_frames)}")
    chosen_cameras = set(cameras) if cameras is not None else set(rig.camera_ids)
    unknown = chosen_cameras - set(rig.camera_ids)
    if unknown:
        raise ReconstructionError(f"{bundle.path}: no camera {sorted(unknown)} in the rig")
    limits = z_range(document)
    saturation = saturation_dn(bundle)
    views = [(i, c) for i, c in bundle.fringe_images()
             if i in chosen_frames and c in chosen_cameras]
    if not views:
        raise ReconstructionError(f"{bundle.path}: no fringe image among the chosen frames and "
                                  "cameras (a camera's image counts only when its own unit's "
                                  "projector is lit)")
    summary: dict[str, Any] = {"cameras": {}, "method": method}
    # Per view: its points, the camera that fixed its orders (None: the depth prior did), the
    # method and why, and its pixels that see a fringe.
    done: dict[tuple[int, str], tuple[CameraCloud, str | None, str, str, int]] = {}
    methods = {unit.id: unit_method(document, unit.id, method) for unit in rig.units}
    judges: dict[tuple[int, str], Phase] = {}  # another unit's views a blind unit needed

    def phase_of(view: tuple[int, str], judge: bool = False) -> Phase:
        """A view's phase; a judge's is kept for its own unit's turn, no other (memory)."""
        phase = judges.get(view) if judge else judges.pop(view, None)
        if phase is None:
            phase = camera_phase(calibrated[view[1]], bundle.load_image(*view), saturation)
            if judge:
                judges[view] = phase
        return phase

    for index, camera_id in views:
        if (index, camera_id) in done:
            continue
        unit = rig.unit_of_camera(camera_id)
        partners = [c for c in unit.cameras if c != camera_id and (index, c) in views]
        cam = calibrated[camera_id]
        phase = phase_of((index, camera_id))
        seen = int(np.count_nonzero(phase.valid))
        chosen, why = methods[unit.id]
        judge = order_judge(views, rig, unit.id, index) if chosen == "blind" else None
        if not partners or (chosen == "blind" and judge is None):
            if depth_prior_mm is None:
                raise ReconstructionError(
                    f"{bundle.path}: frame {index} has no other camera of unit {unit.id} to fix "
                    f"camera {camera_id}'s fringe order; give a depth prior (the surface's "
                    "height within half a fringe's depth) to use the camera alone"
                    if not partners else
                    f"{bundle.path}: unit {unit.id} is blind to the fringe order ({why}) and no "
                    "other unit's camera among the chosen views can fix it; give a depth prior "
                    "(the surface's height within half a fringe's depth), include another "
                    "unit's images, or move one of its cameras to another azimuth and "
                    "calibrate again")
            alone_why = "no partner camera" if not partners else "blind unit"
            progress(f"frame {index}: camera {camera_id} ({alone_why}), order from the depth "
                     "prior")
            done[(index, camera_id)] = (camera_cloud(cam, phase, None, None, limits,
                                                     depth_prior_mm=depth_prior_mm),
                                        None, "depth prior", alone_why, seen)
            continue
        partner = partners[0]
        # Who fixes each camera's orders: its partner, or for a blind unit another unit's
        # camera, whose regions' votes the spatial order takes (docs/notes/fringe-order.md,
        # "A blind unit").
        fixers, judged = (partner, camera_id), None
        if judge is not None:
            judged = (calibrated[judge[1]], phase_of(judge, judge=True))
            fixers, chosen = (judge[1], judge[1]), "spatial"
            why = (f"{why}; its orders fixed by camera {judge[1]} of unit "
                   f"{rig.unit_of_camera(judge[1]).id}")
        progress(f"frame {index}: cameras {camera_id} and {partner} of unit {unit.id} "
                 f"({chosen} fringe order"
                 + (f" from camera {judge[1]})" if judge is not None else ")"))
        partner_phase = phase_of((index, partner))
        cloud_a, cloud_b = unit_clouds(cam, None, calibrated[partner], None, limits,
                                       method=chosen, depth_prior_mm=depth_prior_mm,
                                       phases=(phase, partner_phase),
                                       order_partners=None if judged is None
                                       else (judged, judged))
        done[(index, camera_id)] = (cloud_a, fixers[0], chosen, why, seen)
        done[(index, partner)] = (cloud_b, fixers[1], chosen, why,
                                  int(np.count_nonzero(partner_phase.valid)))
    parts = []
    for (index, camera_id), (camera_points, partner_id, chosen, why, seen) in done.items():
        parts.append(Part(camera_points.points, camera_points.quality,
                          rig.camera_index(camera_id), rig.unit_of_camera(camera_id).id))
        summary["cameras"][camera_id] = {
            "frame": index, "points": len(camera_points.points),
            "fringe_order": camera_points.order_counts, "partner": partner_id,
            "method": chosen, "method_reason": why, "fringe_pixels": seen,
            "coverage": round(len(camera_points.points) / seen, 4) if seen else 0.0}
    fused = fuse(parts, region=region, min_quality=min_quality)
    cloud = PointCloud(fused.points.astype(np.float32), fused.quality, fused.camera)
    summary["points"] = len(cloud)
    summary["dropped"] = {"seam_conflict": fused.dropped_seam,
                          "low_quality": fused.dropped_quality,
                          "outside_region": fused.dropped_region}
    if len(cloud):
        low, high = column_range(cloud.points)
        summary["extent_mm"] = {"min": low.tolist(), "max": high.tolist()}
    else:
        summary["extent_mm"] = None
        summary["empty_reason"] = EMPTY_REASON if not region and not min_quality else \
            f"{EMPTY_REASON}, or the region or minimum quality left none"
    return cloud, summary
