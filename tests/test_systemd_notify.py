"""systemd notifications: READY=1, WATCHDOG=1 while healthy, STOPPING=1, over NOTIFY_SOCKET —
by hand against a datagram socket of the test, and from a real ``eyeserver serve``."""

from __future__ import annotations

import os
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from eyeserver.bench.daemon import DaemonProcess
from eyeserver.service.systemd import (
    Heartbeat,
    notify,
    notify_socket_address,
    watchdog_interval_s,
)
from eyeserver.service.workers import BoundedWorker


class Listener:
    """A systemd manager's notification socket, as far as the daemon can tell."""

    def __init__(self, address: str) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(address)
        self.sock.settimeout(0.2)

    def receive(self, until: str, timeout_s: float = 30.0) -> list[str]:
        """Messages received until one contains the line ``until`` (or the time-out)."""
        messages: list[str] = []
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                messages.append(self.sock.recv(4096).decode())
            except TimeoutError:
                continue
            if until in messages[-1].splitlines():
                return messages
        pytest.fail(f"no {until} within {timeout_s} s; got {messages}")

    def close(self) -> None:
        self.sock.close()


@pytest.fixture
def listener(tmp_path: Path) -> Iterator[tuple[str, Listener]]:
    path = str(tmp_path / "notify.sock")
    receiver = Listener(path)
    yield path, receiver
    receiver.close()


def test_notify_sends_one_datagram_to_a_path_socket(listener: tuple[str, Listener]) -> None:
    path, receiver = listener
    assert notify("READY=1", {"NOTIFY_SOCKET": path})
    assert receiver.receive("READY=1") == ["READY=1"]


def test_notify_supports_abstract_sockets() -> None:
    name = f"eyeserver-test-{os.getpid()}-{time.monotonic_ns()}"
    receiver = Listener("\0" + name)
    try:
        assert notify_socket_address({"NOTIFY_SOCKET": "@" + name}) == "\0" + name
        assert notify("WATCHDOG=1", {"NOTIFY_SOCKET": "@" + name})
        assert receiver.receive("WATCHDOG=1") == ["WATCHDOG=1"]
    finally:
        receiver.close()


def test_without_a_socket_nothing_is_sent_and_nothing_fails(tmp_path: Path) -> None:
    assert not notify("READY=1", {})
    assert not notify("READY=1", {"NOTIFY_SOCKET": "vsock:2:1234"})  # not supported
    assert not notify("READY=1", {"NOTIFY_SOCKET": str(tmp_path / "gone.sock")})


def test_watchdog_interval_is_half_the_period_for_this_process_only() -> None:
    assert watchdog_interval_s({}) is None
    assert watchdog_interval_s({"WATCHDOG_USEC": "30000000"}) == 15.0
    assert watchdog_interval_s({"WATCHDOG_USEC": "30000000",
                                "WATCHDOG_PID": str(os.getpid())}) == 15.0
    assert watchdog_interval_s({"WATCHDOG_USEC": "30000000", "WATCHDOG_PID": "1"}) is None
    assert watchdog_interval_s({"WATCHDOG_USEC": "soon"}) is None


def test_heartbeat_stops_while_a_job_holds_the_worker() -> None:
    worker = BoundedWorker("acquisition", 2)
    heartbeat = Heartbeat(worker)
    assert not heartbeat.beat()  # not running yet
    worker.start()
    release = threading.Event()
    try:
        assert heartbeat.beat()
        time.sleep(0.05)  # the heartbeat job runs
        assert heartbeat.beat()
        time.sleep(0.05)
        worker.submit(release.wait)  # a hardware call that hangs
        assert heartbeat.beat()  # the previous heartbeat had run; a new one queues behind
        time.sleep(0.05)
        assert not heartbeat.beat()  # stuck for a whole interval: systemd will restart us
        release.set()
        time.sleep(0.05)
        assert heartbeat.beat()
    finally:
        release.set()
        worker.stop()


@pytest.mark.slow
def test_a_real_daemon_notifies_ready_watchdog_and_stopping(
        listener: tuple[str, Listener], tmp_path: Path) -> None:
    path, receiver = listener
    daemon = DaemonProcess(tmp_path / "data", log=tmp_path / "serve.log",
                           env={"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "400000"})
    with daemon:
        started = receiver.receive("READY=1")
        assert not any("WATCHDOG=1" in m for m in started)  # not before it is ready
        pings = receiver.receive("WATCHDOG=1", timeout_s=5.0)
        pings += receiver.receive("WATCHDOG=1", timeout_s=5.0)
        assert daemon.client.get("/api/v1/status").status_code == 200
    stopping = receiver.receive("STOPPING=1", timeout_s=5.0)
    assert "STOPPING=1" in stopping[-1].splitlines()
    assert all(m == "WATCHDOG=1" for m in pings)
