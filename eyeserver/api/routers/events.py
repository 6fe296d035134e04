"""``/api/v1/ws/events``: the daemon's live event stream (a WebSocket of JSON text messages).

Authenticate with ``?token=<token>`` or ``Authorization: Bearer <token>`` (any role); without a
valid token the socket is closed with 1008 (policy violation) and the reason, before any
message. The first message describes the daemon as it is; every later one is an event of the
service's :class:`~eyeserver.service.events.EventBus`, in the order it happened. Messages the
client sends are ignored.

Every event carries ``type``, ``seq`` (increasing by one per event of the daemon) and ``time``
(UTC, ISO 8601 with milliseconds, e.g. ``2024-05-06T07:08:09.123Z``), plus:

========================  ==================================================================
``type``                  fields
========================  ==================================================================
``hello`` (first, only)   ``state``, ``units`` (``id``, ``health``, ``reason``),
                          ``active_calibration_id``, ``version``, ``queue_size``,
                          ``last_seq`` (the ``seq`` of the event before the stream's first);
                          ``hello`` has ``time`` but no ``seq``
``state``                 ``state`` (idle, capturing, calibrating, tracking, fault),
                          ``previous``
``device.fault``          ``device_id``, ``unit`` (null for the trigger), ``reason``
``device.recovered``      ``device_id``
``capture.stored``        ``capture_id``, ``unit``, ``calibration_id`` (or null)
``reconstruction.done``   ``capture_id``, ``calibration_id``, ``points``
``calibration.imported``  ``calibration_id``, ``actor``
``calibration.activated`` ``calibration_id``, ``actor``
``dropped``               ``count``: events lost right here (no ``seq``, see below)
========================  ==================================================================

A client that reads too slowly never holds the daemon or the other clients up: the daemon keeps
at most ``event_queue_size`` events for it (setting, default 256) and drops the *oldest* when
more arrive. Before the next event after such a loss it sends ``{"type": "dropped", "count":
n}``; the ``seq`` of that next event has moved on by ``n + 1``. A client whose socket accepts
nothing for ``ws_stall_s`` (default 10 s: it stopped reading) gets a last such notice, counting
every event it will never get, and the close code 4008 with the reason; it finds them after what
it was already sent. A client that needs the whole picture again reads ``GET /api/v1/status``.

A client that reconnects gives ``?after=<seq>``, the last ``seq`` it had: the daemon then sends,
after the ``hello``, the events since then that it still keeps (its newest
:data:`~eyeserver.service.events.HISTORY_EVENTS`), and the ``hello``'s ``last_seq`` says where
they start (``after`` itself, or later when older ones are gone: the difference was lost). An
``after`` beyond the daemon's latest event (from an earlier run) replays nothing.
"""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, WebSocket
from starlette.concurrency import run_in_threadpool

import eyeserver
from eyeserver.api.streaming import opened, stream
from eyeserver.config import Settings
from eyeserver.service.core import Service
from eyeserver.service.events import event_time

__all__ = ["router"]

router = APIRouter(tags=["events"])

@router.websocket("/ws/events", name="events")
async def stream_events(websocket: WebSocket, after: int | None = None) -> None:
    """Send a ``hello`` snapshot, then (``?after=seq``) the kept events after that ``seq``,
    then every event of the daemon until the client leaves."""
    found = await opened(websocket, "service", Service)
    if found is None:
        return
    service, settings = found
    # Subscribe before the snapshot: an event between the two is sent (again), never missed.
    with service.events.subscribe(settings.event_queue_size,
                                  None if after is None else max(after, 0)) as subscription:
        await websocket.accept()
        hello = await run_in_threadpool(_hello, service, settings, subscription.start_seq)
        await stream(websocket, subscription, first=[hello], stall_s=settings.ws_stall_s)


def _hello(service: Service, settings: Settings, last_seq: int) -> dict[str, Any]:
    # Devices describe themselves and the store answers from SQLite: a worker thread's job.
    status = service.status()
    return {
        "type": "hello",
        "time": event_time(),
        "state": status.state,
        "units": [{"id": u.id, "health": u.health, "reason": u.reason} for u in status.units],
        "active_calibration_id": status.active_calibration_id,
        "version": eyeserver.__version__,
        "queue_size": settings.event_queue_size,
        "last_seq": last_seq,
    }
