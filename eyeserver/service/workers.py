"""The daemon's own threads: bounded job queues and the background retry of failed devices.

::

    request threads ──submit──► [ bounded queue ] ──► one worker thread ──► result / error
                     (full: QueueFullError, HTTP 503)

A :class:`BoundedWorker` runs jobs one at a time, in the order they were submitted, on a thread
of its own. The acquisition worker owns the hardware (captures, device settings, reopening failed
devices), so two jobs never drive it at once; the reconstruction worker owns the pipeline (its
cached camera models are not thread-safe). A job waits its turn, so a triggered capture is never
dropped; only when the queue is full is a new job refused, at once, with :class:`QueueFullError`.

:class:`RetryLoop` retries something that failed (the devices in fault) in the background with
exponential back-off, ``1, 2, 4, … 30, 30 …`` seconds, starting again at 1 s once it succeeds. Its
wait is injectable so that tests step it by hand instead of sleeping.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any, Protocol, TypeVar

from eyeserver.errors import EyeserverError, StateConflictError

__all__ = [
    "FIRST_RETRY_DELAY_S",
    "MAX_RETRY_DELAY_S",
    "BoundedWorker",
    "QueueFullError",
    "RetryLoop",
    "RetryWait",
    "backoff_delays",
    "wait_on_event",
]

_log = logging.getLogger(__name__)

_T = TypeVar("_T")

FIRST_RETRY_DELAY_S = 1.0
"""The wait before the first retry of a failed device, seconds."""

MAX_RETRY_DELAY_S = 30.0
"""The longest wait between two retries, seconds: a device that comes back is used again
within half a minute, and a dead one costs one reopen attempt every 30 s."""


class QueueFullError(EyeserverError):
    """A worker's queue is full; the job was refused and nothing was done (HTTP 503)."""

    def __init__(self, queue_name: str, capacity: int) -> None:
        self.queue_name = queue_name
        self.capacity = capacity
        super().__init__(f"the {queue_name} queue is full ({capacity} jobs waiting); "
                         "try again later")


@dataclass
class _Job:
    function: Callable[[], Any]
    future: Future[Any]


class BoundedWorker:
    """One thread that runs submitted jobs in order, with at most ``capacity`` of them waiting.

    Parameters
    ----------
    name : str
        What the queue serves (``"acquisition"``), for messages, logs and the thread's name.
    capacity : int
        Jobs that may wait while one runs; one more is refused with :class:`QueueFullError`.

    Notes
    -----
    :meth:`start` starts the thread; :meth:`stop` lets the jobs already queued finish, refuses
    new ones and joins the thread. A job submitted from the worker's own thread (a job that
    needs another job's work) runs at once, in place, instead of waiting behind itself.
    """

    def __init__(self, name: str, capacity: int) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be at least 1, not {capacity}")
        self.name = name
        self.capacity = int(capacity)
        self._jobs: queue.Queue[_Job | None] = queue.Queue()
        self._lock = threading.Lock()
        self._waiting = 0
        self._accepting = False
        self._thread: threading.Thread | None = None

    @property
    def waiting(self) -> int:
        """Jobs submitted and not started yet."""
        with self._lock:
            return self._waiting

    def start(self) -> None:
        """Start the worker thread. Idempotent."""
        with self._lock:
            if self._thread is not None:
                return
            self._accepting = True
            self._thread = threading.Thread(target=self._run, name=f"eyeserver-{self.name}",
                                            daemon=True)
            self._thread.start()

    def stop(self, timeout_s: float | None = None) -> None:
        """Refuse new jobs, finish the queued ones and join the thread. Idempotent."""
        with self._lock:
            thread, self._thread = self._thread, None
            if thread is None:
                return
            self._accepting = False
            # Not counted in _waiting: the sentinel always fits behind the queued jobs.
            self._jobs.put(None)
        if thread is not threading.current_thread():
            thread.join(timeout_s)

    def on_worker_thread(self) -> bool:
        """Whether the caller is this worker's own thread."""
        thread = self._thread
        return thread is not None and thread is threading.current_thread()

    def submit(self, function: Callable[[], _T]) -> Future[_T]:
        """Queue ``function`` and return the future of its result.

        Raises
        ------
        QueueFullError
            ``capacity`` jobs are already waiting.
        StateConflictError
            The worker is not running (the daemon is starting or shutting down).
        """
        future: Future[_T] = Future()
        if self.on_worker_thread():
            _run_into(function, future)
            return future
        with self._lock:
            if not self._accepting:
                raise StateConflictError(f"the {self.name} worker is not running")
            if self._waiting >= self.capacity:
                raise QueueFullError(self.name, self.capacity)
            self._waiting += 1
            self._jobs.put(_Job(function, future))
        return future

    def call(self, function: Callable[[], _T]) -> _T:
        """Queue ``function``, wait for its turn and its end, and return its result.

        The job's own exception is raised here. Waiting is not cancellable: a job that was
        accepted runs to its end even if nobody waits for it any more.

        Raises
        ------
        QueueFullError, StateConflictError
            As for :meth:`submit`.
        """
        return self.submit(function).result()

    def _run(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            with self._lock:
                self._waiting -= 1
            if job.future.set_running_or_notify_cancel():
                _run_into(job.function, job.future)


def _run_into(function: Callable[[], _T], future: Future[_T]) -> None:
    try:
        result = function()
    except BaseException as exc:  # the caller re-raises it from Future.result()
        future.set_exception(exc)
    else:
        future.set_result(result)


def backoff_delays(first_s: float = FIRST_RETRY_DELAY_S,
                   max_s: float = MAX_RETRY_DELAY_S) -> Iterator[float]:
    """The waits between retries: ``first_s`` doubling up to ``max_s``, then ``max_s`` forever.

    >>> from itertools import islice
    >>> list(islice(backoff_delays(), 8))
    [1.0, 2.0, 4.0, 8.0, 16.0, 30.0, 30.0, 30.0]
    """
    if not 0 < first_s <= max_s:
        raise ValueError(f"need 0 < first_s <= max_s, not {first_s} and {max_s}")
    delay = float(first_s)
    while True:
        yield delay
        delay = min(delay * 2, float(max_s))


class RetryWait(Protocol):
    """How :class:`RetryLoop` waits: ``delay_s`` seconds, or less once ``stop`` is set.

    Returns whether ``stop`` is set. Tests pass one they step by hand.
    """

    def __call__(self, delay_s: float, stop: threading.Event) -> bool: ...


def wait_on_event(delay_s: float, stop: threading.Event) -> bool:
    """The real :class:`RetryWait`: sleep on ``stop`` for ``delay_s`` seconds."""
    return stop.wait(delay_s)


class RetryLoop:
    """A daemon thread that calls ``attempt`` while ``pending()``, backing off between calls.

    Parameters
    ----------
    name : str
        For the thread's name and the logs.
    pending : callable
        Whether there is something to retry (a device in fault). Cheap; called often.
    attempt : callable
        One retry; returns True when nothing is left to retry. An exception counts as a failure.
    wait : RetryWait
        Sleeps between the attempts (:func:`wait_on_event` unless a test steps it).
    first_delay_s, max_delay_s : float
        The back-off schedule (:func:`backoff_delays`).

    Notes
    -----
    The thread sleeps without a time-out while nothing is pending; :meth:`poke` wakes it when
    something fails. Every failed attempt doubles the next wait up to ``max_delay_s``; success,
    or finding nothing pending (someone else fixed it), starts the schedule again.
    """

    def __init__(self, name: str, *, pending: Callable[[], bool], attempt: Callable[[], bool],
                 wait: RetryWait = wait_on_event, first_delay_s: float = FIRST_RETRY_DELAY_S,
                 max_delay_s: float = MAX_RETRY_DELAY_S) -> None:
        backoff_delays(first_delay_s, max_delay_s).__next__()  # validates the schedule
        self.name = name
        self._pending = pending
        self._attempt = attempt
        self._wait = wait
        self._first_delay_s = first_delay_s
        self._max_delay_s = max_delay_s
        self._wake = threading.Condition()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._due_at: float | None = None  # the latest attempt's time.monotonic(); None idle

    def next_attempt_in_s(self) -> float:
        """Seconds until the next attempt: 0 when it is due or running, the schedule's first
        wait while the loop is idle (what something failing now waits)."""
        due = self._due_at
        return self._first_delay_s if due is None else max(0.0, due - time.monotonic())

    def start(self) -> None:
        """Start the thread. Idempotent."""
        with self._wake:
            if self._thread is not None:
                return
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name=f"eyeserver-{self.name}",
                                            daemon=True)
            self._thread.start()

    def stop(self, timeout_s: float | None = None) -> None:
        """Stop the thread (an attempt in progress finishes first) and join it. Idempotent."""
        with self._wake:
            thread, self._thread = self._thread, None
            self._stop.set()
            self._wake.notify_all()
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout_s)

    def poke(self) -> None:
        """Something may have become pending: look again."""
        with self._wake:
            self._wake.notify_all()

    def _run(self) -> None:
        delays = backoff_delays(self._first_delay_s, self._max_delay_s)
        while not self._stop.is_set():
            with self._wake:
                if not self._pending():
                    delays = backoff_delays(self._first_delay_s, self._max_delay_s)
                    self._due_at = None
                    while not self._stop.is_set() and not self._pending():
                        self._wake.wait()
            delay = next(delays)
            self._due_at = time.monotonic() + delay
            if self._stop.is_set() or self._wait(delay, self._stop):
                return
            try:
                done = self._attempt()
            except Exception:
                _log.exception("retry attempt failed", extra={"loop": self.name})
                done = False
            if done:
                delays = backoff_delays(self._first_delay_s, self._max_delay_s)
