"""DICOM out and in (issue 40): a pose measurement as a Spatial Registration and a Surface
Segmentation, and the planned eye from an RT Structure Set and a Spatial Registration.

Every exported object is checked with dicom3tools' ``dciodvfy`` (Debian package
``dicom3tools``; those checks skip, saying so, where it is not installed — CI installs it) and
read back with pydicom. One app serves the module; one measurement is made through the API
(one unit, an injected fit for a known pose) and exported in every way; the planned eye is
built here as contours of known shapes.
"""

from __future__ import annotations

import io
import json
import math
import shutil
import subprocess
import zipfile
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pydicom
import pytest
from fastapi import FastAPI
from pydicom.dataset import Dataset

from eyeserver.calibration.artefact import ARRAYS_FILE, CALIBRATION_FILE
from eyeserver.errors import FormatError
from eyeserver.eye.fit import CloudLike, EyeModel, EyePose, fit_eye
from eyeserver.eye.limbus import LimbusView
from eyeserver.io import dicom, read_ply
from eyeserver.service.core import Service
from eyeserver.service.verification import PoseVerification
from tests.apiclient import API, OPERATOR_TOKEN, Client, auth

OPERATOR = auth(OPERATOR_TOKEN)
PATIENT = "P-DICOM-1"
REFERENCE = {"centre_mm": [0.0, 0.0, -10.0], "gaze": [0.0, 0.0, 1.0]}
SHIFT_MM = (0.12, -0.05, 0.2)  # the measured pose: moved from the reference and turned 1.5°
TILT = math.radians(1.5)
MEASURED_GAZE = (0.0, math.sin(TILT), math.cos(TILT))
DCIODVFY = shutil.which("dciodvfy")
needs_dciodvfy = pytest.mark.skipif(
    DCIODVFY is None, reason="dciodvfy (Debian package dicom3tools) is not installed; CI has it")


# --- a measurement through the API ---------------------------------------------------------


class FixedFit:
    """A fit that answers the measured pose: the deviation and matrix are then known."""

    def __init__(self, centre: Sequence[float]) -> None:
        self.centre = (float(centre[0]), float(centre[1]), float(centre[2]))

    def __call__(self, cloud: CloudLike, model: EyeModel, views: Sequence[LimbusView] = ()
                 ) -> EyePose:
        return EyePose(centre_mm=self.centre, centre_sd_mm=(0.01, 0.01, 0.01),
                       globe_radius_mm=12.0, limbus_centre_mm=None, limbus_sd_mm=None,
                       gaze=MEASURED_GAZE, gaze_sd_deg=0.1, torsion_deg=None,
                       surface_mad_mm=0.05, sclera_points=1000, confidence=0.9)


@pytest.fixture(scope="module")
def measurement(app: FastAPI, client: Client,
                calibrated_rooms: Callable[[str], tuple[Path, Path]]) -> Iterator[Any]:
    """A patient (left eye, one unit: half the capture), a planned reference, an active
    calibration, the simulated eye where the reference wants it and one measurement."""
    caldir = calibrated_rooms("default")[1]
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for name in (CALIBRATION_FILE, ARRAYS_FILE):
            archive.writestr(name, (caldir / name).read_bytes())
    imported = client.post(f"{API}/calibrations", content=buffer.getvalue(),
                           headers={"content-type": "application/zip"})
    assert imported.status_code == 201, imported.text
    assert client.post(f"{API}/calibrations/{imported.json()['id']}/activate").status_code == 200
    assert client.put(f"{API}/patients/{PATIENT}",
                      json={"eye": "left", "unit": "left"}).status_code == 201
    assert client.put(f"{API}/patients/{PATIENT}/fractions/1/reference",
                      json=REFERENCE).status_code == 201
    placed = client.put(f"{API}/sim/eye", json={"position_mm": [0.0, 0.0, -10.0]})
    assert placed.status_code == 200, placed.text
    truth = np.asarray(placed.json()["eye"]["centre_mm"])
    verification = app.state.verification
    assert isinstance(verification, PoseVerification)
    verification.fit = FixedFit(truth + SHIFT_MM)
    try:
        response = client.post(f"{API}/pose/measure",
                               json={"patient_id": PATIENT, "fraction": 1}, headers=OPERATOR)
    finally:
        verification.fit = fit_eye
    assert response.status_code == 201, response.text
    yield response.json()


def _dciodvfy(path: Path) -> list[str]:
    """dciodvfy's errors for a file (its warnings are explained where the attribute is set)."""
    assert DCIODVFY is not None
    run = subprocess.run([DCIODVFY, str(path)], capture_output=True, text=True, timeout=60,
                         check=False)
    lines = (run.stdout + run.stderr).splitlines()
    return [line for line in lines if line.startswith("Error")]


def _export(client: Client, measurement_id: str, **params: str) -> Any:
    return client.get(f"{API}/pose/measurements/{measurement_id}/dicom", params=params,
                      headers=OPERATOR)


@pytest.fixture(scope="module")
def exported(client: Client, measurement: Any, tmp_path_factory: pytest.TempPathFactory
             ) -> dict[str, Path]:
    """The zip's two objects, written to files for dciodvfy."""
    response = _export(client, measurement["id"])
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "application/zip"
    folder = tmp_path_factory.mktemp("dicom")
    with zipfile.ZipFile(io.BytesIO(response.content)) as archive:
        assert sorted(archive.namelist()) == ["registration.dcm", "surface.dcm"]
        archive.extractall(folder)
    return {"registration": folder / "registration.dcm", "surface": folder / "surface.dcm"}


@needs_dciodvfy
@pytest.mark.parametrize("name", ["registration", "surface"])
def test_every_exported_object_passes_dciodvfy(exported: dict[str, Path], name: str) -> None:
    assert _dciodvfy(exported[name]) == []


def test_the_registration_reads_back_as_the_eye_motion(
        exported: dict[str, Path], measurement: Any, service: Service) -> None:
    ds = pydicom.dcmread(exported["registration"])
    registration = dicom.read_registration(ds)
    key = service.store.query("SELECT key FROM patients WHERE patient_id = ?",
                              (PATIENT,))[0][0]
    pose, reference = measurement["pose"], measurement["reference"]["pose"]
    expected = dicom.rigid_motion(reference["centre_mm"], reference["gaze"],
                                  pose["centre_mm"], pose["gaze"])

    assert ds.SOPClassUID == dicom.SPATIAL_REGISTRATION and ds.Modality == "REG"
    assert (ds.PatientID, ds.PatientName, ds.Laterality) == (PATIENT, "", "L")
    assert (ds.Manufacturer, ds.SoftwareVersions) == ("eyeserver", "0.1.0")
    assert ds.FrameOfReferenceUID == dicom.frame_of_reference_uid(key, 1)
    assert registration.frame_of_reference_uid == ds.FrameOfReferenceUID
    [(frame, matrix)] = registration.matrices
    assert frame == ds.FrameOfReferenceUID
    np.testing.assert_allclose(matrix, expected, atol=1e-10)
    # The matrix carries the reference eye onto the measured one: centre and gaze.
    moved = matrix @ np.array([*reference["centre_mm"], 1.0])
    np.testing.assert_allclose(moved[:3], pose["centre_mm"], atol=1e-9)
    np.testing.assert_allclose(matrix[:3, :3] @ reference["gaze"], MEASURED_GAZE, atol=1e-12)
    assert math.degrees(math.acos((np.trace(matrix[:3, :3]) - 1) / 2)) == pytest.approx(1.5)


def test_the_surface_reads_back_as_the_measured_points_and_the_globe(
        exported: dict[str, Path], measurement: Any, service: Service) -> None:
    ds = pydicom.dcmread(exported["surface"])
    registration = pydicom.dcmread(exported["registration"])
    centre = np.asarray(measurement["pose"]["centre_mm"])
    cloud = read_ply(service.cloud_path(measurement["evidence"]["capture_id"])).points
    near = cloud[np.linalg.norm(cloud - centre, axis=1) <= 12.0 + dicom.SURFACE_MARGIN_MM]

    def points(surface: Dataset) -> Any:
        item = surface.SurfacePointsSequence[0]
        xyz = np.frombuffer(item.PointCoordinatesData, dtype="<f4").reshape(-1, 3)
        assert len(xyz) == item.NumberOfSurfacePoints
        return xyz

    measured, globe = ds.SurfaceSequence
    triangles = np.frombuffer(globe.SurfaceMeshPrimitivesSequence[0]
                              .LongTrianglePointIndexList, dtype="<u4").reshape(-1, 3)
    vertices = np.frombuffer(measured.SurfaceMeshPrimitivesSequence[0]
                             .LongVertexPointIndexList, dtype="<u4")

    assert ds.SOPClassUID == dicom.SURFACE_SEGMENTATION and ds.Modality == "SEG"
    assert ds.FrameOfReferenceUID == registration.FrameOfReferenceUID
    assert ds.StudyInstanceUID == registration.StudyInstanceUID
    assert ds.NumberOfSurfaces == 2 and len(ds.SegmentSequence) == 2
    assert len(near) > 1000  # the eye is in view: thousands of points of it
    np.testing.assert_array_equal(points(measured), near)
    assert vertices.tolist() == list(range(1, len(near) + 1))  # indices start at 1
    globe_points = points(globe)
    np.testing.assert_allclose(np.linalg.norm(globe_points - centre, axis=1), 12.0, atol=1e-4)
    assert (len(globe_points), len(triangles)) == (642, 1280)
    assert triangles.min() == 1 and triangles.max() == len(globe_points)
    assert (globe.FiniteVolume, globe.Manifold, measured.RecommendedPresentationType) == \
        ("YES", "YES", "POINTS")
    for segment, code in zip(ds.SegmentSequence, ("81745001", "79652003"), strict=True):
        assert segment.SegmentedPropertyTypeCodeSequence[0].CodeValue == code
        assert segment.AnatomicRegionSequence[0].CodeValue == "81745001"  # SNOMED CT "Eye"
        modifier = segment.AnatomicRegionSequence[0].AnatomicRegionModifierSequence[0]
        assert (modifier.CodeValue, modifier.CodeMeaning) == ("7771000", "Left")


def test_single_objects_are_the_zips_and_exports_repeat(
        client: Client, exported: dict[str, Path], measurement: Any) -> None:
    registration = _export(client, measurement["id"], object="registration")
    surface = _export(client, measurement["id"], object="surface")
    bad = _export(client, measurement["id"], object="plan")

    assert registration.status_code == 200 and surface.status_code == 200
    assert registration.headers["content-type"] == "application/dicom"
    # The same measurement gives the same objects (UIDs derived, times the measurement's).
    assert registration.content == exported["registration"].read_bytes()
    assert surface.content == exported["surface"].read_bytes()
    assert bad.status_code == 422


def test_unknown_measurements_are_404_and_those_without_a_reference_409(
        client: Client, measurement: Any, service: Service) -> None:
    unknown = _export(client, "pose-20260101T000000000Z-0000")
    # A measurement stored without a reference (none is made so today; an older or foreign
    # document may be): nothing to register against.
    store = service.store
    orphan_id = store.new_id("pose")
    [(key, file)] = store.query(
        "SELECT p.key, m.file FROM pose_measurements m JOIN patients p USING (patient_id) "
        "WHERE m.id = ?", (measurement["id"],))
    document = {**json.loads(store.read_document(file)), "id": orphan_id, "reference": None}
    with store.transaction() as db:
        relative = f"patients/{key}/measurements/{orphan_id}.json"
        store.write_document(relative, json.dumps(document))
        db.execute("INSERT INTO pose_measurements (id, patient_id, fraction, created, passed, "
                   "capture_id, file) VALUES (?, ?, ?, ?, ?, ?, ?)",
                   (orphan_id, PATIENT, 1, document["created"], 0,
                    document["evidence"]["capture_id"], relative))
    orphan = _export(client, orphan_id)
    single = _export(client, orphan_id, object="surface")

    assert unknown.status_code == 404
    assert "pose measurement" in unknown.json()["detail"]
    assert orphan.status_code == 409 and single.status_code == 409
    assert "no reference pose to register against" in orphan.json()["detail"]


def test_a_spatial_registration_round_trips() -> None:
    document = {"id": "pose-20261123T151200123Z-4f2a", "patient_id": "P-1", "fraction": 3,
                "eye": "right", "created": "2026-11-23T15:12:00.123Z", "actor": "dr-weber",
                "passed": False, "deviation": {"length_mm": 1.0, "gaze_deg": 20.0},
                "pose": {"centre_mm": [1.0, -0.5, -9.0], "gaze": [0.3, -0.2, 0.9],
                         "globe_radius_mm": 12.1},
                "reference": {"version": 2, "pose": {"centre_mm": [0.0, 0.0, -10.0],
                                                     "gaze": [0.0, 0.0, 1.0]}}}
    equipment = dicom.Equipment("9.9", "station-1")

    data = dicom.encode(dicom.registration_dataset(document, patient_key="pat-1",
                                                   equipment=equipment))
    read = dicom.read_registration(dicom.read_dataset(data, "registration.dcm"))

    [(frame, matrix)] = read.matrices
    assert frame == read.frame_of_reference_uid == dicom.frame_of_reference_uid("pat-1", 3)
    np.testing.assert_allclose(matrix, dicom.rigid_motion(
        [0, 0, -10], [0, 0, 1], [1.0, -0.5, -9.0], [0.3, -0.2, 0.9]), atol=1e-10)
    assert dicom.read_dataset(data, "x").Laterality == "R"
    scaled = _registration_to_wcs(np.diag([2.0, 2.0, 2.0, 1.0]))
    with pytest.raises(FormatError, match="RIGID but not a rotation and a translation"):
        dicom.read_registration(dicom.read_dataset(scaled, "scaled.dcm"))


# --- the planned eye in --------------------------------------------------------------------


PLAN_FRAME = "1.2.826.0.1.3680043.8.498.1"
GLOBE_CENTRE = np.array([31.5, -42.25, 17.75])  # planning frame (LPS), mm
PLANNED_GAZE = np.array([0.0, -1.0, 0.0])  # anterior
# Planning frame → room WCS: -90° about x (anterior -y onto the beam's +z), then a shift.
TO_WCS = np.array([[1.0, 0.0, 0.0, 1.0], [0.0, 0.0, 1.0, 2.0], [0.0, -1.0, 0.0, -30.0],
                   [0.0, 0.0, 0.0, 1.0]])


def _ds(value: float) -> str:
    return f"{value:.6f}"


def _ellipsoid_contours(centre: Any, semi_axes: Sequence[float], step_mm: float = 1.5
                        ) -> list[Any]:
    """Axial (z) slices of an axis-aligned ellipsoid, 48 points each: how a TPS draws it."""
    a, b, c = semi_axes
    contours = []
    for dz in np.arange(-c + step_mm / 2, c, step_mm):
        scale = math.sqrt(1.0 - (dz / c) ** 2)
        angles = np.linspace(0, 2 * math.pi, 48, endpoint=False)
        contours.append(np.column_stack([centre[0] + a * scale * np.cos(angles),
                                         centre[1] + b * scale * np.sin(angles),
                                         np.full(48, centre[2] + dz)]))
    return contours


def _cornea_and_limbus(centre: Any, gaze: Any) -> tuple[Any, Any]:
    """A corneal cap (radius 7.8 mm, apex 13 mm in front of the globe centre) and the limbus
    circle (diameter 11.7 mm, where the cap meets the sclera) on the axis ``gaze``."""
    u = np.cross(gaze, [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    w = np.cross(gaze, u)
    rng = np.random.default_rng(1)
    cap_centre = centre + (13.0 - 7.8) * gaze
    directions = rng.normal(size=(400, 3)) * [0.25, 0.25, 0.25] + gaze
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    cap = cap_centre + 7.8 * directions
    half = 11.7 / 2
    depth = math.sqrt(7.8**2 - half**2)
    angles = np.linspace(0, 2 * math.pi, 36, endpoint=False)
    ring = (cap_centre + depth * gaze + half * (np.outer(np.cos(angles), u)
                                                + np.outer(np.sin(angles), w)))
    return cap, ring


def _structure_set(rois: Sequence[tuple[str, str, list[Any]]], frame: str = PLAN_FRAME
                   ) -> bytes:
    """An RT Structure Set of ``(ROI name, RT ROI Interpreted Type, contours)``."""
    ds = Dataset()
    ds.SOPClassUID = dicom.RT_STRUCTURE_SET
    ds.SOPInstanceUID = dicom.derived_uid("test", "structure set", frame)
    ds.Modality = "RTSTRUCT"
    ds.PatientID = "P-PLAN"
    ds.StructureSetLabel = "EYE PLAN"
    referenced = Dataset()
    referenced.FrameOfReferenceUID = frame
    ds.ReferencedFrameOfReferenceSequence = [referenced]
    ds.StructureSetROISequence, ds.ROIContourSequence, ds.RTROIObservationsSequence = [], [], []
    for number, (name, interpreted, contours) in enumerate(rois, start=1):
        roi = Dataset()
        roi.ROINumber, roi.ReferencedFrameOfReferenceUID, roi.ROIName = number, frame, name
        roi.ROIGenerationAlgorithm = "MANUAL"
        ds.StructureSetROISequence.append(roi)
        contour_items = []
        for points in contours:
            item = Dataset()
            item.ContourGeometricType = "CLOSED_PLANAR" if len(points) > 2 else "POINT"
            item.NumberOfContourPoints = len(points)
            item.ContourData = [_ds(v) for v in np.asarray(points).ravel()]
            contour_items.append(item)
        roi_contour = Dataset()
        roi_contour.ReferencedROINumber = number
        roi_contour.ContourSequence = contour_items
        ds.ROIContourSequence.append(roi_contour)
        observation = Dataset()
        observation.ObservationNumber, observation.ReferencedROINumber = number, number
        observation.RTROIInterpretedType, observation.ROIInterpreter = interpreted, ""
        ds.RTROIObservationsSequence.append(observation)
    return dicom.encode(ds)


def _registration_to_wcs(matrix: Any, source_frame: str = PLAN_FRAME) -> bytes:
    """A Spatial Registration whose own frame is the room's WCS, registering ``source_frame``
    into it by ``matrix``."""
    ds = Dataset()
    ds.SOPClassUID = dicom.SPATIAL_REGISTRATION
    ds.SOPInstanceUID = dicom.derived_uid("test", "registration", source_frame)
    ds.FrameOfReferenceUID = dicom.derived_uid("test", "room")
    transform = Dataset()
    transform.FrameOfReferenceTransformationMatrixType = "RIGID"
    transform.FrameOfReferenceTransformationMatrix = [_ds(v) for v in np.ravel(matrix)]
    registration = Dataset()
    registration.MatrixSequence = [transform]
    item = Dataset()
    item.FrameOfReferenceUID = source_frame
    item.MatrixRegistrationSequence = [registration]
    ds.RegistrationSequence = [item]
    return dicom.encode(ds)


def _zip(files: dict[str, bytes]) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for name, data in files.items():
            archive.writestr(name, data)
    return buffer.getvalue()


def _plan_rois(globe_axes: Sequence[float] = (12.3, 12.3, 12.3)) -> list[tuple[str, str,
                                                                                list[Any]]]:
    cap, ring = _cornea_and_limbus(GLOBE_CENTRE, PLANNED_GAZE)
    other_eye, lens = GLOBE_CENTRE + np.array([-62.0, 0, 0]), GLOBE_CENTRE - np.array([0, 9, 0])
    return [("BODY", "EXTERNAL", _ellipsoid_contours(GLOBE_CENTRE, (80, 90, 40), 10.0)),
            ("Eye_R", "ORGAN", _ellipsoid_contours(GLOBE_CENTRE, globe_axes)),
            ("Eye_L", "ORGAN", _ellipsoid_contours(other_eye, (12.0, 12.0, 12.0))),
            ("Lens_R", "AVOIDANCE", _ellipsoid_contours(lens, (4, 2, 4))),
            ("Cornea_R", "ORGAN", [cap]), ("Limbus_R", "ORGAN", [ring])]


def test_an_rt_structure_set_gives_the_globe_cornea_and_limbus() -> None:
    data = _structure_set(_plan_rois())

    eye = dicom.read_planned_eye(dicom.read_dataset(data, "rs.dcm"), "right")

    assert (eye.globe_roi, eye.cornea_roi, eye.limbus_roi) == ("Eye_R", "Cornea_R", "Limbus_R")
    assert eye.frame_of_reference_uid == PLAN_FRAME
    np.testing.assert_allclose(eye.globe_centre_mm, GLOBE_CENTRE, atol=1e-5)
    assert eye.globe_radius_mm == pytest.approx(12.3, abs=1e-5)
    assert eye.globe_rms_mm < 1e-5
    np.testing.assert_allclose(eye.globe_semi_axes_mm, 12.3, atol=1e-4)
    assert eye.cornea_radius_mm == pytest.approx(7.8, abs=1e-4)
    assert eye.limbus_diameter_mm == pytest.approx(11.7, abs=1e-4)
    assert eye.gaze is not None
    np.testing.assert_allclose(eye.gaze, PLANNED_GAZE, atol=1e-6)
    with pytest.raises(FormatError, match=r"the globe ROIs \('Eye_R'\) are of the right"):
        dicom.read_planned_eye(dicom.read_dataset(_structure_set(_plan_rois()[1:2]), "rs.dcm"),
                               "left")


def test_the_planned_eye_imports_into_the_eye_model_and_reference(client: Client) -> None:
    semi_axes = (12.6, 12.1, 11.7)  # the globe's x, y (axial: anterior -y), z semi-axes
    assert client.put(f"{API}/patients/P-PLAN", json={"eye": "right"}).status_code == 201
    body = _zip({"plan/RS.dcm": _structure_set(_plan_rois(semi_axes)),
                 "plan/REG.dcm": _registration_to_wcs(TO_WCS)})

    response = client.post(f"{API}/patients/P-PLAN/fractions/2/dicom", content=body,
                           headers={"content-type": "application/zip"})
    operator = client.post(f"{API}/patients/P-PLAN/fractions/2/dicom", content=body,
                           headers={"content-type": "application/zip", **OPERATOR})
    in_use = client.get(f"{API}/patients/P-PLAN/fractions/2/reference").json()

    assert response.status_code == 201, response.text
    assert operator.status_code == 403
    ellipsoid = response.json()["eye_model"]["model"]["ellipsoid"]
    rotation = np.asarray(ellipsoid["orientation"])
    shape = rotation @ np.diag(np.asarray(ellipsoid["semi_axes_mm"]) ** 2) @ rotation.T
    expected = TO_WCS[:3, :3] @ np.diag(np.asarray(semi_axes) ** 2) @ TO_WCS[:3, :3].T
    np.testing.assert_allclose(shape, expected, atol=1e-3)  # the globe's shape, in the WCS
    np.testing.assert_allclose(ellipsoid["centre_mm"], GLOBE_CENTRE, atol=1e-4)
    reference = response.json()["reference"]
    assert reference == in_use
    assert reference["source"] == "plan"
    np.testing.assert_allclose(reference["pose"]["centre_mm"],
                               (TO_WCS @ [*GLOBE_CENTRE, 1.0])[:3], atol=1e-4)
    np.testing.assert_allclose(reference["pose"]["gaze"], [0.0, 0.0, 1.0], atol=1e-6)
    assert response.json()["read"]["planned_eye"]["limbus_roi"] == "Limbus_R"


def test_a_structure_set_alone_gives_a_sphere_and_no_reference(client: Client) -> None:
    assert client.put(f"{API}/patients/P-PLAN-2", json={"eye": "right"}).status_code == 201

    response = client.post(f"{API}/patients/P-PLAN-2/fractions/1/dicom",
                           content=_structure_set(_plan_rois()),
                           headers={"content-type": "application/dicom"})
    garbage = client.post(f"{API}/patients/P-PLAN-2/fractions/1/dicom", content=b"not dicom",
                          headers={"content-type": "application/dicom"})
    nobody = client.post(f"{API}/patients/P-nobody/fractions/1/dicom",
                         content=_structure_set(_plan_rois()),
                         headers={"content-type": "application/dicom"})

    assert response.status_code == 201, response.text
    assert response.json()["eye_model"]["model"]["globe_radius_mm"] == pytest.approx(12.3)
    assert response.json()["reference"] is None
    assert "no Spatial Registration" in response.json()["read"]["notes"][0]
    assert client.get(f"{API}/patients/P-PLAN-2/fractions/1/reference").status_code == 404
    assert garbage.status_code == 422
    assert nobody.status_code == 404
