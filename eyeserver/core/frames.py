"""What a camera hands over for one exposure."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from eyeserver.core.types import Image

ID_PATTERN = re.compile(r"^[A-Za-z0-9_-]+$")
"""Device and unit ids: short strings of letters, digits, ``-`` and ``_`` (FORMATS.md)."""


def grey(image: npt.NDArray[Any]) -> npt.NDArray[np.float32]:
    """A colour image ``(H, W, 3)`` or ``(H, W, 4)`` as grey: the mean of its three colour
    channels, the fourth (alpha) ignored. The mean, not a luminance weighting: the fringe of a
    white or near-infrared projector is in every channel, and the mean is the same whatever
    their order (OpenCV's BGR or RGB)."""
    colour: npt.NDArray[np.float32] = np.asarray(image[..., :3], dtype=np.float32)
    return np.asarray(colour.mean(axis=2), dtype=np.float32)


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
