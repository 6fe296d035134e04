"""The beam-hold flag of live tracking: pure, clock-free and deterministic.

One :class:`BeamHold` follows one tracking run. Each processed frame is given to
:meth:`BeamHold.update` as a :class:`FrameObservation` (its camera frame number, whether the eye
was seen, blinking or lost, whether the pose was in tolerance, the fit's confidence), and the
answer says whether the beam must be held on that frame and why::

    rises at once            falls only after `dwell_frames` good frames in a row
    ─────────────────►  hold  ──────────────────────────────────────────────────►  beam on
      out of tolerance, blink, eye lost, confidence < min_confidence, a long gap,
      silence (:meth:`BeamHold.interrupt`)

A frame is *good* when the eye is visible, in tolerance and fitted with at least
``min_confidence``. The hold starts raised (nothing has been seen yet). The hold follows the
eye, not the scheduler. Frame numbers come from the cameras: a gap between two processed frames
means frames went unprocessed (dropped for a newer one, or camera periods missed); they are
always counted (:attr:`BeamDecision.dropped_frames`, never skipped silently). A gap of up to
``max_gap_frames`` (default 2: 80 ms at 25 Hz, in which an eye at rest moves micrometres) keeps
the flag as the frames say; a longer one, with ``hold_on_drop`` (default), is treated as
unseen: the hold rises and the dwell starts again, since the eye could have moved meanwhile
(held on every gap, the beam flipped with the scheduler: docs/notes/hardening.md). Silence
without any frame is the caller's to notice (it has the
clock): :meth:`BeamHold.interrupt` raises the hold and restarts the dwell. Nothing here reads a
clock, so tests replay any sequence exactly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

__all__ = ["BeamDecision", "BeamHold", "BeamHoldConfig", "EyeSeen", "FrameObservation",
           "HoldReason"]

EyeSeen = Literal["visible", "blink", "lost"]
HoldReason = Literal["start", "out_of_tolerance", "blink", "lost", "low_confidence", "dropped",
                     "dwell"]


@dataclass(frozen=True)
class BeamHoldConfig:
    """How the hold behaves.

    Attributes
    ----------
    dwell_frames : int
        Good frames in a row (the current one included) before the hold falls; at least 1.
    min_confidence : float
        A fit less confident than this (0…1) holds the beam.
    hold_on_drop : bool
        Whether a gap of more than ``max_gap_frames`` unprocessed frames raises the hold and
        restarts the dwell.
    max_gap_frames : int
        Unprocessed frames between two processed ones that do not hold the beam (≥ 0; 0
        holds on every gap).
    """

    dwell_frames: int = 3
    min_confidence: float = 0.5
    hold_on_drop: bool = True
    max_gap_frames: int = 2

    def __post_init__(self) -> None:
        if isinstance(self.dwell_frames, bool) or not isinstance(self.dwell_frames, int) \
                or self.dwell_frames < 1:
            raise ValueError(f"dwell_frames must be an integer of at least 1, not "
                             f"{self.dwell_frames!r}")
        if isinstance(self.max_gap_frames, bool) or not isinstance(self.max_gap_frames, int) \
                or self.max_gap_frames < 0:
            raise ValueError(f"max_gap_frames must be an integer of at least 0, not "
                             f"{self.max_gap_frames!r}")
        if not 0.0 <= self.min_confidence <= 1.0:
            raise ValueError(f"min_confidence must be within 0…1, not {self.min_confidence!r}")


@dataclass(frozen=True)
class FrameObservation:
    """What tracking made of one processed frame.

    Attributes
    ----------
    frame : int
        The camera frame number (increasing by one per camera frame).
    eye : {"visible", "blink", "lost"}
        Whether the eye was seen, hidden by the lids, or not found.
    in_tolerance : bool
        Whether the pose was within the patient's tolerances (ignored unless visible).
    confidence : float
        The fit's confidence, 0…1 (ignored unless visible; NaN counts as too low).
    """

    frame: int
    eye: EyeSeen
    in_tolerance: bool = False
    confidence: float = 0.0


@dataclass(frozen=True)
class BeamDecision:
    """The flag for one processed frame.

    Attributes
    ----------
    frame : int
        The frame it is for.
    beam_hold : bool
        True: the beam must not be on.
    reasons : tuple of HoldReason
        Why it is held (empty when not): what is wrong with this frame, ``dropped`` when more
        than ``max_gap_frames`` went unprocessed just before it, ``dwell`` while good frames
        are still being counted, ``start`` before the first frame.
    good_frames : int
        Good frames in a row up to and including this one.
    dropped_frames : int
        Frames dropped since tracking started (gaps between processed frames).
    dropped_now : int
        Frames dropped just before this one.
    """

    frame: int
    beam_hold: bool
    reasons: tuple[HoldReason, ...]
    good_frames: int
    dropped_frames: int
    dropped_now: int


class BeamHold:
    """The beam-hold state machine of one tracking run (see the module docstring)."""

    def __init__(self, config: BeamHoldConfig | None = None) -> None:
        self.config = config or BeamHoldConfig()
        self._last_frame: int | None = None
        self._good = 0
        self._dropped = 0
        self._hold = True

    @property
    def beam_hold(self) -> bool:
        """The flag after the last frame (True before the first)."""
        return self._hold

    @property
    def dropped_frames(self) -> int:
        """Frames dropped so far."""
        return self._dropped

    def interrupt(self) -> None:
        """Raise the hold and restart the dwell without a frame: no processed frame came in
        time (the caller's deadline), so the eye is unseen until good frames come again."""
        self._hold = True
        self._good = 0

    def update(self, seen: FrameObservation) -> BeamDecision:
        """Take one processed frame; frames must come in increasing order.

        Raises
        ------
        ValueError
            ``seen.frame`` is not after the previous frame.
        """
        config = self.config
        dropped_now = 0
        if self._last_frame is not None:
            if seen.frame <= self._last_frame:
                raise ValueError(f"frame {seen.frame} does not follow frame {self._last_frame}")
            dropped_now = seen.frame - self._last_frame - 1
        self._last_frame = seen.frame
        self._dropped += dropped_now
        reasons: list[HoldReason] = []
        if dropped_now > config.max_gap_frames and config.hold_on_drop:
            reasons.append("dropped")
            self._good = 0
        if seen.eye != "visible":
            reasons.append(seen.eye)
        else:
            if not seen.in_tolerance:
                reasons.append("out_of_tolerance")
            if not (math.isfinite(seen.confidence)
                    and seen.confidence >= config.min_confidence):
                reasons.append("low_confidence")
        bad = [r for r in reasons if r != "dropped"]
        self._good = 0 if bad else self._good + 1
        if not reasons and self._good < config.dwell_frames:
            reasons.append("dwell")
        # The `dropped` reason with a good frame restarts the dwell at this frame.
        self._hold = bool(reasons)
        return BeamDecision(seen.frame, self._hold, tuple(reasons), self._good, self._dropped,
                            dropped_now)
