"""eyeserver.core.arrays: NumPy's own calls, faster, with the same answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from eyeserver.core.arrays import distances, rows_where, wrap


def test_whole_turns_wrap_as_the_complex_exponentials_angle() -> None:
    """``core.arrays.wrap`` (the demodulation, the order checks and the phase-to-height
    calibration's walk along Z) gives the angle of exp(i·φ) in place, float32 and float64
    alike, over many turns."""
    rng = np.random.default_rng(3)
    phase = rng.uniform(-200.0, 200.0, 100_000)
    exact = np.angle(np.exp(1j * phase))
    away = np.abs(np.abs(exact) - math.pi) > 1e-9  # ±π itself may come out either way
    same = phase.copy()
    assert wrap(same) is same
    assert np.abs(same - exact)[away].max() < 1e-12
    assert np.abs(same).max() <= math.pi
    single = phase.astype(np.float32)
    wrap(single)
    assert single.dtype == np.float32
    assert np.abs(np.angle(np.exp(1j * (single.astype(np.float64) - exact)))).max() < 1e-4


def test_distances_are_numpys_row_norms_to_the_bit() -> None:
    """``distances`` (the eye fit's and the tracker's distances from a centre) gives exactly
    ``np.linalg.norm(points − centre, axis=1)``, with or without a centre, any column count."""
    rng = np.random.default_rng(4)
    points = rng.normal(0.0, 12.0, (5000, 3))
    centre = np.array([0.4, -1.2, -10.0])
    assert np.array_equal(distances(points, centre), np.linalg.norm(points - centre, axis=1))
    assert np.array_equal(distances(points), np.linalg.norm(points, axis=1))
    flat = points[:, :2].copy()
    assert np.array_equal(distances(flat, [1.0, 2.0]), np.linalg.norm(flat - [1.0, 2.0], axis=1))
    assert distances(np.zeros((0, 3)), centre).shape == (0,)


def test_rows_where_is_boolean_indexing_and_refuses_a_mask_of_another_length() -> None:
    """``rows_where`` (the clouds' subsets) keeps the same rows as ``array[keep]``; a mask that
    does not give one boolean flag per row is an error, not np.compress's silent truncation or
    indices taken for flags."""
    rng = np.random.default_rng(5)
    points = rng.random((1000, 3))
    keep = rng.random(1000) < 0.7
    assert np.array_equal(rows_where(points, keep), points[keep])
    assert np.array_equal(rows_where(keep, keep), keep[keep])
    with pytest.raises(ValueError, match="one boolean flag per row"):
        rows_where(points, keep[:-1])
    with pytest.raises(ValueError, match="one boolean flag per row"):
        rows_where(points, keep.astype(np.int64))
