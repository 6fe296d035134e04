"""The daily QA's figures: the QA phantom's captures measured against its drawing.

The QA phantom is eye phantom 1 of the paper's set (docs/design.md §3): a white ball of 12 mm
radius with a painted iris, on a flat base plate, with 16 dark fiducial dots on the ball and 4 on
the plate. Its geometry here is its *drawing* (:data:`EYE_PHANTOM_1`), the nominal design a
physicist has on paper for a real phantom, placed at its QA position in the room; it is never
the simulator's truth, which the measurement path does not see (import-linter checks it).

From ``frames`` captures of every unit of the still phantom, with the active calibration
(:func:`measure_phantom`):

``localisation_mm``
    How far the drawing, rigidly fitted to the dots found in the images and triangulated by
    each unit's two cameras, moves the ball's centre from its QA position: the system's static
    localisation of a known object, the figure AAPM TG-302 asks of SGRT systems daily (≤ 1 mm
    there, as issue 40 quotes it).
``surface_mm``
    Median |distance| of the measured points to the drawing's surfaces (ball and base plate)
    placed where the dots put the phantom: the shape the system measures, apart from where the
    phantom stands.
``fiducial_mm``
    Median distance between the triangulated dots (stereo calibration only, no fringe
    analysis) and the drawing's dots so placed: an independent check of the geometric
    calibration.
``cross_unit_mm``
    Median |point-to-surface distance| between the two units' clouds where both see the
    phantom: the seam agreement.
``static_noise_mm``
    Per pixel the standard deviation of its height over the frames, median per camera, the
    worst camera: the frame-to-frame repeatability of a still surface.
``drift_vectors_mm``
    Each unit's mean miss of its dots against the phantom placed by all units (one unit: its
    ball centre), from which :func:`calibration_drift_mm` compares the active calibration with
    its QA baseline.

Everything here is pure over stored bundles and a calibration directory; it runs on the
daemon's reconstruction worker.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from eyeserver.calibration.artefact import load_calibration
from eyeserver.core.types import F64
from eyeserver.io import read_bundle
from eyeserver.pipeline.fiducials import detect_fiducials, match_stereo, triangulate
from eyeserver.pipeline.reconstruct import unit_clouds
from eyeserver.reconstruction import calibrated_cameras, unit_pairs, z_range

__all__ = ["EYE_PHANTOM_1", "FIGURES", "PhantomDrawing", "QaMeasurement",
           "calibration_drift_mm", "measure_phantom", "rigid_fit"]


def _ring(radius_mm: float, polar_deg: float, count: int, phase_deg: float,
          centre: tuple[float, float, float]) -> list[tuple[float, float, float]]:
    """``count`` points on a sphere at ``polar_deg`` from +Z, evenly in azimuth from
    ``phase_deg`` (the drawing's dimensioning of a ring of dots)."""
    polar = math.radians(polar_deg)
    return [(centre[0] + radius_mm * math.sin(polar) * math.cos(az),
             centre[1] + radius_mm * math.sin(polar) * math.sin(az),
             centre[2] + radius_mm * math.cos(polar))
            for az in (math.radians(phase_deg + 360.0 * k / count) for k in range(count))]


@dataclass(frozen=True)
class PhantomDrawing:
    """A QA phantom's nominal geometry at its QA position, in the WCS (mm).

    Attributes
    ----------
    name : str
        What the phantom is, for the report.
    centre_mm : tuple of float
        The ball's centre at the QA position.
    radius_mm : float
        The ball's radius.
    base_z_mm : float
        Z of the base plate's face (a plane normal to Z), mm.
    base_half_size_mm : tuple of float
        Half the plate's width (X) and height (Y), mm.
    fiducials_mm : tuple of tuple of float
        The dots' centres at the QA position.
    """

    name: str
    centre_mm: tuple[float, float, float]
    radius_mm: float
    base_z_mm: float
    base_half_size_mm: tuple[float, float]
    fiducials_mm: tuple[tuple[float, float, float], ...]

    def distance(self, points: F64, offset_mm: F64 | None = None) -> F64:
        """|distance| of ``points`` (N × 3) to the phantom's surfaces, the phantom moved by
        ``offset_mm``: the ball, or the base plate's face where a point lies over the plate
        and outside the ball."""
        shift = np.zeros(3) if offset_mm is None else np.asarray(offset_mm, dtype=np.float64)
        centre = np.asarray(self.centre_mm) + shift
        ball = np.abs(np.linalg.norm(points - centre, axis=1) - self.radius_mm)
        rel = points[:, :2] - centre[:2]
        on_plate = (np.abs(rel[:, 0]) <= self.base_half_size_mm[0]) & \
            (np.abs(rel[:, 1]) <= self.base_half_size_mm[1])
        plate = np.where(on_plate, np.abs(points[:, 2] - (self.base_z_mm + shift[2])), np.inf)
        return np.asarray(np.minimum(ball, plate), dtype=np.float64)

    def placed(self, centre_mm: tuple[float, float, float]) -> PhantomDrawing:
        """The same phantom with its ball's centre at ``centre_mm`` (a translation)."""
        dx, dy, dz = (float(c - o) for c, o in zip(centre_mm, self.centre_mm, strict=True))
        return replace(self, centre_mm=centre_mm, base_z_mm=self.base_z_mm + dz,
                       fiducials_mm=tuple((x + dx, y + dy, z + dz)
                                          for x, y, z in self.fiducials_mm))


# The drawing of eye phantom 1 (docs/qa.md): ball Ø 24 mm, dots Ø 1 mm in two rings of 8 at
# 42° and 60° from the ball's axis (the first at 22.5° azimuth), 4 dots on the plate at
# (±22, ±18) mm; the plate's face through the ball's centre, 60 × 50 mm. QA position: the
# ball's centre on the isocentre, axis along +Z, so that plate and ball lie mid-volume (at
# Z = −10, where the eye's centre sits, the plate would lie on the calibrated range's edge).
_QA_CENTRE = (0.0, 0.0, 0.0)
EYE_PHANTOM_1 = PhantomDrawing(
    name="eye phantom 1 (12 mm ball, painted iris, 20 fiducial dots) at its QA position",
    centre_mm=_QA_CENTRE, radius_mm=12.0, base_z_mm=_QA_CENTRE[2],
    base_half_size_mm=(30.0, 25.0),
    fiducials_mm=tuple(_ring(12.0, 42.0, 8, 22.5, _QA_CENTRE) + _ring(12.0, 60.0, 8, 22.5,
                                                                     _QA_CENTRE)
                       + [(x, y, _QA_CENTRE[2]) for x in (-22.0, 22.0) for y in (-18.0, 18.0)]))
"""The QA phantom's drawing: the reference geometry the daily QA measures against."""


FIGURES: dict[str, str] = {
    "localisation_mm": "ball centre found − drawing's QA position, mm",
    "surface_mm": "median |distance| to the drawing's surfaces where the ball was found, mm",
    "fiducial_mm": "median |triangulated dot − drawing's dot|, mm",
    "cross_unit_mm": "median |distance| between the units' surfaces where both see it, mm",
    "static_noise_mm": "frame-to-frame height spread (std) of the still phantom, worst "
                       "camera's median, mm",
    "drift_mm": "change of the units' relative geometry since the calibration's QA baseline, mm",
}
"""Every figure the daily QA judges, with what it is (each has a threshold in the settings)."""

FIDUCIAL_GATE_MM = 2.0
"""A triangulated dot farther than this from every dot of the drawing (at the position found)
is not the phantom's (a dark speck, the iris' edge) and is left out; the dots are ≥ 6 mm
apart."""
BALL_MARGIN_MM = 2.0
"""Points closer than this to the base plate's face are not counted as the ball's (the
details' ball-only figure)."""
SHARED_RADIUS_MM = 0.6
"""The shared region: a point of one unit with at least :data:`SHARED_NEIGHBOURS` points of the
other within this radius, through which the other's local surface is fitted."""
SHARED_NEIGHBOURS = 8
CROSS_SAMPLE = 4000
"""Points of each unit compared with the other (a random subset: plenty for a median)."""


def rigid_fit(source: F64, target: F64) -> tuple[F64, F64]:
    """The rotation ``R`` and translation ``t`` that best map ``source`` onto ``target`` (both
    N × 3, N ≥ 3 not on a line) in least squares, ``target ≈ source @ R.T + t`` (Kabsch's
    method, the reflection excluded).

    Raises
    ------
    ValueError
        Fewer than 3 points, or points on a line (the rotation about it is unknown).
    """
    if len(source) < 3 or len(source) != len(target):
        raise ValueError(f"a rigid fit needs at least 3 paired points, got {len(source)}")
    mean_s, mean_t = source.mean(axis=0), target.mean(axis=0)
    u, singular, vt = np.linalg.svd((source - mean_s).T @ (target - mean_t))
    if singular[1] < 1e-6 * max(singular[0], 1e-12):
        raise ValueError("the points lie on a line: no rotation about it can be found")
    sign = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    rotation = vt.T @ np.diag([1.0, 1.0, sign]) @ u.T
    return rotation, mean_t - rotation @ mean_s


def _matched(found: F64, expected: F64) -> tuple[F64, npt.NDArray[np.intp]]:
    """The dots of the drawing that ``found`` (triangulated in one or more frames) has within
    :data:`FIDUCIAL_GATE_MM`: each one's mean position over the frames, and its index in the
    drawing. (The drawing's dots are ≥ 6 mm apart: whatever lies within the gate of one is that
    dot, seen again.)"""
    if not len(found):
        return np.zeros((0, 3)), np.zeros(0, np.intp)
    gaps, nearest = cKDTree(expected).query(found)
    near = gaps <= FIDUCIAL_GATE_MM
    order = np.unique(nearest[near])
    means = np.asarray([found[near & (nearest == index)].mean(axis=0) for index in order])
    return means.reshape(-1, 3), order.astype(np.intp)


def _cross_unit(first: F64, second: F64, rng: np.random.Generator) -> tuple[F64, int]:
    """Signed point-to-surface distances of a subset of ``first`` to the surface of ``second``
    fitted (a plane through its neighbours) in the shared region, and the points compared."""
    if len(first) == 0 or len(second) < SHARED_NEIGHBOURS:
        return np.zeros(0), 0
    chosen = first if len(first) <= CROSS_SAMPLE else \
        first[rng.choice(len(first), CROSS_SAMPLE, replace=False)]
    tree = cKDTree(second)
    distances, index = tree.query(chosen, k=SHARED_NEIGHBOURS,
                                  distance_upper_bound=SHARED_RADIUS_MM)
    shared = np.all(np.isfinite(distances), axis=1)
    if not shared.any():
        return np.zeros(0), 0
    neighbours = second[index[shared]]  # (M, k, 3)
    centroid = neighbours.mean(axis=1)
    spread = neighbours - centroid[:, None, :]
    covariance = np.einsum("mki,mkj->mij", spread, spread)
    _, vectors = np.linalg.eigh(covariance)
    normal = vectors[:, :, 0]  # the smallest eigenvalue's vector: the local plane's normal
    signed = np.einsum("mi,mi->m", chosen[shared] - centroid, normal)
    return signed, int(shared.sum())


@dataclass
class QaMeasurement:
    """What :func:`measure_phantom` found (figures None where they could not be measured,
    with the reason in ``problems``)."""

    figures: dict[str, float | None]
    details: dict[str, Any] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)
    unit_centres_mm: dict[str, list[float]] = field(default_factory=dict)
    unit_offsets_mm: dict[str, list[float]] = field(default_factory=dict)

    @property
    def drift_vectors_mm(self) -> dict[str, list[float]]:
        """What :func:`calibration_drift_mm` compares with a baseline: with two units or more,
        each unit's mean miss of its dots against the phantom placed by all units (blind to
        the placement, no lever arm to the ball's centre); with one, its ball centre."""
        return self.unit_offsets_mm if len(self.unit_offsets_mm) >= 2 else self.unit_centres_mm


@dataclass
class _Views:
    """What the captures gave: depth per camera and frame, points and dots per unit."""

    depth: dict[str, list[F64]] = field(default_factory=dict)
    points: dict[str, list[F64]] = field(default_factory=dict)
    dots: dict[str, list[F64]] = field(default_factory=dict)


def _reconstruct(calibration: str | Path, bundles: Sequence[str | Path]) -> _Views:
    """Every unit's two cameras of every bundle reconstructed, and the dots found and
    triangulated by each unit's camera pair in every bundle."""
    views = _Views()
    document: dict[str, Any] | None = None
    for number, path in enumerate(bundles):
        bundle = read_bundle(path)
        if document is None:
            document = load_calibration(calibration, bundle.rig)
        cameras = calibrated_cameras(document)
        heights = z_range(document)
        for index, id_a, id_b in unit_pairs(bundle):
            a, b = cameras[id_a], cameras[id_b]
            image_a, image_b = bundle.load_image(index, id_a), bundle.load_image(index, id_b)
            clouds = unit_clouds(a, image_a, b, image_b, heights)
            unit = bundle.rig.unit_of_camera(id_a).id
            for cam, cloud in zip((a, b), clouds, strict=True):
                views.depth.setdefault(cam.camera_id, []).append(cloud.depth_image(cam.shape))
                if number == 0:
                    views.points.setdefault(unit, []).append(cloud.points)
            found = (detect_fiducials(image_a, a.carrier.period_px),
                     detect_fiducials(image_b, b.carrier.period_px))
            pairs = match_stereo(found[0], found[1], a.K, a.dist, a.R, a.T, b.K, b.dist, b.R, b.T)
            if len(pairs):
                views.dots.setdefault(unit, []).append(triangulate(
                    found[0][pairs[:, 0]], found[1][pairs[:, 1]], a.K, a.dist, a.R, a.T,
                    b.K, b.dist, b.R, b.T))
    return views


def measure_phantom(calibration: str | Path, bundles: Sequence[str | Path],
                    drawing: PhantomDrawing = EYE_PHANTOM_1) -> QaMeasurement:
    """Measure the QA phantom in ``bundles`` (captures of every unit of the still phantom, at
    least 2 for the static noise) with the calibration directory ``calibration``.

    The phantom is located by its dots: those triangulated by each unit's camera pair within
    :data:`FIDUCIAL_GATE_MM` of the drawing's, rigidly fitted to them (at least 3 distinct
    dots). That fit places the drawing where the phantom stands, for the surface figure, and
    moves the ball's centre by ``localisation_mm``. (The dots, not the ball's surface: the
    fringe reconstruction keeps less of the steep, partly dark ball than of the plate, and a
    sphere fitted to a cap is biased by what is missing.)

    Returns the figures of the module docstring (``drift_mm`` is left to
    :func:`calibration_drift_mm`, against a baseline), their details and what could not be
    measured.

    Raises
    ------
    ValueError
        No bundle was given.
    FormatError, ReconstructionError
        A bundle or the calibration cannot be read or used.
    """
    if not bundles:
        raise ValueError("measure_phantom needs at least one bundle")
    views = _reconstruct(calibration, bundles)
    result = QaMeasurement(figures=dict.fromkeys(
        ("localisation_mm", "surface_mm", "fiducial_mm", "cross_unit_mm", "static_noise_mm")))
    points_by_unit = {u: np.concatenate(p) for u, p in views.points.items()}
    every = np.concatenate(list(points_by_unit.values())) if points_by_unit else np.zeros((0, 3))
    result.details["points"] = {u: len(p) for u, p in points_by_unit.items()}
    expected = np.asarray(drawing.fiducials_mm, dtype=np.float64)
    centre = np.asarray(drawing.centre_mm, dtype=np.float64)

    # The dots: where the phantom stands (all units), and each unit's own view of it.
    matched = {u: _matched(np.concatenate(d), expected) for u, d in views.dots.items()}
    measured = np.concatenate([m for m, _ in matched.values()]) if matched else np.zeros((0, 3))
    indices = np.concatenate([i for _, i in matched.values()]) if matched \
        else np.zeros(0, np.intp)
    result.details["fiducials"] = {
        "triangulated": {u: sum(len(x) for x in d) for u, d in views.dots.items()},
        "matched": {u: len(i) for u, (_, i) in matched.items()},
        "drawing_dots": len(expected), "gate_mm": FIDUCIAL_GATE_MM}
    placement: tuple[F64, F64] | None = None
    if len(set(indices.tolist())) >= 3:
        try:
            placement = rigid_fit(expected[indices], measured)
        except ValueError as exc:
            result.problems.append(f"the dots found do not place the phantom: {exc}")
    else:
        result.problems.append(
            f"fewer than 3 of the drawing's dots were found within {FIDUCIAL_GATE_MM} mm of "
            "their QA position (is the QA phantom in place?)")
    if placement is not None:
        rotation, shift = placement
        residuals = np.linalg.norm(measured - (expected[indices] @ rotation.T + shift), axis=1)
        found_centre = rotation @ centre + shift
        angle = math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(rotation) - 1) / 2))))
        result.figures["fiducial_mm"] = float(np.median(residuals))
        result.figures["localisation_mm"] = float(np.linalg.norm(found_centre - centre))
        result.details["fiducials"]["residuals_mm"] = residuals.tolist()
        result.details["placement"] = {"centre_mm": found_centre.tolist(),
                                       "offset_mm": (found_centre - centre).tolist(),
                                       "rotation_deg": angle}
        for unit, (unit_dots, unit_indices) in matched.items():
            if len(unit_indices):
                misses = unit_dots - (expected[unit_indices] @ rotation.T + shift)
                result.unit_offsets_mm[unit] = misses.mean(axis=0).tolist()
    for unit, (unit_dots, unit_indices) in matched.items():
        if len(unit_indices) >= 3:
            try:
                unit_rotation, unit_shift = rigid_fit(expected[unit_indices], unit_dots)
            except ValueError:
                continue
            result.unit_centres_mm[unit] = (unit_rotation @ centre + unit_shift).tolist()
    result.details["unit_centres_mm"] = result.unit_centres_mm
    result.details["unit_offsets_mm"] = result.unit_offsets_mm

    # The shape, the drawing placed where the phantom stands.
    if len(every) and placement is not None:
        rotation, shift = placement
        local = (every - shift) @ rotation  # into the drawing's frame: Rᵀ(p − t)
        distance = drawing.distance(local)
        on_ball = np.abs(np.linalg.norm(local - centre, axis=1) - drawing.radius_mm) <= 1.0
        on_ball &= local[:, 2] > drawing.base_z_mm + BALL_MARGIN_MM
        result.figures["surface_mm"] = float(np.median(distance))
        result.details["surface"] = {
            "points": len(every), "p95_mm": float(np.percentile(distance, 95)),
            "beyond_0_5mm": float(np.mean(distance > 0.5)), "ball_points": int(on_ball.sum()),
            "ball_median_mm": float(np.median(distance[on_ball])) if on_ball.any() else None}

    # The seam: each unit's points against the other's surface, both ways.
    units = sorted(points_by_unit)
    if len(units) >= 2:
        rng = np.random.default_rng(0)
        first, second = points_by_unit[units[0]], points_by_unit[units[1]]
        forth, n_forth = _cross_unit(first, second, rng)
        back, n_back = _cross_unit(second, first, rng)
        both = np.concatenate([forth, back])
        result.details["cross_unit"] = {"units": units[:2], "points": n_forth + n_back,
                                        "median_signed_mm": float(np.median(forth))
                                        if len(forth) else None}
        if len(both) >= 100:
            result.figures["cross_unit_mm"] = float(np.median(np.abs(both)))
        else:
            result.problems.append("the units share too little of the phantom to compare "
                                   f"({len(both)} points)")
    else:
        result.problems.append("one unit only: no cross-unit agreement to measure")

    # Repeatability: per pixel over the frames, per camera.
    spreads: dict[str, float | None] = {}
    for camera_id, images in views.depth.items():
        if len(images) < 2:
            continue
        stack = np.stack(images)
        everywhere = np.all(np.isfinite(stack), axis=0)
        spreads[camera_id] = float(np.median(np.std(stack[:, everywhere], axis=0, ddof=1))) \
            if everywhere.sum() >= 100 else None
    result.details["static_noise"] = {"frames": len(bundles), "per_camera_mm": spreads}
    measured_spreads = [s for s in spreads.values() if s is not None]
    if measured_spreads:
        result.figures["static_noise_mm"] = max(measured_spreads)
    else:
        result.problems.append("static noise needs at least 2 frames of the phantom")
    return result


def calibration_drift_mm(vectors_mm: Mapping[str, Sequence[float]],
                         baseline_mm: Mapping[str, Sequence[float]]) -> float | None:
    """How much the units' view of the phantom changed since the baseline, from each unit's
    :attr:`QaMeasurement.drift_vectors_mm` now and then.

    With two or more units: the largest change of a unit's vector *relative to the first
    unit's* (``|(v_u − v_0) − (b_u − b_0)|``), which is blind to where the phantom was put (a
    real phantom is never re-placed to 0.05 mm) and sees any unit moving against the others.
    With one unit: the change of its vector itself, placement included. None when a unit of the
    baseline gave nothing now.
    """
    units = sorted(baseline_mm)
    if not units or any(u not in vectors_mm for u in units):
        return None
    now = {u: np.asarray(vectors_mm[u], dtype=np.float64) for u in units}
    then = {u: np.asarray(baseline_mm[u], dtype=np.float64) for u in units}
    if len(units) == 1:
        return float(np.linalg.norm(now[units[0]] - then[units[0]]))
    first = units[0]
    return max(float(np.linalg.norm((now[u] - now[first]) - (then[u] - then[first])))
               for u in units[1:])
