"""Fusion of camera clouds: seam conflicts between units, quality and region crops."""

from __future__ import annotations

import numpy as np
import pytest

from eyeserver.core.arrays import column_range
from eyeserver.pipeline.fusion import Part, Region, fuse


def _grid(z: float, n: int = 40, spacing: float = 0.1) -> np.ndarray:
    x, y = np.meshgrid(np.arange(n) * spacing, np.arange(n) * spacing)
    return np.stack([x.ravel(), y.ravel(), np.full(x.size, z)], axis=1)


def test_units_agreeing_are_kept_whole() -> None:
    a, b = _grid(1.0), _grid(1.02) + np.array([0.05, 0.05, 0.0])
    fused = fuse([Part(a, np.full(len(a), 0.9, np.float32), 0, "left"),
                  Part(b, np.full(len(b), 0.8, np.float32), 2, "right")])
    assert len(fused.points) == len(a) + len(b)
    assert fused.dropped_seam == 0
    assert set(np.unique(fused.camera)) == {0, 2}


def test_a_unit_a_fringe_off_loses_where_it_is_the_weaker() -> None:
    good, wrong = _grid(1.0), _grid(6.0) + np.array([0.05, 0.05, 0.0])
    fused = fuse([Part(good, np.full(len(good), 0.9, np.float32), 0, "left"),
                  Part(wrong, np.full(len(wrong), 0.5, np.float32), 2, "right")])
    assert fused.dropped_seam == len(wrong)
    assert np.all(fused.camera == 0)
    # Points of one unit are never checked against each other.
    same_unit = fuse([Part(good, np.ones(len(good), np.float32), 0, "left"),
                      Part(wrong, np.ones(len(wrong), np.float32), 1, "left")])
    assert same_unit.dropped_seam == 0


def test_quality_and_region_crops() -> None:
    points = _grid(2.0)
    quality = np.linspace(0, 1, len(points)).astype(np.float32)
    fused = fuse([Part(points, quality, 1, "left")], min_quality=0.5,
                 region=Region((0.0, 0.0, 0.0), (2.0, 4.0, 3.0)))
    assert fused.quality.min() >= 0.5
    assert fused.points[:, 0].max() <= 2.0
    assert fused.dropped_quality == int(np.sum(quality < 0.5))
    assert len(fused.points) + fused.dropped_quality + fused.dropped_region == len(points)


def test_bad_input_is_named() -> None:
    with pytest.raises(ValueError, match="below high"):
        Region((0.0, 0.0, 5.0), (1.0, 1.0, 1.0))
    with pytest.raises(ValueError, match="min_quality"):
        fuse([], min_quality=2.0)
    with pytest.raises(ValueError, match="quality"):
        fuse([Part(np.zeros((3, 3)), np.zeros(2, np.float32), 0, "left")])


def test_seams_are_found_wherever_the_clouds_lie() -> None:
    """The cells are counted from the clouds' least corner: clouds at negative X and Y (the
    room's other side) and one wrong point far off are binned as those at the origin."""
    shift = np.array([-7.3, -3.1, 0.0])
    good, wrong = _grid(1.0) + shift, _grid(6.0) + shift + np.array([0.05, 0.05, 0.0])
    stray = np.array([[-40.0, 25.0, 6.0]])
    fused = fuse([Part(good, np.full(len(good), 0.9, np.float32), 0, "left"),
                  Part(np.vstack([wrong, stray]), np.full(len(wrong) + 1, 0.5, np.float32), 2,
                       "right")])
    assert fused.dropped_seam == len(wrong)
    assert fused.points[-1].tolist() == stray[0].tolist()


def test_column_range_is_each_columns_least_and_largest() -> None:
    values = np.array([[3, -1, 7], [-2, 5, 7], [0, 0, 9]], np.int64)
    low, high = column_range(values)
    assert low.tolist() == [-2, -1, 7] and high.tolist() == [3, 5, 9]
    assert low.dtype == np.int64
