"""Live tracking: the eye's pose at the camera rate, with the beam-hold flag, for ``/ws/pose``.

::

    RigFrameSource ─ acquisition ─► LatestFrame (1 slot) ─ processing ─► EventBus "pose"
     (25 Hz, the patient's unit)    newest wins; a frame    thread:       messages
                                    replaced unread is      deviation,
                                    counted as dropped      BeamHold
                                                             │    ▲ pose
                                                             ▼    │
                                                   worker process: reconstruct,
                                                   follow or fit the eye
                                                   (service.frame_pose)

One :class:`TrackingSession` follows one patient and fraction. The rig streams frame sets of the
patient's unit at the camera rate, paced on an injectable :class:`~eyeserver.core.clock.Clock`,
into a one-place slot where the newest wins: a frame set replaced before the processing thread
took it is *dropped*, a camera slot the rig could not serve in time is *missed*; both are counted
and show as gaps in the frame numbers :class:`~eyeserver.service.beamhold.BeamHold` sees.

A processing thread has each frame set reconstructed and the patient's eye model fitted in a
worker process (:class:`~eyeserver.service.tracking_worker.PoseWorker`: off the GIL and the core
of acquisition and the event loop). With several workers the first takes every frame it is free
for, the next only those it is busy through (:meth:`LatestFrame.take`'s ``rank``); a pose that
comes after a newer frame's was published is dropped, so frames are judged in order. The pose is
compared with the fraction's reference, fed to :class:`BeamHold` and published, one message per
processed frame (fields: README, "Live tracking"; ``latency_ms`` runs from the frame set's
mid-exposure on the rig's clock to the send). No eye, a lost eye or a blink: ``pose`` null and
``beam_hold`` true.

Once a frame gave a pose, the next ones are followed from it, in a window around the eye, the
global fit of the whole images coming back when that fails
(:mod:`~eyeserver.service.frame_pose`: what a worker does with one frame set). A frame after one
that lost the eye is still followed from a last pose at most :data:`FOLLOW_LOST_S` old (the
global fit takes ten frame periods or more); a blink keeps the last globe. Measured:
docs/notes/tracking.md.

Clock, frame source and pose finder (:class:`~eyeserver.service.frame_pose.FindPose`) are
injected, so tests replay any sequence exactly (:meth:`TrackingSession.process_once`). While a
session runs the daemon is in state ``tracking`` (captures get 409).
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
from collections.abc import Callable, Sequence
from contextlib import ExitStack
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any, Protocol

from eyeserver.calibration.artefact import load_calibration
from eyeserver.core.clock import Clock, MonotonicClock
from eyeserver.core.frames import Frame
from eyeserver.errors import DeviceError, EyeserverError, StateConflictError
from eyeserver.eye import LIMBUS_FROM_IMAGES, EyeModel, EyePose, PoseError
from eyeserver.hardware.rig import AcquiredStep, Rig
from eyeserver.reconstruction import ReconstructionError, blind_units
from eyeserver.service.beamhold import BeamHold, BeamHoldConfig, EyeSeen, FrameObservation
from eyeserver.service.core import NoActiveCalibrationError, Service
from eyeserver.service.events import EventBus
from eyeserver.service.frame_pose import FindPose, FrameSet, blind_alone
from eyeserver.service.metrics import TRACKING_OUTCOMES, TrackingFigures
from eyeserver.service.patients import Patients, Tolerances
from eyeserver.service.tracking_worker import PoseWorker
from eyeserver.service.verification import (
    deviation,
    judge,
    measurement_model,
    shape_cancels,
    shape_reason,
)

__all__ = ["CAMERA_RATE_HZ", "DEADLINE_S", "FOLLOW_LOST_S", "FrameSource", "LatestFrame",
           "RigFrameSource", "TrackingControl", "TrackingSession", "start_pose"]

CAMERA_RATE_HZ = 25.0
"""The cameras' frame rate during live tracking."""

DEADLINE_S = 2.0 / CAMERA_RATE_HZ
"""The fail-safe's default deadline: when no processed frame has been published for this long
(two camera periods), the session holds the beam itself (:meth:`TrackingSession.check_deadline`)."""

FOLLOW_LOST_S = 1.0
"""For this long after the last frame that found the eye (by mid-exposure time), a frame after
one that lost it is first followed from that frame's pose, not given the global fit at once."""

_log = logging.getLogger(__name__)
_JOIN_S = 10.0


class FrameSource(Protocol):
    """Where frame sets come from, at the camera rate."""

    def warm_up_frame(self) -> FrameSet | None:
        """Get ready for the stream (a rig prepares its cameras) and take a frame set before
        it to warm the pose finders with (:meth:`~eyeserver.service.frame_pose.FindPose.warm`):
        not one of the stream's frames, nor counted; None: none to take."""
        ...

    def next_frame(self) -> FrameSet | None:
        """Block until the next frame set; None when the source has ended."""
        ...

    @property
    def missed(self) -> int:
        """Camera frames that could not be acquired in time, so far."""
        ...


class RigFrameSource:
    """Frame sets of some units of the rig, paced at ``rate_hz`` on ``clock``.

    Frame ``n`` is due at ``start + n / rate_hz``: its pulse is scheduled for that moment as
    soon as the last frame set has arrived (:meth:`~eyeserver.hardware.rig.Rig.acquire` with
    ``at_ns``), so the frames come at a steady rate with exact times, and the simulated room
    renders each before it is due, as a camera's frame costs the host nothing. ``start`` is
    the first whole period of the clock (a multiple of ``1 / rate_hz`` since its zero) after
    the cameras were prepared for the stream
    (:meth:`~eyeserver.hardware.rig.Rig.prepare_stream`): the frames' times are known
    beforehand, where a simulated room rendered ahead has its frames
    (:meth:`~eyeserver.service.simroom.SimRoomControl.prerender_eye`). An acquisition
    that overruns its period makes the frames whose time has passed *missed* (counted in
    :attr:`missed`), so the frame numbers keep counting camera periods.
    """

    def __init__(self, rig: Rig, unit_ids: Sequence[str], clock: Clock,
                 rate_hz: float = CAMERA_RATE_HZ) -> None:
        if not rate_hz > 0:
            raise ValueError(f"rate_hz must be positive, not {rate_hz}")
        self._rig = rig
        self._unit_ids = list(unit_ids)
        self._clock = clock
        self._period_ns = round(1e9 / rate_hz)
        self._start_ns: int | None = None
        self._prepared = False
        self._next = 0
        self._missed = 0

    @property
    def missed(self) -> int:
        return self._missed

    def _prepare(self) -> None:
        # Cameras that need a moment before their first frame take it before the first frame
        # is due, not out of the first frames.
        if not self._prepared:
            self._rig.prepare_stream(self._unit_ids)
            self._prepared = True

    def warm_up_frame(self) -> FrameSet | None:
        self._prepare()
        return self._frame_set(-1, self._rig.acquire(self._unit_ids))

    def _frame_set(self, frame: int, steps: list[AcquiredStep]) -> FrameSet:
        times = [f.meta.t_ns for step in steps for f in step.frames.values()]
        return FrameSet(frame, round(sum(times) / len(times)), steps,
                        arrived_ns=self._clock.now_ns())

    def next_frame(self) -> FrameSet | None:
        clock = self._clock
        if self._start_ns is None:
            self._prepare()
            self._start_ns = -(-clock.now_ns() // self._period_ns) * self._period_ns
        due_ns = self._start_ns + self._next * self._period_ns
        now = clock.now_ns()
        if now > due_ns + self._period_ns // 2:  # late by more than half a period: missed
            late = (now - due_ns) // self._period_ns
            self._missed += int(late)
            self._next += int(late)
            due_ns += int(late) * self._period_ns
        frame = self._frame_set(self._next, self._rig.acquire(self._unit_ids, at_ns=due_ns))
        self._next += 1
        return frame


class LatestFrame:
    """A one-place slot where the newest frame set wins; replaced ones are counted as dropped."""

    def __init__(self) -> None:
        self._condition = threading.Condition()
        self._item: FrameSet | None = None
        self._closed = False
        self._waiting: list[int] = []  # the ranks of the takers waiting
        self.dropped = 0
        """Frame sets replaced before anyone took them."""

    def put(self, item: FrameSet) -> bool:
        """Offer a frame set; True when it replaced one that was never taken."""
        with self._condition:
            replaced = self._item is not None
            if replaced:
                self.dropped += 1
            self._item = item
            self._condition.notify_all()
            return replaced

    def take(self, timeout_s: float | None = None, rank: int = 0) -> FrameSet | None:
        """The newest frame set (removing it), waiting for one; None when closed and empty or
        on timeout.

        Takers of a lower ``rank`` come first: a frame set goes to a taker of rank ``k`` only
        while none of a lower rank is waiting (one that is, is free for it).
        """
        with self._condition:
            self._waiting.append(rank)
            try:
                ready = self._condition.wait_for(
                    lambda: self._closed or (self._item is not None
                                             and min(self._waiting) >= rank), timeout_s)
            finally:
                self._waiting.remove(rank)
                self._condition.notify_all()  # a lower rank leaving may let a higher one take
            if not ready:
                return None
            item, self._item = self._item, None
            return item

    def count_dropped(self) -> None:
        """Count a frame set that was taken but whose result came too late to be used."""
        with self._condition:
            self.dropped += 1

    def close(self) -> None:
        """Wake a waiting :meth:`take`; what is in the slot can still be taken."""
        with self._condition:
            self._closed = True
            self._condition.notify_all()


def _vector(values: Sequence[float] | None) -> list[float] | None:
    return None if values is None else [float(v) for v in values]


def _finite_or_none(value: float) -> float | None:
    return value if math.isfinite(value) else None


@dataclass
class _Counters:
    acquired: int = 0
    processed: int = 0
    last: dict[str, Any] | None = None
    error: str | None = None
    beam_hold: bool = True
    held_frames: int = 0
    stall: dict[str, Any] | None = None
    stalls: int = 0
    started: str = ""
    stopped: str | None = None
    lock: threading.Lock = field(default_factory=threading.Lock)


def start_pose(reference: dict[str, Any], model: EyeModel) -> EyePose | None:
    """The pose tracking looks for the eye from while it knows none: the reference's globe
    centre and gaze, with the model's radius, as if its limbus had been found in the images —
    so the first frame is followed from it in the cap about the reference gaze
    (:func:`~eyeserver.eye.track.track_eye`, ≈ 30 ms) instead of fitted in the whole
    images (:func:`~eyeserver.eye.fit.fit_eye`, ≈ 0.7 s, 18 camera frames): the patient
    was set up there. Where the limbus is not found near it, the frame gets the global fit of
    the whole images (:class:`~eyeserver.service.frame_pose.PoseFinder`).

    None when the model leaves the radius free (no captured reference holds it): tracking
    holds the radius of the pose it starts from, which must then be a fitted one. An
    ellipsoid's is the sphere's through its limbus
    (:meth:`~eyeserver.eye.fit.EyeModel.radius_through_limbus`).
    """
    radius = model.radius_through_limbus(model.limbus_diameter_mm / 2)
    if radius is None:
        return None
    return EyePose(centre_mm=_triple(reference["centre_mm"]), centre_sd_mm=(0.0, 0.0, 0.0),
                   globe_radius_mm=float(radius),
                   limbus_centre_mm=None if reference.get("limbus_centre_mm") is None
                   else _triple(reference["limbus_centre_mm"]),
                   limbus_sd_mm=None, gaze=_triple(reference["gaze"]), gaze_sd_deg=0.0,
                   torsion_deg=None, surface_mad_mm=0.0, sclera_points=0, confidence=0.0,
                   gaze_source=LIMBUS_FROM_IMAGES)


def _triple(values: Sequence[float]) -> tuple[float, float, float]:
    x, y, z = (float(v) for v in values)
    return x, y, z


class TrackingSession:
    """Live tracking of one patient's eye for one fraction (see the module docstring).

    Parameters
    ----------
    source : FrameSource
        The frame sets at the camera rate.
    find : FindPose or sequence of FindPose
        Frame set and last pose → pose (:class:`~eyeserver.service.frame_pose.PoseFinder` in
        this process, or :class:`~eyeserver.service.tracking_worker.PoseWorker` in its own);
        several work on successive frames at once, a processing thread each; closed when the
        session ends.
    reference : dict
        The fraction's reference pose (``centre_mm``, ``gaze``, ``limbus_centre_mm``).
    tolerances : Tolerances
        The patient's tolerances (``min_confidence`` also holds the beam).
    bus : EventBus
        Where each processed frame's message is published (type ``"pose"``).
    clock : Clock
        The rig's clock: frame times and latencies are on it.
    dwell_frames, hold_on_drop
        :class:`~eyeserver.service.beamhold.BeamHoldConfig`.
    deadline_s : float, optional
        The fail-safe: a watchdog thread holds the beam when no processed frame has been
        published for this long (:meth:`check_deadline`; the daemon's default
        :data:`DEADLINE_S`). None: no watchdog thread (tests call :meth:`check_deadline`).
    on_latency : callable, optional
        Given each published frame's latency (seconds from mid-exposure), for the metrics.
    expected : EyePose, optional
        The last pose until the first frame is processed (:func:`start_pose` of the
        reference): the first frame is followed from where the eye should be, like any other
        (:class:`~eyeserver.service.frame_pose.PoseFinder`). After that, or without it, a frame
        after one that lost the eye is followed from the last pose found up to
        :data:`FOLLOW_LOST_S` before it; with none as recent (nor the reference: the eye may
        not be there), the finder gets no last pose (the global fit). Whether a pose followed
        from it counts is the finder's call: a :class:`~eyeserver.service.frame_pose.PoseFinder`
        with the images takes it only with the limbus found in them.
    """

    def __init__(self, source: FrameSource, find: FindPose | Sequence[FindPose], *,
                 reference: dict[str, Any], tolerances: Tolerances, bus: EventBus, clock: Clock,
                 dwell_frames: int = 3, hold_on_drop: bool = True,
                 deadline_s: float | None = None,
                 info: dict[str, Any] | None = None, expected: EyePose | None = None,
                 on_latency: Callable[[float], None] | None = None) -> None:
        if deadline_s is not None and not deadline_s > 0:
            raise ValueError(f"deadline_s must be positive, not {deadline_s}")
        self.source = source
        self.finders: list[FindPose] = list(find) if isinstance(find, Sequence) else [find]
        if not self.finders:
            raise ValueError("a tracking session needs at least one pose finder")
        self.last_pose: EyePose | None = None
        """The last globe found (a blink's too); None before the first and once lost."""
        self._last_seen: tuple[int, EyePose] | None = None  # (frame time, the last globe)
        self.expected = expected
        self.reference = reference
        self.tolerances = tolerances
        self.bus = bus
        self.clock = clock
        self.info = dict(info or {})
        self.beam = BeamHold(BeamHoldConfig(dwell_frames=dwell_frames,
                                            min_confidence=tolerances.min_confidence,
                                            hold_on_drop=hold_on_drop))
        self.slot = LatestFrame()
        self._counters = _Counters(started=_now_text())
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._on_end: Callable[[], None] | None = None
        self._done = threading.Event()  # all threads have finished
        self._ended = threading.Event()  # ... and on_end has run
        self._publishing = threading.Lock()  # the last pose, the beam hold, the order
        self._last_frame = -1
        self._processing = 0  # processing threads still at work
        self.deadline_s = deadline_s
        self.on_latency = on_latency
        # The watchdog's marks on the clock: the last message published, the last frame set in.
        self._published_ns = self._arrived_ns = clock.now_ns()
        self._newest: FrameSet | None = None  # the last frame set in, for previews

    # --- one step at a time (the threads loop these; tests call them directly) -------------

    def acquire_once(self) -> FrameSet | None:
        """Take the next frame set from the source into the slot; None when the source ended.

        A frame set that arrives once :meth:`stop` was asked for is not offered (nor counted):
        the processing thread may have ended already, and it would be left unread.
        """
        frame_set = self.source.next_frame()
        if frame_set is not None and not self._stop.is_set():
            with self._counters.lock:
                self._counters.acquired += 1
                self._arrived_ns = self.clock.now_ns()
                self._newest = frame_set
            self.slot.put(frame_set)
        return frame_set

    def newest_frame_set(self) -> FrameSet | None:
        """The last frame set acquired (processed or not; None before the first): what a
        preview shows, at no cost to the stream."""
        with self._counters.lock:
            return self._newest

    def process_once(self, timeout_s: float | None = 0.0) -> dict[str, Any] | None:
        """Process the newest frame set in the slot and publish its message (None: none there)."""
        frame_set = self.slot.take(timeout_s)
        if frame_set is None:
            return None
        return self.process(frame_set)

    def process(self, frame_set: FrameSet, find: FindPose | None = None
                ) -> dict[str, Any] | None:
        """Reconstruct, fit, compare, update the beam hold and publish one frame's message.

        ``find`` is the finder to use (default the first). With several at work, a frame whose
        pose comes after a newer frame's was published is not used (None; counted as dropped):
        the beam hold sees the frames in order.
        """
        started_ns = self.clock.now_ns()
        pose: EyePose | None = None
        error: str | None = None
        eye: EyeSeen = "visible"
        finder = find or self.finders[0]
        with self._publishing:
            previous = self.last_pose
            seen = self._last_seen
            if previous is None and self._last_frame < 0:
                previous = self.expected  # nothing processed yet: where the eye should be
            elif previous is None and seen is not None and (
                    frame_set.t_ns - seen[0] <= FOLLOW_LOST_S * 1e9):
                previous = seen[1]  # lost in the last frame: where the eye was seen last
        try:
            pose = finder(frame_set, previous)
        except (PoseError, ReconstructionError, ValueError) as exc:
            eye, error = "lost", str(exc) or type(exc).__name__
        with self._publishing:
            if frame_set.frame <= self._last_frame:
                self.slot.count_dropped()
                return None
            self._last_frame = frame_set.frame
            return self._publish(frame_set, pose, eye, error, started_ns)

    def _publish(self, frame_set: FrameSet, pose: EyePose | None, eye: EyeSeen,
                 error: str | None, started_ns: int) -> dict[str, Any]:
        """The rest of :meth:`process`, in frame order."""
        self.last_pose = pose
        if pose is not None:
            self._last_seen = (frame_set.t_ns, pose)
        if pose is not None and pose.gaze_source == "none":
            # A globe without limbus or cornea: the lids cover the front of the eye.
            eye, error, pose = "blink", "no limbus or cornea visible (blink?)", None
        message: dict[str, Any] = {"t": frame_set.t_ns / 1e9, "t_ns": frame_set.t_ns,
                                   "frame": frame_set.frame, "pose": None, "deviation": None,
                                   "in_tolerance": False, "confidence": 0.0, "eye": eye}
        in_tolerance, confidence = False, 0.0
        if pose is not None:
            ref = self.reference
            found = deviation(pose.centre_mm, pose.gaze, ref["centre_mm"], ref["gaze"],
                              pose.limbus_centre_mm, ref.get("limbus_centre_mm"))
            confidence = float(pose.confidence)
            in_tolerance = judge(found, self.tolerances, confidence).in_tolerance
            message.update(
                pose={"centre_mm": _vector(pose.centre_mm),
                      "limbus_centre_mm": _vector(pose.limbus_centre_mm),
                      "gaze": _vector(pose.gaze)},
                deviation={"delta_mm": list(found.delta_mm),
                           "length_mm": _finite_or_none(found.length_mm),
                           "gaze_deg": _finite_or_none(found.gaze_deg)},
                in_tolerance=in_tolerance,
                confidence=confidence if math.isfinite(confidence) else 0.0)
        decision = self.beam.update(FrameObservation(frame_set.frame, eye, in_tolerance,
                                                     confidence))
        now_ns = self.clock.now_ns()
        message.update(beam_hold=decision.beam_hold, reasons=list(decision.reasons),
                       dropped_frames=self.slot.dropped, missed_frames=self.source.missed,
                       delivery_ms=None if frame_set.arrived_ns is None
                       else (frame_set.arrived_ns - frame_set.t_ns) / 1e6,
                       processing_ms=(now_ns - started_ns) / 1e6,
                       latency_ms=(now_ns - frame_set.t_ns) / 1e6)
        if error is not None:
            message["error"] = error
        counters = self._counters
        with counters.lock:
            counters.processed += 1
            counters.beam_hold = decision.beam_hold
            counters.held_frames += decision.beam_hold
            counters.last = message
            counters.stall = None
            self._published_ns = now_ns
        self.bus.publish("pose", **message)
        if self.on_latency is not None:
            self.on_latency((now_ns - frame_set.t_ns) / 1e9)
        return message

    def check_deadline(self) -> dict[str, Any] | None:
        """The fail-safe: when no processed frame has been published for :attr:`deadline_s`
        (on the session's clock), hold the beam, restart the dwell and publish a ``hold``
        message (once per silence) with its reason: ``no_frames`` when no frame set has come
        from the rig within the deadline either, ``worker_stalled`` when frames come but none
        is processed. The message, or None (in time, already said, or no deadline). A frame
        published afterwards ends the silence; the beam then falls only after the dwell.
        """
        if self.deadline_s is None:
            return None
        deadline_ns = round(self.deadline_s * 1e9)
        with self._publishing:
            counters = self._counters
            with counters.lock:
                now_ns = self.clock.now_ns()
                silent_ns = now_ns - self._published_ns
                if (silent_ns <= deadline_ns or counters.stall is not None
                        or self._stop.is_set()):
                    return None
                reason = ("no_frames" if now_ns - self._arrived_ns > deadline_ns
                          else "worker_stalled")
                self.beam.interrupt()
                counters.beam_hold = True
                counters.stalls += 1
                counters.stall = {"reason": reason, "since": _now_text(),
                                  "silent_ms": silent_ns / 1e6}
                message = {"reason": reason, "beam_hold": True, "at_ns": now_ns,
                           "silent_ms": silent_ns / 1e6, "last_frame": self._last_frame,
                           "frames_acquired": counters.acquired}
            self.bus.publish("hold", **message)
        _log.warning("tracking holds the beam: no processed frame in time",
                     extra={"reason": reason, "silent_ms": round(silent_ns / 1e6, 1)})
        return message

    def _watch_loop(self) -> None:
        assert self.deadline_s is not None
        step_s = self.deadline_s / 4
        while not self._stop.wait(step_s):
            try:
                self.check_deadline()
            except Exception:  # the watchdog must outlive a bad moment; say so
                _log.exception("the tracking watchdog failed a check")

    # --- threads ----------------------------------------------------------------------------

    def start(self, on_end: Callable[[], None] | None = None) -> None:
        """Run acquisition and processing (a thread per pose finder) on their own threads until
        :meth:`stop` or the source ends; ``on_end`` is called once all have finished."""
        self._on_end = on_end
        self._processing = len(self.finders)
        with self._counters.lock:
            self._published_ns = self._arrived_ns = self.clock.now_ns()
        self._threads = [threading.Thread(target=self._acquire_loop, name="tracking-acquisition",
                                          daemon=True),
                         *(threading.Thread(target=self._process_loop, args=(finder, n),
                                            name=f"tracking-processing-{n}", daemon=True)
                           for n, finder in enumerate(self.finders))]
        if self.deadline_s is not None:
            # Not joined at the end: it stops with the session's stop event.
            threading.Thread(target=self._watch_loop, name="tracking-watchdog",
                             daemon=True).start()
        for thread in self._threads:
            thread.start()

    def _warm_up(self) -> None:
        """Warm every finder on a frame set taken before the stream, side by side, around the
        eye where it should be: a worker's first frame otherwise measures the whole images'
        fringe strength and builds the window's cameras (measured in the tracking bench: the
        stream's first two frames, one on each worker, reached the clients 70 and 76 ms after
        mid-exposure; warmed, 28–44 ms). A finder that fails to warm is left to fail on its
        first frame."""
        frame_set = self.source.warm_up_frame()
        expected = self.expected
        if frame_set is None or expected is None:
            return

        def warm(finder: FindPose) -> None:
            try:
                finder.warm(frame_set, expected)
            except Exception:
                _log.warning("warming a pose finder failed", exc_info=True)

        threads = [threading.Thread(target=warm, args=(finder,), name=f"tracking-warm-{n}",
                                    daemon=True) for n, finder in enumerate(self.finders)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()

    def _acquire_loop(self) -> None:
        try:
            self._warm_up()
            while not self._stop.is_set():
                if self.acquire_once() is None:
                    break
        except DeviceError as exc:
            _log.error("tracking acquisition failed", extra={"reason": str(exc)})
            with self._counters.lock:
                self._counters.error = str(exc)
        except Exception as exc:  # the session must end, and say why
            _log.exception("tracking acquisition failed")
            with self._counters.lock:
                self._counters.error = f"{type(exc).__name__}: {exc}"
        finally:
            self.slot.close()

    def _process_loop(self, finder: FindPose, rank: int) -> None:
        try:
            while True:
                frame_set = self.slot.take(None, rank)
                if frame_set is None:
                    break  # closed and empty
                if self._stop.is_set():
                    self.slot.count_dropped()  # taken, but the session is ending
                    break
                self.process(frame_set, finder)
        except Exception as exc:
            _log.exception("tracking processing failed")
            with self._counters.lock:
                self._counters.error = f"{type(exc).__name__}: {exc}"
            self._stop.set()
            self.slot.close()  # the other processing threads end too
        finally:
            with self._counters.lock:
                self._processing -= 1
                last = self._processing == 0
                if last:
                    self._counters.stopped = _now_text()
            if last:
                threading.Thread(target=self._finish, name="tracking-end", daemon=True).start()

    def _finish(self) -> None:
        self._stop.set()  # the watchdog too
        with self._counters.lock:
            self._counters.beam_hold = True
            last_frame = self._last_frame
        # Whatever ended it, the beam is held once no one watches the eye.
        self.bus.publish("hold", reason="ended", beam_hold=True, at_ns=self.clock.now_ns(),
                         last_frame=last_frame)
        for thread in self._threads:
            if thread is not threading.current_thread():
                thread.join(_JOIN_S)
        for finder in self.finders:
            try:
                finder.close()
            except Exception:  # the session has ended either way; say why it did not close
                _log.exception("closing a pose finder failed")
        self._done.set()
        try:
            if self._on_end is not None:
                self._on_end()  # the daemon leaves "tracking" before stop() returns
        finally:
            self._ended.set()

    def stop(self, timeout_s: float = _JOIN_S) -> None:
        """Ask the threads to end and wait for them (frames being processed finish)."""
        self._stop.set()
        self.slot.close()
        self._ended.wait(timeout_s)

    @property
    def running(self) -> bool:
        """Whether the threads are still at work."""
        return bool(self._threads) and not self._done.is_set()

    def status(self) -> dict[str, Any]:
        """Counters, the beam-hold flag and the last message."""
        counters = self._counters
        with counters.lock:
            return {**self.info, "running": self.running, "started": counters.started,
                    "stopped": counters.stopped, "frames_acquired": counters.acquired,
                    "frames_processed": counters.processed,
                    "frames_dropped": self.slot.dropped, "frames_missed": self.source.missed,
                    "frames_held": counters.held_frames, "beam_hold": counters.beam_hold,
                    "stalled": counters.stall, "stalls": counters.stalls,
                    "deadline_ms": None if self.deadline_s is None else self.deadline_s * 1e3,
                    "error": counters.error, "last_message": counters.last}


def _frame_counts(status: dict[str, Any]) -> dict[str, int]:
    """A session status's counts under the metrics' names."""
    return {"acquired": status["frames_acquired"], "processed": status["frames_processed"],
            "dropped": status["frames_dropped"], "missed": status["frames_missed"],
            "held": status["frames_held"], "stalls": status["stalls"]}


def _now_text() -> str:
    return datetime.now(UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


SourceFactory = Callable[[Service, list[str], Clock], FrameSource]
"""Builds the frame source of a session from the service, the unit ids and the clock."""

FinderFactory = Callable[[Service, EyeModel], FindPose]
"""Builds a pose finder of a session from the service and the patient's eye model."""


def rig_source(service: Service, unit_ids: list[str], clock: Clock) -> FrameSource:
    """The daemon's rig at :data:`CAMERA_RATE_HZ`."""
    return RigFrameSource(service.rig, unit_ids, clock)


def worker_finder(service: Service, model: EyeModel) -> FindPose:
    """A started :class:`~eyeserver.service.tracking_worker.PoseWorker` on the active
    calibration: reconstruction and fit in their own process.

    Raises
    ------
    NoActiveCalibrationError
        No calibration is active.
    ReconstructionError
        The active calibration has no phase-to-height models.
    TrackingWorkerError
        The worker process did not start.
    """
    active = service.store.active_calibration()
    if active is None:
        raise NoActiveCalibrationError(
            "no calibration is active: import one (POST /api/v1/calibrations) and activate "
            "it (POST /api/v1/calibrations/{id}/activate)")
    worker = PoseWorker(active.path, service.rig_spec(), model)
    worker.start()
    return worker


class TrackingControl:
    """The daemon's live tracking: at most one :class:`TrackingSession` at a time.

    Parameters
    ----------
    service : Service
        The open daemon (rig, store, state machine, events).
    patients : Patients
        Its patients (eye model, reference, tolerances, unit).
    clock : Clock, optional
        The rig's clock (default: the machine's monotonic clock, which the simulated room uses).
    workers : int
        Pose finders per session, each on its own frames (default 2; the setting
        ``tracking_workers``).
    deadline_s : float
        The sessions' fail-safe deadline (:meth:`TrackingSession.check_deadline`; the setting
        ``tracking_deadline_ms``).
    source_factory, finder_factory
        Public attributes, so tests inject scripted ones (the default finder is a
        :class:`~eyeserver.service.tracking_worker.PoseWorker` on the active calibration).

    :attr:`messages` is the bus of pose messages (``/api/v1/ws/pose``); it outlives sessions, so
    a client stays connected from one session to the next.
    """

    def __init__(self, service: Service, patients: Patients, *,
                 clock: Clock | None = None, workers: int = 2, deadline_s: float = DEADLINE_S,
                 source_factory: SourceFactory = rig_source,
                 finder_factory: FinderFactory = worker_finder) -> None:
        self.service = service
        self.patients = patients
        self.clock: Clock = clock if clock is not None else MonotonicClock()
        self.workers = workers
        self.deadline_s = deadline_s
        if self.workers < 1:
            raise ValueError(f"workers must be at least 1, not {self.workers}")
        self.source_factory = source_factory
        self.finder_factory = finder_factory
        self.messages = EventBus()
        self._lock = threading.Lock()
        self._session: TrackingSession | None = None
        self._hold: ExitStack | None = None
        self._totals: dict[str, int] = dict.fromkeys((*TRACKING_OUTCOMES, "stalls"), 0)
        service.metrics.tracking = self.figures
        self._last_status: dict[str, Any] | None = None

    @property
    def session(self) -> TrackingSession | None:
        """The running (or last) session."""
        with self._lock:
            return self._session

    def start(self, patient_id: str, fraction: int, *, actor: str, dwell_frames: int = 3,
              hold_on_drop: bool = True) -> dict[str, Any]:
        """Start tracking a patient's eye for a fraction; the daemon enters ``tracking``.

        Raises
        ------
        UnknownPatientError, NoReferenceError
            No such patient, or the fraction has no reference pose (HTTP 404).
        NoActiveCalibrationError, StateConflictError
            No calibration is active, or the daemon is busy (tracking already), or the eye
            model leaves the globe's shape unknown against a reference that was not captured
            with it (:func:`~eyeserver.service.verification.shape_cancels`), or the patient's
            unit alone is blind to the fringe order (HTTP 409).
        ValueError
            A bad ``dwell_frames``.
        """
        service = self.service
        patient = self.patients.get(patient_id)
        reference = self.patients.reference(patient_id, fraction)
        stored_model = self.patients.eye_model(patient_id)
        model = measurement_model(stored_model, reference)
        if not shape_cancels(reference, None if stored_model is None else stored_model.version):
            unknown_shape = shape_reason(model.shape_sd_mm, patient.tolerances)
            if unknown_shape is not None:
                raise StateConflictError("cannot track against this reference (from the "
                                         f"{reference.source}): {unknown_shape}")
        unit_ids = service.unit_ids(patient.unit)
        active = service.store.active_calibration()
        if active is not None and len(unit_ids) < 2:
            blind = blind_units(load_calibration(active.path))
            if unit_ids[0] in blind:
                raise StateConflictError("cannot track unit " + unit_ids[0] + " alone: "
                                         + blind_alone(unit_ids[0], blind[unit_ids[0]]))
        with self._lock:
            if self._hold is not None:
                raise StateConflictError("cannot start tracking: the daemon is tracking")
            hold = ExitStack()
            hold.enter_context(service.operation("tracking", "live tracking"))
            finders: list[FindPose] = []
            try:
                source = self.source_factory(service, unit_ids, self.clock)
                for _ in range(self.workers):
                    finders.append(self.finder_factory(service, model))
                session = TrackingSession(
                    source, finders, reference=reference.pose,
                    tolerances=patient.tolerances, bus=self.messages, clock=self.clock,
                    dwell_frames=dwell_frames, hold_on_drop=hold_on_drop,
                    deadline_s=self.deadline_s, expected=start_pose(reference.pose, model),
                    on_latency=service.metrics.tracking_latency,
                    info={"patient_id": patient_id, "fraction": fraction,
                          "unit": patient.unit, "rate_hz": CAMERA_RATE_HZ,
                          "workers": self.workers,
                          "reference_version": reference.version,
                          "eye_model_version": None if stored_model is None
                          else stored_model.version})
            except BaseException:
                for finder in finders:
                    finder.close()
                hold.close()
                raise
            self._session, self._hold = session, hold
        service.store.add_audit_entries(actor, "start_tracking", patient.key, [
            {"patient_id": patient_id, "fraction": fraction, "unit": patient.unit}])
        service.events.publish("tracking.started", fraction=fraction, unit=patient.unit)
        _log.info("tracking started", extra={"fraction": fraction, "unit": patient.unit,
                                             "actor": actor})
        session.start(on_end=lambda: self._release(session))
        return session.status()

    def _release(self, session: TrackingSession) -> None:
        """Leave ``tracking`` once a session's threads have ended (stopped or failed)."""
        with self._lock:
            if self._session is not session or self._hold is None:
                return
            hold, self._hold = self._hold, None
            for name, value in _frame_counts(session.status()).items():
                self._totals[name] += value
        hold.close()
        status = session.status()
        self.service.events.publish("tracking.stopped", frames_processed=status[
            "frames_processed"], frames_dropped=status["frames_dropped"], error=status["error"])
        _log.info("tracking stopped", extra={k: status[k] for k in (
            "frames_acquired", "frames_processed", "frames_dropped", "frames_missed", "error")})

    def stop(self, *, actor: str) -> dict[str, Any]:
        """Stop the running session and leave ``tracking``; its final status.

        Raises
        ------
        StateConflictError
            No session is running (HTTP 409).
        """
        with self._lock:
            session = self._session
            if session is None or self._hold is None:
                raise StateConflictError("no live tracking is running")
        session.stop()
        self._release(session)
        with contextlib.suppress(EyeserverError):
            self.service.store.add_audit_entries(actor, "stop_tracking", "tracking", [
                {k: v for k, v in session.status().items() if k != "last_message"}])
        return session.status()

    def newest_frame(self, camera: str) -> tuple[Frame, int]:
        """The running session's newest frame of ``camera`` and its frame number.

        Raises
        ------
        StateConflictError
            No session is running, or it has acquired no frame yet (HTTP 409).
        KeyError
            ``camera`` is not in the tracked unit's frames.
        """
        session = self.session
        if session is None or not session.running:
            raise StateConflictError("no live tracking is running: a preview shows the frames "
                                     "of a tracking session")
        frame_set = session.newest_frame_set()
        if frame_set is None:
            raise StateConflictError("tracking has acquired no frame yet")
        for step in frame_set.steps:
            if camera in step.frames:
                return step.frames[camera], frame_set.frame
        raise KeyError(camera)

    def status(self) -> dict[str, Any]:
        """The running or last session's status (``running`` false and zero counts before
        the first)."""
        session = self.session
        if session is None:
            return {"running": False, "started": None, "stopped": None, "frames_acquired": 0,
                    "frames_processed": 0, "frames_dropped": 0, "frames_missed": 0,
                    "frames_held": 0, "beam_hold": True, "stalled": None, "stalls": 0,
                    "deadline_ms": None, "error": None, "last_message": None}
        return session.status()

    def figures(self) -> TrackingFigures:
        """For the metrics: ``running``, ``beam_hold`` and the frame counts and stalls summed
        over every session so far (:data:`~eyeserver.service.metrics.TrackingFigures`)."""
        with self._lock:
            running = self._hold is not None  # a session not yet summed into the totals
            totals = dict(self._totals)
        status = self.status()
        if running:
            for name, value in _frame_counts(status).items():
                totals[name] += value
        return {**totals, "running": float(status["running"]),
                "beam_hold": float(status["beam_hold"])}

    def close(self) -> None:
        """Stop a running session (the daemon is shutting down). Idempotent."""
        session = self.session
        if session is not None:
            session.stop()
            self._release(session)
