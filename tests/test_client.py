"""The Python client (``clients/python``, package ``eyeserver_client``) against a live daemon.

One daemon serves the module (behind uvicorn on loopback, :func:`tests.liveserver.live_server`,
on the simulated room), driven only through the client: the workflows of its examples (the
OIS's patient → reference → measure → verdict, the physicist's guided calibration, tracking
with the beam-hold flag), the errors with the daemon's reasons, the token's sources, and the
streams resuming after their connection was cut, by ``seq``, losing nothing unaccounted and
repeating nothing. Connections are cut by a TCP relay between client and daemon
(:class:`_Relay`), as a network or a restarting daemon cuts them. The checks that need no
daemon keep the client from drifting away from it: its models are what the daemon's OpenAPI
document gives, its operations are the document's, its blocking half is the asyncio half's
copy, and it imports nothing of the daemon (it installs alone).

The daemon runs without the daily QA's lockout (tests/apiclient.py), except for the OIS's
workflow, which turns it on to show that the example runs the QA (a physicist's baseline, the
QA phantom placed in the simulated room and the eye put back) before it can verify.

Live tracking runs the scripted frame source and fit of ``tests/test_tracking.py`` (the real
pipeline's speed is the benches'), so the beam hold's changes come at known frames. No test
asserts on wall-clock time; timeouts only keep a broken build from hanging.
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib.util
import inspect
import io
import re
import socket
import sys
import threading
import time
import zipfile
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from types import ModuleType
from typing import Any, TypeVar

import eyeserver_client as ec
import httpx
import pytest
from eyeserver_client import _operations
from eyeserver_client.messages import (
    CalibrationSessionView,
    CaptureStored,
    Disconnected,
    Dropped,
    Event,
    Hello,
    Message,
    PoseMeasured,
    PoseMessage,
    QaRunDone,
    ReconstructionDone,
    Resumed,
    StateChanged,
)
from eyeserver_client.models import CaptureResponse, HealthResponse
from fastapi import FastAPI

from eyeserver.api import create_app
from eyeserver.calibration.artefact import ARRAYS_FILE, CALIBRATION_FILE
from eyeserver.core.clock import ManualClock
from eyeserver.eye.fit import EyePose
from eyeserver.service.frame_pose import PoseFinder
from eyeserver.service.qa import DailyQa
from eyeserver.service.tracking import TrackingControl
from tests.apiclient import OPERATOR_TOKEN, PHYSICIST_TOKEN, test_settings
from tests.liveserver import live_server
from tests.test_tracking import ScriptedPipeline, ScriptedSource

CLIENT = Path(__file__).resolve().parents[1] / "clients" / "python"
PACKAGE = CLIENT / "src" / "eyeserver_client"
M = TypeVar("M", bound=Message)
STREAM_SILENCE_S = 30.0  # only against hangs: a stream that hears nothing this long gives up
TICK = "client_test.tick"


def _load(relative: str) -> ModuleType:
    """A script or example of the client (not a package) as a module."""
    path = CLIENT / relative
    spec = importlib.util.spec_from_file_location(f"eyeserver_client_{path.stem}", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


# --- the client against the daemon's document (no daemon running) --------------------------


def test_the_models_are_what_the_daemons_openapi_document_gives(app: FastAPI) -> None:
    # Fails when a route's schema changed without `python clients/python/scripts/
    # generate_models.py` (or the client's models were edited by hand).
    generator = _load("scripts/generate_models.py")
    assert generator.render(app.openapi()) == (PACKAGE / "models.py").read_text(), (
        "clients/python/src/eyeserver_client/models.py is out of date: run "
        "python clients/python/scripts/generate_models.py")


def test_the_blocking_client_is_the_asyncio_one_without_asyncio() -> None:
    unasync = _load("scripts/unasync.py")
    for source, output, docstring in unasync.FILES:
        expected = unasync.render((PACKAGE / source).read_text(), docstring)
        assert expected == (PACKAGE / output).read_text(), (
            f"{output} is out of date: run python clients/python/scripts/unasync.py")


def test_every_operation_of_the_api_is_a_method_of_the_client(app: FastAPI) -> None:
    documented = {(method.upper(), path) for path, methods in app.openapi()["paths"].items()
                  for method in methods}
    table = _operations.OPERATIONS
    known = {(op.method, ("/api/v1" if op.under_api else "") + op.path) for op in table.values()}
    assert known == documented
    # ... and each is called by a method of the client (the blocking one is its copy).
    source = inspect.getsource(ec.AsyncClient)
    assert sorted(name for name in table if f"ops.{name}," not in source
                  and f"ops.{name})" not in source) == []


def test_the_client_package_imports_nothing_of_the_daemon() -> None:
    # It installs and runs alone (pip install clients/python): httpx, websockets, pydantic.
    daemon = re.compile(r"^\s*(from|import)\s+eyeserver(\.|\s|$)")
    found = [f"{path.name}:{number}" for path in sorted(PACKAGE.glob("*.py"))
             for number, line in enumerate(path.read_text().splitlines(), 1)
             if daemon.match(line)]
    assert found == []
    assert (PACKAGE / "py.typed").is_file()


# --- a daemon on loopback ----------------------------------------------------------------


@pytest.fixture(scope="module")
def base_url(app: FastAPI) -> Iterator[str]:
    with live_server(app) as url:
        yield url


@pytest.fixture(scope="module")
def physicist(base_url: str) -> Iterator[ec.Client]:
    with ec.Client(base_url, token=PHYSICIST_TOKEN) as client:
        yield client


@pytest.fixture(scope="module")
def operator(base_url: str) -> Iterator[ec.Client]:
    with ec.Client(base_url, token=OPERATOR_TOKEN) as client:
        yield client


@pytest.fixture(scope="module")
def calibration_id(physicist: ec.Client,
                   calibrated_rooms: Callable[[str], tuple[Path, Path]]) -> str:
    """The simulated room's calibration, imported and activated through the client."""
    caldir = calibrated_rooms("default")[1]
    archive = io.BytesIO()
    with zipfile.ZipFile(archive, "w") as zipped:
        for name in (CALIBRATION_FILE, ARRAYS_FILE):
            zipped.writestr(name, (caldir / name).read_bytes())
    imported = physicist.import_calibration(archive.getvalue())
    assert imported.active is False and imported.quality
    active = physicist.activate_calibration(imported.id)
    assert active.active is True
    return active.id


class _Relay:
    """A TCP relay on loopback between clients and a daemon. :meth:`cut` breaks every
    connection through it at once, as a network or a daemon that goes away does; ``upstream``
    may then point at another daemon."""

    def __init__(self, upstream: str) -> None:
        self.upstream = upstream
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.url = f"http://127.0.0.1:{self._listener.getsockname()[1]}"
        self._lock = threading.Lock()
        self._open: list[socket.socket] = []
        threading.Thread(target=self._accept, name="relay", daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                near, _ = self._listener.accept()
            except OSError:
                return  # closed
            host, port = self.upstream.removeprefix("http://").split(":")
            try:
                far = socket.create_connection((host, int(port)), timeout=5.0)
            except OSError:
                near.close()  # nobody there: the client sees its connection refused
                continue
            far.settimeout(None)
            with self._lock:
                self._open += [near, far]
            for source, sink in ((near, far), (far, near)):
                threading.Thread(target=self._pump, args=(source, sink), daemon=True).start()

    @staticmethod
    def _pump(source: socket.socket, sink: socket.socket) -> None:
        with contextlib.suppress(OSError):
            while data := source.recv(65536):
                sink.sendall(data)
        for end in (source, sink):
            with contextlib.suppress(OSError):
                end.shutdown(socket.SHUT_RDWR)

    def cut(self) -> None:
        """Break every connection through the relay (no close frame, no FIN first)."""
        with self._lock:
            ends, self._open = self._open, []
        for end in ends:
            with contextlib.suppress(OSError):
                end.shutdown(socket.SHUT_RDWR)
            end.close()

    def close(self) -> None:
        self._listener.close()
        self.cut()


@pytest.fixture
def relay(base_url: str) -> Iterator[_Relay]:
    relay = _Relay(base_url)
    yield relay
    relay.close()


def _account(messages: list[Message]) -> list[int]:
    """The ``seq`` of every event in ``messages``, checking that each one is either received
    or counted as lost (``Dropped``, ``Resumed.missed``) and that none comes twice."""
    seqs: list[int] = []
    expected: int | None = None
    for message in messages:
        if isinstance(message, Hello):
            expected = message.last_seq if expected is None else expected
        elif isinstance(message, Resumed):
            assert message.missed is not None and expected is not None
            expected += message.missed
        elif isinstance(message, Dropped):
            assert expected is not None
            expected += message.count
        elif isinstance(message, Event):
            if expected is not None:
                assert message.seq == expected + 1, (message, expected)
            expected = message.seq
            seqs.append(message.seq)
    assert len(seqs) == len(set(seqs))
    return seqs


def _until(stream: Iterator[Message], kind: type[M], into: list[Message] | None = None,
           where: Callable[[M], bool] = lambda message: True) -> M:
    """Read ``stream`` until a ``kind`` message ``where`` holds; every message read goes
    ``into``."""
    for message in stream:
        if into is not None:
            into.append(message)
        if isinstance(message, kind) and where(message):
            return message
    raise AssertionError("the stream ended")


def _tick(n: int) -> Callable[[Event], bool]:
    return lambda event: event.type == TICK and getattr(event, "n", None) == n


# --- the daemon, errors, tokens ------------------------------------------------------------


def test_health_status_and_devices_are_typed(physicist: ec.Client) -> None:
    assert physicist.health().status == "ok"
    me = physicist.whoami()
    assert me.name == "physicist" and me.roles == ["operator", "physicist"]
    status = physicist.status()
    assert status.state in ("idle", "fault")
    assert {unit.id for unit in status.units} == {"left", "right"}
    assert status.tracking is not None and status.tracking.beam_hold is True
    devices = physicist.devices()
    assert {d.kind for d in devices} >= {"camera", "projector", "trigger"}
    camera = next(d for d in devices if d.kind == "camera")
    assert physicist.device(camera.id) == camera
    assert "eyeserver_" in physicist.metrics()


def test_settings_patients_jobs_and_the_simulated_room_are_typed(
        physicist: ec.Client, operator: ec.Client) -> None:
    camera = next(d for d in physicist.devices() if d.kind == "camera")
    before = camera.details["exposure_us"]
    changed = physicist.configure_device(camera.id, exposure_us=float(before) + 100.0)
    assert changed.details["exposure_us"] == float(before) + 100.0
    physicist.configure_device(camera.id, exposure_us=float(before))
    assert physicist.audit(limit=2)[0].action == "configure_device"

    physicist.put_patient("P-READ", eye="left", tolerance_gaze_deg=0.5)
    assert operator.patient("P-READ").tolerance_gaze_deg == 0.5
    model = physicist.add_eye_model("P-READ", globe_radius_mm=12.2, source="biometry")
    assert model.version == 1 and model.population is False
    assert operator.eye_models("P-READ") == [model] and operator.eye_model("P-READ", 1) == model
    with pytest.raises(ec.NotFound):
        operator.reference("P-READ", 1)
    assert isinstance(operator.jobs(), list)

    eye = physicist.set_sim_eye(position_mm=[0.5, 0.0, -10.0], still=True)
    assert eye.scene.kind == "eye" and eye.eye["centre_mm"][0] == pytest.approx(0.5)
    assert operator.sim_eye().scene.position_mm == (0.5, 0.0, -10.0)
    assert operator.sim_truth()["scene"]
    assert isinstance(operator.sim_prerender_status(), dict)


def test_errors_are_typed_and_carry_the_daemons_reason(
        base_url: str, physicist: ec.Client, operator: ec.Client) -> None:
    with pytest.raises(ec.NotFound) as missing:
        physicist.get_capture("cap-nope")
    assert missing.value.status == 404 and missing.value.reason == "no capture with id 'cap-nope'"
    assert missing.value.detail == missing.value.reason

    with pytest.raises(ec.Invalid) as invalid:  # the daemon's validation, with each problem
        physicist.put_patient("P-ERR", eye="right", tolerance_mm=-1.0)
    assert invalid.value.status == 422 and "tolerance_mm" in invalid.value.reason
    assert invalid.value.errors is not None
    assert invalid.value.errors[0]["loc"] == ["body", "tolerance_mm"]
    with pytest.raises(ec.Invalid, match="unknown unit 'nope'"):
        operator.capture("nope")

    with pytest.raises(ec.Conflict) as conflict:
        operator.stop_tracking()
    assert conflict.value.status == 409 and conflict.value.reason == "no live tracking is running"
    with pytest.raises(ec.Conflict, match="a preview shows the frames of a tracking session"):
        operator.tracking_preview("S1")

    with pytest.raises(ec.AuthError) as forbidden:  # a physicist's route, an operator's token
        operator.configure_device("P1", intensity=0.5)
    assert forbidden.value.status == 403 and "physicist" in forbidden.value.reason
    with ec.Client(base_url, token="wrong-token-0123456789") as stranger:
        with pytest.raises(ec.AuthError) as unknown:
            stranger.status()
        assert unknown.value.status == 401
        with pytest.raises(ec.AuthError, match="a valid token is needed"):
            next(iter(stranger.events()))  # the stream: closed with 1008 and the reason
        assert stranger.health().status == "ok"  # no token needed there

    with socket.socket() as unused:  # a port nobody listens on
        unused.bind(("127.0.0.1", 0))
        nowhere = f"http://127.0.0.1:{unused.getsockname()[1]}"
    with ec.Client(nowhere, token="x", retries=1) as lost, \
            pytest.raises(ec.ConnectionError, match="cannot reach the daemon"):
        lost.status()
    assert issubclass(ec.ConnectionError, ConnectionError)  # the built-in one too


@pytest.mark.slow
def test_a_failed_device_is_unavailable_with_its_reason(physicist: ec.Client) -> None:
    physicist.connect_sim_device("S1", False)
    try:
        with pytest.raises(ec.Unavailable) as failed:
            physicist.capture("left")
        assert failed.value.status == 503
        assert failed.value.reason == "S1: camera is not responding"
        assert failed.value.retry_after_s is not None and failed.value.retry_after_s >= 1
    finally:
        physicist.connect_sim_device("S1", True)
    deadline = time.monotonic() + 60.0
    while physicist.status().state != "idle":  # the daemon reopens it within a second or so
        assert time.monotonic() < deadline
        time.sleep(0.05)


def test_retries_only_what_is_safe_to_repeat() -> None:
    # The daemon sends no Retry-After and cannot be made to drop a request halfway: a
    # transport that answers as scripted shows the policy (the API has no idempotency key).
    def run(method: Callable[[ec.Client], object], script: list[Any]) -> tuple[int, object]:
        attempts = 0

        def answer(request: httpx.Request) -> httpx.Response:
            nonlocal attempts
            attempts += 1
            step = script[min(attempts, len(script)) - 1]
            if isinstance(step, Exception):
                raise step
            assert isinstance(step, httpx.Response)
            return step

        client = ec.Client("http://daemon.test", token="t", retries=2,
                           transport=httpx.MockTransport(answer))
        client.retry.backoff_s = 0.0
        try:
            result: object = method(client)
        except ec.EyeserverError as exc:
            result = exc
        finally:
            client.close()
        return attempts, result

    busy = httpx.Response(503, json={"detail": "the acquisition queue is full"},
                          headers={"Retry-After": "0"})
    status = httpx.Response(200, json={"status": "ok", "version": "9"})
    broken = httpx.ReadError("connection reset")
    refused = httpx.ConnectError("connection refused")
    created = httpx.Response(201, json={"id": "cap-1", "kind": "measurement", "unit": "all",
                                        "calibration_id": None, "created": "now",
                                        "frame_count": 2, "status": "ok"})
    # A read: repeated after a 503 that asks for it, and after a broken connection.
    attempts, result = run(lambda c: c.health(), [busy, broken, status])
    assert attempts == 3 and isinstance(result, HealthResponse)
    # A capture: never repeated once it may have reached the daemon...
    attempts, result = run(lambda c: c.capture(), [busy, created])
    assert attempts == 1 and isinstance(result, ec.Unavailable)
    assert result.reason == "the acquisition queue is full" and result.retry_after_s == 0.0
    attempts, result = run(lambda c: c.capture(), [broken, created])
    assert attempts == 1 and isinstance(result, ec.ConnectionError)
    # ... but repeated when the connection was never made.
    attempts, result = run(lambda c: c.capture(), [refused, created])
    assert attempts == 2 and isinstance(result, CaptureResponse)
    # Gives up after `retries`; an answer it cannot read is said to be one.
    attempts, result = run(lambda c: c.health(), [refused])
    assert attempts == 3 and isinstance(result, ec.ConnectionError)
    attempts, result = run(lambda c: c.health(), [httpx.Response(200, json={"status": 1})])
    assert isinstance(result, ec.UnexpectedResponseError) and "status" in str(result)


def test_the_token_comes_from_the_argument_the_environment_or_a_file(
        base_url: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    for name in ("EYESERVER_TOKEN", "EYESERVER_TOKEN_FILE", "EYESERVER_URL"):
        monkeypatch.delenv(name, raising=False)

    def role(**kwargs: Any) -> str | None:
        with ec.Client(base_url, **kwargs) as client:
            try:
                return client.whoami().role
            except ec.AuthError as exc:
                assert exc.status == 401
                return None

    token_file = tmp_path / "token"
    token_file.write_text(f"{PHYSICIST_TOKEN}\n")  # as `echo` writes it
    assert role() is None  # no token at all: 401
    monkeypatch.setenv("EYESERVER_TOKEN_FILE", str(token_file))
    assert role() == "physicist"
    monkeypatch.setenv("EYESERVER_TOKEN", OPERATOR_TOKEN)  # beats the file of the environment
    assert role() == "operator"
    assert role(token_file=token_file) == "physicist"  # arguments beat the environment
    assert role(token=OPERATOR_TOKEN, token_file=token_file) == "operator"
    monkeypatch.setenv("EYESERVER_URL", base_url + "/api/v1/")
    with ec.Client() as client:
        assert client.base_url == base_url + "/api/v1" and client.status().state
    (tmp_path / "empty").write_text("  \n")
    with pytest.raises(ec.EyeserverError, match="is empty"):
        ec.Client(base_url, token_file=tmp_path / "empty")


# --- streams -------------------------------------------------------------------------------


def test_the_event_stream_resumes_after_its_connection_is_cut_losing_and_repeating_nothing(
        app: FastAPI, relay: _Relay) -> None:
    bus = app.state.service.events
    seen: list[Message] = []
    with ec.Client(relay.url, token=OPERATOR_TOKEN) as client, \
            client.events(silence_s=STREAM_SILENCE_S) as stream:
        first = _until(stream, Hello, seen)
        for n in range(5):
            bus.publish(TICK, n=n)
        _until(stream, Event, seen, _tick(4))

        relay.cut()  # back at once: nothing went by
        lost = _until(stream, Disconnected, seen)
        assert isinstance(lost, Disconnected) and lost.last_seq == first.last_seq + 5
        resumed = _until(stream, Resumed, seen)
        assert resumed == Resumed(last_seq=first.last_seq + 5, missed=0)
        assert isinstance(next(stream), Hello)
        for n in range(5, 10):
            bus.publish(TICK, n=n)
        _until(stream, Event, seen, _tick(9))

        relay.cut()  # three events go by before it is back: the daemon sends them again
        _until(stream, Disconnected, seen)
        for n in range(10, 13):
            bus.publish(TICK, n=n)
        resumed = _until(stream, Resumed, seen)
        assert resumed.missed == 0 and resumed.restarted is False
        bus.publish(TICK, n=13)
        _until(stream, Event, seen, _tick(13))
        assert stream.last_seq == first.last_seq + 14

    seqs = _account(seen)
    start = first.last_seq
    assert seqs == [*range(start + 1, start + 15)]  # none lost, none twice
    ticks = [getattr(m, "n", None) for m in seen if isinstance(m, Event) and m.type == TICK]
    assert ticks == list(range(14))


def test_the_asyncio_event_stream_resumes_the_same_way(app: FastAPI, relay: _Relay) -> None:
    bus = app.state.service.events

    async def read() -> list[Message]:
        seen: list[Message] = []

        async def until(stream: ec.AsyncMessageStream, wanted: Callable[[Message], bool]
                        ) -> Message:
            async for message in stream:
                seen.append(message)
                if wanted(message):
                    return message
            raise AssertionError("the stream ended")

        async with ec.AsyncClient(relay.url, token=OPERATOR_TOKEN) as client:
            assert (await client.status()).state in ("idle", "fault")
            with pytest.raises(ec.NotFound, match="no capture with id 'cap-nope'"):
                await client.get_capture("cap-nope")
            async with client.events(silence_s=STREAM_SILENCE_S) as stream:
                await until(stream, lambda m: isinstance(m, Hello))
                bus.publish(TICK, n=0)
                await until(stream, lambda m: m.type == TICK)
                relay.cut()
                await until(stream, lambda m: isinstance(m, Disconnected))
                bus.publish(TICK, n=1)  # while away
                await until(stream, lambda m: isinstance(m, Hello))
                bus.publish(TICK, n=2)
                await until(stream, lambda m: getattr(m, "n", None) == 2)
        return seen

    seen = asyncio.run(read())
    seqs = _account(seen)
    resumed = [m for m in seen if isinstance(m, Resumed)]
    assert [r.missed for r in resumed] == [0]  # the event sent while away came again
    assert seqs == [seqs[0], seqs[0] + 1, seqs[0] + 2]


def test_a_restarted_daemon_is_told_apart_from_a_gap(tmp_path: Path) -> None:
    data_dir = tmp_path / "data"
    first_app = create_app(test_settings(data_dir))
    with live_server(first_app) as first_url:
        relay = _Relay(first_url)
        client = ec.Client(relay.url, token=OPERATOR_TOKEN)
        stream = client.events(silence_s=STREAM_SILENCE_S)
        stream.connect()
        hello = next(stream)
        assert isinstance(hello, Hello)
        first_app.state.service.events.publish(TICK, n=0)
        assert next(stream).type == TICK
    try:
        # The daemon stopped: it closed the stream itself (uvicorn: 1012, service restart).
        lost = next(stream)
        assert isinstance(lost, Disconnected) and "closed by the daemon: 1012" in lost.reason
        second_app = create_app(test_settings(data_dir))
        with live_server(second_app) as second_url:
            relay.upstream = second_url
            resumed = next(stream)
            assert isinstance(resumed, Resumed)
            assert resumed.restarted is True and resumed.missed is None
            assert resumed.last_seq == hello.last_seq + 1
            again = next(stream)
            assert isinstance(again, Hello) and again.last_seq < hello.last_seq + 1
    finally:
        stream.close()
        client.close()
        relay.close()


# --- the workflows -------------------------------------------------------------------------


@pytest.fixture
def qa_required(app: FastAPI, physicist: ec.Client) -> Iterator[None]:
    """The daily QA's lockout on, as in a treatment room (the module's daemon runs without
    it): verification and tracking answer 409 until a QA run passed. Runs take 2 frames, not
    the default 4, to keep the test short."""
    physicist.qa_status()  # the daemon makes its DailyQa on first use
    saved = app.state.qa
    assert isinstance(saved, DailyQa)
    settings = saved.settings.model_copy(update={"required": True, "frames": 2})
    app.state.qa = DailyQa(saved.service, settings, app.state.settings.data_dir)
    try:
        yield
    finally:
        app.state.qa = saved


@pytest.mark.slow
def test_the_ois_verifies_a_patients_position_through_the_client(
        physicist: ec.Client, operator: ec.Client, calibration_id: str, qa_required: None
        ) -> None:
    example = _load("examples/ois_verification.py")
    patient_id = "P-OIS?1#%"  # printable ASCII: ?, # and % must not cut the path
    physicist.set_sim_eye(position_mm=[0.0, 0.0, -10.0], gaze_deg=[0.0, 0.0], still=True)
    said: list[str] = []
    seen: list[Message] = []
    with operator.events(silence_s=STREAM_SILENCE_S) as events:
        example.prepare(physicist, patient_id, 1, eye="right", unit="left")
        # A calibration just activated: locked until a physicist's QA baseline.
        with pytest.raises(ec.Conflict, match="no QA baseline"):
            example.verify(operator, patient_id, 1)
        status = example.daily_qa(physicist, simulated=True, say=said.append)
        told_qa = _until(events, QaRunDone, seen)
        result = example.verify(operator, patient_id, 1)
        told = _until(events, PoseMeasured, seen)
    # Each event came as its own model (none fell back to the generic one): the daemon's
    # events and the client's messages agree.
    assert {type(m) for m in seen} >= {Hello, StateChanged, CaptureStored, ReconstructionDone,
                                       QaRunDone}
    assert [m.type for m in seen if type(m) in (Event, Message)] == []

    # The QA: the baseline run passed, nothing is locked, and the eye is back where it was.
    assert status.locked is False and status.baseline_run_id == status.last_pass
    assert isinstance(told_qa, QaRunDone) and told_qa.run_id == status.baseline_run_id
    assert told_qa.passed is True and told_qa.baseline is True
    assert any("(baseline): passed" in line for line in said), said
    assert physicist.sim_scene().kind == "eye"
    assert physicist.sim_eye().eye["centre_mm"] == pytest.approx([0.0, 0.0, -10.0])
    assert example.daily_qa(operator, simulated=True, say=said.append) == operator.qa_status()

    assert result.passed is True, result.reasons
    assert result.patient_id == patient_id and result.fraction == 1
    assert result.deviation.length_mm < 0.1 and result.deviation.gaze_deg < 0.5
    assert result.pose.confidence >= 0.5
    assert result.reference.source == "capture"
    assert result.evidence.calibration_id == calibration_id
    assert isinstance(told, PoseMeasured) and told.measurement_id == result.id
    assert told.passed is True
    # Found again by patient and fraction and by id; the reference is the captured one.
    listed = operator.measurements(patient_id, fraction=1)
    assert listed.total == 1 and listed.items[0].id == result.id
    assert operator.measurement(result.id) == result
    reference = operator.reference(patient_id, 1)
    assert reference.source == "capture" and reference.evidence is not None
    assert [r.version for r in operator.references(patient_id, 1)] == [reference.version]
    # The capture is the measurement's evidence: it is kept.
    with pytest.raises(ec.Conflict, match="evidence"):
        physicist.delete_capture(result.evidence.capture_id, reason="tidy up")


@pytest.mark.slow
def test_a_capture_is_reconstructed_listed_and_downloaded(
        physicist: ec.Client, operator: ec.Client, calibration_id: str) -> None:
    physicist.set_sim_scene({"kind": "pyramid"})
    capture = operator.capture("left")
    assert capture.calibration_id == calibration_id and capture.frame_count == 1
    surface = operator.reconstruct(capture.id, method="multi-view", min_quality=0.1)
    assert surface.points > 1000 and surface.options.method == "multi-view"
    assert operator.reconstruction(capture.id).points == surface.points
    assert operator.cloud_ply(capture.id).startswith(b"ply")
    assert operator.preview_png(capture.id).startswith(b"\x89PNG")
    camera = next(iter(surface.cameras))
    assert operator.capture_image(capture.id, 0, camera).startswith(b"\x89PNG")
    job = operator.wait_for_job(operator.reconstruct_captures([capture.id]).id, timeout_s=60.0)
    assert job.state == "succeeded" and job.result is not None
    assert [done["capture_id"] for done in job.result["done"]] == [capture.id]
    names = zipfile.ZipFile(io.BytesIO(operator.capture_bundle(capture.id))).namelist()
    assert f"{capture.id}/bundle.json" in names
    page = operator.captures(unit="left", since=capture.created, limit=5)
    assert [c.id for c in page.items] == [capture.id] and page.total == 1
    physicist.delete_capture(capture.id, reason="a test's capture")
    with pytest.raises(ec.NotFound):
        operator.get_capture(capture.id)


@pytest.mark.slow
def test_the_physicists_guided_calibration_through_the_client(
        physicist: ec.Client, calibration_id: str) -> None:
    example = _load("examples/guided_calibration.py")
    said: list[str] = []
    with physicist.events(silence_s=STREAM_SILENCE_S) as events:
        # The stereo session's guidance: a view answers coverage and what is missing.
        session = physicist.open_stereo_session()
        assert session.kind == "stereo" and session.state == "acquiring"
        assert physicist.status().state == "calibrating"
        with pytest.raises(ec.Conflict, match="calibrating"):
            physicist.capture("all")
        physicist.set_sim_chessboard(position_mm=[0.0, 0.0, 0.0], rotation_deg=[0.0, 0.0, 0.0])
        view = physicist.add_view(session.id)
        assert view.origin is True and all(view.found.values())
        assert view.ready is False and view.missing
        assert all(0 < camera.coverage < 1 for camera in view.cameras.values())
        told = _until(events, CalibrationSessionView)
        assert isinstance(told, CalibrationSessionView) and told.capture_id == view.capture_id
        with pytest.raises(ec.Conflict, match="is not ready to solve"):
            physicist.solve_calibration_session(session.id)
        closed = physicist.close_calibration_session(session.id)
        assert closed.state == "closed" and closed.views is not None and len(closed.views) == 1
        assert physicist.status().state in ("idle", "fault")

    # Phase to height on the active calibration's geometry: plates on the stage, the reference
    # plane, the solve as a job, the drift against the parent; nothing activated.
    made = example.run(physicist, parent_id=calibration_id, simulated=True, say=said.append)
    assert made.parent_id == calibration_id and made.session_id is not None
    assert made.active is False
    assert physicist.status().active_calibration_id == calibration_id
    assert any("height change" in line for line in said), said
    drift = physicist.compare_calibrations(calibration_id, made.id)
    assert drift.summary.max_rotation_deg < 1e-6  # the same geometry
    sessions = {s.id: s for s in physicist.calibration_sessions()}
    assert sessions[made.session_id].state == "done"
    assert sessions[made.session_id].calibration_id == made.id
    assert made.id in {c.id for c in physicist.calibrations()}
    assert physicist.download_calibration(made.id)[:2] == b"PK"


@pytest.fixture
def scripted_tracking(app: FastAPI, base_url: str, physicist: ec.Client, calibration_id: str
                      ) -> Iterator[Callable[[Sequence[object]], None]]:
    """Live tracking on the scripted source and fit; call it with the frames' poses."""
    control = app.state.tracking
    assert isinstance(control, TrackingControl)
    saved = (control.clock, control.deadline_s, control.finder_factory, control.source_factory)
    clock = ManualClock(1_000_000_000)
    pipeline = ScriptedPipeline(clock, reconstruct_s=0.012, fit_s=0.008)
    control.clock = clock
    control.deadline_s = 3600.0  # the manual clock does not move with real time
    control.finder_factory = lambda service, model: PoseFinder(pipeline.reconstruct,
                                                               pipeline.fit, model)

    def script(poses: Sequence[object]) -> None:
        control.source_factory = lambda service, units, c: ScriptedSource(c, list(poses),
                                                                          pace_s=0.02)

    # A planned reference is absolute: the MRI's ellipsoid, known to 0.05 mm, gives the
    # globe's shape.
    physicist.put_patient("P-TRACK", eye="right", unit="left", tolerance_mm=0.5)
    physicist.add_eye_model("P-TRACK", ellipsoid={"semi_axes_mm": [12.1, 11.9, 12.4]},
                            globe_sd_mm=0.05)
    physicist.set_reference("P-TRACK", 1, centre_mm=[0.0, 0.0, -10.0], gaze=[0.0, 0.0, 1.0])
    try:
        yield script
    finally:
        with contextlib.suppress(ec.Conflict):
            physicist.stop_tracking()
        control.clock, control.deadline_s, control.finder_factory, control.source_factory = saved


def _pose(x_mm: float = 0.0) -> EyePose:
    return EyePose(centre_mm=(x_mm, 0.0, -10.0), centre_sd_mm=(0.01, 0.01, 0.01),
                   globe_radius_mm=12.0, limbus_centre_mm=(x_mm, 0.0, 0.0), limbus_sd_mm=0.02,
                   gaze=(0.0, 0.0, 1.0), gaze_sd_deg=0.1, torsion_deg=None,
                   surface_mad_mm=0.05, sclera_points=1000, confidence=0.9,
                   gaze_source="limbus")


def test_tracking_streams_the_beam_hold_flag_through_the_client(
        operator: ec.Client, scripted_tracking: Callable[[Sequence[object]], None]) -> None:
    example = _load("examples/tracking_beam_hold.py")
    # Ten frames at the reference, five 1 mm off (tolerance 0.5 mm), then at the reference.
    scripted_tracking([_pose()] * 10 + [_pose(1.0)] * 5 + [_pose()] * 400)
    said: list[str] = []
    hold, final = example.track(operator, "P-TRACK", 1, seconds=60.0, say=said.append,
                                until=lambda hold, message: len(hold.changes) >= 3)

    # Held from the start, free after the dwell (3 good frames: frame 2), held on the first
    # frame out of tolerance (10) with the reason, free again 3 good frames after the last one
    # out (17). A frame the loaded machine dropped (the newest wins) only moves these later.
    (fall, free), (rise, held), (fall_again, free_again) = [
        (frame, flag) for frame, flag, _ in hold.changes]
    assert (free, held, free_again) == (False, True, False), hold.changes
    assert fall is not None and rise is not None and fall_again is not None
    assert 2 <= fall < 10 <= rise <= 14 and fall_again >= 17, hold.changes
    assert any("tolerance" in reason for reason in hold.changes[1][2]), hold.changes
    assert final.running is False and final.frames_processed >= 18
    assert final.frames_held >= 5
    assert operator.tracking().frames_processed == final.frames_processed


def test_the_pose_stream_resumes_after_a_cut_and_holds_the_beam_meanwhile(
        physicist: ec.Client, relay: _Relay,
        scripted_tracking: Callable[[Sequence[object]], None]) -> None:
    scripted_tracking([_pose()] * 2000)
    seen: list[Message] = []
    with ec.Client(relay.url, token=OPERATOR_TOKEN) as client, client.poses() as stream:
        physicist.start_tracking("P-TRACK", 1)
        for _ in range(5):
            _until(stream, PoseMessage, seen)
        relay.cut()
        lost = _until(stream, Disconnected, seen)
        assert isinstance(lost, Disconnected) and lost.beam_hold is True
        time.sleep(0.3)  # frames go by (≈ 50 a second)
        resumed = _until(stream, Resumed, seen)
        after = _until(stream, PoseMessage, seen)
        physicist.stop_tracking()

    assert resumed.missed is not None and resumed.missed > 0
    assert lost.last_seq is not None and resumed.last_seq == lost.last_seq
    assert after.seq == lost.last_seq + resumed.missed + 1
    seqs = _account(seen)
    assert len(seqs) == len(set(seqs)) >= 6
