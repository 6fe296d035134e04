"""Seedable eye motion: fixational drift, micro-saccades, blinks and scripted events.

The state at time ``t`` is a pure function of the seed and ``t`` (random events are drawn per
10-second window from a generator seeded by the window's index), so a render at a given time is
reproducible whatever order the times are asked in, and a test can drive it with a manual clock.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Annotated, Literal

import numpy as np
from pydantic import ConfigDict, Field

from eyeserver.core.validation import NumbersOnly

_WINDOW_S = 10.0


GazeAngle = Annotated[float, Field(ge=-60.0, le=60.0)]
"""A gaze angle (degrees): beyond ±60° the cornea is not in the cameras' view."""

HeadShift = Annotated[float, Field(ge=-30.0, le=30.0)]
"""A head offset (mm): the eye stays within the cameras' shared view."""

MAX_SCRIPT_EVENTS = 1000


class ScriptEvent(NumbersOnly):
    """One scripted event: a gaze shift (saccade) or a blink starting at ``t_s``."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    t_s: Annotated[float, Field(ge=0, le=86_400)]
    kind: Literal["saccade", "blink", "shift"]
    gaze_deg: tuple[GazeAngle, GazeAngle] = Field(
        (0.0, 0.0), description="saccade target (yaw, pitch) relative to the base gaze")
    shift_mm: tuple[HeadShift, HeadShift, HeadShift] = Field(
        (0.0, 0.0, 0.0), description="'shift': new head offset relative to the base position")
    duration_s: Annotated[float, Field(gt=0, le=60)] = 0.03


class MotionSpec(NumbersOnly):
    """How the simulated eye moves. All zero rates and no script: a still eye.

    Every number is finite and bounded (an eye's rates and amplitudes, with room to spare): an
    unbounded saccade rate held memory for every saccade time, an infinite one broke every
    capture until the scene was replaced (issue 35).
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    seed: Annotated[int, Field(ge=0, le=2**53)] = 0
    drift_deg: Annotated[float, Field(ge=0, le=5, description="RMS fixational drift")] = 0.05
    saccade_rate_hz: Annotated[float, Field(ge=0, le=10)] = 1.0
    saccade_amplitude_deg: Annotated[float, Field(ge=0, le=30)] = 0.3
    blink_rate_hz: Annotated[float, Field(ge=0, le=2)] = 0.0
    blink_duration_s: Annotated[float, Field(gt=0, le=5)] = 0.25
    script: list[ScriptEvent] = Field(default_factory=list, max_length=MAX_SCRIPT_EVENTS)


@dataclass(frozen=True)
class MotionState:
    """Eye-in-head gaze offset (degrees), head offset (mm) and lid openness (0 closed … 1 open)."""

    gaze_offset_deg: tuple[float, float]
    head_offset_mm: tuple[float, float, float]
    openness: float


def _smoothstep(x: float) -> float:
    x = min(max(x, 0.0), 1.0)
    return x * x * (3 - 2 * x)


def _blink_openness(since_start: float, duration: float) -> float:
    # Lids close fast (30 % of the blink), stay shut briefly (15 %), reopen more slowly.
    if since_start < 0 or since_start >= duration:
        return 1.0
    x = since_start / duration
    if x < 0.3:
        return 1.0 - _smoothstep(x / 0.3)
    if x < 0.45:
        return 0.0
    return _smoothstep((x - 0.45) / 0.55)


@lru_cache(maxsize=256)
def _window_events(seed: int, window: int, saccade_rate: float, saccade_amp: float,
                   blink_rate: float) -> tuple[tuple[tuple[float, float, float], ...],
                                               tuple[float, ...]]:
    rng = np.random.default_rng([seed, window, 0x5ACC])
    n_sacc = rng.poisson(saccade_rate * _WINDOW_S)
    times = np.sort(rng.uniform(0, _WINDOW_S, n_sacc)) + window * _WINDOW_S
    # A micro-saccade re-fixates: its landing point scatters about the fixation target.
    angles = rng.uniform(0, 2 * math.pi, n_sacc)
    radii = saccade_amp * np.sqrt(rng.uniform(0, 1, n_sacc))
    saccades = tuple((float(t), float(r * math.cos(a)), float(r * math.sin(a)))
                     for t, a, r in zip(times, angles, radii, strict=True))
    n_blink = rng.poisson(blink_rate * _WINDOW_S)
    blinks = tuple(float(t) for t in np.sort(rng.uniform(0, _WINDOW_S, n_blink))
                   + window * _WINDOW_S)
    return saccades, blinks


BLUR_STEP_MM = 0.05
"""Furthest the eye's surface moves between two of an exposure's sub-renders (mm): about a
pixel at the eye on the default rig, so the sum of sub-renders is as smooth as the motion blur
it stands for once the lens's own blur is added."""

MAX_SUBEXPOSURES = 16
"""Most sub-renders an exposure is made of (a 10-ms exposure in the middle of a 5° saccade
travels ≈ 0.6 mm at the cornea: 12 sub-renders)."""

SURFACE_LEVER_MM = 13.0
"""Distance from the eye's centre of rotation to the corneal apex (mm, Gullstrand's eye):
how far a turn of the gaze moves the front of the eye."""

LID_TRAVEL_MM = 10.0
"""The upper lid's travel from open to shut (mm; the palpebral fissure's height)."""

_BLUR_PROBES = 9
"""Times within an exposure at which the eye's state is probed for its travel."""


class EyeMotion:
    """Evaluate a :class:`MotionSpec` at any time."""

    def __init__(self, spec: MotionSpec) -> None:
        self.spec = spec
        rng = np.random.default_rng([spec.seed, 0xD21F7])
        # Drift: a few slow sinusoids per axis with random phases, scaled to the RMS asked for.
        self._drift_freq = rng.uniform(0.05, 0.6, size=(2, 3))
        self._drift_phase = rng.uniform(0, 2 * math.pi, size=(2, 3))
        self._drift_amp = spec.drift_deg * math.sqrt(2.0 / 3.0)

    def _events(self, window: int) -> tuple[tuple[tuple[float, float, float], ...],
                                            tuple[float, ...]]:
        s = self.spec
        return _window_events(s.seed, window, s.saccade_rate_hz, s.saccade_amplitude_deg,
                              s.blink_rate_hz)

    def state(self, t_s: float) -> MotionState:
        """The eye's state at ``t_s`` seconds."""
        s = self.spec
        drift = self._drift_amp * np.sum(
            np.sin(2 * math.pi * self._drift_freq * t_s + self._drift_phase), axis=1)
        gaze = [float(drift[0]), float(drift[1])]

        # Random micro-saccades: the latest one that has started sets the landing offset,
        # blended from the one before over 25 ms.
        window = math.floor(t_s / _WINDOW_S) if t_s >= 0 else -1
        history: list[tuple[float, float, float]] = []
        for w in range(window, max(window - 3, -1), -1):
            history = [e for e in self._events(w)[0] if e[0] <= t_s] + history
            if len(history) >= 2:
                break
        if history:
            t0, yaw, pitch = history[-1]
            prev = history[-2][1:] if len(history) > 1 else (0.0, 0.0)
            blend = _smoothstep((t_s - t0) / 0.025)
            gaze[0] += prev[0] + (yaw - prev[0]) * blend
            gaze[1] += prev[1] + (pitch - prev[1]) * blend

        openness = 1.0
        for w in (window - 1, window):
            if w < 0:
                continue
            for tb in self._events(w)[1]:
                openness = min(openness, _blink_openness(t_s - tb, s.blink_duration_s))

        # Scripted events override: saccades set the gaze target, shifts move the head.
        script_gaze = (0.0, 0.0)
        head = (0.0, 0.0, 0.0)
        prev_gaze = (0.0, 0.0)
        prev_head = (0.0, 0.0, 0.0)
        for event in sorted(s.script, key=lambda e: e.t_s):
            if event.t_s > t_s:
                break
            blend = _smoothstep((t_s - event.t_s) / event.duration_s)
            if event.kind == "saccade":
                prev_gaze = script_gaze
                script_gaze = tuple(p + (g - p) * blend  # type: ignore[assignment]
                                    for p, g in zip(prev_gaze, event.gaze_deg, strict=True))
            elif event.kind == "shift":
                prev_head = head
                head = tuple(p + (g - p) * blend  # type: ignore[assignment]
                             for p, g in zip(prev_head, event.shift_mm, strict=True))
            else:
                openness = min(openness, _blink_openness(t_s - event.t_s, event.duration_s))
        return MotionState(gaze_offset_deg=(gaze[0] + script_gaze[0], gaze[1] + script_gaze[1]),
                           head_offset_mm=head, openness=openness)

    def sub_exposures(self, t_mid_s: float, exposure_s: float) -> tuple[float, ...]:
        """Times (seconds) of the sub-renders whose mean is an exposure of ``exposure_s``
        centred at ``t_mid_s``, so that the eye's motion within it blurs the image as it blurs
        a camera's: equal slices of the exposure, one per :data:`BLUR_STEP_MM` of the surface's
        travel (the gaze's turn at :data:`SURFACE_LEVER_MM`, the head's shift and the lid's
        closing, summed over the exposure), at most :data:`MAX_SUBEXPOSURES`; ``(t_mid_s,)``
        alone where the eye moves less than that (drift and micro-saccades within a 10-ms
        exposure)."""
        start = t_mid_s - exposure_s / 2
        states = [self.state(t) for t in np.linspace(start, start + exposure_s, _BLUR_PROBES)]
        travel = 0.0
        for a, b in itertools.pairwise(states):
            turn = math.hypot(b.gaze_offset_deg[0] - a.gaze_offset_deg[0],
                              b.gaze_offset_deg[1] - a.gaze_offset_deg[1])
            shift = math.dist(a.head_offset_mm, b.head_offset_mm)
            travel += (math.radians(turn) * SURFACE_LEVER_MM + shift
                       + abs(b.openness - a.openness) * LID_TRAVEL_MM)
        count = min(MAX_SUBEXPOSURES, math.ceil(travel / BLUR_STEP_MM))
        if count <= 1:
            return (t_mid_s,)
        return tuple(start + (k + 0.5) * exposure_s / count for k in range(count))
