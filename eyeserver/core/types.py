"""Type aliases the layers share: numpy arrays by dtype, and the progress callback (with its
silent default).

Defined once here, at the bottom layer, so that the pipeline, the calibration, the simulated room,
the service and the benches all annotate with the same names.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeAlias

import numpy as np
import numpy.typing as npt

__all__ = ["F32", "F64", "Bool", "Image", "Progress", "quiet"]

F32: TypeAlias = npt.NDArray[np.float32]
"""A float32 array (per-pixel images of phase, modulation, brightness: half float64's memory)."""

F64: TypeAlias = npt.NDArray[np.float64]
"""A float64 array (geometry, fits and anything else that needs the precision)."""

Bool: TypeAlias = npt.NDArray[np.bool_]
"""A boolean array: a mask per pixel or per point."""

Image: TypeAlias = npt.NDArray[np.uint8] | npt.NDArray[np.uint16]
"""A single-channel camera image of shape ``(height, width)``: uint8, or uint16 holding 10 or 12
significant bits unshifted."""

Progress: TypeAlias = Callable[[str], None]
"""Where a long procedure reports what it is doing, one short message at a time (the command
line prints them time-stamped on stderr: :func:`eyeserver.commands.progress`)."""


def quiet(_: str) -> None:
    """A :data:`Progress` that reports nothing: the default where nobody is listening."""
