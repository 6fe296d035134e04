"""Array helpers the layers share where NumPy's own call is measurably slow."""

from __future__ import annotations

import math
from typing import TypeVar

import cv2
import numpy as np
import numpy.typing as npt

__all__ = ["ANGLE_ERROR_RAD", "angle", "column_range", "distances", "rows_where", "wrap"]

ScalarT = TypeVar("ScalarT", bound=np.generic)
FloatArrayT = TypeVar("FloatArrayT", bound=npt.NDArray[np.floating])


def column_range(array: npt.NDArray[ScalarT]) -> tuple[npt.NDArray[ScalarT],
                                                       npt.NDArray[ScalarT]]:
    """Each column's least and largest value of an (N, C) array with N ≥ 1, as two (C,) arrays.

    Column by column because NumPy's reduction along the first axis of a tall, narrow array is
    many times slower (measured: docs/notes/speed.md).
    """
    columns = range(array.shape[1])
    low: npt.NDArray[ScalarT] = np.array([array[:, c].min() for c in columns], array.dtype)
    high: npt.NDArray[ScalarT] = np.array([array[:, c].max() for c in columns], array.dtype)
    return low, high


def distances(points: npt.NDArray[np.floating], centre: npt.ArrayLike | None = None,
              ) -> npt.NDArray[np.float64]:
    """Each row's Euclidean length of the ``(N, C)`` ``points`` less ``centre`` (or of the rows
    themselves): ``np.linalg.norm(points − centre, axis=1)``, to the bit.

    Column by column: NumPy's norm along the short axis took 0.9 ms for 20,000 points of three
    coordinates on this machine, this 0.07 (docs/notes/speed.md).
    """
    total = np.zeros(len(points))
    offsets = None if centre is None else np.asarray(centre, dtype=np.float64)
    for column in range(points.shape[1]):
        part = points[:, column] if offsets is None else points[:, column] - offsets[column]
        total += part * part
    return np.sqrt(total, out=total)


ANGLE_ERROR_RAD = 2e-4
"""Largest error of :func:`angle` against a float64 ``arctan2``, rad (measured 1.7e-4 with
OpenCV 4.x's polynomial; ``tests/test_demodulate.py`` holds it to this bound)."""


def angle(y: npt.ArrayLike, x: npt.ArrayLike, *, centred: bool = True) -> npt.NDArray[np.float32]:
    """The angle of the vectors ``(x, y)``, float32 radians, in ``[−π, π]`` (``centred``) or
    ``[0, 2π)``; the shape of ``y``, which ``x`` must share.

    ``cv2.phase``, a vectorised polynomial within :data:`ANGLE_ERROR_RAD` of the exact angle,
    in place of ``np.arctan2``: NumPy's float32 ``arctan2`` is not vectorised on this machine
    (AVX2) and took 5 of a 640 × 512 demodulation's 10 ms, cv2.phase 0.2 (docs/notes/speed.md).
    The error is some 30 times below the phase noise of an 8-bit fringe image.
    """
    y32 = np.ascontiguousarray(y, dtype=np.float32)
    x32 = np.ascontiguousarray(x, dtype=np.float32)
    if y32.shape != x32.shape:
        raise ValueError(f"x and y must have the same shape, not {x32.shape} and {y32.shape}")
    if y32.size == 0:
        return np.zeros(y32.shape, np.float32)
    # OpenCV takes 2-D matrices: a flat view of any shape, and its shape back.
    flat_x, flat_y = x32.reshape(-1, 1), y32.reshape(-1, 1)
    result = np.asarray(cv2.phase(flat_x, flat_y), dtype=np.float32)
    if centred:
        # 2π where the angle passes π, taken off: cv2's threshold and subtraction, since
        # NumPy's masked subtraction (``where=``) took ten times as long here.
        turn = cv2.threshold(result, math.pi, 2 * math.pi, cv2.THRESH_BINARY)[1]
        cv2.subtract(result, turn, dst=result)
    return result.reshape(y32.shape)


def wrap(phase: FloatArrayT) -> FloatArrayT:
    """``phase`` (radians, a float array) wrapped into ``[−π, π]`` in place by taking whole
    turns off, and returned, in its own precision: the angle of ``exp(i·phase)`` to 1e-15 rad
    in float64, where NumPy's complex exponential and angle took 70 times as long, and
    ``np.mod`` on float32 ten times (docs/notes/speed.md)."""
    turns = np.rint(phase * (0.5 / math.pi))
    turns *= 2.0 * math.pi
    phase -= turns
    return phase


def rows_where(array: npt.NDArray[ScalarT], keep: npt.NDArray[np.bool_]) -> npt.NDArray[ScalarT]:
    """The rows of ``array`` where the boolean ``keep`` (one per row) holds: ``array[keep]``.

    By ``np.compress``: NumPy's boolean indexing of a tall, narrow array took 2.8 ms for
    155,000 rows of three float64 on this machine, ``np.compress`` 0.45 (docs/notes/speed.md).
    """
    if keep.dtype != np.bool_ or keep.shape != array.shape[:1]:
        # (np.compress would take indices as flags and a short mask as cut short: silently.)
        raise ValueError(f"keep must hold one boolean flag per row: {keep.dtype} {keep.shape} "
                         f"for {array.shape}")
    return np.compress(keep, array, axis=0)
