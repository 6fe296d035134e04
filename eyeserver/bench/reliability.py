"""``eyeserver bench reliability``: what a client sees when things go wrong (issue 35).

Every part runs a real ``eyeserver serve`` on loopback
(:class:`~eyeserver.bench.daemon.DaemonProcess`, a data directory of its own) and looks at it
only through its API, as the oncology information system would:

1. **kill -9**: a client posts captures back to back while the daemon is SIGKILLed after a
   random delay (seeded), then restarted on the same data directory, cycle after cycle. Every
   capture answered 201 must then be listed as acknowledged and its bundle (``bundle.zip``, as
   the API serves it) must read back whole: acknowledged / lost / corrupted, and the requests
   that got no answer (in flight at the kill) apart, with how many of those were stored.
2. **unplug and replug** one device of each kind (``PUT /api/v1/sim/devices/{id}``) while
   captures of its unit are posted: is the fault seen in ``/status`` and as a ``device.fault``
   event, which answers did the captures get meanwhile; then, the captures stopped and the
   device plugged back, how long until the daemon recovers on its own (its background retry)
   and says so (``device.recovered``), and whether a capture works again. An unplugged
   projector is found by its driver's check before each pulse, without a calibration; a dark
   one (a dead LED) only by the fringe check on a lit frame with a calibration active, which
   unplugging does not exercise.
3. **disk full and freed**: the data directory on a small tmpfs (root only), filled with a
   ballast file until captures fail; they must fail with 507 and a JSON reason, nothing stored
   may suffer, and captures must work again once the ballast is gone (also after a restart).
4. **load**: 100 clients reading ``GET /status`` back to back and 20 posting captures, with one
   ``/api/v1/ws/events`` client counting what it receives and what it lost: status latency
   under load beside idle and the goal, capture throughput and answers, and the CPU time the
   daemon, the clients and every other process took meanwhile (other work on the machine
   shows there).
5. **fuzz**: schemathesis over every operation of the daemon's own OpenAPI document with both
   roles' tokens, bounded (seeded, a few examples per operation): requests, 5xx answers,
   undocumented status codes, bodies that break their schema (as tests/test_api_fuzz.py, whose
   left-out operations and checks this follows).

The client runs on the same cores as the daemon: under load its threads take CPU time from it
and their own scheduling adds to the latencies they measure, so the figures are what a client
on the daemon's machine sees, not the daemon's time alone. :func:`findings` lists what went
wrong (lost or corrupted captures, 500s, a fault not detected or not recovered, a goal missed):
daemon bugs to fix, never to hide.
"""

from __future__ import annotations

import errno
import io
import itertools
import json
import os
import random
import re
import shutil
import subprocess
import tempfile
import threading
import time
import zipfile
from collections import Counter
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from types import TracebackType
from typing import TYPE_CHECKING, Any

import httpx
import numpy as np
from websockets.sync.client import ClientConnection, connect

from eyeserver.bench.daemon import API, DaemonProcess, checked
from eyeserver.bench.machine import machine, reference_ms
from eyeserver.core.types import Progress, quiet
from eyeserver.errors import EyeserverError, FormatError
from eyeserver.io import read_bundle

if TYPE_CHECKING:  # a dev dependency: the fuzz imports it when it runs
    import schemathesis
    import schemathesis.core.failures

__all__ = ["FORMAT", "FUZZ_LEFT_OUT", "STATUS_P99_GOAL_MS", "check_bundle", "findings",
           "format_text", "run", "stream_losses", "tally_captures"]

FORMAT = "eyeserver.bench.reliability/1"
STATUS_P99_GOAL_MS = 100.0
"""Issue 35's goal: ``GET /status`` answered within 100 ms at the 99th percentile under load."""
REQUEST_TIMEOUT_S = 120.0
"""Any one request (a daemon's first capture of a unit renders the room's geometry)."""
FIRST_ACK_TIMEOUT_S = 60.0
"""How long a kill cycle waits for its first acknowledged capture before killing anyway."""
MAX_KILL_DELAY_S = 2.0
"""Kills come at a uniformly drawn delay up to this after the cycle's first acknowledged
capture: among steady captures, not only in the daemon's start-up."""
DETECT_TIMEOUT_S = 30.0
"""How long an unplugged device may stay unnoticed before it counts as not detected."""
RECOVER_TIMEOUT_S = 90.0
"""How long a replugged device may take to recover before it counts as not recovered (the
daemon's background retry backs off up to every 30 s)."""
EVENT_GRACE_S = 5.0
"""How long after ``/status`` shows a change its event may still arrive on the stream."""
POLL_S = 0.05
"""Interval of ``/status`` polls while waiting for a fault or a recovery."""
UNPLUG_POST_PAUSE_S = 0.1
"""Pause between a poster's captures while a device is unplugged (a client retrying, not a
flood of refusals)."""
IDLE_STATUS_REQUESTS = 200
"""Sequential ``GET /status`` requests timed on the idle daemon before the load."""
STORED_BEFORE_FULL = 3
"""Captures stored on the tmpfs before it is filled (what must survive the full disk)."""
TRIES_WHILE_FULL = 6
"""Captures posted while the disk is full (the first ones may still fit in the slack)."""
FUZZ_LEFT_OUT = ("/sim/eye/prerender", "/tracking/start")
"""Operations the fuzz leaves out, as tests/test_api_fuzz.py does: rendering ahead takes
minutes of frames, and tracking starts worker processes (tests/test_tracking.py covers it)."""
SCHEMA_FAILURE_CODES = frozenset({"ST104", "ST105", "ST106", "ST107", "ST108", "ST109", "ST110",
                                  "ST111"})
"""schemathesis's failure codes of an answer whose body, headers or content type break the
document (ST108: the body breaks its JSON schema)."""
UNDOCUMENTED_STATUS_CODE = "ST103"
SERVER_ERROR_CODE = "ST101"
COUNTED_FAILURE_CODES = SCHEMA_FAILURE_CODES | {UNDOCUMENTED_STATUS_CODE, SERVER_ERROR_CODE}
"""Failures the fuzz counts under a name of their own; the others are listed by title."""
DOCUMENTED_5XX = frozenset({"503", "504", "507"})
"""5xx answers the API documents (a device failed or timed out, a queue or the disk is full);
any other 5xx is a bug."""
KEPT_IDS = 20
"""Lost or corrupted ids listed in the report (all are counted)."""


def _detail(response: httpx.Response) -> str | None:
    """The JSON error reason of an answer (None when the body is not ``{"detail": str}``)."""
    try:
        body = response.json()
    except ValueError:
        return None
    detail = body.get("detail") if isinstance(body, dict) else None
    return detail if isinstance(detail, str) else None


def _auth(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def _ms_summary(samples_s: Sequence[float]) -> dict[str, Any]:
    """Count, median, p99 and maximum of latencies in seconds, in milliseconds."""
    if not samples_s:
        return {"requests": 0, "p50_ms": None, "p99_ms": None, "max_ms": None}
    values = np.asarray(samples_s) * 1e3
    return {"requests": len(samples_s), "p50_ms": round(float(np.percentile(values, 50)), 2),
            "p99_ms": round(float(np.percentile(values, 99)), 2),
            "max_ms": round(float(values.max()), 2)}


# --- clients ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Answer:
    """What one posted capture got: ``status`` None when no answer came (``sent`` False when
    the connection was refused, so the request never reached a daemon)."""

    unit: str
    sent_s: float
    """time.monotonic() when the request went out."""
    answered_s: float
    status: int | None
    body: Any = None
    detail: str | None = None
    sent: bool = True


class _Poster:
    """A thread posting captures back to back (``units`` in turn) until stopped."""

    def __init__(self, url: str, token: str, units: Sequence[str], *,
                 pause_s: float = 0.0) -> None:
        self.answers: list[_Answer] = []
        self.first_ack = threading.Event()
        self._stop = threading.Event()
        self._url, self._token, self._units, self._pause_s = url, token, units, pause_s
        self._thread = threading.Thread(target=self._run, daemon=True)

    def start(self) -> _Poster:
        self._thread.start()
        return self

    def stop(self) -> None:
        """Send no further capture (the one under way still gets its answer, or none)."""
        self._stop.set()

    def join(self) -> list[_Answer]:
        self._thread.join()
        return self.answers

    def _run(self) -> None:
        with httpx.Client(base_url=self._url, timeout=REQUEST_TIMEOUT_S,
                          headers=_auth(self._token)) as client:
            for unit in itertools.cycle(self._units):
                if self._stop.is_set():
                    return
                sent_s = time.monotonic()
                try:
                    response = client.post(f"{API}/captures", json={"unit": unit})
                except httpx.ConnectError as exc:  # nothing listens: the request never left
                    self.answers.append(_Answer(unit, sent_s, time.monotonic(), None,
                                               detail=str(exc), sent=False))
                    self._stop.wait(0.05)
                    continue
                except httpx.TransportError as exc:  # sent, but no answer came
                    self.answers.append(_Answer(unit, sent_s, time.monotonic(), None,
                                               detail=f"{type(exc).__name__}: {exc}"))
                    continue
                try:
                    body = response.json()
                except ValueError:
                    body = None
                self.answers.append(_Answer(unit, sent_s, time.monotonic(), response.status_code,
                                           body=body, detail=_detail(response)))
                if response.status_code == 201:
                    self.first_ack.set()
                if self._pause_s:
                    self._stop.wait(self._pause_s)


class _StatusReader:
    """A thread reading ``GET /status`` back to back until stopped, timing each answer."""

    def __init__(self, url: str, token: str) -> None:
        self.latencies_s: list[float] = []
        self.statuses: Counter[str] = Counter()
        self._stop = threading.Event()
        self._url, self._token = url, token
        self._thread = threading.Thread(target=self._run, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()

    def join(self) -> None:
        self._thread.join()

    def _run(self) -> None:
        with httpx.Client(base_url=self._url, timeout=REQUEST_TIMEOUT_S,
                          headers=_auth(self._token)) as client:
            while not self._stop.is_set():
                started = time.perf_counter()
                try:
                    # The body is read but not parsed: the client's CPU time goes to the daemon.
                    code = str(client.get(f"{API}/status").status_code)
                except httpx.TransportError as exc:
                    code = type(exc).__name__
                    self._stop.wait(0.05)
                if code == "200":
                    self.latencies_s.append(time.perf_counter() - started)
                self.statuses[code] += 1


class _EventReader:
    """One ``/api/v1/ws/events`` client on its own thread, keeping every message with its
    arrival (time.monotonic()); a context manager that connects and closes."""

    def __init__(self, daemon: DaemonProcess) -> None:
        self._url = (daemon.url.replace("http", "ws", 1) + f"{API}/ws/events?token="
                     + daemon.operator_token)
        self.messages: list[tuple[float, dict[str, Any]]] = []
        self.error: str | None = None
        self._stop = threading.Event()
        self._ws: ClientConnection | None = None
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> _EventReader:
        self._ws = connect(self._url, compression=None, open_timeout=30).__enter__()
        self._thread.start()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 traceback: TracebackType | None) -> None:
        self._stop.set()
        self._thread.join()
        if self._ws is not None:
            self._ws.__exit__(exc_type, exc, traceback)

    def _run(self) -> None:
        assert self._ws is not None
        while not self._stop.is_set():
            try:
                text = self._ws.recv(timeout=0.2)
            except TimeoutError:
                continue
            except Exception as exc:  # the daemon closed the stream: report, do not hide
                self.error = f"{type(exc).__name__}: {exc}"
                return
            self.messages.append((time.monotonic(), json.loads(text)))

    def first(self, kind: str, after_s: float, *, device_id: str | None = None,
              timeout_s: float = 0.0) -> float | None:
        """When the first ``kind`` event (for ``device_id``, if given) arrived after
        ``after_s``, waiting up to ``timeout_s`` for it; None when none did."""
        deadline = time.monotonic() + timeout_s
        while True:
            for arrived, message in list(self.messages):
                if arrived >= after_s and message.get("type") == kind and (
                        device_id is None or message.get("device_id") == device_id):
                    return arrived
            if time.monotonic() >= deadline:
                return None
            time.sleep(POLL_S)


def stream_losses(messages: Iterable[Mapping[str, Any]]) -> dict[str, Any]:
    """What an event stream's client received and lost, from its messages in order.

    The stream says every loss (a ``dropped`` notice with its ``count`` before the next event,
    whose ``seq`` moved on by ``count + 1``); a jump of ``seq`` that no notice explains is a loss
    nobody was told of (``unannounced``), and a ``seq`` that does not increase is counted as
    ``out_of_order``. ``lost`` is both losses together.
    """
    received: Counter[str] = Counter()
    notices = announced = unannounced = out_of_order = 0
    expected: int | None = None
    pending = 0
    for message in messages:
        kind = str(message.get("type"))
        received[kind] += 1
        if kind == "hello":
            expected = int(message["last_seq"]) + 1
            continue
        if kind == "dropped":
            notices += 1
            pending += int(message["count"])
            announced += int(message["count"])
            continue
        seq = message.get("seq")
        if not isinstance(seq, int):
            continue
        if expected is not None:
            if seq < expected:
                out_of_order += 1
            else:
                unannounced += max(0, seq - expected - pending)
        pending = 0
        expected = seq + 1 if expected is None else max(expected, seq + 1)
    return {"messages": sum(received.values()), "by_type": dict(sorted(received.items())),
            "dropped_notices": notices, "announced_lost": announced,
            "unannounced_lost": unannounced, "out_of_order": out_of_order,
            "lost": announced + unannounced}


# --- the store, checked through the API -------------------------------------------------------


def list_captures(client: httpx.Client) -> dict[str, dict[str, Any]]:
    """Every capture ``GET /api/v1/captures`` lists, by id."""
    listed: dict[str, dict[str, Any]] = {}
    offset = 0
    while True:
        page = checked(client.get(f"{API}/captures", params={"limit": 1000, "offset": offset}),
                        "capture list")
        for item in page["items"]:
            listed[item["id"]] = item
        offset += len(page["items"])
        if not page["items"] or offset >= page["total"]:
            return listed


def check_bundle(client: httpx.Client, capture: Mapping[str, Any]) -> str | None:
    """Why a listed capture's bundle is not intact, or None when it is.

    The bundle is fetched as the API serves it (``bundle.zip``), its members' CRCs checked,
    unpacked, read with :func:`~eyeserver.io.read_bundle` (FORMATS.md) and every image decoded
    and checked against the rig; its frames must be as many as the listing says.
    """
    capture_id = str(capture["id"])
    if capture.get("status") != "ok":
        return f"listed with status {capture.get('status')!r}"
    response = client.get(f"{API}/captures/{capture_id}/bundle.zip")
    if response.status_code != 200:
        return f"bundle.zip: HTTP {response.status_code}: {response.text[:200]}"
    try:
        with zipfile.ZipFile(io.BytesIO(response.content)) as archive, \
                tempfile.TemporaryDirectory(prefix="eyeserver-bundle-") as scratch:
            broken = archive.testzip()
            if broken is not None:
                return f"bundle.zip: {broken} fails its CRC"
            for name in archive.namelist():
                parts = PurePosixPath(name).parts
                if not parts or parts[0] != capture_id or ".." in parts:
                    return f"bundle.zip: member {name!r} outside the folder {capture_id}/"
            archive.extractall(scratch)
            bundle = read_bundle(Path(scratch) / capture_id)
            for frame in bundle.frames:
                for camera_id in bundle.cameras_in_frame(frame.index):
                    bundle.load_image(frame.index, camera_id)
    except (zipfile.BadZipFile, FormatError, OSError, KeyError, ValueError) as exc:
        return f"{type(exc).__name__}: {exc}"
    if len(bundle.frames) != capture.get("frame_count"):
        return (f"{len(bundle.frames)} frames in the bundle, {capture.get('frame_count')} "
                "listed")
    return None


def tally_captures(acknowledged: Mapping[str, Mapping[str, Any]],
                   listed: Mapping[str, Mapping[str, Any]],
                   broken: Mapping[str, str], *, no_answer: int = 0) -> dict[str, Any]:
    """Acknowledged captures against what the store lists afterwards.

    Parameters
    ----------
    acknowledged : mapping
        Capture id → the 201 answer's body, for every capture the daemon acknowledged.
    listed : mapping
        Capture id → its item in ``GET /api/v1/captures`` afterwards.
    broken : mapping
        Capture id → why its bundle is not intact (:func:`check_bundle`), for listed ones.
    no_answer : int
        Captures sent that got no answer (in flight when the daemon died).

    Returns
    -------
    dict
        ``lost``: acknowledged but not listed; ``corrupted``: listed but broken, or listed
        otherwise than acknowledged (acknowledged or not: a capture stored without an answer
        must be whole too); ``stored_without_answer``: listed but never acknowledged; the first
        :data:`KEPT_IDS` ids of each with the reasons.
    """
    lost = sorted(set(acknowledged) - set(listed))
    corrupted: dict[str, str] = dict(broken)
    for capture_id in sorted(set(acknowledged) & set(listed)):
        if capture_id not in corrupted and dict(listed[capture_id]) != dict(
                acknowledged[capture_id]):
            corrupted[capture_id] = (f"listed as {dict(listed[capture_id])}, acknowledged as "
                                     f"{dict(acknowledged[capture_id])}")
    unanswered = sorted(set(listed) - set(acknowledged))
    return {
        "acknowledged": len(acknowledged),
        "lost": len(lost),
        "corrupted": len(corrupted),
        "intact_acknowledged": len(set(acknowledged) - set(lost) - set(corrupted)),
        "no_answer": no_answer,
        "stored_without_answer": len(unanswered),
        "listed": len(listed),
        "lost_ids": lost[:KEPT_IDS],
        "corrupted_ids": dict(sorted(corrupted.items())[:KEPT_IDS]),
    }


def verify_store(client: httpx.Client, acknowledged: Mapping[str, Mapping[str, Any]], *,
                 no_answer: int = 0) -> dict[str, Any]:
    """List the store and check every listed bundle; :func:`tally_captures` of the result."""
    listed = list_captures(client)
    broken = {capture_id: why for capture_id, item in listed.items()
              if (why := check_bundle(client, item)) is not None}
    return tally_captures(acknowledged, listed, broken, no_answer=no_answer)


def _acknowledged(answers: Iterable[_Answer]) -> dict[str, dict[str, Any]]:
    return {a.body["id"]: a.body for a in answers
            if a.status == 201 and isinstance(a.body, dict) and "id" in a.body}


def _statuses(answers: Iterable[_Answer]) -> dict[str, int]:
    counts = Counter("no answer" if a.status is None and a.sent else
                     "refused connection" if a.status is None else str(a.status)
                     for a in answers)
    return dict(sorted(counts.items()))


def _reasons(answers: Iterable[_Answer]) -> dict[str, str]:
    """The first reason given for each status other than 201."""
    reasons: dict[str, str] = {}
    for answer in answers:
        if answer.status not in (None, 201) and answer.detail:
            reasons.setdefault(str(answer.status), answer.detail[:200])
    return reasons


def _units(client: httpx.Client) -> list[str]:
    return [unit["id"] for unit in checked(client.get(f"{API}/status"), "status")["units"]]


def _warm_up(client: httpx.Client, units: Iterable[str]) -> list[dict[str, Any]]:
    """A capture of each of ``units``: a daemon's first capture of a unit renders the room's
    geometry (seconds), which is start-up, not what the parts measure. The 201 answers."""
    return [checked(client.post(f"{API}/captures", json={"unit": unit}),
                     f"warm-up capture of {unit}") for unit in units]


# --- 1. kill -9 -------------------------------------------------------------------------------


def kill_during_captures(work: Path, cycles: int, rng: random.Random, *,
                         env: Mapping[str, str] | None = None,
                         progress: Progress = quiet) -> dict[str, Any]:
    """SIGKILL the daemon ``cycles`` times while a client posts captures of ``left`` back to
    back, restarting it on the same data directory; then check the store (see the module).

    One unit keeps the daemon's warm-up after each start short; the store's durability does not
    depend on which unit a bundle holds.
    """
    work.mkdir(parents=True, exist_ok=True)
    daemon = DaemonProcess(work / "data", log=work / "daemon.log", env=dict(env or {}))
    answers: list[_Answer] = []
    kills: list[dict[str, Any]] = []
    try:
        for cycle in range(cycles):
            daemon.start()
            poster = _Poster(daemon.url, daemon.physicist_token, ("left",)).start()
            acknowledged_in_time = poster.first_ack.wait(FIRST_ACK_TIMEOUT_S)
            delay_s = rng.uniform(0.0, MAX_KILL_DELAY_S)
            time.sleep(delay_s)
            poster.stop()
            daemon.kill()
            cycle_answers = poster.join()
            answers += cycle_answers
            kills.append({"delay_s": round(delay_s, 3),
                          "acknowledged": len(_acknowledged(cycle_answers)),
                          "no_answer": sum(a.status is None and a.sent for a in cycle_answers),
                          "first_acknowledged_in_time": acknowledged_in_time})
            progress(f"kill -9: cycle {cycle + 1}/{cycles} after {delay_s:.2f} s: "
                     f"{kills[-1]['acknowledged']} acknowledged, {kills[-1]['no_answer']} "
                     "without answer")
        daemon.start()
        progress("kill -9: restarted; checking every listed capture's bundle")
        acknowledged = _acknowledged(answers)
        report = verify_store(daemon.client, acknowledged,
                              no_answer=sum(a.status is None and a.sent for a in answers))
        report["state_after_restart"] = checked(daemon.client.get(f"{API}/status"),
                                                 "status")["state"]
    finally:
        daemon.stop()
    quarantine = work / "data" / "quarantine"
    report.update({
        "cycles": cycles, "max_delay_s": MAX_KILL_DELAY_S, "kills": kills,
        "statuses": _statuses(answers), "refusal_reasons": _reasons(answers),
        "quarantined": len(list(quarantine.iterdir())) if quarantine.is_dir() else 0})
    return report


# --- 2. unplug and replug ---------------------------------------------------------------------


def _status(client: httpx.Client) -> dict[str, Any]:
    body: dict[str, Any] = checked(client.get(f"{API}/status"), "status")
    return body


def _device_health(status: Mapping[str, Any], device_id: str) -> str | None:
    return next((str(d["health"]) for d in status["devices"] if d["id"] == device_id), None)


def _wait_status(client: httpx.Client, done: Callable[[dict[str, Any]], bool],
                 timeout_s: float) -> tuple[float | None, set[str]]:
    """Poll ``/status`` until ``done(status)``: when it was (time.monotonic(), None if not
    within ``timeout_s``) and the daemon states seen meanwhile."""
    states: set[str] = set()
    deadline = time.monotonic() + timeout_s
    while True:
        status = _status(client)
        states.add(str(status["state"]))
        if done(status):
            return time.monotonic(), states
        if time.monotonic() >= deadline:
            return None, states
        time.sleep(POLL_S)


def choose_devices(devices: Sequence[Mapping[str, Any]],
                   wanted: Sequence[str] | None) -> list[dict[str, Any]]:
    """The devices to unplug: ``wanted`` by id, or the first of each kind (``/devices`` order).

    Raises
    ------
    EyeserverError
        A wanted id the daemon does not have.
    """
    by_id = {str(d["id"]): dict(d) for d in devices}
    if wanted:
        unknown = [d for d in wanted if d not in by_id]
        if unknown:
            raise EyeserverError(f"--devices: no device {', '.join(unknown)} (the daemon has "
                                 f"{', '.join(by_id)})")
        return [by_id[d] for d in wanted]
    chosen: dict[str, dict[str, Any]] = {}
    for device in devices:
        chosen.setdefault(str(device["kind"]), dict(device))
    return list(chosen.values())


def _unplug_one(daemon: DaemonProcess, events: _EventReader, device: Mapping[str, Any],
                unplugged_s: float, progress: Progress) -> dict[str, Any]:
    """One unplug and replug of ``device`` while its unit's captures are posted; its figures."""
    client, device_id = daemon.client, str(device["id"])
    unit = str(device["unit"] or "all")  # the trigger serves every unit
    poster = _Poster(daemon.url, daemon.physicist_token, (unit,),
                     pause_s=UNPLUG_POST_PAUSE_S).start()
    poster.first_ack.wait(FIRST_ACK_TIMEOUT_S)
    unplug_sent = time.monotonic()
    unplug = client.put(f"{API}/sim/devices/{device_id}", json={"connected": False})
    detected_at, states = _wait_status(
        client, lambda s: _device_health(s, device_id) == "fault", DETECT_TIMEOUT_S)
    # Captures go on being refused for a while; /status is watched meanwhile.
    _, later_states = _wait_status(client, lambda _: False, unplugged_s)
    poster.stop()
    answers = [a for a in poster.join() if a.sent_s >= unplug_sent]
    # Nobody touches the device from here: the daemon must find it back by itself.
    replug = client.put(f"{API}/sim/devices/{device_id}", json={"connected": True})
    replugged_at = time.monotonic()
    recovered_at, _ = _wait_status(
        client, lambda s: _device_health(s, device_id) == "ok" and s["state"] != "fault",
        RECOVER_TIMEOUT_S)
    fault_event = events.first("device.fault", unplug_sent, device_id=device_id,
                               timeout_s=EVENT_GRACE_S if detected_at else 0.0)
    recovered_event = events.first("device.recovered", replugged_at, device_id=device_id,
                                   timeout_s=EVENT_GRACE_S if recovered_at else 0.0)
    after = client.post(f"{API}/captures", json={"unit": unit})

    def since(start: float, end: float | None) -> float | None:
        return None if end is None else round(end - start, 3)

    acknowledged_after_detection = sum(
        a.status == 201 for a in answers if detected_at is not None and a.sent_s > detected_at)
    result = {
        "device": device_id, "kind": device["kind"], "unit": device["unit"],
        "captures_of": unit, "unplugged_s": unplugged_s,
        "injected": unplug.status_code == 200, "replugged": replug.status_code == 200,
        "detected": detected_at is not None, "detect_s": since(unplug_sent, detected_at),
        "state_fault_seen": "fault" in (states | later_states),
        "fault_event": fault_event is not None,
        "fault_event_s": since(unplug_sent, fault_event),
        "recovered": recovered_at is not None,
        "recover_s": since(replugged_at, recovered_at),
        "recovered_event": recovered_event is not None,
        "recovered_event_s": since(replugged_at, recovered_event),
        "captures_while_unplugged": _statuses(answers),
        "refusal_reasons": _reasons(answers),
        "acknowledged_after_detection": acknowledged_after_detection,
        "capture_after_recovery": after.status_code,
    }
    progress(f"unplug {device_id} ({device['kind']}): detected "
             f"{result['detect_s'] if result['detected'] else 'NO'} s, recovered "
             f"{result['recover_s'] if result['recovered'] else 'NO'} s after the replug; "
             f"captures meanwhile {result['captures_while_unplugged']}")
    return result


def unplug_devices(work: Path, *, rounds: int = 1, devices: Sequence[str] | None = None,
                   unplugged_s: float = 2.0, env: Mapping[str, str] | None = None,
                   progress: Progress = quiet) -> dict[str, Any]:
    """Unplug and replug each chosen device ``rounds`` times while its unit's captures are
    posted, ``unplugged_s`` seconds after the fault was seen (see the module)."""
    work.mkdir(parents=True, exist_ok=True)
    with DaemonProcess(work / "data", log=work / "daemon.log", env=dict(env or {})) as daemon:
        client = daemon.client
        chosen = choose_devices(checked(client.get(f"{API}/devices"), "devices"), devices)
        units = {str(d["unit"]) for d in chosen if d["unit"] is not None}
        if any(d["unit"] is None for d in chosen):  # the trigger's captures take every unit
            units.update(_units(client))
        progress(f"unplug: warm-up captures of {', '.join(sorted(units))}")
        _warm_up(client, sorted(units))
        with _EventReader(daemon) as events:
            results = [_unplug_one(daemon, events, device, unplugged_s, progress)
                       for _ in range(rounds) for device in chosen]
            time.sleep(0.5)  # the last events on their way
        stream = stream_losses(message for _, message in events.messages)
        stream["error"] = events.error
        return {"devices": results, "events": stream}


# --- 3. disk full and freed -------------------------------------------------------------------


def _fill(path: Path) -> int:
    """Write zeros to ``path`` until the disk is full; the bytes written."""
    written = 0
    chunk = bytes(1 << 20)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        while True:
            try:
                written += os.write(fd, chunk)
            except OSError as exc:
                if exc.errno != errno.ENOSPC:
                    raise
                if len(chunk) <= 4096:  # a page short of full is full
                    break
                chunk = chunk[:len(chunk) // 4]
        os.fsync(fd)
    finally:
        os.close(fd)
    return written


def _unmount(mount: Path) -> str | None:
    """Unmount ``mount`` (lazily when busy); None, or why it failed."""
    done = subprocess.run(["umount", str(mount)], capture_output=True, text=True, check=False)
    if done.returncode == 0:
        return None
    lazy = subprocess.run(["umount", "-l", str(mount)], capture_output=True, text=True,
                          check=False)
    return None if lazy.returncode == 0 else (done.stderr.strip() or lazy.stderr.strip())


def disk_full(work: Path, size_mib: int, *, env: Mapping[str, str] | None = None,
              progress: Progress = quiet) -> dict[str, Any]:
    """The daemon's data directory on a ``size_mib`` MiB tmpfs, filled and freed (see the
    module); ``{"skipped": why}`` when it cannot be mounted (not root, no ``mount``)."""
    if not hasattr(os, "geteuid") or os.geteuid() != 0:
        return {"skipped": "mounting a tmpfs needs root"}
    mount = work / "tmpfs"
    mount.mkdir(parents=True, exist_ok=True)
    try:
        mounted = subprocess.run(
            ["mount", "-t", "tmpfs", "-o", f"size={size_mib}m,mode=0700", "tmpfs", str(mount)],
            capture_output=True, text=True, check=False)
    except OSError as exc:
        return {"skipped": f"mount: {exc}"}
    if mounted.returncode != 0:
        return {"skipped": f"mount failed: {mounted.stderr.strip() or mounted.returncode}"}
    try:
        report: dict[str, Any] = {"tmpfs_mib": size_mib}
        daemon = DaemonProcess(mount / "data", log=work / "daemon.log", env=dict(env or {}))
        with daemon:
            client = daemon.client
            progress(f"disk full: {STORED_BEFORE_FULL} captures on a {size_mib} MiB tmpfs, "
                     "then a ballast file until the disk is full")
            acknowledged = {c["id"]: c for c in _warm_up(client, ["left"] * STORED_BEFORE_FULL)}
            report["ballast_bytes"] = _fill(mount / "ballast")
            full: list[dict[str, Any]] = []
            for _ in range(TRIES_WHILE_FULL):
                response = client.post(f"{API}/captures", json={"unit": "left"})
                full.append({"status": response.status_code, "detail": _detail(response)})
                if response.status_code == 201:
                    acknowledged[response.json()["id"]] = response.json()
            failed = [a for a in full if a["status"] != 201]
            report["while_full"] = {
                "captures": len(full), "acknowledged": len(full) - len(failed),
                "statuses": dict(sorted(Counter(str(a["status"]) for a in full).items())),
                "all_failures_507_with_reason": bool(failed) and all(
                    a["status"] == 507 and a["detail"] for a in failed),
                "reason": next((a["detail"] for a in failed if a["detail"]), None),
                "status_answers": client.get(f"{API}/status").status_code}
            report["store_while_full"] = verify_store(client, acknowledged)
            (mount / "ballast").unlink()
            progress("disk full: ballast deleted; capturing again")
            after = [client.post(f"{API}/captures", json={"unit": "left"}) for _ in range(2)]
            acknowledged.update({r.json()["id"]: r.json() for r in after
                                 if r.status_code == 201})
            report["after_freeing"] = {
                "statuses": dict(sorted(Counter(str(r.status_code) for r in after).items())),
                "recovered": all(r.status_code == 201 for r in after),
                "state": _status(client)["state"]}
        with daemon:  # the start-up's recovery sees what the full disk left behind
            report["store_after_restart"] = verify_store(daemon.client, acknowledged)
        quarantine = mount / "data" / "quarantine"
        report["quarantined"] = len(list(quarantine.iterdir())) if quarantine.is_dir() else 0
        return report
    finally:
        problem = _unmount(mount)
        if problem is not None:
            progress(f"disk full: could not unmount {mount}: {problem}")


# --- 4. load ----------------------------------------------------------------------------------


_WRK_TIME = re.compile(r"^([0-9.]+)(us|ms|s)$")
_WRK_UNIT_MS = {"us": 1e-3, "ms": 1.0, "s": 1e3}


def _wrk_ms(text: str) -> float:
    match = _WRK_TIME.match(text)
    if match is None:
        raise ValueError(f"not a wrk duration: {text!r}")
    return round(float(match.group(1)) * _WRK_UNIT_MS[match.group(2)], 2)


def parse_wrk(output: str) -> dict[str, Any]:
    """The status summary (as :func:`_ms_summary`, with ``statuses``) from ``wrk --latency``'s
    report: requests, median, p99 and maximum latency, and the answers that were not 2xx.

    Raises
    ------
    ValueError
        The report lacks its latency distribution or request count.
    """
    percentiles = dict(re.findall(r"^\s+(50|99)%\s+(\S+)$", output, re.MULTILINE))
    latency = re.search(r"^\s+Latency\s+\S+\s+\S+\s+(\S+)", output, re.MULTILINE)
    requests = re.search(r"^\s+(\d+) requests in", output, re.MULTILINE)
    if len(percentiles) < 2 or latency is None or requests is None:
        raise ValueError(f"wrk's report has no latency distribution:\n{output}")
    refused = re.search(r"Non-2xx or 3xx responses: (\d+)", output)
    errors = re.search(r"Socket errors: (.*)$", output, re.MULTILINE)
    total, bad = int(requests.group(1)), int(refused.group(1)) if refused else 0
    statuses = {"200": total - bad, **({"not 2xx": bad} if bad else {}),
                **({"socket errors": errors.group(1)} if errors else {})}
    return {"requests": total, "p50_ms": _wrk_ms(percentiles["50"]),
            "p99_ms": _wrk_ms(percentiles["99"]), "max_ms": _wrk_ms(latency.group(1)),
            "statuses": statuses}


class _WrkStatus:
    """``wrk`` reading ``GET /status`` over ``clients`` connections for ``seconds``: a client
    in C that takes a small share of the cores a Python one would, so the latency it measures
    is the daemon's more than its own (the Python readers, :class:`_StatusReader`, saturate
    their own interpreter long before the daemon: issue 35's p99 of 5.9 s was largely that)."""

    def __init__(self, url: str, token: str, clients: int, seconds: float) -> None:
        self._command = ["wrk", "-t2", f"-c{clients}", f"-d{max(1, round(seconds))}s",
                         "--latency", "-H", f"Authorization: Bearer {token}",
                         f"{url}{API}/status"]
        self._process: subprocess.Popen[str] | None = None

    def start(self) -> None:
        self._process = subprocess.Popen(self._command, stdout=subprocess.PIPE,
                                         stderr=subprocess.STDOUT, text=True)

    def result(self) -> dict[str, Any]:
        """Wait for wrk's end and read its report."""
        assert self._process is not None
        output, _ = self._process.communicate()
        return parse_wrk(output)


def load(work: Path, seconds: float, *, status_clients: int = 100, capture_clients: int = 20,
         env: Mapping[str, str] | None = None, use_wrk: bool | None = None,
         progress: Progress = quiet) -> dict[str, Any]:
    """``status_clients`` connections reading ``/status`` and ``capture_clients`` threads
    posting captures (every unit and ``all`` in turn), back to back for ``seconds``, with one
    event-stream client; idle status latency measured first (see the module). The status
    readers are ``wrk`` when it is installed (``use_wrk`` None) or asked for, else threads."""
    if use_wrk is None:
        use_wrk = shutil.which("wrk") is not None
    work.mkdir(parents=True, exist_ok=True)
    with DaemonProcess(work / "data", log=work / "daemon.log", env=dict(env or {})) as daemon:
        client = daemon.client
        units = [*_units(client), "all"]
        progress("load: warm-up captures, then the idle status latency")
        _warm_up(client, units)
        idle: list[float] = []
        for _ in range(IDLE_STATUS_REQUESTS):
            started = time.perf_counter()
            checked(client.get(f"{API}/status"), "status")
            idle.append(time.perf_counter() - started)
        progress(f"load: {status_clients} status readers and {capture_clients} capture posters "
                 f"for {seconds:g} s")
        readers = [] if use_wrk else [_StatusReader(daemon.url, daemon.operator_token)
                                      for _ in range(status_clients)]
        wrk = _WrkStatus(daemon.url, daemon.operator_token, status_clients, seconds) \
            if use_wrk else None
        with _EventReader(daemon) as events:
            cpu_before = _cpu_now(daemon.pid)
            started_s = time.monotonic()
            posters = [_Poster(daemon.url, daemon.operator_token,
                               units[n % len(units):] + units[:n % len(units)]).start()
                       for n in range(capture_clients)]
            for reader in readers:
                reader.start()
            if wrk is not None:
                wrk.start()
                under_load = wrk.result()  # it stops on its own after ``seconds``
            else:
                time.sleep(seconds)
            for reader in readers:
                reader.stop()
            for poster in posters:
                poster.stop()
            for reader in readers:
                reader.join()
            answers = [a for poster in posters for a in poster.join()]
            elapsed_s = time.monotonic() - started_s
            cpu = _cpu_used(cpu_before, _cpu_now(daemon.pid))
            acknowledged = _acknowledged(answers)
            # Every acknowledged capture's event must arrive; give the last ones a moment.
            deadline = time.monotonic() + EVENT_GRACE_S
            while time.monotonic() < deadline and not acknowledged.keys() <= {
                    m.get("capture_id") for _, m in list(events.messages)}:
                time.sleep(POLL_S)
        stored_events = {m.get("capture_id") for _, m in events.messages
                         if m.get("type") == "capture.stored"}
        if wrk is None:
            statuses: Counter[str] = Counter()
            for reader in readers:
                statuses.update(reader.statuses)
            under_load = {**_ms_summary([t for r in readers for t in r.latencies_s]),
                          "statuses": dict(sorted(statuses.items()))}
        stream = stream_losses(message for _, message in events.messages)
        stream.update({"error": events.error,
                       "capture_stored_missing": len(set(acknowledged) - stored_events)})
        return {
            "seconds": seconds, "elapsed_s": round(elapsed_s, 2),
            "status_clients": status_clients, "capture_clients": capture_clients,
            "status_idle": _ms_summary(idle),
            "status_client": "wrk" if wrk is not None else "python threads",
            "status_under_load": under_load,
            "status_p99_goal_ms": STATUS_P99_GOAL_MS,
            "captures": {"posted": len(answers), "acknowledged": len(acknowledged),
                         "per_s": round(len(acknowledged) / elapsed_s, 2),
                         "statuses": _statuses(answers), "refusal_reasons": _reasons(answers),
                         "latency": _ms_summary([a.answered_s - a.sent_s for a in answers
                                                 if a.status == 201])},
            "events": stream,
            "cpu_s": {"cores": os.cpu_count(), **cpu},
            "note": "the clients run on the daemon's cores: they take CPU time from it (wrk's "
                    "counts as another process's) and add their own scheduling to the "
                    "latencies they measure",
        }


def _cpu_now(pid: int) -> tuple[float, float | None, float | None]:
    """CPU seconds used so far by this process (every thread), by process ``pid`` and by the
    whole machine (every core's busy time; the last two None without Linux's /proc)."""
    tick = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
    client = time.process_time()
    try:
        # /proc/PID/stat: utime and stime are the 14th and 15th fields, the 12th and 13th
        # after the command name's closing parenthesis.
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        daemon: float | None = (int(fields[11]) + int(fields[12])) / tick
        # /proc/stat's cpu line: user nice system idle iowait irq softirq steal …; busy is
        # all but idle, iowait and steal (the hypervisor's, not this machine's).
        ticks = [int(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
        machine_busy: float | None = sum(ticks[i] for i in (0, 1, 2, 5, 6)) / tick
    except (OSError, ValueError, IndexError):
        daemon = machine_busy = None
    return client, daemon, machine_busy


def _cpu_used(before: tuple[float, float | None, float | None],
              after: tuple[float, float | None, float | None]) -> dict[str, float | None]:
    """CPU seconds between two :func:`_cpu_now`: the bench's clients, the daemon, and every
    other process of the machine (what else shared the cores during the measurement)."""
    client = after[0] - before[0]
    daemon = None if after[1] is None or before[1] is None else after[1] - before[1]
    busy = None if after[2] is None or before[2] is None else after[2] - before[2]
    other = None if busy is None or daemon is None else max(0.0, busy - daemon - client)
    return {"client": round(client, 2), "daemon": None if daemon is None else round(daemon, 2),
            "other": None if other is None else round(other, 2)}


# --- 5. fuzz ----------------------------------------------------------------------------------


@dataclass
class _FuzzTally:
    """What the fuzz's cases got, over every operation and role."""

    statuses: Counter[str] = field(default_factory=Counter)
    by_code: Counter[str] = field(default_factory=Counter)
    other_failures: Counter[str] = field(default_factory=Counter)
    samples: list[dict[str, Any]] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)

    def record(self, label: str, role: str, status: int,
               failures: Sequence[schemathesis.core.failures.Failure]) -> None:
        self.statuses[str(status)] += 1
        for failure in failures:
            self.by_code[failure.code] += 1
            if failure.code not in COUNTED_FAILURE_CODES:
                self.other_failures[failure.title] += 1
            if len(self.samples) < KEPT_IDS:
                self.samples.append({"operation": label, "role": role, "status": status,
                                     "failure": failure.title,
                                     "message": failure.message[:300]})


def _fuzz_operation(operation: schemathesis.APIOperation[Any, Any, Any, Any], base_url: str,
                    role: str, token: str, examples: int, seed: int, tally: _FuzzTally) -> None:
    """Up to ``examples`` cases of one operation, its documented examples among them, sent
    with one role's token and checked; into ``tally``."""
    from hypothesis import HealthCheck, Phase, given, settings
    from hypothesis import seed as hypothesis_seed
    from hypothesis import strategies as st
    from schemathesis.errors import FailureGroup
    from schemathesis.specs.openapi.checks import (
        negative_data_rejection,
        positive_data_acceptance,
    )

    headers = _auth(token)
    excluded: list[schemathesis.CheckFunction] = [positive_data_acceptance,
                                                  negative_data_rejection]
    strategies = [*operation.get_strategies_from_examples(), operation.as_strategy()]

    @hypothesis_seed(seed)
    @settings(max_examples=examples, deadline=None, database=None,
              phases=[Phase.explicit, Phase.generate], suppress_health_check=list(HealthCheck))
    @given(st.one_of(strategies))
    def call(case: schemathesis.Case[Any]) -> None:
        response = case.call(base_url=base_url, headers=headers, timeout=REQUEST_TIMEOUT_S)
        failures: list[schemathesis.core.failures.Failure] = []
        try:
            case.validate_response(response, excluded_checks=excluded, headers=headers,
                                   transport_kwargs={"base_url": base_url, "headers": headers,
                                                     "timeout": REQUEST_TIMEOUT_S})
        except FailureGroup as group:
            failures = list(group.exceptions)
        tally.record(operation.label, role, response.status_code, failures)

    call()


def fuzz(work: Path, examples: int, *, operations: str | None = None, seed: int = 0,
         env: Mapping[str, str] | None = None, progress: Progress = quiet) -> dict[str, Any]:
    """A schemathesis run over every operation of the daemon's own OpenAPI document (those
    whose path matches the regular expression ``operations``, if given) but
    :data:`FUZZ_LEFT_OUT`, at most ``examples`` cases per operation and role, seeded;
    ``{"skipped": why}`` without schemathesis (a dev dependency).

    Every check runs but two, as in tests/test_api_fuzz.py (whose docstring says why):
    ``positive_data_acceptance`` and ``negative_data_rejection``. ``server_errors`` counts the
    5xx answers the API does not document (:data:`DOCUMENTED_5XX`).
    """
    try:
        import schemathesis
        from schemathesis.core.result import Ok
    except ImportError as exc:
        return {"skipped": f"schemathesis is not installed ({exc}); it comes with "
                           "pip install -e '.[dev]'"}
    work.mkdir(parents=True, exist_ok=True)

    @schemathesis.serializer("application/zip")
    def _zip_body(ctx: object, value: object) -> bytes:
        # A calibration upload's body as generated: the daemon must refuse any that is not a
        # calibration zip with a 4xx.
        return value if isinstance(value, bytes) else str(value).encode()

    tally = _FuzzTally()
    with DaemonProcess(work / "data", log=work / "daemon.log", env=dict(env or {})) as daemon:
        document = checked(daemon.client.get(f"{API}/openapi.json"), "OpenAPI document")
        schema = schemathesis.openapi.from_dict(document).exclude(
            path_regex="|".join(f"^{re.escape(API + path)}$" for path in FUZZ_LEFT_OUT))
        chosen = []
        for result in schema.get_all_operations():
            if isinstance(result, Ok):
                chosen.append(result.ok())
            else:  # an operation the document describes unusably
                tally.errors.append(f"{type(result.err()).__name__}: {result.err()}"[:300])
        if operations:
            chosen = [op for op in chosen if re.search(operations, op.path)]
        roles = {"operator": daemon.operator_token, "physicist": daemon.physicist_token}
        progress(f"fuzz: {len(chosen)} operations × {len(roles)} roles, at most {examples} "
                 "cases each")
        for number, operation in enumerate(chosen, 1):
            for role, token in roles.items():
                try:
                    _fuzz_operation(operation, daemon.url, role, token, examples, seed, tally)
                except Exception as exc:  # a transport error, a generation failure: reported
                    tally.errors.append(f"{operation.label} ({role}): {type(exc).__name__}: "
                                        f"{exc}"[:300])
            if number % 10 == 0 or number == len(chosen):
                progress(f"fuzz: {number}/{len(chosen)} operations, "
                         f"{sum(tally.statuses.values())} requests")
    return {
        "operations": len(chosen), "roles": sorted(roles), "examples_per_operation": examples,
        "seed": seed, "left_out": list(FUZZ_LEFT_OUT),
        "excluded_checks": ["positive_data_acceptance", "negative_data_rejection"],
        "requests": sum(tally.statuses.values()),
        "statuses": dict(sorted(tally.statuses.items())),
        "server_errors": _server_errors(tally.statuses),
        "undocumented_status": tally.by_code[UNDOCUMENTED_STATUS_CODE],
        "schema_mismatches": sum(n for code, n in tally.by_code.items()
                                 if code in SCHEMA_FAILURE_CODES),
        "other_failures": dict(sorted(tally.other_failures.items())),
        "failures_by_code": dict(sorted(tally.by_code.items())),
        "failure_samples": tally.samples,
        "errors": tally.errors,
    }


# --- the whole bench --------------------------------------------------------------------------


def _part_dir(base: Path, name: str) -> Path:
    path = base / name
    if path.exists() and any(path.iterdir()):
        raise EyeserverError(f"{path} is not empty: give the bench a fresh directory")
    path.mkdir(parents=True, exist_ok=True)
    return path


def run(*, kill_cycles: int = 12, unplug_rounds: int = 1,
        devices: Sequence[str] | None = None, unplugged_s: float = 2.0, disk_mib: int = 128,
        load_seconds: float = 30.0, status_clients: int = 100, capture_clients: int = 20,
        fuzz_examples: int = 3, fuzz_operations: str | None = None, seed: int = 0,
        room_file: Path | None = None, work: Path | None = None,
        progress: Progress = quiet) -> dict[str, Any]:
    """Run the five parts (each skipped when its size is 0) and report (JSON-able).

    ``work`` keeps each part's data directory and daemon log (``kill/``, ``unplug/``, …; must
    not hold an earlier run's); by default they go to a temporary directory.

    Raises
    ------
    DaemonError
        A daemon did not start, or a request a part relies on failed (the message says which).
    """
    started = time.monotonic()
    env = {} if room_file is None else {"EYESERVER_ROOM_FILE": str(room_file)}
    with tempfile.TemporaryDirectory(prefix="eyeserver-bench-reliability-") as scratch:
        base = work or Path(scratch)
        report: dict[str, Any] = {
            "format": FORMAT, "machine": machine(), "seed": seed,
            "options": {"kill_cycles": kill_cycles, "unplug_rounds": unplug_rounds,
                        "devices": list(devices) if devices else None,
                        "unplugged_s": unplugged_s, "disk_mib": disk_mib,
                        "load_seconds": load_seconds, "status_clients": status_clients,
                        "capture_clients": capture_clients, "fuzz_examples": fuzz_examples,
                        "fuzz_operations": fuzz_operations,
                        "room": str(room_file) if room_file else None},
            "reference_fft_ms": {"at_start": round(reference_ms(), 2)}}
        report["kill"] = (kill_during_captures(_part_dir(base, "kill"), kill_cycles,
                                      random.Random(seed), env=env, progress=progress)
                          if kill_cycles else {"skipped": "--kill-cycles 0"})
        report["unplug"] = (unplug_devices(_part_dir(base, "unplug"), rounds=unplug_rounds,
                                           devices=devices, unplugged_s=unplugged_s, env=env,
                                           progress=progress)
                            if unplug_rounds else {"skipped": "--unplug-rounds 0"})
        report["disk_full"] = (disk_full(_part_dir(base, "disk"), disk_mib, env=env,
                                         progress=progress)
                               if disk_mib else {"skipped": "--disk-mib 0"})
        report["load"] = (load(_part_dir(base, "load"), load_seconds,
                               status_clients=status_clients, capture_clients=capture_clients,
                               env=env, progress=progress)
                          if load_seconds else {"skipped": "--load-seconds 0"})
        report["fuzz"] = (fuzz(_part_dir(base, "fuzz"), fuzz_examples,
                               operations=fuzz_operations, seed=seed, env=env,
                               progress=progress)
                          if fuzz_examples else {"skipped": "--fuzz-examples 0"})
    report["reference_fft_ms"]["at_end"] = round(reference_ms(), 2)
    report["duration_s"] = round(time.monotonic() - started, 1)
    report["findings"] = findings(report)
    return report


def _store_findings(where: str, store: Mapping[str, Any] | None) -> list[str]:
    if not store:
        return []
    found = []
    if store["lost"]:
        found.append(f"{where}: {store['lost']} acknowledged capture(s) LOST: "
                     f"{', '.join(store['lost_ids'])}")
    if store["corrupted"]:
        found.append(f"{where}: {store['corrupted']} stored capture(s) CORRUPTED: "
                     + "; ".join(f"{k}: {v}" for k, v in store["corrupted_ids"].items()))
    return found


def _server_errors(statuses: Mapping[str, int]) -> int:
    """Answers with a 5xx status the API does not document (500: a bug)."""
    return sum(n for code, n in statuses.items()
               if code.startswith("5") and code not in DOCUMENTED_5XX)


def findings(report: Mapping[str, Any]) -> list[str]:
    """What went wrong in a report, one sentence each: acknowledged captures lost or
    corrupted, 500s, faults not detected or not recovered, events lost, goals missed, fuzz
    failures. Empty when nothing did."""
    found: list[str] = []
    kill = report.get("kill", {})
    if "skipped" not in kill:
        found += _store_findings("kill -9", kill)
        if kill.get("state_after_restart") not in (None, "idle"):
            found.append(f"kill -9: the restarted daemon is {kill['state_after_restart']}, "
                         "not idle")
        if _server_errors(kill.get("statuses", {})):
            found.append(f"kill -9: captures answered {kill['statuses']}")
    unplug = report.get("unplug", {})
    for device in unplug.get("devices", []):
        name = f"unplug {device['device']} ({device['kind']})"
        for flag, what in (("injected", "the unplug was refused"),
                           ("detected", "the fault was NOT detected in /status"),
                           ("fault_event", "no device.fault event"),
                           ("recovered", "NOT recovered after the replug"),
                           ("recovered_event", "no device.recovered event")):
            if not device[flag]:
                found.append(f"{name}: {what}")
        if device["acknowledged_after_detection"]:
            found.append(f"{name}: {device['acknowledged_after_detection']} capture(s) of its "
                         "unit acknowledged after the fault was detected")
        if _server_errors(device["captures_while_unplugged"]):
            found.append(f"{name}: captures answered {device['captures_while_unplugged']}")
        if device["capture_after_recovery"] != 201:
            found.append(f"{name}: a capture after the recovery answered "
                         f"{device['capture_after_recovery']}")
    if unplug.get("events", {}).get("lost"):
        found.append(f"unplug: the event stream lost {unplug['events']['lost']} event(s)")
    disk = report.get("disk_full", {})
    if disk and "skipped" not in disk:
        full = disk["while_full"]
        if not full["all_failures_507_with_reason"]:
            found.append(f"disk full: captures answered {full['statuses']} (expected 507 with "
                         "a JSON reason)")
        if full["status_answers"] != 200:
            found.append(f"disk full: /status answered {full['status_answers']}")
        found += _store_findings("disk full", disk["store_while_full"])
        found += _store_findings("disk full, after a restart", disk["store_after_restart"])
        if not disk["after_freeing"]["recovered"]:
            found.append(f"disk freed: captures answered {disk['after_freeing']['statuses']}")
    load_part = report.get("load", {})
    if load_part and "skipped" not in load_part:
        p99 = load_part["status_under_load"]["p99_ms"]
        if p99 is None or p99 > load_part["status_p99_goal_ms"]:
            found.append(f"load: status p99 {p99} ms under load, goal ≤ "
                         f"{load_part['status_p99_goal_ms']:g} ms")
        if set(load_part["status_under_load"]["statuses"]) - {"200"}:
            found.append(f"load: /status answered {load_part['status_under_load']['statuses']}")
        if _server_errors(load_part["captures"]["statuses"]) or \
                load_part["captures"]["statuses"].get("no answer"):
            found.append(f"load: captures answered {load_part['captures']['statuses']}")
        events = load_part["events"]
        if events["lost"] or events["capture_stored_missing"] or events["error"]:
            found.append(f"load: event stream lost {events['lost']} event(s), "
                         f"{events['capture_stored_missing']} acknowledged capture(s) without "
                         f"capture.stored{', ' + events['error'] if events['error'] else ''}")
    fuzz_part = report.get("fuzz", {})
    if fuzz_part and "skipped" not in fuzz_part:
        for key, what in (("server_errors", "5xx answers other than 503, 504, 507"),
                          ("undocumented_status", "undocumented status codes"),
                          ("schema_mismatches", "answers that break their schema")):
            if fuzz_part[key]:
                found.append(f"fuzz: {fuzz_part[key]} {what}")
        if fuzz_part["other_failures"]:
            found.append(f"fuzz: other failed checks {fuzz_part['other_failures']}")
        if fuzz_part["errors"]:
            found.append(f"fuzz: {len(fuzz_part['errors'])} run(s) broke off: "
                         f"{fuzz_part['errors'][0]}")
    return found


# --- text -------------------------------------------------------------------------------------


def _seconds(value: float | None) -> str:
    return "—" if value is None else f"{value:.2f} s"


def _store_text(store: Mapping[str, Any]) -> str:
    return (f"{store['acknowledged']} acknowledged: {store['lost']} lost, {store['corrupted']} "
            f"corrupted, {store['intact_acknowledged']} intact")


def format_text(report: Mapping[str, Any]) -> str:
    """The report for people."""
    m = report["machine"]
    lines = [f"eyeserver bench reliability — {m['platform']}, {m['cpu_count']} CPUs, Python "
             f"{m['python']}, seed {report['seed']}, {report['duration_s']} s"]
    kill = report["kill"]
    if "skipped" in kill:
        lines.append(f"kill -9: skipped ({kill['skipped']})")
    else:
        lines += [f"kill -9, {kill['cycles']} cycles: {_store_text(kill)}; "
                  f"{kill['no_answer']} in flight without answer, "
                  f"{kill['stored_without_answer']} of them stored (and checked); "
                  f"{kill['quarantined']} interrupted write(s) quarantined; restarted daemon "
                  f"{kill['state_after_restart']}",
                  f"  answers {kill['statuses']}"]
    unplug = report["unplug"]
    if "skipped" in unplug:
        lines.append(f"unplug/replug: skipped ({unplug['skipped']})")
    else:
        lines.append("unplug/replug (captures of its unit posted while unplugged; nobody "
                     "touching it after the replug):")
        for d in unplug["devices"]:
            lines.append(
                f"  {d['device']:<4} {d['kind']:<9} injected {d['injected']}, detected "
                f"{_seconds(d['detect_s']) if d['detected'] else 'NO'} (event "
                f"{_seconds(d['fault_event_s']) if d['fault_event'] else 'NONE'}), recovered "
                f"{_seconds(d['recover_s']) if d['recovered'] else 'NO'} after the replug "
                f"(event {_seconds(d['recovered_event_s']) if d['recovered_event'] else 'NONE'}"
                f"); captures meanwhile {d['captures_while_unplugged']}; after "
                f"{d['capture_after_recovery']}")
        lines.append(f"  event stream: {unplug['events']['messages']} messages, "
                     f"{unplug['events']['lost']} lost")
    disk = report["disk_full"]
    if "skipped" in disk:
        lines.append(f"disk full: skipped ({disk['skipped']})")
    else:
        full = disk["while_full"]
        verdict = ("all 507 with a reason" if full["all_failures_507_with_reason"]
                   else "NOT all 507 with a reason")
        lines += [f"disk full ({disk['tmpfs_mib']} MiB tmpfs): captures answered "
                  f"{full['statuses']} ({verdict}: {full['reason']!r}); stored: "
                  f"{_store_text(disk['store_while_full'])}; "
                  f"freed: {disk['after_freeing']['statuses']}, after a restart "
                  f"{_store_text(disk['store_after_restart'])}"]
    load_part = report["load"]
    if "skipped" in load_part:
        lines.append(f"load: skipped ({load_part['skipped']})")
    else:
        idle, busy = load_part["status_idle"], load_part["status_under_load"]
        captures, events = load_part["captures"], load_part["events"]
        goal = load_part["status_p99_goal_ms"]
        met = busy["p99_ms"] is not None and busy["p99_ms"] <= goal
        cpu = load_part["cpu_s"]
        lines += [f"load, {load_part['seconds']} s ({load_part['elapsed_s']} s until the last "
                  f"answer): {load_part['status_clients']} status readers "
                  f"({load_part.get('status_client', 'python threads')}), "
                  f"{load_part['capture_clients']} capture posters, 1 event stream",
                  f"  GET /status idle     p50 {idle['p50_ms']} ms, p99 {idle['p99_ms']} ms, "
                  f"max {idle['max_ms']} ms ({idle['requests']} requests)",
                  f"  GET /status loaded   p50 {busy['p50_ms']} ms, p99 {busy['p99_ms']} ms, "
                  f"max {busy['max_ms']} ms ({busy['requests']} requests)   goal p99 ≤ "
                  f"{goal:g} ms  {'met' if met else 'NOT met'}",
                  f"  captures {captures['per_s']}/s ({captures['acknowledged']} of "
                  f"{captures['posted']}), answers {captures['statuses']}",
                  f"  event stream {events['messages']} messages, {events['lost']} lost, "
                  f"{events['capture_stored_missing']} capture.stored missing",
                  f"  CPU meanwhile: daemon {cpu['daemon']} s, clients {cpu['client']} s, other "
                  f"processes {cpu['other']} s, of {cpu['cores']} cores × "
                  f"{load_part['elapsed_s']} s",
                  f"  ({load_part['note']})"]
    fz = report["fuzz"]
    if "skipped" in fz:
        lines.append(f"fuzz: skipped ({fz['skipped']})")
    else:
        lines.append(f"fuzz: {fz['operations']} operations × {len(fz['roles'])} roles, "
                     f"{fz['requests']} requests: {fz['server_errors']} 5xx, "
                     f"{fz['undocumented_status']} undocumented status, "
                     f"{fz['schema_mismatches']} schema mismatches; statuses {fz['statuses']}")
    found = report["findings"]
    lines.append("findings: none" if not found else "FINDINGS:")
    lines += [f"  - {f}" for f in found]
    return "\n".join(lines)
