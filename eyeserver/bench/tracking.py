"""``eyeserver bench tracking``: live tracking end to end, as the beam controller would see it.

A daemon on loopback (:class:`~eyeserver.bench.daemon.DaemonProcess`) with a calibration of the
simulated rig, a patient whose reference is captured at rest, then the eye set moving (slight
drift and a scripted saccade out of tolerance and back) and live tracking for a while, read on
``/api/v1/ws/pose`` by twenty WebSocket clients, one of which never reads. Figures:

* camera frames acquired at 25 Hz (share of the camera periods), and the share *processed*
  (delivered as pose messages): the rest were dropped (the newest frame wins) and are counted;
* end-to-end latency, frame mid-exposure → message received by the client (both on the
  machine's monotonic clock), median and p99, beside the daemon's own figure at the send;
* the beam hold's reaction to the saccade: camera frames from the saccade's end to the first
  message held for ``out_of_tolerance``, and whether the first frame processed after it was;
* what the 19 reading clients received (messages per second) and what the silent one lost.
"""

from __future__ import annotations

import contextlib
import json
import math
import socket
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from websockets.sync.client import ClientConnection, connect

from eyeserver.bench.daemon import DaemonError, DaemonProcess, zip_directory
from eyeserver.bench.simcal import calibrate_room
from eyeserver.hardware.sim.config import load_room

__all__ = ["format_text", "run"]

API = "/api/v1"
RATE_HZ = 25.0
PATIENT = "P-BENCH-TRACK"
SACCADE_DEG = 8.0
TOLERANCE_GAZE_DEG = 2.0
TOLERANCE_MM = 0.5
CLIENTS = 20

Progress = Callable[[str], None]


def _quiet(_: str) -> None:
    pass


def _checked(response: Any, what: str) -> dict[str, Any]:
    if response.status_code >= 300:
        raise DaemonError(f"{what}: HTTP {response.status_code}: {response.text}")
    body: dict[str, Any] = response.json() if response.content else {}
    return body


class _Reader:
    """One WebSocket client on its own thread, recording every message with its arrival."""

    def __init__(self, ws: ClientConnection, *, silent: bool = False) -> None:
        self.ws = ws
        self.silent = silent
        self.messages: list[tuple[int, dict[str, Any]]] = []  # (monotonic ns at arrival, msg)
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        try:
            while True:
                text = self.ws.recv()
                self.messages.append((time.monotonic_ns(), json.loads(text)))
        except BaseException as exc:  # the connection closes at the end
            self.error = exc

    def start(self) -> None:
        if not self.silent:
            self.thread.start()

    def drain(self, timeout_s: float = 5.0) -> None:
        """Read what is waiting (the silent client, at the end)."""
        try:
            while True:
                text = self.ws.recv(timeout=timeout_s)
                self.messages.append((time.monotonic_ns(), json.loads(text)))
        except TimeoutError:
            return
        except Exception as exc:  # e.g. closed by the server's keep-alive: it never answered
            self.error = exc


def _percentile(values: list[float], q: float) -> float | None:
    return float(np.percentile(values, q)) if values else None


def run(seconds: float = 60.0, *, calibration: Path | None = None,
        room_file: Path | None = None, work: Path | None = None,
        progress: Progress = _quiet) -> dict[str, Any]:
    """Track for ``seconds`` on a daemon on loopback and measure; the report (JSON-able)."""
    with tempfile.TemporaryDirectory(prefix="eyeserver-bench-tracking-") as scratch:
        base = work or Path(scratch)
        if calibration is None:
            progress("calibrating the simulated rig (≈ 1 minute)")
            calibration = calibrate_room(load_room(room_file), base / "cal", seed=0,
                                         progress=progress)
        env = {} if room_file is None else {"EYESERVER_ROOM_FILE": str(room_file)}
        with DaemonProcess(base / "daemon-data", log=base / "daemon.log", env=env) as daemon:
            return _run(daemon, seconds, calibration, progress)


def _run(daemon: DaemonProcess, seconds: float, calibration: Path,
         progress: Progress) -> dict[str, Any]:
    client = daemon.client
    progress("importing the calibration, placing the eye, capturing the reference at rest")
    imported = _checked(client.post(f"{API}/calibrations", content=zip_directory(calibration),
                                    headers={"content-type": "application/zip"}), "import")
    _checked(client.post(f"{API}/calibrations/{imported['id']}/activate"), "activation")
    _checked(client.put(f"{API}/patients/{PATIENT}", json={
        "eye": "right", "unit": "left", "tolerance_mm": TOLERANCE_MM,
        "tolerance_gaze_deg": TOLERANCE_GAZE_DEG}), "patient")
    _checked(client.put(f"{API}/sim/eye", json={"motion": None, "gaze_deg": [0.0, 0.0]}),
             "still eye")
    reference = _checked(client.post(f"{API}/patients/{PATIENT}/fractions/1/reference/capture",
                                     timeout=120), "reference")
    # The script's clock starts at this PUT: the saccade comes half-way through tracking and
    # the eye returns to the reference gaze one second later.
    lead_s = 3.0
    saccade_s = lead_s + seconds / 2
    motion = {"seed": 1, "drift_deg": 0.02, "saccade_rate_hz": 0.0, "blink_rate_hz": 0.0,
              "script": [{"t_s": saccade_s, "kind": "saccade",
                          "gaze_deg": [SACCADE_DEG, 0.0], "duration_s": 0.03},
                         {"t_s": saccade_s + 1.0, "kind": "saccade", "gaze_deg": [0.0, 0.0],
                          "duration_s": 0.03}]}
    _checked(client.put(f"{API}/sim/eye", json={"motion": motion}), "eye motion")
    before = time.monotonic_ns()
    eye = _checked(client.get(f"{API}/sim/eye"), "eye truth")
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
        status, elapsed_s, started = _track(client, seconds, saccade_s, lead_s, silent,
                                            readers, progress)
    return _report(seconds, elapsed_s, started, status, reference, readers, silent,
                   saccade_end_ns)


def _track(client: Any, seconds: float, saccade_s: float, lead_s: float, silent: _Reader,
           readers: list[_Reader], progress: Progress
           ) -> tuple[dict[str, Any], float, dict[str, Any]]:
    """Track for ``seconds`` while the readers read: the daemon's final status, the time
    tracked, and its answer to the start."""
    for reader in readers:
        reader.start()
    try:
        progress(f"tracking for {seconds:g} s with {CLIENTS} clients on /ws/pose "
                 f"(saccade of {SACCADE_DEG:g}° at {saccade_s - lead_s:g} s)")
        started = _checked(client.post(f"{API}/tracking/start", json={
            "patient_id": PATIENT, "fraction": 1}), "tracking start")
        t0 = time.monotonic()
        remaining = seconds - (time.monotonic() - t0)
        while remaining > 0:
            time.sleep(min(remaining, 1.0))
            remaining = seconds - (time.monotonic() - t0)
        status = _checked(client.post(f"{API}/tracking/stop"), "tracking stop")
        elapsed_s = time.monotonic() - t0
        time.sleep(0.5)  # the last messages reach the readers
        silent.drain()
    finally:
        for reader in [silent, *readers]:
            reader.ws.close()
        for reader in readers:
            reader.thread.join(5)
    return status, elapsed_s, started


def _report(seconds: float, elapsed_s: float, started: dict[str, Any], status: dict[str, Any],
            reference: dict[str, Any], readers: list[_Reader], silent: _Reader,
            saccade_end_ns: int) -> dict[str, Any]:
    main = [(arrived, m) for arrived, m in readers[0].messages if m.get("type") == "pose"]
    acquired, missed = status["frames_acquired"], status["frames_missed"]
    processed, dropped = status["frames_processed"], status["frames_dropped"]
    periods = acquired + missed
    end_to_end = [(arrived - m["t_ns"]) / 1e6 for arrived, m in main]
    at_send = [float(m["latency_ms"]) for _, m in main]
    processing = [float(m["processing_ms"]) for _, m in main]
    after = [m for _, m in main if m["t_ns"] >= saccade_end_ns]
    before = [m for _, m in main if m["t_ns"] < saccade_end_ns - 30_000_000]
    at_rest = [m["deviation"] for m in before if m["deviation"] is not None]
    held = next((m for m in after if "out_of_tolerance" in m["reasons"]), None)
    first_after = after[0] if after else None
    period_ns = 1e9 / RATE_HZ
    reaction: dict[str, Any] = {
        "saccade_deg": SACCADE_DEG, "tolerance_gaze_deg": TOLERANCE_GAZE_DEG,
        "first_processed_frame_after_saccade_held": None if first_after is None
        else "out_of_tolerance" in first_after["reasons"],
        "frames_from_saccade_end_to_hold": None if held is None
        else math.ceil((held["t_ns"] - saccade_end_ns) / period_ns),
        "processed_frames_from_saccade_end_to_hold": None if held is None
        else after.index(held),
        # Only meaningful when the beam was not already held for the same reason at rest.
        "held_out_of_tolerance_before_saccade": sum(
            1 for m in before if "out_of_tolerance" in m["reasons"]),
        "processed_before_saccade": len(before),
        "first_after_saccade_gaze_deg": None if first_after is None or
        first_after["deviation"] is None else first_after["deviation"]["gaze_deg"],
    }
    rates = [sum(1 for _, m in r.messages if m.get("type") == "pose") / elapsed_s
             for r in readers]
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
        "unit": started.get("unit"),
        "reference": {"centre_mm": reference.get("pose", {}).get("centre_mm"),
                      "gaze": reference.get("pose", {}).get("gaze")},
        "frames": {"camera_periods": periods, "acquired": acquired, "missed": missed,
                   "processed": processed, "dropped": dropped, "held": status["frames_held"],
                   "acquired_share": acquired / periods if periods else None,
                   "processed_share": processed / periods if periods else None,
                   "processed_rate_hz": processed / elapsed_s, "goal_share": 0.99},
        "latency_ms": {"end_to_end_median": _percentile(end_to_end, 50),
                       "end_to_end_p99": _percentile(end_to_end, 99),
                       "at_send_median": _percentile(at_send, 50),
                       "at_send_p99": _percentile(at_send, 99),
                       "processing_median": _percentile(processing, 50),
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


def format_text(report: dict[str, Any]) -> str:
    """The report for people."""
    f, lat, reaction, clients = (report["frames"], report["latency_ms"],
                                 report["beam_hold_reaction"], report["clients"])
    share = f["processed_share"]
    lines = [
        f"live tracking, {report['elapsed_s']} s on the simulated room (unit "
        f"{report['unit']}, cameras at {report['rate_hz']:g} Hz)",
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
        f"{_fmt(lat['at_send_p99'])} ms; processing median {_fmt(lat['processing_median'])} ms)",
        f"  saccade {reaction['saccade_deg']:g}° (tolerance {reaction['tolerance_gaze_deg']:g}°): "
        f"first processed frame after it held: "
        f"{reaction['first_processed_frame_after_saccade_held']}, "
        f"{reaction['frames_from_saccade_end_to_hold']} camera frame(s) from its end to the "
        f"hold ({reaction['processed_frames_from_saccade_end_to_hold']} processed frames before)",
        f"  (before the saccade {reaction['held_out_of_tolerance_before_saccade']} of "
        f"{reaction['processed_before_saccade']} processed frames were already held out of "
        "tolerance)",
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
    if clients.get("silent_closed"):
        lines.append(f"  the client that never read was closed: {clients['silent_closed']}")
    if report.get("error"):
        lines.append(f"  the session ended by itself: {report['error']}")
    return "\n".join(lines)
