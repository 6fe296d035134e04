"""Phase-to-height calibration from the plate stack and the reference plane (docs/design.md §5).

Per camera: the carrier is measured on the reference image and kept; every plate image is
demodulated and its phase taken relative to the reference. The 1 mm steps move each pixel's phase
by much less than π, so the stack is unwrapped along Z, pixel by pixel, walking outwards from the
reference plane (where Δφ ≡ 0): the whole calibrated range becomes monotonic, not just the part
spatial unwrapping could reach. The eleven Du & Wang coefficients are then fitted on undistorted,
normalised image coordinates (from the stereo calibration), and the residuals reported per camera
and per Z. A plane whose residual stands out means the walk slipped by 2π there, and the
calibration stops with that plane named rather than produce a wrong model.

Each unit's fringe-order margin is computed too: how far (rad) the nearest wrong order's
predicted phase in the unit's other camera lies from the right one's, over the calibrated
volume; the multi-view fringe order needs a clear margin (docs/design.md §4 step 4).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from eyeserver.calibration.stereo import CalibrationError
from eyeserver.core.arrays import wrap
from eyeserver.core.types import F64, Progress, quiet
from eyeserver.io import Bundle, RigSpec, read_bundle, rig_from_dict
from eyeserver.pipeline.demodulate import (
    border_mask,
    demodulate,
    measure_carrier,
    phase_difference,
)
from eyeserver.pipeline.geometry import (
    intersect_plane_z,
    pixel_grid_normalised,
    rays_from_normalised,
)
from eyeserver.pipeline.phase_height import PhaseHeightModel, fit_phase_height

SAMPLE_STRIDE = 4
"""Every 4th pixel along each axis feeds the fit (20 k pixels per plane): plenty for 11
coefficients, and it keeps a 36-plane stack at a few hundred thousand samples."""
SLIP_MM = 1.0
"""A plane whose median |residual| exceeds this has slipped by 2π (one fringe is ≈ 5 mm)."""
MARGIN_WARNING_RAD = 0.5
"""Below this, noise can pick the wrong fringe order (docs/design.md §4 step 4)."""


def _fringe_frames(bundle: Bundle, camera_id: str) -> list[int]:
    return [index for index, cid in bundle.fringe_images() if cid == camera_id]


def _valid(modulation: npt.NDArray[np.float32]) -> npt.NDArray[np.bool_]:
    # Fringe amplitude well below what the plate shows elsewhere: shadow, border or no plate.
    reference_level = float(np.percentile(modulation, 90))
    return np.asarray(modulation > 0.3 * reference_level)


def _unwrap_along_z(z_values: list[float], wrapped: list[npt.NDArray[np.float32]],
                    valid: list[npt.NDArray[np.bool_]], z_reference: float,
                    ) -> tuple[list[F64], list[npt.NDArray[np.bool_]]]:
    """Absolute Δφ per plane, walking outwards from the plane nearest the reference."""
    start = int(np.argmin([abs(z - z_reference) for z in z_values]))
    unwrapped: list[F64 | None] = [None] * len(z_values)
    chain: list[npt.NDArray[np.bool_] | None] = [None] * len(z_values)
    unwrapped[start] = wrapped[start].astype(np.float64)
    chain[start] = valid[start]
    for direction in (1, -1):
        k = start + direction
        while 0 <= k < len(z_values):
            previous = unwrapped[k - direction]
            assert previous is not None
            step = wrap(wrapped[k] - previous)
            unwrapped[k] = previous + step
            # A pixel stays trustworthy only while every plane between it and the reference was.
            prior = chain[k - direction]
            assert prior is not None
            chain[k] = prior & valid[k]
            k += direction
    return [u for u in unwrapped if u is not None], [c for c in chain if c is not None]


def fringe_order_margin(model_a: PhaseHeightModel, model_b: PhaseHeightModel,
                        cam_a: dict[str, Any], cam_b: dict[str, Any], z_range: tuple[float, float],
                        half_width_mm: float = 8.0) -> dict[str, float | int]:
    """Smallest phase gap (rad) in camera B between the right and any wrong fringe order of A.

    For points on a grid over the calibrated volume, each candidate order k ≠ 0 of camera A
    moves the point along A's ray to another height inside the calibrated range; the phase B
    would then see differs from the true one by a gap. The margin is the smallest |gap| over
    points and candidates. A range shallower than any wrong order's step leaves no candidate:
    the margin is then π, the largest a wrapped gap can be (a calibration with plates over
    −4…+4 mm gave ``inf`` here, which no JSON holds).
    """
    xs = np.linspace(-half_width_mm, half_width_mm, 7)
    zs = np.linspace(z_range[0], z_range[1], 15)
    grid = np.stack(np.meshgrid(xs, xs, zs, indexing="ij"), axis=-1).reshape(-1, 3)

    def normalised(cam: dict[str, Any], points: F64) -> tuple[F64, F64]:
        local = points @ cam["R"].T + cam["T"]
        return local[..., 0] / local[..., 2], local[..., 1] / local[..., 2]

    xa, ya = normalised(cam_a, grid)
    xb, yb = normalised(cam_b, grid)
    phase_a = model_a.phase(xa, ya, grid[:, 2])
    phase_b = model_b.phase(xb, yb, grid[:, 2])
    centre_a = -cam_a["R"].T @ cam_a["T"]
    rays = rays_from_normalised(xa, ya, cam_a["R"])
    smallest, orders = math.pi, 0
    for k in range(1, 40):
        found = False
        for sign in (1, -1):
            z_k = model_a.height(xa, ya, phase_a + sign * 2 * math.pi * k)
            inside = (z_k >= z_range[0]) & (z_k <= z_range[1])
            if not np.any(inside):
                continue
            found = True
            points = intersect_plane_z(centre_a, rays[inside], z_k[inside])
            xk, yk = normalised(cam_b, points)
            gap = np.angle(np.exp(1j * (model_b.phase(xk, yk, z_k[inside]) - phase_b[inside])))
            smallest = min(smallest, float(np.min(np.abs(gap))))
            orders = max(orders, k)
        if not found:
            break
    return {"margin_rad": smallest, "orders_checked": orders}


SAFE_STEP_SHARE = 0.8
"""A step between neighbouring planes may move a pixel's phase by at most this share of π: the
walk along Z takes the nearest 2π multiple, so π is where it slips, and noise and the few pixels
steeper than the percentile need the rest."""
SENSITIVITY_PERCENTILE = 99.0
"""The phase sensitivity of a camera is this percentile over its valid pixels: the steepest
part of the view (the fringes are denser where the plate is nearer the projector) decides."""


def phase_sensitivity(plate_path: str | Path, reference_path: str | Path,
                      plate_index: int | None = None) -> dict[str, float]:
    """Each camera's fringe-phase sensitivity to height (rad/mm), measured between the reference
    plane and one plate near it.

    The phase difference of the plate and the reference is taken wrapped, so the plate must be
    close enough that no pixel's phase moved by π or more: a probe 1 mm from the reference is,
    for any rig whose fringes span more than 2 mm of height.

    Parameters
    ----------
    plate_path, reference_path : path
        A ``plate`` bundle (its frame ``plate_index`` is used; default the one nearest the
        reference but not at its height) and the ``reference`` bundle.

    Returns
    -------
    dict of str to float
        Per camera with fringe images in both: the :data:`SENSITIVITY_PERCENTILE` percentile
        of |Δφ| / |Δz| over the pixels with fringes in both, rad/mm.

    Raises
    ------
    CalibrationError
        The plate lies at the reference's height, or its phase moved by more than
        :data:`SAFE_STEP_SHARE` π somewhere (too far for a wrapped difference to be trusted).
    """
    plate, reference = read_bundle(plate_path), read_bundle(reference_path)
    found: dict[str, float] = {}
    for camera_id in reference.rig.camera_ids:
        ref_frames, plate_frames = (_fringe_frames(reference, camera_id),
                                    _fringe_frames(plate, camera_id))
        if not ref_frames or not plate_frames:
            continue
        z_reference = reference.frame(ref_frames[0]).z_mm or 0.0
        if plate_index is None:
            # The nearest height that is not the reference's own (a stack may hold that too).
            away = [i for i in plate_frames
                    if abs((plate.frame(i).z_mm or 0.0) - z_reference) > 1e-6] or plate_frames
            index = min(away, key=lambda i: abs((plate.frame(i).z_mm or 0.0) - z_reference))
        else:
            index = plate_index
        dz = (plate.frame(index).z_mm or 0.0) - z_reference
        if abs(dz) < 1e-6:
            raise CalibrationError(f"{plate.path}: the plate is at the reference's height "
                                   f"({z_reference:+.2f} mm); its phase says nothing of height")
        ref_image = reference.load_image(ref_frames[0], camera_id)
        carrier = measure_carrier(ref_image)
        ref = demodulate(ref_image, carrier)
        moved = demodulate(plate.load_image(index, camera_id), carrier)
        valid = (_valid(ref.modulation) & _valid(moved.modulation)
                 & border_mask(ref_image.shape, math.ceil(carrier.period_px)))
        if not np.any(valid):
            raise CalibrationError(f"camera {camera_id}: no pixel with fringes in both the "
                                   "plate and the reference")
        change = np.abs(phase_difference(moved.surface_phase(), ref.surface_phase()))[valid]
        steepest = float(np.percentile(change, SENSITIVITY_PERCENTILE))
        if steepest > SAFE_STEP_SHARE * math.pi:
            raise CalibrationError(
                f"camera {camera_id}: the plate {dz:+.2f} mm from the reference moved the phase "
                f"by {steepest:.2f} rad, too near π to measure the sensitivity; put a probe "
                "plate nearer the reference (0.5 mm)")
        found[camera_id] = steepest / abs(dz)
    return found


def safe_step_mm(sensitivity_rad_per_mm: float) -> float:
    """The largest spacing of neighbouring planes (the reference among them) that keeps every
    step of the walk along Z under :data:`SAFE_STEP_SHARE` π, rounded down to 0.1 mm."""
    if not sensitivity_rad_per_mm > 0:
        raise ValueError(f"sensitivity_rad_per_mm must be positive, got {sensitivity_rad_per_mm}")
    return math.floor(10 * SAFE_STEP_SHARE * math.pi / sensitivity_rad_per_mm) / 10


def model_sensitivity(document: dict[str, Any]) -> dict[str, float]:
    """Each camera's fringe-phase sensitivity to height (rad/mm) from a calibration's own
    phase-to-height models (its ``phase_to_height`` section): the
    :data:`SENSITIVITY_PERCENTILE` percentile of |∂Δφ/∂Z| over the image (every 8th pixel) and
    the calibrated Z range. Empty without such a section."""
    section = document.get("phase_to_height") or {}
    found: dict[str, float] = {}
    for camera_id, entry in (section.get("cameras") or {}).items():
        cam = document["cameras"][camera_id]
        model = PhaseHeightModel.from_dict(entry["model"])
        x_grid, y_grid = pixel_grid_normalised(cam["width"], cam["height"], cam["K"],
                                               cam["dist"])
        xs, ys = x_grid[4::8, 4::8].ravel(), y_grid[4::8, 4::8].ravel()
        low, high = entry["z_range_mm"]
        slopes = []
        for z in np.linspace(low, high - 0.5, 8):
            slopes.append(np.abs(model.phase(xs, ys, np.full(xs.shape, z + 0.5))
                                 - model.phase(xs, ys, np.full(xs.shape, z))) / 0.5)
        every = np.concatenate(slopes)
        every = every[np.isfinite(every)]
        if every.size:
            found[camera_id] = float(np.percentile(every, SENSITIVITY_PERCENTILE))
    return found


def heights_needed(acquired_mm: list[float], z_range_mm: tuple[float, float],
                   max_step_mm: float) -> list[float]:
    """Plate heights (mm, ascending, to 0.01 mm) that, added to ``acquired_mm`` (the plates and
    the reference plane), cover ``z_range_mm`` with no two neighbouring planes more than
    ``max_step_mm`` apart: the largest gaps split evenly, the range's ends reached exactly.

    >>> heights_needed([10.0, 9.0], (5.0, 10.0), 2.0)
    [5.0, 7.0]
    """
    low, high = sorted(z_range_mm)
    if not max_step_mm > 0:
        raise ValueError(f"max_step_mm must be positive, got {max_step_mm}")
    have = sorted(set(acquired_mm))
    if not have:
        count = max(1, math.ceil((high - low) / max_step_mm - 1e-9))
        return [round(low + (high - low) * k / count, 2) for k in range(count + 1)]
    needed: list[float] = []
    ends = ([low] if have[0] > low else []) + have + ([high] if have[-1] < high else [])
    for a, b in itertools.pairwise(ends):
        count = math.ceil((b - a) / max_step_mm - 1e-9)
        needed += [round(a + (b - a) * k / count, 2) for k in range(1, count)]
    needed += ([low] if have[0] > low else []) + ([high] if have[-1] < high else [])
    return sorted(set(needed))


def calibrate_phase_height(document: dict[str, Any], plate_path: str | Path,
                           reference_path: str | Path, progress: Progress = quiet,
                           ) -> tuple[dict[str, Any], dict[str, npt.NDArray[np.float32]]]:
    """Fit every camera's phase-to-height model; returns the document's new section and arrays.

    ``document`` is a loaded stereo calibration (:func:`~eyeserver.calibration.artefact.
    load_calibration`). The arrays are each camera's reference phase (``reference_phase_<id>``),
    which measurements are taken relative to.
    """
    rig: RigSpec = rig_from_dict(document["rig"], "<calibration>")
    plate = read_bundle(plate_path)
    reference = read_bundle(reference_path)
    for bundle, kind in ((plate, "plate"), (reference, "reference")):
        if bundle.kind != kind:
            raise CalibrationError(f"{bundle.path}: expected a '{kind}' bundle, "
                                   f"not '{bundle.kind}'")
        if bundle.rig.to_dict() != rig.to_dict():
            raise CalibrationError(f"{bundle.path}: its rig is not the calibration's rig")
    section: dict[str, Any] = {"cameras": {}, "units": {}}
    arrays: dict[str, npt.NDArray[np.float32]] = {}
    models: dict[str, PhaseHeightModel] = {}
    for camera_id in rig.camera_ids:
        cam = document["cameras"][camera_id]
        ref_frames = _fringe_frames(reference, camera_id)
        if not ref_frames:
            raise CalibrationError(f"{reference.path}: camera {camera_id} has no fringe image "
                                   "(its unit's projector is not lit in any frame)")
        z_reference = reference.frame(ref_frames[0]).z_mm
        assert z_reference is not None
        ref_image = reference.load_image(ref_frames[0], camera_id)
        carrier = measure_carrier(ref_image)
        ref = demodulate(ref_image, carrier)
        ref_phase = ref.surface_phase()
        stack = sorted((plate.frame(i).z_mm or 0.0, i) for i in _fringe_frames(plate, camera_id))
        if len(stack) < 3:
            raise CalibrationError(f"{plate.path}: camera {camera_id} has fringe images at "
                                   f"{len(stack)} heights; the fit needs at least 3")
        progress(f"camera {camera_id}: demodulating {len(stack)} plate heights")
        z_values, wrapped, valid = [], [], []
        # The FTM corrupts about a fringe period at every image border (docs/design.md §4 step 1;
        # measured here: 3 % of samples off by 0.1–20 mm, nearly all within 70 px of an edge).
        ref_valid = _valid(ref.modulation) & border_mask(ref_image.shape,
                                                         math.ceil(carrier.period_px))
        for z, index in stack:
            result = demodulate(plate.load_image(index, camera_id), carrier)
            z_values.append(z)
            wrapped.append(phase_difference(result.surface_phase(), ref_phase))
            valid.append(_valid(result.modulation) & ref_valid)
        unwrapped, chain = _unwrap_along_z(z_values, wrapped, valid, z_reference)
        x_grid, y_grid = pixel_grid_normalised(cam["width"], cam["height"], cam["K"],
                                               cam["dist"])
        sub = (slice(SAMPLE_STRIDE // 2, None, SAMPLE_STRIDE),) * 2
        xs, ys, dphis, zs = [], [], [], []
        for z, dphi, ok in zip(z_values, unwrapped, chain, strict=True):
            keep = ok[sub]
            xs.append(x_grid[sub][keep])
            ys.append(y_grid[sub][keep])
            dphis.append(dphi[sub][keep])
            zs.append(np.full(int(keep.sum()), z))
        counts = [len(z) for z in zs]
        if min(counts) == 0:
            empty = [z for z, n in zip(z_values, counts, strict=True) if n == 0]
            raise CalibrationError(f"camera {camera_id}: no usable fringes at Z = {empty} mm "
                                   "(check that the plate fills the view and is lit)")
        progress(f"camera {camera_id}: fitting the phase-to-height model")
        x_all, y_all = np.concatenate(xs), np.concatenate(ys)
        dphi_all, z_all = np.concatenate(dphis), np.concatenate(zs)
        fit = fit_phase_height(x_all, y_all, dphi_all, z_all, rng=0)
        # Least squares is pulled by the few samples whose phase the FTM corrupted (plate and
        # image borders, specks of shadow): measured, they bend the whole model by up to
        # 0.1 mm. Refit on the inliers; the residuals are still reported on every sample.
        spread = 1.4826 * float(np.median(np.abs(fit.residual_mm)))
        inliers = np.abs(fit.residual_mm) < max(5 * spread, 0.02)
        refit = fit_phase_height(x_all[inliers], y_all[inliers], dphi_all[inliers],
                                 z_all[inliers], rng=0)
        residual_all = refit.model.height(x_all, y_all, dphi_all) - z_all
        fit = replace(refit, residual_mm=residual_all,
                      rmse_mm=float(np.sqrt(np.mean(residual_all**2))),
                      median_abs_mm=float(np.median(np.abs(residual_all))),
                      iqr_mm=float(np.subtract(*np.percentile(np.abs(residual_all), [75, 25]))))
        per_z = []
        offset = 0
        for z, n in zip(z_values, counts, strict=True):
            residual = fit.residual_mm[offset:offset + n]
            offset += n
            q1, median, q3 = np.percentile(np.abs(residual), [25, 50, 75])
            per_z.append({"z_mm": z, "median_abs_mm": float(median), "iqr_mm": float(q3 - q1),
                          "points": n})
        worst = max(per_z, key=lambda entry: entry["median_abs_mm"])
        if worst["median_abs_mm"] > SLIP_MM:
            raise CalibrationError(
                f"camera {camera_id}: the plane at Z = {worst['z_mm']:+.1f} mm is off by "
                f"{worst['median_abs_mm']:.1f} mm after the fit; the unwrapping along Z slipped "
                "by a fringe there (steps too coarse for this rig's sensitivity, or the plate "
                "was not where the bundle says)")
        models[camera_id] = fit.model
        section["cameras"][camera_id] = {
            "carrier_cycles_per_px": list(carrier.frequency),
            "model": fit.model.to_dict(),
            "reference_z_mm": z_reference,
            "z_range_mm": [z_values[0], z_values[-1]],
            "quality": {"median_abs_mm": fit.median_abs_mm, "iqr_mm": fit.iqr_mm,
                        "rmse_mm": fit.rmse_mm, "condition_number": fit.condition_number,
                        "per_z": per_z},
        }
        arrays[f"reference_phase_{camera_id}"] = np.asarray(ref_phase, np.float32)
    for unit in rig.units:
        if len(unit.cameras) < 2:
            section["units"][unit.id] = {"margin_rad": None, "orders_checked": 0,
                                         "note": "one camera: no multi-view fringe order"}
            continue
        a, b = unit.cameras[0], unit.cameras[1]
        z_range = tuple(section["cameras"][a]["z_range_mm"])
        margin: dict[str, Any] = {
            **fringe_order_margin(models[a], models[b], document["cameras"][a],
                                  document["cameras"][b], (z_range[0], z_range[1])),
            "cameras": [a, b]}
        if margin["margin_rad"] < MARGIN_WARNING_RAD:
            margin["note"] = (
                f"too blind for the multi-view fringe order: a wrong order comes within "
                f"{margin['margin_rad']:.2f} rad (< {MARGIN_WARNING_RAD} rad); move one camera "
                "to another azimuth")
        section["units"][unit.id] = margin
    return section, arrays


def add_phase_height(calibration: str | Path, plate_path: str | Path,
                     reference_path: str | Path, progress: Progress = quiet,
                     ) -> dict[str, Any]:
    """Calibrate phase to height and add it, with its inputs' hashes, to the stereo calibration
    directory ``calibration`` (rewritten atomically); returns the new section."""
    from eyeserver.calibration.artefact import load_calibration, write_calibration
    from eyeserver.io import bundle_hash

    document = load_calibration(calibration)
    arrays = document.pop("arrays")
    section, new_arrays = calibrate_phase_height(document, plate_path, reference_path,
                                                 progress=progress)
    document["phase_to_height"] = section
    document["inputs"]["phase_to_height"] = [
        {"bundle": Path(p).name, "sha256": bundle_hash(p)} for p in (plate_path, reference_path)]
    write_calibration(calibration, document, {**arrays, **new_arrays}, overwrite=True)
    return section
