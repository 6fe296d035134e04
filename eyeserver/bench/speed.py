"""``eyeserver bench speed``: how fast things run on this machine.

Today it measures the simulated room, which the live daemon will drive at the camera rate while
reconstruction shares the same cores: the time to render one frame-set of 2 cameras (one unit)
and of 4 cameras (two units), for a moving patient eye (geometry re-cast every frame: the live
case) and for a still scene (geometry cached, only the sensor is simulated per frame). The
pipeline's stages join this report when they exist (DESIGN §8 names their keys).
"""

from __future__ import annotations

import os
import platform
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from eyeserver.core.clock import ManualClock
from eyeserver.hardware.sim.config import RoomConfig
from eyeserver.hardware.sim.motion import MotionSpec
from eyeserver.hardware.sim.room import SimRoom
from eyeserver.hardware.sim.scenes import EyeSpec, SceneSpec

Progress = Callable[[str], None]

PENDING = ("frame_to_pose_p99_ms",)
"""Speed keys of DESIGN §8 whose stages are not built yet (reported as such, never invented)."""


def _quiet(_: str) -> None:
    pass


def machine() -> dict[str, Any]:
    """Where the figures came from."""
    return {"python": platform.python_version(), "numpy": np.__version__,
            "platform": platform.platform(), "processor": platform.processor() or "unknown",
            "cpu_count": os.cpu_count()}


def _summary(samples_s: Sequence[float]) -> dict[str, float]:
    ms = np.asarray(samples_s) * 1e3
    return {"median_ms": float(np.median(ms)), "p95_ms": float(np.percentile(ms, 95)),
            "min_ms": float(np.min(ms)), "n": len(ms)}


def time_frames(room: SimRoom, clock: ManualClock, cameras: Sequence[tuple[str, str]],
                frames: int, rng: np.random.Generator) -> list[float]:
    """Seconds per frame-set: each frame advances the clock 40 ms and renders every
    ``(camera, projector)`` pair once, as the rig does for one trigger cycle."""
    samples = []
    for _ in range(frames):
        clock.advance(0.04)
        t_s = clock.now_ns() / 1e9
        started = time.perf_counter()
        for camera_id, projector_id in cameras:
            room.render(camera_id, t_s=t_s, projectors={projector_id: 1.0},
                        exposure_us=room.config.lighting.exposure_ref_us, gain_db=0.0, rng=rng)
        samples.append(time.perf_counter() - started)
    return samples


def sim_render(config: RoomConfig, frames: int = 30, progress: Progress = _quiet,
               ) -> dict[str, Any]:
    """Render times of 2- and 4-camera frame-sets, moving eye and still scene."""
    clock = ManualClock(0)
    room = SimRoom(config, clock=clock)
    rng = np.random.default_rng(0)
    pairs = [(cid, unit.projector.id) for unit in config.units for cid in
             (c.id for c in unit.cameras)]
    two, four = pairs[:2], pairs[:4]
    for camera_id, _ in four:
        room.renderer.cameras[camera_id].rays()  # one-off set-up, not a per-frame cost
    results: dict[str, Any] = {}
    moving = SceneSpec(kind="eye", eye=EyeSpec(motion=MotionSpec(seed=1)))
    still = SceneSpec(kind="eye")
    for label, spec in (("moving_eye", moving), ("still_eye", still)):
        room.set_scene(spec)
        time_frames(room, clock, four, 1, rng)  # warm-up (fills the still scene's cache)
        for name, cams in (("2cam", two), ("4cam", four)):
            if len(cams) < (2 if name == "2cam" else 4):
                continue
            progress(f"sim render, {label.replace('_', ' ')}, {name} ({frames} frames)")
            results[f"{label}_{name}"] = _summary(time_frames(room, clock, cams, frames, rng))
    return results


def pipeline(config: RoomConfig, calibration: Path, work: Path, frames: int = 30,
             progress: Progress = _quiet) -> dict[str, Any]:
    """Reconstruction times of a 2-camera (one unit) and a 4-camera frame-set of an eye
    phantom, single-threaded, for both fringe-order paths (images already in memory)."""
    from eyeserver.calibration.artefact import load_calibration
    from eyeserver.hardware.sim.sessions import SimSession
    from eyeserver.io import read_bundle
    from eyeserver.pipeline.reconstruct import METHODS, unit_clouds
    from eyeserver.service.reconstruction import calibrated_cameras

    bundle_path = work / "speed_eye_phantom_1"
    with SimSession.open(config, seed=3) as session:
        session.record(SceneSpec(kind="eye_phantom_1"), bundle_path, overwrite=True)
    bundle = read_bundle(bundle_path)
    document = load_calibration(calibration, bundle.rig)
    cameras = calibrated_cameras(document)
    z_range = tuple(document["phase_to_height"]["cameras"][bundle.rig.camera_ids[0]]
                    ["z_range_mm"])
    pairs = []
    for index in bundle.frame_indices:
        ids = [c for i, c in bundle.fringe_images() if i == index]
        if len(ids) >= 2:
            pairs.append((bundle.load_image(index, ids[0]), cameras[ids[0]],
                          bundle.load_image(index, ids[1]), cameras[ids[1]]))
    results: dict[str, Any] = {}
    for method in METHODS:
        runs = frames if method == "multi-view" else max(3, frames // 5)
        for label, used in (("2cam", pairs[:1]), ("4cam", pairs[:2])):
            if len(used) < (1 if label == "2cam" else 2):
                continue
            progress(f"reconstruction, {method}, {label} ({runs} frame-sets)")
            samples = []
            for _ in range(runs + 1):
                started = time.perf_counter()
                for image_a, cam_a, image_b, cam_b in used:
                    unit_clouds(cam_a, image_a, cam_b, image_b,
                                (float(z_range[0]), float(z_range[1])), method=method)
                samples.append(time.perf_counter() - started)
            results[f"{method}_{label}"] = _summary(samples[1:])  # the first fills caches
    return results


def run(config: RoomConfig, frames: int = 30, progress: Progress = _quiet,
        calibration: Path | None = None) -> dict[str, Any]:
    """The whole speed report as one JSON-able document (``calibration``: a calibration of the
    simulated rig; made on the spot when not given)."""
    from eyeserver.bench.simcal import calibrate_room

    started = time.perf_counter()
    render = sim_render(config, frames, progress)
    with tempfile.TemporaryDirectory(prefix="eyeserver-speed-") as tmp:
        work = Path(tmp)
        if calibration is None:
            progress("calibrating the simulated rig for the pipeline timings")
            calibration = calibrate_room(config, work, 0, progress)
        reconstruction = pipeline(config, calibration, work, frames, progress)
    report: dict[str, Any] = {
        "format": "eyeserver.bench.speed/1",
        "machine": machine(),
        "units": "milliseconds per frame-set (median unless named p95)",
        "sim_render": render,
        "reconstruction": reconstruction,
        "pending": {key: "not built yet: the eye pose (issue 7) comes first"
                    for key in PENDING},
    }
    for label in ("2cam", "4cam"):
        if f"multi-view_{label}" in reconstruction:
            report[f"frameset_{label}_ms"] = reconstruction[f"multi-view_{label}"]["median_ms"]
    if "moving_eye_2cam" in render:
        report["sim_render_2cam_ms"] = render["moving_eye_2cam"]["median_ms"]
    if "moving_eye_4cam" in render:
        report["sim_render_4cam_ms"] = render["moving_eye_4cam"]["median_ms"]
    report["duration_s"] = round(time.perf_counter() - started, 1)
    return report


def format_text(report: dict[str, Any]) -> str:
    """A human-readable table of the report."""
    lines = [f"eyeserver bench speed — {report['machine']['platform']}, "
             f"{report['machine']['cpu_count']} CPUs, Python {report['machine']['python']}", ""]
    lines.append(f"{'simulated room render':<34}{'median ms':>10}{'p95 ms':>10}")
    for key, value in report["sim_render"].items():
        lines.append(f"  {key.replace('_', ' '):<32}{value['median_ms']:>10.1f}"
                     f"{value['p95_ms']:>10.1f}")
    lines.append("goal: a live 2-camera frame in ≤ 20 ms (25 Hz, sharing the cores with "
                 "reconstruction)")
    lines.append("")
    lines.append(f"{'reconstruction (one thread)':<34}{'median ms':>10}{'p95 ms':>10}")
    for key, value in report["reconstruction"].items():
        lines.append(f"  {key.replace('_', ' '):<32}{value['median_ms']:>10.1f}"
                     f"{value['p95_ms']:>10.1f}")
    lines.append("goal: a 2-camera frame-set in ≤ 10 ms, a 4-camera one in ≤ 20 ms (DESIGN §6)")
    lines.append("")
    for key, why in report["pending"].items():
        lines.append(f"{key}: {why}")
    lines.append(f"took {report['duration_s']} s")
    return "\n".join(lines)

