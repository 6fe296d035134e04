"""Live tracking: the mechanisms on a manual clock with a scripted frame source and fit, then
``/api/v1/tracking`` and ``/api/v1/ws/pose`` over a real server.

Nothing here measures wall-clock time: frame times and latencies come from
:class:`~eyeserver.core.clock.ManualClock`; real time only paces the scripted source (so it
does not spin) and bounds waits against hangs.
"""

from __future__ import annotations

import io
import json
import socket
import threading
import time
import zipfile
from collections.abc import Iterator
from contextlib import ExitStack
from dataclasses import dataclass
from typing import Any

import cv2
import httpx
import numpy as np
import numpy.typing as npt
import pytest
from fastapi import FastAPI
from prometheus_client.parser import text_string_to_metric_families
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import ClientConnection, connect

from eyeserver.api import create_app
from eyeserver.api.routers import tracking as tracking_routes
from eyeserver.calibration.artefact import ARRAYS_FILE, CALIBRATION_FILE
from eyeserver.core.clock import Clock, ManualClock, MonotonicClock
from eyeserver.core.frames import Frame, FrameMeta
from eyeserver.eye.fit import CloudLike, EyeModel, EyePose, PoseError
from eyeserver.hardware.base import TriggerPulse, TriggerStep
from eyeserver.hardware.rig import AcquiredStep
from eyeserver.service.events import EventBus
from eyeserver.service.frame_pose import FrameSet, PoseFinder
from eyeserver.service.patients import Tolerances
from eyeserver.service.preview import camera_jpeg
from eyeserver.service.tracking import (
    FOLLOW_LOST_S,
    LatestFrame,
    RigFrameSource,
    TrackingControl,
    TrackingSession,
    start_pose,
)
from tests.apiclient import API, OPERATOR_TOKEN, PHYSICIST_TOKEN, auth, test_settings
from tests.liveserver import live_server

TIMEOUT_S = 60.0  # only against hangs
REFERENCE = {"centre_mm": [0.0, 0.0, -10.0], "gaze": [0.0, 0.0, 1.0], "limbus_centre_mm": None}
TOLERANCES = Tolerances(translation_mm=0.5, gaze_deg=1.0, min_confidence=0.5)


@dataclass(frozen=True)
class _Cloud:
    points: npt.NDArray[Any]
    quality: npt.NDArray[Any] | None = None
    script: object = None


def _pose(centre: tuple[float, float, float] = (0.0, 0.0, -10.0),
          gaze: tuple[float, float, float] = (0.0, 0.0, 1.0), confidence: float = 0.9,
          gaze_source: str = "limbus") -> EyePose:
    return EyePose(centre_mm=centre, centre_sd_mm=(0.01, 0.01, 0.01), globe_radius_mm=12.0,
                   limbus_centre_mm=(centre[0], centre[1], centre[2] + 10.0), limbus_sd_mm=0.02,
                   gaze=gaze, gaze_sd_deg=0.1, torsion_deg=None, surface_mad_mm=0.05,
                   sclera_points=1000, confidence=confidence, gaze_source=gaze_source)


class ScriptedSource:
    """Frame ``n`` at ``start + n × 40 ms`` on the clock; ``data`` of each frame from a script
    (a pose, or an exception the fit raises); ends after ``count`` frames (None: never)."""

    def __init__(self, clock: Clock, script: list[object] | None = None,
                 count: int | None = None, pace_s: float = 0.0) -> None:
        self.clock = clock
        self.script = script or []
        self.count = count if count is not None or script is None else len(self.script)
        self.pace_s = pace_s
        self.frame = 0

    @property
    def missed(self) -> int:
        return 0

    def warm_up_frame(self) -> FrameSet | None:
        return None

    def next_frame(self) -> FrameSet | None:
        if self.count is not None and self.frame >= self.count:
            return None
        if self.frame:
            self.clock.sleep(0.040)
        if self.pace_s:
            time.sleep(self.pace_s)  # real time: only so the thread does not spin
        data = self.script[self.frame] if self.frame < len(self.script) else _pose()
        frame_set = FrameSet(self.frame, self.clock.now_ns(), data=data)
        self.frame += 1
        return frame_set


class ScriptedPipeline:
    """Reconstruction and fit that take a set time on the clock and answer the script."""

    def __init__(self, clock: Clock, reconstruct_s: float = 0.0, fit_s: float = 0.0) -> None:
        self.clock = clock
        self.reconstruct_s = reconstruct_s
        self.fit_s = fit_s
        self.fitted: list[EyeModel] = []

    def reconstruct(self, frame_set: FrameSet) -> CloudLike:
        self.clock.sleep(self.reconstruct_s)
        return _Cloud(np.zeros((0, 3)), script=frame_set.data)

    def fit(self, cloud: CloudLike, model: EyeModel) -> EyePose:
        self.clock.sleep(self.fit_s)
        self.fitted.append(model)
        script = getattr(cloud, "script", None)
        if isinstance(script, Exception):
            raise script
        assert isinstance(script, EyePose)
        return script


def _session(clock: ManualClock, script: list[object], *, reconstruct_s: float = 0.0,
             fit_s: float = 0.0, dwell_frames: int = 3, bus: EventBus | None = None
             ) -> TrackingSession:
    pipeline = ScriptedPipeline(clock, reconstruct_s, fit_s)
    return TrackingSession(ScriptedSource(clock, script),
                           PoseFinder(pipeline.reconstruct, pipeline.fit, EyeModel.population()),
                           reference=REFERENCE,
                           tolerances=TOLERANCES, bus=bus or EventBus(), clock=clock,
                           dwell_frames=dwell_frames)


def _gaze(deg: float) -> tuple[float, float, float]:
    rad = np.radians(deg)
    return (float(np.sin(rad)), 0.0, float(np.cos(rad)))


# --- the mechanisms ---------------------------------------------------------------------------


def test_the_newest_frame_wins_and_replaced_frames_are_counted() -> None:
    slot = LatestFrame()
    assert slot.put(FrameSet(0, 0)) is False
    assert slot.put(FrameSet(1, 40)) is True
    assert slot.put(FrameSet(2, 80)) is True
    taken = slot.take(0)
    assert taken is not None and taken.frame == 2
    assert slot.dropped == 2
    assert slot.take(0) is None
    slot.put(FrameSet(3, 120))
    slot.close()
    last = slot.take(None)
    assert last is not None and last.frame == 3  # closing keeps what was put
    assert slot.take(None) is None


def test_a_frame_goes_to_the_lowest_ranked_free_taker() -> None:
    # The first worker takes every frame it is free for (its caches stay warm, and the workers
    # do not share the cores with each other); the second takes the frames the first is busy
    # through (a global fit's second).
    slot = LatestFrame()
    got: dict[int, list[int]] = {0: [], 1: []}
    spare_waiting = threading.Event()

    def take(rank: int) -> None:
        if rank == 1:
            spare_waiting.set()
        item = slot.take(TIMEOUT_S, rank)
        assert item is not None
        got[rank].append(item.frame)

    spare = threading.Thread(target=take, args=(1,))
    spare.start()
    assert spare_waiting.wait(TIMEOUT_S)
    first = threading.Thread(target=take, args=(0,))
    first.start()
    while 0 not in slot._waiting:  # both are waiting
        time.sleep(0.001)
    slot.put(FrameSet(0, 0))
    first.join(TIMEOUT_S)
    assert got == {0: [0], 1: []}  # the first is free: it takes the frame, the spare waits on
    slot.put(FrameSet(1, 40))  # the first is busy now (not waiting): the spare takes it
    spare.join(TIMEOUT_S)
    assert got == {0: [0], 1: [1]}
    # A spare that times out while a lower rank waits takes nothing and leaves the frame.
    slot.put(FrameSet(2, 80))
    slot._waiting.append(0)  # as if the first were waiting
    assert slot.take(0.01, rank=1) is None
    slot._waiting.remove(0)
    again = slot.take(0, rank=1)
    assert again is not None and again.frame == 2


def test_a_session_processes_only_the_newest_frame_and_reports_the_drops() -> None:
    clock = ManualClock(1_000_000_000)
    session = _session(clock, [_pose()] * 6)
    session.acquire_once()
    assert session.process_once() is not None  # frame 0
    for _ in range(3):
        session.acquire_once()
    message = session.process_once()

    assert message is not None and message["frame"] == 3
    assert message["dropped_frames"] == 2
    # Two frames unprocessed are counted, not held (BeamHoldConfig.max_gap_frames): the beam
    # is still held here only by the dwell after frame 0.
    assert message["beam_hold"] is True and message["reasons"] == ["dwell"]
    status = session.status()
    assert (status["frames_acquired"], status["frames_processed"],
            status["frames_dropped"]) == (4, 2, 2)
    assert session.beam.dropped_frames == 2  # the gap in frame numbers, as BeamHold saw it
    session.acquire_once()
    nxt = session.process_once()
    assert nxt is not None and nxt["frame"] == 4 and "dropped" not in nxt["reasons"]
    assert session.process_once() is None  # nothing new: nothing is processed twice


def test_a_pose_that_comes_after_a_newer_frames_is_dropped_not_published() -> None:
    # Two finders at work: frame 1's pose is published before frame 0's arrives.
    clock = ManualClock(1_000_000_000)
    bus = EventBus()
    session = _session(clock, [_pose(centre=(0.0, 0.0, 0.0)), _pose(centre=(0.1, 0.0, 0.0))],
                       bus=bus)
    first, second = session.source.next_frame(), session.source.next_frame()
    assert first is not None and second is not None
    newer = session.process(second)
    assert newer is not None and newer["frame"] == 1
    assert session.process(first) is None  # too late: the beam hold saw frame 1 already
    status = session.status()
    assert (status["frames_processed"], status["frames_dropped"]) == (1, 1)
    assert session.last_pose is not None and session.last_pose.centre_mm[0] == 0.1


def test_several_finders_share_the_frames_and_publish_them_in_order() -> None:
    clock = ManualClock(1_000_000_000)
    pipeline = ScriptedPipeline(clock)
    used: list[int] = []
    closed: list[int] = []

    class Finder(PoseFinder):
        def __init__(self, number: int) -> None:
            super().__init__(pipeline.reconstruct, pipeline.fit, EyeModel.population())
            self.number = number

        def __call__(self, frame_set: FrameSet, previous: EyePose | None) -> EyePose:
            used.append(self.number)
            time.sleep(0.002 * (1 + frame_set.frame % 3))  # real time: uneven, overlapping
            return super().__call__(frame_set, previous)

        def close(self) -> None:
            closed.append(self.number)

    frames = 60
    published: list[dict[str, Any]] = []

    class Recorded(EventBus):
        def publish(self, type: str, **data: Any) -> int:
            if type == "pose":  # not the hold the session's end publishes
                published.append(data)
            return 0

    session = TrackingSession(ScriptedSource(clock, count=frames, pace_s=0.001),
                              [Finder(0), Finder(1)], reference=REFERENCE,
                              tolerances=TOLERANCES, bus=Recorded(), clock=clock)
    done = threading.Event()
    session.start(on_end=done.set)
    assert done.wait(TIMEOUT_S)
    status = session.status()
    numbers = [m["frame"] for m in published]
    assert numbers == sorted(set(numbers))  # in order, none twice
    assert status["frames_processed"] == len(published)
    assert status["frames_processed"] + status["frames_dropped"] == frames
    assert set(used) == {0, 1} and sorted(closed) == [0, 1]
    assert status["running"] is False and status["error"] is None


def test_the_first_frame_is_looked_for_where_the_reference_expects_the_eye() -> None:
    clock = ManualClock(1_000_000_000)
    moved, lost = _pose((0.3, 0.0, -10.0)), PoseError("no sclera")
    script: list[object] = [_pose(gaze_source="limbus (images)"), moved, lost, _pose()]
    pipeline = ScriptedPipeline(clock)
    given: list[EyePose | None] = []

    def find(frame_set: FrameSet, previous: EyePose | None) -> EyePose:
        given.append(previous)
        return pipeline.fit(pipeline.reconstruct(frame_set), EyeModel.population())

    held = EyeModel(globe_radius_mm=11.5)
    expected = start_pose(REFERENCE, held)
    assert expected is not None and start_pose(REFERENCE, EyeModel.population()) is None
    assert expected.centre_mm == (0.0, 0.0, -10.0) and expected.gaze == (0.0, 0.0, 1.0)
    assert expected.globe_radius_mm == 11.5 and expected.gaze_source == "limbus (images)"
    session = TrackingSession(ScriptedSource(clock, script), find, reference=REFERENCE,
                              tolerances=TOLERANCES, bus=EventBus(), clock=clock,
                              expected=expected)
    for _ in script:
        session.acquire_once()
        session.process_once()
    # From the reference's pose first, then from each last pose; after a frame that lost the
    # eye, from the last pose found (FOLLOW_LOST_S: the next test).
    assert given == [expected, script[0], moved, moved]

    # Which poses followed from it count is the pose finder's call (test_eyetrack.py); a
    # first frame that found no eye from it is lost, and the next gets the global fit.
    given.clear()
    session = TrackingSession(ScriptedSource(clock, [lost, _pose()]), find,
                              reference=REFERENCE, tolerances=TOLERANCES, bus=EventBus(),
                              clock=clock, expected=expected)
    for _ in range(2):
        session.acquire_once()
        session.process_once()
    assert given == [expected, None]


def test_after_a_lost_frame_the_eye_is_followed_from_where_it_was_last_found_for_a_while(
) -> None:
    clock = ManualClock(1_000_000_000)
    found, lost = _pose((0.3, 0.0, -10.0)), PoseError("no eye in this frame")
    periods = round(FOLLOW_LOST_S / 0.040)  # frames 40 ms apart (ScriptedSource)
    again = _pose((0.5, 0.0, -10.0))
    script: list[object] = [found, *[lost] * (periods + 1), again, _pose()]
    pipeline = ScriptedPipeline(clock)
    given: list[EyePose | None] = []

    def find(frame_set: FrameSet, previous: EyePose | None) -> EyePose:
        given.append(previous)
        return pipeline.fit(pipeline.reconstruct(frame_set), EyeModel.population())

    session = TrackingSession(ScriptedSource(clock, script), find, reference=REFERENCE,
                              tolerances=TOLERANCES, bus=EventBus(), clock=clock)
    messages = []
    for _ in script:
        session.acquire_once()
        messages.append(session.process_once())

    # No pose yet: the global fit; then up to FOLLOW_LOST_S after the frame that found it,
    # every frame is followed from that pose (the finder decides whether what it finds from
    # there counts); frames later than that get the global fit (None), and the eye found
    # again is followed from its new pose.
    assert given[0] is None
    assert given[1:periods + 1] == [found] * periods
    assert given[periods + 1:periods + 3] == [None, None]
    assert given[-1] == again
    # The lost frames are lost all the same: beam held, no pose.
    assert all(m is not None and m["eye"] == "lost" and m["beam_hold"]
               for m in messages[1:periods + 2])


def test_beam_hold_rises_on_the_first_out_of_tolerance_frame_and_falls_after_the_dwell(
) -> None:
    clock = ManualClock()
    # Frames 0-5 steady, 6-7 a saccade of 5° (tolerance 1°), 8-13 steady again.
    script: list[object] = [_pose(gaze=_gaze(5.0) if n in (6, 7) else _gaze(0.1))
                            for n in range(14)]
    session = _session(clock, script, dwell_frames=3)
    holds, in_tolerance = [], []
    for _ in script:
        session.acquire_once()
        message = session.process_once()
        assert message is not None
        holds.append(message["beam_hold"])
        in_tolerance.append(message["in_tolerance"])

    assert in_tolerance == [n not in (6, 7) for n in range(14)]
    # Held until the third good frame, released, held at once on frame 6 (the saccade's
    # first), and released again on the third good frame after it (frame 10).
    assert holds == [True, True, False, False, False, False, True, True, True, True,
                     False, False, False, False]
    assert session.status()["frames_held"] == 6


def test_a_message_has_the_pose_the_deviation_and_latency_from_the_frame_time() -> None:
    clock = ManualClock(5_000_000_000)
    bus = EventBus()
    centre = (0.3, 0.0, -9.7)
    session = _session(clock, [_pose(centre=centre, gaze=_gaze(0.5), confidence=0.8)],
                       reconstruct_s=0.021, fit_s=0.009, bus=bus)
    session.acquire_once()
    message = session.process_once()

    assert message is not None
    assert message["t"] == 5.0 and message["t_ns"] == 5_000_000_000 and message["frame"] == 0
    assert message["latency_ms"] == pytest.approx(30.0)
    assert message["processing_ms"] == pytest.approx(30.0)
    assert message["pose"] == {"centre_mm": list(centre),
                               "limbus_centre_mm": [0.3, 0.0, pytest.approx(0.3)],
                               "gaze": list(_gaze(0.5))}
    assert message["deviation"]["delta_mm"] == pytest.approx([0.3, 0.0, 0.3])
    assert message["deviation"]["length_mm"] == pytest.approx(0.3 * 2 ** 0.5)
    assert message["deviation"]["gaze_deg"] == pytest.approx(0.5)
    assert message["in_tolerance"] is True and message["confidence"] == 0.8
    assert message["beam_hold"] is True and message["reasons"] == ["dwell"]
    assert message["eye"] == "visible"
    assert json.loads(json.dumps(message)) == message
    assert session.bus is bus and bus.last_seq == 1


@pytest.mark.parametrize(("script", "eye"), [
    (PoseError("no globe in the cloud"), "lost"),
    (_pose(gaze_source="none"), "blink"),
])
def test_a_failed_fit_or_a_blink_holds_the_beam_with_no_pose(script: object, eye: str) -> None:
    clock = ManualClock()
    session = _session(clock, [_pose(), _pose(), _pose(), script, _pose()])
    messages = []
    for _ in range(5):
        session.acquire_once()
        messages.append(session.process_once())

    assert [m["beam_hold"] for m in messages if m] == [True, True, False, True, True]
    failed = messages[3]
    assert failed is not None
    assert failed["pose"] is None and failed["deviation"] is None
    assert failed["eye"] == eye and failed["reasons"] == [eye] and failed["confidence"] == 0.0
    assert failed["error"]


def test_low_confidence_holds_the_beam() -> None:
    session = _session(ManualClock(), [_pose(confidence=0.2)])
    session.acquire_once()
    message = session.process_once()
    assert message is not None
    assert message["in_tolerance"] is True and message["beam_hold"] is True
    assert "low_confidence" in message["reasons"]


class _FakeRig:
    """Takes ``PREPARE_S`` of the clock to prepare its cameras for the stream, then pulses at
    the scheduled time (now if that has passed), takes ``busy_s`` of the clock to deliver (the
    simulated room's rendering) and no less than 4 ms after the pulse (exposure and transfer);
    frames mid-exposure 1 and 3 ms after the pulse."""

    def __init__(self, clock: ManualClock, busy_s: list[float]) -> None:
        self.clock = clock
        self.busy_s = busy_s
        self.prepared: list[list[str]] = []
        self.calls: list[tuple[float, float]] = []  # (called, pulse) ms after the stream's start

    def prepare_stream(self, unit_ids: list[str]) -> None:
        self.prepared.append(list(unit_ids))
        self.clock.advance(PREPARE_S)

    def acquire(self, unit_ids: list[str], *, at_ns: int | None = None) -> list[AcquiredStep]:
        assert self.prepared, "acquired before the cameras were prepared"
        now = self.clock.now_ns()
        pulse = now if at_ns is None else max(now, at_ns)
        self.calls.append(((now - STREAM_NS) / 1e6, (pulse - STREAM_NS) / 1e6))
        step = TriggerStep(projectors=("P1",), cameras=("S1", "S2"))
        frames = {c: Frame(np.zeros((2, 2), np.uint8),
                           FrameMeta(c, len(self.calls), pulse + 1_000_000 + k * 2_000_000,
                                     2000.0, 0.0, 0, 8))
                  for k, c in enumerate(("S1", "S2"))}
        self.clock.advance(self.busy_s[len(self.calls) - 1])
        self.clock.sleep(max(0.0, (pulse + 4_000_000 - self.clock.now_ns()) / 1e9))
        return [AcquiredStep(TriggerPulse(len(self.calls), pulse, step), frames)]


START_NS = 10_000_000_000
PREPARE_S = 1.52  # the stream starts on a whole camera period (40 ms) of the clock
STREAM_NS = START_NS + round(PREPARE_S * 1e9)


def test_the_rig_source_schedules_frames_at_the_camera_rate_and_counts_missed_ones() -> None:
    clock = ManualClock(START_NS)
    rig = _FakeRig(clock, [0.010, 0.010, 0.130, 0.010, 0.010])
    source = RigFrameSource(rig, ["left"], clock)  # type: ignore[arg-type]
    frames = [source.next_frame() for _ in range(5)]

    # The cameras are prepared once, before the first frame's time is set: the time they take
    # (the simulated room's first render of a moving eye) costs no frames.
    assert rig.prepared == [["left"]]
    assert [f.frame for f in frames if f] == [0, 1, 2, 4, 5]  # frame 3 was missed
    assert source.missed == 1
    # Each pulse is scheduled for its due time as soon as the last frames arrived (so the room
    # can render ahead); frame 4, due at 160 ms, is fired at once, 14 ms late (within half a
    # period), frame 5 on time again.
    assert rig.calls == [(0.0, 0.0), (10.0, 40.0), (44.0, 80.0), (174.0, 174.0),
                         (184.0, 200.0)]
    first, late = frames[0], frames[3]
    assert first is not None and first.t_ns == STREAM_NS + 2_000_000  # mean mid-exposure
    assert late is not None and late.t_ns == STREAM_NS + 176_000_000
    # In the daemon's hands when the rig returned them: 4 ms after the pulse, or once rendered.
    assert [(f.arrived_ns - STREAM_NS) / 1e6 for f in frames if f] == [10.0, 44.0, 174.0,
                                                                        184.0, 204.0]
    session = TrackingSession(source, lambda frame_set, previous: _pose(), reference=REFERENCE,
                              tolerances=TOLERANCES, bus=EventBus(), clock=clock)
    message = session.process(first)
    assert message is not None and message["delivery_ms"] == 8.0  # 2 ms mid-exposure → 10 ms
    assert message["latency_ms"] >= message["delivery_ms"] + message["processing_ms"]


def test_the_rig_source_takes_a_warm_up_frame_before_the_stream() -> None:
    clock = ManualClock(START_NS)
    rig = _FakeRig(clock, [0.010, 0.010, 0.010])
    source = RigFrameSource(rig, ["left"], clock)  # type: ignore[arg-type]
    warm = source.warm_up_frame()
    frames = [source.next_frame() for _ in range(2)]
    # Prepared once, for both; the warm-up frame is taken at once, the stream's time set after
    # it: its first frame is frame 0, due at the first whole camera period of the clock after
    # the warm-up frame has arrived (10 ms after a whole period: 30 ms later), where frames
    # rendered ahead are (the simulated room's pre-rendered stream).
    assert rig.prepared == [["left"]]
    assert warm is not None and warm.frame == -1 and warm.t_ns == STREAM_NS + 2_000_000
    assert [f.frame for f in frames if f] == [0, 1] and source.missed == 0
    assert rig.calls == [(0.0, 0.0), (10.0, 40.0), (44.0, 80.0)]
    assert all(f.steps[0].pulse.t_ns % 40_000_000 == 0 for f in frames if f)


def test_the_finders_are_warmed_side_by_side_before_the_stream_where_the_eye_should_be(
        ) -> None:
    clock = ManualClock(1_000_000_000)
    pipeline = ScriptedPipeline(clock)
    warmed: list[tuple[int, int, EyePose, str]] = []
    calls: list[int] = []
    both = threading.Barrier(2, timeout=TIMEOUT_S)

    class Finder(PoseFinder):
        def __init__(self, number: int) -> None:
            super().__init__(pipeline.reconstruct, pipeline.fit, EyeModel.population())
            self.number = number

        def warm(self, frame_set: FrameSet, expected: EyePose) -> None:
            warmed.append((self.number, frame_set.frame, expected,
                           threading.current_thread().name))
            both.wait()  # each waits for the other: side by side
            if self.number:
                raise RuntimeError("a finder that fails to warm fails on its frames, if at all")

        def __call__(self, frame_set: FrameSet, previous: EyePose | None) -> EyePose:
            calls.append(frame_set.frame)
            return super().__call__(frame_set, previous)

    class Warming(ScriptedSource):
        def warm_up_frame(self) -> FrameSet | None:
            return FrameSet(-1, self.clock.now_ns(), data=_pose())

    published: list[dict[str, Any]] = []

    class Recorded(EventBus):
        def publish(self, type: str, **data: Any) -> int:
            if type == "pose":  # not the hold the session's end publishes
                published.append(data)
            return 0

    expected = start_pose(REFERENCE, EyeModel(globe_radius_mm=12.0))
    assert expected is not None
    session = TrackingSession(Warming(clock, count=3, pace_s=0.005), [Finder(0), Finder(1)],
                              reference=REFERENCE, tolerances=TOLERANCES, bus=Recorded(),
                              clock=clock, expected=expected)
    done = threading.Event()
    session.start(on_end=done.set)
    assert done.wait(TIMEOUT_S)
    assert sorted((n, f, e) for n, f, e, _ in warmed) == [(0, -1, expected), (1, -1, expected)]
    assert len({name for *_, name in warmed}) == 2
    # The warm-up frame is neither processed nor counted; the stream's frames are.
    assert calls and -1 not in calls and -1 not in [m["frame"] for m in published]
    status = session.status()
    assert status["frames_acquired"] == status["frames_processed"] + status["frames_dropped"]
    assert status["frames_acquired"] == 3 and status["error"] is None


class _Recorded:
    """A bus that keeps what is published, in order: ``(type, fields)``."""

    def __init__(self) -> None:
        self.published: list[tuple[str, dict[str, Any]]] = []
        self._lock = threading.Lock()

    def publish(self, type: str, **data: Any) -> int:
        with self._lock:
            self.published.append((type, data))
            return len(self.published)

    def of(self, kind: str) -> list[dict[str, Any]]:
        with self._lock:
            return [data for t, data in self.published if t == kind]


def _watched(clock: Clock, source: Any, bus: _Recorded, deadline_s: float = 0.08
             ) -> TrackingSession:
    pipeline = ScriptedPipeline(clock)
    return TrackingSession(source, PoseFinder(pipeline.reconstruct, pipeline.fit,
                                              EyeModel.population()),
                           reference=REFERENCE, tolerances=TOLERANCES,
                           bus=bus, clock=clock, deadline_s=deadline_s)  # type: ignore[arg-type]


def test_no_processed_frame_within_the_deadline_holds_the_beam_and_says_why() -> None:
    clock = ManualClock(1_000_000_000)
    bus = _Recorded()
    session = _watched(clock, ScriptedSource(clock, [_pose()] * 10), bus)
    for _ in range(4):
        session.acquire_once()
        session.process_once()
    assert session.status()["beam_hold"] is False

    clock.advance(0.08)  # exactly the deadline: in time
    assert session.check_deadline() is None
    clock.advance(0.01)  # the rig has sent nothing for 90 ms
    hold = session.check_deadline()

    assert hold is not None and hold["reason"] == "no_frames" and hold["beam_hold"] is True
    assert hold["last_frame"] == 3 and hold["silent_ms"] == pytest.approx(90.0)
    assert bus.of("hold") == [hold]
    status = session.status()
    assert status["beam_hold"] is True and status["stalls"] == 1
    assert status["stalled"]["reason"] == "no_frames"
    assert session.check_deadline() is None  # said once per silence
    # The next frame ends the silence; the beam falls only after the dwell again.
    resumed = []
    for _ in range(3):
        session.acquire_once()
        message = session.process_once()
        assert message is not None
        resumed.append(message)
    assert [m["beam_hold"] for m in resumed] == [True, True, False]
    assert resumed[0]["reasons"] == ["dwell"]
    assert session.status()["stalled"] is None


def test_frames_that_come_but_are_not_processed_are_a_stalled_worker() -> None:
    clock = ManualClock(1_000_000_000)
    bus = _Recorded()
    session = _watched(clock, ScriptedSource(clock, [_pose()] * 10), bus)
    session.acquire_once()
    session.process_once()
    for _ in range(3):  # 120 ms of frames, none processed
        session.acquire_once()

    hold = session.check_deadline()

    assert hold is not None and hold["reason"] == "worker_stalled"
    assert hold["frames_acquired"] == 4


def test_the_watchdog_holds_the_beam_when_the_rig_stops_delivering() -> None:
    # Real threads and the machine's clock: the rig's frames stop after the fifth.
    clock = MonotonicClock()
    release = threading.Event()

    class Stalling(ScriptedSource):
        def next_frame(self) -> FrameSet | None:
            if self.frame == 5:
                release.wait(TIMEOUT_S)
            time.sleep(0.040)
            if self.frame >= 12:
                return None
            frame_set = FrameSet(self.frame, self.clock.now_ns(), data=_pose())
            self.frame += 1
            return frame_set

    bus = _Recorded()
    session = _watched(clock, Stalling(clock), bus)
    done = threading.Event()
    session.start(on_end=done.set)
    deadline = time.monotonic() + TIMEOUT_S
    while not bus.of("hold") and time.monotonic() < deadline:
        time.sleep(0.01)
    stalled = session.status()
    release.set()
    assert done.wait(TIMEOUT_S)

    holds = bus.of("hold")
    assert holds and holds[0]["reason"] == "no_frames" and holds[0]["last_frame"] == 4
    assert stalled["beam_hold"] is True and stalled["stalled"]["reason"] == "no_frames"
    # Frames came again, and when the session ended by itself the beam was held with it.
    assert [m["frame"] for m in bus.of("pose")][-1] == 11
    assert holds[-1]["reason"] == "ended" and bus.published[-1][0] == "hold"
    assert session.status()["beam_hold"] is True


# --- the API and the pose stream over a real server ------------------------------------------


@pytest.fixture(scope="module")
def app(tmp_path_factory: pytest.TempPathFactory) -> FastAPI:
    data_dir = tmp_path_factory.mktemp("tracking") / "data"
    return create_app(test_settings(data_dir))


@pytest.fixture(scope="module")
def base_url(app: FastAPI) -> Iterator[str]:
    with live_server(app) as url:
        yield url


@pytest.fixture(scope="module")
def tracking(app: FastAPI, base_url: str) -> TrackingControl:
    return scripted_tracking(app, base_url)


def scripted_tracking(app: FastAPI, base_url: str) -> TrackingControl:
    """The app's tracking on a manual clock with a scripted pipeline and frame source, and a
    patient P-T1 with a planned reference (the MRI's ellipsoid)."""
    control = app.state.tracking
    assert isinstance(control, TrackingControl)
    clock = ManualClock(1_000_000_000)
    pipeline = ScriptedPipeline(clock, reconstruct_s=0.012, fit_s=0.008)
    control.clock = clock
    # The manual clock moves only with the script, not with the threads' real time: the
    # fail-safe deadline is tested on its own (above), not against it.
    control.deadline_s = 3600.0
    control.finder_factory = lambda service, model: PoseFinder(pipeline.reconstruct,
                                                               pipeline.fit, model)
    control.source_factory = lambda service, units, c: ScriptedSource(c, pace_s=0.002)
    # A planned reference is absolute: the MRI's ellipsoid, known to 0.05 mm, gives the
    # globe's shape.
    _planned_patient(base_url, "P-T1", "right", {"ellipsoid": {"semi_axes_mm": [12.1, 11.9, 12.4]},
                                                "globe_sd_mm": 0.05})
    return control


def _planned_patient(base_url: str, patient_id: str, eye: str,
                     model: dict[str, Any] | None = None) -> None:
    """A patient tracked with unit left against the planned ``REFERENCE`` for fraction 1, with
    ``model`` as eye model (an ``ellipsoid`` and its ``globe_sd_mm``; None: population
    defaults)."""
    physicist = auth(PHYSICIST_TOKEN)
    requests = [
        httpx.put(f"{base_url}{API}/patients/{patient_id}", json={"eye": eye, "unit": "left"},
                  headers=physicist),
        httpx.put(f"{base_url}{API}/patients/{patient_id}/fractions/1/reference",
                  json=REFERENCE, headers=physicist)]
    if model is not None:
        requests.append(httpx.post(f"{base_url}{API}/patients/{patient_id}/eye-models",
                                   json=model, headers=physicist))
    for request in requests:
        assert request.status_code in (200, 201), request.text


def _post(base_url: str, path: str, body: dict[str, Any] | None = None,
          token: str = OPERATOR_TOKEN) -> httpx.Response:
    return httpx.post(f"{base_url}{API}{path}", json=body, headers=auth(token),
                      timeout=TIMEOUT_S)


def _put(base_url: str, path: str, body: dict[str, Any]) -> httpx.Response:
    return httpx.put(f"{base_url}{API}{path}", json=body, headers=auth(PHYSICIST_TOKEN),
                     timeout=TIMEOUT_S)


def _get(base_url: str, path: str) -> dict[str, Any]:
    response = httpx.get(f"{base_url}{API}{path}", headers=auth(OPERATOR_TOKEN),
                         timeout=TIMEOUT_S)
    assert response.status_code == 200, response.text
    body: dict[str, Any] = response.json()
    return body


def _connect(base_url: str, token: str | None = OPERATOR_TOKEN, **kwargs: Any
             ) -> ClientConnection:
    query = "" if token is None else f"?token={token}"
    url = base_url.replace("http://", "ws://", 1) + f"{API}/ws/pose{query}"
    return connect(url, compression=None, open_timeout=TIMEOUT_S, close_timeout=5,
                   ping_interval=None, **kwargs)


def _recv(ws: ClientConnection) -> dict[str, Any]:
    message: dict[str, Any] = json.loads(ws.recv(timeout=TIMEOUT_S))
    return message


def _wait_state(base_url: str, state: str) -> None:
    deadline = time.monotonic() + TIMEOUT_S
    while _get(base_url, "/status")["state"] != state:
        assert time.monotonic() < deadline, f"the daemon did not become {state}"
        time.sleep(0.01)


@pytest.mark.slow
def test_tracking_starts_streams_and_stops_through_the_api(
    base_url: str, tracking: TrackingControl, app: FastAPI
) -> None:
    assert _post(base_url, "/tracking/stop").status_code == 409  # nothing to stop
    eye = _put(base_url, "/sim/eye", {"position_mm": [0.0, 0.0, -10.0]})
    assert eye.status_code == 200, eye.text
    with _connect(base_url) as ws:
        started = _post(base_url, "/tracking/start", {"patient_id": "P-T1", "fraction": 1})
        assert started.status_code == 201, started.text
        assert started.json()["running"] is True and started.json()["unit"] == "left"
        assert _get(base_url, "/status")["state"] == "tracking"
        # Nothing else may use the hardware meanwhile.
        capture = _post(base_url, "/captures", {"unit": "left"})
        assert capture.status_code == 409 and "tracking" in capture.json()["detail"]
        again = _post(base_url, "/tracking/start", {"patient_id": "P-T1", "fraction": 1})
        assert again.status_code == 409
        # The simulated eye may move under tracking (a demonstration need not script it all),
        # but no other scene may take its place.
        moved = _put(base_url, "/sim/eye", {"position_mm": [1.0, 0.0, -10.0]})
        assert moved.status_code == 200, moved.text
        plate = _put(base_url, "/sim/scene", {"kind": "plate"})
        assert plate.status_code == 409 and "tracking" in plate.json()["detail"]

        messages = [_recv(ws) for _ in range(10)]
        stopped = _post(base_url, "/tracking/stop")

    assert stopped.status_code == 200, stopped.text
    final = stopped.json()
    assert final["running"] is False and final["error"] is None
    assert final["frames_processed"] >= 10
    # Every acquired frame was processed or dropped, but for one that stop() left unread.
    assert final["frames_acquired"] - 1 <= final["frames_processed"] + final["frames_dropped"]
    assert final["frames_processed"] + final["frames_dropped"] <= final["frames_acquired"]
    assert _get(base_url, "/status")["state"] == "idle"
    assert _get(base_url, "/tracking")["frames_processed"] == final["frames_processed"]
    pose = [m for m in messages if m["type"] == "pose"]
    assert final["last_message"]["frame"] >= pose[-1]["frame"]
    assert pose, messages
    for message in pose:
        assert {"t", "frame", "pose", "deviation", "in_tolerance", "beam_hold", "latency_ms",
                "confidence"} <= set(message)
        assert set(message["pose"]) == {"centre_mm", "limbus_centre_mm", "gaze"}
        assert {"delta_mm", "gaze_deg"} <= set(message["deviation"])
        # The scripted pipeline takes 20 ms of the manual clock; the send adds none of it.
        assert message["latency_ms"] >= 20.0
    frames = [m["frame"] for m in pose]
    assert frames == sorted(frames)
    assert _post(base_url, "/tracking/stop").status_code == 409
    assert _post(base_url, "/captures", {"unit": "left"}).status_code == 201
    metrics = httpx.get(f"{base_url}/metrics", headers=auth(OPERATOR_TOKEN), timeout=TIMEOUT_S)
    samples = {(sample.name, tuple(sorted(sample.labels.items()))): sample.value
               for family in text_string_to_metric_families(metrics.text)
               for sample in family.samples}
    processed = samples[("eyeserver_tracking_frames_total", (("outcome", "processed"),))]
    assert processed >= final["frames_processed"]  # earlier sessions of this module count too
    assert samples[("eyeserver_tracking_latency_seconds_count", ())] >= final["frames_processed"]
    assert samples[("eyeserver_tracking_running", ())] == 0


@pytest.mark.slow
def test_the_pose_stream_beats_when_there_is_nothing_to_send_and_status_shows_the_hold(
    base_url: str, tracking: TrackingControl, monkeypatch: pytest.MonkeyPatch
) -> None:
    with monkeypatch.context() as patched:
        # The first heartbeat is sent on connecting, not after the stream's silence.
        patched.setattr(tracking_routes, "HEARTBEAT_S", 3600.0)
        with _connect(base_url) as ws:
            first = _recv(ws)
    with _connect(base_url) as ws:
        _recv(ws)
        message = _recv(ws)  # nothing else to send: the next heartbeat after a second

    assert first["type"] == "heartbeat" and first["tracking"] is False
    assert first["beam_hold"] is True
    assert message["type"] == "heartbeat"
    assert message["tracking"] is False and message["beam_hold"] is True
    assert message["stalled"] is None and "time" in message
    summary = _get(base_url, "/status")["tracking"]
    assert summary == {"running": False, "beam_hold": True, "stalled": None}


class _ImageSource(ScriptedSource):
    """A scripted source whose frame ``n`` carries images of cameras S1 and S2 (12-bit, 64 ×
    48): S1 all at ``(16 n) mod 4096``, S2 a left-to-right ramp, so a preview tells which
    frame and camera it shows."""

    def next_frame(self) -> FrameSet | None:
        frame_set = super().next_frame()
        if frame_set is None:
            return None
        n = frame_set.frame
        images = {"S1": np.full((48, 64), (16 * n) % 4096, np.uint16),
                  "S2": np.tile(np.linspace(0, 4095, 64).astype(np.uint16), (48, 1))}
        frames = {c: Frame(image, FrameMeta(c, n, frame_set.t_ns, 2000.0, 0.0, 0, 12))
                  for c, image in images.items()}
        step = AcquiredStep(TriggerPulse(n, frame_set.t_ns, TriggerStep(("P1",), ("S1", "S2"))),
                            frames)
        return FrameSet(n, frame_set.t_ns, [step], data=frame_set.data)


@pytest.mark.slow
def test_the_preview_shows_the_tracked_units_newest_frame_and_says_why_not(
    base_url: str, tracking: TrackingControl
) -> None:
    def preview(camera: str) -> httpx.Response:
        return httpx.get(f"{base_url}{API}/tracking/preview/{camera}.jpg",
                         headers=auth(OPERATOR_TOKEN), timeout=TIMEOUT_S)

    idle = preview("S1")
    assert idle.status_code == 409
    assert idle.json() == {"detail": "no live tracking is running: a preview shows the frames "
                                     "of a tracking session"}
    assert httpx.get(f"{base_url}{API}/tracking/preview/S1.jpg").status_code == 401
    original = tracking.source_factory
    tracking.source_factory = lambda service, units, c: _ImageSource(c, pace_s=0.01)
    try:
        started = _post(base_url, "/tracking/start", {"patient_id": "P-T1", "fraction": 1})
        assert started.status_code == 201, started.text
        deadline = time.monotonic() + TIMEOUT_S
        while _get(base_url, "/tracking")["frames_acquired"] < 3:
            assert time.monotonic() < deadline, "no frames acquired"
            time.sleep(0.01)
        shown = [preview("S1") for _ in range(3)]
        ramp = preview("S2")
        unknown = preview("S9")
    finally:
        stopped = _post(base_url, "/tracking/stop")
        tracking.source_factory = original
    assert stopped.status_code == 200, stopped.text

    numbers = []
    for answer in shown:
        assert answer.status_code == 200 and answer.headers["content-type"] == "image/jpeg"
        assert answer.headers["cache-control"] == "no-store"
        image = cv2.imdecode(np.frombuffer(answer.content, np.uint8), cv2.IMREAD_UNCHANGED)
        assert image.shape == (48, 64) and image.dtype == np.uint8
        number = int(answer.headers["x-frame"])
        numbers.append(number)
        # 12 bits shown as 8: the frame's level over 16, within the JPEG's error.
        assert abs(float(image.mean()) - ((16 * number) % 4096) / 16) < 2.0
    assert numbers == sorted(numbers) and numbers[-1] <= stopped.json()["frames_acquired"]
    gradient = cv2.imdecode(np.frombuffer(ramp.content, np.uint8), cv2.IMREAD_UNCHANGED)
    assert gradient[:, :8].mean() < 20 and gradient[:, -8:].mean() > 235  # S2's own image
    assert unknown.status_code == 404
    assert unknown.json()["detail"] == "camera 'S9' is not one of the tracked unit's"
    assert preview("S1").status_code == 409  # stopped: no preview


def test_a_camera_image_becomes_a_small_grey_jpeg() -> None:
    image = np.tile(np.arange(1280, dtype=np.uint16) % 1024, (960, 1))  # 10 bits
    decoded = cv2.imdecode(np.frombuffer(camera_jpeg(image, bit_depth=10, max_side_px=640),
                                         np.uint8), cv2.IMREAD_UNCHANGED)
    assert decoded.shape == (480, 640)
    # Half size: column k averages source columns 2k, 2k + 1 of 1023; 10 bits shown as 8.
    assert decoded[:, 0].mean() < 3 and abs(decoded[:, 254].mean() - 127) < 3
    assert decoded[:, 510].mean() > 250
    with pytest.raises(ValueError, match="image"):
        camera_jpeg(np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(ValueError, match="bit_depth"):
        camera_jpeg(np.zeros((4, 4), np.uint16), bit_depth=4)


def test_tracking_with_two_workers_publishes_in_order(
    base_url: str, tracking: TrackingControl
) -> None:
    original, tracking.workers = tracking.workers, 2
    try:
        with _connect(base_url) as ws:
            started = _post(base_url, "/tracking/start", {"patient_id": "P-T1", "fraction": 1})
            assert started.status_code == 201, started.text
            assert started.json()["workers"] == 2
            messages = [_recv(ws) for _ in range(20)]
            stopped = _post(base_url, "/tracking/stop")
    finally:
        tracking.workers = original
    assert stopped.status_code == 200 and stopped.json()["error"] is None
    frames = [m["frame"] for m in messages if m["type"] == "pose"]
    assert len(frames) >= 10 and frames == sorted(set(frames))
    with pytest.raises(ValueError, match="workers"):
        TrackingControl(tracking.service, tracking.patients, workers=0)


def test_tracking_needs_an_operator_a_patient_and_a_reference(
    base_url: str, tracking: TrackingControl
) -> None:
    body = {"patient_id": "P-T1", "fraction": 1}
    assert httpx.post(f"{base_url}{API}/tracking/start", json=body).status_code == 401
    assert _post(base_url, "/tracking/start", {"patient_id": "P-none", "fraction": 1}
                 ).status_code == 404
    assert _post(base_url, "/tracking/start", {"patient_id": "P-T1", "fraction": 9}
                 ).status_code == 404
    assert _post(base_url, "/tracking/start", {"patient_id": "P-T1"}).status_code == 422
    assert _get(base_url, "/status")["state"] == "idle"


def test_tracking_against_a_planned_pose_needs_the_globes_shape(
    base_url: str, tracking: TrackingControl
) -> None:
    # Population defaults leave the globe's shape unknown: its centre is known only to
    # ±1.3 mm along the gaze against a planned (absolute) pose, so tracking is refused rather
    # than released on it; a reference captured at set-up with the same model would do.
    _planned_patient(base_url, "P-T2", "left")
    refused = _post(base_url, "/tracking/start", {"patient_id": "P-T2", "fraction": 1})
    assert refused.status_code == 409, refused.text
    reason = refused.json()["detail"]
    assert "the eye model leaves the globe's shape uncertain" in reason and "±1.30 mm" in reason
    assert "capture a reference at set-up" in reason
    assert _get(base_url, "/status")["state"] == "idle"
    # The MRI's ellipsoid with an MRI's typical error (0.2 mm a semi-axis, the default) still
    # leaves the centre's depth ±0.36 mm (2 sd): more than half the 0.2-mm tolerance.
    _planned_patient(base_url, "P-T3", "left", {"ellipsoid": {"semi_axes_mm": [12.1, 11.9, 12.4]}})
    refused = _post(base_url, "/tracking/start", {"patient_id": "P-T3", "fraction": 1})
    assert refused.status_code == 409, refused.text
    assert "±0.36 mm" in refused.json()["detail"]
    assert _get(base_url, "/status")["state"] == "idle"


@pytest.mark.parametrize("token", [None, "wrong-token"])
def test_the_pose_stream_closes_with_1008_without_a_valid_token(
    base_url: str, token: str | None
) -> None:
    with _connect(base_url, token) as ws, pytest.raises(ConnectionClosed) as closed:
        ws.recv(timeout=TIMEOUT_S)
    assert closed.value.rcvd is not None and closed.value.rcvd.code == 1008


@pytest.mark.slow
def test_twenty_clients_one_never_reading_all_others_get_every_message(
    base_url: str, tracking: TrackingControl
) -> None:
    frames, readers = 300, 19
    original = tracking.source_factory
    tracking.source_factory = lambda service, units, c: ScriptedSource(
        c, count=frames, pace_s=0.002)
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.connect(("127.0.0.1", int(base_url.rsplit(":", 1)[1])))
    stack = ExitStack()
    received: list[list[dict[str, Any]]] = [[] for _ in range(readers)]
    errors: list[BaseException] = []

    def read(index: int, ws: ClientConnection) -> None:
        try:
            while True:
                message = _recv(ws)
                if message["type"] == "heartbeat":
                    continue  # a second without messages (a slow start on a busy machine)
                received[index].append(message)
                if message.get("frame") == frames - 1:
                    return
        except BaseException as exc:
            errors.append(exc)

    try:
        silent = stack.enter_context(_connect(base_url, sock=sock, max_queue=1))
        clients = [stack.enter_context(_connect(base_url)) for _ in range(readers)]
        threads = [threading.Thread(target=read, args=(n, ws)) for n, ws in enumerate(clients)]
        for thread in threads:
            thread.start()
        started = _post(base_url, "/tracking/start", {"patient_id": "P-T1", "fraction": 1})
        assert started.status_code == 201, started.text
        for thread in threads:
            thread.join(TIMEOUT_S)
        _wait_state(base_url, "idle")  # the source ended: the session ended by itself
        status = _get(base_url, "/tracking")
        late = [_recv(silent)]
        while late[-1].get("frame") != frames - 1:
            late.append(_recv(silent))
    finally:
        stack.close()
        tracking.source_factory = original

    assert not errors, errors
    processed = status["frames_processed"]
    assert status["running"] is False and status["frames_acquired"] == frames
    assert processed + status["frames_dropped"] == frames
    first = received[0]
    for messages in received:
        assert [m["type"] for m in messages].count("dropped") == 0
        assert [m["frame"] for m in messages] == [m["frame"] for m in first]
        assert len(messages) == processed
        seqs = [m["seq"] for m in messages]
        assert seqs == list(range(seqs[0], seqs[0] + processed))
    # The silent client lost only its oldest messages, and was told how many.
    lost = sum(m["count"] for m in late if m["type"] == "dropped")
    assert lost + len([m for m in late if m["type"] == "pose"]) == processed
    assert late[-1]["frame"] == frames - 1


def test_one_blind_unit_is_not_tracked(tmp_path: Any, calibrated_rooms: Any) -> None:
    """A calibration whose units are blind to the fringe order (examples/rooms/blind.toml):
    tracking one unit alone is refused (409) with the reason before any frame, since only the
    other unit's images could fix its orders."""
    caldir = calibrated_rooms("blind")[1]
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for name in (CALIBRATION_FILE, ARRAYS_FILE):
            archive.writestr(name, (caldir / name).read_bytes())
    app = create_app(test_settings(tmp_path / "data"))
    with live_server(app) as base_url:
        physicist = auth(PHYSICIST_TOKEN)
        imported = httpx.post(f"{base_url}{API}/calibrations", content=buffer.getvalue(),
                              headers={"content-type": "application/zip", **physicist},
                              timeout=TIMEOUT_S)
        assert imported.status_code == 201, imported.text
        calibration = imported.json()["id"]
        assert httpx.post(f"{base_url}{API}/calibrations/{calibration}/activate",
                          headers=physicist, timeout=TIMEOUT_S).status_code == 200
        _planned_patient(base_url, "P-B1", "right", {
            "ellipsoid": {"semi_axes_mm": [12.1, 11.9, 12.4]}, "globe_sd_mm": 0.05})

        refused = _post(base_url, "/tracking/start", {"patient_id": "P-B1", "fraction": 1})

        assert refused.status_code == 409, refused.text
        assert "cannot track unit left alone" in refused.json()["detail"]
        assert "blind to the fringe order" in refused.json()["detail"]
        assert _get(base_url, "/tracking")["running"] is False
