"""``eyeserver bench pose``: eye pose accuracy on random simulated eyes (issues 7 and 34).

Each pose's eye is a patient's (``--eyes patient``, the default: every property drawn per eye
from its population range, :func:`eyeserver.hardware.sim.population.draw`; docs/eye-model.md)
or the old painted eye (``--eyes sharp``: a sharp limbus and the fit's own anatomy, globes of
12, 11 and 13 mm in turn, drawn exactly as before issue 34 so that the old figures reproduce).
The bench places it within ±5 mm of the default position and ±10° of gaze, renders it in the
simulated room, reconstructs it and fits it with the population model (radius fitted) or, with
``--biometry``, with what the patient's MRI and biometry give, each off by its typical error
(:func:`eyeserver.hardware.sim.population.biometry`, entered as the daemon takes a physicist's
entry: :class:`~eyeserver.service.patients.EyeModelSpec`; never the truth). The fitted globe
centre and gaze are compared with the scene's truth, overall and per bin of what makes a limbus
hard to find (:data:`BINS`); beside them how well the poses' stated uncertainties cover their
errors and how often a wrong pose wears a confident face (:func:`confident_wrong`: off by more
than the clinic's tolerance while the daemon's check against a planned pose lets it through:
its confidence passes the default ``min_confidence``, the eye model leaves little of the
globe's shape unknown and the pose's own stated sd is within the tolerance). A fit that raises
is a refusal, not a wrong pose. A 1 mm shift between two captures of the same eye must be
measured as ≈ 1 mm (a clear fail of the 0.2 mm clinical tolerance). Ground truth is only read
here, after the fit.
"""

from __future__ import annotations

import json
import math
import re
import shutil
import tempfile
import time
from collections import Counter
from collections.abc import Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import numpy as np

from eyeserver.bench.machine import machine
from eyeserver.bench.report import (
    DESCRIPTORS,
    by_globe_text,
    confident_wrong_text,
    displacement_text,
    eyes_text,
    number_text,
    p95_text,
    refusals_text,
    separation_text,
    uncertainty_coverage,
)
from eyeserver.bench.simcal import calibrate_room
from eyeserver.core.memory import keep_freed_memory
from eyeserver.core.types import Progress, quiet
from eyeserver.errors import EyeserverError
from eyeserver.eye import EyeModel, EyePose, fit_eye
from eyeserver.hardware.sim import population
from eyeserver.hardware.sim.config import RoomConfig
from eyeserver.hardware.sim.scenes import EyeSpec, SceneSpec
from eyeserver.hardware.sim.sessions import SimSession
from eyeserver.reconstruction import limbus_views, reconstruct_bundle
from eyeserver.service.patients import (
    DEFAULT_MIN_CONFIDENCE,
    DEFAULT_TOLERANCE_MM,
    EllipsoidSpec,
    EyeModelSpec,
    Tolerances,
)
from eyeserver.service.verification import (
    combined_sd_mm,
    gaze_angle_deg,
    measurement_reason,
    shape_reason,
    turned_shape_sd_mm,
)

FORMAT = "eyeserver.bench.pose/2"
GOALS = {"centre_mm": 0.1, "gaze_deg": 0.5, "surface_mad_mm": 0.10, "paper_surface_mad_mm": 0.43,
         "within_2_sd": 0.95, "confident_wrong": 0}
EYES = ("patient", "sharp")
"""The eyes the bench draws (``--eyes``; :func:`eyeserver.hardware.sim.population.draw`)."""
RADII_MM = (12.0, 11.0, 13.0)
"""The sharp eye's globe radii, in turn (as the bench drew them before issue 34)."""
SHIFT_MM = 1.0
TOLERANCE_MM = DEFAULT_TOLERANCE_MM
"""The clinic's tolerance on the globe centre: a pose off by more is wrong."""
GOOD_MM = GOALS["centre_mm"]
"""A pose within this of the truth is good: refusing it costs the patient a beam hold for
nothing."""


def _placed(rng: np.random.Generator, eye: EyeSpec) -> SceneSpec:
    """``eye`` within ±5 mm of the default position and ±10° of gaze (position first, then
    gaze: the draws of the bench before issue 34)."""
    position = np.array([0.0, 0.0, -10.0]) + rng.uniform(-5.0, 5.0, 3)
    gaze = rng.uniform(-10.0, 10.0, 2)
    return SceneSpec(kind="eye", position_mm=tuple(float(v) for v in position),
                     eye=eye.model_copy(update={"gaze_deg": (float(gaze[0]), float(gaze[1]))}))


def random_spec(rng: np.random.Generator, radius: float) -> SceneSpec:
    """The sharp eye with a globe of ``radius`` within ±5 mm of the default position and ±10°
    of gaze."""
    return _placed(rng, EyeSpec(globe_radius_mm=radius))


MOVE_MM = 1.0
"""Largest move of the eye per axis between a reference capture and a measurement
(``--displacement``): set-up errors that a verification must catch are of this order."""

MOVE_DEG = 2.0
"""Largest turn of the gaze per axis between them (a patient fixating the light again)."""


def moved(rng: np.random.Generator, spec: SceneSpec) -> SceneSpec:
    """``spec``'s eye moved by up to :data:`MOVE_MM` per axis and turned by up to
    :data:`MOVE_DEG` in yaw and pitch: the same eye, captured again."""
    shift = rng.uniform(-MOVE_MM, MOVE_MM, 3)
    turn = rng.uniform(-MOVE_DEG, MOVE_DEG, 2)
    yaw, pitch = spec.eye.gaze_deg
    return spec.model_copy(update={
        "position_mm": tuple(float(p + d) for p, d in zip(spec.position, shift, strict=True)),
        "eye": spec.eye.model_copy(update={"gaze_deg": (yaw + float(turn[0]),
                                                        pitch + float(turn[1]))})})


def displacement_error(first: EyePose, second: EyePose, first_truth: dict[str, Any],
                       second_truth: dict[str, Any]) -> dict[str, Any]:
    """How well two fits of one eye measure its move between them: the centre's
    ``(C₂ − C₁) − (T₂ − T₁)`` (mm) and the gaze's turn ``(g₂ − g₁) − (t₂ − t₁)`` (degrees, as
    an angle for small turns), against the truth; ``passes`` as the daemon's check against a
    reference captured with the same model (:func:`passes` with the shape's share of the turn,
    :func:`~eyeserver.service.verification.turned_shape_sd_mm`; whatever the first capture's
    confidence, though the daemon refuses a reference below ``min_confidence``). Beside them
    both captures' confidences and the move's own stated sd per axis (mm: the two poses'
    :attr:`~eyeserver.eye.fit.EyePose.centre_sd_mm` together, the shape's left out), which
    the check weighs as :func:`~eyeserver.service.verification.measured_sd_mm` does
    (:func:`~eyeserver.service.verification.combined_sd_mm`)."""
    moved_by = np.subtract(second.centre_mm, first.centre_mm)
    true_move = np.subtract(second_truth["centre_mm"], first_truth["centre_mm"])
    turn = np.subtract(second.gaze, first.gaze)
    true_turn = np.subtract(second_truth["gaze"], first_truth["gaze"])
    error = float(np.linalg.norm(moved_by - true_move))
    shape = turned_shape_sd_mm(second.shape_sd_mm, second.gaze, first.gaze)
    move_sd = list(combined_sd_mm(first.centre_sd_mm, second.centre_sd_mm))
    return {"error_mm": error,
            "gaze_turn_error_deg": math.degrees(float(np.linalg.norm(turn - true_turn))),
            "true_move_mm": float(np.linalg.norm(true_move)),
            "confidences": [first.confidence, second.confidence],
            "move_sd_mm": move_sd,
            "confident_wrong": confident_wrong(error, second.confidence, shape_sd_mm=shape,
                                               measured_sd_mm=move_sd)}


@dataclass
class Streams:
    """The bench's random streams, each its own so that one choice leaves the others' draws
    alone: ``poses`` the positions and gazes (seeded as before issue 34: the sharp eye's
    scenes are the old ones), ``eyes`` the population's eyes, ``errors`` the biometry's
    measurement errors (with and without ``--biometry`` the same eyes at the same poses)."""

    poses: np.random.Generator
    eyes: np.random.Generator
    errors: np.random.Generator
    moves: np.random.Generator
    """The eye's move between a reference capture and a measurement (``--displacement``)."""

    @classmethod
    def from_seed(cls, seed: int) -> Streams:
        """The streams of ``seed`` (deterministic; a SeedSequence's children do not depend on
        how many are spawned, so adding one left the others' draws alone)."""
        eyes, errors, moves = np.random.SeedSequence(seed).spawn(3)
        return cls(np.random.default_rng(seed), np.random.default_rng(eyes),
                   np.random.default_rng(errors), np.random.default_rng(moves))


def draw_spec(streams: Streams, eyes: str, n: int) -> SceneSpec:
    """The ``n``-th pose's scene: the sharp eye with the ``n``-th of :data:`RADII_MM`, or a
    patient's eye from the population; either placed by :func:`_placed`.

    Raises
    ------
    ValueError
        ``eyes`` not one of :data:`EYES`.
    """
    if eyes == "sharp":
        return random_spec(streams.poses, RADII_MM[n % len(RADII_MM)])
    if eyes not in EYES:
        raise ValueError(f"eyes must be one of {', '.join(EYES)}, not {eyes!r}")
    return _placed(streams.poses, population.draw(streams.eyes, eyes))


def biometry_model(biometry: Mapping[str, Any]) -> EyeModel:
    """The patient's model from a biometry (:func:`eyeserver.hardware.sim.population.biometry`)
    as a physicist enters it and the daemon takes it (:class:`EyeModelSpec`): the MRI's
    ellipsoid where it gives semi-axes, its orientation the entry's default (the eye's axes at
    rest: the eye under the beam looks up to 14° away from them), else the sphere of its
    radius; the keratometer's cornea and the white-to-white limbus diameter."""
    semi_axes = biometry.get("globe_semi_axes_mm")
    if semi_axes is not None:
        spec = EyeModelSpec(ellipsoid=EllipsoidSpec(semi_axes_mm=tuple(semi_axes)),
                            cornea_radius_mm=biometry["cornea_radius_mm"],
                            limbus_diameter_mm=biometry["limbus_diameter_mm"])
    else:
        spec = EyeModelSpec(globe_radius_mm=biometry["globe_radius_mm"],
                            cornea_radius_mm=biometry["cornea_radius_mm"],
                            limbus_diameter_mm=biometry["limbus_diameter_mm"])
    return spec.to_eye_model()


def _measure(session: SimSession, spec: SceneSpec, caldir: Path, bundle: Path,
             units: list[str] | None, model: EyeModel,
             ) -> tuple[EyePose | None, dict[str, Any], float, str | None]:
    """Render, reconstruct and fit one pose: the pose (None refused, with why), the truth and
    the fit's seconds. The reconstruction's refusals count as the fit's: either way the
    daemon gives no pose."""
    session.record(spec, bundle, units=units, overwrite=True)
    truth = json.loads((bundle / "truth.json").read_text())["eye"]
    try:
        cloud, _ = reconstruct_bundle(caldir, bundle)
        views = limbus_views(caldir, bundle)
        started = time.perf_counter()
        pose = fit_eye(cloud, model, views)
    except EyeserverError as exc:
        return None, truth, 0.0, f"{type(exc).__name__}: {exc}"
    return pose, truth, time.perf_counter() - started, None


BOOTSTRAP_RESAMPLES = 4000
"""Resamples behind a p95's interval (:func:`p95_interval`)."""


def p95_interval(values: Any, level: float = 0.95) -> tuple[float, float] | None:
    """A percentile-bootstrap ``level`` interval of the 95th percentile of ``values``: how far
    the p95 of another draw of as many poses may lie (with 66 poses of one globe size it rests
    on the three or four largest errors). Deterministic (a fixed generator), None for fewer
    than two values. The percentile bootstrap of a tail quantile is rough (it cannot reach
    beyond the largest value seen), so it is read as a scale of the draw's luck, not as exact
    coverage."""
    arr = np.asarray(values, dtype=np.float64)
    if len(arr) < 2:
        return None
    draws = np.random.default_rng(0).integers(0, len(arr), (BOOTSTRAP_RESAMPLES, len(arr)))
    p95s = np.percentile(arr[draws], 95, axis=1)
    tail = 50.0 * (1.0 - level)
    low, high = np.percentile(p95s, [tail, 100.0 - tail])
    return float(low), float(high)


def _stats(values: list[float], interval: bool = False) -> dict[str, Any]:
    """Median, p95 and max of ``values`` (None each when empty); with ``interval``, the p95's
    bootstrap interval too (``p95_interval``: ``[low, high]`` or None)."""
    arr = np.asarray(values, dtype=np.float64)
    stats: dict[str, Any] = {"median": None, "p95": None, "max": None}
    if len(arr):
        stats = {"median": float(np.median(arr)), "p95": float(np.percentile(arr, 95)),
                 "max": float(arr.max())}
    if interval:
        bounds = p95_interval(arr)
        stats["p95_interval"] = None if bounds is None else list(bounds)
    return stats


EXACT = (0.0, 0.0, 0.0)
"""A measured sd per axis of nothing (mm): a made-up row's, or an old run's without it."""


def passes(confidence: float, shape_sd_mm: float = 0.0,
           min_confidence: float = DEFAULT_MIN_CONFIDENCE,
           measured_sd_mm: Sequence[float] = EXACT) -> bool:
    """Whether the daemon's check of a pose against a planned (absolute) pose lets it through:
    its confidence passes ``min_confidence`` (``confidence >= min_confidence``; default the
    daemon's), and neither what the eye model leaves unknown of the globe's shape
    (:attr:`~eyeserver.eye.fit.EyePose.shape_sd_mm`) nor the measurement's own sd per axis
    (the pose's :attr:`~eyeserver.eye.fit.EyePose.centre_sd_mm`, a move's with its
    reference's) leaves a reason to refuse (:func:`~eyeserver.service.verification.
    shape_reason` and :func:`~eyeserver.service.verification.measurement_reason`, as
    :func:`~eyeserver.service.verification.judge` asks). The bench scores absolute poses."""
    tolerances = Tolerances(translation_mm=TOLERANCE_MM)
    return (confidence >= min_confidence and shape_reason(shape_sd_mm, tolerances) is None
            and measurement_reason(measured_sd_mm, tolerances) is None)


def confident_wrong(centre_error_mm: float, confidence: float,
                    min_confidence: float = DEFAULT_MIN_CONFIDENCE,
                    shape_sd_mm: float = 0.0, measured_sd_mm: Sequence[float] = EXACT) -> bool:
    """Whether a pose is wrong with a confident face: its centre off by more than the clinic's
    tolerance (:data:`TOLERANCE_MM`) while the daemon's check lets it through
    (:func:`passes`)."""
    return centre_error_mm > TOLERANCE_MM and passes(confidence, shape_sd_mm, min_confidence,
                                                     measured_sd_mm)


def _passes_row(row: dict[str, Any], min_confidence: float) -> bool:
    """:func:`passes` for a fitted row of the bench."""
    return passes(row["confidence"], row.get("shape_sd_mm", 0.0), min_confidence,
                  row.get("measured_sd_mm", EXACT))


def _fitted(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [r for r in rows if r["error"] is None]


def _share(part: int, whole: int) -> float | None:
    return part / whole if whole else None


def confident_wrong_summary(rows: list[dict[str, Any]],
                            min_confidence: float = DEFAULT_MIN_CONFIDENCE) -> dict[str, Any]:
    """How many of the bench's poses (``rows``: ``error`` None for a fitted pose, then its
    ``centre_error_mm`` and ``confidence``) are wrong with a confident face
    (:func:`confident_wrong`): their ``count``, their share of all poses (refusals included)
    and of the ``wrong`` ones (off by more than :data:`TOLERANCE_MM`, whatever their
    confidence; None when none is), and the ``min_confidence`` used. Refusals are never
    wrong."""
    fitted = _fitted(rows)
    wrong = [r for r in fitted if r["centre_error_mm"] > TOLERANCE_MM]
    count = sum(1 for r in wrong if _passes_row(r, min_confidence))
    return {"count": count, "share_of_poses": _share(count, len(rows)), "wrong": len(wrong),
            "share_of_wrong": _share(count, len(wrong)), "wrong_above_mm": TOLERANCE_MM,
            "min_confidence": min_confidence}


def confidence_separation(rows: list[dict[str, Any]],
                          min_confidence: float = DEFAULT_MIN_CONFIDENCE) -> dict[str, Any]:
    """How well the confidence separates wrong poses (off by more than :data:`TOLERANCE_MM`)
    from good ones (within :data:`GOOD_MM`): the largest and median confidence of the wrong
    (below ``min_confidence`` all are refused), the median of the good, and the share of the
    good that the daemon's check refuses (:func:`passes`: beam holds for nothing). None where a
    group is empty."""
    fitted = _fitted(rows)
    wrong = [r["confidence"] for r in fitted if r["centre_error_mm"] > TOLERANCE_MM]
    good_rows = [r for r in fitted if r["centre_error_mm"] <= GOOD_MM]
    good = [r["confidence"] for r in good_rows]
    refused = sum(1 for r in good_rows if not _passes_row(r, min_confidence))
    return {"min_confidence": min_confidence, "wrong_above_mm": TOLERANCE_MM,
            "wrong": len(wrong), "max_confidence_when_wrong": max(wrong) if wrong else None,
            "median_confidence_when_wrong": float(np.median(wrong)) if wrong else None,
            "good_within_mm": GOOD_MM, "good": len(good),
            "median_confidence_when_good": float(np.median(good)) if good else None,
            "good_refused": refused, "good_refused_share": _share(refused, len(good))}


def _reason(error: str) -> str:
    """A refusal's message with its numbers taken out, so that alike refusals count as one."""
    return re.sub(r"\b\d+(?:\.\d+)?\b", "N", error)


def refusals(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The poses the pipeline refused (raised on): their count, share and reasons (messages
    with their numbers taken out, most frequent first)."""
    reasons = Counter(_reason(r["error"]) for r in rows if r["error"] is not None)
    count = sum(reasons.values())
    return {"count": count, "share": _share(count, len(rows)),
            "reasons": dict(reasons.most_common())}


@dataclass(frozen=True)
class Bin:
    """One bin of a descriptor: ``low ≤ value < high``, or ``low < value ≤ high`` when
    ``right_closed``."""

    label: str
    low: float
    high: float
    right_closed: bool = False

    def holds(self, value: float) -> bool:
        """Whether ``value`` falls in this bin."""
        if self.right_closed:
            return self.low < value <= self.high
        return self.low <= value < self.high


BINS: dict[str, tuple[Bin, ...]] = {
    "limbus_width_mm": (Bin("< 0.5", -math.inf, 0.5), Bin("0.5–1.0", 0.5, 1.0),
                        Bin("1.0–1.5", 1.0, 1.5), Bin("≥ 1.5", 1.5, math.inf)),
    "limbus_contrast": (Bin("< 0.3", -math.inf, 0.3), Bin("0.3–0.5", 0.3, 0.5),
                        Bin("0.5–0.7", 0.5, 0.7), Bin("≥ 0.7", 0.7, math.inf)),
    "lid_cover": (Bin("0", -math.inf, 0.0, True), Bin("0–0.15", 0.0, 0.15, True),
                  Bin("0.15–0.3", 0.15, 0.3, True), Bin("> 0.3", 0.3, math.inf, True)),
    "anatomy_mismatch_mm": (Bin("< 0.4", -math.inf, 0.4), Bin("0.4–0.6", 0.4, 0.6),
                            Bin("0.6–0.8", 0.6, 0.8), Bin("≥ 0.8", 0.8, math.inf)),
    "mri_sd_mm": (Bin("< 0.2", -math.inf, 0.2), Bin("0.2–0.3", 0.2, 0.3),
                  Bin("≥ 0.3", 0.3, math.inf)),
}
"""The bins of each of :func:`eyeserver.hardware.sim.population.describe`'s descriptors, fixed
edges chosen for the patient population's draws (docs/eye-model.md; shares of 3000 draws):

- limbus width (10–90 %, mm; drawn U(0.2, 2.0)): half-millimetre steps, the first holding the
  sharp eye's 0 and the narrowest patient limbi (≈ 18, 29, 26 and 27 %);
- limbus contrast (Michelson, sclera against iris; patient ≈ 0–0.89, median 0.42): 0.3, 0.5
  and 0.7 (≈ 29, 33, 22 and 16 %), the sharp eye's 0.75 in the last;
- lid cover (share of the limbus's circumference, the eye at rest): none (46 % of patient
  eyes, and the sharp eye), up to 0.15, to 0.3, beyond (≈ 10, 25 and 19 %);
- anatomy mismatch (mm from the fit's own anatomy; patient ≈ 0.08–0.99, median 0.59): 0.4,
  0.6 and 0.8 (≈ 22, 31, 31 and 16 %), the sharp eye's 0 in the first;
- the MRI's error (``--biometry`` only: the sd of this patient's semi-axes' errors, drawn
  0.1–0.4 mm, :data:`eyeserver.hardware.sim.population.MRI_ERROR_SCALE`): below, at and above
  the fit's default 0.2 mm (a third, a third and a third).

Each bin of 600 poses thus holds some 60 or more, enough for a p95 whose bootstrap interval
says how far it may move."""


def by_bin(rows: list[dict[str, Any]],
           min_confidence: float = DEFAULT_MIN_CONFIDENCE) -> dict[str, list[dict[str, Any]]]:
    """The figures per bin of each descriptor (:data:`BINS`; ``rows`` carry theirs under
    ``eye``): poses, fitted, refused, confident wrong, and the centre's and gaze's median, p95
    with its bootstrap interval and max over the bin's fitted poses."""
    out: dict[str, list[dict[str, Any]]] = {}
    for name, bins in BINS.items():
        if not any(name in r["eye"] for r in rows):
            continue  # a descriptor of another kind of run (the MRI's error without biometry)
        entries = []
        for b in bins:
            these = [r for r in rows if b.holds(r["eye"][name])]
            fitted = _fitted(these)
            entries.append({
                "bin": b.label, "low": b.low if math.isfinite(b.low) else None,
                "high": b.high if math.isfinite(b.high) else None,
                "right_closed": b.right_closed, "poses": len(these), "fitted": len(fitted),
                "refused": len(these) - len(fitted),
                "confident_wrong": confident_wrong_summary(these, min_confidence)["count"],
                "centre_error_mm": _stats([r["centre_error_mm"] for r in fitted],
                                          interval=True),
                "gaze_error_deg": _stats([r["gaze_error_deg"] for r in fitted],
                                         interval=True)})
        out[name] = entries
    return out


@dataclass(frozen=True)
class _Setup:
    """What every pose of a run shares (sent to each worker process with its cases)."""

    config: RoomConfig
    calibration: Path
    units: list[str] | None
    seed: int
    work: Path
    min_confidence: float


@dataclass(frozen=True)
class _Case:
    """One pose's draws, made in order by the run before any is rendered, so that a pose's
    figures do not depend on which process renders it or when."""

    n: int
    spec: SceneSpec
    model: EyeModel
    measured: dict[str, Any] | None
    """The biometry the model was entered from (``--biometry``), else None."""
    again: SceneSpec | None
    """The eye moved for its second capture (``--displacement``), else None."""


def case_seed(seed: int, n: int) -> int:
    """The simulated room's seed (its cameras' noise) for the run's ``n``-th capture: a
    function of the run's seed and ``n`` alone, so a pose renders the same in any worker and
    any order (``--jobs``)."""
    return int(np.random.SeedSequence([seed, n]).generate_state(1)[0])


def _score(setup: _Setup, case: _Case) -> dict[str, Any]:
    """Render, reconstruct and fit one pose (and its moved capture) in a room of its own, and
    score it against the truth: the run's row for it."""
    work = setup.work / f"pose_{case.n}"
    try:
        with SimSession.open(setup.config, seed=case_seed(setup.seed, case.n)) as session:
            pose, truth, seconds, error = _measure(session, case.spec, setup.calibration,
                                                   work / "eye", setup.units, case.model)
            described = population.describe(case.spec.eye)
            if case.measured is not None:
                described["mri_sd_mm"] = case.measured["mri_sd_mm"]
            row: dict[str, Any] = {"globe_radius_mm": truth["globe_radius_mm"],
                                   "eye": described, "biometry": case.measured,
                                   "error": error, "confident_wrong": False}
            if pose is None:
                return row
            error_mm = np.asarray(pose.centre_mm) - truth["centre_mm"]
            centre_error = float(np.linalg.norm(error_mm))
            # The stated sd per axis: the measurement's and the unknown shape's, the latter
            # along the gaze.
            stated = np.hypot(pose.centre_sd_mm,
                              pose.shape_sd_mm * np.abs(np.asarray(pose.gaze)))
            row.update({
                "centre_error_mm": centre_error,
                "centre_error_in_sd": [float(e / sd) for e, sd in
                                       zip(np.abs(error_mm), stated, strict=True)],
                "centre_error_axes_mm": [float(e) for e in error_mm],
                "centre_sd_stated_mm": [float(sd) for sd in stated],
                "gaze_error_deg": gaze_angle_deg(pose.gaze, truth["gaze"]),
                "gaze_sd_deg": pose.gaze_sd_deg,
                "radius_error_mm": pose.globe_radius_mm - truth["globe_radius_mm"],
                "limbus_error_mm": None if pose.limbus_centre_mm is None
                else float(np.linalg.norm(np.asarray(pose.limbus_centre_mm)
                                          - truth["limbus_centre_mm"])),
                "gaze_source": pose.gaze_source,
                "surface_mad_mm": pose.surface_mad_mm,
                "sclera_points": pose.sclera_points, "confidence": pose.confidence,
                "shape_sd_mm": pose.shape_sd_mm,
                "measured_sd_mm": [float(sd) for sd in pose.centre_sd_mm],
                "confident_wrong": confident_wrong(centre_error, pose.confidence,
                                                   setup.min_confidence, pose.shape_sd_mm,
                                                   pose.centre_sd_mm),
                "fit_ms": 1000.0 * seconds})
            if case.again is not None:
                second, second_truth, _, why = _measure(session, case.again,
                                                        setup.calibration, work / "moved",
                                                        setup.units, case.model)
                row["displacement"] = ({"error": why} if second is None else
                                       {"error": None, **displacement_error(
                                           pose, second, truth, second_truth)})
            return row
    finally:
        shutil.rmtree(work, ignore_errors=True)


def _worker_start() -> None:
    """A worker process set up as a command's own (``eyeserver.cli.main`` keeps freed memory;
    a spawned worker does not run it), with OpenCV and the BLAS on one thread each: ``--jobs``
    workers share the cores, and each library's own threads would fight the other workers for
    them (as the tracking workers found: docs/notes/tracking.md)."""
    import cv2
    from threadpoolctl import threadpool_limits

    keep_freed_memory()
    threadpool_limits(limits=1, user_api="blas")
    cv2.setNumThreads(1)


def _rows(setup: _Setup, cases: list[_Case], jobs: int, progress: Progress,
          ) -> list[dict[str, Any]]:
    """Every case's row, in the cases' order: in this process for one job, else on ``jobs``
    worker processes (each pose costs seconds of rendering and fitting, so the processes'
    start and the pickled cases cost little). The first failure stops the run."""
    total = len(cases)
    if jobs == 1:
        rows = []
        for case in cases:
            progress(f"pose {case.n + 1}/{total}")
            rows.append(_score(setup, case))
        return rows
    found: dict[int, dict[str, Any]] = {}
    pool = ProcessPoolExecutor(min(jobs, total), mp_context=get_context("spawn"),
                               initializer=_worker_start)
    try:
        futures = {pool.submit(_score, setup, case): case.n for case in cases}
        for future in as_completed(futures):
            found[futures[future]] = future.result()
            progress(f"pose {len(found)}/{total} done")
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
    return [found[case.n] for case in cases]


def run(config: RoomConfig, *, poses: int = 200, seed: int = 0, calibration: Path | None = None,
        units: list[str] | None = None, eyes: str = "patient", biometry: bool = False,
        displacement: bool = False, jobs: int = 1, progress: Progress = quiet,
        ) -> dict[str, Any]:
    """The pose bench as one JSON-able document.

    ``units``: capture only these units (default all: the default room's two look at the one
    eye); ``eyes``: one of :data:`EYES`; ``biometry``: the patient's model from the eye's
    biometry with its measurement errors (:func:`biometry_model`) instead of the population
    model with the radius fitted; ``displacement``: each fitted eye captured again, moved
    (:func:`moved`), and the move measured (:func:`displacement_error`): what a verification
    against a reference captured at set-up sees, where the globe's unknown shape cancels;
    ``jobs``: worker processes sharing the poses (the figures are the same for any number:
    every draw is made first, and each capture's noise comes from :func:`case_seed`).

    Raises
    ------
    EyeserverError
        A unit the room does not have, or eyes it cannot draw.
    """
    known = [unit.id for unit in config.units]
    unknown = [u for u in units or () if u not in known]
    if unknown:
        raise EyeserverError(f"the room has no unit {', '.join(unknown)} (it has "
                             f"{', '.join(known)})")
    if eyes not in EYES:
        raise EyeserverError(f"no eyes {eyes!r} (choose from {', '.join(EYES)})")
    if jobs < 1:
        raise EyeserverError(f"jobs must be at least 1, not {jobs}")
    streams = Streams.from_seed(seed)
    min_confidence = DEFAULT_MIN_CONFIDENCE

    def model_of(eye: EyeSpec) -> tuple[EyeModel, dict[str, Any] | None]:
        if not biometry:
            return EyeModel.population(), None
        measured = dict(population.biometry(eye, streams.errors))
        return biometry_model(measured), measured

    cases = []
    for n in range(poses):
        spec = draw_spec(streams, eyes, n)
        model, measured = model_of(spec.eye)
        again = moved(streams.moves, spec) if displacement else None
        cases.append(_Case(n, spec, model, measured, again))
    base = (random_spec(streams.poses, 12.0) if eyes == "sharp"
            else draw_spec(streams, eyes, poses))
    shifted = base.model_copy(update={"position_mm": (
        base.position[0] + SHIFT_MM, base.position[1], base.position[2])})
    shift_model, _ = model_of(base.eye)  # one patient, one model for both captures

    with tempfile.TemporaryDirectory(prefix="eyeserver-bench-pose-") as tmp:
        work = Path(tmp)
        caldir = calibration
        if caldir is None:
            progress("calibrating the simulated rig (≈ 1 minute)")
            caldir = calibrate_room(config, work, seed, progress)
        setup = _Setup(config, caldir, units, seed, work, min_confidence)
        rows = _rows(setup, cases, jobs, progress)
        progress("1 mm shift between two captures")
        with SimSession.open(config, seed=case_seed(seed, poses)) as session:
            first, _, _, e1 = _measure(session, base, caldir, work / "shift_a", units,
                                       shift_model)
            second, _, _, e2 = _measure(session, shifted, caldir, work / "shift_b", units,
                                        shift_model)
    shift: dict[str, Any] = {"true_shift_mm": SHIFT_MM, "tolerance_mm": TOLERANCE_MM,
                             "error": e1 or e2}
    if first is not None and second is not None:
        measured_mm = float(np.linalg.norm(np.subtract(second.centre_mm, first.centre_mm)))
        shift.update({"measured_shift_mm": measured_mm,
                      "fails_tolerance": measured_mm > TOLERANCE_MM})
    fitted = _fitted(rows)
    report: dict[str, Any] = {
        "format": FORMAT, "machine": {**machine(), "jobs": jobs}, "seed": seed,
        "poses": poses, "fitted": len(fitted), "goals": GOALS,
        "units": units or known, "eyes": eyes, "biometry": biometry,
        "model": ("the patient's biometry with measurement errors (MRI globe, keratometry, "
                  "white-to-white), as the daemon takes it" if biometry
                  else "population, radius fitted"),
        "min_confidence": min_confidence,
        "centre_error_mm": _stats([r["centre_error_mm"] for r in fitted], interval=True),
        "gaze_error_deg": _stats([r["gaze_error_deg"] for r in fitted], interval=True),
        "radius_error_mm": _stats([abs(r["radius_error_mm"]) for r in fitted]),
        "limbus_centre_error_mm": _stats([r["limbus_error_mm"] for r in fitted
                                          if r["limbus_error_mm"] is not None]),
        "gaze_sources": {source: sum(1 for r in fitted if r["gaze_source"] == source)
                         for source in sorted({r["gaze_source"] for r in fitted})},
        "surface_mad_mm": _stats([r["surface_mad_mm"] for r in fitted]),
        "sclera_points": _stats([float(r["sclera_points"]) for r in fitted]),
        "confidence": _stats([r["confidence"] for r in fitted]),
        "fit_ms": _stats([r["fit_ms"] for r in fitted]),
        "uncertainty": _calibration(fitted),
        "confident_wrong": confident_wrong_summary(rows, min_confidence),
        "confidence_separation": confidence_separation(rows, min_confidence),
        "refusals": refusals(rows),
        "by_bin": by_bin(rows, min_confidence)}
    if displacement:
        report["displacement"] = displacement_summary(rows)
    if eyes == "sharp":
        report["by_globe_radius"] = _by_globe_radius(rows)
    report.update({"shift": shift, "cases": rows})
    return report


def displacement_summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The moves measured (``--displacement``): pairs tried (fitted first captures), pairs
    whose second capture was fitted, the centre's and the gaze turn's errors, and the
    confidently wrong moves (off by more than :data:`TOLERANCE_MM` yet passing the check
    against a captured reference)."""
    pairs = [r["displacement"] for r in rows if "displacement" in r]
    fitted = [d for d in pairs if d["error"] is None]
    return {"move_mm": MOVE_MM, "turn_deg": MOVE_DEG, "pairs": len(pairs),
            "fitted": len(fitted),
            "error_mm": _stats([d["error_mm"] for d in fitted], interval=True),
            "gaze_turn_error_deg": _stats([d["gaze_turn_error_deg"] for d in fitted],
                                          interval=True),
            "confident_wrong": sum(1 for d in fitted if d["confident_wrong"])}


def _by_globe_radius(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The sharp eye's figures per globe size (:data:`RADII_MM`)."""
    fitted = _fitted(rows)
    by_radius = {}
    for radius in RADII_MM:
        these = [r for r in fitted if r["globe_radius_mm"] == radius]
        by_radius[f"{radius:g}"] = {
            "poses": sum(1 for r in rows if r["globe_radius_mm"] == radius),
            "centre_error_mm": _stats([r["centre_error_mm"] for r in these], interval=True),
            "gaze_error_deg": _stats([r["gaze_error_deg"] for r in these], interval=True)}
    return by_radius


def _calibration(fitted: list[dict[str, Any]]) -> dict[str, Any]:
    """How often the errors lie within one and two of the pose's stated standard deviations,
    beside what a normal error would give: per axis of the centre (68 and 95 %), and for the
    gaze's angle, whose stated sd is that of a tilt in two axes at once (63 and 98 %)."""
    axes = np.concatenate([r["centre_error_in_sd"] for r in fitted]) if fitted else np.zeros(0)
    gaze = np.array([r["gaze_error_deg"] / r["gaze_sd_deg"] for r in fitted
                     if r["gaze_sd_deg"] > 0])

    def within(values: Any, k: float) -> float | None:
        return float(np.mean(values <= k)) if len(values) else None

    return {"centre_axes_within_1_sd": within(axes, 1.0),
            "centre_axes_within_2_sd": within(axes, 2.0),
            "gaze_within_1_sd": within(gaze, 1.0), "gaze_within_2_sd": within(gaze, 2.0),
            "normal": {"centre_axes_within_1_sd": 0.683, "centre_axes_within_2_sd": 0.954,
                       "gaze_within_1_sd": 1.0 - math.exp(-1.0),
                       "gaze_within_2_sd": 1.0 - math.exp(-4.0)}}


def format_text(report: dict[str, Any]) -> str:
    """The report for people."""
    def line(name: str, key: str, goal: str) -> str:
        s = report[key]
        if s["median"] is None:
            return f"{name}: not measured"
        return f"{name}: median {s['median']:.3f}, p95 {p95_text(s)}  (goal {goal})"

    out = [f"eye pose bench: {report['fitted']}/{report['poses']} poses fitted "
           f"({eyes_text(report)}; units {', '.join(report.get('units', ['all']))}; model: "
           f"{report['model']}; min_confidence {report['min_confidence']:g}, the daemon's)",
           line("globe centre error (mm)", "centre_error_mm", "≤ 0.1 mm"),
           line("gaze error (deg)", "gaze_error_deg", "≤ 0.5°"),
           line("globe radius |error| (mm)", "radius_error_mm", "-"),
           line("limbus centre error (mm)", "limbus_centre_error_mm", "-"),
           line("surface–model median |distance| (mm)", "surface_mad_mm",
                "≤ 0.10 mm; paper 0.43 mm"),
           line("sclera points", "sclera_points", "-"),
           line("confidence", "confidence", "-"),
           line("fit time (ms)", "fit_ms", "-")]
    out += [by_globe_text(radius, by) for radius, by in report.get("by_globe_radius", {}).items()]
    out.append("p95s in brackets: their 95 % bootstrap intervals (how far another draw of as "
               "many poses may put them)")
    out.append("gaze from: " + ", ".join(f"{k} {v}" for k, v in report["gaze_sources"].items()))
    coverage = uncertainty_coverage(report)
    if coverage is not None:
        out.append(f"{coverage} (goal: ≥ 95 % within 2 sd)")
    out += [confident_wrong_text(report), separation_text(report), refusals_text(report)]
    if "displacement" in report:
        out.append(displacement_text(report))
    shift = report["shift"]
    if "measured_shift_mm" in shift:
        verdict = "FAIL (detected)" if shift["fails_tolerance"] else "pass (missed!)"
        out.append(f"1 mm shift: measured {shift['measured_shift_mm']:.3f} mm → {verdict} "
                   f"against {shift['tolerance_mm']} mm")
    else:
        out.append(f"1 mm shift: not measured ({shift['error']})")
    out += ["", "per bin (centre mm, gaze °: median and p95 (95 % bootstrap interval) over the "
            "bin's fitted poses):"]
    header = (f"{'descriptor':<32} {'bin':<9} {'fitted':>9}  {'centre median':>13}  "
              f"{'centre p95':<22}  {'gaze median':>11}  {'gaze p95':<22}  confident wrong")
    out.append(header)
    for name, entries in report["by_bin"].items():
        for entry in entries:
            centre, gaze = entry["centre_error_mm"], entry["gaze_error_deg"]
            out.append(f"{DESCRIPTORS.get(name, name):<32} {entry['bin']:<9} "
                       f"{entry['fitted']:>4}/{entry['poses']:<4}  "
                       f"{number_text(centre['median']):>13}  {p95_text(centre):<22}  "
                       f"{number_text(gaze['median']):>11}  {p95_text(gaze):<22}  "
                       f"{entry['confident_wrong']}")
    return "\n".join(out)
