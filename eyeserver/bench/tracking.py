"""``eyeserver bench tracking``: live tracking end to end, as the beam controller would see it.

A daemon on loopback (:class:`~eyeserver.bench.daemon.DaemonProcess`) with a calibration of the
simulated rig, a patient whose reference is captured at rest, then the eye set moving (slight
drift, a scripted saccade out of tolerance and back, a blink) and live tracking for a while, read on
``/api/v1/ws/pose`` by twenty WebSocket clients, one of which never reads. Figures:

* camera frames acquired at 25 Hz (share of the camera periods), and the share *processed*
  (delivered as pose messages): the rest were dropped (the newest frame wins) and are counted;
* end-to-end latency, frame mid-exposure → message received by the client (both on the
  machine's monotonic clock), median and p99, beside the daemon's own figure at the send;
* the beam hold's reaction to the saccade: camera frames from the saccade's end to the first
  message held for ``out_of_tolerance``, and whether the first frame processed after it held
  the beam (and why);
* the blink: the processed frames with the lids half shut or more (the script's truth), how
  many held the beam and were seen as a blink, the processing around it;
* what the 19 reading clients received (messages per second) and what the silent one lost.

With ``prerendered``, the simulated room renders the tracked unit's frames of the whole script
before tracking starts (``POST /api/v1/sim/eye/prerender``): the stream then costs the cores
what real cameras' frames cost the host, nothing, and the figures are the daemon's own. Live
(the default), the room renders every frame set on the cores the daemon runs on.
"""

from __future__ import annotations

import contextlib
import gc
import itertools
import json
import math
import socket
import tempfile
import threading
import time
from collections import Counter
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from websockets.sync.client import ClientConnection, connect

from eyeserver.bench.daemon import API, DaemonProcess, checked, zip_directory
from eyeserver.bench.machine import reference_ms
from eyeserver.bench.simcal import calibrate_room
from eyeserver.core.clock import MonotonicClock
from eyeserver.core.types import Progress, quiet
from eyeserver.errors import EyeserverError
from eyeserver.eye import EyeModel, fit_eye
from eyeserver.hardware.sim import population
from eyeserver.hardware.sim.config import load_room
from eyeserver.hardware.sim.motion import EyeMotion, MotionSpec
from eyeserver.hardware.sim.scenes import EyeSpec, SceneSpec, scene_truth
from eyeserver.hardware.sim.sessions import SimSession
from eyeserver.io.rig_file import rig_from_dict
from eyeserver.service.events import EventBus
from eyeserver.service.frame_pose import FrameSet, PoseFinder, RigReconstructor
from eyeserver.service.patients import Tolerances
from eyeserver.service.tracking import TrackingSession, start_pose
from eyeserver.service.tracking_worker import PoseWorker
from eyeserver.service.verification import gaze_angle_deg

__all__ = ["format_replayed", "format_text", "replayed", "run"]

RATE_HZ = 25.0
PATIENT = "P-BENCH-TRACK"
SACCADE_DEG = 8.0
BLINK_S = 0.3
TOLERANCE_GAZE_DEG = 2.0
TOLERANCE_MM = 0.5
CLIENTS = 20
UNIT = "left"
"""The patient's unit: the one that tracks (and whose frames are rendered ahead)."""
PRERENDER_MARGIN_S = 10.0
"""Script rendered ahead beyond the tracked seconds: the start (workers, warm-up) and stop."""


class _Reader:
    """One WebSocket client on its own thread, recording every message with its arrival.

    The messages are kept as received text and parsed when first read after the run: parsing
    on arrival filled the bench's process with 20 clients' dictionaries, whose garbage
    collection (a full pass over tens of thousands of them) held the readers up to ≈ 0.1 s —
    measured in this process, not in the daemon: it showed as latency the daemon did not add.
    """

    def __init__(self, ws: ClientConnection, *, silent: bool = False) -> None:
        self.ws = ws
        self.silent = silent
        self._received: list[tuple[int, str | bytes]] = []  # (monotonic ns at arrival, text)
        self._parsed: list[tuple[int, dict[str, Any]]] | None = None
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, daemon=True)

    @property
    def messages(self) -> list[tuple[int, dict[str, Any]]]:
        """(monotonic ns at arrival, message) of everything received so far."""
        if self._parsed is None or len(self._parsed) != len(self._received):
            self._parsed = [(arrived, json.loads(text)) for arrived, text in self._received]
        return self._parsed

    def _run(self) -> None:
        try:
            while True:
                text = self.ws.recv()
                self._received.append((time.monotonic_ns(), text))
        except BaseException as exc:  # the connection closes at the end
            self.error = exc

    def start(self) -> None:
        if not self.silent:
            self.thread.start()

    def drain(self, timeout_s: float = 5.0) -> None:
        """Read what is waiting (the silent client, at the end): up to the ``hold`` the
        session's end publishes, its last message (kept: a full queue drops the oldest). Not
        up to a timeout alone: the stream's heartbeat never lets it go quiet."""
        try:
            while True:
                text = self.ws.recv(timeout=timeout_s)
                self._received.append((time.monotonic_ns(), text))
                message = json.loads(text)
                if message.get("type") == "hold" and message.get("reason") == "ended":
                    return
        except TimeoutError:
            return
        except Exception as exc:  # e.g. closed by the server's keep-alive: it never answered
            self.error = exc


def _percentile(values: list[float], q: float) -> float | None:
    return float(np.percentile(values, q)) if values else None


def run(seconds: float = 60.0, *, calibration: Path | None = None,
        room_file: Path | None = None, work: Path | None = None, workers: int = 2,
        prerendered: bool = False, eyes: str = "sharp", seed: int = 0, unit: str = UNIT,
        progress: Progress = quiet) -> dict[str, Any]:
    """Track for ``seconds`` on a daemon on loopback (``unit``: the patient's, ``all`` for
    both units interleaved; ``workers``: its ``tracking_workers``;
    ``prerendered``: the room's frames rendered before tracking, see the module; ``eyes``:
    the room's sharp eye, or a patient's drawn with ``seed``
    (:func:`~eyeserver.hardware.sim.population.draw`)) and measure; the report (JSON-able)."""
    if eyes not in ("sharp", "patient"):
        raise ValueError(f"eyes must be sharp or patient, not {eyes!r}")
    if unit == "all" and prerendered:
        raise ValueError("the room renders ahead for one unit: --unit all needs live rendering")
    with tempfile.TemporaryDirectory(prefix="eyeserver-bench-tracking-") as scratch:
        base = work or Path(scratch)
        if calibration is None:
            progress("calibrating the simulated rig (≈ 1 minute)")
            calibration = calibrate_room(load_room(room_file), base / "cal", seed=0,
                                         progress=progress)
        env = {"EYESERVER_TRACKING_WORKERS": str(workers)}
        if room_file is not None:
            env["EYESERVER_ROOM_FILE"] = str(room_file)
        at_start = reference_ms()
        with DaemonProcess(base / "daemon-data", log=base / "daemon.log", env=env) as daemon:
            report = _run(daemon, seconds, calibration, prerendered, eyes, seed, unit, progress)
        report["reference_fft_ms"] = {"at_start": round(at_start, 2),
                                      "at_end": round(reference_ms(), 2)}
        return report


class ReferenceRefusedError(EyeserverError):
    """The daemon refused the reference captured at rest (its reason the message): the eye was
    not seen well enough to track from, so the run measures nothing more. ``eye``: the
    patient eye's descriptors as a report carries them (None for the sharp eye)."""

    def __init__(self, reason: str, eye: dict[str, Any] | None) -> None:
        super().__init__(reason)
        self.reason = reason
        self.eye = eye


def _described(drawn: EyeSpec | None, seed: int) -> dict[str, Any] | None:
    """A drawn patient eye's descriptors and seed, as a report carries them (None: sharp)."""
    return None if drawn is None else {"seed": seed, **population.describe(drawn)}


def _run(daemon: DaemonProcess, seconds: float, calibration: Path, prerendered: bool,
         eyes: str, seed: int, unit: str, progress: Progress) -> dict[str, Any]:
    client = daemon.client
    progress("importing the calibration, placing the eye, capturing the reference at rest")
    imported = checked(client.post(f"{API}/calibrations", content=zip_directory(calibration),
                                    headers={"content-type": "application/zip"}), "import")
    checked(client.post(f"{API}/calibrations/{imported['id']}/activate"), "activation")
    checked(client.put(f"{API}/patients/{PATIENT}", json={
        "eye": "right", "unit": unit, "tolerance_mm": TOLERANCE_MM,
        "tolerance_gaze_deg": TOLERANCE_GAZE_DEG}), "patient")
    drawn = None
    if eyes == "patient":
        drawn = population.draw(np.random.default_rng(seed), "patient")
        checked(client.put(f"{API}/sim/scene", json=SceneSpec(kind="eye", eye=drawn)
                            .model_dump(mode="json")), "patient eye")
    checked(client.put(f"{API}/sim/eye", json={"motion": None, "gaze_deg": [0.0, 0.0]}),
             "still eye")
    captured = client.post(f"{API}/patients/{PATIENT}/fractions/1/reference/capture",
                           timeout=120)
    if captured.status_code == 422:  # the daemon's answer to a pose too weak to track from
        raise ReferenceRefusedError(captured.json()["detail"], _described(drawn, seed))
    reference = checked(captured, "reference")
    # The script's clock starts at this PUT: the saccade comes half-way through tracking and
    # the eye returns to the reference gaze one second later.
    lead_s = 3.0
    saccade_s = lead_s + seconds / 2
    blink_s = lead_s + 3 * seconds / 4
    motion = {"seed": 1, "drift_deg": 0.02, "saccade_rate_hz": 0.0, "blink_rate_hz": 0.0,
              "script": [{"t_s": saccade_s, "kind": "saccade",
                          "gaze_deg": [SACCADE_DEG, 0.0], "duration_s": 0.03},
                         {"t_s": saccade_s + 1.0, "kind": "saccade", "gaze_deg": [0.0, 0.0],
                          "duration_s": 0.03},
                         {"t_s": blink_s, "kind": "blink", "duration_s": BLINK_S}]}
    checked(client.put(f"{API}/sim/eye", json={"motion": motion}), "eye motion")
    ahead = None
    if prerendered:
        script_s = lead_s + seconds + PRERENDER_MARGIN_S
        progress(f"rendering {script_s:g} s of the moving eye ahead (unit {unit}'s cameras; "
                 "≈ 0.3–0.5 s a second of script)")
        ahead = checked(client.post(f"{API}/sim/eye/prerender", json={
            "unit": unit, "seconds": script_s}, timeout=3600), "rendering ahead")
    before = time.monotonic_ns()
    eye = checked(client.get(f"{API}/sim/eye"), "eye truth")
    after = time.monotonic_ns()
    # The daemon and this process share CLOCK_MONOTONIC: the script's start on it.
    epoch_ns = (before + after) // 2 - round(float(eye["t_s"]) * 1e9)
    saccade_end_ns = epoch_ns + round((saccade_s + 0.03) * 1e9)

    url = daemon.url.replace("http://", "ws://", 1) + f"{API}/ws/pose?token=" \
        + daemon.operator_token
    port = int(daemon.url.rsplit(":", 1)[1])
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.connect(("127.0.0.1", port))
    # websockets wants its connections entered as context managers (else a DeprecationWarning
    # from its version 14 on); the stack closes them all at the end.
    with contextlib.ExitStack() as connections:
        silent = _Reader(connections.enter_context(connect(
            url, sock=sock, max_queue=1, compression=None, ping_interval=None)), silent=True)
        readers = [_Reader(connections.enter_context(connect(url, compression=None,
                                                             ping_interval=None)))
                   for _ in range(CLIENTS - 1)]
        status, elapsed_s, started, start_ns = _track(client, seconds, saccade_s, lead_s,
                                                      silent, readers, progress)
    report = _report(seconds, elapsed_s, started, start_ns, status, reference, readers, silent,
                     saccade_end_ns)
    report["slowest"] = _slowest(readers[0], epoch_ns)
    report["script"] = {"saccade_s": saccade_s, "blink_s": blink_s}
    report["blink"] = _blink(readers[0], EyeMotion(MotionSpec.model_validate(motion)), epoch_ns,
                             blink_s)
    report["eyes"] = eyes
    report["unit"] = unit
    report["eye"] = _described(drawn, seed)
    scene = SceneSpec.model_validate(checked(client.get(f"{API}/sim/scene"), "scene"))
    report["accuracy"] = tracked_accuracy(
        [m for _, m in readers[0].messages if m.get("type") == "pose"], scene, epoch_ns,
        [(saccade_s, 0.03), (saccade_s + 1.0, 0.03), (blink_s, BLINK_S)])
    report["prerendered"] = None if ahead is None else {
        "seconds": ahead["seconds"], "took_s": ahead["took_s"],
        "megabytes": ahead["megabytes"],
        "cameras": checked(client.get(f"{API}/sim/eye/prerender"), "rendered ahead")}
    return report


def _slowest(reader: _Reader, epoch_ns: int, count: int = 8) -> list[dict[str, Any]]:
    """The ``count`` pose messages with the longest latency to the reader, slowest first: when
    in the script (``script_s``; the saccade and the blink are at known times), the latency,
    the frame's delivery and processing, what was seen of the eye."""
    arrived = [(a - m["t_ns"], m) for a, m in reader.messages if m.get("type") == "pose"]
    arrived.sort(key=lambda item: item[0], reverse=True)
    return [{"frame": m["frame"], "script_s": round((m["t_ns"] - epoch_ns) / 1e9, 2),
             "latency_ms": round(latency / 1e6, 1), "delivery_ms": m.get("delivery_ms"),
             "processing_ms": m["processing_ms"], "eye": m["eye"]}
            for latency, m in arrived[:count]]


def _blink(reader: _Reader, motion: EyeMotion, epoch_ns: int, blink_s: float
           ) -> dict[str, Any]:
    """What the scripted blink did to the stream: the processed frames with the lids half
    shut or more (the script's truth at each frame's time), how many held the beam and were
    seen as a blink, and the processing around it."""
    def scene_s(message: dict[str, Any]) -> float:
        return float(message["t_ns"] - epoch_ns) / 1e9

    messages = [m for _, m in reader.messages if m.get("type") == "pose"]
    shut = [m for m in messages if motion.state(scene_s(m)).openness <= 0.5]
    around = [float(m["processing_ms"]) for m in messages
              if blink_s - 0.2 <= scene_s(m) <= blink_s + BLINK_S + 0.2]
    return {"duration_s": BLINK_S, "frames_half_shut": len(shut),
            "held": sum(1 for m in shut if m["beam_hold"]),
            "seen_as_blink": sum(1 for m in shut if m["eye"] == "blink"),
            "with_pose": sum(1 for m in shut if m["pose"] is not None),
            "processing_ms_max_around": max(around) if around else None}


MOVING_MARGIN_S = 0.1
"""Frames within this of a scripted saccade or blink are not "at rest" (the pose then lags the
eye by the processing's time)."""


def tracked_accuracy(messages: list[dict[str, Any]], scene: SceneSpec, epoch_ns: int,
                     events: list[tuple[float, float]]) -> dict[str, Any]:
    """The tracked poses against the truth at each frame's mid-exposure (the scene's script
    evaluated there): globe centre (mm) and gaze (degrees) errors, median, p95 and max, over
    every pose message with a pose and over those at rest (none of ``events``, ``(start s,
    duration s)`` on the script's clock, within :data:`MOVING_MARGIN_S`); and the beam against
    the truth (:func:`beam_against_truth`)."""
    rows = []
    for message in messages:
        pose = message.get("pose")
        if not pose or pose.get("centre_mm") is None or pose.get("gaze") is None:
            continue
        at = float(message["t_ns"] - epoch_ns) / 1e9
        eye = scene_truth(scene, at)["eye"]
        centre = float(np.linalg.norm(np.subtract(pose["centre_mm"], eye["centre_mm"])))
        gaze = gaze_angle_deg(pose["gaze"], eye["gaze"])
        moving = any(start - MOVING_MARGIN_S <= at <= start + duration + MOVING_MARGIN_S
                     for start, duration in events)
        rows.append((centre, gaze, moving))

    def stats(values: list[float]) -> dict[str, float | None]:
        if not values:
            return {"median": None, "p95": None, "max": None}
        return {"median": float(np.median(values)), "p95": float(np.percentile(values, 95)),
                "max": float(max(values))}

    rest = [r for r in rows if not r[2]]
    return {"frames": len(rows), "centre_error_mm": stats([r[0] for r in rows]),
            "gaze_error_deg": stats([r[1] for r in rows]), "frames_at_rest": len(rest),
            "at_rest_centre_error_mm": stats([r[0] for r in rest]),
            "at_rest_gaze_error_deg": stats([r[1] for r in rest]),
            "beam": beam_against_truth(messages, scene, epoch_ns)}


def beam_against_truth(messages: list[dict[str, Any]], scene: SceneSpec,
                       epoch_ns: int) -> dict[str, int]:
    """Every pose message's beam decision against where the eye truly was at its frame: out of
    tolerance when the true centre lies more than :data:`TOLERANCE_MM` from the reference's
    (the still eye the reference was captured of: ``scene`` without its motion) or the true
    gaze more than :data:`TOLERANCE_GAZE_DEG` from its gaze. The safety figure is
    ``released_out_of_tolerance`` (goal 0); ``released_within_tolerance`` of
    ``within_tolerance`` says how often the beam could be given where it should be."""
    still = scene.model_copy(update={"eye": scene.eye.model_copy(update={"motion": None})})
    reference = scene_truth(still, 0.0)["eye"]
    counts = {"out_of_tolerance": 0, "released_out_of_tolerance": 0, "within_tolerance": 0,
              "released_within_tolerance": 0}
    for message in messages:
        if "beam_hold" not in message:
            continue
        eye = scene_truth(scene, float(message["t_ns"] - epoch_ns) / 1e9)["eye"]
        moved = float(np.linalg.norm(np.subtract(eye["centre_mm"], reference["centre_mm"])))
        turned = gaze_angle_deg(eye["gaze"], reference["gaze"])
        where = ("out_of_tolerance" if moved > TOLERANCE_MM or turned > TOLERANCE_GAZE_DEG
                 else "within_tolerance")
        counts[where] += 1
        if not message["beam_hold"]:
            counts[f"released_{where}"] += 1
    return counts


def _track(client: Any, seconds: float, saccade_s: float, lead_s: float, silent: _Reader,
           readers: list[_Reader], progress: Progress
           ) -> tuple[dict[str, Any], float, dict[str, Any], int]:
    """Track for ``seconds`` while the readers read: the daemon's final status, the time
    tracked, its answer to the start, and when the start was asked for (monotonic ns).

    This process's objects (the imported modules, the daemon's client) are frozen out of the
    garbage collector while the readers read: its first full collection came ≈ 12 s into the
    stream and held the readers 47–74 ms (measured with ``gc.callbacks``), latency the daemon
    did not add (the daemon and its tracking workers ran none during the stream).
    """
    gc.collect()
    gc.freeze()
    for reader in readers:
        reader.start()
    try:
        progress(f"tracking for {seconds:g} s with {CLIENTS} clients on /ws/pose "
                 f"(saccade of {SACCADE_DEG:g}° at {saccade_s - lead_s:g} s)")
        start_ns = time.monotonic_ns()
        started = checked(client.post(f"{API}/tracking/start", json={
            "patient_id": PATIENT, "fraction": 1}), "tracking start")
        t0 = time.monotonic()
        remaining = seconds - (time.monotonic() - t0)
        while remaining > 0:
            time.sleep(min(remaining, 1.0))
            remaining = seconds - (time.monotonic() - t0)
        status = checked(client.post(f"{API}/tracking/stop"), "tracking stop")
        elapsed_s = time.monotonic() - t0
        time.sleep(0.5)  # the last messages reach the readers
        silent.drain()
    finally:
        for reader in [silent, *readers]:
            reader.ws.close()
        for reader in readers:
            reader.thread.join(5)
        gc.unfreeze()
    return status, elapsed_s, started, start_ns


def _holds_at_rest(before: list[dict[str, Any]]) -> dict[str, Any]:
    """The beam held while the eye rests in tolerance (before the saccade, from the first
    release of the beam on): the frames held, the times it rose, and why (the hold must follow
    the eye, not the scheduler: docs/notes/hardening.md)."""
    released = next((k for k, m in enumerate(before) if not m["beam_hold"]), None)
    rest = [] if released is None else before[released:]
    held = [m for m in rest if m["beam_hold"]]
    return {"released_at_rest": released is not None, "frames_at_rest": len(rest),
            "held_at_rest": len(held),
            "holds_rising_at_rest": sum(1 for a, b in itertools.pairwise(rest)
                                        if b["beam_hold"] and not a["beam_hold"]),
            "held_at_rest_reasons": dict(Counter(r for m in held for r in m["reasons"]))}


def _report(seconds: float, elapsed_s: float, started: dict[str, Any], start_ns: int,
            status: dict[str, Any], reference: dict[str, Any], readers: list[_Reader],
            silent: _Reader, saccade_end_ns: int) -> dict[str, Any]:
    main = [(arrived, m) for arrived, m in readers[0].messages if m.get("type") == "pose"]
    acquired, missed = status["frames_acquired"], status["frames_missed"]
    processed, dropped = status["frames_processed"], status["frames_dropped"]
    periods = acquired + missed
    # The camera periods run from the first frame on: the cameras are prepared for the stream
    # first (the simulated room casts the moving eye's static part), and rates are over them.
    stream_s = periods / RATE_HZ
    end_to_end = [(arrived - m["t_ns"]) / 1e6 for arrived, m in main]
    at_send = [float(m["latency_ms"]) for _, m in main]
    processing = [float(m["processing_ms"]) for _, m in main]
    delivery = [float(m["delivery_ms"]) for _, m in main if m.get("delivery_ms") is not None]
    after = [m for _, m in main if m["t_ns"] >= saccade_end_ns]
    before = [m for _, m in main if m["t_ns"] < saccade_end_ns - 30_000_000]
    at_rest = [m["deviation"] for m in before if m["deviation"] is not None]
    held = next((m for m in after if "out_of_tolerance" in m["reasons"]), None)
    first_after = after[0] if after else None
    period_ns = 1e9 / RATE_HZ
    reaction: dict[str, Any] = {
        "saccade_deg": SACCADE_DEG, "tolerance_gaze_deg": TOLERANCE_GAZE_DEG,
        # Held for whatever reason (out of tolerance, or the eye not found in that frame).
        "first_processed_frame_after_saccade_held": None if first_after is None
        else bool(first_after["beam_hold"]),
        "first_processed_frame_after_saccade_reasons": None if first_after is None
        else list(first_after["reasons"]),
        "frames_from_saccade_end_to_hold": None if held is None
        else math.ceil((held["t_ns"] - saccade_end_ns) / period_ns),
        "processed_frames_from_saccade_end_to_hold": None if held is None
        else after.index(held),
        # Only meaningful when the beam was not already held for the same reason at rest.
        "held_out_of_tolerance_before_saccade": sum(
            1 for m in before if "out_of_tolerance" in m["reasons"]),
        **_holds_at_rest(before),
        "processed_before_saccade": len(before),
        "first_after_saccade_gaze_deg": None if first_after is None or
        first_after["deviation"] is None else first_after["deviation"]["gaze_deg"],
    }
    rates = [sum(1 for _, m in r.messages if m.get("type") == "pose") / stream_s
             for r in readers] if periods else []
    lost = [sum(m.get("count", 0) for _, m in r.messages if m.get("type") == "dropped")
            for r in readers]
    silent_pose = sum(1 for _, m in silent.messages if m.get("type") == "pose")
    silent_lost = sum(m.get("count", 0) for _, m in silent.messages
                      if m.get("type") == "dropped")
    reasons: dict[str, int] = {}
    for _, m in main:
        for reason in m["reasons"]:
            reasons[reason] = reasons.get(reason, 0) + 1
    good = [m for _, m in main if m["pose"] is not None]
    return {
        "seconds": seconds, "elapsed_s": round(elapsed_s, 2), "rate_hz": RATE_HZ,
        "stream_s": round(stream_s, 2),
        "first_pose_after_start_s": round((main[0][1]["t_ns"] - start_ns) / 1e9, 2)
        if main else None,
        "unit": started.get("unit"),
        "reference": {"centre_mm": reference.get("pose", {}).get("centre_mm"),
                      "gaze": reference.get("pose", {}).get("gaze")},
        "frames": {"camera_periods": periods, "acquired": acquired, "missed": missed,
                   "processed": processed, "dropped": dropped, "held": status["frames_held"],
                   "acquired_share": acquired / periods if periods else None,
                   "processed_share": processed / periods if periods else None,
                   "processed_rate_hz": processed / stream_s if periods else None,
                   "goal_share": 0.99},
        "latency_ms": {"end_to_end_median": _percentile(end_to_end, 50),
                       "end_to_end_p99": _percentile(end_to_end, 99),
                       "at_send_median": _percentile(at_send, 50),
                       "at_send_p99": _percentile(at_send, 99),
                       "processing_median": _percentile(processing, 50),
                       "processing_p99": _percentile(processing, 99),
                       "delivery_median": _percentile(delivery, 50),
                       "delivery_p99": _percentile(delivery, 99),
                       "goal_p99": 40.0},
        "fits": {"with_pose": len(good), "without_pose": len(main) - len(good),
                 "in_tolerance": sum(1 for m in good if m["in_tolerance"]),
                 "hold_reasons": reasons,
                 "at_rest_length_mm_median": _percentile(
                     [d["length_mm"] for d in at_rest if d["length_mm"] is not None], 50),
                 "at_rest_gaze_deg_median": _percentile(
                     [d["gaze_deg"] for d in at_rest if d["gaze_deg"] is not None], 50)},
        "beam_hold_reaction": reaction,
        "clients": {"count": CLIENTS, "readers": len(readers),
                    "reader_rate_hz_min": min(rates) if rates else None,
                    "reader_rate_hz_max": max(rates) if rates else None,
                    "reader_messages_lost": sum(lost),
                    "silent_received": silent_pose, "silent_lost": silent_lost,
                    "silent_closed": None if silent.error is None else repr(silent.error)},
        "error": status.get("error"),
    }


def _fmt(value: float | None, digits: int = 1) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"


def accuracy_text(accuracy: dict[str, Any]) -> str:
    """:func:`tracked_accuracy` in words."""
    def pair(key: str, digits: int) -> str:
        s = accuracy[key]
        return f"{_fmt(s['median'], digits)}/{_fmt(s['p95'], digits)}"

    return (f"tracked pose against the truth at each frame (median/p95): centre "
            f"{pair('centre_error_mm', 3)} mm, gaze {pair('gaze_error_deg', 2)}° over "
            f"{accuracy['frames']} frames with a pose; at rest ({accuracy['frames_at_rest']} "
            f"frames, {MOVING_MARGIN_S:g} s clear of the saccades and the blink) "
            f"{pair('at_rest_centre_error_mm', 3)} mm, {pair('at_rest_gaze_error_deg', 2)}° "
            "(goal as the global fit's: ≤ 0.1 mm, ≤ 0.5° p95)" + _beam_text(accuracy.get("beam")))


def _beam_text(beam: dict[str, int] | None) -> str:
    """:func:`beam_against_truth` in words ('' for a report without it)."""
    if beam is None:
        return ""
    return (f"; against the truth, the beam was released on {beam['released_out_of_tolerance']}"
            f" of the {beam['out_of_tolerance']} frames with the eye out of tolerance (goal 0) "
            f"and on {beam['released_within_tolerance']} of the {beam['within_tolerance']} "
            f"within it ({TOLERANCE_MM:g} mm, {TOLERANCE_GAZE_DEG:g}° from the reference)")


def eye_text(eye: dict[str, Any] | None) -> str:
    """A report's patient eye (its ``eye``) in words, `` (seed 0: limbus 1.88 mm wide, …)``;
    '' for the sharp eye (None)."""
    if not eye:
        return ""
    return (f" (seed {eye['seed']}: limbus {eye['limbus_width_mm']:.2f} mm wide, contrast "
            f"{eye['limbus_contrast']:.2f}, lid cover {eye['lid_cover']:.2f}, anatomy mismatch "
            f"{eye['anatomy_mismatch_mm']:.2f} mm)")


def format_text(report: dict[str, Any]) -> str:
    """The report for people."""
    f, lat, reaction, clients = (report["frames"], report["latency_ms"],
                                 report["beam_hold_reaction"], report["clients"])
    share = f["processed_share"]
    ahead = report.get("prerendered")
    room = ("the simulated room rendered ahead" if ahead else
            "the simulated room, rendered live on the same cores")
    if report.get("eye"):
        room += f", a patient's eye{eye_text(report['eye'])}"
    lines = [
        f"live tracking, {report['elapsed_s']} s on {room} (unit "
        f"{report['unit']}, cameras at {report['rate_hz']:g} Hz): {report.get('stream_s')} s "
        f"of camera periods, the first pose {_fmt(report.get('first_pose_after_start_s'))} s "
        "after the start (workers started, cameras prepared)",
        f"  camera periods {f['camera_periods']}: acquired {f['acquired']} "
        f"({_fmt(100 * (f['acquired_share'] or 0))} %), missed {f['missed']}",
        f"  processed (pose messages) {f['processed']} = {_fmt(100 * (share or 0))} % of camera "
        f"frames, {_fmt(f['processed_rate_hz'])} Hz   goal ≥ 99 % at 25 Hz  "
        f"{'met' if share and share >= 0.99 else 'NOT met'}",
        f"  dropped (newest frame wins, counted) {f['dropped']}; beam held on {f['held']}",
        f"  latency frame → client, median {_fmt(lat['end_to_end_median'])} ms, p99 "
        f"{_fmt(lat['end_to_end_p99'])} ms   goal p99 < 40 ms  "
        f"{'met' if (lat['end_to_end_p99'] or 1e9) < 40 else 'NOT met'}",
        f"  (at the daemon's send: median {_fmt(lat['at_send_median'])} ms, p99 "
        f"{_fmt(lat['at_send_p99'])} ms; of which frames in the daemon's hands after "
        f"{_fmt(lat.get('delivery_median'))}/{_fmt(lat.get('delivery_p99'))} ms, processing "
        f"{_fmt(lat['processing_median'])}/{_fmt(lat.get('processing_p99'))} ms, median/p99)",
        f"  saccade {reaction['saccade_deg']:g}° (tolerance {reaction['tolerance_gaze_deg']:g}°): "
        f"first processed frame after it held: "
        f"{reaction['first_processed_frame_after_saccade_held']} "
        f"({', '.join(reaction.get('first_processed_frame_after_saccade_reasons') or []) or '-'}"
        f"), {reaction['frames_from_saccade_end_to_hold']} camera frame(s) from its end to the "
        f"hold out of tolerance ({reaction['processed_frames_from_saccade_end_to_hold']} "
        "processed frames before)",
        f"  (before the saccade {reaction['held_out_of_tolerance_before_saccade']} of "
        f"{reaction['processed_before_saccade']} processed frames were already held out of "
        "tolerance)",
        f"  at rest (unit {report.get('unit', UNIT)}, from the first release to the saccade): "
        f"held on {reaction.get('held_at_rest')} of {reaction.get('frames_at_rest')} processed "
        f"frames, rose {reaction.get('holds_rising_at_rest')} times "
        f"({reaction.get('held_at_rest_reasons') or '-'}; goal: none)",
        f"  fits: {report['fits']['with_pose']} with a pose, {report['fits']['without_pose']} "
        f"without; {report['fits']['in_tolerance']} in tolerance; at rest median |Δ| "
        f"{_fmt(report['fits']['at_rest_length_mm_median'], 3)} mm, gaze "
        f"{_fmt(report['fits']['at_rest_gaze_deg_median'], 2)}°; hold reasons "
        f"{report['fits']['hold_reasons']}",
        f"  {clients['count']} WebSocket clients: {clients['readers']} readers received "
        f"{_fmt(clients['reader_rate_hz_min'])}–{_fmt(clients['reader_rate_hz_max'])} "
        f"messages/s, lost {clients['reader_messages_lost']}; the one that never read lost "
        f"{clients['silent_lost']} (kept {clients['silent_received']})",
    ]
    accuracy = report.get("accuracy")
    if accuracy:
        lines.append("  " + accuracy_text(accuracy))
    blink = report.get("blink")
    if blink:
        lines.append(
            f"  blink {blink['duration_s']:g} s: {blink['frames_half_shut']} processed frames "
            f"with the lids half shut or more, {blink['held']} held the beam, "
            f"{blink['seen_as_blink']} seen as a blink, {blink['with_pose']} with a pose; "
            f"processing ≤ {_fmt(blink['processing_ms_max_around'])} ms around it")
    slowest = report.get("slowest")
    if slowest:
        lines.append("  slowest frames (latency ms at script time s, eye): " + ", ".join(
            f"{m['latency_ms']:.0f} at {m['script_s']:.2f} ({m['eye']})" for m in slowest)
            + f"; saccade at {report['script']['saccade_s']:g} s, blink at "
            f"{report['script']['blink_s']:g} s")
    if ahead:
        used = sum(c["used"] for c in ahead["cameras"].values())
        live = sum(c["live"] for c in ahead["cameras"].values())
        lines.append(
            f"  rendered ahead: {ahead['seconds']:g} s of the script in {ahead['took_s']:g} s "
            f"({ahead['megabytes']:g} MB); camera frames taken from it {used}, rendered at "
            f"once {live} (the warm-up frame's, and any off the stream's times)")
    if clients.get("silent_closed"):
        lines.append(f"  the client that never read was closed: {clients['silent_closed']}")
    reference = report.get("reference_fft_ms")
    if reference:
        lines.append(f"  machine speed: one 640 × 512 FFT took {reference['at_start']:.2f} ms "
                     f"before, {reference['at_end']:.2f} ms after (compare runs only at similar "
                     "values)")
    if report.get("error"):
        lines.append(f"  the session ended by itself: {report['error']}")
    return "\n".join(lines)


# --- the pipeline alone: the moving eye rendered beforehand, replayed at the camera rate -----


class _Replay:
    """Frame sets rendered beforehand, handed out at ``RATE_HZ`` on the machine's monotonic
    clock as if acquired now (mid-exposure time: when each is due)."""

    def __init__(self, steps: list[Any], clock: MonotonicClock) -> None:
        self._steps = steps
        self._clock = clock
        self._period_ns = round(1e9 / RATE_HZ)
        self._start_ns: int | None = None
        self._next = 0

    @property
    def missed(self) -> int:
        return 0

    def warm_up_frame(self) -> FrameSet | None:
        """The first frame set, as the daemon's rig takes one before the stream."""
        return FrameSet(-1, self._clock.now_ns(), self._steps[0]) if self._steps else None

    def next_frame(self) -> FrameSet | None:
        if self._next >= len(self._steps):
            return None
        now = self._clock.now_ns()
        if self._start_ns is None:
            self._start_ns = now
        due_ns = self._start_ns + self._next * self._period_ns
        if due_ns > now:
            self._clock.sleep((due_ns - now) / 1e9)
        frame = FrameSet(self._next, due_ns, self._steps[self._next],
                         arrived_ns=self._clock.now_ns())
        self._next += 1
        return frame


class _Recorded(EventBus):
    """An event bus that keeps what is published (no subscribers needed)."""

    def __init__(self) -> None:
        super().__init__()
        self.messages: list[dict[str, Any]] = []

    def publish(self, type: str, **data: Any) -> int:
        if type == "pose":  # not the fail-safe's holds (the first global fit, the end)
            self.messages.append(data)
        return 0


def replayed(calibration: Path, seconds: float = 10.0, *, room_file: Path | None = None,
             workers: int = 2, progress: Progress = quiet) -> dict[str, Any]:
    """Live tracking's pipeline alone (the report, JSON-able).

    ``seconds`` of the moving simulated eye (fixational drift) are rendered first, then handed
    at 25 Hz from memory to a tracking session with its worker process
    (:class:`~eyeserver.service.tracking_worker.PoseWorker`), as :mod:`eyeserver.service.
    tracking` runs it in the daemon: what the reconstruction and fit achieve when the cameras
    cost no CPU, as real ones cost none, while :func:`run` has the simulated room render each
    frame on the same cores. No HTTP or WebSocket here: latency is to the message's publishing.
    The reference is the global fit of the first frame (its radius held, as a captured
    reference's is); the session looks for the eye there first, as the daemon's does
    (:func:`~eyeserver.service.tracking.start_pose`). ``workers``: worker processes, each on
    its own frames (the daemon's ``tracking_workers``).
    """
    config = load_room(room_file)
    count = max(1, round(seconds * RATE_HZ))
    progress(f"rendering {count} frames of the moving eye to replay")
    motion = MotionSpec(seed=1, drift_deg=0.02, saccade_rate_hz=0.0, blink_rate_hz=0.0)
    with SimSession.open(config, seed=1) as session:
        session.room.set_scene(SceneSpec(kind="eye", eye=EyeSpec(motion=motion)))
        rig = rig_from_dict(session.rig.spec(), "<simulated rig>")
        unit = session.rig.units[0].id
        steps = []
        for _ in range(count):
            session.clock.advance(1.0 / RATE_HZ)
            steps.append(session.rig.acquire([unit]))
    first = PoseFinder(RigReconstructor(calibration, rig), fit_eye, EyeModel.population())(
        FrameSet(0, 0, steps[0]), None)
    model = replace(EyeModel.population(), globe_radius_mm=first.globe_radius_mm,
                    globe_sd_mm=0.0)  # a fit's radius, not a measured one
    finders = [PoseWorker(calibration, rig, model) for _ in range(workers)]
    for finder in finders:
        finder.start()
    clock = MonotonicClock()
    bus = _Recorded()
    reference = {"centre_mm": list(first.centre_mm), "gaze": list(first.gaze)}
    session_ = TrackingSession(_Replay(steps, clock), finders, reference=reference,
                               tolerances=Tolerances(), bus=bus, clock=clock,
                               expected=start_pose(reference, model))
    progress(f"replaying them at {RATE_HZ:g} Hz through the tracking worker")
    done = threading.Event()
    session_.start(on_end=done.set)
    done.wait(seconds + 60.0)
    session_.stop()
    status = session_.status()
    # The first frame is followed from the reference, as in the daemon, but with cold caches
    # (its window's cameras, the fringe strength): the figures are those of following the
    # eye, from the next processed frame on.
    steady = bus.messages[1:]
    latency = [m["latency_ms"] for m in steady]
    processing = [m["processing_ms"] for m in steady]
    processed = len(bus.messages)
    return {"seconds": count / RATE_HZ, "rate_hz": RATE_HZ, "frames": count,
            "workers": len(finders),
            "processed": processed, "processed_share": processed / count,
            "dropped": status["frames_dropped"], "error": status["error"],
            "with_pose": sum(1 for m in bus.messages if m["pose"] is not None),
            "first_frame_latency_ms": bus.messages[0]["latency_ms"] if bus.messages else None,
            "latency_ms": {"median": _percentile(latency, 50), "p99": _percentile(latency, 99)},
            "processing_ms": {"median": _percentile(processing, 50),
                              "p99": _percentile(processing, 99)}}


def format_replayed(report: dict[str, Any]) -> str:
    """The replay's figures, one line for people."""
    latency, workers = report["latency_ms"], report.get("workers", 1)
    return (f"pipeline alone ({report['seconds']:g} s of the moving eye rendered beforehand, "
            f"replayed at {report['rate_hz']:g} Hz, {workers} worker"
            f"{'s' if workers > 1 else ''}): {report['processed']} of "
            f"{report['frames']} frames processed ({100 * report['processed_share']:.1f} %), "
            f"{report['with_pose']} with a pose; frame → pose "
            f"{_ms_text(latency['median'])} median, {_ms_text(latency['p99'])} p99 (after the "
            f"first frame, {_ms_text(report['first_frame_latency_ms'])}); processing "
            f"{_ms_text(report['processing_ms']['median'])} median, "
            f"{_ms_text(report['processing_ms']['p99'])} p99")


def _ms_text(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.0f} ms"
