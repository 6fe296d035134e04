"""Array helpers the layers share where NumPy's own call is measurably slow."""

from __future__ import annotations

from typing import TypeVar

import numpy as np
import numpy.typing as npt

__all__ = ["column_range"]

ScalarT = TypeVar("ScalarT", bound=np.generic)


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
