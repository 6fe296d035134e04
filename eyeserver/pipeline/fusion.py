"""Fusion of the cameras' point clouds into one (docs/design.md §4 step 7), and a region of
interest.

Every camera's cloud is in the WCS already, so fusion is a union that keeps, per point, its
quality and the camera it came from. Two things need care:

* **Seams between units.** The paper's largest errors (1.0–1.5 mm) sat where the two units'
  clouds meet. Each unit's points are checked against the other units' surfaces: where another
  unit has a point in the same :data:`SEAM_RADIUS_MM` cell of X, Y but at a height more than
  :data:`SEAM_TOLERANCE_MM` away, the two disagree by a fringe order (a unit can take a wrong
  order consistently in both its cameras, e.g. on a surface beyond the calibrated volume) and
  the lower-quality side's point is dropped.
* **Quality.** Points below a quality threshold are dropped; the rest keep their quality so a
  consumer (the eye model's fit) can weight them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from eyeserver.core.arrays import column_range, rows_where
from eyeserver.core.types import F32, F64

SEAM_RADIUS_MM = 0.25
"""Another unit's point in the same X, Y cell of this size describes the same part of the
surface."""
SEAM_TOLERANCE_MM = 1.0
"""Heights of the same surface point from two units differ by hundredths of a mm; a wrong fringe
order by a fringe's depth (≈ 5 mm on the default rig)."""


@dataclass(frozen=True)
class Region:
    """An axis-aligned box in the WCS, mm (``low`` and ``high`` corners, inclusive)."""

    low: tuple[float, float, float]
    high: tuple[float, float, float]

    def __post_init__(self) -> None:
        if len(self.low) != 3 or len(self.high) != 3:
            raise ValueError("low and high must be (x, y, z) triples")
        if not all(np.isfinite(self.low)) or not all(np.isfinite(self.high)):
            raise ValueError("low and high must be finite")
        if any(lo >= hi for lo, hi in zip(self.low, self.high, strict=True)):
            raise ValueError(f"low {self.low} must be below high {self.high} on every axis")

    def contains(self, points: npt.ArrayLike) -> npt.NDArray[np.bool_]:
        """Which of ``points`` (N, 3) lie inside."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        return np.asarray(np.all((p >= self.low) & (p <= self.high), axis=1))


@dataclass
class Part:
    """One camera's contribution: WCS points, quality in [0, 1], the camera's index in the rig,
    and the unit it belongs to (points of one unit are not checked against each other)."""

    points: F64
    quality: F32
    camera: int
    unit: str


@dataclass
class Fused:
    """The fused cloud and how many points each check removed."""

    points: F64
    quality: F32
    camera: npt.NDArray[np.uint8]
    dropped_seam: int
    dropped_quality: int
    dropped_region: int


def seam_conflicts(parts: Sequence[Part]) -> list[npt.NDArray[np.bool_]]:
    """Per part, which points another unit's surface contradicts and that unit's point there is
    of higher quality (see the module docstring).

    The other units' points are binned on an X, Y grid of :data:`SEAM_RADIUS_MM` cells, each
    cell keeping one point's height and quality; a point is compared with its own cell. (A
    k-d tree did the same in 0.3 s for a 4-camera frame-set, most of its time; the grid takes
    a few milliseconds.)
    """
    conflicts = [np.zeros(len(p.points), bool) for p in parts]
    units = sorted({p.unit for p in parts})
    if len(units) < 2 or not any(len(p.points) for p in parts):
        return conflicts
    ranges = [column_range(p.points[:, :2]) for p in parts if len(p.points)]
    low = np.min([r[0] for r in ranges], axis=0)
    high = np.max([r[1] for r in ranges], axis=0)
    columns = int((high[1] - low[1]) / SEAM_RADIUS_MM) + 1
    size = (int((high[0] - low[0]) / SEAM_RADIUS_MM) + 1) * columns
    # Each part's cell once (its coordinates are at least ``low``: truncation is the floor).
    cells = [((p.points[:, 0] - low[0]) * (1 / SEAM_RADIUS_MM)).astype(np.int64) * columns
             + ((p.points[:, 1] - low[1]) * (1 / SEAM_RADIUS_MM)).astype(np.int64)
             for p in parts]
    for unit in units:
        others = [n for n, p in enumerate(parts) if p.unit != unit and len(p.points)]
        if not others:
            continue
        height = np.full(size, np.nan)
        quality = np.zeros(size, np.float32)
        for n in others:
            height[cells[n]] = parts[n].points[:, 2]
            quality[cells[n]] = parts[n].quality
        for n, part in enumerate(parts):
            if part.unit != unit or not len(part.points):
                continue
            with np.errstate(invalid="ignore"):
                conflicts[n] = ((np.abs(height[cells[n]] - part.points[:, 2])
                                 > SEAM_TOLERANCE_MM) & (quality[cells[n]] >= part.quality))
    return conflicts


def fuse(parts: Sequence[Part], *, region: Region | None = None,
         min_quality: float = 0.0) -> Fused:
    """One cloud from the cameras' clouds: seam conflicts, low quality and points outside
    ``region`` removed; each point keeps its quality and camera index.

    Parameters
    ----------
    parts : sequence of Part
        The cameras' clouds.
    region : Region, optional
        Keep only points inside this box (the region of interest: the eye and its
        surroundings, say).
    min_quality : float, optional
        Drop points of lower quality, in [0, 1].
    """
    if not 0.0 <= min_quality <= 1.0:
        raise ValueError(f"min_quality must be in [0, 1], not {min_quality!r}")
    for part in parts:
        if part.points.ndim != 2 or part.points.shape[1] != 3:
            raise ValueError(f"parts: points must be (N, 3), not {part.points.shape}")
        if part.quality.shape != (len(part.points),):
            raise ValueError("parts: quality must have one value per point")
        if not 0 <= part.camera <= 255:
            raise ValueError(f"parts: camera index must be 0–255, not {part.camera}")
    conflicts = seam_conflicts(parts)
    points, quality, camera = [], [], []
    seam = low = outside = 0
    for part, clash in zip(parts, conflicts, strict=True):
        keep = ~clash
        seam += int(clash.sum())
        poor = keep & (part.quality < min_quality)
        low += int(poor.sum())
        keep &= ~poor
        if region is not None:
            out = keep & ~region.contains(part.points)
            outside += int(out.sum())
            keep &= ~out
        whole = bool(keep.all())  # most parts keep every point: no copy through a mask
        points.append(part.points if whole else rows_where(part.points, keep))
        quality.append(part.quality if whole else part.quality[keep])
        camera.append(np.full(len(points[-1]), part.camera, np.uint8))
    if not parts:
        return Fused(np.zeros((0, 3)), np.zeros(0, np.float32), np.zeros(0, np.uint8), 0, 0, 0)
    return Fused(np.concatenate(points), np.concatenate(quality).astype(np.float32),
                 np.concatenate(camera), seam, low, outside)
