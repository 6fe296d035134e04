"""Recorded sessions in the simulated room: capture bundles of scenes and whole calibration sets.

Everything is captured the way the daemon will capture it, through a :class:`Rig` of simulated
drivers (trigger pulses, interleaved units, frame metadata), and written in FORMATS.md's formats.
The scene's ground truth goes beside the images as ``truth.json``, which bundle readers ignore
and the measurement path never opens.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from eyeserver.core.clock import ManualClock
from eyeserver.core.types import Progress, quiet
from eyeserver.hardware.bundling import bundle_frames
from eyeserver.hardware.rig import Rig
from eyeserver.hardware.sim.config import RoomConfig
from eyeserver.hardware.sim.drivers import build_sim_rig
from eyeserver.hardware.sim.room import SimRoom
from eyeserver.hardware.sim.scenes import SceneSpec
from eyeserver.hardware.sim.truth import room_truth
from eyeserver.io import (
    BundleFrameData,
    BundleKind,
    ChessboardSpec,
    atomic_write_text,
    rig_from_dict,
    write_bundle,
    write_rig,
)

TRUTH_FILE = "truth.json"


def bundle_kind(spec: SceneSpec) -> BundleKind:
    """The capture-bundle kind a scene is recorded as."""
    if spec.kind == "chessboard":
        return "chessboard"
    if spec.kind == "plate":
        return "plate"
    if spec.kind == "reference":
        return "reference"
    return "measurement"


@dataclass
class SimSession:
    """A simulated room with its rig open, on a manual clock, for recording bundles."""

    room: SimRoom
    rig: Rig
    clock: ManualClock

    @classmethod
    def open(cls, config: RoomConfig, seed: int | None = None) -> SimSession:
        """Build the room (``seed`` overrides the room file's) and open its simulated rig."""
        if seed is not None:
            config = config.model_copy(update={"seed": seed})
        clock = ManualClock(0)
        room = SimRoom(config, clock=clock)
        rig = build_sim_rig(room, clock=clock)
        rig.open()
        return cls(room=room, rig=rig, clock=clock)

    def close(self) -> None:
        """Close the rig."""
        self.rig.close()

    def __enter__(self) -> SimSession:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def acquire(self, spec: SceneSpec, units: Sequence[str] | None = None,
                scene_time_s: float = 0.0) -> list[BundleFrameData]:
        """Place ``spec`` and capture it as a bundle would hold it.

        Chessboards are filmed under the room lights with every projector dark, in one frame;
        anything else in ambient light, one frame per unit with that unit's projector lit.
        ``scene_time_s`` lets a moving scene run that long before the capture.
        """
        self.room.set_scene(spec)
        self.clock.advance(scene_time_s)
        if spec.kind == "chessboard":
            self.room.set_room_lights(True)
            try:
                return bundle_frames([self.rig.acquire_unlit()], None)
            finally:
                self.room.set_room_lights(False)
        unit_ids = list(units) if units is not None else [u.id for u in self.rig.units]
        z_mm = spec.position[2] if spec.kind in ("plate", "reference") else None
        return bundle_frames(self.rig.acquire(unit_ids), z_mm)

    def record(self, spec: SceneSpec, out: Path, *, units: Sequence[str] | None = None,
               origin: bool = False, overwrite: bool = False, scene_time_s: float = 0.0,
               ) -> Path:
        """Capture ``spec`` into a bundle directory ``out`` with its ``truth.json``.

        The truth is the scene's at the first frame's mid-exposure time.
        """
        frames = self.acquire(spec, units, scene_time_s)
        truth = room_truth(self.room, _mid_exposure_s(frames))
        kind = bundle_kind(spec)
        chessboard = (ChessboardSpec(spec.cols, spec.rows, spec.square_mm, origin)
                      if kind == "chessboard" else None)
        self.write(out, kind, frames, truth, chessboard=chessboard, overwrite=overwrite)
        return out

    def write(self, out: Path, kind: BundleKind, frames: list[BundleFrameData],
              truth: dict[str, Any] | list[Any], *, chessboard: ChessboardSpec | None = None,
              overwrite: bool = False) -> None:
        """Write captured ``frames`` as a bundle with ``truth`` as its ``truth.json``."""
        rig = rig_from_dict(self.rig.spec(), "<simulated rig>")
        depth = max(self.room.camera_format(c)[2] for f in frames for c in f.images)
        write_bundle(out, kind, rig, frames, chessboard=chessboard,
                     bit_depth=depth if depth > 8 else None, extra={"simulated": True},
                     overwrite=overwrite)
        atomic_write_text(out / TRUTH_FILE, json.dumps(truth, indent=1) + "\n")


def _mid_exposure_s(frames: Sequence[BundleFrameData]) -> float:
    t_ns = frames[0].t_ns
    return 0.0 if t_ns is None else t_ns / 1e9


def calibration_poses() -> list[tuple[tuple[float, float, float], tuple[float, float, float]]]:
    """Chessboard poses ``(position_mm, rotation_deg)`` for a calibration set; the first is the
    origin board. The others tilt ±20–25° about X and Y, turn in plane and move in depth, so
    every camera sees the board foreshortened several ways (what intrinsics need)."""
    return [
        ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
        ((0.0, 0.0, 5.0), (20.0, 0.0, 0.0)),
        ((0.0, 0.0, 5.0), (-20.0, 0.0, 0.0)),
        ((0.0, 0.0, -5.0), (0.0, 22.0, 0.0)),
        ((0.0, 0.0, -5.0), (0.0, -22.0, 0.0)),
        ((3.0, -2.0, 10.0), (15.0, 15.0, 10.0)),
        ((-3.0, 2.0, 10.0), (-15.0, -15.0, -10.0)),
        ((2.0, 3.0, -8.0), (18.0, -18.0, 25.0)),
        ((-2.0, -3.0, -8.0), (-18.0, 18.0, -25.0)),
        ((0.0, 0.0, 15.0), (0.0, 0.0, 90.0)),
        ((0.0, 0.0, 0.0), (10.0, -25.0, 180.0)),
        ((4.0, 0.0, 3.0), (-25.0, 10.0, 45.0)),
    ]


def plate_heights(z_min: float = -10.0, z_max: float = 25.0, step: float = 1.0) -> list[float]:
    """Nominal plate heights from ``z_min`` to ``z_max`` inclusive."""
    if step <= 0 or z_max < z_min:
        raise ValueError(f"bad plate range {z_min}…{z_max} step {step}")
    count = round((z_max - z_min) / step)
    return [round(z_min + k * step, 6) for k in range(count + 1)]


def write_calibration_set(session: SimSession, out: Path, *, z_values: Sequence[float] | None
                          = None, reference_z: float = 10.0, overwrite: bool = False,
                          progress: Progress = quiet) -> dict[str, Any]:
    """Write ``rig.json``, ``chessboard_NN/``, ``plate/`` and ``reference/`` under ``out``.

    Returns a summary (what was written). The plate bundle repeats each Z once per projector,
    as FORMATS.md describes; its truth file lists the plate's truth at every Z.
    """
    out.mkdir(parents=True, exist_ok=True)
    write_rig(out / "rig.json", rig_from_dict(session.rig.spec(), "<simulated rig>"))
    poses = calibration_poses()
    for n, (position, rotation) in enumerate(poses):
        progress(f"chessboard {n + 1}/{len(poses)}")
        session.record(SceneSpec(kind="chessboard", position_mm=position, rotation_deg=rotation),
                       out / f"chessboard_{n:02d}", origin=(n == 0), overwrite=overwrite)
    z_list = list(z_values) if z_values is not None else plate_heights()
    frames: list[BundleFrameData] = []
    truths: list[Any] = []
    for k, z in enumerate(z_list):
        progress(f"plate Z = {z:+.1f} mm ({k + 1}/{len(z_list)})")
        captured = session.acquire(SceneSpec(kind="plate", position_mm=(0.0, 0.0, z)))
        frames.extend(captured)
        truths.append(room_truth(session.room, _mid_exposure_s(captured)))
    session.write(out / "plate", "plate", frames, truths, overwrite=overwrite)
    progress(f"reference plane Z = {reference_z:+.1f} mm")
    session.record(SceneSpec(kind="reference", position_mm=(0.0, 0.0, reference_z)),
                   out / "reference", overwrite=overwrite)
    return {"rig": "rig.json", "chessboards": len(poses), "plate_heights": len(z_list),
            "reference_z_mm": reference_z}
