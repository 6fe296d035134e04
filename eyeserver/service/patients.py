"""Patients, their versioned eye models and their reference poses per fraction.

::

    DATA_DIR/patients/<key>/
      eye-model-v0001.json            one file per version, never rewritten
      reference-f0003-v0001.json      the reference pose of fraction 3, one file per version
      measurements/<pose id>.json     pose measurements (eyeserver.service.verification)

A patient is known by the opaque identifier the oncology information system (OIS) gives it; the
daemon adds a random ``key`` (``pat-<16 hex>``) that names its directory and stands for it in
the audit trail's ``target``, so the identifier never appears in a path or an audit target, and
in the audit file only hashed (:func:`~eyeserver.service.audit.hash_patient_id`, through the
``patient_id`` field of each detail). Every change is one audited store transaction, written
after its file (:meth:`~eyeserver.service.storage.Store.write_document`), so a row never lacks
its file. Nothing here is ever deleted: a new eye model or reference is a new version, and the
newest version is the one in use.

The unit that measures a patient's eye (``unit``, default ``"all"``) is per patient: on a rig
whose units each look at one eye it names the unit on the treated eye's side; in the simulated
room both units look at the one eye, so ``"all"`` (both, interleaved) is right there.
"""

from __future__ import annotations

import json
import logging
import math
import secrets
from collections.abc import Mapping
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Annotated, Any, Literal

from pydantic import ConfigDict, Field, model_validator

from eyeserver.core.validation import NumbersOnly
from eyeserver.errors import EyeserverError
from eyeserver.eye import EyeModel
from eyeserver.service.audit import AuditTrail
from eyeserver.service.storage import Store

__all__ = [
    "DEFAULT_MIN_CONFIDENCE",
    "DEFAULT_TOLERANCE_GAZE_DEG",
    "DEFAULT_TOLERANCE_MM",
    "PATIENT_ID_PATTERN",
    "EllipsoidSpec",
    "Eye",
    "EyeModelSpec",
    "EyeModelVersion",
    "NoReferenceError",
    "Patient",
    "Patients",
    "ReferencePose",
    "ReferencePoseSpec",
    "Tolerances",
    "UnknownPatientError",
]

Eye = Literal["right", "left"]
Vec3 = tuple[float, float, float]

DEFAULT_TOLERANCE_MM = 0.2
"""Largest accepted length of the translation vector, mm (the clip-based practice,
docs/design.md §6)."""

DEFAULT_TOLERANCE_GAZE_DEG = 1.0
"""Largest accepted angle between measured and reference gaze, degrees."""

DEFAULT_MIN_CONFIDENCE = 0.5
"""Smallest fit confidence (0…1) with which a measurement may pass."""

PATIENT_ID_PATTERN = r"^[!-.0-\[\]-~]{1,128}$"
"""Printable ASCII without spaces, ``/`` and ``\\``, 1 to 128 characters."""

_log = logging.getLogger(__name__)


class UnknownPatientError(EyeserverError):
    """No patient has this identifier (HTTP 404). The message does not repeat it: it may reach
    the audit file, where patient identifiers appear only hashed."""


class NoReferenceError(EyeserverError):
    """A fraction has no reference pose yet (HTTP 404)."""


def _now_text() -> str:
    return datetime.now(UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def _finite(values: tuple[float, ...], name: str) -> None:
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"{name} must be finite")


@dataclass(frozen=True)
class Tolerances:
    """What a pose measurement must meet to pass (per patient)."""

    translation_mm: float = DEFAULT_TOLERANCE_MM
    gaze_deg: float = DEFAULT_TOLERANCE_GAZE_DEG
    min_confidence: float = DEFAULT_MIN_CONFIDENCE

    def __post_init__(self) -> None:
        if not (math.isfinite(self.translation_mm) and self.translation_mm > 0):
            raise ValueError(f"translation_mm must be > 0, not {self.translation_mm}")
        if not (math.isfinite(self.gaze_deg) and self.gaze_deg > 0):
            raise ValueError(f"gaze_deg must be > 0, not {self.gaze_deg}")
        if not 0.0 <= self.min_confidence <= 1.0:
            raise ValueError(f"min_confidence must be within 0…1, not {self.min_confidence}")

    def to_dict(self) -> dict[str, float]:
        """As stored and answered."""
        return {"translation_mm": self.translation_mm, "gaze_deg": self.gaze_deg,
                "min_confidence": self.min_confidence}


class EllipsoidSpec(NumbersOnly):
    """The anterior segment as an ellipsoid (from MRI)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    centre_mm: Vec3 = Field((0.0, 0.0, 0.0), description="Centre in the imaging (MRI) frame, "
                            "kept for the record; the fit finds where the eye is in the room.")
    semi_axes_mm: tuple[Annotated[float, Field(gt=5, lt=20)],
                        Annotated[float, Field(gt=5, lt=20)],
                        Annotated[float, Field(gt=5, lt=20)]] = Field(
        description="Semi-axes a, b, c, mm.", examples=[(12.1, 11.9, 12.4)])
    orientation: tuple[Vec3, Vec3, Vec3] = Field(
        ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
        description="Rotation from the ellipsoid's axes to the WCS as three rows; its columns "
        "are the semi-axes' directions. Must be a rotation (orthonormal, determinant +1).")

    @model_validator(mode="after")
    def _a_rotation(self) -> EllipsoidSpec:
        _finite(self.centre_mm, "centre_mm")
        rows = self.orientation
        _finite(tuple(v for row in rows for v in row), "orientation")
        for i in range(3):
            for j in range(3):
                dot = sum(rows[k][i] * rows[k][j] for k in range(3))
                if abs(dot - (1.0 if i == j else 0.0)) > 1e-4:
                    raise ValueError("orientation must be orthonormal (a rotation matrix)")
        (a, b, c), (d, e, f), (g, h, k) = rows
        if a * (e * k - f * h) - b * (d * k - f * g) + c * (d * h - e * g) < 0:
            raise ValueError("orientation must be a rotation (determinant +1), not a reflection")
        return self


class EyeModelSpec(NumbersOnly):
    """A patient's eye model as imported: a sphere, an ellipsoid, or population defaults.

    ``{}`` is the population model: the globe's radius is fitted, cornea 7.8 mm, limbus
    11.7 mm. Give ``globe_radius_mm`` for a spherical globe of known size, or ``ellipsoid`` for
    the MRI-derived anterior segment (not both).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    globe_radius_mm: Annotated[float, Field(gt=5, lt=20)] | None = Field(
        None, description="A spherical globe's radius, mm; null: fitted.", examples=[12.2])
    ellipsoid: EllipsoidSpec | None = Field(None, description="The anterior segment's "
                                            "ellipsoid; null: a sphere.")
    cornea_radius_mm: Annotated[float, Field(gt=4, lt=15)] = Field(
        7.8, description="Anterior corneal radius of curvature, mm.")
    limbus_diameter_mm: Annotated[float, Field(gt=6, lt=16)] = Field(
        11.7, description="Limbus (white-to-white) diameter, mm.")
    globe_sd_mm: Annotated[float, Field(ge=0, lt=2)] | None = Field(
        None, description="The sd of globe_radius_mm or of each ellipsoid semi-axis (the MRI's "
        "measurement error), mm; null: 0.2 mm, the typical MRI error. It moves the fitted "
        "centre along the gaze, counts against a planned reference and cancels from one "
        "captured at set-up with the same model.", examples=[0.1])
    source: Annotated[str, Field(max_length=500)] | None = Field(
        None, description="Where the model comes from (free text, e.g. the MRI study).",
        examples=["MRI 2026-11-02, T2 3D, segmented by J. Doe"])

    @model_validator(mode="after")
    def _consistent(self) -> EyeModelSpec:
        if self.globe_radius_mm is not None and self.ellipsoid is not None:
            raise ValueError("give globe_radius_mm or ellipsoid, not both")
        if self.globe_sd_mm is not None and self.population:
            raise ValueError("globe_sd_mm is the error of globe_radius_mm or of the ellipsoid: "
                             "give one of them with it")
        half = self.limbus_diameter_mm / 2
        smallest = min([self.cornea_radius_mm]
                       + ([self.globe_radius_mm] if self.globe_radius_mm else [])
                       + (list(self.ellipsoid.semi_axes_mm) if self.ellipsoid else []))
        if half >= smallest:
            raise ValueError("the limbus must be narrower than the cornea and the globe")
        return self

    @property
    def population(self) -> bool:
        """True when nothing patient-specific was given about the globe's shape."""
        return self.globe_radius_mm is None and self.ellipsoid is None

    def to_eye_model(self) -> EyeModel:
        """The pipeline's :class:`~eyeserver.eye.fit.EyeModel`."""
        ellipsoid = self.ellipsoid
        return EyeModel(
            globe_radius_mm=self.globe_radius_mm,
            globe_semi_axes_mm=None if ellipsoid is None else ellipsoid.semi_axes_mm,
            orientation=None if ellipsoid is None else ellipsoid.orientation,
            cornea_radius_mm=self.cornea_radius_mm, limbus_diameter_mm=self.limbus_diameter_mm,
            **({} if self.globe_sd_mm is None else {"globe_sd_mm": self.globe_sd_mm}))


class ReferencePoseSpec(NumbersOnly):
    """A reference pose in the WCS, from the treatment plan."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    centre_mm: Vec3 = Field(description="Globe centre, mm, WCS.", examples=[(0.0, 0.0, -10.0)])
    gaze: Vec3 = Field(description="Gaze direction (normalised when stored), WCS.",
                       examples=[(0.0, 0.0, 1.0)])
    limbus_centre_mm: Vec3 | None = Field(None, description="Limbus centre, mm, WCS, if "
                                          "planned.")
    plan: Annotated[str, Field(max_length=500)] | None = Field(
        None, description="Which plan it comes from (free text).", examples=["plan 4, v2"])

    @model_validator(mode="after")
    def _finite_and_unit(self) -> ReferencePoseSpec:
        _finite(self.centre_mm, "centre_mm")
        _finite(self.gaze, "gaze")
        if self.limbus_centre_mm is not None:
            _finite(self.limbus_centre_mm, "limbus_centre_mm")
        if math.hypot(*self.gaze) < 1e-9:
            raise ValueError("gaze must not be the zero vector")
        return self

    def pose(self) -> dict[str, Any]:
        """``centre_mm``, unit ``gaze`` and ``limbus_centre_mm`` as stored."""
        norm = math.hypot(*self.gaze)
        return {"centre_mm": list(self.centre_mm), "gaze": [g / norm for g in self.gaze],
                "limbus_centre_mm": None if self.limbus_centre_mm is None
                else list(self.limbus_centre_mm)}


@dataclass(frozen=True)
class Patient:
    """A patient as the daemon knows it; ``eye_model_version`` None: population defaults."""

    patient_id: str
    key: str
    eye: Eye
    unit: str
    tolerances: Tolerances
    created: str
    updated: str
    eye_model_version: int | None


@dataclass(frozen=True)
class EyeModelVersion:
    """One stored version of a patient's eye model."""

    patient_id: str
    version: int
    created: str
    actor: str
    model: EyeModelSpec


@dataclass(frozen=True)
class ReferencePose:
    """One stored version of a fraction's reference pose.

    ``source`` is ``plan`` (imported) or ``capture`` (measured at set-up, ``evidence`` then
    names the capture, calibration, eye model version and holds the fit).
    """

    patient_id: str
    fraction: int
    version: int
    created: str
    actor: str
    source: Literal["plan", "capture"]
    pose: dict[str, Any]
    plan: str | None
    evidence: dict[str, Any] | None


class Patients:
    """The patients of one store, with their eye models and reference poses.

    Parameters
    ----------
    store : Store
        The open store (its tables ``patients``, ``eye_models``, ``pose_references``).
    audit : AuditTrail
        Where failed changes are recorded (successful ones come through the store's rows).

    All methods block (disk, SQLite) and are thread-safe.
    """

    def __init__(self, store: Store, audit: AuditTrail) -> None:
        self.store = store
        self.audit = audit

    # --- patients ---------------------------------------------------------------------------

    def put(self, patient_id: str, *, eye: Eye, unit: str = "all",
            tolerances: Tolerances | None = None, actor: str) -> tuple[Patient, bool]:
        """Create or update a patient (eye, measuring unit, tolerances); audited.

        Returns the patient and whether it was created.
        """
        chosen = tolerances or Tolerances()
        now = _now_text()
        settings = json.dumps(chosen.to_dict())
        with self.store.transaction() as db:
            row = db.execute("SELECT key FROM patients WHERE patient_id = ?",
                             (patient_id,)).fetchone()
            created = row is None
            key = f"pat-{secrets.token_hex(8)}" if created else str(row[0])
            if created:
                db.execute("INSERT INTO patients (patient_id, key, eye, unit, settings, created, "
                           "updated) VALUES (?, ?, ?, ?, ?, ?, ?)",
                           (patient_id, key, eye, unit, settings, now, now))
            else:
                db.execute("UPDATE patients SET eye = ?, unit = ?, settings = ?, updated = ? "
                           "WHERE patient_id = ?", (eye, unit, settings, now, patient_id))
            self.store.audit_in(db, actor, "create_patient" if created else "update_patient",
                                key, {"patient_id": patient_id, "eye": eye, "unit": unit,
                                      "tolerances": chosen.to_dict()})
        _log.info("patient stored", extra={"patient_key": key, "new_patient": created,
                                           "actor": actor})
        return self.get(patient_id), created

    def get(self, patient_id: str) -> Patient:
        """One patient; :class:`UnknownPatientError` when there is none with this id."""
        rows = self.store.query(
            "SELECT p.patient_id, p.key, p.eye, p.unit, p.settings, p.created, p.updated, "
            "(SELECT MAX(version) FROM eye_models m WHERE m.patient_id = p.patient_id) "
            "FROM patients p WHERE p.patient_id = ?", (patient_id,))
        if not rows:
            raise UnknownPatientError("no patient with this id (PUT /api/v1/patients/{id} "
                                      "first)")
        pid, key, eye, unit, settings, created, updated, version = rows[0]
        return Patient(pid, key, eye, unit, Tolerances(**json.loads(settings)), created,
                       updated, None if version is None else int(version))

    # --- eye models -------------------------------------------------------------------------

    def add_eye_model(self, patient_id: str, model: EyeModelSpec, *, actor: str
                      ) -> EyeModelVersion:
        """Store ``model`` as the patient's next eye-model version (the one used from now)."""
        patient = self.get(patient_id)
        with self.store.transaction() as db:
            # Inside the write transaction: two imports at once get different versions.
            newest = db.execute("SELECT MAX(version) FROM eye_models WHERE patient_id = ?",
                                (patient_id,)).fetchone()[0]
            version = 1 + int(newest or 0)
            created = _now_text()
            relative = f"patients/{patient.key}/eye-model-v{version:04d}.json"
            document = {"format": "eyeserver.eye-model/1", "patient_key": patient.key,
                        "version": version, "created": created, "actor": actor,
                        "model": model.model_dump(mode="json")}
            self.store.write_document(relative, json.dumps(document, indent=2) + "\n")
            db.execute("INSERT INTO eye_models (patient_id, version, created, actor, file) "
                       "VALUES (?, ?, ?, ?, ?)", (patient_id, version, created, actor, relative))
            self.store.audit_in(db, actor, "add_eye_model", patient.key,
                                {"patient_id": patient_id, "version": version,
                                 "population": model.population})
        return EyeModelVersion(patient_id, version, created, actor, model)

    def eye_models(self, patient_id: str) -> list[EyeModelVersion]:
        """Every eye-model version of a patient, oldest first."""
        self.get(patient_id)
        rows = self.store.query("SELECT version, file FROM eye_models WHERE patient_id = ? "
                                "ORDER BY version", (patient_id,))
        return [self._eye_model(patient_id, int(version), file) for version, file in rows]

    def eye_model(self, patient_id: str, version: int | None = None) -> EyeModelVersion | None:
        """One version (default: the newest) of a patient's eye model; None when the patient
        has none (population defaults apply) or has no such version."""
        patient = self.get(patient_id)
        chosen = patient.eye_model_version if version is None else version
        if chosen is None:
            return None
        rows = self.store.query("SELECT file FROM eye_models WHERE patient_id = ? AND "
                                "version = ?", (patient_id, chosen))
        return self._eye_model(patient_id, chosen, rows[0][0]) if rows else None

    def _eye_model(self, patient_id: str, version: int, file: str) -> EyeModelVersion:
        document = json.loads(self.store.read_document(file))
        return EyeModelVersion(patient_id, version, document["created"], document["actor"],
                               EyeModelSpec.model_validate(document["model"]))

    # --- reference poses --------------------------------------------------------------------

    def set_reference(self, patient_id: str, fraction: int, pose: Mapping[str, Any], *,
                      source: Literal["plan", "capture"], actor: str, plan: str | None = None,
                      evidence: Mapping[str, Any] | None = None) -> ReferencePose:
        """Store the next version of a fraction's reference pose (the one used from now)."""
        patient = self.get(patient_id)
        with self.store.transaction() as db:
            newest = db.execute("SELECT MAX(version) FROM pose_references WHERE patient_id = ? "
                                "AND fraction = ?", (patient_id, fraction)).fetchone()[0]
            version = 1 + int(newest or 0)
            created = _now_text()
            relative = f"patients/{patient.key}/reference-f{fraction:04d}-v{version:04d}.json"
            document = {"format": "eyeserver.reference-pose/1", "patient_key": patient.key,
                        "fraction": fraction, "version": version, "created": created,
                        "actor": actor, "source": source, "plan": plan, "pose": dict(pose),
                        "evidence": None if evidence is None else dict(evidence)}
            self.store.write_document(relative, json.dumps(document, indent=2) + "\n")
            db.execute("INSERT INTO pose_references (patient_id, fraction, version, created, "
                       "actor, source, file) VALUES (?, ?, ?, ?, ?, ?, ?)",
                       (patient_id, fraction, version, created, actor, source, relative))
            self.store.audit_in(db, actor, "set_reference_pose", patient.key,
                                {"patient_id": patient_id, "fraction": fraction,
                                 "version": version, "source": source,
                                 "capture_id": (evidence or {}).get("capture_id")})
        return self._reference(patient_id, relative)

    def reference(self, patient_id: str, fraction: int) -> ReferencePose:
        """The newest reference pose of a fraction; :class:`NoReferenceError` without one."""
        self.get(patient_id)
        rows = self.store.query("SELECT file FROM pose_references WHERE patient_id = ? AND "
                                "fraction = ? ORDER BY version DESC LIMIT 1",
                                (patient_id, fraction))
        if not rows:
            raise NoReferenceError(
                f"fraction {fraction} has no reference pose: import the plan's "
                f"(PUT …/fractions/{fraction}/reference) or capture one at set-up "
                f"(POST …/fractions/{fraction}/reference/capture)")
        return self._reference(patient_id, rows[0][0])

    def references(self, patient_id: str, fraction: int) -> list[ReferencePose]:
        """Every version of a fraction's reference pose, oldest first."""
        self.get(patient_id)
        rows = self.store.query("SELECT file FROM pose_references WHERE patient_id = ? AND "
                                "fraction = ? ORDER BY version", (patient_id, fraction))
        return [self._reference(patient_id, file) for (file,) in rows]

    def reference_captures(self) -> dict[str, str]:
        """The captures that captured reference poses were measured on → which reference
        (fraction and version; no patient id: this goes into error messages)."""
        held = {}
        for fraction, version, file in self.store.query(
                "SELECT fraction, version, file FROM pose_references WHERE source = 'capture'"):
            evidence = json.loads(self.store.read_document(file)).get("evidence") or {}
            if evidence.get("capture_id"):
                held[str(evidence["capture_id"])] = (
                    f"the evidence of version {version} of a reference pose of fraction "
                    f"{fraction}")
        return held

    def _reference(self, patient_id: str, file: str) -> ReferencePose:
        d = json.loads(self.store.read_document(file))
        return ReferencePose(patient_id, int(d["fraction"]), int(d["version"]), d["created"],
                             d["actor"], d["source"], d["pose"], d.get("plan"), d.get("evidence"))
