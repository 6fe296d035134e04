"""The daemon's figures in the Prometheus text format (``GET /metrics``).

=============================================  =======  =========================================
metric                                         type     labels / meaning
=============================================  =======  =========================================
``eyeserver_info``                             gauge    ``version``; always 1
``eyeserver_state``                            gauge    ``state``: 1 for the daemon's state, 0 for
                                                        the others (idle, capturing, …, fault)
``eyeserver_device_up``                        gauge    ``device``, ``kind``, ``unit``: 1 ok,
                                                        0 in fault
``eyeserver_frames_acquired_total``            counter  ``camera``: frames read in captures and
                                                        calibration sessions
``eyeserver_frames_dropped_total``             counter  ``camera``: exposures the camera lost
                                                        since it was last opened (a reopen after
                                                        a fault: a counter reset to Prometheus)
``eyeserver_captures_total``                   counter  ``unit``: captures stored
``eyeserver_reconstruction_seconds``           histo.   time of one reconstruction (worker only,
                                                        not the wait in its queue)
``eyeserver_queue_waiting``                    gauge    ``queue`` (acquisition, reconstruction):
                                                        jobs waiting
``eyeserver_queue_capacity``                   gauge    ``queue``: jobs that may wait
``eyeserver_events_dropped_total``             counter  events lost by slow stream clients
``eyeserver_tracking_running``                 gauge    1 while live tracking runs
``eyeserver_tracking_beam_hold``               gauge    1 while the beam is held (also with no
                                                        tracking: nothing watches the eye)
``eyeserver_tracking_frames_total``            counter  ``outcome``: acquired, processed,
                                                        dropped, missed, held (over all sessions)
``eyeserver_tracking_stalls_total``            counter  times no processed frame came within
                                                        the deadline (the fail-safe hold)
``eyeserver_tracking_latency_seconds``         histo.   mid-exposure to publication of each
                                                        processed frame
``eyeserver_event_subscribers``                gauge    open live-stream subscriptions
``process_*``                                  …        prometheus_client's process figures
                                                        (start time, CPU, memory, files)
=============================================  =======  =========================================

Counts the service keeps are plain numbers here, read at scrape time together with the live
figures (state, devices, queues), so that every camera and unit of the rig is listed from the
start with 0 rather than appearing at its first frame. Each service has a registry of its own
(never the library's global one): tests run several daemons in one process. What a scrape reads
from the daemon is stated here (:class:`MeasuredService`): this module does not import
:mod:`eyeserver.service.core`, which imports it.
"""

from __future__ import annotations

import threading
from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from typing import Protocol

from prometheus_client import CollectorRegistry, Histogram, ProcessCollector, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric

import eyeserver
from eyeserver.errors import EyeserverError
from eyeserver.hardware.rig import AcquiredStep, Rig
from eyeserver.service.events import EventBus

__all__ = ["CONTENT_TYPE", "RECONSTRUCTION_BUCKETS_S", "SERVICE_STATES", "TRACKING_OUTCOMES",
           "DeviceReading", "MeasuredService", "QueueReading", "ServiceMetrics",
           "TrackingFigures"]

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"
"""The media type of :meth:`ServiceMetrics.render`: the classic text format, which every
Prometheus reads (all names here are plain ``[a-z_]``, so nothing needs the 1.0 format's
escaping)."""

RECONSTRUCTION_BUCKETS_S = (0.1, 0.25, 0.5, 1.0, 2.0, 5.0, 10.0, 30.0, 60.0)
"""Upper bounds of the reconstruction-time buckets, seconds (one fused cloud takes ~1 s)."""

TRACKING_LATENCY_BUCKETS_S = (0.01, 0.02, 0.03, 0.04, 0.06, 0.08, 0.12, 0.25, 0.5, 1.0)
"""Upper bounds of tracking's latency buckets, seconds (the goal: p99 ≤ 40 ms)."""

TRACKING_OUTCOMES = ("acquired", "processed", "dropped", "missed", "held")
"""The frame counts of :data:`TrackingFigures`, as ``eyeserver_tracking_frames_total``'s
``outcome`` label."""

TrackingFigures = Mapping[str, float]
"""What live tracking reports at a scrape: ``running`` and ``beam_hold`` (0 or 1), ``stalls``
and each of :data:`TRACKING_OUTCOMES`, summed over every session so far."""

SERVICE_STATES = ("idle", "capturing", "calibrating", "tracking", "fault")


class DeviceReading(Protocol):
    """What a scrape reads of one device (:class:`~eyeserver.service.core.DeviceStatus`)."""

    @property
    def id(self) -> str: ...

    @property
    def kind(self) -> str: ...

    @property
    def unit(self) -> str | None: ...

    @property
    def health(self) -> str:
        """``ok`` or ``fault``."""
        ...

    @property
    def details(self) -> Mapping[str, object]:
        """The driver's figures; a camera's ``dropped_frames`` is read."""
        ...


class QueueReading(Protocol):
    """What a scrape reads of one job queue (:class:`~eyeserver.service.workers.BoundedWorker`)."""

    @property
    def name(self) -> str: ...

    @property
    def capacity(self) -> int: ...

    @property
    def waiting(self) -> int: ...


class MeasuredService(Protocol):
    """What :class:`ServiceMetrics` reads from the daemon at a scrape
    (:class:`~eyeserver.service.core.Service`)."""

    @property
    def state(self) -> str:
        """One of :data:`SERVICE_STATES`."""
        ...

    @property
    def events(self) -> EventBus: ...

    @property
    def rig(self) -> Rig:
        """The open rig; raises an :class:`~eyeserver.errors.EyeserverError` while closed."""
        ...

    @property
    def acquisition_worker(self) -> QueueReading: ...

    @property
    def reconstruction_worker(self) -> QueueReading: ...

    def devices(self) -> Sequence[DeviceReading]:
        """Every device of the open rig; raises like :attr:`rig`."""
        ...


class ServiceMetrics:
    """The counters of one daemon (:class:`MeasuredService`) and their exposition.

    The service calls :meth:`capture_stored`, :meth:`frames_read` and
    :meth:`reconstruction_done`, live tracking :meth:`tracking_latency` and registers its
    figures (:attr:`tracking`); :meth:`render` reads everything else from the service at scrape
    time. Thread-safe.
    """

    def __init__(self, service: MeasuredService) -> None:
        self._service = service
        self._lock = threading.Lock()
        self._frames: Counter[str] = Counter()
        self._captures: Counter[str] = Counter()
        self.registry = CollectorRegistry(auto_describe=False)
        self._reconstruction = Histogram(
            "eyeserver_reconstruction_seconds", "Time of one reconstruction on its worker.",
            buckets=RECONSTRUCTION_BUCKETS_S, registry=self.registry)
        self._latency = Histogram(
            "eyeserver_tracking_latency_seconds", "Live tracking: mid-exposure to publication.",
            buckets=TRACKING_LATENCY_BUCKETS_S, registry=self.registry)
        self.tracking: Callable[[], TrackingFigures] | None = None
        """Live tracking's figures at a scrape (set by the daemon's tracking control)."""
        self.registry.register(_LiveCollector(self))
        ProcessCollector(registry=self.registry)

    def capture_stored(self, unit: str, steps: Sequence[AcquiredStep]) -> None:
        """Count a stored capture of ``unit`` and the frames each camera gave for it."""
        with self._lock:
            self._captures[unit] += 1
        self.frames_read(steps)

    def frames_read(self, steps: Sequence[AcquiredStep]) -> None:
        """Count the frames each camera gave (a capture's, a calibration session's)."""
        with self._lock:
            for step in steps:
                self._frames.update(step.frames.keys())

    def tracking_latency(self, seconds: float) -> None:
        """Count one tracked frame published ``seconds`` after its mid-exposure."""
        self._latency.observe(seconds)

    def reconstruction_done(self, duration_s: float) -> None:
        """Count one reconstruction that took ``duration_s`` seconds."""
        self._reconstruction.observe(duration_s)

    def render(self) -> bytes:
        """Every metric in the Prometheus text format (:data:`CONTENT_TYPE`)."""
        return generate_latest(self.registry)

    def _counts(self) -> tuple[dict[str, int], dict[str, int]]:
        with self._lock:
            return dict(self._frames), dict(self._captures)


class _LiveCollector:
    """Reads the service at each scrape (a custom collector of prometheus_client)."""

    def __init__(self, metrics: ServiceMetrics) -> None:
        self._metrics = metrics

    def collect(self) -> Iterator[Metric]:
        service = self._metrics._service
        frames, captures = self._metrics._counts()
        info = GaugeMetricFamily("eyeserver_info", "The daemon's version.", labels=["version"])
        info.add_metric([eyeserver.__version__], 1)
        yield info
        state = GaugeMetricFamily("eyeserver_state", "1 for the daemon's current state.",
                                  labels=["state"])
        current = service.state
        for name in SERVICE_STATES:
            state.add_metric([name], 1 if name == current else 0)
        yield state
        yield from _queues(service)
        events_dropped = CounterMetricFamily(
            "eyeserver_events_dropped", "Events lost to full queues of slow stream clients.")
        events_dropped.add_metric([], service.events.dropped_total)
        yield events_dropped
        subscribers = GaugeMetricFamily("eyeserver_event_subscribers",
                                        "Open subscriptions of the live event stream.")
        subscribers.add_metric([], service.events.subscriber_count)
        yield subscribers
        try:
            devices = service.devices()
            units = [u.id for u in service.rig.units]
        except EyeserverError:  # not open (starting or stopping): no device figures
            devices, units = [], []
        up = GaugeMetricFamily("eyeserver_device_up", "1 while the device is ok, 0 in fault.",
                               labels=["device", "kind", "unit"])
        acquired = CounterMetricFamily("eyeserver_frames_acquired",
                                       "Frames read from the camera in captures.",
                                       labels=["camera"])
        dropped = CounterMetricFamily("eyeserver_frames_dropped",
                                      "Exposures the camera lost since it was last opened.",
                                      labels=["camera"])
        for device in devices:
            up.add_metric([device.id, device.kind, device.unit or ""],
                          1 if device.health == "ok" else 0)
            if device.kind == "camera":
                acquired.add_metric([device.id], frames.get(device.id, 0))
                lost = device.details.get("dropped_frames")
                if isinstance(lost, int | float) and not isinstance(lost, bool):
                    dropped.add_metric([device.id], lost)
        yield from (up, acquired, dropped)
        stored = CounterMetricFamily("eyeserver_captures", "Captures stored.", labels=["unit"])
        for unit in _union(units, ["all"], captures):
            stored.add_metric([unit], captures.get(unit, 0))
        yield stored
        figures = self._metrics.tracking
        if figures is not None:
            yield from _tracking(figures())


def _tracking(figures: TrackingFigures) -> Iterator[Metric]:
    for name, text in (("running", "1 while live tracking runs."),
                       ("beam_hold", "1 while the beam is held (also when nothing is tracked).")):
        gauge = GaugeMetricFamily(f"eyeserver_tracking_{name}", text)
        gauge.add_metric([], figures[name])
        yield gauge
    frames = CounterMetricFamily("eyeserver_tracking_frames", "Live tracking's frames, over "
                                 "all sessions.", labels=["outcome"])
    for outcome in TRACKING_OUTCOMES:
        frames.add_metric([outcome], figures[outcome])
    yield frames
    stalls = CounterMetricFamily("eyeserver_tracking_stalls", "Times no processed frame came "
                                 "within the deadline (the fail-safe held the beam).")
    stalls.add_metric([], figures["stalls"])
    yield stalls


def _queues(service: MeasuredService) -> Iterator[Metric]:
    waiting = GaugeMetricFamily("eyeserver_queue_waiting", "Jobs waiting in the worker's "
                                "queue.", labels=["queue"])
    capacity = GaugeMetricFamily("eyeserver_queue_capacity", "Jobs that may wait in the "
                                 "worker's queue.", labels=["queue"])
    for worker in (service.acquisition_worker, service.reconstruction_worker):
        waiting.add_metric([worker.name], worker.waiting)
        capacity.add_metric([worker.name], worker.capacity)
    yield waiting
    yield capacity


def _union(*groups: Iterable[str]) -> list[str]:
    seen: dict[str, None] = {}
    for group in groups:
        seen.update(dict.fromkeys(group))
    return list(seen)
