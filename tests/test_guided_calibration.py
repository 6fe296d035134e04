"""Guided calibration through the API on the simulated room, jobs, and calibration versions.

The proof: a stereo session (the board moved with ``PUT /sim/chessboard``) and a phase-to-height
session (the plate moved by the daemon's simulated stage) calibrate the room end to end; the
result, activated, reconstructs a pyramid within 0.05 mm (median) of its exact surface.

To keep the module near two minutes, the stereo session takes the poses of the offline
calibration set in order only until the daemon answers ``ready`` (eight of the twelve), and the
phase-to-height session covers −8…+10 mm (the pyramid's −6…+6 mm and the reference plane) at
the heights the session asks for: it measures the room's fringe sensitivity on the reference
plane and a probe plate 1 mm from it (≈ 1.4 rad/mm at the steepest pixels) and plans planes
at most 1.7 mm apart, so that no step of the unwrapping along Z moves a phase by π
(docs/design.md §5).
"""

from __future__ import annotations

import io
import itertools
import math
import threading
import time
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from eyeserver.bench.daemon import zip_directory
from eyeserver.calibration.phase_height import heights_needed, safe_step_mm
from eyeserver.hardware.sim.config import load_room
from eyeserver.hardware.sim.scoring import score_cloud
from eyeserver.hardware.sim.sessions import calibration_poses
from eyeserver.io import read_ply
from eyeserver.service.calibration_session import PlateStep, Session
from eyeserver.service.events import EventBus
from eyeserver.service.jobs import JobContext, Jobs
from eyeserver.service.workers import QueueFullError
from tests.apiclient import API, OPERATOR_TOKEN, Client, auth

Z_RANGE = [-8.0, 10.0]
REFERENCE_Z = 10.0
PROBE_Z = 9.0


def _ok(response: Any, status: int = 200) -> Any:
    assert response.status_code == status, response.text
    return response.json()


def _wait_job(client: Client, job_id: str, timeout_s: float = 120) -> dict[str, Any]:
    deadline = time.monotonic() + timeout_s
    while True:
        job = _ok(client.get(f"{API}/jobs/{job_id}"))
        if job["state"] in ("succeeded", "failed", "cancelled"):
            return dict(job)
        assert time.monotonic() < deadline, job
        time.sleep(0.2)


# --- jobs, without the rig ------------------------------------------------------------------

def _jobs(capacity: int = 2) -> tuple[Jobs, EventBus]:
    bus = EventBus()
    jobs = Jobs(bus, capacity)
    jobs.start()
    return jobs, bus


def test_a_job_reports_progress_and_its_result() -> None:
    jobs, _ = _jobs()
    seen: list[float] = []

    def work(context: JobContext) -> dict[str, Any]:
        for k in range(4):
            context.progress(k / 4, f"step {k}")
            seen.append(jobs.get(context.job_id).progress)
        return {"answer": 42}

    try:
        job = jobs.submit("test", work, actor="tester")
        done = jobs.wait(job.id, 5)
    finally:
        jobs.stop()
    assert done.state == "succeeded" and done.result == {"answer": 42}
    assert done.progress == 1.0 and seen == [0.0, 0.25, 0.5, 0.75]
    assert done.actor == "tester" and done.started and done.finished


def test_a_failed_job_keeps_the_reason_and_what_it_finished() -> None:
    jobs, _ = _jobs()

    def work(context: JobContext) -> dict[str, Any]:
        context.progress(0.5, "half", partial={"done": ["a"]})
        raise ValueError("the plate was not where the bundle says")

    try:
        done = jobs.wait(jobs.submit("test", work, actor="t").id, 5)
    finally:
        jobs.stop()
    assert done.state == "failed"
    assert done.error == "the plate was not where the bundle says"
    assert done.result == {"done": ["a"]}


def test_cancelling_stops_a_running_job_at_its_next_check_and_a_queued_one_at_once() -> None:
    jobs, _ = _jobs()
    started, release = threading.Event(), threading.Event()

    def slow(context: JobContext) -> dict[str, Any]:
        started.set()
        release.wait(5)
        context.check_cancelled()
        return {}

    try:
        running = jobs.submit("slow", slow, actor="t")
        queued = jobs.submit("slow", slow, actor="t")
        assert started.wait(5)
        assert jobs.cancel(queued.id).state == "cancelled"
        assert jobs.cancel(running.id).state == "running"  # it stops at its next check
        release.set()
        assert jobs.wait(running.id, 5).state == "cancelled"
    finally:
        jobs.stop()
    assert jobs.get(queued.id).started is None


def test_the_job_queue_is_bounded() -> None:
    jobs, _ = _jobs(capacity=1)
    release = threading.Event()

    def blocked(context: JobContext) -> dict[str, Any]:
        release.wait(5)
        return {}

    try:
        jobs.submit("b", blocked, actor="t")
        time.sleep(0.1)  # the first one is running
        jobs.submit("b", blocked, actor="t")
        with pytest.raises(QueueFullError):
            jobs.submit("b", blocked, actor="t")
    finally:
        release.set()
        jobs.stop()


# --- the API --------------------------------------------------------------------------------

def test_operators_may_not_calibrate(client: Client) -> None:
    response = client.post(f"{API}/calibration-sessions", json={"kind": "stereo"},
                           headers=auth(OPERATOR_TOKEN))
    assert response.status_code == 403, response.text


def test_unknown_jobs_answer_404(client: Client) -> None:
    assert client.get(f"{API}/jobs/job-000000000000").status_code == 404
    assert client.post(f"{API}/jobs/job-000000000000/cancel").status_code == 404


@pytest.mark.slow
def test_guided_calibration_end_to_end(client: Client, tmp_path: Path) -> None:
    started = time.monotonic()
    # --- stereo ---
    session = _ok(client.post(f"{API}/calibration-sessions", json={"kind": "stereo"}), 201)
    sid = session["id"]
    assert _ok(client.get(f"{API}/status"))["state"] == "calibrating"
    refused = client.post(f"{API}/captures", json={"unit": "all"})
    assert refused.status_code == 409 and "calibrating" in refused.json()["detail"]
    # Only one session holds the rig.
    assert client.post(f"{API}/calibration-sessions",
                       json={"kind": "stereo"}).status_code == 409

    answers = []
    for n, (position, rotation) in enumerate(calibration_poses()):
        # The guidance at work: views are added until the daemon says the session is ready.
        _ok(client.put(f"{API}/sim/chessboard",
                       json={"position_mm": position, "rotation_deg": rotation}))
        answer = _ok(client.post(f"{API}/calibration-sessions/{sid}/views"), 201)
        answers.append(answer)
        assert answer["origin"] == (n == 0)
        if answer["ready"]:
            break
    first, last = answers[0], answers[-1]
    assert all(first["found"].values())
    assert not first["ready"] and any("needs 4" in m for m in first["missing"])
    for camera in first["cameras"].values():
        assert 0 < camera["coverage"] < 1 and camera["views_found"] == 1
        assert camera["origin_found"]
    assert last["ready"], last["missing"]
    # Solving before ready is refused; now it is accepted and releases the daemon.
    job = _ok(client.post(f"{API}/calibration-sessions/{sid}/solve"), 202)
    assert _ok(client.get(f"{API}/status"))["state"] in ("idle", "fault")
    stereo = _wait_job(client, job["id"])
    assert stereo["state"] == "succeeded", stereo["error"]
    stereo_id = stereo["result"]["calibration_id"]
    stereo_cal = _ok(client.get(f"{API}/calibrations/{stereo_id}"))
    assert stereo_cal["quality"]["reprojection_median_px"] < 0.15
    assert stereo_cal["parent_id"] is None and stereo_cal["session_id"] == sid
    assert _ok(client.get(f"{API}/calibration-sessions/{sid}"))["state"] == "done"
    stereo_s = time.monotonic() - started

    # --- phase to height on the stage, at the heights the session asks for ---
    session = _ok(client.post(f"{API}/calibration-sessions", json={
        "kind": "phase-height", "calibration_id": stereo_id, "z_range_mm": Z_RANGE}), 201)
    pid = session["id"]
    # A stereo parent says nothing of the fringes: the session asks for the probe first.
    assert session["plan"]["needed_heights_mm"] is None and not session["ready"]
    assert "probe plate 1 mm from it" in session["plan"]["next"]
    _ok(client.put(f"{API}/sim/scene", json={"kind": "reference",
                                             "position_mm": [0, 0, REFERENCE_Z]}))
    reference = _ok(client.post(f"{API}/calibration-sessions/{pid}/reference",
                                json={"z_mm": REFERENCE_Z}), 201)
    assert reference["plan"]["next"] == "a probe plate at Z = +9.00 or +11.00 mm, to measure " \
        "this rig's fringe sensitivity"
    probe = _ok(client.post(f"{API}/calibration-sessions/{pid}/plates",
                            json={"z_mm": PROBE_Z, "move_stage": True}), 201)
    plan = probe["plan"]
    assert set(plan["sensitivity_rad_per_mm"]) == {"S1", "S2", "S3", "S4"}
    assert all(1.0 < s < 2.0 for s in plan["sensitivity_rad_per_mm"].values()), plan
    assert plan["sensitivity_source"].startswith("measured: the plate at Z = +9.00 mm")
    assert 1.2 <= plan["max_step_mm"] <= 2.0
    planes = sorted([REFERENCE_Z, PROBE_Z, *plan["needed_heights_mm"]])
    assert planes[0] == Z_RANGE[0] and planes[-1] == Z_RANGE[1]
    assert max(b - a for a, b in itertools.pairwise(planes)) <= plan[
        "max_step_mm"] + 0.01
    assert any("no two neighbouring planes" in m for m in probe["missing"])
    refused = client.post(f"{API}/calibration-sessions/{pid}/solve")  # not ready: says why
    assert refused.status_code == 409 and "the plate at Z = " in refused.json()["detail"]
    for z in plan["needed_heights_mm"]:
        step = _ok(client.post(f"{API}/calibration-sessions/{pid}/plates",
                               json={"z_mm": z, "move_stage": True}), 201)
        assert step["moved_by_stage"]
    assert step["ready"], step["missing"]
    assert step["plan"]["needed_heights_mm"] == [] and step["plan"]["next"] == "solve"
    plates = len(plan["needed_heights_mm"]) + 1
    job = _ok(client.post(f"{API}/calibration-sessions/{pid}/solve"), 202)
    p2h = _wait_job(client, job["id"])
    assert p2h["state"] == "succeeded", p2h["error"]
    p2h_id = p2h["result"]["calibration_id"]
    p2h_cal = _ok(client.get(f"{API}/calibrations/{p2h_id}"))
    assert p2h_cal["parent_id"] == stereo_id
    assert p2h_cal["version"] == stereo_cal["version"] + 1
    assert p2h_cal["quality"]["p2h_residual_median_mm"] < 0.03
    p2h_s = time.monotonic() - started - stereo_s

    # --- measure with it ---
    _ok(client.post(f"{API}/calibrations/{p2h_id}/activate"))
    _ok(client.put(f"{API}/sim/scene", json={"kind": "pyramid"}))
    capture = _ok(client.post(f"{API}/captures", json={"unit": "all"}), 201)
    truth = _ok(client.get(f"{API}/sim/truth"))
    job = _ok(client.post(f"{API}/jobs/reconstructions",
                          json={"capture_ids": [capture["id"]]}), 202)
    batch = _wait_job(client, job["id"])
    assert batch["state"] == "succeeded" and batch["progress"] == 1.0
    assert [d["capture_id"] for d in batch["result"]["done"]] == [capture["id"]]
    (tmp_path / "cloud.ply").write_bytes(
        _ok_bytes(client, f"{API}/captures/{capture['id']}/cloud.ply"))
    cloud = read_ply(tmp_path / "cloud.ply")
    score = score_cloud(truth, cloud, load_room(None))
    print(f"guided calibration: stereo {stereo_s:.0f} s "
          f"({stereo_cal['quality']['reprojection_median_px']:.3f} px), p2h {p2h_s:.0f} s "
          f"({p2h_cal['quality']['p2h_residual_median_mm']:.4f} mm), pyramid median "
          f"{score['median_mm']:.4f} mm over {score['points']} points")
    assert score["median_mm"] < 0.05

    # --- compare and download ---
    drift = _ok(client.get(f"{API}/calibrations/compare", params={"a": stereo_id, "b": p2h_id}))
    for camera in drift["cameras"].values():  # same geometry: no drift, no p2h in the parent
        assert camera["rotation_deg"] < 1e-6 and camera["centre_shift_norm_mm"] < 1e-9
        assert camera["phase_to_height"] is None
    same = _ok(client.get(f"{API}/calibrations/compare", params={"a": p2h_id, "b": p2h_id}))
    assert same["summary"]["max_height_change_mm"] == pytest.approx(0.0, abs=1e-6)
    response = client.get(f"{API}/calibrations/{p2h_id}/download")
    assert response.status_code == 200
    names = zipfile.ZipFile(io.BytesIO(response.content)).namelist()
    assert f"{p2h_id}/calibration.json" in names and f"{p2h_id}/arrays.npz" in names
    inputs = {n.split("/")[2] for n in names if n.startswith(f"{p2h_id}/inputs/")}
    # Its own plates and reference, and the parent's chessboard views it inherits.
    assert len(inputs) == plates + 1 + len(answers)
    assert client.get(f"{API}/calibrations/compare",
                      params={"a": p2h_id, "b": "cal-nope"}).status_code == 404
    # A download uploads again (another daemon, a reinstall): the calibration, not its inputs.
    again = client.post(f"{API}/calibrations", content=response.content,
                        headers={"content-type": "application/zip"})
    assert again.status_code == 201, again.text
    assert again.json()["quality"] == _ok(client.get(f"{API}/calibrations/{p2h_id}"))["quality"]
    # The inputs are the calibration's evidence: they cannot be deleted.
    evidence = sorted(inputs)[0]
    refused = client.delete(f"{API}/captures/{evidence}", params={"reason": "tidy up"})
    assert refused.status_code == 409
    assert "is an input of calibration" in refused.json()["detail"]
    assert client.get(f"{API}/captures/{evidence}").status_code == 200


def _ok_bytes(client: Client, path: str) -> bytes:
    response = client.get(path)
    assert response.status_code == 200, response.text
    return bytes(response.content)


@pytest.mark.slow
def test_a_closed_session_releases_the_daemon_and_a_view_refuses_a_second_origin(
        client: Client) -> None:
    session = _ok(client.post(f"{API}/calibration-sessions", json={"kind": "stereo"}), 201)
    sid = session["id"]
    assert client.post(f"{API}/calibration-sessions/{sid}/plates",
                       json={"z_mm": 0}).status_code == 409  # not a phase-height session
    _ok(client.put(f"{API}/sim/chessboard", json={}))
    view = _ok(client.post(f"{API}/calibration-sessions/{sid}/views"), 201)
    assert view["origin"]
    second = client.post(f"{API}/calibration-sessions/{sid}/views", json={"origin": True})
    assert second.status_code == 409 and "origin" in second.json()["detail"]
    assert _ok(client.delete(f"{API}/calibration-sessions/{sid}"))["state"] == "closed"
    assert _ok(client.get(f"{API}/status"))["state"] in ("idle", "fault")
    assert client.post(f"{API}/calibration-sessions/{sid}/views").status_code == 409


@pytest.mark.slow
def test_a_failed_phase_height_solve_takes_more_plates_and_solves_again(
        client: Client, calibrated_rooms: Callable[[str], tuple[Path, Path]]) -> None:
    # A parent with its own phase-to-height models: the session knows the room's sensitivity
    # at the opening and lists the heights at once.
    _, caldir = calibrated_rooms("default")
    parent = _ok(client.post(f"{API}/calibrations", content=zip_directory(caldir),
                             headers={"content-type": "application/zip"}), 201)["id"]
    session = _ok(client.post(f"{API}/calibration-sessions", json={
        "kind": "phase-height", "calibration_id": parent, "z_range_mm": [6.0, 10.0]}), 201)
    sid, plan = session["id"], session["plan"]
    assert plan["sensitivity_source"] == f"the phase-to-height models of {parent}"
    assert all(1.0 < s < 2.5 for s in plan["sensitivity_rad_per_mm"].values()), plan
    assert plan["needed_heights_mm"][0] == 6.0 and plan["needed_heights_mm"][-1] == 10.0
    _ok(client.put(f"{API}/sim/scene", json={"kind": "reference",
                                             "position_mm": [0, 0, REFERENCE_Z]}))
    plan = _ok(client.post(f"{API}/calibration-sessions/{sid}/reference",
                           json={"z_mm": REFERENCE_Z}), 201)["plan"]
    heights = plan["needed_heights_mm"]
    assert len(heights) >= 3 and 10.0 not in heights  # the reference covers its own height
    # One plate is not there: the physicist typed its height with the plate out of the room.
    wrong = heights[1]
    for z in heights:
        if z == wrong:
            _ok(client.put(f"{API}/sim/scene", json={"kind": "empty"}))
        answer = _ok(client.post(f"{API}/calibration-sessions/{sid}/plates",
                                 json={"z_mm": z, "move_stage": z != wrong}), 201)
    assert answer["ready"], answer["missing"]
    failed = _wait_job(client, _ok(client.post(f"{API}/calibration-sessions/{sid}/solve"),
                                   202)["id"])
    # The walk along Z finds no fringe there and slips: the plane after it is reported off.
    assert failed["state"] == "failed" and "the unwrapping along Z slipped" in failed["error"]
    after = _ok(client.get(f"{API}/calibration-sessions/{sid}"))
    assert after["state"] == "failed" and after["error"] == failed["error"]
    assert after["failures"] == []  # recorded when the session is extended
    # After a slip the plan asks for planes half as far apart.
    assert after["plan"]["max_step_mm"] == math.floor(10 * plan["max_step_mm"] / 2) / 10
    assert after["plan"]["needed_heights_mm"] and not after["ready"]
    assert _ok(client.get(f"{API}/status"))["state"] in ("idle", "fault")

    # Extended: the plate again at the height it was said to be (it replaces the wrong one),
    # then whatever the plan asks for; the session calibrates again and solves.
    again = _ok(client.post(f"{API}/calibration-sessions/{sid}/plates",
                            json={"z_mm": wrong, "move_stage": True}), 201)
    assert _ok(client.get(f"{API}/status"))["state"] == "calibrating"
    for z in again["plan"]["needed_heights_mm"]:
        again = _ok(client.post(f"{API}/calibration-sessions/{sid}/plates",
                                json={"z_mm": z, "move_stage": True}), 201)
    assert again["ready"], again["missing"]
    extended = _ok(client.get(f"{API}/calibration-sessions/{sid}"))
    assert extended["state"] == "acquiring"
    assert [(f["job_id"], f["error"]) for f in extended["failures"]] == [
        (failed["id"], failed["error"])]
    assert sorted(p["z_mm"] for p in extended["plates"]).count(wrong) == 1
    solved = _wait_job(client, _ok(client.post(f"{API}/calibration-sessions/{sid}/solve"),
                                   202)["id"])
    assert solved["state"] == "succeeded", solved["error"]
    made = _ok(client.get(f"{API}/calibrations/{solved['result']['calibration_id']}"))
    assert made["parent_id"] == parent
    assert made["quality"]["p2h_residual_median_mm"] < 0.05
    assert _ok(client.get(f"{API}/calibration-sessions/{sid}"))["state"] == "done"


def test_the_plan_spaces_the_planes_under_the_safe_step() -> None:
    # Without planes: the range evenly; with some: the gaps split, the ends reached.
    assert heights_needed([], (0.0, 4.0), 1.5) == [0.0, 1.33, 2.67, 4.0]
    assert heights_needed([10.0, 9.0], (6.0, 10.0), 1.4) == [6.0, 7.0, 8.0]
    assert heights_needed([10.0, 9.0, 6.0], (6.0, 10.0), 1.4) == [7.0, 8.0]
    assert heights_needed([10.0, 9.0, 8.0, 7.0, 6.0], (6.0, 10.0), 1.4) == []
    assert heights_needed([12.0], (6.0, 10.0), 3.0) == [6.0, 9.0]  # the plane beyond counts
    # 0.8 π per step at the steepest pixels, to 0.1 mm down.
    assert safe_step_mm(1.4) == 1.7 and safe_step_mm(math.pi) == 0.8
    with pytest.raises(ValueError, match="max_step_mm"):
        heights_needed([], (0.0, 1.0), 0.0)


def test_a_slipped_solve_halves_the_step_of_the_plan() -> None:
    session = Session(id="cs-test", kind="phase-height", actor="physicist", created="now",
                      z_range_mm=(6.0, 10.0), sensitivity={"S1": 1.4, "S2": 1.2},
                      reference=PlateStep("cap-ref", 10.0, False))
    assert session.plate_plan()["max_step_mm"] == 1.7  # the steeper camera decides
    assert session.plate_plan()["needed_heights_mm"] == [6.0, 7.33, 8.67]
    session.state, session.error = "failed", ("camera S1: the plane at Z = +7.3 mm is off by "
                                              "5.2 mm after the fit; the unwrapping along Z "
                                              "slipped by a fringe there")
    assert session.plate_plan()["max_step_mm"] == 0.8
    session.failures.append({"job_id": "job-1", "error": session.error, "heights_mm": []})
    session.error = "no usable fringes"  # a failure of another kind does not halve it again
    assert session.plate_plan()["max_step_mm"] == 0.8
    status = session.phase_height_status()
    assert not status["ready"] and "more than 0.8 mm apart" in status["missing"][-1]
