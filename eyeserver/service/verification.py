"""Position verification: is the patient's eye where the plan wants it?

``measure(patient, fraction)`` captures the patient's unit (:attr:`Patient.unit`), reconstructs
the capture with the active calibration, fits the patient's newest eye model (population
defaults without one) and compares the pose with the fraction's newest reference:

* ``delta_mm = measured centre − reference centre`` (ΔX, ΔY, ΔZ in the WCS, mm) and its length;
* ``gaze_deg``: the angle between measured and reference gaze;
* it passes when ``|Δ| ≤ translation_mm``, ``gaze_deg ≤ gaze_deg`` tolerance, the fit's
  confidence is at least ``min_confidence`` and what the eye model leaves unknown of the
  globe's shape is small against the tolerance (:func:`model_sd_mm`: it cancels against a
  reference captured at set-up, not against a planned pose), and every unit of the patient's
  set-up gave the reconstruction at least :data:`MIN_UNIT_POINTS` points (a unit with a dark
  projector gives none; a captured reference is refused then); ``reasons`` says what failed.

The result is stored with its evidence (capture id — its bundle and ``cloud.ply`` stay with the
capture —, the reconstruction's calibration id, the eye-model version, each unit's points and
the fit) as
``patients/<key>/measurements/<pose id>.json`` and a row, in one audited transaction; the
capture of a stored measurement or captured reference is never deleted, by a person (HTTP 409)
or the retention rule (:meth:`PoseVerification.evidence_captures`). A fit that
fails raises :class:`~eyeserver.eye.fit.PoseError` (HTTP 422); the failure is written
to the audit file with the capture it was tried on.

The deviation arithmetic (:func:`deviation`, :func:`judge`) is pure and kept apart for tests.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from typing import Any, Literal, Protocol

import numpy as np

from eyeserver.errors import EyeserverError
from eyeserver.eye import CloudLike, EyeModel, EyePose, LimbusView, PoseError, fit_eye
from eyeserver.eye.track import lids_closed
from eyeserver.io import RigSpec, read_ply
from eyeserver.reconstruction import limbus_views
from eyeserver.service.core import NoActiveCalibrationError, Service
from eyeserver.service.patients import (
    EyeModelVersion,
    Patient,
    Patients,
    ReferencePose,
    Tolerances,
)
from eyeserver.service.storage import UnknownIdError

__all__ = ["MEASURED_SD_SHARE", "MIN_UNIT_POINTS", "MODEL_SD_SHARE", "Deviation", "FitFunction",
           "PoseVerification", "Verdict", "combined_sd_mm", "deviation", "gaze_angle_deg", "judge",
           "measured_sd_mm", "measurement_model", "measurement_reason", "model_sd_mm",
           "shape_cancels", "shape_reason", "turned_shape_sd_mm", "unit_contributions",
           "unit_shortfalls"]

class FitFunction(Protocol):
    """What fits an eye model to a cloud and, when given, the fringe images it came from
    (:func:`~eyeserver.eye.fit.fit_eye`)."""

    def __call__(self, cloud: CloudLike, model: EyeModel,
                 views: Sequence[LimbusView] = (), /) -> EyePose: ...


Vector = Sequence[float]

_log = logging.getLogger(__name__)


def _now_text() -> str:
    return datetime.now(UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def gaze_angle_deg(a: Vector, b: Vector) -> float:
    """The angle between two directions, degrees (0…180; they need not be unit vectors).

    ``atan2(|a×b|, a·b)`` rather than ``acos`` of the dot product: it stays accurate for the
    small angles that matter here (acos loses half the digits near 0).

    >>> round(gaze_angle_deg((0, 0, 1), (0, math.sin(0.01), math.cos(0.01))), 6)
    0.572958
    """
    cross = (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])
    dot = a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
    return math.degrees(math.atan2(math.hypot(*cross), dot))


@dataclass(frozen=True)
class Deviation:
    """Measured minus reference, in the WCS.

    Attributes
    ----------
    delta_mm : (ΔX, ΔY, ΔZ)
        Globe centre, measured − reference, mm.
    length_mm : float
        ``|delta_mm|``.
    gaze_deg : float
        Angle between the measured and the reference gaze, degrees.
    limbus_delta_mm : (ΔX, ΔY, ΔZ) or None
        Limbus centre, measured − reference, when both are known.
    model_sd_mm : float
        The deviation's sd along the gaze from what the eye model does not say about the
        globe's shape (:func:`model_sd_mm`), mm.
    measured_sd_mm : (sdX, sdY, sdZ)
        The deviation's sd per WCS axis from the measurements themselves, mm: the pose's
        stated centre sd and a captured reference's (:func:`measured_sd_mm`).
    """

    delta_mm: tuple[float, float, float]
    length_mm: float
    gaze_deg: float
    limbus_delta_mm: tuple[float, float, float] | None = None
    model_sd_mm: float = 0.0
    measured_sd_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def to_dict(self) -> dict[str, Any]:
        """As stored and answered."""
        return {"delta_mm": list(self.delta_mm), "length_mm": self.length_mm,
                "gaze_deg": self.gaze_deg,
                "limbus_delta_mm": None if self.limbus_delta_mm is None
                else list(self.limbus_delta_mm), "model_sd_mm": self.model_sd_mm,
                "measured_sd_mm": list(self.measured_sd_mm)}


def _difference(a: Vector, b: Vector) -> tuple[float, float, float]:
    return (float(a[0]) - float(b[0]), float(a[1]) - float(b[1]), float(a[2]) - float(b[2]))


def deviation(measured_centre: Vector, measured_gaze: Vector, reference_centre: Vector,
              reference_gaze: Vector, measured_limbus: Vector | None = None,
              reference_limbus: Vector | None = None) -> Deviation:
    """Measured − reference pose (see :class:`Deviation`).

    >>> d = deviation((0.1, 0.0, -9.8), (0, 0, 1), (0.0, 0.0, -10.0), (0, 0, 1))
    >>> [round(v, 6) for v in d.delta_mm], round(d.length_mm, 6), d.gaze_deg
    ([0.1, 0.0, 0.2], 0.223607, 0.0)
    """
    delta = _difference(measured_centre, reference_centre)
    limbus = (None if measured_limbus is None or reference_limbus is None
              else _difference(measured_limbus, reference_limbus))
    return Deviation(delta, math.hypot(*delta), gaze_angle_deg(measured_gaze, reference_gaze),
                     limbus)


def model_sd_mm(pose: EyePose, reference: ReferencePose, eye_model_version: int | None
                ) -> float:
    """The sd (mm) that the globe's unknown shape (:attr:`EyePose.shape_sd_mm`) leaves in the
    deviation of ``pose``, fitted with the patient's ``eye_model_version`` (None: population
    defaults), from ``reference``.

    A reference captured at set-up with the same eye-model version carries the same error of
    the same eye (the sphere's centre off along the gaze by an amount fixed by the globe's
    shape): it cancels but for the gaze's turn between them, ``shape_sd · |g − g_ref|``. A
    planned reference, or one captured with another model, is absolute: the whole of it counts.
    """
    if shape_cancels(reference, eye_model_version):
        return turned_shape_sd_mm(pose.shape_sd_mm, pose.gaze, reference.pose["gaze"])
    return float(pose.shape_sd_mm)


def measured_sd_mm(pose: EyePose, reference: ReferencePose) -> tuple[float, float, float]:
    """The sd per WCS axis (mm) the measurements leave in the deviation of ``pose`` from
    ``reference``: the pose's stated :attr:`~eyeserver.eye.fit.EyePose.centre_sd_mm` and, for a
    reference captured at set-up, its own fit's (the two independent); a planned pose is exact
    by definition."""
    fit = (reference.evidence or {}).get("fit") if reference.source == "capture" else None
    ref_sd = fit.get("centre_sd_mm") if isinstance(fit, dict) else None
    return combined_sd_mm(pose.centre_sd_mm, (0.0, 0.0, 0.0) if ref_sd is None else ref_sd)


def combined_sd_mm(first: Vector, second: Vector) -> tuple[float, float, float]:
    """The sd per axis (mm) of the difference of two independent measurements of sds
    ``first`` and ``second`` per axis: each axis's in quadrature."""
    x, y, z = (math.hypot(float(a), float(b)) for a, b in zip(first, second, strict=True))
    return x, y, z


def turned_shape_sd_mm(shape_sd_mm: float, gaze: Vector, reference_gaze: Vector) -> float:
    """What an unknown globe shape of sd ``shape_sd_mm`` (along the gaze, mm) leaves in the
    move between two fits of one eye with one model: its share of the gaze's turn,
    ``shape_sd · |g − g_ref|`` (unit gazes)."""
    return float(shape_sd_mm) * math.hypot(*(a - b for a, b in zip(gaze, reference_gaze,
                                                                   strict=True)))


def shape_cancels(reference: ReferencePose, eye_model_version: int | None) -> bool:
    """Whether the globe's unknown shape cancels from a deviation from ``reference`` of a pose
    fitted with ``eye_model_version``: the reference was captured with the same model
    (:func:`model_sd_mm`)."""
    evidence = reference.evidence or {}
    return (reference.source == "capture" and "eye_model_version" in evidence
            and evidence["eye_model_version"] == eye_model_version)


MODEL_SD_SHARE = 0.5
"""Share of the translation tolerance the model's own uncertainty (2 sd, :func:`model_sd_mm`)
may take: beyond it a deviation within the tolerance says nothing (with population defaults
against a planned pose, 2 × 0.65 mm against 0.2 mm)."""


MEASURED_SD_SHARE = 1.0
"""Largest share of the translation tolerance the deviation's own measured sd
(:func:`measured_sd_mm`, its worst axis) may take. At one sd equal to the tolerance a pose
exactly at the reference is already measured out of tolerance a third of the time along that
axis: beyond it the measurement cannot tell a deviation within the tolerance from one outside.
The pose bench's moves of sharp eyes pass it and the poorly seen patient eyes' that passed off
by more than the tolerance do not (docs/notes/patient-eye.md, fifteenth session)."""


@dataclass(frozen=True)
class Verdict:
    """Pass or fail, with the reasons of a fail (empty when it passes)."""

    passed: bool
    in_tolerance: bool
    reasons: tuple[str, ...]


def judge(found: Deviation, tolerances: Tolerances, confidence: float) -> Verdict:
    """Compare a deviation with the tolerances; a fit less confident than ``min_confidence``
    fails too (``in_tolerance`` then still tells whether the numbers were within)."""
    reasons = []
    if not found.length_mm <= tolerances.translation_mm:  # NaN fails
        reasons.append(f"translation {found.length_mm:.3f} mm exceeds "
                       f"{tolerances.translation_mm:g} mm")
    if not found.gaze_deg <= tolerances.gaze_deg:
        reasons.append(f"gaze deviation {found.gaze_deg:.2f}° exceeds {tolerances.gaze_deg:g}°")
    in_tolerance = not reasons
    if not confidence >= tolerances.min_confidence:
        reasons.append(f"fit confidence {confidence:.2f} is below "
                       f"{tolerances.min_confidence:g}")
    unknown_shape = shape_reason(found.model_sd_mm, tolerances)
    if unknown_shape is not None:
        reasons.append(unknown_shape)
    vague = measurement_reason(found.measured_sd_mm, tolerances)
    if vague is not None:
        reasons.append(vague)
    return Verdict(not reasons, in_tolerance, tuple(reasons))


def shape_reason(model_sd_mm: float, tolerances: Tolerances) -> str | None:
    """Why a deviation whose globe shape is this uncertain (:func:`model_sd_mm`) says nothing
    against ``tolerances``, or None where 2 sd take at most :data:`MODEL_SD_SHARE` of the
    translation tolerance."""
    if 2.0 * model_sd_mm <= MODEL_SD_SHARE * tolerances.translation_mm:
        return None
    return (f"the eye model leaves the globe's shape uncertain (no MRI ellipsoid, or the error "
            f"of the one given): against this reference the centre is known only to "
            f"±{2.0 * model_sd_mm:.2f} mm (2 sd) along the gaze, more than {MODEL_SD_SHARE:g} "
            f"of the {tolerances.translation_mm:g} mm tolerance; enter the MRI's ellipsoid with "
            "its error (globe_sd_mm) in the eye model or capture a reference at set-up")


def measurement_reason(measured_sd: Sequence[float], tolerances: Tolerances,
                       subject: str = "the centre's deviation (with the reference's sd)"
                       ) -> str | None:
    """Why a ``subject`` measured this uncertainly (sd per axis, mm: :func:`measured_sd_mm`)
    says nothing against ``tolerances``, or None where its worst axis's sd is at most
    :data:`MEASURED_SD_SHARE` of the translation tolerance. Without it the check passed a
    deviation within the tolerance whatever the fit said of its own error."""
    worst = max(math.inf if math.isnan(sd) else float(sd) for sd in measured_sd)
    if worst <= MEASURED_SD_SHARE * tolerances.translation_mm:
        return None
    return (f"the measurement states {subject} only to ±{2.0 * worst:.2f} mm (2 sd), more "
            f"than {MEASURED_SD_SHARE * 2.0:g} × the {tolerances.translation_mm:g} mm "
            "tolerance: the eye was seen too poorly to tell (the limbus or the sclera barely "
            "visible); measure again with the eye open, still and looking at the fixation "
            "light")


MIN_UNIT_POINTS = 500
"""Fewest reconstructed points an optical unit of the patient's set-up must give for its
measurement to count: a unit whose projector is dark (or whose view is blocked) gives none,
and a pose from the other unit alone passed with nothing in the record saying so (issue 35);
an eye in view gives each unit thousands."""


def unit_contributions(summary: dict[str, Any], rig: RigSpec, unit_ids: Sequence[str]
                       ) -> dict[str, dict[str, Any]]:
    """Each unit of ``unit_ids``: the points each of its cameras gave to a reconstruction
    (:func:`~eyeserver.reconstruction.reconstruct_bundle`'s ``summary``; a camera
    missing there gave none) and their sum."""
    cameras = summary.get("cameras", {})
    out: dict[str, dict[str, Any]] = {}
    for unit_id in unit_ids:
        unit = rig.unit(unit_id)
        points = {c: int(cameras.get(c, {}).get("points", 0)) for c in unit.cameras}
        out[unit_id] = {"points": sum(points.values()), "cameras": points}
    return out


def unit_shortfalls(units: dict[str, dict[str, Any]]) -> tuple[str, ...]:
    """Why the units that gave fewer than :data:`MIN_UNIT_POINTS` points make a measurement
    void (empty when every unit gave enough)."""
    return tuple(f"unit {unit_id} gave {seen['points']} points (at least {MIN_UNIT_POINTS} "
                 "needed): its projector may be dark or its view blocked"
                 for unit_id, seen in units.items() if seen["points"] < MIN_UNIT_POINTS)


@dataclass(frozen=True)
class _Observation:
    capture_id: str
    unit: str
    calibration_id: str
    eye_model_version: int | None
    eye_model: dict[str, Any] | None
    cloud_points: int
    units: dict[str, dict[str, Any]]
    pose: EyePose
    looks_shut: bool = False
    """Live tracking's blink test (:func:`~eyeserver.eye.track.lids_closed`) finds shut lids
    inside the fitted limbus: on a capture of an open eye, the pose's gaze or globe is off."""

    def evidence(self) -> dict[str, Any]:
        return {"capture_id": self.capture_id, "unit": self.unit,
                "calibration_id": self.calibration_id,
                "eye_model_version": self.eye_model_version, "eye_model": self.eye_model,
                "cloud_points": self.cloud_points, "units": self.units,
                "fit": self.pose.to_dict()}


def measurement_model(stored: EyeModelVersion | None, reference: ReferencePose | None
                      ) -> EyeModel:
    """The eye model a patient's eye is measured with: the stored version (population defaults
    without one), holding the globe radius a captured ``reference`` was fitted with
    where the model leaves the radius free — so that the fit's radius uncertainty (±0.15 mm
    from the narrow band of sclera the lids leave) cannot move the centre between reference
    and measurement."""
    model = EyeModel.population() if stored is None else stored.model.to_eye_model()
    fit = {} if reference is None or reference.evidence is None else \
        reference.evidence.get("fit") or {}
    held = fit.get("globe_radius_mm")
    if isinstance(held, (int, float)) and math.isfinite(held) \
            and model.globe_radius_mm is None and model.globe_semi_axes_mm is None:
        # A fit's radius, not a measured one: its error is the reference's, in both fits.
        model = replace(model, globe_radius_mm=float(held), globe_sd_mm=0.0)
    return model


class PoseVerification:
    """Pose measurements of the patients of one daemon.

    Parameters
    ----------
    service : Service
        The open daemon (capture, reconstruction, store, audit, events).
    patients : Patients
        Its patients.
    fit : FitFunction, optional
        The eye fit (default :func:`~eyeserver.eye.fit.fit_eye`); tests give their
        own for determinism. A public attribute.

    All methods block (hardware, disk, CPU) and are thread-safe.
    """

    def __init__(self, service: Service, patients: Patients, fit: FitFunction = fit_eye
                 ) -> None:
        self.service = service
        self.patients = patients
        self.fit = fit
        # A stored result's capture is its evidence: it is never deleted (nor by retention).
        service.keep_as_evidence(self.evidence_captures)

    def evidence_captures(self) -> dict[str, str]:
        """The captures of stored pose measurements and captured reference poses → what of."""
        held = self.patients.reference_captures()
        for measurement_id, capture_id in self.service.store.query(
                "SELECT id, capture_id FROM pose_measurements"):
            held[str(capture_id)] = f"the evidence of pose measurement {measurement_id}"
        return held

    # --- measuring --------------------------------------------------------------------------

    def _observe(self, patient: Patient, actor: str, action: str, fraction: int,
                 reference: ReferencePose | None = None, *, blink_test: bool = False,
                 ) -> _Observation:
        """Capture, reconstruct and fit (with :func:`measurement_model`); a failure after the
        capture is audited with it. With ``blink_test``, live tracking's blink test is run on
        the capture with the pose found (:attr:`_Observation.looks_shut`; ≈ 50 ms)."""
        service = self.service
        if service.store.active_calibration() is None:  # before moving any hardware
            raise NoActiveCalibrationError(
                "no calibration is active: import one (POST /api/v1/calibrations) and activate "
                "it (POST /api/v1/calibrations/{id}/activate)")
        stored_model = self.patients.eye_model(patient.patient_id)
        model = measurement_model(stored_model, reference)
        capture = service.capture(patient.unit)
        try:
            summary = service.reconstruct(capture.id)
            cloud = read_ply(service.cloud_path(capture.id))
            calibration = service.store.get_calibration(str(summary["calibration_id"]))
            views = limbus_views(calibration.path, capture.path)
            pose = self.fit(cloud, model, views)
            looks_shut = blink_test and pose.gaze_source != "none" and lids_closed(
                np.asarray(cloud.points, dtype=np.float64),
                np.asarray(pose.centre_mm, dtype=np.float64), pose.globe_radius_mm,
                np.asarray(pose.gaze, dtype=np.float64), model.limbus_diameter_mm / 2)
        except EyeserverError as exc:
            self._audit_failure(actor, action, patient, fraction, capture.id,
                                str(exc) or type(exc).__name__)
            raise
        return _Observation(
            capture.id, patient.unit, str(summary["calibration_id"]),
            None if stored_model is None else stored_model.version,
            None if stored_model is None else stored_model.model.model_dump(mode="json"),
            int(summary["points"]),
            unit_contributions(summary, service.rig_spec(), service.unit_ids(patient.unit)),
            pose, looks_shut)

    def _audit_failure(self, actor: str, action: str, patient: Patient, fraction: int,
                       capture_id: str, error: str) -> None:
        """An ``error`` audit line for a measurement that failed after its capture."""
        self.service.audit.record(actor, action, patient.key, {
            "patient_id": patient.patient_id, "fraction": fraction, "capture_id": capture_id,
            "error": error}, "error")

    def measure(self, patient_id: str, fraction: int, *, actor: str) -> dict[str, Any]:
        """Measure the pose of a patient's eye and compare it with the fraction's reference.

        Returns
        -------
        dict
            The stored measurement (see the module docstring and ``GET
            /api/v1/pose/measurements/{id}``).

        Raises
        ------
        UnknownPatientError, NoReferenceError
            No such patient, or no reference for the fraction (HTTP 404).
        NoActiveCalibrationError
            No calibration is active (HTTP 409); nothing was captured.
        PoseError
            No eye could be fitted (HTTP 422; the reason says why).
        StateConflictError, DeviceError, QueueFullError, ReconstructionError
            As for :meth:`Service.capture` and :meth:`Service.reconstruct`.
        """
        patient = self.patients.get(patient_id)
        reference = self.patients.reference(patient_id, fraction)
        seen = self._observe(patient, actor, "measure_pose", fraction, reference)
        pose = seen.pose
        ref = reference.pose
        found = replace(deviation(pose.centre_mm, pose.gaze, ref["centre_mm"], ref["gaze"],
                                  pose.limbus_centre_mm, ref.get("limbus_centre_mm")),
                        model_sd_mm=model_sd_mm(pose, reference, seen.eye_model_version),
                        measured_sd_mm=measured_sd_mm(pose, reference))
        verdict = judge(found, patient.tolerances, pose.confidence)
        missing = unit_shortfalls(seen.units)
        if missing:  # a unit of the set-up saw nothing: the pose is not the whole set-up's
            verdict = Verdict(False, verdict.in_tolerance, verdict.reasons + missing)
        store = self.service.store
        measurement_id = store.new_id("pose")
        relative = f"patients/{patient.key}/measurements/{measurement_id}.json"
        document: dict[str, Any] = {
            "format": "eyeserver.pose-measurement/1", "id": measurement_id,
            "patient_id": patient_id, "fraction": fraction, "eye": patient.eye,
            "created": _now_text(), "actor": actor, "passed": verdict.passed,
            "in_tolerance": verdict.in_tolerance, "reasons": list(verdict.reasons),
            "deviation": found.to_dict(), "tolerances": patient.tolerances.to_dict(),
            "pose": pose.to_dict(),
            "reference": {"version": reference.version, "source": reference.source,
                          "pose": reference.pose},
            "evidence": seen.evidence()}
        text = json.dumps(document, indent=2) + "\n"
        with store.transaction() as db:
            store.write_document(relative, text)
            db.execute("INSERT INTO pose_measurements (id, patient_id, fraction, created, "
                       "passed, capture_id, file) VALUES (?, ?, ?, ?, ?, ?, ?)",
                       (measurement_id, patient_id, fraction, document["created"],
                        int(verdict.passed), seen.capture_id, relative))
            store.audit_in(db, actor, "measure_pose", measurement_id, {
                "patient_id": patient_id, "fraction": fraction, "passed": verdict.passed,
                "length_mm": found.length_mm, "gaze_deg": found.gaze_deg,
                "capture_id": seen.capture_id})
        _log.info("pose measured", extra={"measurement_id": measurement_id,
                                          "passed": verdict.passed,
                                          "length_mm": round(found.length_mm, 4),
                                          "gaze_deg": round(found.gaze_deg, 3)})
        # No patient id on the event stream: room displays need the verdict, not the name.
        self.service.events.publish("pose.measured", measurement_id=measurement_id,
                                    fraction=fraction, passed=verdict.passed,
                                    length_mm=found.length_mm, gaze_deg=found.gaze_deg)
        result: dict[str, Any] = json.loads(text)
        return result

    def capture_reference(self, patient_id: str, fraction: int, *, actor: str
                          ) -> ReferencePose:
        """Measure the eye at set-up and store the pose as the fraction's next reference.

        Raises as :meth:`measure`, except that no reference is needed; and
        :class:`~eyeserver.eye.PoseError` for a pose less confident than the patient's
        ``min_confidence`` or whose stated centre sd exceeds the tolerance
        (:func:`measurement_reason`): every later measurement and tracked frame is compared
        with the reference, so a weak one would make every check fail for the wrong reason and
        tracking take the open eye for shut lids (docs/notes/patient-eye.md, "Eighth
        session"); and for
        a pose whose own capture live tracking's blink test would take for shut lids (the
        open eye's pose off, whatever its confidence).
        """
        patient = self.patients.get(patient_id)
        seen = self._observe(patient, actor, "set_reference_pose", fraction, blink_test=True)
        reasons = list(unit_shortfalls(seen.units))
        pose = seen.pose
        minimum = patient.tolerances.min_confidence
        if not pose.confidence >= minimum:
            reasons.append(f"the eye was fitted at confidence {pose.confidence:.2f}, below the "
                           f"patient's min_confidence {minimum:g} (the limbus not seen well: "
                           "capture again with the eye open, still and looking at the "
                           "fixation light)")
        if seen.looks_shut:
            # Tracking's blink test looks for lids inside the limbus about the reference's
            # gaze: a reference whose own capture looks shut there would hold every open frame
            # as a blink (docs/notes/patient-eye.md, "Eighth session").
            reasons.append("live tracking's blink test finds shut lids inside the limbus this "
                           "pose places on the open eye (its gaze or globe is off, or the lids "
                           "were closing): capture again with the eye open, still and looking "
                           "at the fixation light")
        vague = measurement_reason(pose.centre_sd_mm, patient.tolerances, "the centre")
        if vague is not None:  # every measurement against it would fail for its sake
            reasons.append(vague)
        if reasons:
            reason = "cannot take this capture as the reference: " + "; ".join(reasons)
            self._audit_failure(actor, "set_reference_pose", patient, fraction,
                                seen.capture_id, reason)
            raise PoseError(reason)
        return self.patients.set_reference(
            patient_id, fraction, {"centre_mm": list(pose.centre_mm), "gaze": list(pose.gaze),
                                   "limbus_centre_mm": None if pose.limbus_centre_mm is None
                                   else list(pose.limbus_centre_mm)},
            source="capture", actor=actor, evidence=seen.evidence())

    # --- reading ----------------------------------------------------------------------------

    def get(self, measurement_id: str) -> dict[str, Any]:
        """One stored measurement; :class:`UnknownIdError` for an unknown id."""
        rows = self.service.store.query("SELECT file FROM pose_measurements WHERE id = ?",
                                        (measurement_id,))
        if not rows:
            raise UnknownIdError(measurement_id, "pose measurement")
        document: dict[str, Any] = json.loads(self.service.store.read_document(rows[0][0]))
        return document

    def find(self, patient_id: str, fraction: int | None = None, *, limit: int = 50,
             offset: int = 0, order: Literal["newest", "oldest"] = "newest",
             ) -> tuple[list[dict[str, Any]], int]:
        """A patient's measurements (of one fraction, if given), newest first, one page, and
        how many there are in all; :class:`UnknownPatientError` for an unknown patient."""
        self.patients.get(patient_id)
        where = "WHERE patient_id = ?" + ("" if fraction is None else " AND fraction = ?")
        parameters: list[object] = [patient_id] + ([] if fraction is None else [fraction])
        store = self.service.store
        total = int(store.query(f"SELECT COUNT(*) FROM pose_measurements {where}",
                                parameters)[0][0])
        direction = "DESC" if order == "newest" else "ASC"
        rows = store.query(f"SELECT file FROM pose_measurements {where} ORDER BY id "
                           f"{direction} LIMIT ? OFFSET ?", [*parameters, limit, offset])
        return [json.loads(store.read_document(file)) for (file,) in rows], total
