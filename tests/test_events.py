"""The live event stream: the bus on its own, then ``/api/v1/ws/events`` over a real server.

The bus tests need no daemon. The stream tests run the app behind uvicorn on loopback
(:func:`tests.liveserver.live_server`) and read it with the ``websockets`` client, so flow control
and slow clients behave as in production. One server serves the module; rendering the simulated
room's first capture of a unit takes seconds. No test asserts on wall-clock time: timeouts are
generous and only keep a broken build from hanging.
"""

from __future__ import annotations

import asyncio
import json
import re
import socket
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import httpx
import pytest
from fastapi import FastAPI
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import ClientConnection, connect

from eyeserver.api import create_app
from eyeserver.hardware.sim.drivers import SimCamera
from eyeserver.service import events as events_module
from eyeserver.service.core import Service
from eyeserver.service.events import EventBus, SubscriptionClosedError, event_time
from tests.apiclient import API, OPERATOR_TOKEN, PHYSICIST_TOKEN, auth, test_settings
from tests.liveserver import live_server

TIMEOUT_S = 60.0  # only against hangs
QUEUE_SIZE = 64
TIME = re.compile(r"^\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z$")


# --- the bus ----------------------------------------------------------------------------------


def test_events_are_stamped_with_type_increasing_seq_and_utc_time() -> None:
    bus = EventBus()

    async def run() -> list[dict[str, Any]]:
        with bus.subscribe(8) as subscription:
            assert bus.publish("state", state="capturing", previous="idle") == 1
            assert bus.publish("capture.stored", capture_id="cap-1") == 2
            return [await subscription.get(), await subscription.get()]

    first, second = asyncio.run(run())

    assert first["type"] == "state" and first["seq"] == 1
    assert first["state"] == "capturing" and first["previous"] == "idle"
    assert second == {"type": "capture.stored", "seq": 2, "time": second["time"],
                      "capture_id": "cap-1"}
    assert TIME.match(first["time"]) and TIME.match(second["time"])
    assert json.loads(json.dumps(first)) == first
    assert bus.last_seq == 2


def test_event_time_is_utc_with_milliseconds() -> None:
    assert TIME.match(event_time())


def test_a_full_queue_drops_its_oldest_events_and_says_how_many() -> None:
    bus = EventBus()

    async def run() -> tuple[list[dict[str, Any]], int, int]:
        with bus.subscribe(3) as slow, bus.subscribe(100) as fast:
            for i in range(10):
                bus.publish("tick", i=i)
            received = [await slow.get() for _ in range(4)]
            assert slow.get_nowait() is None
            assert [(await fast.get())["i"] for _ in range(10)] == list(range(10))
            assert fast.dropped == 0
            return received, slow.dropped, bus.subscriber_count

    received, dropped, subscribers = asyncio.run(run())

    # The notice comes first: 7 events were lost before the three newest.
    assert received[0] == {"type": "dropped", "count": 7}
    assert [e["i"] for e in received[1:]] == [7, 8, 9]
    assert received[1]["seq"] - 0 - 1 == 7  # the gap in seq is the count
    assert dropped == 7
    assert bus.dropped_total == 7
    assert subscribers == 2
    assert bus.subscriber_count == 0  # both left with their context


def test_drops_are_reported_again_after_each_loss() -> None:
    bus = EventBus()

    async def run() -> list[dict[str, Any]]:
        with bus.subscribe(2) as subscription:
            for i in range(3):
                bus.publish("tick", i=i)
            first = [await subscription.get() for _ in range(3)]
            for i in range(3, 8):
                bus.publish("tick", i=i)
            return first + [await subscription.get() for _ in range(3)]

    messages = asyncio.run(run())

    assert [(m["type"], m.get("count", m.get("i"))) for m in messages] == [
        ("dropped", 1), ("tick", 1), ("tick", 2), ("dropped", 3), ("tick", 6), ("tick", 7)]
    assert bus.dropped_total == 4


def test_threads_publish_concurrently_and_every_subscriber_sees_seq_order() -> None:
    bus = EventBus()
    threads, per_thread = 4, 500

    def publisher(name: str) -> None:
        for i in range(per_thread):
            bus.publish("tick", thread=name, i=i)

    async def run() -> list[list[dict[str, Any]]]:
        with bus.subscribe(threads * per_thread) as one, bus.subscribe(threads * per_thread) as two:
            workers = [threading.Thread(target=publisher, args=(f"t{n}",)) for n in range(threads)]
            for worker in workers:
                worker.start()
            # Read while they publish: the loop is woken from the threads.
            received = [[await asyncio.wait_for(s.get(), TIMEOUT_S)
                         for _ in range(threads * per_thread)] for s in (one, two)]
            for worker in workers:
                worker.join(TIMEOUT_S)
            return received

    for events in asyncio.run(run()):
        assert [e["seq"] for e in events] == list(range(1, threads * per_thread + 1))
        for n in range(threads):
            assert [e["i"] for e in events if e["thread"] == f"t{n}"] == list(range(per_thread))
    assert bus.dropped_total == 0


def test_publishing_never_waits_for_a_subscriber_whose_loop_is_blocked() -> None:
    bus = EventBus()

    async def run() -> tuple[bool, list[dict[str, Any]]]:
        with bus.subscribe(5) as subscription:
            worker = threading.Thread(target=lambda: [bus.publish("tick", i=i)
                                                      for i in range(10_000)])
            worker.start()
            worker.join(TIMEOUT_S)  # blocks this loop: nobody reads while the thread publishes
            finished = not worker.is_alive()
            return finished, [await subscription.get() for _ in range(6)]

    finished, received = asyncio.run(run())

    assert finished
    assert received[0] == {"type": "dropped", "count": 9_995}
    assert [e["i"] for e in received[1:]] == list(range(9_995, 10_000))


def test_closing_a_subscription_unsubscribes_and_wakes_its_reader() -> None:
    bus = EventBus()

    async def run() -> None:
        subscription = bus.subscribe(4)
        waiting = asyncio.create_task(subscription.get())
        await asyncio.sleep(0)
        threading.Thread(target=subscription.close).start()  # from another thread, as on exit
        with pytest.raises(SubscriptionClosedError):
            await asyncio.wait_for(waiting, TIMEOUT_S)
        assert bus.subscriber_count == 0
        bus.publish("tick")  # nobody to deliver to
        subscription.close()  # idempotent

    asyncio.run(run())
    assert bus.dropped_total == 0


def test_a_subscription_whose_loop_has_closed_is_forgotten() -> None:
    bus = EventBus()

    async def subscribe() -> None:
        bus.subscribe(1)

    asyncio.run(subscribe())  # the loop closes with the subscription still open
    bus.publish("tick")

    assert bus.subscriber_count == 0


def test_bad_arguments_are_rejected() -> None:
    bus = EventBus()
    with pytest.raises(ValueError, match="maxsize"):
        asyncio.run(_subscribe(bus, 0))
    with pytest.raises(ValueError, match="seq"):
        bus.publish("tick", seq=3)
    with pytest.raises(RuntimeError):
        bus.subscribe(1)  # no running loop


async def _subscribe(bus: EventBus, maxsize: int) -> None:
    bus.subscribe(maxsize).close()


# --- the stream over a real server ------------------------------------------------------------


@pytest.fixture(scope="module")
def app(tmp_path_factory: pytest.TempPathFactory) -> FastAPI:
    data_dir = tmp_path_factory.mktemp("events") / "data"
    # The silent client of the slow-client test reads again only after the others have had
    # everything: it must not be taken for one that stopped reading meanwhile.
    return create_app(test_settings(data_dir, event_queue_size=QUEUE_SIZE, ws_stall_s=30.0))


@pytest.fixture(scope="module")
def base_url(app: FastAPI) -> Iterator[str]:
    with live_server(app) as url:
        yield url


@pytest.fixture
def service(app: FastAPI, base_url: str) -> Service:
    running = app.state.service
    assert isinstance(running, Service)
    return running


def _ws_url(base_url: str, query: str = "") -> str:
    return base_url.replace("http://", "ws://", 1) + f"{API}/ws/events" + query


def _connect(base_url: str, token: str | None = OPERATOR_TOKEN, *, header: bool = False,
             **kwargs: Any) -> ClientConnection:
    query = "" if token is None or header else f"?token={token}"
    headers = auth(token) if header and token is not None else None
    return connect(_ws_url(base_url, query), additional_headers=headers, compression=None,
                   open_timeout=TIMEOUT_S, close_timeout=5, ping_interval=None, **kwargs)


def _recv(ws: ClientConnection) -> dict[str, Any]:
    message: dict[str, Any] = json.loads(ws.recv(timeout=TIMEOUT_S))
    return message


def _read_until(ws: ClientConnection,
                last: Callable[[dict[str, Any]], bool]) -> list[dict[str, Any]]:
    messages = [_recv(ws)]
    while not last(messages[-1]):
        messages.append(_recv(ws))
    return messages


def _capture(base_url: str, unit: str) -> httpx.Response:
    return httpx.post(f"{base_url}{API}/captures", json={"unit": unit},
                      headers=auth(OPERATOR_TOKEN), timeout=TIMEOUT_S)


def test_a_reconnecting_subscriber_gets_the_kept_events_after_its_seq_again(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(events_module, "HISTORY_EVENTS", 5)
    bus = EventBus()
    for i in range(8):
        bus.publish("tick", i=i)  # seq 1..8; the bus keeps 4..8

    async def replayed(after: int | None, maxsize: int = 100) -> tuple[int, list[Any]]:
        with bus.subscribe(maxsize, after) as subscription:
            got = []
            while (event := subscription.get_nowait()) is not None:
                got.append(event.get("i", event))
            return subscription.start_seq, got

    assert asyncio.run(replayed(6)) == (6, [6, 7])  # seq 7 and 8 again
    assert asyncio.run(replayed(8)) == (8, [])  # nothing went by
    # Older than what is kept: from the oldest kept on, the start says what is lost (1..3).
    assert asyncio.run(replayed(0)) == (3, [3, 4, 5, 6, 7])
    assert asyncio.run(replayed(50)) == (8, [])  # a seq of an earlier run of the daemon
    assert asyncio.run(replayed(None)) == (8, [])
    # More than the queue holds: its oldest are dropped and said so, as live events are.
    assert asyncio.run(replayed(0, maxsize=2)) == (3, [{"type": "dropped", "count": 3}, 6, 7])
    with pytest.raises(ValueError, match="after"):
        asyncio.run(replayed(-1))


def _summary(events: list[dict[str, Any]]) -> list[tuple[str, ...]]:
    return [(e["type"], e["state"], e["previous"]) if e["type"] == "state"
            else (e["type"], e.get("device_id") or e.get("capture_id") or "") for e in events]


def test_hello_describes_the_daemon_then_a_capture_streams_in_order(
    base_url: str, service: Service
) -> None:
    with _connect(base_url) as ws:
        hello = _recv(ws)
        response = _capture(base_url, "left")
        events = _read_until(ws, lambda e: e["type"] == "state" and e["state"] == "idle")

    assert hello["type"] == "hello"
    assert TIME.match(hello["time"])
    assert hello["state"] == "idle"
    assert hello["units"] == [{"id": "left", "health": "ok", "reason": None},
                              {"id": "right", "health": "ok", "reason": None}]
    assert hello["active_calibration_id"] is None
    assert hello["queue_size"] == QUEUE_SIZE
    assert response.status_code == 201, response.text
    capture_id = response.json()["id"]
    assert _summary(events) == [("state", "capturing", "idle"),
                                ("capture.stored", capture_id),
                                ("state", "idle", "capturing")]
    assert events[1]["unit"] == "left" and events[1]["calibration_id"] is None
    assert [e["seq"] for e in events] == list(range(hello["last_seq"] + 1,
                                                    hello["last_seq"] + 4))
    assert all(TIME.match(e["time"]) for e in events)


def test_a_client_back_with_after_gets_what_went_by_after_its_hello(
    base_url: str, service: Service
) -> None:
    with _connect(base_url) as ws:
        last = _recv(ws)["last_seq"]
        service.events.publish("test.tick", n=0)
        had = _recv(ws)["seq"]
    for n in (1, 2):  # while it is away
        service.events.publish("test.tick", n=n)
    query = f"?token={OPERATOR_TOKEN}&after={had}"
    with connect(_ws_url(base_url, query), compression=None, open_timeout=TIMEOUT_S,
                 close_timeout=5, ping_interval=None) as ws:
        hello = _recv(ws)
        again = [_recv(ws), _recv(ws)]

    assert had == last + 1
    assert hello["type"] == "hello" and hello["last_seq"] == had
    assert [(e["type"], e["seq"], e["n"]) for e in again] == [("test.tick", had + 1, 1),
                                                             ("test.tick", had + 2, 2)]


@pytest.mark.slow
def test_a_device_fault_and_its_recovery_are_streamed(base_url: str, service: Service) -> None:
    camera = service.rig.camera("S3")
    assert isinstance(camera, SimCamera)
    with _connect(base_url, header=True) as ws:
        _recv(ws)  # hello
        camera.inject_fault("disconnect")
        failed = _capture(base_url, "right")
        faulted = _read_until(ws, lambda e: e["type"] == "state" and e["state"] == "fault")
        # Captures refused while it lasts are not new faults (issue 35's bench counted one
        # event per refusal).
        refused = [_capture(base_url, "right") for _ in range(3)]
        camera.reconnect()
        recovered = _capture(base_url, "right")
        back = _read_until(ws, lambda e: e["type"] == "state" and e["state"] == "idle")

    assert failed.status_code == 503
    assert [r.status_code for r in refused] == [503] * 3
    assert _summary(faulted) == [("state", "capturing", "idle"), ("device.fault", "S3"),
                                 ("state", "fault", "capturing")]
    assert faulted[1]["unit"] == "right"
    assert faulted[1]["reason"] == "camera is not responding"
    assert recovered.status_code == 201
    # The capture reopens S3, unless a background retry of the daemon got there first; no
    # refusal or failed retry before the replug is told as a fault again.
    steps = _summary(back)
    assert ("device.fault", "S3") not in steps
    stored = steps.index(("capture.stored", recovered.json()["id"]))
    assert ("device.recovered", "S3") in steps[:stored]
    assert [step[:2] for step in steps[:stored] if step[0] == "state"][-1] == ("state",
                                                                             "capturing")
    assert steps[stored + 1:] == [("state", "idle", "capturing")]


@pytest.mark.parametrize("token", [OPERATOR_TOKEN, PHYSICIST_TOKEN])
@pytest.mark.parametrize("header", [False, True], ids=["query", "bearer"])
def test_a_valid_token_is_accepted_either_way(base_url: str, token: str, header: bool) -> None:
    with _connect(base_url, token, header=header) as ws:
        assert _recv(ws)["type"] == "hello"


_REFUSED = [
    pytest.param("", [], id="no-token"),
    pytest.param("?token=wrong-token-0123456789", [], id="query-wrong"),
    pytest.param("?token=", [], id="query-empty"),
    pytest.param("", [(b"authorization", b"Bearer wrong-token-0123456789")], id="bearer-wrong"),
    pytest.param("", [(b"authorization", f"Basic {OPERATOR_TOKEN}".encode())], id="not-bearer"),
]


@pytest.mark.parametrize(("query", "headers"), _REFUSED)
def test_a_missing_or_wrong_token_closes_the_socket_with_1008(
    base_url: str, query: str, headers: list[tuple[bytes, bytes]]
) -> None:
    extra = [(k.decode(), v.decode()) for k, v in headers]
    with (connect(_ws_url(base_url, query), additional_headers=extra,
                  open_timeout=TIMEOUT_S) as ws,
          pytest.raises(ConnectionClosed) as closed):
        ws.recv(timeout=TIMEOUT_S)

    assert closed.value.rcvd is not None
    assert closed.value.rcvd.code == 1008
    assert closed.value.rcvd.reason == ("a valid token is needed (?token= or Authorization: "
                                        "Bearer)")


@pytest.mark.slow
def test_a_client_that_never_reads_delays_no_one_and_loses_its_oldest_events(
    base_url: str, service: Service
) -> None:
    readers, published, batch = 19, 2000, QUEUE_SIZE // 2
    # 12 MB in all: more than the socket buffers between the server and the silent client can
    # hold (Linux lets a loopback send buffer grow to 4 MB), so its queue must overflow.
    padding = "x" * 6000
    bus = service.events
    dropped_before = bus.dropped_total

    # The silent client reads nothing (not even its hello) until every other client has
    # everything.
    stack = ExitStack()  # websockets wants its connections used as context managers
    silent = _silent_client(base_url, stack)

    progress: list[int] = [0] * readers  # the last seq each reader has seen
    received: list[list[dict[str, Any]]] = [[] for _ in range(readers)]
    seen = threading.Condition()
    target = 0  # the seq the publisher waits for
    errors: list[BaseException] = []

    def read(index: int, ws: ClientConnection) -> None:
        try:
            _recv(ws)  # hello
            while True:
                message = _recv(ws)
                received[index].append(message)
                with seen:
                    progress[index] = message.get("seq", progress[index])
                    if progress[index] >= target:
                        seen.notify_all()
                if message["type"] == "test.end":
                    return
        except BaseException as exc:  # reported by the test thread
            errors.append(exc)
            with seen:
                seen.notify_all()

    clients = [stack.enter_context(_connect(base_url)) for _ in range(readers)]
    threads = [threading.Thread(target=read, args=(n, ws)) for n, ws in enumerate(clients)]
    for thread in threads:
        thread.start()
    capture: dict[str, httpx.Response] = {}
    capturing = threading.Thread(target=lambda: capture.update(response=_capture(base_url,
                                                                                 "left")))
    try:
        first = bus.last_seq + 1
        for start in range(0, published, batch):
            for i in range(start, min(start + batch, published)):
                last = bus.publish("test.load", i=i, padding=padding)
            if start >= published // 2 and not capturing.is_alive() and not capture:
                capturing.start()  # a real capture in the middle of the load
            # Pace the load by the readers, so their own queues never overflow: a reader
            # that were held up by the silent client would make this wait time out.
            with seen:
                target = last
                assert seen.wait_for(lambda last=last: errors or min(progress) >= last,
                                     TIMEOUT_S), \
                    f"readers stuck at {min(progress)} of {last}"
            assert not errors, errors
        capturing.join(TIMEOUT_S)
        end = bus.publish("test.end")
        for thread in threads:
            thread.join(TIMEOUT_S)
        assert not errors, errors
        silent_dropped = bus.dropped_total - dropped_before

        # Now the silent client reads: the oldest events are gone, the newest are there.
        hello = _recv(silent)
        late = _read_until(silent, lambda e: e["type"] == "test.end")
    finally:
        stack.close()

    assert capture["response"].status_code == 201, capture["response"].text
    for messages in received:
        assert [e["seq"] for e in messages] == list(range(first, end + 1))  # nothing lost
        assert [e["i"] for e in messages if e["type"] == "test.load"] == list(range(published))
        ours = [e for e in messages if e["type"] in ("state", "capture.stored")]
        assert _summary(ours) == [("state", "capturing", "idle"),
                                  ("capture.stored", capture["response"].json()["id"]),
                                  ("state", "idle", "capturing")]
    assert silent_dropped > 0
    notices = [e["count"] for e in late if e["type"] == "dropped"]
    assert sum(notices) == silent_dropped
    # Each notice stands exactly in its gap of seq; the silent client ends with the newest.
    previous = hello["last_seq"]
    missing = 0
    for message in late:
        if message["type"] == "dropped":
            missing = message["count"]
            continue
        assert message["seq"] == previous + 1 + missing
        previous, missing = message["seq"], 0
    assert late[-1]["seq"] == end
    assert [e["type"] for e in late[-QUEUE_SIZE // 2:]].count("dropped") == 0


def _silent_client(base_url: str, stack: ExitStack) -> ClientConnection:
    """A client with a small receive buffer and queue that reads nothing until told."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    # Before connecting: the window is agreed in the handshake (shrinking it later stalls TCP).
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.connect(("127.0.0.1", int(base_url.rsplit(":", 1)[1])))
    return stack.enter_context(_connect(base_url, sock=sock, max_queue=1))


def test_a_client_that_stops_reading_gets_a_last_notice_then_4008(tmp_path: Path) -> None:
    stall_s = 0.5
    app = create_app(test_settings(tmp_path / "data", event_queue_size=QUEUE_SIZE,
                                   ws_stall_s=stall_s))
    padding = "x" * 6000  # a few hundred events fill the loopback socket's buffers
    with live_server(app) as url, ExitStack() as stack:
        bus = app.state.service.events
        silent = _silent_client(url, stack)
        assert bus.subscriber_count == 1
        dropped_before = bus.dropped_total
        # Publish until the daemon lets the client go (it stays subscribed while it accepts).
        deadline = time.monotonic() + TIMEOUT_S
        while bus.subscriber_count and time.monotonic() < deadline:
            for i in range(32):
                bus.publish("test.load", i=i, padding=padding)
            time.sleep(0.01)
        assert bus.subscriber_count == 0, "the daemon kept a client that read nothing"
        last_offered = bus.last_seq
        dropped = bus.dropped_total - dropped_before
        # Now it reads: what it was sent, the last notice, the close.
        received: list[dict[str, Any]] = []
        with pytest.raises(ConnectionClosed) as closed:
            while True:
                received.append(_recv(silent))

    assert closed.value.rcvd is not None
    assert closed.value.rcvd.code == 4008
    assert closed.value.rcvd.reason == "too slow: accepted nothing for 0.5 s"
    hello, events, last = received[0], received[1:-1], received[-1]
    assert hello["type"] == "hello"
    assert last["type"] == "dropped" and last["count"] > 0
    notices = [e["count"] for e in events if e["type"] == "dropped"] + [last["count"]]
    # Every event it was offered either reached it or is counted in a notice, and the bus
    # counted as dropped exactly what the notices say.
    delivered = [e["seq"] for e in events if e["type"] != "dropped"]
    assert delivered == sorted(delivered) and len(set(delivered)) == len(delivered)
    assert delivered[0] == hello["last_seq"] + 1
    assert len(delivered) + sum(notices) == delivered[-1] - hello["last_seq"] + last["count"]
    assert delivered[-1] + last["count"] <= last_offered
    assert sum(notices) == dropped


def test_the_stream_unsubscribes_when_its_clients_leave(base_url: str, service: Service) -> None:
    def settle(count: int) -> int:
        deadline = time.monotonic() + TIMEOUT_S
        while service.events.subscriber_count != count and time.monotonic() < deadline:
            time.sleep(0.02)
        return service.events.subscriber_count

    assert settle(0) == 0  # the clients of the other tests have gone
    with _connect(base_url) as ws, _connect(base_url, header=True) as other:
        _recv(ws)
        _recv(other)
        assert service.events.subscriber_count == 2
    assert settle(0) == 0


def test_settings_reject_an_empty_event_queue(tmp_path: Path) -> None:
    from eyeserver.errors import ConfigError

    with pytest.raises(ConfigError, match="event_queue_size"):
        test_settings(tmp_path, event_queue_size=0)
