"""`eyeserver serve` as a real process: it starts, answers the health check and stops."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

pytestmark = pytest.mark.slow  # every test here takes over a second

STARTUP_DEADLINE_S = 30.0
SHUTDOWN_TIMEOUT_S = 10.0


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port: int = probe.getsockname()[1]
        return port


def _eyeserver_command() -> list[str]:
    # The installed console script, as a user runs it; `python -m eyeserver` if it is missing.
    script = Path(sys.executable).with_name("eyeserver")
    return [str(script)] if script.exists() else [sys.executable, "-m", "eyeserver"]


def _wait_until_healthy(process: subprocess.Popen[bytes], url: str, log: Path) -> httpx.Response:
    deadline = time.monotonic() + STARTUP_DEADLINE_S
    while time.monotonic() < deadline:
        if process.poll() is not None:
            pytest.fail(
                f"eyeserver serve exited with {process.returncode} before answering:\n"
                + log.read_text(errors="replace")
            )
        try:
            response = httpx.get(url, timeout=1.0)
        except httpx.TransportError:
            time.sleep(0.1)
            continue
        if response.status_code == 200:
            return response
        time.sleep(0.1)
    pytest.fail(
        f"no 200 from {url} within {STARTUP_DEADLINE_S} s:\n" + log.read_text(errors="replace")
    )


def test_serve_answers_health_and_stops(tmp_path: Path) -> None:
    port = _free_port()
    data_dir = tmp_path / "data"
    log = tmp_path / "serve.log"
    environment = {
        name: value
        for name, value in os.environ.items()
        if not name.upper().startswith("EYESERVER_")
    }
    environment["EYESERVER_DATA_DIR"] = str(data_dir)
    command = [*_eyeserver_command(), "serve", "--host", "127.0.0.1", "--port", str(port)]

    with log.open("wb") as log_stream:
        process = subprocess.Popen(
            command,
            stdin=subprocess.DEVNULL,
            stdout=log_stream,
            stderr=subprocess.STDOUT,
            env=environment,
            cwd=tmp_path,
        )
        try:
            response = _wait_until_healthy(process, f"http://127.0.0.1:{port}/api/v1/health", log)
            assert response.json()["status"] == "ok"
            # The browser's way to a stream puts the token in the query: never in the log.
            httpx.get(f"http://127.0.0.1:{port}/api/v1/status?token=never-logged-7f3a",
                      timeout=30)
            assert data_dir.is_dir()
        finally:
            if process.poll() is None:
                process.send_signal(signal.SIGTERM)
            try:
                process.wait(timeout=SHUTDOWN_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()

    # uvicorn shuts down gracefully on SIGTERM, then lets the signal end the process.
    assert process.returncode in (0, -signal.SIGTERM), log.read_text(errors="replace")
    lines = [line for line in log.read_text().splitlines() if line.strip()]
    records = [json.loads(line) for line in lines]  # every line is one JSON object
    messages = [record["message"] for record in records]
    assert "eyeserver starting" in messages
    assert "eyeserver stopped" in messages
    assert "never-logged-7f3a" not in log.read_text()
    assert any("token=[redacted]" in str(record.get("path")) for record in records)
