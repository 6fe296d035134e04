"""systemd's notification protocol (``sd_notify``), by hand: one datagram per message.

Under ``Type=notify`` systemd passes the path of a datagram socket in ``NOTIFY_SOCKET`` (a file
path, or ``@name`` for a socket in the abstract namespace) and, with ``WatchdogSec=``, the
watchdog period in ``WATCHDOG_USEC`` (with ``WATCHDOG_PID``, the process it is meant for). The
daemon sends ``READY=1`` once it is serving, ``WATCHDOG=1`` every half period while it is
healthy and ``STOPPING=1`` when it shuts down (see :mod:`eyeserver.service.operations`). Without
``NOTIFY_SOCKET`` (not under systemd) every call is a cheap no-op.

What "healthy" means for the watchdog (:class:`Heartbeat`): the event loop runs (the pings are
sent from it, so a blocked loop stops them) and the acquisition worker finishes jobs (a
heartbeat job put in its queue at one ping has run by the next). A hardware call that never
returns therefore gets the daemon restarted after ``WatchdogSec``. A device in *fault* does not
stop the pings: the daemon already retries it and recovers by itself, and a restart would not
bring an unplugged camera back, only interrupt everything else.

Reference: ``sd_notify(3)`` and ``systemd.service(5)``; the protocol is stable and documented
for implementations without libsystemd.
"""

from __future__ import annotations

import logging
import os
import socket
from collections.abc import Mapping
from concurrent.futures import Future

from eyeserver.service.workers import BoundedWorker, QueueFullError

__all__ = ["Heartbeat", "notify", "notify_socket_address", "watchdog_interval_s"]

_log = logging.getLogger(__name__)


def notify_socket_address(environ: Mapping[str, str] | None = None) -> str | None:
    """The address in ``NOTIFY_SOCKET`` as :mod:`socket` wants it (``@`` becomes the abstract
    namespace's leading NUL), or None when unset or of a kind not supported (``vsock:``)."""
    value = (os.environ if environ is None else environ).get("NOTIFY_SOCKET", "")
    if value.startswith("@"):
        return "\0" + value[1:]
    if value.startswith("/"):
        return value
    return None


def notify(message: str, environ: Mapping[str, str] | None = None) -> bool:
    """Send ``message`` (``"READY=1"``, newline-separated assignments) to systemd.

    Returns whether it was sent; False without ``NOTIFY_SOCKET`` or when the socket refuses
    (logged: the daemon keeps running either way).
    """
    address = notify_socket_address(environ)
    if address is None:
        return False
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as sock:
            sock.connect(address)
            sock.sendall(message.encode("utf-8"))
    except OSError as exc:
        _log.warning("systemd notification failed", extra={
            "notify_message": message, "reason": str(exc)})
        return False
    return True


def watchdog_interval_s(environ: Mapping[str, str] | None = None) -> float | None:
    """Seconds between two ``WATCHDOG=1``: half of ``WATCHDOG_USEC``, as ``sd_notify(3)``
    advises; None when no watchdog is asked for, or it is meant for another process."""
    env = os.environ if environ is None else environ
    try:
        usec = int(env.get("WATCHDOG_USEC", ""))
    except ValueError:
        return None
    pid = env.get("WATCHDOG_PID")
    if usec <= 0 or (pid and pid.strip() != str(os.getpid())):
        return None
    return usec / 2 / 1e6


class Heartbeat:
    """Whether a worker still finishes jobs: the watchdog's health check.

    Each :meth:`beat` checks that the heartbeat job queued by the previous one has run, then
    queues a new one. The job does nothing, so it only measures whether the worker gets to it.
    """

    def __init__(self, worker: BoundedWorker) -> None:
        self._worker = worker
        self._pending: Future[None] | None = None

    def beat(self) -> bool:
        """True when the worker is alive and moving; call it once per watchdog interval."""
        if self._pending is not None and not self._pending.done():
            return False  # one job has held the worker for a whole interval
        try:
            self._pending = self._worker.submit(_nothing)
        except QueueFullError:
            self._pending = None  # busy with queued captures, but it finished our last job
        except Exception:  # not running: starting or stopping
            return False
        return True


def _nothing() -> None:
    return None
