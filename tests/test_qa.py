"""The daily QA (issue 40): runs on the simulated room's QA phantom, the lockout of position
verification and tracking, the physicist's override, the history, the trends and the report.

The arithmetic (rigid fit, drift, the drawing's distance) is checked on its own; then one daemon
with the lockout on (``qa.required``, the clinical default) serves the module, and the tests run
in file order as a morning would: locked without a baseline, a baseline, a moved phantom, the
next day, an override, a miscalibrated rig, a new calibration. They depend on each other's
state, so all of them are marked slow (the fast tier leaves the daemon's tests out together).
"""

from __future__ import annotations

import io
import json
import math
import typing
import zipfile
from collections.abc import Callable, Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from fastapi import FastAPI

from eyeserver.api import create_app
from eyeserver.api.routers.qa import Figure
from eyeserver.calibration.artefact import ARRAYS_FILE, CALIBRATION_FILE
from eyeserver.config import QaThresholds, Settings
from eyeserver.service.qa import DailyQa
from eyeserver.service.qa_figures import (
    EYE_PHANTOM_1,
    FIGURES,
    calibration_drift_mm,
    rigid_fit,
)
from tests.apiclient import API, OPERATOR_TOKEN, Client, auth, test_settings

OPERATOR = auth(OPERATOR_TOKEN)
QA_POSITION = [0.0, 0.0, 0.0]
"""Where the QA phantom's drawing puts the ball's centre (docs/qa.md)."""

# --- the arithmetic ---------------------------------------------------------------------------


def test_the_routes_figures_are_the_measured_ones() -> None:
    assert set(typing.get_args(Figure)) == set(FIGURES) == set(QaThresholds.model_fields)


def test_the_clinical_default_locks_and_the_deploy_file_keeps_it() -> None:
    assert Settings.load(data_dir=Path("/nonexistent")).qa.required
    deploy = Path(__file__).resolve().parents[1] / "deploy" / "eyeserver.toml"
    assert Settings.load(deploy).qa.required


def test_a_rigid_fit_recovers_a_rotation_and_a_translation() -> None:
    rng = np.random.default_rng(1)
    source = rng.normal(size=(12, 3)) * 10
    angle = math.radians(7.0)
    rotation = np.array([[math.cos(angle), -math.sin(angle), 0], [math.sin(angle),
                         math.cos(angle), 0], [0, 0, 1]])
    target = source @ rotation.T + [0.3, -0.2, 1.0]

    found_rotation, found_shift = rigid_fit(source, target)

    assert found_rotation == pytest.approx(rotation, abs=1e-12)
    assert found_shift == pytest.approx([0.3, -0.2, 1.0], abs=1e-12)
    with pytest.raises(ValueError, match="line"):
        rigid_fit(np.outer(np.arange(5.0), [1, 2, 3]), np.outer(np.arange(5.0), [1, 2, 3]))


def test_the_drift_is_blind_to_the_placement_but_not_to_a_unit_moving() -> None:
    baseline = {"left": [0.0, 0.0, 0.0], "right": [0.01, 0.0, 0.0]}
    placed_elsewhere = {"left": [0.5, 0.2, 0.0], "right": [0.51, 0.2, 0.0]}
    one_unit_moved = {"left": [0.0, 0.0, 0.0], "right": [0.01, 0.0, 0.08]}

    assert calibration_drift_mm(placed_elsewhere, baseline) == pytest.approx(0.0, abs=1e-12)
    assert calibration_drift_mm(one_unit_moved, baseline) == pytest.approx(0.08)
    assert calibration_drift_mm({"left": [0.0, 0.0, 0.0]}, baseline) is None  # a unit lost
    # One unit alone: its own centre, placement included.
    assert calibration_drift_mm({"left": [0.0, 0.03, 0.04]},
                                {"left": [0.0, 0.0, 0.0]}) == pytest.approx(0.05)


def test_the_drawing_lies_on_its_own_surfaces() -> None:
    drawing = EYE_PHANTOM_1
    on_ball = np.asarray(drawing.fiducials_mm[:16])
    on_plate = np.asarray(drawing.fiducials_mm[16:])
    assert drawing.distance(on_ball) == pytest.approx(0.0, abs=1e-9)
    assert drawing.distance(on_plate) == pytest.approx(0.0, abs=1e-9)
    moved = drawing.placed((0.0, 0.5, 0.0))
    assert drawing.distance(np.asarray(moved.fiducials_mm[16:])) == pytest.approx(0.0, abs=1e-9)
    assert drawing.distance(np.asarray([[0.0, 0.0, drawing.radius_mm + 0.2]])) == \
        pytest.approx([0.2])


# --- the daemon, lockout on --------------------------------------------------------------------


@pytest.fixture(scope="module")
def app(data_dir: Path) -> FastAPI:
    """The daemon with the clinical default: the daily QA locks verification and tracking."""
    return create_app(test_settings(data_dir, qa={"required": True}))


@pytest.fixture(scope="module")
def caldir(calibrated_rooms: Callable[[str], tuple[Path, Path]]) -> Path:
    return calibrated_rooms("default")[1]


def _import(client: Client, caldir: Path, change: Callable[[dict[str, Any]], None] | None = None,
            ) -> str:
    """Import (and activate) the calibration in ``caldir``, its document changed by ``change``."""
    document = json.loads((caldir / CALIBRATION_FILE).read_text())
    if change is not None:
        change(document)
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr(CALIBRATION_FILE, json.dumps(document))
        archive.writestr(ARRAYS_FILE, (caldir / ARRAYS_FILE).read_bytes())
    imported = client.post(f"{API}/calibrations", content=buffer.getvalue(),
                           headers={"content-type": "application/zip"})
    assert imported.status_code == 201, imported.text
    calibration = str(imported.json()["id"])
    assert client.post(f"{API}/calibrations/{calibration}/activate").status_code == 200
    return calibration


@pytest.fixture(scope="module")
def calibration_id(client: Client, caldir: Path) -> str:
    return _import(client, caldir)


@pytest.fixture(scope="module")
def qa(app: FastAPI, client: Client) -> DailyQa:
    assert client.get(f"{API}/qa/status").status_code == 200  # made on first use
    daily = app.state.qa
    assert isinstance(daily, DailyQa)
    return daily


@pytest.fixture
def tomorrow(qa: DailyQa) -> Iterator[None]:
    """The daemon's clock a day ahead for the test."""
    qa.clock = lambda: datetime.now(UTC) + timedelta(days=1)
    yield
    qa.clock = lambda: datetime.now(UTC)


def _place_phantom(client: Client, position: list[float] = QA_POSITION) -> None:
    placed = client.put(f"{API}/sim/scene", json={"kind": "eye_phantom_1",
                                                  "position_mm": position})
    assert placed.status_code == 200, placed.text


def _run(client: Client, expected: int = 201, **body: Any) -> Any:
    headers = body.pop("headers", {})
    response = client.post(f"{API}/qa/runs", json=body, headers=headers)
    assert response.status_code == expected, response.text
    return response.json()


def _locked(client: Client) -> str:
    """The 409 reasons of verification and tracking (they must agree)."""
    measured = client.post(f"{API}/pose/measure", json={"patient_id": "P-QA", "fraction": 1},
                           headers=OPERATOR)
    tracked = client.post(f"{API}/tracking/start", json={"patient_id": "P-QA", "fraction": 1},
                          headers=OPERATOR)
    assert (measured.status_code, tracked.status_code) == (409, 409), (measured.text,
                                                                       tracked.text)
    assert measured.json()["detail"].startswith("position verification is locked by the daily "
                                                "QA: ")
    assert tracked.json()["detail"].startswith("tracking is locked by the daily QA: ")
    return str(measured.json()["detail"])


def _unlocked(client: Client) -> None:
    """Verification and tracking pass the gate: the patient is unknown (404), not 409."""
    for path in ("pose/measure", "tracking/start"):
        response = client.post(f"{API}/{path}", json={"patient_id": "P-QA", "fraction": 1},
                               headers=OPERATOR)
        assert response.status_code == 404, response.text


@pytest.mark.slow
def test_without_an_active_calibration_everything_is_locked(client: Client, qa: DailyQa,
                                                            ) -> None:
    status = client.get(f"{API}/qa/status").json()
    assert status["locked"] and status["reason"] == "no calibration is active"
    assert "no calibration is active" in _locked(client)
    assert _run(client, 409)["detail"].startswith("no calibration is active")


@pytest.mark.slow
def test_a_calibration_without_a_qa_baseline_locks(client: Client, calibration_id: str) -> None:
    status = client.get(f"{API}/qa/status").json()

    assert status["locked"] and status["calibration_id"] == calibration_id
    assert f"the active calibration {calibration_id} has no QA baseline" in status["reason"]
    assert "has no QA baseline" in _locked(client)


@pytest.mark.slow
def test_an_operator_may_run_the_qa_but_not_set_a_baseline(client: Client,
                                                           calibration_id: str) -> None:
    _place_phantom(client)
    refused = client.post(f"{API}/qa/runs", json={"baseline": True}, headers=OPERATOR)
    assert refused.status_code == 403

    run = _run(client, frames=2, headers=OPERATOR)

    # Every figure is measured and within its threshold, but there is no baseline to pass.
    assert not run["passed"] and not run["baseline"] and run["actor"] == "operator"
    assert run["reasons"] == [f"calibration {calibration_id} has no QA baseline: a physicist "
                              "runs the QA with baseline=true once after activating it"]
    assert run["figures"]["drift_mm"] == {"value": None, "threshold": 0.05, "passed": False}
    assert all(f["passed"] for name, f in run["figures"].items() if name != "drift_mm")
    assert len(run["capture_ids"]) == 2
    assert "has no QA baseline" in _locked(client)


@pytest.mark.slow
def test_the_baseline_run_passes_and_lifts_the_lockout(client: Client,
                                                      calibration_id: str) -> None:
    run = _run(client, baseline=True)

    assert run["passed"] and run["baseline"] and run["reasons"] == []
    assert run["baseline_run_id"] == run["id"] and run["calibration_id"] == calibration_id
    figures = {name: f["value"] for name, f in run["figures"].items()}
    assert figures["drift_mm"] == 0.0
    # The healthy simulated room is far inside every threshold (docs/qa.md quotes them).
    assert figures["localisation_mm"] < 0.03 and figures["surface_mm"] < 0.02
    assert figures["fiducial_mm"] < 0.03 and figures["cross_unit_mm"] < 0.02
    assert 0.0 < figures["static_noise_mm"] < 0.015
    assert sorted(run["drift_vectors_mm"]) == ["left", "right"]
    status = client.get(f"{API}/qa/status").json()
    assert not status["locked"] and status["reason"] is None
    assert status["baseline_run_id"] == status["last_pass"] == run["id"]
    _unlocked(client)


@pytest.mark.slow
def test_a_moved_phantom_fails_and_locks_again(client: Client, qa: DailyQa) -> None:
    _place_phantom(client, [0.3, 0.0, 0.0])
    run = _run(client, frames=2)
    _place_phantom(client)

    assert not run["passed"]
    localisation = run["figures"]["localisation_mm"]
    assert localisation["value"] == pytest.approx(0.3, abs=0.03) and not localisation["passed"]
    assert run["reasons"] == [f"localisation_mm {localisation['value']:.3f} mm exceeds 0.1 mm"]
    # The units still agree with each other: the calibration has not drifted.
    assert run["figures"]["drift_mm"]["passed"] and run["figures"]["cross_unit_mm"]["passed"]
    status = client.get(f"{API}/qa/status").json()
    assert status["locked"] and status["failures_since_pass"] == 1
    assert "1 QA run(s) failed since today's pass" in _locked(client)
    # A clinic that allows one failed re-run after the pass is not locked by one.
    settings = qa.settings
    qa.settings = settings.model_copy(update={"max_consecutive_failures": 2})
    try:
        _unlocked(client)
    finally:
        qa.settings = settings
    _locked(client)


@pytest.mark.slow
def test_the_next_daily_run_passes_with_its_drift_measured(client: Client) -> None:
    baseline = client.get(f"{API}/qa/status").json()["baseline_run_id"]

    run = _run(client, headers=OPERATOR)

    assert run["passed"], run["reasons"]
    assert not run["baseline"] and run["baseline_run_id"] == baseline
    assert 0.0 < run["figures"]["drift_mm"]["value"] < 0.03
    _unlocked(client)


@pytest.mark.slow
def test_yesterdays_qa_does_not_count_today(client: Client, tomorrow: None) -> None:
    status = client.get(f"{API}/qa/status").json()

    assert status["locked"] and status["last_run"] is None
    assert "has not passed with calibration" in status["reason"]
    _locked(client)


@pytest.mark.slow
def test_a_physicist_overrides_the_lockout_with_a_reason_audited(
        client: Client, tomorrow: None, app: FastAPI, monkeypatch: pytest.MonkeyPatch) -> None:
    reason = "phantom <cracked>; position checked by X-ray clips instead"
    bus = app.state.service.events
    published: list[tuple[str, dict[str, Any]]] = []
    publish = bus.publish

    def recorded(type: str, **data: Any) -> int:
        published.append((type, data))
        return int(publish(type, **data))

    monkeypatch.setattr(bus, "publish", recorded)
    assert client.post(f"{API}/qa/override", json={"reason": reason},
                       headers=OPERATOR).status_code == 403
    assert client.post(f"{API}/qa/override", json={"reason": "   "}).status_code == 422

    overridden = client.post(f"{API}/qa/override", json={"reason": reason})

    assert overridden.status_code == 200, overridden.text
    status = overridden.json()
    assert not status["locked"] and "has not passed" in status["qa_reason"]
    assert status["override"]["reason"] == reason and status["override"]["actor"] == "physicist"
    _unlocked(client)
    audit = client.get(f"{API}/audit", params={"limit": 20}).json()["items"]
    given = [a for a in audit if a["action"] == "qa_override" and a["outcome"] == "ok"]
    assert given[0]["detail"]["reason"] == reason and given[0]["actor"] == "physicist"
    assert "has not passed" in given[0]["detail"]["lockout_reason"]
    # Nothing left to override; then withdrawn (audited), the lockout holds again.
    assert client.post(f"{API}/qa/override", json={"reason": reason}).status_code == 409
    withdrawn = client.delete(f"{API}/qa/override")
    assert withdrawn.status_code == 200 and withdrawn.json()["locked"]
    assert client.delete(f"{API}/qa/override").status_code == 404
    assert [a["action"] for a in client.get(f"{API}/audit").json()["items"]
            if a["action"].startswith("qa_override") and a["outcome"] == "ok"][:2] == [
                "qa_override_withdrawn", "qa_override"]
    _locked(client)
    # Every console hears of both (the event stream), the override named.
    override_id = status["override"]["id"]
    assert [(t, d) for t, d in published if t.startswith("qa.override")] == [
        ("qa.override", {"override_id": override_id, "actor": "physicist"}),
        ("qa.override_withdrawn", {"override_id": override_id, "actor": "physicist"})]


@pytest.mark.slow
def test_the_history_lists_every_run_and_its_trends(client: Client) -> None:
    listed = client.get(f"{API}/qa/runs").json()
    runs = listed["items"]
    assert listed["total"] == 4 and [r["passed"] for r in runs] == [True, False, True, False]
    assert [r["id"] for r in runs] == sorted((r["id"] for r in runs), reverse=True)
    assert client.get(f"{API}/qa/runs/{runs[1]['id']}").json() == runs[1]
    assert client.get(f"{API}/qa/runs/qa-nope").status_code == 404
    assert client.get(f"{API}/qa/runs", params={"day": "2001-01-01"}).json()["total"] == 0

    trends = client.get(f"{API}/qa/trends", params={"days": 7}).json()

    assert set(trends["figures"]) == set(FIGURES)
    localisation = trends["figures"]["localisation_mm"]
    assert [p["run_id"] for p in localisation["points"]] == [r["id"] for r in reversed(runs)]
    assert [p["passed"] for p in localisation["points"]] == [True, True, False, True]
    assert localisation["points"][2]["value"] == runs[1]["figures"]["localisation_mm"]["value"]
    assert [p["baseline"] for p in localisation["points"]] == [False, True, False, False]
    assert localisation["threshold"] == 0.1
    png = client.get(f"{API}/qa/trends/localisation_mm.png")
    assert png.status_code == 200 and png.headers["content-type"] == "image/png"
    image = cv2.imdecode(np.frombuffer(png.content, np.uint8), cv2.IMREAD_COLOR)
    assert image.shape == (260, 700, 3)
    # Red (BGR) marks the failed run.
    assert ((image[:, :, 2] > 180) & (image[:, :, 1] < 80) & (image[:, :, 0] < 80)).any()
    assert client.get(f"{API}/qa/trends/nothing_mm.png").status_code == 422


@pytest.mark.slow
def test_the_days_report_is_printable_html(client: Client) -> None:
    runs = client.get(f"{API}/qa/runs").json()["items"]

    report = client.get(f"{API}/qa/report")

    assert report.status_code == 200
    assert report.headers["content-type"].startswith("text/html")
    page = report.text
    assert page.startswith("<!DOCTYPE html>") and "@media print" in page
    assert all(r["id"] in page for r in runs)
    assert page.count('class="fail">FAIL') >= 2 and "exceeds 0.1 mm" in page
    assert page.count('src="data:image/png;base64,') == len(FIGURES)
    other = client.get(f"{API}/qa/report", params={"day": "2001-01-01"}).text
    assert "No QA run on this day." in other


@pytest.mark.slow
def test_the_days_report_escapes_and_shows_the_override(client: Client, tomorrow: None) -> None:
    reason = "phantom <b>gone</b> & back tomorrow"
    assert client.post(f"{API}/qa/override", json={"reason": reason}).status_code == 200
    try:
        page = client.get(f"{API}/qa/report").text
    finally:
        assert client.delete(f"{API}/qa/override").status_code == 200
    assert "phantom &lt;b&gt;gone&lt;/b&gt; &amp; back tomorrow" in page and "<b>gone" not in page
    assert "No QA run on this day." in page


@pytest.mark.slow
def test_a_miscalibrated_rig_cannot_become_a_baseline(client: Client, caldir: Path,
                                                      calibration_id: str) -> None:
    def shift_left_unit(document: dict[str, Any]) -> None:
        # Both cameras of the left unit claimed 0.3 mm further along +X than they stand.
        shift = np.array([0.3, 0.0, 0.0])
        for camera_id in ("S1", "S2"):
            camera = document["cameras"][camera_id]
            rotation = np.asarray(camera["R"])
            camera["T"] = (np.asarray(camera["T"]) - rotation @ shift).tolist()
            camera["centre_mm"] = (np.asarray(camera["centre_mm"]) + shift).tolist()

    perturbed = _import(client, caldir, shift_left_unit)
    try:
        assert "has no QA baseline" in _locked(client)  # a new calibration voids the baseline
        run = _run(client, baseline=True, frames=2)

        assert not run["passed"] and not run["baseline"] and run["baseline_run_id"] is None
        # The left unit's dots triangulate 0.3 mm along +X, the right unit's where they are:
        # placed by both, the phantom lands halfway and the dots miss the drawing by about
        # 0.15 mm. (The surfaces hardly move: mostly the plate, which the shift runs along.)
        failed = {name for name, f in run["figures"].items() if not f["passed"]}
        assert failed == {"localisation_mm", "fiducial_mm"}, run["figures"]
        assert run["figures"]["localisation_mm"]["value"] == pytest.approx(0.15, abs=0.03)
        status = client.get(f"{API}/qa/status").json()
        assert status["calibration_id"] == perturbed and status["baseline_run_id"] is None
        assert status["locked"]
    finally:
        assert client.post(f"{API}/calibrations/{calibration_id}/activate").status_code == 200
    # Back on the calibration with a baseline: today's pass with it counts again.
    assert client.get(f"{API}/qa/status").json()["baseline_run_id"] is not None


@pytest.mark.slow
def test_a_new_calibration_needs_a_new_baseline(client: Client, caldir: Path) -> None:
    renewed = _import(client, caldir)  # the same numbers, but another calibration

    status = client.get(f"{API}/qa/status").json()
    assert status["calibration_id"] == renewed and status["baseline_run_id"] is None
    assert f"the active calibration {renewed} has no QA baseline" in _locked(client)
    run = _run(client, baseline=True, frames=2)
    assert run["passed"] and run["baseline"]
    _unlocked(client)
