"""Guided calibration through the API on the simulated room, jobs, and calibration versions.

The proof: a stereo session (the board moved with ``PUT /sim/chessboard``) and a phase-to-height
session (the plate moved by the daemon's simulated stage) calibrate the room end to end; the
result, activated, reconstructs a pyramid within 0.05 mm (median) of its exact surface.

To keep the module near two minutes, the stereo session takes the poses of the offline
calibration set in order only until the daemon answers ``ready`` (eight of the twelve), and the
plate stack 2 mm steps from −8 to +10 mm (10 heights, covering the pyramid's −6…+6 mm)
instead of 36 heights in 1 mm steps: 2 mm moves each pixel's phase by ≈ 2.4 rad, still below
the π the unwrapping along Z allows (docs/design.md §5).
"""

from __future__ import annotations

import io
import threading
import time
import zipfile
from pathlib import Path
from typing import Any

import pytest

from eyeserver.hardware.sim.config import load_room
from eyeserver.hardware.sim.scoring import score_cloud
from eyeserver.hardware.sim.sessions import calibration_poses
from eyeserver.io import read_ply
from eyeserver.service.events import EventBus
from eyeserver.service.jobs import JobContext, Jobs
from eyeserver.service.workers import QueueFullError
from tests.apiclient import API, OPERATOR_TOKEN, Client, auth

PLATE_HEIGHTS = [float(z) for z in range(-8, 11, 2)]
REFERENCE_Z = 10.0


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

    # --- phase to height on the stage ---
    session = _ok(client.post(f"{API}/calibration-sessions",
                              json={"kind": "phase-height", "calibration_id": stereo_id}), 201)
    pid = session["id"]
    for z in PLATE_HEIGHTS:
        step = _ok(client.post(f"{API}/calibration-sessions/{pid}/plates",
                               json={"z_mm": z, "move_stage": True}), 201)
        assert step["moved_by_stage"]
    assert _ok(client.get(f"{API}/sim/scene"))["position_mm"][2] == PLATE_HEIGHTS[-1]
    assert client.post(f"{API}/calibration-sessions/{pid}/solve").status_code == 409  # no ref
    _ok(client.put(f"{API}/sim/scene", json={"kind": "reference",
                                             "position_mm": [0, 0, REFERENCE_Z]}))
    _ok(client.post(f"{API}/calibration-sessions/{pid}/reference",
                    json={"z_mm": REFERENCE_Z}), 201)
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
    assert len(inputs) == len(PLATE_HEIGHTS) + 1 + len(answers)
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
