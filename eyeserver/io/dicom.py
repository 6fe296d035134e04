"""DICOM for position verification: a pose measurement out, the planned eye in (issue 40).

Export
    Each stored pose measurement (:mod:`eyeserver.service.verification`) becomes two objects in
    one Frame of Reference per patient and fraction — the room's WCS at that fraction's set-up,
    mm, with a UID derived from the daemon's patient key and the fraction, so every export of
    a fraction shares it (:func:`frame_of_reference_uid`):

    * a **Spatial Registration** (SOP Class 1.2.840.10008.5.1.4.1.1.66.1, PS3.3 A.39): one
      Registration Sequence item in that frame whose RIGID 4 × 4 matrix is the eye's motion
      from the fraction's reference pose to the measured pose (:func:`rigid_motion`),
      ``x_measured = M · x_reference`` (homogeneous, mm); the correction that brings the eye
      back is ``M⁻¹``. Both poses lie in the same WCS, so the item's frame is the object's own:
      the matrix is a motion within the frame, not a change of frame.
    * a **Surface Segmentation** (1.2.840.10008.5.1.4.1.1.66.5, A.57) in the same frame:
      segment 1 the measured points near the eye (the capture's fused cloud within
      :data:`SURFACE_MARGIN_MM` of the fitted globe, as vertices: a point cloud has no mesh),
      segment 2 the fitted globe of the measured pose as a closed triangulated sphere. Both are
      coded as the eye (SNOMED CT 81745001 "Eye", 79652003 "Eyeball" for the globe) with the
      treated eye's laterality.

    UIDs of studies, series and instances are derived the same way (study: patient and
    fraction; series and instance: the measurement), so exporting a measurement twice gives the
    same objects rather than two look-alikes. The patient is named as the daemon stores it:
    Patient ID is the OIS's id, Patient's Name empty (the daemon stores no name).

Import
    :func:`read_plan` reads the planned eye from an **RT Structure Set** (:func:`read_planned_eye`:
    the globe, and the cornea and limbus where ROIs for them exist, fitted to their contour
    points) and, from a **Spatial Registration** (:func:`read_registration`), the rigid
    transform from the structure set's frame to the room's WCS (the registration's own
    frame). It answers the fields of an eye model and, given the registration and a gaze
    (cornea or limbus ROI), of a planned reference pose in the WCS.

Every attribute written and read is listed where it is set; the objects pass dicom3tools'
``dciodvfy`` without errors (tests/test_dicom.py). Readers raise
:class:`~eyeserver.errors.FormatError` naming the object and the attribute.
"""

from __future__ import annotations

import io
import math
import platform
import re
import uuid
import zipfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal

import numpy as np
import numpy.typing as npt
from pydicom import dcmread
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.multival import MultiValue
from pydicom.uid import UID, ExplicitVRLittleEndian
from pydicom.valuerep import format_number_as_ds

from eyeserver.errors import FormatError, StateConflictError
from eyeserver.io.ply import read_ply

__all__ = [
    "DICOM_OBJECTS",
    "RT_STRUCTURE_SET",
    "SPATIAL_REGISTRATION",
    "SURFACE_MARGIN_MM",
    "SURFACE_SEGMENTATION",
    "DicomObject",
    "Equipment",
    "NoReferencePoseError",
    "PlanImport",
    "PlannedEye",
    "Registration",
    "derived_uid",
    "dicom_objects",
    "encode",
    "export_measurement",
    "frame_of_reference_uid",
    "read_dataset",
    "read_plan",
    "read_planned_eye",
    "read_registration",
    "registration_dataset",
    "rigid_motion",
    "surface_dataset",
    "zip_objects",
]

F64 = npt.NDArray[np.float64]
Vec3 = tuple[float, float, float]
DicomObject = Literal["registration", "surface"]

SPATIAL_REGISTRATION = "1.2.840.10008.5.1.4.1.1.66.1"
"""SOP Class UID of the Spatial Registration Storage."""
SURFACE_SEGMENTATION = "1.2.840.10008.5.1.4.1.1.66.5"
"""SOP Class UID of the Surface Segmentation Storage."""
RT_STRUCTURE_SET = "1.2.840.10008.5.1.4.1.1.481.3"
"""SOP Class UID of the RT Structure Set Storage."""

DICOM_OBJECTS: dict[DicomObject, str] = {"registration": "registration.dcm",
                                         "surface": "surface.dcm"}
"""The exported objects and their file names in the zip."""

SURFACE_MARGIN_MM = 5.0
"""The measured points exported lie within the fitted globe's radius plus this of its centre
(mm): the globe's visible front with the lids and lashes on it, not the face around."""

_MIN_SURFACE_POINTS = 10
"""Fewer measured points near the eye than this: segment 1 is left out (said in its place)."""

_ICOSPHERE_SUBDIVISIONS = 3
"""The fitted globe's mesh: an icosahedron subdivided 3 times, 642 vertices and 1280
triangles, within 0.1 mm of a 12 mm sphere."""

# A fixed namespace, uuid5(NAMESPACE_URL, "urn:eyeserver:dicom"): the same names give the same
# UIDs on every daemon and every run.
_UID_NAMESPACE = uuid.UUID("e18f52f5-3e70-5f39-ad70-3fbe80985866")

Code = tuple[str, str, str]  # (Code Value, Coding Scheme Designator, Code Meaning)
_EYE: Code = ("81745001", "SCT", "Eye")
_EYEBALL: Code = ("79652003", "SCT", "Eyeball")
_CORNEA: Code = ("28726007", "SCT", "Cornea")
_ANATOMICAL_STRUCTURE: Code = ("91723000", "SCT", "Anatomical Structure")
_LATERALITY: dict[str, Code] = {"right": ("24028007", "SCT", "Right"),
                                "left": ("7771000", "SCT", "Left")}
_IMAGE_CONTENT_ALIGNMENT: Code = ("125024", "DCM", "Image Content-based Alignment")  # CID 7100
# CID 7162, the families of surface algorithms: the measured segment is the cloud's points
# within a distance of the fitted globe (a neighbourhood), the globe a fitted model.
_NEIGHBORHOOD_ANALYSIS: Code = ("123101", "DCM", "Neighborhood Analysis")
_MODEL_FIT: Code = ("123111", "DCM", "Deformable Models")


def derived_uid(*parts: str) -> str:
    """A UID from a name: ``2.25.<the name's UUID (version 5) as a decimal integer>``.

    ITU-T X.667's ``2.25`` arc takes any UUID as an integer, at most 44 characters here (the
    limit is 64); the same parts give the same UID everywhere, different parts a different one
    with the chance of a 122-bit hash collision.

    >>> derived_uid("example") == derived_uid("example") != derived_uid("example", "2")
    True
    """
    return f"2.25.{uuid.uuid5(_UID_NAMESPACE, '/'.join(parts)).int}"


def frame_of_reference_uid(patient_key: str, fraction: int) -> str:
    """The Frame of Reference UID of a patient's fraction: the room's WCS at its set-up.

    From the daemon's opaque patient key (``pat-…``, random, stable), not the OIS's id, so
    the UID cannot be traced back to the patient without the daemon's store.
    """
    return derived_uid("frame-of-reference", patient_key, str(int(fraction)))


_IMPLEMENTATION_UID = derived_uid("implementation")


@dataclass(frozen=True)
class Equipment:
    """What made the objects (General and Enhanced General Equipment modules).

    ``device_serial_number`` is type 1 in the Enhanced General Equipment module; the daemon has
    no serial number of its own, so :meth:`this_host` names the computer it runs on.
    """

    software_version: str
    device_serial_number: str
    manufacturer: str = "eyeserver"
    model_name: str = "eyeserver"

    @classmethod
    def this_host(cls, software_version: str) -> Equipment:
        """This daemon on this computer (its host name as the serial number)."""
        return cls(software_version, (platform.node() or "unknown")[:64])


class NoReferencePoseError(StateConflictError):
    """A measurement has no reference pose to register against (HTTP 409)."""


# --- geometry -----------------------------------------------------------------------------------


def _unit(vector: npt.ArrayLike, name: str) -> F64:
    v = np.asarray(vector, dtype=np.float64)
    norm = float(np.linalg.norm(v))
    if v.shape != (3,) or not math.isfinite(norm) or norm < 1e-12:
        raise ValueError(f"{name} must be a finite non-zero 3-vector")
    return v / norm


def _rotation_between(a: F64, b: F64) -> F64:
    """The smallest rotation turning unit vector ``a`` onto unit vector ``b`` (3 × 3)."""
    axis = np.cross(a, b)
    sine, cosine = float(np.linalg.norm(axis)), float(np.dot(a, b))
    if sine < 1e-12:
        if cosine > 0:
            return np.eye(3)
        # Opposite: half a turn about any axis perpendicular to a.
        helper = np.eye(3)[int(np.argmin(np.abs(a)))]
        axis = np.cross(a, helper) / np.linalg.norm(np.cross(a, helper))
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    k = axis / sine
    cross = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    angle = math.atan2(sine, cosine)  # Rodrigues' formula
    rotation: F64 = np.eye(3) + math.sin(angle) * cross + (1.0 - math.cos(angle)) * (cross @ cross)
    return rotation


def rigid_motion(reference_centre: npt.ArrayLike, reference_gaze: npt.ArrayLike,
                 measured_centre: npt.ArrayLike, measured_gaze: npt.ArrayLike) -> F64:
    """The eye's rigid motion from a reference pose to a measured pose, 4 × 4 homogeneous, mm.

    ``M = [[R, t], [0, 1]]`` with ``R`` the smallest rotation turning the reference gaze onto
    the measured one and ``t = c_measured − R · c_reference``, so that ``M`` carries the
    reference globe centre onto the measured one and ``R · g_reference = g_measured``. The eye's
    roll about its gaze (torsion) is not measured against the reference and is taken as 0: of
    the six degrees of freedom, five are measured.

    >>> m = rigid_motion((0, 0, -10), (0, 0, 1), (0.1, 0.0, -9.8), (0, 0, 1))
    >>> np.round(m[:3, 3], 6).tolist(), bool(np.allclose(m[:3, :3], np.eye(3)))
    ([0.1, 0.0, 0.2], True)
    """
    rotation = _rotation_between(_unit(reference_gaze, "reference_gaze"),
                                 _unit(measured_gaze, "measured_gaze"))
    matrix = np.eye(4)
    matrix[:3, :3] = rotation
    matrix[:3, 3] = (np.asarray(measured_centre, dtype=np.float64)
                     - rotation @ np.asarray(reference_centre, dtype=np.float64))
    if not np.all(np.isfinite(matrix)):
        raise ValueError("the poses must be finite")
    return matrix


def _icosphere(subdivisions: int) -> tuple[F64, npt.NDArray[np.int64]]:
    """A unit sphere's vertices (V, 3) and outward counter-clockwise triangles (T, 3, 0-based)."""
    t = (1.0 + math.sqrt(5.0)) / 2.0
    vertices = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t),
                (0, -1, -t), (0, 1, -t), (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]
    faces = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4),
             (11, 10, 2), (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8),
             (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    points = [np.asarray(v, dtype=np.float64) / np.linalg.norm(v) for v in vertices]
    for _ in range(subdivisions):
        middle: dict[tuple[int, int], int] = {}  # an edge's new vertex, shared by its faces
        finer = []
        for a, b, c in faces:
            ab, bc, ca = (_midpoint(points, middle, a, b), _midpoint(points, middle, b, c),
                          _midpoint(points, middle, c, a))
            finer += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = finer
    return np.asarray(points), np.asarray(faces, dtype=np.int64)


def _midpoint(points: list[F64], middle: dict[tuple[int, int], int], i: int, j: int) -> int:
    """The index of the unit vector halfway between points ``i`` and ``j`` (added once)."""
    key = (min(i, j), max(i, j))
    if key not in middle:
        m = points[i] + points[j]
        points.append(m / np.linalg.norm(m))
        middle[key] = len(points) - 1
    return middle[key]


def _fit_sphere(points: F64) -> tuple[F64, float, float]:
    """Algebraic (Kåsa) least-squares sphere: centre, radius and the points' RMS distance from
    it (mm). Exact for points on a sphere; contours cover the whole globe, so its small-cap
    bias does not arise."""
    mean = points.mean(axis=0)
    q = points - mean  # centred: well conditioned far from the origin
    design = np.column_stack([2.0 * q, np.ones(len(q))])
    solution, *_ = np.linalg.lstsq(design, np.einsum("ij,ij->i", q, q), rcond=None)
    centre = solution[:3]
    radius = math.sqrt(max(float(solution[3] + centre @ centre), 0.0))
    residual = np.linalg.norm(q - centre, axis=1) - radius
    return centre + mean, radius, float(np.sqrt(np.mean(residual**2)))


def _fit_ellipsoid(points: F64) -> tuple[F64, F64, F64]:
    """Algebraic least-squares ellipsoid of any orientation: centre (mm), semi-axes (mm, largest
    first) and their directions as the columns of a rotation (determinant +1).

    The quadric ``xᵀAx + 2gᵀx = 1`` in coordinates centred on the points' mean (inside the
    globe, so the constant cannot vanish) and scaled to unit RMS; ``ValueError`` when the
    quadric is not an ellipsoid (too few or coplanar points).
    """
    mean = points.mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum((points - mean) ** 2, axis=1)))) or 1.0
    x, y, z = ((points - mean) / scale).T
    design = np.column_stack([x * x, y * y, z * z, 2 * x * y, 2 * x * z, 2 * y * z,
                              2 * x, 2 * y, 2 * z])
    v, *_ = np.linalg.lstsq(design, np.ones(len(x)), rcond=None)
    quadric = np.array([[v[0], v[3], v[4]], [v[3], v[1], v[5]], [v[4], v[5], v[2]]])
    centre = -np.linalg.solve(quadric, v[6:9])
    values, vectors = np.linalg.eigh(quadric / (1.0 + centre @ quadric @ centre))
    if not np.all(values > 0):
        raise ValueError("the points do not lie on an ellipsoid")
    if np.linalg.det(vectors) < 0:
        vectors[:, 2] = -vectors[:, 2]
    return centre * scale + mean, scale / np.sqrt(values), vectors


def _fit_circle(points: F64) -> tuple[F64, F64, float]:
    """A circle in space: centre (mm), the unit normal of its plane and its radius (mm), from
    the points' best plane (SVD) and an algebraic circle in it."""
    mean = points.mean(axis=0)
    _, _, axes = np.linalg.svd(points - mean)
    u, w, normal = axes
    q = np.column_stack([(points - mean) @ u, (points - mean) @ w])
    design = np.column_stack([2.0 * q, np.ones(len(q))])
    solution, *_ = np.linalg.lstsq(design, np.einsum("ij,ij->i", q, q), rcond=None)
    centre = solution[:2]
    radius = math.sqrt(max(float(solution[2] + centre @ centre), 0.0))
    return mean + centre[0] * u + centre[1] * w, normal, radius


def _transformed(matrix: F64, point: Sequence[float] | F64) -> F64:
    return np.asarray(matrix[:3, :3] @ np.asarray(point, dtype=np.float64) + matrix[:3, 3])


# --- writing ------------------------------------------------------------------------------------


def _ds(value: float) -> str:
    """A Decimal String of at most 16 characters for a float (DS's limit)."""
    return str(format_number_as_ds(float(value)))


def _code(code: Code) -> Dataset:
    item = Dataset()
    item.CodeValue, item.CodingSchemeDesignator, item.CodeMeaning = code
    return item


def _date_time(text: str, source: str, field: str) -> datetime:
    try:
        moment = datetime.fromisoformat(text.replace("Z", "+00:00"))
    except (TypeError, ValueError) as exc:
        raise FormatError(source, field, f"not an ISO 8601 time: {text!r}") from exc
    return (moment if moment.tzinfo else moment.replace(tzinfo=UTC)).astimezone(UTC)


@dataclass(frozen=True)
class _Measured:
    """What an export takes from a stored measurement document."""

    id: str
    patient_id: str
    fraction: int
    eye: Literal["right", "left"]
    created: datetime
    actor: str
    passed: bool
    length_mm: float
    gaze_deg: float
    centre: F64
    gaze: F64
    radius: float
    reference_centre: F64
    reference_gaze: F64
    reference_version: int
    cloud_points: int | None


def _vector(value: Any, source: str, field: str) -> F64:
    try:
        vector = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise FormatError(source, field, "must be three numbers") from exc
    if vector.shape != (3,) or not np.all(np.isfinite(vector)):
        raise FormatError(source, field, "must be three finite numbers")
    return vector


def _measured(document: Mapping[str, Any]) -> _Measured:
    """The fields of a pose measurement (``GET /api/v1/pose/measurements/{id}``) an export
    needs; :class:`NoReferencePoseError` without a reference pose."""
    source = f"pose measurement {document.get('id', '?')}"
    reference = document.get("reference")
    reference = reference if isinstance(reference, Mapping) else {}
    reference_pose = reference.get("pose")
    if not isinstance(reference_pose, Mapping) or reference_pose.get("gaze") is None:
        raise NoReferencePoseError(
            f"{source} has no reference pose to register against: a spatial registration "
            "needs the fraction's reference (set one, then measure again)")
    try:
        pose, deviation = document["pose"], document["deviation"]
        eye = document["eye"]
        if eye not in ("right", "left"):
            raise FormatError(source, "eye", f"must be 'right' or 'left', not {eye!r}")
        evidence = document.get("evidence") or {}
        cloud_points = evidence.get("cloud_points")
        return _Measured(
            id=str(document["id"]), patient_id=str(document["patient_id"]),
            fraction=int(document["fraction"]), eye=eye,
            created=_date_time(document["created"], source, "created"),
            actor=str(document.get("actor") or ""), passed=bool(document["passed"]),
            length_mm=float(deviation["length_mm"]), gaze_deg=float(deviation["gaze_deg"]),
            centre=_vector(pose["centre_mm"], source, "pose.centre_mm"),
            gaze=_vector(pose["gaze"], source, "pose.gaze"),
            radius=float(pose["globe_radius_mm"]),
            reference_centre=_vector(reference_pose["centre_mm"], source,
                                     "reference.pose.centre_mm"),
            reference_gaze=_vector(reference_pose["gaze"], source, "reference.pose.gaze"),
            reference_version=int(reference.get("version") or 0),
            cloud_points=None if cloud_points is None else int(cloud_points))
    except (KeyError, TypeError, ValueError) as exc:
        raise FormatError(source, None, f"not a pose measurement: {exc}") from exc


def _common(ds: Dataset, measured: _Measured, *, patient_key: str, equipment: Equipment,
            sop_class: str, kind: str, modality: str, series_number: int,
            series_description: str, series_laterality: bool) -> None:
    """The modules both objects share: SOP Common, Patient, General Study, General Series,
    Frame of Reference, General Equipment (and the content date and time)."""
    date, time = measured.created.strftime("%Y%m%d"), measured.created.strftime("%H%M%S.%f")
    # SOP Common: UTF-8 (plan names and actors may not be ASCII), times in UTC said so.
    ds.SpecificCharacterSet = "ISO_IR 192"
    ds.SOPClassUID = sop_class
    ds.SOPInstanceUID = derived_uid("instance", measured.id, kind)
    ds.InstanceCreationDate, ds.InstanceCreationTime = date, time
    ds.TimezoneOffsetFromUTC = "+0000"
    # Patient: as the daemon stores it (no name, birth date or sex: type 2, empty).
    ds.PatientName = ""
    ds.PatientID = measured.patient_id
    ds.PatientBirthDate = ""
    ds.PatientSex = ""
    # General Study: one study per patient and fraction.
    ds.StudyInstanceUID = derived_uid("study", patient_key, str(measured.fraction))
    ds.StudyDate, ds.StudyTime = date, time
    ds.ReferringPhysicianName = ""
    ds.StudyID = f"F{measured.fraction}"
    ds.AccessionNumber = ""
    ds.StudyDescription = f"Eye position, fraction {measured.fraction}"
    # General Series (+ the modality's series module): laterality from the patient's record.
    ds.Modality = modality
    ds.SeriesInstanceUID = derived_uid("series", measured.id, kind)
    ds.SeriesNumber = series_number
    ds.SeriesDate, ds.SeriesTime = date, time
    ds.SeriesDescription = series_description
    ds.BodyPartExamined = "EYE"
    if series_laterality:
        # Type 2C, for a paired body part. Not in a segmentation, whose segments carry it
        # (Anatomic Region and Segmented Property Type Modifier): dciodvfy refuses it there.
        ds.Laterality = "R" if measured.eye == "right" else "L"
    # Frame of Reference: the fraction's set-up in the room's WCS.
    ds.FrameOfReferenceUID = frame_of_reference_uid(patient_key, measured.fraction)
    ds.PositionReferenceIndicator = ""
    # General Equipment.
    ds.Manufacturer = equipment.manufacturer
    ds.ManufacturerModelName = equipment.model_name
    ds.DeviceSerialNumber = equipment.device_serial_number
    ds.SoftwareVersions = equipment.software_version
    # Content date and time (both content modules): when the measurement was made.
    ds.ContentDate, ds.ContentTime = date, time
    ds.InstanceNumber = 1
    # The token's name (e.g. "physicist", "dr-weber") as the family name: dciodvfy warns of a
    # "Retired Person Name form" for any name without a ^, the one warning it gives here.
    ds.ContentCreatorName = measured.actor[:64]


def registration_dataset(measurement: Mapping[str, Any], *, patient_key: str,
                         equipment: Equipment) -> Dataset:
    """The Spatial Registration of a stored pose measurement: the eye's rigid motion from the
    fraction's reference pose to the measured pose (:func:`rigid_motion`) in the fraction's
    frame.

    ``measurement`` is the stored document (``GET /api/v1/pose/measurements/{id}``);
    ``patient_key`` the daemon's key of its patient (:func:`frame_of_reference_uid`).
    :class:`NoReferencePoseError` when it has no reference pose.
    """
    measured = _measured(measurement)
    ds = Dataset()
    _common(ds, measured, patient_key=patient_key, equipment=equipment,
            sop_class=SPATIAL_REGISTRATION, kind="registration", modality="REG",
            series_number=1, series_description="Eye position verification: pose correction",
            series_laterality=True)
    matrix = rigid_motion(measured.reference_centre, measured.reference_gaze, measured.centre,
                          measured.gaze)
    # Content Identification macro: Content Label is a CS (16 characters, upper case).
    ds.ContentLabel = "EYE_POSE"
    verdict = "passed" if measured.passed else "failed"
    ds.ContentDescription = (f"Eye moved {measured.length_mm:.3f} mm, {measured.gaze_deg:.2f} "
                             f"deg; {verdict}")[:64]
    transform = Dataset()
    transform.FrameOfReferenceTransformationMatrixType = "RIGID"
    transform.FrameOfReferenceTransformationMatrix = [_ds(v) for v in matrix.ravel()]
    registration = Dataset()
    registration.FrameOfReferenceTransformationComment = (
        f"x_measured = M x_reference (ref v{measured.reference_version})")[:64]
    registration.RegistrationTypeCodeSequence = [_code(_IMAGE_CONTENT_ALIGNMENT)]
    registration.MatrixSequence = [transform]
    item = Dataset()
    item.FrameOfReferenceUID = ds.FrameOfReferenceUID
    item.MatrixRegistrationSequence = [registration]
    ds.RegistrationSequence = [item]
    return ds


def _cielab(lightness: float, a: float, b: float) -> list[int]:
    """PS3.3 C.10.7.1.1's scaled CIELab: L* 0–100 and a*, b* −128…127 onto 0…65535."""
    return [round(lightness * 65535 / 100), round((a + 128) * 65535 / 255),
            round((b + 128) * 65535 / 255)]


def _algorithm(code: Code, name: str, version: str, parameters: str | None = None) -> Dataset:
    item = Dataset()
    item.AlgorithmFamilyCodeSequence = [_code(code)]
    item.AlgorithmName = name
    item.AlgorithmVersion = version
    if parameters is not None:
        item.AlgorithmParameters = parameters
    return item


def _segment(number: int, label: str, description: str, property_type: Code, eye: str,
             algorithm: Dataset) -> Dataset:
    """A Segment Sequence item (Segment Description macro and the surface it references)."""
    laterality = _code(_LATERALITY[eye])
    segment = Dataset()
    segment.SegmentNumber = number
    segment.SegmentLabel = label
    segment.SegmentDescription = description
    segment.SegmentAlgorithmType = "AUTOMATIC"
    segment.SegmentedPropertyCategoryCodeSequence = [_code(_ANATOMICAL_STRUCTURE)]
    property_item = _code(property_type)
    property_item.SegmentedPropertyTypeModifierCodeSequence = [laterality]
    segment.SegmentedPropertyTypeCodeSequence = [property_item]
    region = _code(_EYE)
    region.AnatomicRegionModifierSequence = [_code(_LATERALITY[eye])]
    segment.AnatomicRegionSequence = [region]
    segment.SurfaceCount = 1
    reference = Dataset()
    reference.ReferencedSurfaceNumber = number
    reference.SegmentSurfaceGenerationAlgorithmIdentificationSequence = [algorithm]
    reference.SegmentSurfaceSourceInstanceSequence = []
    segment.ReferencedSurfaceSequence = [reference]
    return segment


def _surface(number: int, points: F64, *, presentation: Literal["POINTS", "SURFACE"],
             triangles: npt.NDArray[np.int64] | None, comment: str, colour: list[int],
             opacity: float) -> Dataset:
    """A Surface Sequence item: its points (float32, mm) and mesh primitives (1-based indices:
    vertices for a point cloud, triangles for a closed mesh)."""
    surface = Dataset()
    surface.SurfaceNumber = number
    surface.SurfaceComments = comment
    # Not modified after it was made: choosing the cloud's points near the eye is how the
    # segment's surface is made (its generation algorithm says so), not a later decimation.
    surface.SurfaceProcessing = "NO"
    surface.RecommendedDisplayGrayscaleValue = 0xFFFF
    surface.RecommendedDisplayCIELabValue = colour
    surface.RecommendedPresentationOpacity = opacity
    surface.RecommendedPresentationType = presentation
    closed = triangles is not None
    surface.FiniteVolume = "YES" if closed else "NO"
    surface.Manifold = "YES" if closed else "NO"
    coordinates = np.ascontiguousarray(points, dtype="<f4")
    point_item = Dataset()
    point_item.NumberOfSurfacePoints = len(coordinates)
    point_item.PointCoordinatesData = coordinates.tobytes()
    point_item.PointsBoundingBoxCoordinates = [float(v) for v in np.concatenate(
        [coordinates.min(axis=0), coordinates.max(axis=0)])]
    surface.SurfacePointsSequence = [point_item]
    surface.SurfacePointsNormalsSequence = []
    primitives = Dataset()
    if triangles is None:
        primitives.LongVertexPointIndexList = np.arange(
            1, len(coordinates) + 1, dtype="<u4").tobytes()
        primitives.LongEdgePointIndexList = b""
        primitives.LongTrianglePointIndexList = b""
    else:
        primitives.LongVertexPointIndexList = b""
        primitives.LongEdgePointIndexList = b""
        primitives.LongTrianglePointIndexList = (np.ascontiguousarray(triangles, dtype="<u4")
                                                 + 1).tobytes()
    primitives.TriangleStripSequence = []
    primitives.TriangleFanSequence = []
    primitives.LineSequence = []
    primitives.FacetSequence = []
    surface.SurfaceMeshPrimitivesSequence = [primitives]
    return surface


def _points_near_the_eye(measured: _Measured, cloud: npt.ArrayLike | None
                         ) -> tuple[F64 | None, str]:
    """The cloud's points near the fitted globe, or None and why not."""
    if cloud is None:
        return None, "no measured cloud"
    points = np.asarray(cloud, dtype=np.float64).reshape(-1, 3)
    if measured.cloud_points is not None and len(points) != measured.cloud_points:
        return None, "cloud reconstructed again since: not exported"
    keep = np.linalg.norm(points - measured.centre, axis=1) <= measured.radius + SURFACE_MARGIN_MM
    if int(keep.sum()) < _MIN_SURFACE_POINTS:
        return None, "too few measured points near the eye"
    return points[keep], ""


def surface_dataset(measurement: Mapping[str, Any], *, patient_key: str,
                    equipment: Equipment, cloud: npt.ArrayLike | None) -> Dataset:
    """The Surface Segmentation of a stored pose measurement, in the fraction's frame.

    Segment and surface 1: the points of ``cloud`` (N × 3, WCS mm: the measurement's capture's
    fused cloud) within the fitted globe's radius plus :data:`SURFACE_MARGIN_MM` of its centre,
    as vertices. Left out — and said so in the content description — when ``cloud`` is None,
    is not the cloud the measurement was made on (another point count than its evidence's: the
    capture was reconstructed again since) or has fewer than 10 points there. The last segment
    and surface: the fitted globe of the measured pose, a closed triangulated sphere of its
    radius about its centre (642 vertices, 1280 triangles).
    """
    measured = _measured(measurement)
    ds = Dataset()
    _common(ds, measured, patient_key=patient_key, equipment=equipment,
            sop_class=SURFACE_SEGMENTATION, kind="surface", modality="SEG",
            series_number=2, series_description="Eye position verification: eye surface",
            series_laterality=False)
    ds.ContentLabel = "EYE_SURFACE"
    segments, surfaces = [], []
    near, note = _points_near_the_eye(measured, cloud)
    if near is not None:
        parameters = (f"the capture's fused cloud within {measured.radius:.2f} + "
                      f"{SURFACE_MARGIN_MM:g} mm of the fitted globe centre")
        segments.append(_segment(
            1, "Measured eye surface", "Fringe-projection points near the eye (with lids "
            "and lashes), room WCS, mm", _EYE, measured.eye,
            _algorithm(_NEIGHBORHOOD_ANALYSIS, "eyeserver reconstruct",
                       equipment.software_version, parameters)))
        surfaces.append(_surface(
            1, near, presentation="POINTS", triangles=None,
            comment="Measured points near the eye: a point cloud, no mesh",
            colour=_cielab(70.0, 30.0, 60.0), opacity=1.0))
    unit_sphere, triangles = _icosphere(_ICOSPHERE_SUBDIVISIONS)
    number = len(segments) + 1
    segments.append(_segment(
        number, "Fitted globe", f"Fitted globe of the measured pose: sphere r = "
        f"{measured.radius:.2f} mm, a model, not measured points", _EYEBALL, measured.eye,
        _algorithm(_MODEL_FIT, "eyeserver eye fit", equipment.software_version,
                   "least-squares fit of the eye model to the sclera and limbus")))
    surfaces.append(_surface(
        number, measured.centre + measured.radius * unit_sphere, presentation="SURFACE",
        triangles=triangles, comment="Triangulated sphere of the fitted globe (icosphere)",
        colour=_cielab(80.0, 0.0, 0.0), opacity=0.5))
    ds.ContentDescription = ("Measured eye surface and fitted globe" if near is not None else
                             f"Fitted globe only ({note})")[:64]
    ds.SegmentSequence = segments
    ds.NumberOfSurfaces = len(surfaces)
    ds.SurfaceSequence = surfaces
    return ds


def encode(ds: Dataset) -> bytes:
    """A DICOM file (Part 10: preamble, file meta information, explicit VR little endian)."""
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = ds.SOPClassUID
    meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    meta.ImplementationClassUID = UID(_IMPLEMENTATION_UID)
    meta.ImplementationVersionName = "EYESERVER"
    ds.file_meta = meta
    buffer = io.BytesIO()
    ds.save_as(buffer, enforce_file_format=True)
    return buffer.getvalue()


def export_measurement(measurement: Mapping[str, Any], *, patient_key: str,
                       equipment: Equipment, cloud_path: str | Path | None,
                       objects: Sequence[DicomObject] = ("registration", "surface"),
                       ) -> dict[str, bytes]:
    """The DICOM files of a stored pose measurement by file name (:data:`DICOM_OBJECTS`).

    ``cloud_path`` is the measurement's capture's ``cloud.ply`` (None when there is none).
    :class:`NoReferencePoseError` (HTTP 409) when the measurement has no reference pose: the
    surface alone would hide that the registration is missing, so neither is made.
    """
    _measured(measurement)  # fails before any work without a reference
    files: dict[str, bytes] = {}
    for name in objects:
        if name == "registration":
            ds = registration_dataset(measurement, patient_key=patient_key,
                                      equipment=equipment)
        else:
            cloud = None if cloud_path is None else read_ply(cloud_path).points
            ds = surface_dataset(measurement, patient_key=patient_key, equipment=equipment,
                                 cloud=cloud)
        files[DICOM_OBJECTS[name]] = encode(ds)
    return files


def zip_objects(files: Mapping[str, bytes]) -> bytes:
    """A zip of the files, stored (DICOM's binary data hardly deflates)."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_STORED) as archive:
        for name, data in files.items():
            archive.writestr(name, data)
    return buffer.getvalue()


# --- reading ------------------------------------------------------------------------------------


def read_dataset(data: bytes, source: str) -> Dataset:
    """A DICOM object from its bytes (a Part 10 file, or a bare data set in implicit or explicit
    VR); :class:`FormatError` naming ``source`` when it is not one."""
    try:
        ds = dcmread(io.BytesIO(data), force=True)
        ds.SOPClassUID  # noqa: B018  # parsing is lazy: reach an attribute to find garbage
    except Exception as exc:  # the parser's many errors on foreign bytes, at the boundary
        raise FormatError(source, None, f"not a readable DICOM object ({exc})") from exc
    return ds


def _attribute(ds: Dataset, keyword: str, source: str, where: str = "") -> Any:
    """A type 1 attribute's value; :class:`FormatError` when absent or empty."""
    value = ds.get(keyword)
    if value is None or (hasattr(value, "__len__") and len(value) == 0):
        raise FormatError(source, f"{where}{keyword}", "missing")
    return value


def _matrix(values: Any, source: str, field: str) -> F64:
    try:
        matrix = np.asarray([float(v) for v in values], dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise FormatError(source, field, "must be 16 numbers") from exc
    if matrix.shape != (16,) or not np.all(np.isfinite(matrix)):
        raise FormatError(source, field, "must be 16 finite numbers")
    return matrix.reshape(4, 4)


@dataclass(frozen=True)
class Registration:
    """What a Spatial Registration says: for each registered frame, the rigid transform of its
    coordinates into the registration's own frame (4 × 4 homogeneous, mm).

    Attributes read: SOP Class UID, SOP Instance UID, Frame of Reference UID; per Registration
    Sequence item its Frame of Reference UID (items referencing images alone are refused) and
    the Matrix Registration Sequence's Matrix Sequence: each Frame of Reference Transformation
    Matrix with its Type, which must be RIGID (an orthonormal rotation, determinant +1),
    applied in the order listed.
    """

    sop_instance_uid: str
    frame_of_reference_uid: str
    matrices: tuple[tuple[str, F64], ...]

    def matrix_from(self, frame_uid: str, source: str = "<spatial registration>") -> F64:
        """The transform from ``frame_uid`` into this registration's frame."""
        for uid, matrix in self.matrices:
            if uid == frame_uid:
                return matrix
        known = ", ".join(uid for uid, _ in self.matrices)
        raise FormatError(source, "RegistrationSequence", f"registers frames {known}, not the "
                          f"structure set's frame {frame_uid}")


def read_registration(ds: Dataset, source: str = "<spatial registration>") -> Registration:
    """The rigid transforms of a Spatial Registration (:class:`Registration`)."""
    if str(ds.get("SOPClassUID", "")) != SPATIAL_REGISTRATION:
        raise FormatError(source, "SOPClassUID", f"{ds.get('SOPClassUID')} is not a Spatial "
                          f"Registration ({SPATIAL_REGISTRATION})")
    matrices = []
    for index, item in enumerate(_attribute(ds, "RegistrationSequence", source)):
        where = f"RegistrationSequence[{index}]."
        frame = str(_attribute(item, "FrameOfReferenceUID", source, where))
        matrix_items = _attribute(item, "MatrixRegistrationSequence", source, where)
        total = np.eye(4)
        for step, transform in enumerate(_attribute(
                matrix_items[0], "MatrixSequence", source, f"{where}MatrixRegistrationSequence"
                "[0].")):
            field = f"{where}MatrixRegistrationSequence[0].MatrixSequence[{step}]."
            kind = str(transform.get("FrameOfReferenceTransformationMatrixType", ""))
            if kind != "RIGID":
                raise FormatError(source, f"{field}FrameOfReferenceTransformationMatrixType",
                                  f"{kind or 'missing'}: only RIGID transforms place an eye")
            matrix = _matrix(_attribute(transform, "FrameOfReferenceTransformationMatrix",
                                        source, field),
                             source, f"{field}FrameOfReferenceTransformationMatrix")
            rotation = matrix[:3, :3]
            if (not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-4)
                    or np.linalg.det(rotation) < 0
                    or not np.allclose(matrix[3], [0, 0, 0, 1], atol=1e-9)):
                raise FormatError(source, f"{field}FrameOfReferenceTransformationMatrix",
                                  "RIGID but not a rotation and a translation")
            total = matrix @ total  # each applied after the ones before it
        matrices.append((frame, total))
    return Registration(str(_attribute(ds, "SOPInstanceUID", source)),
                        str(_attribute(ds, "FrameOfReferenceUID", source)), tuple(matrices))


@dataclass(frozen=True)
class PlannedEye:
    """The planned eye of an RT Structure Set, in its frame of reference (mm).

    The globe: the least-squares ellipsoid through its contour points (``globe_centre_mm``,
    ``globe_semi_axes_mm`` largest first along the columns of ``globe_axes``, given as rows)
    and the least-squares sphere (``sphere_centre_mm``, ``globe_radius_mm``; ``globe_rms_mm``
    the points' RMS distance from it: how far the globe is from a sphere). The ellipsoid's
    centre is the globe's: a sphere's is pulled towards where the contours sample the surface
    more densely. The cornea, where an ROI holds it: the sphere through its points (radius of
    curvature) and their centroid. The limbus, where an ROI holds it: the circle through its
    points. ``gaze`` points from the globe centre to the limbus centre (else the cornea's
    centroid); None without either.
    """

    structure_set_uid: str
    frame_of_reference_uid: str
    globe_roi: str
    globe_points: int
    globe_centre_mm: Vec3
    sphere_centre_mm: Vec3
    globe_radius_mm: float
    globe_rms_mm: float
    globe_semi_axes_mm: Vec3
    globe_axes: tuple[Vec3, Vec3, Vec3]
    cornea_roi: str | None = None
    cornea_radius_mm: float | None = None
    cornea_centroid_mm: Vec3 | None = None
    limbus_roi: str | None = None
    limbus_centre_mm: Vec3 | None = None
    limbus_diameter_mm: float | None = None
    gaze: Vec3 | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-able (lists for vectors), as the import route answers it."""
        return {"structure_set_uid": self.structure_set_uid,
                "frame_of_reference_uid": self.frame_of_reference_uid,
                "globe_roi": self.globe_roi, "globe_points": self.globe_points,
                "globe_centre_mm": list(self.globe_centre_mm),
                "sphere_centre_mm": list(self.sphere_centre_mm),
                "globe_radius_mm": self.globe_radius_mm, "globe_rms_mm": self.globe_rms_mm,
                "globe_semi_axes_mm": list(self.globe_semi_axes_mm),
                "globe_axes": [list(row) for row in self.globe_axes],
                "cornea_roi": self.cornea_roi, "cornea_radius_mm": self.cornea_radius_mm,
                "cornea_centroid_mm": _listed(self.cornea_centroid_mm),
                "limbus_roi": self.limbus_roi, "limbus_centre_mm": _listed(self.limbus_centre_mm),
                "limbus_diameter_mm": self.limbus_diameter_mm, "gaze": _listed(self.gaze)}


def _listed(vector: Vec3 | None) -> list[float] | None:
    return None if vector is None else list(vector)


def _vec3(values: F64) -> Vec3:
    return float(values[0]), float(values[1]), float(values[2])


Role = Literal["globe", "cornea", "limbus"]
_ROLE_WORDS: dict[Role, re.Pattern[str]] = {
    "cornea": re.compile(r"\bcornea[l]?\b"),
    "limbus": re.compile(r"\b(limbus|limbal|corneoscleral)\b"),
    "globe": re.compile(r"\b(globe|eye|eyeball|bulbus|bulb|oculus)\b"),
}
# Structures of or in the eye that are not the globe however their names mention it.
_NOT_GLOBE = re.compile(r"\b(lens|retina|macula|disc|disk|nerve|chiasm|tumou?r|[gcp]tv|itv|"
                        r"cornea|limbus|lid|lids|lacrimal|sclera|iris|ciliary|vitreous|"
                        r"fovea|choroid|optic|prv|ring|marker|clip|clips)\b")
_CODES: dict[Role, tuple[str, ...]] = {"globe": (_EYE[0], _EYEBALL[0]), "cornea": (_CORNEA[0],),
                                       "limbus": ()}
_SIDES = {"right": re.compile(r"\b(r|rt|right|od|dexter)\b"),
          "left": re.compile(r"\b(l|lt|left|os|sinister)\b")}


def _words(*texts: str) -> str:
    """Lower-case words: ``Eye_R`` → ``eye r`` (so that ``\\b`` sees the parts)."""
    return " ".join(re.sub(r"[^a-z0-9]+", " ", re.sub(r"([a-z])([A-Z])", r"\1 \2", t).lower())
                    for t in texts if t)


@dataclass(frozen=True)
class _Roi:
    number: int
    name: str
    frame: str
    words: str
    codes: tuple[str, ...]
    points: F64


def _rois(ds: Dataset, source: str) -> list[_Roi]:
    """Every ROI with contour points: the attributes of the Structure Set, ROI Contour and RT ROI
    Observations modules that name and locate it."""
    observations: dict[int, tuple[str, tuple[str, ...]]] = {}
    for item in ds.get("RTROIObservationsSequence", []):
        number = item.get("ReferencedROINumber")
        if number is None:
            continue
        codes = tuple(str(code.get("CodeValue", ""))
                      for code in item.get("RTROIIdentificationCodeSequence", []))
        observations[int(number)] = (
            f"{item.get('RTROIInterpretedType', '')} {item.get('ROIObservationLabel', '')}",
            codes)
    points: dict[int, list[F64]] = {}
    for index, item in enumerate(ds.get("ROIContourSequence", [])):
        number = item.get("ReferencedROINumber")
        if number is None:
            raise FormatError(source, f"ROIContourSequence[{index}].ReferencedROINumber",
                              "missing")
        for contour in item.get("ContourSequence", []):
            data = contour.get("ContourData")
            if data is None:
                continue
            xyz = np.asarray([float(v) for v in (data if isinstance(data, MultiValue)
                                                 else [data])])
            if xyz.size % 3 or not np.all(np.isfinite(xyz)):
                raise FormatError(source, f"ROIContourSequence[{index}].ContourData",
                                  "must be finite (x, y, z) triplets")
            points.setdefault(int(number), []).append(xyz.reshape(-1, 3))
    rois = []
    for index, item in enumerate(_attribute(ds, "StructureSetROISequence", source)):
        number = int(_attribute(item, "ROINumber", source, f"StructureSetROISequence[{index}]."))
        if number not in points:
            continue
        name = str(item.get("ROIName", ""))
        interpreted, codes = observations.get(number, ("", ()))
        rois.append(_Roi(number, name, str(item.get("ReferencedFrameOfReferenceUID", "")),
                         _words(name, interpreted), codes, np.concatenate(points[number])))
    return rois


def _role_of(roi: _Roi) -> Role | None:
    for role in ("cornea", "limbus", "globe"):
        if any(code in roi.codes for code in _CODES[role]) or _ROLE_WORDS[role].search(
                roi.words):
            if role == "globe" and _NOT_GLOBE.search(roi.words) and not roi.codes:
                continue
            return role
    return None


def _side_of(roi: _Roi) -> str | None:
    sides = [side for side, words in _SIDES.items() if words.search(roi.words)]
    return sides[0] if len(sides) == 1 else None


def _choose(rois: list[_Roi], role: Role, eye: str | None, source: str) -> _Roi | None:
    """The ROI holding ``role``: the only one, or the only one of the treated eye's side."""
    found = [roi for roi in rois if _role_of(roi) == role]
    if eye is not None:
        other = "left" if eye == "right" else "right"
        if found and all(_side_of(roi) == other for roi in found):
            names = ", ".join(repr(roi.name) for roi in found)
            raise FormatError(source, "StructureSetROISequence", f"the {role} ROIs ({names}) "
                              f"are of the {other} eye; the patient's treated eye is the {eye}")
        if len(found) > 1:
            found = [roi for roi in found if _side_of(roi) in (eye, None)] or found
            if len(found) > 1:
                found = [roi for roi in found if _side_of(roi) == eye] or found
    if len(found) > 1:
        names = ", ".join(repr(roi.name) for roi in found)
        raise FormatError(source, "StructureSetROISequence", f"several ROIs may be the {role} "
                          f"({names}); keep one, or name their sides")
    return found[0] if found else None


def read_planned_eye(ds: Dataset, eye: Literal["right", "left"] | None = None,
                     source: str = "<RT structure set>") -> PlannedEye:
    """The planned eye of an RT Structure Set (:class:`PlannedEye`), in its frame (mm).

    Which ROI is what comes from its ROI Name (3006,0026), its RT ROI Interpreted Type
    (3006,00A4), ROI Observation Label (3006,0085) and RT ROI Identification Code Sequence
    (3006,0086): the globe is named globe, eye, eyeball or bulbus (not lens, retina, tumour, …)
    or coded SNOMED CT 81745001 or 79652003; the cornea named cornea or coded 28726007; the
    limbus named limbus, limbal or corneoscleral. Where several could be the globe, the one of
    the treated ``eye``'s side (R/L/right/left/OD/OS in its name) is taken; a globe only of the
    other side is refused. The points are every ROI Contour's Contour Data (3006,0050)
    triplets, whatever the Contour Geometric Type; the frame is the globe ROI's Referenced
    Frame of Reference UID (3006,0024).
    """
    if str(ds.get("SOPClassUID", "")) != RT_STRUCTURE_SET:
        raise FormatError(source, "SOPClassUID", f"{ds.get('SOPClassUID')} is not an RT "
                          f"Structure Set ({RT_STRUCTURE_SET})")
    rois = _rois(ds, source)
    globe = _choose(rois, "globe", eye, source)
    if globe is None:
        names = ", ".join(repr(roi.name) for roi in rois) or "none with contours"
        raise FormatError(source, "StructureSetROISequence", "no ROI is the globe (named "
                          f"globe, eye or eyeball, or coded SNOMED CT 81745001); ROIs: {names}")
    if len(globe.points) < 12:
        raise FormatError(source, "ROIContourSequence", f"the globe ROI {globe.name!r} has "
                          f"{len(globe.points)} points; an ellipsoid needs at least 12")
    sphere_centre, radius, rms = _fit_sphere(globe.points)
    try:
        centre, semi_axes, axes = _fit_ellipsoid(globe.points)
    except (ValueError, np.linalg.LinAlgError) as exc:
        raise FormatError(source, "ROIContourSequence", f"the globe ROI {globe.name!r} is not "
                          f"an ellipsoid ({exc})") from exc
    found: dict[str, Any] = {}
    cornea = _choose(rois, "cornea", eye, source)
    if cornea is not None and len(cornea.points) >= 4:
        _, cornea_radius, _ = _fit_sphere(cornea.points)
        found.update(cornea_roi=cornea.name, cornea_radius_mm=cornea_radius,
                     cornea_centroid_mm=_vec3(cornea.points.mean(axis=0)))
    limbus = _choose(rois, "limbus", eye, source)
    if limbus is not None and len(limbus.points) >= 3:
        limbus_centre, _, limbus_radius = _fit_circle(limbus.points)
        found.update(limbus_roi=limbus.name, limbus_centre_mm=_vec3(limbus_centre),
                     limbus_diameter_mm=2.0 * limbus_radius)
    front = found.get("limbus_centre_mm") or found.get("cornea_centroid_mm")
    if front is not None:
        direction = np.asarray(front) - centre
        if np.linalg.norm(direction) > 1e-6:
            found["gaze"] = _vec3(direction / np.linalg.norm(direction))
    frames = [str(item.get("FrameOfReferenceUID", ""))
              for item in ds.get("ReferencedFrameOfReferenceSequence", [])]
    frame = globe.frame or (frames[0] if len(frames) == 1 else "")
    if not frame:
        raise FormatError(source, "StructureSetROISequence.ReferencedFrameOfReferenceUID",
                          "missing")
    return PlannedEye(
        structure_set_uid=str(ds.get("SOPInstanceUID", "")), frame_of_reference_uid=frame,
        globe_roi=globe.name, globe_points=len(globe.points), globe_centre_mm=_vec3(centre),
        sphere_centre_mm=_vec3(sphere_centre),
        globe_radius_mm=radius, globe_rms_mm=rms, globe_semi_axes_mm=_vec3(semi_axes),
        globe_axes=(_vec3(axes[0]), _vec3(axes[1]), _vec3(axes[2])), **found)


@dataclass(frozen=True)
class PlanImport:
    """A plan read from DICOM: the eye model's fields (``EyeModelSpec``), the reference pose's
    (``ReferencePoseSpec``, WCS) or None, and why not (``notes``)."""

    eye: PlannedEye
    registration_uid: str | None
    wcs_frame_uid: str | None
    eye_model: dict[str, Any]
    reference: dict[str, Any] | None
    notes: tuple[str, ...]

    def to_dict(self) -> dict[str, Any]:
        """What was read, JSON-able."""
        return {"planned_eye": self.eye.to_dict(), "registration_uid": self.registration_uid,
                "wcs_frame_of_reference_uid": self.wcs_frame_uid, "notes": list(self.notes)}


def read_plan(objects: Sequence[tuple[str, bytes]],
              eye: Literal["right", "left"] | None = None) -> PlanImport:
    """The planned eye and, with a Spatial Registration, the planned reference pose.

    ``objects`` are (name, bytes) of DICOM files: exactly one RT Structure Set and at most one
    Spatial Registration (others are refused, naming them). The eye model is the globe's
    ellipsoid turned into the WCS by the registration (its centre kept in the planning frame
    for the record), or, without one, the globe's sphere (its radius: the WCS orientation of
    an ellipsoid would be unknown); the cornea's radius and the limbus's diameter where their
    ROIs exist. The reference pose needs both the registration (the structure set's frame in
    the room) and a gaze (a cornea or limbus ROI): globe centre, gaze and limbus centre carried
    into the WCS by the registration's rigid transform.
    """
    try:
        return _read_plan(objects, eye)
    except (ValueError, TypeError, KeyError, AttributeError, IndexError) as exc:
        # Values are converted when first read (a DS that is no number, a broken sequence).
        raise FormatError("<uploaded DICOM>", None, f"unreadable ({exc})") from exc


def _read_plan(objects: Sequence[tuple[str, bytes]], eye: Literal["right", "left"] | None
               ) -> PlanImport:
    structures: list[tuple[str, Dataset]] = []
    registrations: list[tuple[str, Dataset]] = []
    for name, data in objects:
        ds = read_dataset(data, name)
        sop_class = str(ds.get("SOPClassUID", ""))
        if sop_class == RT_STRUCTURE_SET:
            structures.append((name, ds))
        elif sop_class == SPATIAL_REGISTRATION:
            registrations.append((name, ds))
        else:
            raise FormatError(name, "SOPClassUID", f"{sop_class or 'missing'}: only an RT "
                              "Structure Set and a Spatial Registration are read")
    if len(structures) != 1 or len(registrations) > 1:
        raise FormatError("<upload>", None, f"{len(structures)} RT Structure Sets and "
                          f"{len(registrations)} Spatial Registrations: give one structure set "
                          "and at most one registration")
    structure_name, structure = structures[0]
    planned = read_planned_eye(structure, eye, structure_name)
    source = (f"DICOM RT Structure Set {planned.structure_set_uid}, ROI {planned.globe_roi!r}"
              f" ({planned.globe_points} points, sphere rms {planned.globe_rms_mm:.2f} mm)")
    model: dict[str, Any] = {}
    notes = []
    registration: Registration | None = None
    if registrations:
        registration_name, registration_ds = registrations[0]
        registration = read_registration(registration_ds, registration_name)
        to_wcs = registration.matrix_from(planned.frame_of_reference_uid, registration_name)
        axes = to_wcs[:3, :3] @ np.asarray(planned.globe_axes)
        model["ellipsoid"] = {"centre_mm": list(planned.globe_centre_mm),
                              "semi_axes_mm": list(planned.globe_semi_axes_mm),
                              "orientation": axes.tolist()}
        source += f", in the WCS by Spatial Registration {registration.sop_instance_uid}"
    else:
        model["globe_radius_mm"] = planned.globe_radius_mm
        notes.append("no Spatial Registration: the globe is stored as a sphere (an ellipsoid's "
                     "orientation in the room is unknown) and no reference pose is set")
    if planned.cornea_radius_mm is not None:
        model["cornea_radius_mm"] = planned.cornea_radius_mm
    if planned.limbus_diameter_mm is not None:
        model["limbus_diameter_mm"] = planned.limbus_diameter_mm
    model["source"] = source[:500]
    reference = None
    if planned.gaze is None:
        notes.append("no cornea or limbus ROI: the planned gaze is unknown and no reference "
                     "pose is set")
    elif registration is not None:
        to_wcs = registration.matrix_from(planned.frame_of_reference_uid)
        reference = {
            "centre_mm": _transformed(to_wcs, planned.globe_centre_mm).tolist(),
            "gaze": (to_wcs[:3, :3] @ np.asarray(planned.gaze)).tolist(),
            "limbus_centre_mm": None if planned.limbus_centre_mm is None
            else _transformed(to_wcs, planned.limbus_centre_mm).tolist(),
            "plan": (f"DICOM RT Structure Set {planned.structure_set_uid}, Spatial "
                     f"Registration {registration.sop_instance_uid}")[:500]}
    return PlanImport(planned, None if registration is None else registration.sop_instance_uid,
                      None if registration is None else registration.frame_of_reference_uid,
                      model, reference, tuple(notes))


def dicom_objects(body: bytes, content_type: str, max_bytes: int) -> list[tuple[str, bytes]]:
    """The DICOM files of an upload: ``application/dicom`` is one object, ``application/zip``
    holds them as members (folders and names do not matter; directories and a ``DICOMDIR``
    are skipped). Nothing in an archive is trusted: encrypted members are refused and members
    are read at most ``max_bytes`` in all, whatever sizes they declare (:class:`FormatError`).
    """
    if content_type == "application/dicom":
        return [("<uploaded DICOM object>", body)]
    if content_type not in ("application/zip", "application/x-zip-compressed"):
        raise FormatError("<upload>", None, f"the body must be application/zip or "
                          f"application/dicom, not {content_type or 'untyped'}")
    source = "<uploaded zip>"
    try:
        archive = zipfile.ZipFile(io.BytesIO(body))
    except zipfile.BadZipFile as exc:
        raise FormatError(source, None, f"not a zip archive ({exc})") from exc
    found, budget = [], max_bytes
    with archive:
        for info in archive.infolist():
            if info.is_dir() or info.filename.rsplit("/", 1)[-1].upper() == "DICOMDIR":
                continue
            if info.flag_bits & 0x1:
                raise FormatError(source, info.filename, "encrypted members are not read")
            try:
                with archive.open(info) as member:
                    data = member.read(budget + 1)
            except (zipfile.BadZipFile, NotImplementedError, OSError, EOFError) as exc:
                raise FormatError(source, info.filename, f"cannot be read ({exc})") from exc
            budget -= len(data)
            if budget < 0:
                raise FormatError(source, info.filename, f"the archive unpacks to more than "
                                  f"{max_bytes} bytes")
            found.append((info.filename, data))
    if not found:
        raise FormatError(source, None, "holds no files")
    return found
