"""``eyeserver serve`` as a child process on loopback, for the benches and the tests.

A real process measures what a client of the daemon sees (HTTP stack, threads, another
interpreter), and it can be killed with SIGKILL to check that nothing acknowledged is lost.

::

    with DaemonProcess(data_dir, log=work / "serve.log") as daemon:
        daemon.client.get("/api/v1/status")     # httpx.Client with the physicist's token
"""

from __future__ import annotations

import io
import os
import secrets
import signal
import socket
import ssl
import subprocess
import sys
import time
import zipfile
from pathlib import Path
from types import TracebackType
from typing import IO, Any

import httpx

from eyeserver.errors import EyeserverError

__all__ = ["API", "DaemonError", "DaemonProcess", "checked", "free_port", "zip_directory"]

API = "/api/v1"
"""The versioned API's prefix."""

STARTUP_S = 60.0
"""How long the daemon may take to answer its health check (it opens and renders the room)."""


class DaemonError(EyeserverError):
    """The daemon process did not start or stop as expected; the message quotes its log."""


def checked(response: httpx.Response, what: str) -> Any:
    """The JSON body of a successful answer (None when it has none).

    Raises
    ------
    DaemonError
        The answer was not a success; the message names ``what``, the status and the start of
        the body.
    """
    if response.status_code >= 300:
        raise DaemonError(f"{what}: HTTP {response.status_code}: {response.text[:300]}")
    return response.json() if response.content else None


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port: int = probe.getsockname()[1]
        return port


def zip_directory(directory: Path) -> bytes:
    """The files directly in ``directory`` as a zip (a calibration to upload)."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
        for path in sorted(directory.iterdir()):
            if path.is_file():
                archive.write(path, path.name)
    return buffer.getvalue()


class DaemonProcess:
    """``eyeserver serve`` on 127.0.0.1 with its own data directory and tokens.

    Parameters
    ----------
    data_dir : Path
        The daemon's ``EYESERVER_DATA_DIR`` (kept across restarts of this object).
    log : Path
        File that receives the daemon's stdout and stderr (JSON log lines), appended.
    env : dict, optional
        Further ``EYESERVER_*`` settings (and other variables, such as ``NOTIFY_SOCKET``). The
        caller's own ``EYESERVER_*`` variables are not passed on.
    tls : ssl.SSLContext, optional
        For a daemon configured for HTTPS (``EYESERVER_TLS_*`` in ``env``): the client context
        (trusted CA, client certificate) of the health check and of :attr:`client`.

    Notes
    -----
    :meth:`start` (or ``with``) launches the process and waits for ``/api/v1/health``;
    :attr:`client` then talks to it with the physicist's token, :attr:`operator_token` and
    :attr:`physicist_token` are the two tokens it accepts. :meth:`kill` is SIGKILL, :meth:`stop`
    SIGTERM (a graceful shut-down). :meth:`start` may be called again after either. The daily
    QA's lockout is off (``EYESERVER_QA__REQUIRED=false``) unless ``env`` sets it.
    """

    def __init__(self, data_dir: Path, *, log: Path, env: dict[str, str] | None = None,
                 tls: ssl.SSLContext | None = None) -> None:
        self.data_dir = data_dir
        self.log = log
        self.operator_token = secrets.token_urlsafe(24)
        self.physicist_token = secrets.token_urlsafe(24)
        self._env = dict(env or {})
        self._tls = tls
        self._process: subprocess.Popen[bytes] | None = None
        self._client: httpx.Client | None = None
        self._log_stream: IO[bytes] | None = None
        self.url = ""

    @property
    def client(self) -> httpx.Client:
        """An HTTP client of the running daemon, with the physicist's token."""
        if self._client is None:
            raise DaemonError("the daemon is not running")
        return self._client

    @property
    def pid(self) -> int:
        """The daemon's process id."""
        if self._process is None:
            raise DaemonError("the daemon is not running")
        return self._process.pid

    def start(self) -> DaemonProcess:
        """Launch the daemon and wait until it answers its health check.

        Raises
        ------
        DaemonError
            It exited or did not answer within :data:`STARTUP_S`; the message holds its log.
        """
        port = free_port()
        # Nor systemd's variables: a daemon under test must not notify the tests' own manager.
        env = {k: v for k, v in os.environ.items() if not k.upper().startswith("EYESERVER_")
               and k not in ("NOTIFY_SOCKET", "WATCHDOG_USEC", "WATCHDOG_PID")}
        # The daily QA's lockout off unless ``env`` says otherwise: the benches and the tests
        # that start a daemon measure accuracy, speed and recovery, not the morning routine
        # (tests/test_qa.py does, with it on; docs/qa.md).
        env.update({"EYESERVER_DATA_DIR": str(self.data_dir),
                    "EYESERVER_TOKENS": f"operator:{self.operator_token},"
                                        f"physicist:{self.physicist_token}",
                    "EYESERVER_QA__REQUIRED": "false",
                    **self._env})
        self._log_stream = self.log.open("ab")
        self._process = subprocess.Popen(
            [sys.executable, "-m", "eyeserver", "serve", "--host", "127.0.0.1",
             "--port", str(port)],
            stdin=subprocess.DEVNULL, stdout=self._log_stream, stderr=subprocess.STDOUT, env=env)
        self.url = f"{'http' if self._tls is None else 'https'}://127.0.0.1:{port}"
        verify: ssl.SSLContext | bool = True if self._tls is None else self._tls
        deadline = time.monotonic() + STARTUP_S
        while time.monotonic() < deadline:
            if self._process.poll() is not None:
                self._reap()
                raise DaemonError(f"eyeserver serve exited with {self._process.returncode} "
                                  f"before answering:\n{self._log_text()}")
            try:
                if httpx.get(f"{self.url}/api/v1/health", timeout=1.0,
                             verify=verify).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            time.sleep(0.1)
        else:
            self.kill()
            raise DaemonError(f"eyeserver serve did not answer within {STARTUP_S:.0f} s:\n"
                              f"{self._log_text()}")
        self._client = httpx.Client(
            base_url=self.url, timeout=120.0, verify=verify,
            headers={"Authorization": f"Bearer {self.physicist_token}"})
        return self

    def kill(self) -> None:
        """SIGKILL: the daemon dies at once, as on a crash or power loss."""
        if self._process is not None and self._process.poll() is None:
            self._process.kill()
        self._reap()

    def stop(self, timeout_s: float = 20.0) -> int:
        """SIGTERM and wait (SIGKILL after ``timeout_s``); the exit status.

        Our client's idle connections are closed first, as a client that is done does: over
        TLS the daemon closes an idle connection with a close_notify and waits for the
        answer, which a pooled connection nobody reads never gives, so the daemon stopped
        only when its grace period ran out (``SHUTDOWN_GRACE_S``, 10 s; 0.2 s closed first).
        """
        if self._client is not None:
            self._client.close()
        if self._process is not None and self._process.poll() is None:
            self._process.send_signal(signal.SIGTERM)
            try:
                self._process.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self._process.kill()
        code = self._reap()
        return code

    def _reap(self) -> int:
        code = 0
        if self._process is not None:
            code = self._process.wait()
        if self._client is not None:
            self._client.close()
            self._client = None
        if self._log_stream is not None:
            self._log_stream.close()
            self._log_stream = None
        return code

    def _log_text(self) -> str:
        return self.log.read_text(errors="replace")[-4000:] if self.log.exists() else ""

    def __enter__(self) -> DaemonProcess:
        return self.start()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 traceback: TracebackType | None) -> None:
        self.stop()
