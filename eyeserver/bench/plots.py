"""PNG figures of the accuracy bench, the pictures a physicist would look for in a validation
report: the fiducial error against position in the volume, its histogram per axis, and maps of
the error on an eye phantom per unit and fused. Matplotlib's object API (no pyplot, so no global
state and no display): a ``Figure`` saves itself as PNG through Agg."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from eyeserver.hardware.sim.config import RoomConfig
from eyeserver.io import PointCloud

MAP_POINTS = 60_000
"""Points drawn per error map (a random subset: the maps are dense enough by far)."""
MAP_LIMIT_MM = 0.2
"""Top of the error maps' colour scale."""


def error_map(cloud: PointCloud, distance: np.ndarray, config: RoomConfig) -> dict[str, Any]:
    """X, Y and |distance| of a subset of the cloud's points, fused and per unit."""
    rng = np.random.default_rng(0)
    camera_ids = [c.id for u in config.units for c in u.cameras]
    unit_of = {c.id: u.id for u in config.units for c in u.cameras}
    units = np.asarray([unit_of[camera_ids[int(i)]] for i in cloud.camera]) \
        if cloud.camera is not None else np.full(len(cloud), "all")
    out: dict[str, Any] = {}
    for name in ["fused", *[u.id for u in config.units]]:
        chosen = np.flatnonzero(units == name) if name != "fused" else np.arange(len(cloud))
        if len(chosen) > MAP_POINTS:
            chosen = rng.choice(chosen, MAP_POINTS, replace=False)
        out[name] = (cloud.points[chosen, 0], cloud.points[chosen, 1], np.abs(distance[chosen]))
    return out


def write_figures(report: dict[str, Any], fiducials: list[dict[str, Any]],
                  maps: dict[str, Any], out: Path) -> list[str]:
    """Write the figures under ``out`` and return their file names."""
    written = []
    if fiducials:
        position = np.asarray([f["stereo_mm"] for f in fiducials])
        error = np.asarray([f["error_mm"] for f in fiducials])
        norm = np.linalg.norm(error, axis=1)
        fig = Figure(figsize=(13, 4))
        axes = fig.subplots(1, 3, sharey=True)
        for axis, (ax, name) in enumerate(zip(axes, "XYZ", strict=True)):
            ax.scatter(position[:, axis], norm, s=8, alpha=0.7)
            ax.axhline(0.15, color="tab:green", ls="--", lw=1, label="goal 0.15 mm")
            ax.axhline(0.58, color="tab:red", ls=":", lw=1, label="paper 0.58 mm (median)")
            ax.set_xlabel(f"{name} of the fiducial, mm (WCS)")
        axes[0].set_ylabel("|fringe − triangulation|, mm")
        axes[0].legend(loc="upper left", fontsize=8)
        fig.suptitle(f"3-D error at {len(norm)} fiducials against position in the volume")
        fig.tight_layout()
        fig.savefig(out / "fiducial_error_vs_position.png", dpi=110)
        written.append("fiducial_error_vs_position.png")

        fig = Figure(figsize=(13, 3.6))
        axes = fig.subplots(1, 3, sharey=True)
        for axis, (ax, name) in enumerate(zip(axes, "xyz", strict=True)):
            ax.hist(error[:, axis], bins=30, color="tab:blue", alpha=0.8)
            ax.set_xlabel(f"{name}: fringe − triangulation, mm")
            ax.set_title(f"median |{name}| {np.median(np.abs(error[:, axis])):.3f} mm",
                         fontsize=10)
        axes[0].set_ylabel("fiducials")
        fig.suptitle("fiducial error per axis")
        fig.tight_layout()
        fig.savefig(out / "fiducial_error_per_axis.png", dpi=110)
        written.append("fiducial_error_per_axis.png")
    if maps:
        names = [n for n in maps if n != "fused"] + ["fused"]
        fig = Figure(figsize=(4.6 * len(names), 4.4))
        axes = fig.subplots(1, len(names), sharex=True, sharey=True)
        image = None
        for ax, name in zip(np.atleast_1d(axes), names, strict=True):
            x, y, d = maps[name]
            image = ax.scatter(x, y, c=np.minimum(d, MAP_LIMIT_MM), s=0.4, cmap="viridis",
                               vmin=0.0, vmax=MAP_LIMIT_MM, rasterized=True)
            ax.set_title(f"{name}: median {np.median(d):.3f} mm" if len(d) else name)
            ax.set_xlabel("X, mm")
            ax.set_aspect("equal")
        np.atleast_1d(axes)[0].set_ylabel("Y, mm")
        if image is not None:
            fig.colorbar(image, ax=axes, label=f"|distance| to the exact surface, mm "
                         f"(clipped at {MAP_LIMIT_MM})")
        fig.suptitle("eye phantom 1: error map per unit and fused (4 views)")
        fig.savefig(out / "eye_phantom_error_map.png", dpi=110)
        written.append("eye_phantom_error_map.png")
    return written
