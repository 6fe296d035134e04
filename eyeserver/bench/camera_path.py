"""The frame path through a real camera driver: Aravis's fake GigE Vision camera on loopback
through :class:`~eyeserver.hardware.drivers.genicam.GenicamCamera`, beside the simulated
camera of the default room, triggered and read as the rig does (issue 38).

Per driver, ``frames`` software-triggered frames one after the other: frames per second, the
time from the trigger to the frame in the caller's hands (medians and p95s) and the frames
dropped; for the GenICam driver also its own latency, from Aravis handing the buffer over to the
frame in the caller's hands (the image copied out, queued, the reader woken). What each holds:

- the fake camera looks for a software trigger once per 40 ms (its own 25-Hz loop), so its
  trigger → frame time is 0–40 ms of waiting plus the exposure, the transfer (a 640 × 512 Mono8
  frame over loopback GVSP) and the driver, and its frame rate at most 25 per second; a real
  camera on its trigger line starts the exposure within microseconds;
- the simulated camera renders its image when the trigger fires (the room's renderer), so its
  trigger → frame time is the render.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from eyeserver.core.clock import MonotonicClock
from eyeserver.core.types import Progress, quiet
from eyeserver.errors import DeviceError
from eyeserver.hardware.base import Camera, TriggerStep
from eyeserver.hardware.drivers.genicam import GenicamCamera
from eyeserver.hardware.emulators.fakegv import FakeGigECamera, find_fake_camera_program
from eyeserver.hardware.registry import DriverContext
from eyeserver.hardware.sim.config import RoomConfig
from eyeserver.hardware.sim.drivers import build_sim_rig
from eyeserver.hardware.sim.room import SimRoom
from eyeserver.hardware.sim.scenes import SceneSpec

__all__ = ["frame_path", "frame_path_lines"]

_WIDTH, _HEIGHT = 640, 512


def _summary_ms(samples_s: list[float]) -> dict[str, float]:
    values = np.asarray(samples_s) * 1e3
    return {"median_ms": float(np.median(values)), "p95_ms": float(np.percentile(values, 95))}


def _time_frames(camera: Camera, trigger: Callable[[], object], frames: int,
                 ) -> dict[str, Any]:
    """``frames`` frames of ``camera``, each triggered by ``trigger()`` and read at once."""
    clock = MonotonicClock()
    to_frame, in_driver = [], []
    started = time.perf_counter()
    dropped_before = camera.describe().get("dropped_frames", 0)
    for _ in range(frames):
        fired_ns = clock.now_ns()
        trigger()
        frame = camera.read_frame(timeout_s=2.0)
        now_ns = clock.now_ns()
        to_frame.append((now_ns - fired_ns) / 1e9)
        received = frame.extra.get("received_ns")
        if isinstance(received, int):
            in_driver.append((now_ns - received) / 1e9)
    seconds = time.perf_counter() - started
    dropped = camera.describe().get("dropped_frames", 0)
    figures = {"frames": frames, "frames_per_s": frames / seconds,
               "trigger_to_frame": _summary_ms(to_frame),
               "dropped_frames": dropped - dropped_before
               if isinstance(dropped, int) and isinstance(dropped_before, int) else None}
    if in_driver:
        figures["received_to_frame"] = _summary_ms(in_driver)
    return figures


def _genicam(frames: int) -> dict[str, Any]:
    with FakeGigECamera("127.0.0.1") as fake:
        camera = GenicamCamera("S1", context=DriverContext(), address=fake.address,
                               trigger_source="Software", width=_WIDTH, height=_HEIGHT)
        camera.open()
        try:
            camera.set_exposure_us(10_000)
            _time_frames(camera, camera.software_trigger, 3)  # warm-up: clock offset, buffers
            return _time_frames(camera, camera.software_trigger, frames)
        finally:
            camera.close()
            camera.wait_released()


def _simulated(config: RoomConfig, frames: int) -> dict[str, Any]:
    room = SimRoom(config)
    room.set_scene(SceneSpec(kind="eye"))
    rig = build_sim_rig(room)
    rig.open()
    try:
        unit = rig.units[0]
        camera = unit.cameras[0]
        rig.trigger.set_sequence([TriggerStep(projectors=(unit.projector.id,),
                                              cameras=(camera.id,))])
        _time_frames(camera, rig.trigger.fire, 3)  # warm-up: the still scene's render cache
        return _time_frames(camera, rig.trigger.fire, frames)
    finally:
        rig.close()


def frame_path(config: RoomConfig, frames: int = 100, progress: Progress = quiet,
               ) -> dict[str, Any]:
    """The frame path's figures per driver (module docstring); the GenICam driver's are
    ``pending`` with the reason where Aravis's fake camera or PyGObject is missing."""
    report: dict[str, Any] = {
        "what": "software-triggered frames one after the other, 640 × 512 Mono8, exposure "
                "10 ms: trigger → frame in hand; the GenICam driver's own latency, buffer "
                "received → frame in hand",
    }
    progress(f"frame path: {frames} frames of the simulated camera")
    report["simulated"] = _simulated(config, frames)
    if find_fake_camera_program() is None:
        report["genicam_pending"] = "Aravis's fake camera is not installed " \
                                    "(scripts/system-packages.sh)"
        return report
    progress(f"frame path: {frames} frames of Aravis's fake GigE Vision camera on loopback")
    try:
        report["genicam"] = _genicam(frames)
    except DeviceError as exc:
        report["genicam_pending"] = str(exc)
    return report


def frame_path_lines(report: dict[str, Any]) -> list[str]:
    """The frame path as a markdown table (the speed page and ``bench speed``'s text)."""
    lines = [f"The frame path through the camera drivers ({report['what']}):", "",
             "| driver | frames/s | trigger → frame median ms | p95 ms | in the driver median ms "
             "| p95 ms | dropped |", "|---|---|---|---|---|---|---|"]
    for key, name in (("simulated", "simulated camera (renders on the trigger)"),
                      ("genicam", "GenicamCamera, Aravis's fake GigE camera on loopback")):
        figures = report.get(key)
        if figures is None:
            continue
        driver = figures.get("received_to_frame")
        inside = (f"{driver['median_ms']:.2f} | {driver['p95_ms']:.2f}" if driver
                  else "– | –")
        lines.append(f"| {name} | {figures['frames_per_s']:.1f} | "
                     f"{figures['trigger_to_frame']['median_ms']:.1f} | "
                     f"{figures['trigger_to_frame']['p95_ms']:.1f} | {inside} | "
                     f"{figures['dropped_frames']} |")
    if "genicam_pending" in report:
        lines.append(f"| GenicamCamera | pending: {report['genicam_pending']} | | | | | |")
    lines += ["", "The fake camera looks for a software trigger once per 40 ms, which sets its "
              "trigger → frame time and its 25 frames/s; a camera on a trigger line does not "
              "wait.", ""]
    return lines
