"""What the daemon does for its operators while it serves: systemd notifications, the watchdog
and the retention rule, as one async context around the time the API is up.

::

    async with operations(service, settings):    # READY=1; watchdog and retention tasks start
        ...                                      # serving
    # on leaving: STOPPING=1, the tasks are cancelled (before the service closes)

Both tasks run on the event loop: the watchdog's pings stop if the loop blocks (see
:mod:`eyeserver.service.systemd` for what else stops them); the retention rule runs its deletions
on a worker thread.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator, Callable
from datetime import datetime

from eyeserver.config import Settings
from eyeserver.service.core import Service
from eyeserver.service.retention import RETENTION_INTERVAL_S, purge_expired
from eyeserver.service.systemd import Heartbeat, notify, watchdog_interval_s

__all__ = ["operations", "retention_loop", "watchdog_loop"]

_log = logging.getLogger(__name__)


async def watchdog_loop(interval_s: float, healthy: Callable[[], bool],
                        send: Callable[[str], bool] = notify) -> None:
    """Send ``WATCHDOG=1`` every ``interval_s`` while ``healthy()``; runs until cancelled."""
    was_healthy = True
    while True:
        is_healthy = healthy()
        if is_healthy:
            send("WATCHDOG=1")
        if is_healthy != was_healthy:
            (_log.info if is_healthy else _log.error)(
                "watchdog pings resumed" if is_healthy else
                "watchdog pings withheld: the acquisition worker is stuck")
            was_healthy = is_healthy
        await asyncio.sleep(interval_s)


async def retention_loop(service: Service, retention_days: float,
                         interval_s: float = RETENTION_INTERVAL_S,
                         clock: Callable[[], datetime] | None = None) -> None:
    """Apply the retention rule now and then every ``interval_s``; runs until cancelled."""
    while True:
        try:
            await asyncio.to_thread(purge_expired, service, retention_days, clock)
        except Exception:  # a bad run must not end the rule for good
            _log.exception("retention run failed")
        await asyncio.sleep(interval_s)


@contextlib.asynccontextmanager
async def operations(service: Service, settings: Settings) -> AsyncIterator[None]:
    """Tell systemd the daemon is ready, keep its watchdog fed and apply the retention rule
    while the block runs; tell it the daemon is stopping on leaving. ``service`` must be open.
    """
    tasks: list[asyncio.Task[None]] = []
    interval_s = watchdog_interval_s()
    if interval_s is not None:
        heartbeat = Heartbeat(service.acquisition_worker)
        tasks.append(asyncio.create_task(watchdog_loop(interval_s, heartbeat.beat),
                                         name="eyeserver-watchdog"))
    if settings.retention_days is not None:
        tasks.append(asyncio.create_task(retention_loop(service, settings.retention_days),
                                         name="eyeserver-retention"))
    notify("READY=1\nSTATUS=serving")
    try:
        yield
    finally:
        notify("STOPPING=1\nSTATUS=shutting down")
        for task in tasks:
            task.cancel()
        for task in tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await task
