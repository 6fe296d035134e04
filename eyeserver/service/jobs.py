"""Long operations as jobs: queued, run on a thread of their own, watched and cancelled by id.

::

    submit() ──► queued ──► running ──► succeeded (result)
                   │           ├──────► failed (error: the reason)
                   └───────────┴──────► cancelled

A job is a function of a :class:`JobContext`: it reports how far it got with
:meth:`JobContext.progress` (published on the service's event bus as ``job.progress`` and kept in
its record) and calls :meth:`JobContext.check_cancelled` between steps, which raises
:class:`JobCancelled` once someone asked to cancel it. Cancelling is cooperative: a job stops at
its next check, never in the middle of a step, so whatever it finished (a stored reconstruction,
a stored calibration) is complete. A queued job that is cancelled never starts.

Jobs run one at a time, in order, on the ``jobs`` :class:`~eyeserver.service.workers.
BoundedWorker`; at most ``capacity`` may wait and one more is refused with
:class:`~eyeserver.service.workers.QueueFullError` (HTTP 503). A job that needs the hardware or
the pipeline queues on their workers in turn, so it never races a capture.

The records are kept in memory only (the newest :data:`KEEP_FINISHED` finished ones): a restart
forgets every job, and a job interrupted by one is gone. What it had finished is kept, complete,
in the store (each reconstruction or calibration is written atomically on its own).
"""

from __future__ import annotations

import logging
import secrets
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

from eyeserver.errors import EyeserverError
from eyeserver.service.events import EventBus, event_time
from eyeserver.service.storage import UnknownIdError
from eyeserver.service.workers import BoundedWorker

__all__ = ["KEEP_FINISHED", "Job", "JobCancelled", "JobContext", "JobState", "JobWork", "Jobs"]

JobState = Literal["queued", "running", "succeeded", "failed", "cancelled"]
FINISHED: frozenset[JobState] = frozenset({"succeeded", "failed", "cancelled"})

KEEP_FINISHED = 200
"""Finished jobs remembered (in memory); older ones are forgotten first."""

_log = logging.getLogger(__name__)


class JobCancelled(EyeserverError):  # noqa: N818  (a signal, not a failure)
    """Raised by :meth:`JobContext.check_cancelled` once the job was asked to stop."""


@dataclass(frozen=True)
class Job:
    """A snapshot of one job.

    Attributes
    ----------
    id : str
        ``job-<12 hex digits>``.
    kind : str
        What it does (``"reconstructions"``, ``"stereo-solve"``, ``"phase-height-solve"``).
    actor : str
        Who asked for it.
    state : {"queued", "running", "succeeded", "failed", "cancelled"}
    progress : float
        0 to 1, as last reported.
    message : str
        What it is doing (or did) last.
    result : dict or None
        What it produced, once succeeded (a cancelled job keeps what it had finished).
    error : str or None
        Why it failed or was cancelled.
    created, started, finished : str or None
        UTC times, ISO 8601 with milliseconds.
    """

    id: str
    kind: str
    actor: str
    state: JobState
    progress: float
    message: str
    result: dict[str, Any] | None
    error: str | None
    created: str
    started: str | None
    finished: str | None


JobWork = Callable[["JobContext"], dict[str, Any]]
"""A job's work: runs on the jobs thread and returns its result (JSON-able)."""


@dataclass
class _Record:
    id: str
    kind: str
    actor: str
    work: JobWork
    state: JobState = "queued"
    progress: float = 0.0
    message: str = "queued"
    result: dict[str, Any] | None = None
    error: str | None = None
    created: str = field(default_factory=event_time)
    started: str | None = None
    finished: str | None = None
    cancel: threading.Event = field(default_factory=threading.Event)
    partial: dict[str, Any] | None = None

    def snapshot(self) -> Job:
        return Job(self.id, self.kind, self.actor, self.state, self.progress, self.message,
                   None if self.result is None else dict(self.result), self.error,
                   self.created, self.started, self.finished)


class JobContext:
    """What a running job sees of itself: progress reports and the cancellation flag."""

    def __init__(self, jobs: Jobs, record: _Record) -> None:
        self._jobs = jobs
        self._record = record

    @property
    def job_id(self) -> str:
        """The job's id."""
        return self._record.id

    @property
    def cancelled(self) -> bool:
        """Whether someone asked to cancel the job."""
        return self._record.cancel.is_set()

    def progress(self, fraction: float, message: str, *,
                 partial: dict[str, Any] | None = None) -> None:
        """Report that the job is ``fraction`` (0–1, clipped) done, doing ``message``.

        ``partial`` is what it has finished so far; it becomes the result of a job cancelled
        or failed afterwards, so a client learns which items were done.
        """
        self._jobs._progress(self._record, fraction, message, partial)

    def check_cancelled(self) -> None:
        """Raise :class:`JobCancelled` when someone asked to cancel the job."""
        if self._record.cancel.is_set():
            raise JobCancelled(f"job {self._record.id} was cancelled")


class Jobs:
    """The daemon's jobs: a bounded queue, one thread, records kept in memory.

    Parameters
    ----------
    events : EventBus
        Where ``job.state`` and ``job.progress`` events go.
    capacity : int
        Jobs that may wait while one runs; one more is refused with ``QueueFullError``.
    """

    def __init__(self, events: EventBus, capacity: int) -> None:
        self._events = events
        self._worker = BoundedWorker("jobs", capacity)
        self._lock = threading.Lock()
        self._records: dict[str, _Record] = {}

    def start(self) -> None:
        """Start the jobs thread. Idempotent."""
        self._worker.start()

    def stop(self) -> None:
        """Ask every job to stop, refuse new ones and join the thread (the running job stops
        at its next cancellation check; queued ones never start). Idempotent."""
        with self._lock:
            for record in self._records.values():
                if record.state not in FINISHED:
                    record.cancel.set()
        self._worker.stop()

    def submit(self, kind: str, work: JobWork, *, actor: str) -> Job:
        """Queue ``work`` as a job of ``kind`` asked for by ``actor``; returns its snapshot.

        Raises
        ------
        QueueFullError
            ``capacity`` jobs are already waiting (nothing was queued).
        StateConflictError
            The daemon is starting or shutting down.
        """
        record = _Record(id=f"job-{secrets.token_hex(6)}", kind=kind, actor=actor, work=work)
        with self._lock:
            self._records[record.id] = record
        try:
            self._worker.submit(lambda: self._run(record))
        except BaseException:
            with self._lock:
                del self._records[record.id]
            raise
        self._events.publish("job.state", job_id=record.id, kind=kind, state="queued")
        _log.info("job queued", extra={"job_id": record.id, "kind": kind, "actor": actor})
        return record.snapshot()

    def get(self, job_id: str) -> Job:
        """One job's snapshot; :class:`~eyeserver.service.storage.UnknownIdError` if unknown
        (or forgotten)."""
        with self._lock:
            record = self._records.get(job_id)
            if record is None:
                raise UnknownIdError(job_id, "job")
            return record.snapshot()

    def list_jobs(self) -> list[Job]:
        """Every job remembered, newest first."""
        with self._lock:
            return [r.snapshot() for r in reversed(self._records.values())]

    def cancel(self, job_id: str) -> Job:
        """Ask a job to stop: a queued one is cancelled at once, a running one at its next
        check. A finished job is left as it is. Returns its snapshot."""
        with self._lock:
            record = self._records.get(job_id)
            if record is None:
                raise UnknownIdError(job_id, "job")
            if record.state in FINISHED:
                return record.snapshot()
            record.cancel.set()
            if record.state == "queued":
                self._finish(record, "cancelled", error="cancelled before it started")
            return record.snapshot()

    def wait(self, job_id: str, timeout_s: float) -> Job:
        """Block until the job has finished or ``timeout_s`` passed; returns its snapshot."""
        deadline = time.monotonic() + timeout_s
        while True:
            job = self.get(job_id)
            if job.state in FINISHED or time.monotonic() >= deadline:
                return job
            time.sleep(0.02)

    # --- on the jobs thread -------------------------------------------------------------

    def _run(self, record: _Record) -> None:
        with self._lock:
            if record.state != "queued":  # cancelled while it waited
                return
            record.state, record.started, record.message = "running", event_time(), "started"
        self._events.publish("job.state", job_id=record.id, kind=record.kind, state="running")
        try:
            result = record.work(JobContext(self, record))
        except JobCancelled as exc:
            with self._lock:
                self._finish(record, "cancelled", result=record.partial, error=str(exc))
        except Exception as exc:
            # The reason is for the client: an eyeserver error says what went wrong; anything
            # else is a bug, logged with its traceback.
            if not isinstance(exc, EyeserverError):
                _log.exception("job crashed", extra={"job_id": record.id, "kind": record.kind})
            reason = str(exc) or type(exc).__name__
            with self._lock:
                self._finish(record, "failed", result=record.partial, error=reason)
        else:
            with self._lock:
                record.progress = 1.0
                self._finish(record, "succeeded", result=result)

    def _progress(self, record: _Record, fraction: float, message: str,
                  partial: dict[str, Any] | None) -> None:
        fraction = min(max(float(fraction), 0.0), 1.0)
        with self._lock:
            record.progress, record.message = fraction, message
            if partial is not None:
                record.partial = dict(partial)
        self._events.publish("job.progress", job_id=record.id, kind=record.kind,
                             progress=fraction, message=message)

    def _finish(self, record: _Record, state: JobState, *, result: dict[str, Any] | None = None,
                error: str | None = None) -> None:
        # Under self._lock.
        record.state, record.finished = state, event_time()
        record.result, record.error = result, error
        record.message = {"succeeded": "done", "failed": "failed",
                          "cancelled": "cancelled"}.get(state, record.message)
        self._events.publish("job.state", job_id=record.id, kind=record.kind, state=state,
                             error=error)
        log = _log.warning if state == "failed" else _log.info
        log("job finished", extra={"job_id": record.id, "kind": record.kind, "state": state,
                                   "error": error})
        finished = [r for r in self._records.values() if r.state in FINISHED]
        for old in finished[:max(0, len(finished) - KEEP_FINISHED)]:
            del self._records[old.id]
