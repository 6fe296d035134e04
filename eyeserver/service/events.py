"""The daemon's event bus: what happened, for the live stream (``/api/v1/ws/events``).

::

    worker threads ── publish() ──► EventBus ──► Subscription (bounded deque) ──► get() on a loop
                                           └───► Subscription (bounded deque) ──► get() on a loop

:meth:`EventBus.publish` is called from any thread (the service's workers, the event loop) and
never waits for a subscriber: it stamps the event (``type``, ``seq``, ``time``) and appends it
to every subscription's bounded queue. A full queue drops its *oldest* event, so a slow client
loses history, never the present, and never slows the daemon or the other clients down. The
subscriber's event loop is woken with :meth:`asyncio.AbstractEventLoop.call_soon_threadsafe`,
at most once per wake-up, so a starved loop never accumulates more than one callback per
subscription either.

A client that reconnects may ask for what it missed (:meth:`EventBus.subscribe`'s ``after``):
the bus keeps its newest :data:`HISTORY_EVENTS` events and queues those after ``after`` first.

How drops are reported: :meth:`Subscription.get` returns, before the next event after a loss, a
notice ``{"type": "dropped", "count": n}``: ``n`` events were lost right there (the ``seq`` of
the next event minus that of the last one received, minus one). The notice has no ``seq`` of
its own. The subscriber's cumulative count is :attr:`Subscription.dropped`; the bus keeps the
total over all subscribers (:attr:`EventBus.dropped_total`) and the number of subscribers for
metrics.
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
from collections import deque
from datetime import UTC, datetime
from typing import Any

__all__ = ["HISTORY_EVENTS", "Event", "EventBus", "Subscription", "SubscriptionClosedError",
           "event_time"]

HISTORY_EVENTS = 1024
"""The newest events the bus keeps for a client that reconnects (:meth:`EventBus.subscribe`'s
``after``): minutes of a busy daemon's events, a few hundred kB."""

Event = dict[str, Any]
"""One event: ``{"type": str, "seq": int, "time": str, **data}``, JSON-able."""


_RESERVED = frozenset({"type", "seq", "time"})


class SubscriptionClosedError(Exception):
    """:meth:`Subscription.get` on a subscription that was closed."""


def event_time(moment: datetime | None = None) -> str:
    """``moment`` (default: now) as UTC ISO 8601 with milliseconds and ``Z``.

    >>> event_time(datetime(2024, 5, 6, 7, 8, 9, 123456, tzinfo=UTC))
    '2024-05-06T07:08:09.123Z'
    """
    moment = datetime.now(UTC) if moment is None else moment.astimezone(UTC)
    return moment.isoformat(timespec="milliseconds").removesuffix("+00:00") + "Z"


class Subscription:
    """One subscriber's bounded queue of events, read on the event loop it was made on.

    Made by :meth:`EventBus.subscribe`; use it as a context manager (or call :meth:`close`) so
    the bus forgets it.
    """

    def __init__(self, bus: EventBus, loop: asyncio.AbstractEventLoop, maxsize: int) -> None:
        self._bus = bus
        self._loop = loop
        self.maxsize = maxsize
        self._lock = threading.Lock()
        self._queue: deque[Event] = deque()
        self._dropped = 0
        self._unreported = 0  # dropped since the last notice
        self._wake_pending = False
        self._closed = False
        self._ready = asyncio.Event()  # set on the loop only
        self.start_seq = 0
        """The ``seq`` of the last event before this subscription; it gets every later one."""

    @property
    def dropped(self) -> int:
        """Events this subscriber lost to a full queue, in all."""
        with self._lock:
            return self._dropped

    @property
    def pending(self) -> int:
        """Events queued and not yet read."""
        with self._lock:
            return len(self._queue)

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` was called."""
        return self._closed

    def _offer(self, event: Event) -> int:
        """Queue ``event`` (any thread, under the bus lock); returns how many were dropped."""
        with self._lock:
            if self._closed:
                return 0
            dropped = 0
            if len(self._queue) >= self.maxsize:
                self._queue.popleft()
                dropped = 1
                self._dropped += 1
                self._unreported += 1
            self._queue.append(event)
            wake = not self._wake_pending
            self._wake_pending = True
        if wake:
            try:
                self._loop.call_soon_threadsafe(self._wake)
            except RuntimeError:  # the loop is closed: nobody will ever read this
                with self._lock:
                    self._closed = True
                    self._queue.clear()
        return dropped

    def _wake(self) -> None:
        # On the loop. Anything offered before this point is in the queue; anything offered
        # after it schedules another wake-up.
        with self._lock:
            self._wake_pending = False
        self._ready.set()

    async def get(self) -> Event:
        """The next event, or a ``{"type": "dropped", "count": n}`` notice before it.

        Call on the subscription's own event loop.

        Raises
        ------
        SubscriptionClosedError
            The subscription was closed (also while waiting).
        """
        while True:
            with self._lock:
                if self._closed:
                    raise SubscriptionClosedError("the event subscription is closed")
                if self._unreported:
                    count, self._unreported = self._unreported, 0
                    return {"type": "dropped", "count": count}
                if self._queue:
                    return self._queue.popleft()
                self._ready.clear()
            await self._ready.wait()

    def get_nowait(self) -> Event | None:
        """The next event or drop notice if one is queued, else None (any thread)."""
        with self._lock:
            if self._unreported:
                count, self._unreported = self._unreported, 0
                return {"type": "dropped", "count": count}
            return self._queue.popleft() if self._queue else None

    def abandon(self, unsent: int = 0, untold: int = 0) -> int:
        """:meth:`close` for a client that is cut off: the events still queued, and ``unsent``
        more read from it but not delivered, count as dropped. Returns every event the client
        will never hear of: those, the drops not yet reported and ``untold`` (the count of a
        drop notice read but not delivered). 0 once closed."""
        with self._lock:
            if self._closed:
                return 0
            dropped = len(self._queue) + unsent
            lost = dropped + self._unreported + untold
            self._dropped += dropped
            self._unreported = 0
            # Closed in the same breath: an event offered after this count would be dropped by
            # the bus's count but told to no one (seen under load: 30 of 1,541).
            self._closed = True
            self._queue.clear()
        self._bus._count_dropped(dropped)
        self._leave()
        return lost

    def close(self) -> None:
        """Leave the bus and wake a waiting :meth:`get` (which then raises). Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._queue.clear()
        self._leave()

    def _leave(self) -> None:
        """Forget this closed subscription on the bus and wake a waiting :meth:`get`."""
        self._bus._forget(self)
        with contextlib.suppress(RuntimeError):  # a closed loop: nothing waits on it
            self._loop.call_soon_threadsafe(self._ready.set)

    def __enter__(self) -> Subscription:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


class EventBus:
    """Fans events out from any thread to the subscriptions of event loops.

    Notes
    -----
    One lock orders the whole fan-out, so every subscriber sees events in ``seq`` order even when
    several threads publish at once. It is held only to append to the queues, never while
    waiting for a reader.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._seq = 0
        self._subscriptions: list[Subscription] = []
        self._dropped_total = 0
        self._history: deque[Event] = deque(maxlen=HISTORY_EVENTS)

    @property
    def last_seq(self) -> int:
        """The ``seq`` of the latest event published (0 before the first)."""
        with self._lock:
            return self._seq

    @property
    def subscriber_count(self) -> int:
        """Open subscriptions."""
        with self._lock:
            return len(self._subscriptions)

    @property
    def dropped_total(self) -> int:
        """Events lost to full queues, summed over every subscriber there ever was."""
        with self._lock:
            return self._dropped_total

    def publish(self, type: str, **data: Any) -> int:
        """Stamp an event and queue it for every subscriber; never blocks on one.

        Parameters
        ----------
        type : str
            The event type, e.g. ``"state"`` or ``"capture.stored"``.
        **data
            JSON-able fields of the event (``type``, ``seq`` and ``time`` are reserved).

        Returns
        -------
        int
            The event's ``seq`` (1 for the first event of the bus, increasing by one).

        Raises
        ------
        ValueError
            ``data`` names a field the bus sets itself.
        """
        reserved = _RESERVED.intersection(data)
        if reserved:
            raise ValueError(f"event fields {sorted(reserved)} are set by the bus")
        with self._lock:
            self._seq += 1
            event: Event = {"type": type, "seq": self._seq, "time": event_time(), **data}
            self._history.append(event)
            for subscription in self._subscriptions:
                self._dropped_total += subscription._offer(event)
            # A subscription whose loop has gone is forgotten here (its close() cannot run
            # under this lock).
            self._subscriptions = [s for s in self._subscriptions if not s.closed]
            return self._seq

    def subscribe(self, maxsize: int = 256, after: int | None = None) -> Subscription:
        """A new subscription, read on the running event loop, holding at most ``maxsize``.

        ``after``: the ``seq`` of the last event a reconnecting client had; the events since
        then that the bus still keeps (:data:`HISTORY_EVENTS`) are queued first, so a client
        that was away misses none it can be given again (its :attr:`Subscription.start_seq`
        says where they begin: ``after``, or later when the oldest are gone). An ``after``
        beyond the latest event (a client of an earlier run of the daemon) replays nothing.

        Raises
        ------
        ValueError
            ``maxsize`` is below 1, or ``after`` is negative.
        RuntimeError
            No event loop is running in this thread.
        """
        if maxsize < 1:
            raise ValueError(f"maxsize must be at least 1, got {maxsize}")
        if after is not None and after < 0:
            raise ValueError(f"after must be a seq (0 or more), got {after}")
        subscription = Subscription(self, asyncio.get_running_loop(), maxsize)
        with self._lock:
            subscription.start_seq = self._seq
            if after is not None and after < self._seq:
                again = [event for event in self._history if event["seq"] > after]
                if again:
                    subscription.start_seq = int(again[0]["seq"]) - 1
                for event in again:
                    self._dropped_total += subscription._offer(event)
            self._subscriptions.append(subscription)
        return subscription

    def _count_dropped(self, count: int) -> None:
        with self._lock:
            self._dropped_total += count

    def _forget(self, subscription: Subscription) -> None:
        with self._lock:
            if subscription in self._subscriptions:
                self._subscriptions.remove(subscription)
