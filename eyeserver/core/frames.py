"""What a camera hands over for one exposure."""

from __future__ import annotations

import re
from dataclasses import dataclass, field

from eyeserver.core.types import Image

ID_PATTERN = re.compile(r"^[A-Za-z0-9_-]+$")
"""Device and unit ids: short strings of letters, digits, ``-`` and ``_`` (FORMATS.md)."""


def is_valid_id(value: str) -> bool:
    """True when ``value`` is a legal device or unit id."""
    return bool(ID_PATTERN.fullmatch(value)) and len(value) <= 64


@dataclass(frozen=True)
class FrameMeta:
    """Metadata of one camera exposure.

    Attributes
    ----------
    camera_id : str
        The camera that delivered the frame.
    frame_counter : int
        The camera's own count of frames delivered since ``open()``, starting at 0.
    t_ns : int
        Mid-exposure time in nanoseconds on the rig's monotonic clock.
    exposure_us : float
        Exposure time actually used, microseconds.
    gain_db : float
        Analogue gain actually used, decibels.
    dropped_frames : int
        Frames the camera has dropped since ``open()`` (cumulative), so a consumer sees gaps.
    bit_depth : int
        Significant bits per pixel (8, 10 or 12); 10 and 12 bits come unshifted in uint16.
    projectors_on : tuple of str
        Projectors lit during this exposure.
    trigger_index : int
        Index of the trigger pulse that started the exposure.
    """

    camera_id: str
    frame_counter: int
    t_ns: int
    exposure_us: float
    gain_db: float
    dropped_frames: int
    bit_depth: int
    projectors_on: tuple[str, ...] = ()
    trigger_index: int = 0


@dataclass(frozen=True)
class Frame:
    """One image (``uint8`` or ``uint16``, shape ``(height, width)``) with its metadata."""

    image: Image
    meta: FrameMeta
    extra: dict[str, object] = field(default_factory=dict)
