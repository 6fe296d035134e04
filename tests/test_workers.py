"""The daemon's workers: bounded job queues and the back-off retry loop, without hardware."""

from __future__ import annotations

import threading
from itertools import islice

import pytest

from eyeserver.api.errors import status_code_for
from eyeserver.errors import StateConflictError
from eyeserver.service.workers import BoundedWorker, QueueFullError, RetryLoop, backoff_delays


@pytest.fixture
def worker() -> BoundedWorker:
    running = BoundedWorker("acquisition", capacity=2)
    running.start()
    return running


def _block(worker: BoundedWorker) -> threading.Event:
    """Occupy the worker until the returned event is set."""
    started, release = threading.Event(), threading.Event()
    worker.submit(lambda: (started.set(), release.wait(30)))
    assert started.wait(10)
    return release


def test_jobs_run_one_at_a_time_in_order_on_one_thread(worker: BoundedWorker) -> None:
    release = _block(worker)
    seen: list[tuple[int, str]] = []
    futures = [worker.submit(lambda n=n: seen.append((n, threading.current_thread().name)))
               for n in range(2)]
    waiting = worker.waiting
    release.set()
    for future in futures:
        future.result(timeout=10)
    worker.stop()

    assert waiting == 2
    assert seen == [(0, "eyeserver-acquisition"), (1, "eyeserver-acquisition")]


def test_a_full_queue_refuses_at_once_and_names_itself(worker: BoundedWorker) -> None:
    release = _block(worker)
    accepted = [worker.submit(lambda: "queued") for _ in range(2)]
    with pytest.raises(QueueFullError) as refused:
        worker.submit(lambda: "one too many")
    release.set()
    results = [future.result(timeout=10) for future in accepted]
    after = worker.call(lambda: "room again")
    worker.stop()

    assert str(refused.value) == ("the acquisition queue is full (2 jobs waiting); "
                                  "try again later")
    assert status_code_for(refused.value) == 503
    assert results == ["queued", "queued"]
    assert after == "room again"


def test_a_job_error_reaches_its_caller_and_the_worker_goes_on(worker: BoundedWorker) -> None:
    def fail() -> None:
        raise ValueError("bad job")

    with pytest.raises(ValueError, match="bad job"):
        worker.call(fail)
    assert worker.call(lambda: 42) == 42
    worker.stop()


def test_a_job_may_call_the_worker_without_waiting_for_itself(worker: BoundedWorker) -> None:
    assert worker.call(lambda: worker.call(lambda: "inner")) == "inner"
    worker.stop()


def test_stop_finishes_queued_jobs_then_refuses_new_ones(worker: BoundedWorker) -> None:
    release = _block(worker)
    queued = worker.submit(lambda: "finished")
    release.set()
    worker.stop()

    assert queued.result(timeout=0) == "finished"
    with pytest.raises(StateConflictError, match="acquisition worker is not running"):
        worker.submit(lambda: None)


def test_the_back_off_doubles_to_its_cap() -> None:
    assert list(islice(backoff_delays(), 7)) == [1.0, 2.0, 4.0, 8.0, 16.0, 30.0, 30.0]
    assert list(islice(backoff_delays(0.5, 1.5), 4)) == [0.5, 1.0, 1.5, 1.5]
    with pytest.raises(ValueError):
        next(backoff_delays(2.0, 1.0))


def test_the_retry_loop_backs_off_on_failure_and_starts_again_after_success() -> None:
    delays: list[float] = []
    outcomes = iter([False, False, RuntimeError("broken"), True, False, True])
    pending = threading.Event()
    pending.set()
    finished = threading.Event()

    def attempt() -> bool:
        outcome = next(outcomes)
        if isinstance(outcome, Exception):
            raise outcome
        if outcome and len(delays) >= 6:
            pending.clear()
            finished.set()
        return outcome

    loop = RetryLoop("test", pending=pending.is_set, attempt=attempt,
                     wait=lambda delay_s, stop: delays.append(delay_s) or stop.is_set())
    loop.start()
    assert finished.wait(10)
    loop.stop()

    # Failures (an exception is one) double the wait; a success starts from 1 s again.
    assert delays == [1.0, 2.0, 4.0, 8.0, 1.0, 2.0]


def test_the_retry_loop_sleeps_until_poked_and_stops_promptly() -> None:
    faults: list[str] = []
    attempted = threading.Event()

    def attempt() -> bool:
        faults.clear()
        attempted.set()
        return True

    loop = RetryLoop("test", pending=lambda: bool(faults), attempt=attempt,
                     wait=lambda delay_s, stop: stop.is_set())
    loop.start()
    assert not attempted.wait(0.1)  # nothing pending: no attempt
    faults.append("S1")
    loop.poke()
    assert attempted.wait(10)
    loop.stop(timeout_s=10)
