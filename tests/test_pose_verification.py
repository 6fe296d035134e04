"""Position verification (``POST /api/v1/pose/measure``) and the simulated eye (``/sim/eye``).

The deviation arithmetic is checked on its own; through the API, the mechanisms (capture,
reconstruction, storage, evidence, verdicts, errors) run with an injected fit for determinism,
then once end to end through the real fit on the simulated room. One app serves the module; the
tests run in file order (the first need a daemon without an active calibration).
"""

from __future__ import annotations

import io
import json
import math
import zipfile
from collections.abc import Callable, Iterator, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any, Literal

import httpx
import pytest
from anyio.from_thread import start_blocking_portal
from fastapi import FastAPI

from eyeserver.api import create_app
from eyeserver.api.auth import TokenTable
from eyeserver.api.routers.sim import NO_SIM_ROOM
from eyeserver.calibration.artefact import ARRAYS_FILE, CALIBRATION_FILE
from eyeserver.eye.fit import CloudLike, EyeModel, EyePose, PoseError, fit_eye
from eyeserver.eye.limbus import LimbusView
from eyeserver.eye.tunables import SHAPE_SD_MM
from eyeserver.hardware.sim.drivers import build_sim_rig
from eyeserver.hardware.sim.room import SimRoom
from eyeserver.io import rig_from_dict
from eyeserver.service.core import Service
from eyeserver.service.patients import ReferencePose, Tolerances
from eyeserver.service.verification import (
    MIN_UNIT_POINTS,
    PoseVerification,
    deviation,
    gaze_angle_deg,
    judge,
    measured_sd_mm,
    model_sd_mm,
    unit_contributions,
    unit_shortfalls,
)
from tests.apiclient import API, OPERATOR_TOKEN, Client, auth, test_settings

OPERATOR = auth(OPERATOR_TOKEN)
REFERENCE = {"centre_mm": [0.0, 0.0, -10.0], "gaze": [0.0, 0.0, 1.0]}


# --- the arithmetic ---------------------------------------------------------------------------


def test_the_deviation_is_measured_minus_reference() -> None:
    found = deviation((0.3, -0.1, -9.5), (0, 0, 1), (0.1, 0.1, -10.0), (0, 0, 1),
                      (0.3, 0.0, 2.0), (0.0, 0.0, 2.5))

    assert found.delta_mm == pytest.approx((0.2, -0.2, 0.5))
    assert found.length_mm == pytest.approx(math.sqrt(0.04 + 0.04 + 0.25))
    assert found.gaze_deg == 0.0
    assert found.limbus_delta_mm == pytest.approx((0.3, 0.0, -0.5))


@pytest.mark.parametrize("angle_deg", [0.01, 0.5, 1.0, 10.0, 90.0, 179.0])
def test_the_gaze_deviation_is_the_angle_between_the_gazes(angle_deg: float) -> None:
    a = math.radians(angle_deg)
    tilted = (math.sin(a) * 3.0, 0.0, math.cos(a) * 3.0)  # need not be a unit vector

    assert gaze_angle_deg((0, 0, 1), tilted) == pytest.approx(angle_deg, abs=1e-9)


@pytest.mark.parametrize(("delta", "gaze_deg", "confidence", "passed", "in_tolerance", "words"), [
    ((0.1, 0.1, 0.1), 0.5, 0.9, True, True, []),
    ((0.2, 0.0, 0.0), 1.0, 0.5, True, True, []),  # on the limits passes
    ((0.15, 0.15, 0.0), 0.0, 0.9, False, False, ["translation 0.212 mm exceeds 0.2 mm"]),
    ((0.0, 0.0, 0.0), 1.01, 0.9, False, False, ["gaze deviation 1.01° exceeds 1°"]),
    ((0.0, 0.0, 0.0), 0.0, 0.49, False, True, ["fit confidence 0.49 is below 0.5"]),
    ((math.nan, 0.0, 0.0), 0.0, 0.9, False, False, ["translation nan mm exceeds 0.2 mm"]),
])
def test_the_verdict_follows_the_tolerances(delta: tuple[float, float, float], gaze_deg: float,
                                            confidence: float, passed: bool,
                                            in_tolerance: bool, words: list[str]) -> None:
    found = deviation(delta, (0, 0, 1), (0, 0, 0), (0, 0, 1))
    found = type(found)(found.delta_mm, found.length_mm, gaze_deg)

    verdict = judge(found, Tolerances(), confidence)

    assert (verdict.passed, verdict.in_tolerance, list(verdict.reasons)) == \
        (passed, in_tolerance, words)


@pytest.mark.parametrize(("uncertain", "at_limit", "reason"), [
    # With population defaults the centre is known to ±0.65 mm (1 sd) along the gaze in
    # absolute terms (tunables.SHAPE_SD_MM): a planned pose cannot be checked to 0.2 mm. On the
    # limit (2 sd = half the tolerance) it passes.
    ({"model_sd_mm": SHAPE_SD_MM}, {"model_sd_mm": 0.05},
     "the eye model leaves the globe's shape uncertain (no MRI ellipsoid, or the error of the "
     "one given): against this reference the centre is known only to ±1.30 mm (2 sd) along "
     "the gaze, more than 0.5 of the 0.2 mm tolerance; enter the MRI's ellipsoid with its "
     "error (globe_sd_mm) in the eye model or capture a reference at set-up"),
    # A deviation whose own stated sd (the pose's with the reference's) along one axis exceeds
    # the tolerance says nothing: the fit could not tell in from out (a patient eye 0.5 mm off
    # passed at sd 0.24 mm before; docs/notes/patient-eye.md). On the limit (1 sd = the
    # tolerance) it passes.
    ({"measured_sd_mm": (0.01, 0.02, 0.24)}, {"measured_sd_mm": (0.2, 0.2, 0.2)},
     "the measurement states the centre's deviation (with the reference's sd) only to ±0.48 mm "
     "(2 sd), more than 2 × the 0.2 mm tolerance: the eye was seen too poorly to tell (the "
     "limbus or the sclera barely visible); measure again with the eye open, still and looking "
     "at the fixation light")], ids=["shape", "measured"])
def test_a_deviation_known_too_uncertainly_fails_within_the_tolerance(
        uncertain: dict[str, Any], at_limit: dict[str, Any], reason: str) -> None:
    found = replace(deviation((0.05, 0.0, 0.0), (0, 0, 1), (0, 0, 0), (0, 0, 1)), **uncertain)

    verdict = judge(found, Tolerances(), 0.9)

    assert not verdict.passed and verdict.in_tolerance
    assert verdict.reasons == (reason,)
    assert judge(replace(found, **at_limit), Tolerances(), 0.9).passed


def test_the_measured_sd_is_stored_and_weighed_against_the_patients_tolerance() -> None:
    found = replace(deviation((0.05, 0.0, 0.0), (0, 0, 1), (0, 0, 0), (0, 0, 1)),
                    measured_sd_mm=(0.01, 0.02, 0.24))

    assert found.to_dict()["measured_sd_mm"] == [0.01, 0.02, 0.24]
    assert judge(found, Tolerances(translation_mm=0.5), 0.9).passed
    assert not judge(replace(found, measured_sd_mm=(0.0, math.nan, 0.0)), Tolerances(),
                     0.9).passed


def test_the_measured_sd_counts_a_captured_references_own() -> None:
    pose = EyePose(centre_mm=(0.0, 0.0, -10.0), centre_sd_mm=(0.03, 0.04, 0.12),
                   globe_radius_mm=12.0, limbus_centre_mm=None, limbus_sd_mm=None,
                   gaze=(0.0, 0.0, 1.0), gaze_sd_deg=0.1, torsion_deg=None,
                   surface_mad_mm=0.05, sclera_points=1000, confidence=0.9)
    stored = {"centre_mm": [0.0, 0.0, -10.0], "gaze": [0.0, 0.0, 1.0]}
    planned = ReferencePose("P", 1, 1, "now", "someone", "plan", stored, None, None)
    captured = ReferencePose("P", 1, 2, "now", "someone", "capture", stored, None,
                             {"eye_model_version": None,
                              "fit": {"centre_sd_mm": [0.04, 0.03, 0.16]}})

    assert measured_sd_mm(pose, planned) == (0.03, 0.04, 0.12)  # a plan is exact
    assert measured_sd_mm(pose, captured) == pytest.approx((0.05, 0.05, 0.2))


def test_the_shape_cancels_against_a_reference_captured_with_the_same_model() -> None:
    tilt = math.radians(2.0)
    pose = EyePose(centre_mm=(0.0, 0.0, -10.0), centre_sd_mm=(0.01, 0.01, 0.01),
                   globe_radius_mm=12.0, limbus_centre_mm=None, limbus_sd_mm=None,
                   gaze=(0.0, math.sin(tilt), math.cos(tilt)), gaze_sd_deg=0.1,
                   torsion_deg=None, surface_mad_mm=0.05, sclera_points=1000, confidence=0.9,
                   shape_sd_mm=SHAPE_SD_MM)

    def reference(source: Literal["plan", "capture"], version: int | None) -> ReferencePose:
        evidence = None if source == "plan" else {"eye_model_version": version}
        return ReferencePose("P", 1, 1, "now", "someone", source,
                             {"centre_mm": [0.0, 0.0, -10.0], "gaze": [0.0, 0.0, 1.0]}, None,
                             evidence)

    # The same error of the same eye, but for the gaze's 2° turn: 0.65 × 2 sin 1°.
    turned = SHAPE_SD_MM * 2.0 * math.sin(tilt / 2.0)
    assert model_sd_mm(pose, reference("capture", None), None) == pytest.approx(turned)
    assert model_sd_mm(pose, reference("capture", 3), 3) == pytest.approx(turned)
    assert model_sd_mm(pose, reference("capture", 2), 3) == SHAPE_SD_MM  # another model
    assert model_sd_mm(pose, reference("plan", None), None) == SHAPE_SD_MM


# --- through the API --------------------------------------------------------------------------


class FakeFit:
    """A fit that answers a set pose (or raises), and remembers what it was given."""

    def __init__(self) -> None:
        self.centre = (0.0, 0.0, -10.0)
        self.gaze = (0.0, 0.0, 1.0)
        self.confidence = 0.9
        self.sd = 0.01
        self.error: str | None = None
        self.calls: list[tuple[int, EyeModel]] = []
        self.views: list[LimbusView] = []

    def __call__(self, cloud: CloudLike, model: EyeModel, views: Sequence[LimbusView] = ()
                 ) -> EyePose:
        self.calls.append((len(cloud.points), model))
        self.views = list(views)
        if self.error is not None:
            raise PoseError(self.error)
        return EyePose(centre_mm=self.centre, centre_sd_mm=(self.sd, self.sd, self.sd),
                       globe_radius_mm=12.0, limbus_centre_mm=None, limbus_sd_mm=None,
                       gaze=self.gaze, gaze_sd_deg=0.1, torsion_deg=None, surface_mad_mm=0.05,
                       sclera_points=1000, confidence=self.confidence)


@pytest.fixture(scope="module")
def fake_fit(app: FastAPI, client: Client) -> Iterator[FakeFit]:
    verification = app.state.verification
    assert isinstance(verification, PoseVerification)
    fake = FakeFit()
    verification.fit = fake
    yield fake
    verification.fit = fit_eye


@pytest.fixture(scope="module")
def patient(client: Client) -> str:
    assert client.put(f"{API}/patients/P-100", json={"eye": "right"}).status_code == 201
    assert client.put(f"{API}/patients/P-100/fractions/1/reference",
                      json=REFERENCE).status_code == 201
    return "P-100"


@pytest.fixture(scope="module")
def calibration_id(client: Client,
                   calibrated_rooms: Callable[[str], tuple[Path, Path]]) -> str:
    caldir = calibrated_rooms("default")[1]
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for name in (CALIBRATION_FILE, ARRAYS_FILE):
            archive.writestr(name, (caldir / name).read_bytes())
    imported = client.post(f"{API}/calibrations", content=buffer.getvalue(),
                           headers={"content-type": "application/zip"})
    assert imported.status_code == 201, imported.text
    calibration = imported.json()["id"]
    assert client.post(f"{API}/calibrations/{calibration}/activate").status_code == 200
    return str(calibration)


def _measure(client: Client, patient_id: str = "P-100", fraction: int = 1,
             expected: int = 201) -> Any:
    response = client.post(f"{API}/pose/measure", json={"patient_id": patient_id,
                                                        "fraction": fraction}, headers=OPERATOR)
    assert response.status_code == expected, response.text
    return response.json()


def test_without_an_active_calibration_nothing_is_captured_409(
        client: Client, patient: str, fake_fit: FakeFit) -> None:
    body = _measure(client, patient, expected=409)

    assert "no calibration is active" in body["detail"]
    assert client.get(f"{API}/captures").json()["total"] == 0


def test_unknown_patients_and_missing_references_are_404(client: Client, patient: str) -> None:
    unknown = _measure(client, "P-nobody", expected=404)
    no_reference = _measure(client, patient, fraction=7, expected=404)
    bad = client.post(f"{API}/pose/measure", json={"patient_id": patient, "fraction": 0})

    assert "no patient" in unknown["detail"]
    assert "fraction 7 has no reference pose" in no_reference["detail"]
    assert bad.status_code == 422


@pytest.mark.slow
def test_a_pose_at_the_reference_passes_with_its_evidence(
        client: Client, patient: str, fake_fit: FakeFit, calibration_id: str,
        data_dir: Path) -> None:
    fake_fit.centre, fake_fit.gaze = (0.05, -0.05, -9.95), (0.0, 0.0, 1.0)

    body = _measure(client, patient)

    assert body["passed"] is True and body["in_tolerance"] is True and body["reasons"] == []
    assert body["deviation"]["delta_mm"] == pytest.approx([0.05, -0.05, 0.05])
    assert body["deviation"]["length_mm"] == pytest.approx(math.sqrt(3) * 0.05)
    assert body["deviation"]["gaze_deg"] == 0.0
    assert body["deviation"]["measured_sd_mm"] == [0.01, 0.01, 0.01]  # the plan's exact
    assert body["tolerances"] == {"translation_mm": 0.2, "gaze_deg": 1.0, "min_confidence": 0.5}
    assert (body["patient_id"], body["fraction"], body["eye"]) == ("P-100", 1, "right")
    assert body["pose"]["centre_mm"] == [0.05, -0.05, -9.95]
    assert body["reference"] == {"version": 1, "source": "plan",
                                 "pose": {**REFERENCE, "limbus_centre_mm": None}}
    evidence = body["evidence"]
    assert evidence["calibration_id"] == calibration_id
    assert evidence["unit"] == "all"
    assert evidence["eye_model_version"] is None  # population defaults
    assert evidence["fit"] == body["pose"]
    assert evidence["cloud_points"] > 1000
    # The fit also saw the capture's fringe images, one per camera, for the limbus.
    assert sorted(v.camera.camera_id for v in fake_fit.views) == ["S1", "S2", "S3", "S4"]
    assert client.get(f"{API}/captures/{evidence['capture_id']}").status_code == 200
    assert client.get(f"{API}/captures/{evidence['capture_id']}/cloud.ply").status_code == 200
    assert fake_fit.calls[-1] == (evidence["cloud_points"], EyeModel.population())
    assert body["id"].startswith("pose-")
    # The capture is the stored result's evidence: it cannot be deleted.
    refused = client.delete(f"{API}/captures/{evidence['capture_id']}",
                            params={"reason": "tidy up"})
    assert refused.status_code == 409
    assert f"the evidence of pose measurement {body['id']}" in refused.json()["detail"]
    assert client.get(f"{API}/captures/{evidence['capture_id']}").status_code == 200


@pytest.mark.slow
def test_a_1_mm_shift_gaze_shift_or_poor_fit_fails(
        client: Client, patient: str, fake_fit: FakeFit, calibration_id: str) -> None:
    model = client.post(f"{API}/patients/{patient}/eye-models",
                        json={"globe_radius_mm": 12.2}).json()
    fake_fit.centre, fake_fit.gaze = (1.0, 0.0, -10.0), (0.0, 0.0, 1.0)
    shifted = _measure(client, patient)
    tilt = math.radians(2.0)
    fake_fit.centre, fake_fit.gaze = (0.0, 0.0, -10.0), (0.0, math.sin(tilt), math.cos(tilt))
    fake_fit.confidence = 0.3
    tilted = _measure(client, patient)
    fake_fit.gaze, fake_fit.confidence = (0.0, 0.0, 1.0), 0.9
    fake_fit.sd = 0.25  # in the tolerance, but the fit says it cannot tell
    vague = _measure(client, patient)
    fake_fit.sd = 0.01

    assert shifted["passed"] is False
    assert shifted["deviation"]["delta_mm"] == pytest.approx([1.0, 0.0, 0.0])
    assert shifted["reasons"] == ["translation 1.000 mm exceeds 0.2 mm"]
    assert shifted["evidence"]["eye_model_version"] == model["version"]
    assert shifted["evidence"]["eye_model"]["globe_radius_mm"] == 12.2
    assert fake_fit.calls[-2][1].globe_radius_mm == 12.2
    assert tilted["passed"] is False and tilted["in_tolerance"] is False
    assert tilted["deviation"]["gaze_deg"] == pytest.approx(2.0)
    assert tilted["reasons"] == ["gaze deviation 2.00° exceeds 1°",
                                 "fit confidence 0.30 is below 0.5"]
    assert vague["passed"] is False and vague["in_tolerance"] is True
    assert vague["deviation"]["measured_sd_mm"] == [0.25, 0.25, 0.25]
    assert [r[:57] for r in vague["reasons"]] == [
        "the measurement states the centre's deviation (with the r"]


def test_a_failed_fit_is_422_with_its_reason_and_audited(
        client: Client, patient: str, fake_fit: FakeFit, calibration_id: str,
        data_dir: Path) -> None:
    fake_fit.error = "too little sclera is visible (212 points): open the retractors"
    try:
        body = _measure(client, patient, expected=422)
    finally:
        fake_fit.error = None

    assert body["detail"] == "too little sclera is visible (212 points): open the retractors"
    last = json.loads((data_dir / "audit.jsonl").read_text().splitlines()[-1])
    assert (last["action"], last["outcome"]) == ("measure_pose", "error")
    assert last["detail"]["capture_id"].startswith("cap-")
    assert last["detail"]["patient_id"].startswith("hmac-sha256:")
    assert "P-100" not in (data_dir / "audit.jsonl").read_text()


def test_a_weak_pose_is_not_taken_as_the_reference(
        client: Client, patient: str, fake_fit: FakeFit, calibration_id: str,
        data_dir: Path) -> None:
    """Every later check compares with the reference: a pose below the patient's
    min_confidence, or stating its centre less well than the tolerance, is refused with the
    reason (422), audited, and the reference stays."""
    before = client.get(f"{API}/patients/{patient}/fractions/1/reference").json()
    fake_fit.confidence = 0.18
    try:
        refused = client.post(f"{API}/patients/{patient}/fractions/1/reference/capture",
                              headers=OPERATOR)
        fake_fit.confidence, fake_fit.sd = 0.9, 0.21
        vague = client.post(f"{API}/patients/{patient}/fractions/1/reference/capture",
                            headers=OPERATOR)
    finally:
        fake_fit.confidence, fake_fit.sd = 0.9, 0.01

    assert refused.status_code == 422, refused.text
    assert refused.json()["detail"] == (
        "cannot take this capture as the reference: the eye was fitted at confidence 0.18, "
        "below the patient's min_confidence 0.5 (the limbus not seen well: capture again "
        "with the eye open, still and looking at the fixation light)")
    assert vague.status_code == 422, vague.text
    assert vague.json()["detail"] == (
        "cannot take this capture as the reference: the measurement states the centre only to "
        "±0.42 mm (2 sd), more than 2 × the 0.2 mm tolerance: the eye was seen too poorly to "
        "tell (the limbus or the sclera barely visible); measure again with the eye open, "
        "still and looking at the fixation light")
    assert client.get(f"{API}/patients/{patient}/fractions/1/reference").json() == before
    last = json.loads((data_dir / "audit.jsonl").read_text().splitlines()[-1])
    assert (last["action"], last["outcome"]) == ("set_reference_pose", "error")
    # At the patient's confidence the same capture is taken.
    taken = client.post(f"{API}/patients/{patient}/fractions/2/reference/capture",
                        headers=OPERATOR)
    assert taken.status_code == 201, taken.text


def test_a_reference_whose_own_open_eye_looks_shut_is_refused(
        client: Client, patient: str, fake_fit: FakeFit, calibration_id: str) -> None:
    """Live tracking takes frames for a blink where its blink test finds lids inside the limbus
    about the reference's gaze: a reference whose own capture of the open eye looks shut there
    (a gaze 20° off, at a confidence that passes, on an eye with a narrow lid opening) is
    refused with the reason; the same capture with the true gaze is taken."""
    scene = client.get(f"{API}/sim/scene").json()
    placed = client.put(f"{API}/sim/scene", json={
        "kind": "eye", "position_mm": [1.5, -1.0, -11.0],
        "eye": {"gaze_deg": [7.0, -4.0], "aperture_mm": [9.0, 5.5]}}, headers=OPERATOR)
    assert placed.status_code == 200, placed.text
    truth = client.get(f"{API}/sim/eye").json()["eye"]
    gaze = truth["gaze"]
    across = [0.0, gaze[2], -gaze[1]]  # gaze × x̂: a direction across the gaze
    norm = math.hypot(*across)
    turn = math.radians(20.0)
    fake_fit.centre = tuple(truth["centre_mm"])
    fake_fit.gaze = tuple(math.cos(turn) * g + math.sin(turn) * a / norm
                          for g, a in zip(gaze, across, strict=True))
    try:
        refused = client.post(f"{API}/patients/{patient}/fractions/3/reference/capture",
                              headers=OPERATOR)
        fake_fit.gaze = tuple(gaze)
        taken = client.post(f"{API}/patients/{patient}/fractions/3/reference/capture",
                            headers=OPERATOR)
    finally:
        fake_fit.centre, fake_fit.gaze = (0.0, 0.0, -10.0), (0.0, 0.0, 1.0)
        client.put(f"{API}/sim/scene", json=scene, headers=OPERATOR)

    assert refused.status_code == 422, refused.text
    assert refused.json()["detail"] == (
        "cannot take this capture as the reference: live tracking's blink test finds shut "
        "lids inside the limbus this pose places on the open eye (its gaze or globe is off, "
        "or the lids were closing): capture again with the eye open, still and looking at "
        "the fixation light")
    assert taken.status_code == 201, taken.text


@pytest.mark.slow  # it lists the measurements of the tests above, slow ones among them
def test_measurements_are_found_by_patient_fraction_and_id(
        client: Client, patient: str, calibration_id: str) -> None:
    listed = client.get(f"{API}/pose/measurements", params={"patient_id": patient},
                        headers=OPERATOR).json()
    by_fraction = client.get(f"{API}/pose/measurements",
                             params={"patient_id": patient, "fraction": 2}).json()
    newest = listed["items"][0]
    again = client.get(f"{API}/pose/measurements/{newest['id']}", headers=OPERATOR)
    unknown = client.get(f"{API}/pose/measurements/pose-20260101T000000000Z-0000")
    nobody = client.get(f"{API}/pose/measurements", params={"patient_id": "P-nobody"})

    assert listed["total"] == 4  # the failed fit stored nothing
    assert [m["passed"] for m in listed["items"]] == [False, False, False, True]  # newest 1st
    assert by_fraction["total"] == 0
    assert again.status_code == 200 and again.json() == newest
    assert unknown.status_code == 404
    assert nobody.status_code == 404


def test_a_dark_projector_fails_the_measurement_and_keeps_the_capture(
        client: Client, patient: str, fake_fit: FakeFit, calibration_id: str,
        data_dir: Path) -> None:
    # Issue 35: with one unit's projector dark the other unit's pose passed (confidence 0.94)
    # and nothing in the record said so. A projector driven at zero is as dark as a dead LED,
    # and its driver answers: only the images tell.
    before = client.get(f"{API}/pose/measurements", params={"patient_id": patient}).json()
    dimmed = client.request("PATCH", f"{API}/devices/P2", json={"intensity": 0.0})
    assert dimmed.status_code == 200, dimmed.text
    try:
        failed = _measure(client, patient, expected=503)
        status = client.get(f"{API}/status").json()
    finally:
        relit = client.request("PATCH", f"{API}/devices/P2", json={"intensity": 1.0})
    after = client.get(f"{API}/pose/measurements", params={"patient_id": patient}).json()

    detail = failed["detail"]
    assert detail.startswith("P2: no fringes in the frames it lit (S3, S4: contrast 0.0")
    assert "the projector gives no light" in detail
    assert after["total"] == before["total"]  # no pose from the other unit alone
    assert status["state"] == "fault"
    p2 = next(d for d in status["devices"] if d["id"] == "P2")
    assert p2["health"] == "fault" and "no fringes" in p2["reason"]
    # The capture is kept, with each camera's check in its bundle.
    capture_id = detail.rsplit("(capture ", 1)[1].split(" kept)")[0]
    bundle = json.loads((data_dir / "captures" / capture_id / "bundle.json").read_text())
    checks = bundle["fringe_check"]
    assert checks["S3"]["dark"] is True and checks["S4"]["dark"] is True
    assert checks["S1"]["dark"] is False and checks["S1"]["contrast"] > 0.3
    # Lit again, the next capture clears the fault (PATCH reopened nothing by hand).
    assert relit.status_code == 200, relit.text
    lit = _measure(client, patient)
    assert lit["passed"] is True
    assert client.get(f"{API}/status").json()["state"] == "idle"
    assert min(u["points"] for u in lit["evidence"]["units"].values()) >= MIN_UNIT_POINTS


def test_a_unit_that_gives_too_few_points_voids_a_measurement() -> None:
    rig = rig_from_dict({"format": "eyeserver.rig/1",
                             "cameras": [{"id": c, "width": 640, "height": 512}
                                         for c in ("S1", "S2", "S3", "S4")],
                             "projectors": [{"id": "P1"}, {"id": "P2"}],
                             "units": [{"id": "left", "projector": "P1", "cameras": ["S1", "S2"]},
                                       {"id": "right", "projector": "P2",
                                        "cameras": ["S3", "S4"]}]}, "<test rig>")
    summary = {"cameras": {"S1": {"points": 9000}, "S2": {"points": 8000},
                           "S3": {"points": 300}}}  # S4 gave nothing at all

    units = unit_contributions(summary, rig, ["left", "right"])

    assert units == {"left": {"points": 17000, "cameras": {"S1": 9000, "S2": 8000}},
                     "right": {"points": 300, "cameras": {"S3": 300, "S4": 0}}}
    (reason,) = unit_shortfalls(units)
    assert reason.startswith(f"unit right gave 300 points (at least {MIN_UNIT_POINTS} needed)")
    assert unit_shortfalls(unit_contributions(summary, rig, ["left"])) == ()


# --- the simulated eye --------------------------------------------------------------------------


def test_the_simulated_eye_is_posed_and_read_back(client: Client) -> None:
    placed = client.put(f"{API}/sim/eye", json={"position_mm": [0.5, -0.3, -10.0],
                                                "gaze_deg": [3.0, 0.0],
                                                "globe_radius_mm": 12.4}, headers=OPERATOR)
    kept = client.put(f"{API}/sim/eye", json={"gaze_deg": [0.0, 0.0]})
    read = client.get(f"{API}/sim/eye", headers=OPERATOR)

    assert placed.status_code == 200, placed.text
    eye = placed.json()["eye"]
    assert eye["centre_mm"] == pytest.approx([0.5, -0.3, -10.0])
    assert gaze_angle_deg(eye["gaze"], (0, 0, 1)) == pytest.approx(3.0)
    assert eye["globe_radius_mm"] == 12.4
    assert kept.json()["eye"]["centre_mm"] == pytest.approx([0.5, -0.3, -10.0])  # kept
    assert kept.json()["scene"]["eye"]["globe_radius_mm"] == 12.4
    assert read.json()["eye"]["gaze"] == pytest.approx([0.0, 0.0, 1.0])


def test_a_motion_script_starts_and_stops(client: Client) -> None:
    script = {"drift_deg": 0, "saccade_rate_hz": 0,
              "script": [{"t_s": 0.0, "kind": "saccade", "gaze_deg": [5.0, 0.0],
                          "duration_s": 0.001}]}
    moving = client.put(f"{API}/sim/eye", json={"motion": script})
    after_saccade = client.get(f"{API}/sim/eye").json()["eye"]["gaze"]
    still = client.put(f"{API}/sim/eye", json={"motion": None})

    assert moving.status_code == 200, moving.text
    assert moving.json()["scene"]["eye"]["motion"]["script"][0]["kind"] == "saccade"
    assert gaze_angle_deg(after_saccade, (0, 0, 1)) == pytest.approx(5.0, abs=1e-6)
    assert still.json()["scene"]["eye"]["motion"] is None


def test_the_moving_eye_is_rendered_ahead_for_a_unit(client: Client) -> None:
    still_eye = client.post(f"{API}/sim/eye/prerender", json={"unit": "left", "seconds": 0.2})
    script = {"drift_deg": 0.05, "saccade_rate_hz": 0}
    client.put(f"{API}/sim/eye", json={"motion": script})
    ahead = client.post(f"{API}/sim/eye/prerender", json={"unit": "left", "seconds": 0.2})
    status = client.get(f"{API}/sim/eye/prerender")
    script_s = client.get(f"{API}/sim/eye").json()["t_s"]
    wrong = [client.post(f"{API}/sim/eye/prerender", json=body) for body in (
        {"unit": "middle", "seconds": 1}, {"unit": "left", "seconds": 0},
        {"unit": "left", "seconds": 1000}, {"unit": "left"})]
    client.put(f"{API}/sim/eye", json={"motion": None})
    forgotten = client.get(f"{API}/sim/eye/prerender")

    assert still_eye.status_code == 422 and "not a moving eye" in still_eye.json()["detail"]
    assert ahead.status_code == 200, ahead.text
    body = ahead.json()
    assert body["unit"] == "left" and body["frames"] == 5 and body["rate_hz"] == 25.0
    assert body["megabytes"] == pytest.approx(2 * 5 * 640 * 512 / 1e6, abs=0.1)
    assert status.json() == {c: {"left": 5, "used": 0, "live": 0} for c in body["cameras"]}
    assert 0 <= script_s < 1.0  # the script restarted when the frames were ready
    assert [w.status_code for w in wrong] == [422, 422, 422, 422]
    assert "no unit 'middle'" in wrong[0].json()["detail"]
    assert forgotten.json() == {}


@pytest.mark.parametrize("body", [{"limbus_diameter_mm": 15.5, "cornea_radius_mm": 7.0},
                                  {"globe_radius_mm": 30}, {"motion": {"blink_rate_hz": -1}},
                                  {"spin": 1}])
def test_an_impossible_simulated_eye_is_422(client: Client, body: dict[str, Any]) -> None:
    before = client.get(f"{API}/sim/eye").json()

    response = client.put(f"{API}/sim/eye", json=body)

    assert response.status_code == 422, response.text
    assert client.get(f"{API}/sim/eye").json()["scene"] == before["scene"]


def test_sim_eye_on_another_scene_and_on_real_hardware(client: Client,
                                                       tmp_path: Path) -> None:
    client.put(f"{API}/sim/scene", json={"kind": "pyramid"})
    not_an_eye = client.get(f"{API}/sim/eye")
    client.put(f"{API}/sim/eye", json={})  # the eye again, for the tests after

    settings = test_settings(tmp_path / "data")
    app = create_app(settings)
    with Service(settings, rig=build_sim_rig(SimRoom())) as service:
        app.state.tokens = TokenTable.for_settings(settings)
        app.state.service = service
        with start_blocking_portal() as portal, \
                portal.wrap_async_context_manager(httpx.AsyncClient(
                    transport=httpx.ASGITransport(app=app), base_url="http://test")) as http:
            real = Client(portal, http)
            answers = [real.get(f"{API}/sim/eye"), real.put(f"{API}/sim/eye", json={})]

    assert not_an_eye.status_code == 409
    assert "not the patient eye" in not_an_eye.json()["detail"]
    assert [a.status_code for a in answers] == [404, 404]
    assert all(a.json() == {"detail": NO_SIM_ROOM} for a in answers)


# --- end to end through the real fit --------------------------------------------------------


@pytest.mark.slow
def test_end_to_end_a_captured_reference_then_a_1_mm_shift(
        app: FastAPI, client: Client, calibration_id: str) -> None:
    verification = app.state.verification
    assert isinstance(verification, PoseVerification)
    verification.fit = fit_eye
    assert client.put(f"{API}/patients/P-200", json={"eye": "left"}).status_code == 201
    assert client.put(f"{API}/sim/eye", json={"position_mm": [0.0, 0.0, -10.0],
                                              "gaze_deg": [0.0, 0.0], "motion": None}
                      ).status_code == 200

    reference = client.post(f"{API}/patients/P-200/fractions/1/reference/capture")
    assert reference.status_code == 201, reference.text
    same = _measure(client, "P-200")
    client.put(f"{API}/sim/eye", json={"position_mm": [1.0, 0.0, -10.0]})
    shifted = _measure(client, "P-200")

    ref = reference.json()
    assert ref["source"] == "capture"
    assert ref["evidence"]["calibration_id"] == calibration_id
    refused = client.delete(f"{API}/captures/{ref['evidence']['capture_id']}",
                            params={"reason": "tidy up"})
    assert refused.status_code == 409
    assert "the evidence of version 1 of a reference pose of fraction 1" in refused.json()[
        "detail"]
    # Absolute accuracy is the bench's (eyeserver bench pose); here a guard: the radius fitted
    # from a narrow band of sclera leaves the centre ≈ 0.2 mm off along the gaze.
    assert ref["pose"]["centre_mm"] == pytest.approx([0.0, 0.0, -10.0], abs=0.3)
    assert gaze_angle_deg(ref["pose"]["gaze"], [0.0, 0.0, 1.0]) < 0.5
    assert ref["evidence"]["fit"]["gaze_source"] == "limbus (images)"
    # The same still eye twice agrees well within the clinical tolerance (measured: 0.009 mm,
    # 0.05°; the globe radius is held from the reference); a 1 mm shift is a clear fail
    # (measured 0.98 mm).
    assert same["deviation"]["length_mm"] < 0.05
    assert same["deviation"]["gaze_deg"] < 0.3
    # The population model's unknown globe shape cancels against the captured reference.
    assert same["pose"]["shape_sd_mm"] == SHAPE_SD_MM
    assert same["deviation"]["model_sd_mm"] < 0.01
    assert same["passed"] is True, same["reasons"]
    assert shifted["passed"] is False
    assert shifted["deviation"]["delta_mm"] == pytest.approx([1.0, 0.0, 0.0], abs=0.1)
