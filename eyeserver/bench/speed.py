"""``eyeserver bench speed``: how fast things run on this machine.

The simulated room, which the live daemon drives at the camera rate on the same cores: the time
to render a frame-set of 2 cameras (one unit) and of 4 (two units), for a moving patient eye
(geometry re-cast every frame) and for a still scene (only the sensor simulated per frame).

The reconstruction, on the fringe images of an eye phantom recorded in the simulated room and
held in memory (no file I/O is timed), with OpenCV held to one thread of its own:

* **Frame-sets** (images → fused cloud: each unit's :func:`unit_clouds`, then :func:`fuse`), for
  both fringe-order paths; single-threaded, with two worker threads taking the two units of a
  4-camera frame-set (latency), and with two workers taking a frame-set each (throughput).
* **Stages**, each timed on its own per camera, repeated ``frames`` times on the same images
  and summed over the cameras of each frame-set. Their names against the issue's list:

  ============================  ===================================================================
  issue                         stage(s) here
  ============================  ===================================================================
  demodulation                  ``demodulation`` (:func:`demodulate` without its bend
                                correction), ``bend_correction`` (:func:`with_bend_bias`),
                                ``reference_subtraction`` (:func:`phase_difference`)
  masks                         ``masks`` (the rest of :func:`camera_phase`)
  unwrapping, fringe order      multi-view path (one step does both): ``fringe_order_grid``
                                (:func:`grid_order`), ``fringe_order_propagate``
                                (:func:`propagate_order`); spatial path: ``spatial_unwrapping``
                                (:func:`spatial_unwrap`), ``spatial_region_order``
                                (:func:`spatial_order`)
  phase-to-height               ``phase_to_height`` (``PhaseHeightModel.height``)
  transversal mapping           ``transversal_mapping`` (:meth:`CalibratedCamera.points_at`)
  (checks in ``unit_clouds``)   ``order_check``, ``cloud_assembly``, ``cross_check``, ``despeckle``
  fusion                        ``fusion`` (:func:`fuse`, per frame-set)
  ============================  ===================================================================

* **Peers** on the same images, as time ratios (peer ÷ ours, above 1 when ours is faster), each
  with its agreement to ours: scikit-image's ``unwrap_phase`` on the whole masked phase against
  :func:`spatial_unwrap`; the regions voted on every third pixel against :func:`spatial_order`;
  a plain FFT Fourier-transform method (``rfft2``, a fixed box around the carrier, inverse) and
  OpenCV contrib's ``structured_light`` FTP against :func:`demodulate`. The contrib peer needs
  ``opencv-contrib-python-headless`` *instead of* ``opencv-python-headless`` (both are the
  ``cv2`` package: never install the two); without it the peer is reported unavailable.
* **Memory**: the process's peak resident set and the Python-visible peak of one frame-set
  (tracemalloc: numpy arrays, not OpenCV's or the FFT's internal buffers).
"""

from __future__ import annotations

import os
import resource
import sys
import tempfile
import time
import tracemalloc
from collections import defaultdict
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Executor, ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any, NamedTuple, ParamSpec, TypeVar

import numpy as np
import numpy.typing as npt

from eyeserver.bench import tracking
from eyeserver.bench.api import api_latency
from eyeserver.bench.camera_path import frame_path, frame_path_lines
from eyeserver.bench.machine import machine, reference_ms
from eyeserver.bench.simcal import calibrate_room
from eyeserver.core.clock import ManualClock
from eyeserver.core.types import F32, Progress, quiet
from eyeserver.hardware.sim.config import RoomConfig
from eyeserver.hardware.sim.motion import MotionSpec
from eyeserver.hardware.sim.room import SimRoom
from eyeserver.hardware.sim.scenes import EyeSpec, SceneSpec

if TYPE_CHECKING:
    from eyeserver.pipeline.demodulate import Carrier
    from eyeserver.pipeline.fusion import Fused
    from eyeserver.pipeline.reconstruct import CalibratedCamera, CameraCloud, Phase

P = ParamSpec("P")
T = TypeVar("T")

TRACKING_GOAL_P99_MS = 40.0
"""docs/design.md §6 / issue 7: frame mid-exposure → pose message on the WebSocket, p99."""

BOTH_UNITS_GOAL_P99_MS = 25.0
"""Issue 37: the same with both units tracked (four cameras, each unit's frames in turn)."""

GOALS_MS = {"frameset_2cam_ms": 10.0, "frameset_4cam_ms": 20.0}
"""docs/design.md §6: on 2 cores a 2-camera frame-set in ≤ 10 ms (4× the 25 Hz camera rate), a
4-camera one in ≤ 20 ms (2×)."""

WORKERS = 2
"""Worker threads of the parallel timings: the two units of a 4-camera frame-set (numpy, scipy's
FFT and OpenCV release the GIL), as the daemon will run them on this 2-core machine."""

STAGES: dict[str, str] = {
    "demodulation": "demodulate: FTM (border continuation, FFT, band, inverse)",
    "bend_correction": "with_bend_bias: the band edge's phase bias where the fringes bend "
                       "(demodulate's measure_bends)",
    "reference_subtraction": "phase_difference against the reference plane's phase",
    "masks": "camera_phase's masks: modulation, border, saturation, edge erosion",
    "fringe_order_grid": "grid_order: multi-view order on every 3rd pixel (with the partner's "
                         "phase resampled onto its pinhole image)",
    "fringe_order_propagate": "propagate_order: full-resolution order from the grid (the "
                              "multi-view path's unwrapping)",
    "phase_to_height": "PhaseHeightModel.height of every masked-in pixel",
    "transversal_mapping": "CalibratedCamera.points_at: X, Y where each pixel's ray meets its "
                           "height",
    "order_check": "every pixel's order checked against the partner camera's phase",
    "cloud_assembly": "quality, range crop (camera_cloud's last step)",
    "cross_check": "points the partner's own reconstruction confirms (unit_clouds)",
    "despeckle": "patches of continuous depth under 1000 px dropped unless the partner "
                 "confirms a 200 px+ patch's order as a whole",
    "spatial_unwrapping": "spatial path: spatial_unwrap (scikit-image's Herráez unwrapping of "
                          "every second pixel, each pixel stepped to a sample)",
    "spatial_region_order": "spatial path: one order per unwrapped region, voted by multi-view "
                            "picks on every 9th pixel (on every 3rd of a region they do not "
                            "settle)",
}
"""Per-camera stages of the reconstruction, in pipeline order (``fusion`` is per frame-set)."""

MULTI_VIEW_STAGES = tuple(s for s in STAGES if not s.startswith("spatial_"))
SPATIAL_STAGES = tuple(s for s in STAGES if not s.startswith("fringe_order_"))


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


def sim_render(config: RoomConfig, frames: int = 30, progress: Progress = quiet,
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


# --- the reconstruction's input -------------------------------------------------------------


@dataclass(frozen=True)
class UnitImages:
    """One unit's two fringe images of a frame-set, with their calibrated cameras."""

    unit_id: str
    cam_a: CalibratedCamera
    image_a: npt.NDArray[Any]
    cam_b: CalibratedCamera
    image_b: npt.NDArray[Any]


@dataclass(frozen=True)
class RecordedFrameSet:
    """What the pipeline timings run on: a frame-set recorded in the simulated room and held in
    memory, its units' images (the 2-camera frame-set is the first unit, the 4-camera one the
    first two), the calibrated range and the rig's camera indices. (Not live tracking's
    ``FrameSet`` in :mod:`eyeserver.service`, one camera frame of the rig.)"""

    units: tuple[UnitImages, ...]
    z_range: tuple[float, float]
    saturation_dn: float | None
    camera_index: dict[str, int]

    def sizes(self) -> dict[str, tuple[UnitImages, ...]]:
        """The frame-sets there are images for: ``{"2cam": one unit, "4cam": two units}``."""
        sets = {"2cam": self.units[:1], "4cam": self.units[:2]}
        return {label: used for label, used in sets.items()
                if len(used) == (1 if label == "2cam" else 2)}


def record_frameset(config: RoomConfig, calibration: Path, work: Path) -> RecordedFrameSet:
    """Record an eye phantom in the simulated room (every unit lit in turn) and load it with the
    calibration, as ``eyeserver reconstruct`` would."""
    from eyeserver.calibration.artefact import load_calibration
    from eyeserver.hardware.sim.sessions import SimSession
    from eyeserver.io import read_bundle
    from eyeserver.reconstruction import (
        calibrated_cameras,
        saturation_dn,
        unit_pairs,
        z_range,
    )

    bundle_path = work / "speed_eye_phantom_1"
    with SimSession.open(config, seed=3) as session:
        session.record(SceneSpec(kind="eye_phantom_1"), bundle_path, overwrite=True)
    bundle = read_bundle(bundle_path)
    document = load_calibration(calibration, bundle.rig)
    cameras = calibrated_cameras(document)
    units = [UnitImages(bundle.rig.unit_of_camera(id_a).id, cameras[id_a],
                        bundle.load_image(index, id_a), cameras[id_b],
                        bundle.load_image(index, id_b))
             for index, id_a, id_b in unit_pairs(bundle)]
    return RecordedFrameSet(
        units=tuple(units), z_range=z_range(document), saturation_dn=saturation_dn(bundle),
        camera_index={c: bundle.rig.camera_index(c) for c in bundle.rig.camera_ids})


def reconstruct_frameset(frameset: RecordedFrameSet, units: Sequence[UnitImages], method: str,
                         executor: Executor | None = None) -> Fused:
    """Images → fused cloud: each unit's clouds (in parallel on ``executor`` when given), then
    fusion, as ``eyeserver reconstruct`` does without the file I/O."""
    from eyeserver.pipeline.fusion import Part, fuse
    from eyeserver.pipeline.reconstruct import unit_clouds

    def one(unit: UnitImages) -> tuple[CameraCloud, CameraCloud]:
        return unit_clouds(unit.cam_a, unit.image_a, unit.cam_b, unit.image_b,
                           frameset.z_range, method=method,
                           saturation_dn=frameset.saturation_dn)

    clouds = list(executor.map(one, units)) if executor else [one(u) for u in units]
    parts = [Part(cloud.points, cloud.quality, frameset.camera_index[cloud.camera_id],
                  unit.unit_id) for unit, pair in zip(units, clouds, strict=True)
             for cloud in pair]
    return fuse(parts)


@contextmanager
def _threads(count: int) -> Iterator[None]:
    """OpenCV's own thread pool and the BLAS's held to ``count`` threads, so that
    "single-threaded" is (the BLAS's second thread slows a frame-set: docs/notes/speed.md)."""
    import cv2
    from threadpoolctl import threadpool_limits

    previous = cv2.getNumThreads()
    cv2.setNumThreads(count)
    try:
        with threadpool_limits(limits=count, user_api="blas"):
            yield
    finally:
        cv2.setNumThreads(previous)


# --- whole frame-sets -----------------------------------------------------------------------


def _repeat(call: Callable[[], object], runs: int) -> list[float]:
    """Seconds per call, ``runs`` times after one warm-up (which fills the caches)."""
    call()
    samples = []
    for _ in range(runs):
        started = time.perf_counter()
        call()
        samples.append(time.perf_counter() - started)
    return samples


def pipeline(frameset: RecordedFrameSet, frames: int = 100, progress: Progress = quiet,
             ) -> dict[str, Any]:
    """Single-threaded times of 2- and 4-camera frame-sets (images → fused cloud), for both
    fringe-order paths (the spatial one, ≈ 0.1 s a camera, a fifth as often)."""
    from eyeserver.pipeline.reconstruct import METHODS

    results: dict[str, Any] = {}
    for method in METHODS:
        runs = frames if method == "multi-view" else max(3, frames // 5)
        for label, used in frameset.sizes().items():
            progress(f"reconstruction, {method}, {label} ({runs} frame-sets)")
            samples = _repeat(partial(reconstruct_frameset, frameset, used, method), runs)
            results[f"{method}_{label}"] = _summary(samples)
    return results


def parallel(frameset: RecordedFrameSet, frames: int = 100, progress: Progress = quiet,
             ) -> dict[str, Any]:
    """Multi-view frame-sets on :data:`WORKERS` threads: the units of one 4-camera frame-set in
    parallel (its latency), and one frame-set per worker (throughput, each frame-set taking as
    long as alone or longer)."""
    sizes = frameset.sizes()
    results: dict[str, Any] = {"workers": WORKERS}
    with ThreadPoolExecutor(max_workers=WORKERS, thread_name_prefix="speed") as executor:
        if "4cam" in sizes:
            progress(f"reconstruction, multi-view, 4cam, units on {WORKERS} threads "
                     f"({frames} frame-sets)")
            samples = _repeat(lambda: reconstruct_frameset(frameset, sizes["4cam"], "multi-view",
                                                           executor), frames)
            summary = _summary(samples)
            results["units_in_parallel_4cam"] = summary
            results["units_in_parallel_4cam_per_s"] = 1e3 / summary["median_ms"]
        for label, used in sizes.items():
            progress(f"reconstruction, multi-view, {label}, one frame-set per thread "
                     f"({frames} frame-sets)")

            def one(_: int, used: Sequence[UnitImages] = used) -> None:
                reconstruct_frameset(frameset, used, "multi-view")  # a cloud kept is memory held

            list(executor.map(one, range(WORKERS)))  # warm-up
            started = time.perf_counter()
            list(executor.map(one, range(frames)))
            wall_s = time.perf_counter() - started
            results[f"framesets_per_worker_{label}"] = {
                "wall_ms_per_frameset": wall_s * 1e3 / frames,
                "framesets_per_s": frames / wall_s, "n": frames}
    return results


# --- stage by stage -------------------------------------------------------------------------


class _Samples:
    """Seconds per call of each (owner, stage): owner a camera id or a frame-set label."""

    def __init__(self) -> None:
        self.seconds: dict[tuple[str, str], list[float]] = defaultdict(list)

    def time(self, owner: str, stage: str, call: Callable[P, T], *args: P.args,
             **kwargs: P.kwargs) -> T:
        started = time.perf_counter()
        result = call(*args, **kwargs)
        self.seconds[(owner, stage)].append(time.perf_counter() - started)
        return result


@contextmanager
def _stand_in(module: ModuleType, name: str, value: object) -> Iterator[None]:
    """``module.name`` replaced by ``value`` for the block.

    The bench times a public function minus a step it calls (the masks are
    :func:`camera_phase` without its demodulation; the spatial path's region order is
    :func:`spatial_order` without scikit-image's unwrapping) by standing in that step's result,
    computed just before: the pipeline's own code runs, nothing is copied into the bench. Only
    the single-threaded stage loop does this; the module is restored afterwards.
    """
    original = getattr(module, name)
    setattr(module, name, value)
    try:
        yield
    finally:
        setattr(module, name, original)


def _returning(value: object) -> Callable[..., object]:
    return lambda *_args, **_kwargs: value


def _phase_to_height(camera: CalibratedCamera, phase: Phase, pixels: npt.NDArray[np.intp],
                     order: npt.NDArray[np.int64]) -> npt.NDArray[np.float64]:
    x, y = camera.x.ravel()[pixels], camera.y.ravel()[pixels]
    return camera.model.height(x, y, phase.dphi.ravel()[pixels] + 2 * np.pi * order)


def _transversal(camera: CalibratedCamera, pixels: npt.NDArray[np.intp],
                 z: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    return camera.points_at(pixels, z)


def _order_check(cam_a: CalibratedCamera, cam_b: CalibratedCamera, phase_b: Phase,
                 pixels: npt.NDArray[np.intp], z: npt.NDArray[np.float64],
                 ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.bool_]]:
    # The multi-view branch of camera_cloud's check (private helpers: the check has no public
    # entry point of its own). Keep in step with reconstruct.camera_cloud.
    from eyeserver.pipeline.reconstruct import MAX_MISMATCH_RAD, _mismatch

    cost = _mismatch(cam_a, cam_b, phase_b.pinhole_view(cam_b), pixels, np.nan_to_num(z))
    return cost, np.asarray(cost < MAX_MISMATCH_RAD)


def _cross_check(cloud: CameraCloud, camera: CalibratedCamera, phase: Phase,
                 other: CameraCloud, other_camera: CalibratedCamera) -> CameraCloud:
    # unit_clouds' check of each camera's points against the other's reconstruction (private
    # helpers, as unit_clouds calls them).
    from eyeserver.pipeline.reconstruct import _checked, _contradicted

    known, wrong = _contradicted(cloud, camera, other, other_camera)
    return cloud.subset(_checked(cloud, known, wrong, camera, phase))


def _fresh(phase: Phase) -> Phase:
    """``phase`` without its cached pinhole view."""
    from eyeserver.pipeline.reconstruct import Phase

    return Phase(phase.dphi, phase.modulation, phase.valid, phase.bend_bias)


def dense_grid_votes(cam_a: CalibratedCamera, phase_a: Phase, cam_b: CalibratedCamera,
                     phase_b: Phase, z_range: tuple[float, float],
                     ) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.int64],
                                npt.NDArray[np.bool_]]:
    """The spatial order's regions voted by the multi-view picks on every third pixel, as
    :func:`spatial_order` did before it voted on a sparse grid first (the peer)."""
    from eyeserver.pipeline.reconstruct import grid_order, spatial_order

    return spatial_order(cam_a, phase_a, cam_b, phase_b, z_range, None,
                         grid=grid_order(cam_a, phase_a, cam_b, phase_b, z_range))


def skimage_unwrap(phase: Phase) -> Any:
    """scikit-image's Herráez unwrapping of a camera's whole masked wrapped phase (a masked
    array), as :func:`spatial_order` called it before :func:`spatial_unwrap` (the peer)."""
    from skimage.restoration import unwrap_phase

    masked = np.ma.masked_array(phase.dphi.astype(np.float64), mask=~phase.valid)
    return unwrap_phase(masked)  # type: ignore[no-untyped-call]


def _multi_view_pass(frameset: RecordedFrameSet, samples: _Samples) -> dict[str, Any]:
    """One repetition of the multi-view path, stage by stage, in :func:`unit_clouds`' order
    (unit by unit: both cameras' phases, both clouds, the cross-check, the speckle filter), then
    fusion per frame-set. Returns what the side pass and the checks need: phases, demodulations
    and the clouds."""
    from eyeserver.pipeline import reconstruct
    from eyeserver.pipeline.demodulate import demodulate, phase_difference, with_bend_bias
    from eyeserver.pipeline.fusion import Part, fuse
    from eyeserver.pipeline.reconstruct import (
        _cloud,
        _despeckled,
        camera_phase,
        grid_order,
        propagate_order,
    )

    out: dict[str, Any] = {"phases": {}, "demodulated": {}, "clouds": {}}
    parts = []
    for unit in frameset.units[:2]:
        pair = ((unit.cam_a, unit.image_a), (unit.cam_b, unit.image_b))
        phases: dict[str, Phase] = out["phases"]
        for cam, image in pair:
            cid = cam.camera_id
            demodulated = samples.time(cid, "demodulation", demodulate, image, cam.carrier,
                                       measure_bends=False)
            demodulated = samples.time(cid, "bend_correction", with_bend_bias, demodulated,
                                       cam.carrier)
            dphi = samples.time(cid, "reference_subtraction", phase_difference,
                                demodulated.surface_phase(), cam.reference_phase)
            # A fresh Phase every pass: the partner's pinhole view is computed in grid_order,
            # once per frame, as in unit_clouds.
            with _stand_in(reconstruct, "demodulate", _returning(demodulated)), \
                    _stand_in(reconstruct, "with_bend_bias", _returning(demodulated)), \
                    _stand_in(reconstruct, "phase_difference", _returning(dphi)):
                phases[cid] = samples.time(cid, "masks", camera_phase, cam, image,
                                           frameset.saturation_dn)
            out["demodulated"][cid] = demodulated
        clouds = {}
        for cam_a, cam_b in ((unit.cam_a, unit.cam_b), (unit.cam_b, unit.cam_a)):
            a, b = cam_a.camera_id, cam_b.camera_id
            grid = samples.time(a, "fringe_order_grid", grid_order, cam_a, phases[a], cam_b,
                                phases[b], frameset.z_range)
            pixels, order = samples.time(a, "fringe_order_propagate", propagate_order, grid,
                                         phases[a])
            z = samples.time(a, "phase_to_height", _phase_to_height, cam_a, phases[a], pixels,
                             order)
            points = samples.time(a, "transversal_mapping", _transversal, cam_a, pixels, z)
            cost, keep = samples.time(a, "order_check", _order_check, cam_a, cam_b, phases[b],
                                      pixels, z)
            clouds[a] = samples.time(a, "cloud_assembly", _cloud, cam_a, phases[a],
                                     pixels[keep], points[keep], z[keep], cost[keep],
                                     np.zeros(int(keep.sum()), np.uint8), frameset.z_range)
        checked = {
            cam.camera_id: samples.time(cam.camera_id, "cross_check", _cross_check,
                                        clouds[cam.camera_id], cam, phases[cam.camera_id],
                                        clouds[other.camera_id], other)
            for cam, other in ((unit.cam_a, unit.cam_b), (unit.cam_b, unit.cam_a))}
        for cam, other in ((unit.cam_a, unit.cam_b), (unit.cam_b, unit.cam_a)):
            cloud = samples.time(cam.camera_id, "despeckle", _despeckled,
                                 checked[cam.camera_id], cam.shape, cam, other,
                                 phases[other.camera_id], frameset.z_range)
            out["clouds"][cam.camera_id] = cloud
            parts.append(Part(cloud.points, cloud.quality,
                              frameset.camera_index[cam.camera_id], unit.unit_id))
    for label, used in frameset.sizes().items():
        samples.time(label, "fusion", fuse, parts[:2 * len(used)])
    return out


def _side_pass(frameset: RecordedFrameSet, samples: _Samples, peers: dict[str, Callable[..., Any]],
               state: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """One repetition of the spatial path's own stages and of the peers, per camera, on the
    phases of a multi-view pass (``state``); returns the peers' results (phases,
    scikit-image's unwrapped phase) and :func:`spatial_unwrap`'s, per camera.

    Kept apart from the multi-view passes: interleaved, their large allocations (memory handed
    back and faulted in again) inflated the multi-view stages, whose sum for a 2-camera
    frame-set came to 205 ms against 124 ms for the whole. For the same reason each peer is
    compared with our stage timed again just before it, in this pass (``ours:…``), not with
    the stage table's figure.
    """
    from eyeserver.pipeline import reconstruct
    from eyeserver.pipeline.demodulate import demodulate
    from eyeserver.pipeline.reconstruct import spatial_order, spatial_unwrap

    peer_phase: dict[str, dict[str, Any]] = defaultdict(dict)
    for unit in frameset.units[:2]:
        for cam, image in ((unit.cam_a, unit.image_a), (unit.cam_b, unit.image_b)):
            cid = cam.camera_id
            phase = state["phases"][cid]
            unwrapped = samples.time(cid, "spatial_unwrapping", spatial_unwrap, phase)
            peer_phase["spatial_unwrap"][cid] = unwrapped
            peer_phase["skimage_unwrap_phase"][cid] = samples.time(
                cid, "skimage_unwrap_phase", skimage_unwrap, phase)
            other = unit.cam_b if cam is unit.cam_a else unit.cam_a
            seen = state["phases"][other.camera_id]
            with _stand_in(reconstruct, "spatial_unwrap", _returning(unwrapped)):
                # The partner's phase anew each time: its pinhole view is made in the first
                # grid_order, as in unit_clouds.
                peer_phase["spatial_order"][cid] = samples.time(
                    cid, "spatial_region_order", spatial_order, cam, phase, other,
                    _fresh(seen), frameset.z_range, None)
                peer_phase["dense_grid_votes"][cid] = samples.time(
                    cid, "dense_grid_votes", dense_grid_votes, cam, phase, other, _fresh(seen),
                    frameset.z_range)
            samples.time(cid, "ours:demodulation", demodulate, image, cam.carrier,
                         measure_bends=False)
            samples.time(cid, "ours:demodulation_bent", demodulate, image, cam.carrier)
            for name, peer in peers.items():
                peer_phase[name][cid] = samples.time(cid, name, peer, image, cam.carrier)
    return peer_phase


def _by_frameset(samples: _Samples, frameset: RecordedFrameSet, stages: Sequence[str],
                 ) -> dict[str, list[float]]:
    """Per frame-set, the seconds of ``stages`` summed over its cameras, pass by pass."""
    totals = {}
    for label, used in frameset.sizes().items():
        ids = [c.camera_id for u in used for c in (u.cam_a, u.cam_b)]
        per_pass = np.zeros(len(samples.seconds[(label, "fusion")]))
        for cid in ids:
            for stage in stages:
                per_pass += np.asarray(samples.seconds[(cid, stage)])
        totals[label] = list(per_pass + np.asarray(samples.seconds[(label, "fusion")]))
    return totals


def stages(frameset: RecordedFrameSet, frames: int = 100, progress: Progress = quiet,
           ) -> tuple[dict[str, Any], dict[str, Any]]:
    """Every stage timed on its own, ``frames`` passes over the same images after one warm-up;
    the peers timed in the same passes. Returns the stage report and the peer report."""
    from importlib import metadata

    import cv2
    import scipy

    progress(f"multi-view stages, {2 * len(frameset.units[:2])} cameras ({frames} passes)")
    ftp, ftp_reason = opencv_ftp()
    peers: dict[str, Callable[..., Any]] = {"numpy_fft_ftm": fft_ftm}
    if ftp is not None:
        peers["opencv_contrib_ftp"] = ftp
    samples = _Samples()
    last = _multi_view_pass(frameset, _Samples())  # warm-up
    for index in range(frames):
        if index and index % 25 == 0:
            progress(f"  multi-view stages, pass {index} of {frames}")
        last = _multi_view_pass(frameset, samples)
    progress(f"spatial-path stages and peers ({frames} passes)")
    try:
        last["peer_phase"] = _side_pass(frameset, _Samples(), peers, last)  # warm-up
    except cv2.error as exc:
        if "opencv_contrib_ftp" not in peers:
            raise
        # The contrib module exists but refused these images: report why, time the rest.
        del peers["opencv_contrib_ftp"]
        ftp_reason = f"cv2.structured_light FTP failed on these images: {exc}"
        last["peer_phase"] = _side_pass(frameset, _Samples(), peers, last)
    for index in range(frames):
        if index and index % 25 == 0:
            progress(f"  spatial-path stages and peers, pass {index} of {frames}")
        _side_pass(frameset, samples, peers, last)

    cameras = [c.camera_id for u in frameset.units[:2] for c in (u.cam_a, u.cam_b)]
    report: dict[str, Any] = {
        "passes": frames, "opencv_threads": 1,
        "per_camera": {cid: {stage: _summary(samples.seconds[(cid, stage)])
                             for stage in STAGES} for cid in cameras},
        "per_frameset": {},
        "reproduces_unit_clouds": _reproduces(frameset, last["clouds"]),
        "descriptions": {**STAGES, "fusion": "fuse: seam check between units, union (per "
                                             "frame-set)"},
    }
    for label, used in frameset.sizes().items():
        ids = [c.camera_id for u in used for c in (u.cam_a, u.cam_b)]
        block: dict[str, Any] = {}
        for stage in STAGES:
            block[stage] = _summary(list(np.sum([samples.seconds[(cid, stage)] for cid in ids],
                                                axis=0)))
        block["fusion"] = _summary(samples.seconds[(label, "fusion")])
        report["per_frameset"][label] = block
    for path, names in (("multi_view", MULTI_VIEW_STAGES), ("spatial", SPATIAL_STAGES)):
        for label, total in _by_frameset(samples, frameset, names).items():
            report["per_frameset"][label][f"sum_{path}"] = _summary(total)

    def stage_peer(peer: str, ours: str, what: str, against: str) -> dict[str, Any]:
        """A peer timed as a stage of the side pass against our stage ``ours``."""
        return _peer(what, against, {cid: samples.seconds[(cid, peer)] for cid in cameras},
                     {cid: samples.seconds[(cid, ours)] for cid in cameras})

    peer_report: dict[str, Any] = {}
    peer_report["skimage_unwrap_phase"] = stage_peer(
        "skimage_unwrap_phase", "spatial_unwrapping",
        "scikit-image " + metadata.version("scikit-image") + " unwrap_phase of every masked "
        "pixel (the spatial path's unwrapping before spatial_unwrap)",
        "spatial_unwrap (scikit-image's unwrapping of every second pixel), timed just before "
        "the peer in the same pass")
    peer_report["skimage_unwrap_phase"].update(_unwrap_agreement(last, cameras))
    peer_report["dense_grid_votes"] = stage_peer(
        "dense_grid_votes", "spatial_region_order",
        "spatial_order's regions voted by multi-view picks on every 3rd pixel (grid_order, "
        "then the vote: the spatial path before the sparse vote)",
        "spatial_order (picks on every 9th pixel, every 3rd where they do not settle a "
        "region), timed just before the peer in the same pass, the unwrapping stood in")
    peer_report["dense_grid_votes"].update(_order_agreement(last, cameras))
    ours_demod = {cid: samples.seconds[(cid, "ours:demodulation")] for cid in cameras}
    ours_bent = np.concatenate([samples.seconds[(cid, "ours:demodulation_bent")]
                                for cid in cameras])
    peer_report["numpy_fft_ftm"] = _peer(
        f"scipy.fft {scipy.__version__}: rfft2, fixed box of ±{FFT_BOX_HALF_WIDTH:g}·|f| around "
        "the carrier, two irfft2 (real and imaginary part of the analytic signal)",
        DEMODULATION_AGAINST, {cid: samples.seconds[(cid, "numpy_fft_ftm")] for cid in cameras},
        ours_demod)
    peer_report["numpy_fft_ftm"].update(_agreement(last, "numpy_fft_ftm", cameras))
    # The peer has no bend correction; with ours added, the ratio the pipeline pays.
    with_bends_ms = float(np.median(ours_bent)) * 1e3
    peer_report["numpy_fft_ftm"]["with_bend_correction"] = {
        "ours_median_ms": with_bends_ms,
        "time_ratio": peer_report["numpy_fft_ftm"]["peer_median_ms"] / with_bends_ms}
    if ftp is None or "opencv_contrib_ftp" not in peers:
        peer_report["opencv_contrib_ftp"] = {"available": False, "reason": ftp_reason}
    else:
        peer_report["opencv_contrib_ftp"] = _peer(
            f"OpenCV {cv2.__version__} structured_light.SinusoidalPattern, methodId FTP (the "
            "same image three times: one crashes it; phase = π/2 − its output)",
            DEMODULATION_AGAINST, {cid: samples.seconds[(cid, "opencv_contrib_ftp")]
                                   for cid in cameras}, ours_demod)
        peer_report["opencv_contrib_ftp"].update(_agreement(last, "opencv_contrib_ftp",
                                                            cameras))
    return report, peer_report


DEMODULATION_AGAINST = ("demodulate without its bend correction (the same method: the peer has "
                        "none), timed just before the peer in the same pass")


def _peer(what: str, against: str, peer_s: dict[str, list[float]],
          ours_s: dict[str, list[float]]) -> dict[str, Any]:
    """Peer and our times per camera and pooled, and their ratio ``time_ratio`` (peer ÷ ours:
    above 1 when ours is faster)."""
    per_camera = {}
    for cid in peer_s:
        peer, ours = _summary(peer_s[cid]), _summary(ours_s[cid])
        per_camera[cid] = {"peer": peer, "ours": ours,
                           "time_ratio": peer["median_ms"] / ours["median_ms"]}
    peer_ms = float(np.median(np.concatenate(list(peer_s.values())))) * 1e3
    ours_ms = float(np.median(np.concatenate(list(ours_s.values())))) * 1e3
    return {"available": True, "peer": what, "against": against,
            "peer_median_ms": peer_ms, "ours_median_ms": ours_ms,
            "time_ratio": peer_ms / ours_ms, "per_camera": per_camera}


def _agreement(state: dict[str, Any], name: str, cameras: Sequence[str]) -> dict[str, Any]:
    """|peer's wrapped phase − demodulate's| inside the pipeline's mask, rad (median, p95)."""
    differences = []
    for cid in cameras:
        ours = state["demodulated"][cid].wrapped_phase
        theirs = state["peer_phase"][name][cid]
        valid = state["phases"][cid].valid
        differences.append(np.abs(np.angle(np.exp(1j * (theirs[valid] - ours[valid])))))
    pooled = np.concatenate(differences) if differences else np.zeros(1)
    return {"phase_vs_ours_median_rad": float(np.median(pooled)),
            "phase_vs_ours_p95_rad": float(np.percentile(pooled, 95))}


def _unwrap_agreement(state: dict[str, Any], cameras: Sequence[str]) -> dict[str, Any]:
    """How often :func:`spatial_unwrap`'s steps differ from scikit-image's on the whole image
    beyond one offset per region (which the region's vote sets anyway), over the pixels both
    unwrap, and how many of scikit-image's pixels ours leaves out."""
    differ = left_out = total = 0
    for cid in cameras:
        ours = state["peer_phase"]["spatial_unwrap"][cid]
        theirs = np.ma.getdata(state["peer_phase"]["skimage_unwrap_phase"][cid]).ravel()
        phase = state["phases"][cid]
        steps = np.rint((theirs[ours.pixels] - phase.dphi.ravel()[ours.pixels])
                        / (2 * np.pi)).astype(np.int64) - ours.steps
        for region in np.unique(ours.region):
            _, counts = np.unique(steps[ours.region == region], return_counts=True)
            differ += int(counts.sum() - counts.max())
        left_out += int(phase.valid.sum()) - len(ours.pixels)
        total += int(phase.valid.sum())
    return {"orders_differ_share": differ / max(total, 1),
            "left_out_share": left_out / max(total, 1)}


def _order_agreement(state: dict[str, Any], cameras: Sequence[str]) -> dict[str, Any]:
    """Over the pixels either vote orders, the share whose order (or whether it has one)
    differs between :func:`spatial_order` and the dense vote."""
    differ = total = 0
    for cid in cameras:
        size = state["phases"][cid].dphi.size
        orders = []
        for name in ("spatial_order", "dense_grid_votes"):
            pixels, order, _ = state["peer_phase"][name][cid]
            image = np.full(size, np.iinfo(np.int64).min)
            image[pixels] = order
            orders.append(image)
        either = np.flatnonzero((orders[0] != np.iinfo(np.int64).min)
                                | (orders[1] != np.iinfo(np.int64).min))
        differ += int(np.count_nonzero(orders[0][either] != orders[1][either]))
        total += either.size
    return {"pixel_orders_differ_share": differ / max(total, 1)}


def _reproduces(frameset: RecordedFrameSet, clouds: dict[str, CameraCloud]) -> bool:
    """Do the stages, called one by one, give unit_clouds' points (same pixels)?"""
    from eyeserver.pipeline.reconstruct import unit_clouds

    for unit in frameset.units[:2]:
        pair = unit_clouds(unit.cam_a, unit.image_a, unit.cam_b, unit.image_b,
                           frameset.z_range, saturation_dn=frameset.saturation_dn)
        for cloud in pair:
            if not np.array_equal(np.sort(cloud.pixels),
                                  np.sort(clouds[cloud.camera_id].pixels)):
                return False
    return True


# --- peers ----------------------------------------------------------------------------------

FFT_BOX_HALF_WIDTH = 0.5
"""Half-side of the plain FFT baseline's box band, as a fraction of the carrier's |f|: the box
then rejects the background (|f| away) and the conjugate fringe (2|f| away) for any carrier."""


def fft_ftm(image: npt.ArrayLike, carrier: Carrier) -> F32:
    """The plain FFT Fourier-transform method (Takeda 1982): wrapped phase of ``image``.

    ``rfft2``, a fixed box band around the carrier, and the analytic signal back from two real
    inverse transforms (real part ½·irfft2(band), imaginary part ½·irfft2(−i·band)); no border
    handling, no taper. The image is transposed when the carrier runs mostly along the rows, so
    the band never touches the real transform's zero column. The phase has
    :func:`demodulate`'s sign convention.
    """
    import scipy.fft

    values = np.asarray(image, dtype=np.float32)
    fy, fx = carrier.frequency
    transposed = abs(fy) > abs(fx)
    if transposed:
        values, fy, fx = values.T, fx, fy
    sign = 1.0 if fx > 0 else -1.0  # the band at +f; the conjugate one gives −φ
    fy, fx = sign * fy, sign * fx
    height, width = values.shape
    half = FFT_BOX_HALF_WIDTH * carrier.cycles_per_px
    rows = np.flatnonzero(np.abs(np.fft.fftfreq(height) - fy) <= half)
    cols = np.flatnonzero(np.abs(np.fft.rfftfreq(width) - fx) <= half)
    spectrum = scipy.fft.rfft2(values - np.float32(values.mean()), workers=1)
    band = np.zeros_like(spectrum)
    band[np.ix_(rows, cols)] = spectrum[np.ix_(rows, cols)]
    real = scipy.fft.irfft2(band, s=(height, width), workers=1)
    imaginary = scipy.fft.irfft2(-1j * band, s=(height, width), workers=1)
    phase = np.arctan2(imaginary, real).astype(np.float32) * np.float32(sign)
    return np.ascontiguousarray(phase.T if transposed else phase)


def _opencv_distributions() -> dict[str, str]:
    from importlib import metadata

    found = {}
    for name in ("opencv-python-headless", "opencv-python", "opencv-contrib-python-headless",
                 "opencv-contrib-python"):
        try:
            found[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return found


def opencv_ftp() -> tuple[Callable[[npt.ArrayLike, Carrier], F32] | None, str]:
    """OpenCV contrib's ``structured_light`` FTP as a phase function with
    :func:`demodulate`'s conventions, or None and why it is unavailable.

    Its traps (docs/notes/design-measurements.md): a single image crashes the process (so the
    same image goes in three times), its phase is π/2 minus the fringe's, its filter is a fixed
    42×42 box around the spectral peak, and its unwrapper's mask follows the ``Params`` size
    (set to the image's).
    Only 8-bit images give the right phase: deeper ones are scaled to 8 bits first.
    """
    import cv2

    structured_light = getattr(cv2, "structured_light", None)
    if structured_light is None:
        installed = _opencv_distributions()
        have = ", ".join(f"{n} {v}" for n, v in installed.items()) or "an unknown distribution"
        version = next(iter(installed.values()), "<the same version>")
        return None, (f"cv2.structured_light is missing: OpenCV {cv2.__version__} comes from "
                      f"{have}, without the contrib modules; opencv-contrib-python-headless=="
                      f"{version} in its place provides them (a superset; never install both, "
                      "they share the cv2 package)")
    patterns: dict[tuple[int, int, bool], Any] = {}

    def phase(image: npt.ArrayLike, carrier: Carrier) -> F32:
        pixels = np.asarray(image)
        if pixels.dtype != np.uint8:
            # Measured: float32 and 16-bit input give a phase off by radians; 8 bits work.
            span = max(float(pixels.max()), 1.0)
            pixels = np.clip(np.rint(pixels * (255.0 / span)), 0, 255).astype(np.uint8)
        fy, fx = carrier.frequency
        key = (pixels.shape[0], pixels.shape[1], abs(fy) > abs(fx))
        if key not in patterns:
            params = structured_light.SinusoidalPattern.Params()
            params.height, params.width, params.horizontal = key
            params.methodId = structured_light.FTP
            patterns[key] = structured_light.SinusoidalPattern_create(params)
        wrapped, _ = patterns[key].computePhaseMap([pixels, pixels, pixels])
        converted = np.float32(np.pi / 2) - np.asarray(wrapped, dtype=np.float32)
        return np.asarray(np.angle(np.exp(1j * converted)), dtype=np.float32)

    return phase, "available"


# --- memory ---------------------------------------------------------------------------------


def peak_rss_mib() -> float:
    """The process's peak resident set so far, MiB (ru_maxrss: KiB on Linux, bytes on macOS)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return float(peak) / (2 ** 20 if sys.platform == "darwin" else 2 ** 10)


def traced_peak_mib(frameset: RecordedFrameSet, units: Sequence[UnitImages]) -> float:
    """Peak of the memory Python's allocators see (numpy arrays included; OpenCV's and the
    FFT's internal buffers not) while one multi-view frame-set is reconstructed, MiB."""
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        baseline, _ = tracemalloc.get_traced_memory()
        reconstruct_frameset(frameset, units, "multi-view")
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    return (peak - baseline) / 2 ** 20


# --- the report -----------------------------------------------------------------------------


class TrackingRun(NamedTuple):
    """One of the speed report's live-tracking runs (:data:`TRACKING_RUNS`)."""

    prefix: str
    """Of its flat figures (``{prefix}frame_to_pose_p99_ms``…)."""
    how: str
    """How the room served the frames, for the page."""
    room: str
    """The same, short, for the text output."""
    goal_p99_ms: float
    """Its latency goal, frame → pose p99."""


TRACKING_RUNS: dict[str, TrackingRun] = {
    "tracking": TrackingRun(
        "", "the simulated room renders each frame set on the same cores",
        "rendered live on the same cores", TRACKING_GOAL_P99_MS),
    "tracking_prerendered": TrackingRun(
        "prerendered_", "the simulated room's frames rendered before tracking (eyeserver bench "
        "tracking --prerendered): the cameras cost the cores nothing, as real ones",
        "rendered ahead", TRACKING_GOAL_P99_MS),
    "tracking_both_units": TrackingRun(
        "both_units_", "both units tracked (eyeserver bench tracking --unit all: four cameras, "
        "each unit's frames in turn), the simulated room renders each frame set on the same "
        "cores", "rendered live, both units tracked", BOTH_UNITS_GOAL_P99_MS),
    "tracking_patient": TrackingRun(
        "patient_", "a patient's eye drawn from the population (eyeserver bench tracking "
        "--eyes patient --prerendered), the room's frames rendered before tracking",
        "rendered ahead, a patient's eye", TRACKING_GOAL_P99_MS),
}
"""The speed report's live-tracking runs, by the key of their block."""

PATIENT_EYE_SEED = 0
"""The patient eye of the speed report's ``tracking_patient`` run
(:func:`eyeserver.hardware.sim.population.draw` with this seed; the report describes it)."""


def tracking_figures(live: dict[str, Any] | None, ahead: dict[str, Any] | None,
                     both: dict[str, Any] | None = None,
                     patient: dict[str, Any] | None = None) -> dict[str, Any]:
    """The speed report's part for ``eyeserver bench tracking``'s reports, the simulated room
    rendered ``live`` and rendered ``ahead``, ``both`` units tracked, rendered live, and a
    ``patient``'s eye, rendered ahead (any None: not run); the runs as :data:`TRACKING_RUNS`
    names them."""
    report: dict[str, Any] = {}
    for (key, (prefix, how, _, goal_ms)), run_report in zip(
            TRACKING_RUNS.items(), (live, ahead, both, patient), strict=True):
        if run_report is None:
            continue
        latency, counted = run_report["latency_ms"], run_report["frames"]
        report[key] = {
            "seconds": run_report["seconds"],
            "what": "eyeserver bench tracking: a daemon on loopback tracks the moving simulated "
                    f"eye at 25 Hz, {how}{tracking.eye_text(run_report.get('eye'))}; latency "
                    "from a frame's mid-exposure to its pose message received by a WebSocket "
                    "client",
            "latency_ms": latency, "frames": counted, "slowest": run_report["slowest"],
            "beam_hold_reaction": run_report["beam_hold_reaction"],
            "blink": run_report.get("blink"), "accuracy": run_report.get("accuracy"),
            "clients": run_report["clients"],
            "reference_fft_ms": run_report["reference_fft_ms"], "goal_p99_ms": goal_ms}
        report[f"{prefix}frame_to_pose_median_ms"] = latency["end_to_end_median"]
        report[f"{prefix}frame_to_pose_p99_ms"] = latency["end_to_end_p99"]
        report[f"{prefix}tracking_processed_share"] = counted["processed_share"]
    if report:
        report["frame_to_pose_goal_p99_ms"] = TRACKING_GOAL_P99_MS
    return report


def run(config: RoomConfig, frames: int = 100, progress: Progress = quiet,
        calibration: Path | None = None, room_file: Path | None = None,
        api_requests: int = 10, tracking_seconds: int = 60,
        replay_seconds: int = 10, replay_workers: int = 2) -> dict[str, Any]:
    """The whole speed report as one JSON-able document (``calibration``: a calibration of the
    simulated rig; made on the spot when not given). ``room_file`` is the file ``config`` came
    from (None: the default room), for the daemon of the API timings; ``api_requests`` requests
    of each kind are timed through the API (0: none); live tracking runs ``tracking_seconds``
    through a daemon four times (:mod:`eyeserver.bench.tracking`, 0: not run) for the frame →
    pose latency, the simulated room rendered live and rendered ahead, both units tracked
    (rendered live: the room renders ahead for one unit), a patient's eye
    (:data:`PATIENT_EYE_SEED`, rendered ahead), and its pipeline alone on
    ``replay_seconds`` of frames rendered beforehand
    (:func:`~eyeserver.bench.tracking.replayed` with ``replay_workers`` worker processes, 0:
    not run)."""
    started = time.perf_counter()
    load_at_start = os.getloadavg()
    reference_at_start = reference_ms()
    render = sim_render(config, frames, progress)
    with tempfile.TemporaryDirectory(prefix="eyeserver-speed-") as tmp:
        work = Path(tmp)
        if calibration is None:
            progress("calibrating the simulated rig for the pipeline timings")
            calibration = calibrate_room(config, work, 0, progress)
        frameset = record_frameset(config, calibration, work)
        api = None
        if api_requests:
            api = api_latency(calibration, work, api_requests, room_file, progress)
        live = ahead = both = patient = None
        patient_refused: dict[str, Any] | None = None
        if tracking_seconds:
            progress(f"live tracking for {tracking_seconds} s (frame → pose latency), the room "
                     "rendered live")
            (work / "tracking").mkdir()
            live = tracking.run(tracking_seconds, calibration=calibration, room_file=room_file,
                                work=work / "tracking", progress=progress)
            progress(f"live tracking for {tracking_seconds} s, the room rendered ahead")
            (work / "tracking-ahead").mkdir()
            ahead = tracking.run(tracking_seconds, calibration=calibration,
                                 room_file=room_file, work=work / "tracking-ahead",
                                 prerendered=True, progress=progress)
            progress(f"live tracking for {tracking_seconds} s with both units, the room "
                     "rendered live")
            (work / "tracking-both").mkdir()
            both = tracking.run(tracking_seconds, calibration=calibration, room_file=room_file,
                                work=work / "tracking-both", unit="all", progress=progress)
            progress(f"live tracking for {tracking_seconds} s of a patient's eye, the room "
                     "rendered ahead")
            (work / "tracking-patient").mkdir()
            try:
                patient = tracking.run(tracking_seconds, calibration=calibration,
                                       room_file=room_file, work=work / "tracking-patient",
                                       prerendered=True, eyes="patient",
                                       seed=PATIENT_EYE_SEED, progress=progress)
            except tracking.ReferenceRefusedError as exc:
                patient_refused = {"seed": PATIENT_EYE_SEED, "eye": tracking.eye_text(exc.eye),
                                   "reason": exc.reason}
        alone = None
        if replay_seconds:
            progress(f"live tracking's pipeline alone, {replay_seconds} s replayed")
            alone = tracking.replayed(calibration, replay_seconds, room_file=room_file,
                                      workers=replay_workers, progress=progress)
    cameras = frame_path(config, min(frames, 100), progress)
    rss_before_mib = peak_rss_mib()
    with _threads(1):
        reconstruction = pipeline(frameset, frames, progress)
        stage_report, peer_report = stages(frameset, frames, progress)
        threads = parallel(frameset, frames, progress)
        progress("memory of one frame-set (tracemalloc)")
        traced = {f"frameset_{label}_traced_peak_mib": traced_peak_mib(frameset, used)
                  for label, used in frameset.sizes().items()}
    single = {f"framesets_{label}_per_s": 1e3 / reconstruction[f"multi-view_{label}"]
              ["median_ms"] for label in frameset.sizes()}
    threads["single_thread"] = single
    report: dict[str, Any] = {
        "format": "eyeserver.bench.speed/1",
        "machine": {**machine(), "opencv_threads_during_reconstruction": 1,
                    "blas_threads_during_reconstruction": 1,
                    "openblas_num_threads": os.environ.get("OPENBLAS_NUM_THREADS", "unset"),
                    # Other work on the cores inflates every figure: say how busy they were.
                    "load_average_at_start": [round(x, 2) for x in load_at_start],
                    "load_average_at_end": [round(x, 2) for x in os.getloadavg()],
                    "reference_fft_ms_at_start": round(reference_at_start, 2),
                    "reference_fft_ms_at_end": round(reference_ms(), 2)},
        "units": "milliseconds per frame-set or call (median unless named p95); frame-sets "
                 "are images in memory → fused cloud",
        "goals_ms": dict(GOALS_MS),
        "sim_render": render,
        "frame_path": cameras,
        "reconstruction": reconstruction,
        "stages": stage_report,
        "parallel": threads,
        "peers": peer_report,
        "memory": {"peak_rss_mib": peak_rss_mib(),
                   "peak_rss_before_reconstruction_mib": rss_before_mib, **traced},
    }
    for label in ("2cam", "4cam"):
        if f"multi-view_{label}" in reconstruction:
            report[f"frameset_{label}_ms"] = reconstruction[f"multi-view_{label}"]["median_ms"]
            report[f"framesets_{label}_per_s"] = single[f"framesets_{label}_per_s"]
    if "units_in_parallel_4cam" in threads:
        report["frameset_4cam_2threads_ms"] = threads["units_in_parallel_4cam"]["median_ms"]
        report["framesets_4cam_2threads_per_s"] = threads["units_in_parallel_4cam_per_s"]
    report["peak_rss_mib"] = report["memory"]["peak_rss_mib"]
    if api is not None:
        report["api"] = {
            "requests": api_requests,
            "what": "request sent → answer received, from a client on loopback to an "
                    "'eyeserver serve' process: a capture until its 201 (bundle durable; the "
                    "simulated room renders the images), a reconstruction until its summary "
                    "(bundle read, pipeline, cloud.ply written)",
            "captures": {unit: _summary(s) for unit, s in api["captures"].items()},
            "reconstructions": {unit: _summary(s) for unit, s in api["reconstructions"].items()},
        }
        report["api_capture_all_ms"] = report["api"]["captures"]["all"]["median_ms"]
        report["api_reconstruction_all_ms"] = report["api"]["reconstructions"]["all"]["median_ms"]
    if "moving_eye_2cam" in render:
        report["sim_render_2cam_ms"] = render["moving_eye_2cam"]["median_ms"]
    if "moving_eye_4cam" in render:
        report["sim_render_4cam_ms"] = render["moving_eye_4cam"]["median_ms"]
    report.update(tracking_figures(live, ahead, both, patient))
    if patient_refused is not None:
        report["tracking_patient_refused"] = patient_refused
    if alone is not None:
        report["tracking_replay"] = alone
        report["pipeline_frame_to_pose_median_ms"] = alone["latency_ms"]["median"]
        report["pipeline_frame_to_pose_p99_ms"] = alone["latency_ms"]["p99"]
        report["pipeline_processed_share"] = alone["processed_share"]
    report["duration_s"] = round(time.perf_counter() - started, 1)
    return report


def _ms(value: float) -> str:
    return f"{value:.1f}" if value >= 1 or value == 0 else f"{value:.2f}"


def _whole_ms(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.0f} ms"


def refused_text(refused: dict[str, Any]) -> str:
    """The patient-eye run that did not track (``tracking_patient_refused``), in words."""
    return (f"Live tracking of a patient's eye{refused['eye']}: not run, the daemon refused "
            f"the reference captured at rest: {refused['reason']}.")


def tracking_lines(report: dict[str, Any]) -> list[str]:
    """:func:`format_text`'s lines for the live-tracking runs of a speed report."""
    lines: list[str] = []
    if report.get("tracking_patient_refused"):
        lines += ["", refused_text(report["tracking_patient_refused"])]
    for key, run in TRACKING_RUNS.items():
        live = report.get(key)
        if not live:
            continue
        share = live["frames"]["processed_share"]
        latency = live["latency_ms"]
        lines.append("")
        lines.append(f"live tracking ({live['seconds']} s at 25 Hz, the simulated room "
                     f"{run.room}): frame → pose message "
                     f"{_whole_ms(latency['end_to_end_median'])} median, "
                     f"{_whole_ms(latency['end_to_end_p99'])} p99 (goal p99 "
                     f"{live.get('goal_p99_ms', run.goal_p99_ms):.0f} ms); "
                     f"{'n/a' if share is None else f'{100 * share:.1f}'} % of the camera "
                     f"frames processed (goal 99 %), the rest dropped (newest frame wins) "
                     f"or missed, and counted")
    return lines


def format_text(report: dict[str, Any]) -> str:
    """Human-readable tables of the report."""
    lines = [f"eyeserver bench speed — {report['machine']['platform']}, "
             f"{report['machine']['cpu_count']} CPUs, Python {report['machine']['python']}"]
    if "load_average_at_start" in report["machine"]:
        lines.append("load average (1, 5, 15 min) at start "
                     f"{report['machine']['load_average_at_start']}, at end "
                     f"{report['machine']['load_average_at_end']}: other work on the cores "
                     "inflates every figure")
    if "reference_fft_ms_at_start" in report["machine"]:
        lines.append("machine speed: one 640 × 512 FFT took "
                     f"{report['machine']['reference_fft_ms_at_start']:.2f} ms at start, "
                     f"{report['machine']['reference_fft_ms_at_end']:.2f} ms at end (compare "
                     "figures only between runs at similar values)")
    lines.append("")
    lines.append(f"{'simulated room render':<34}{'median ms':>10}{'p95 ms':>10}")
    for key, value in report["sim_render"].items():
        lines.append(f"  {key.replace('_', ' '):<32}{value['median_ms']:>10.1f}"
                     f"{value['p95_ms']:>10.1f}")
    lines.append("goal: a live 2-camera frame in ≤ 20 ms (25 Hz, sharing the cores with "
                 "reconstruction)")
    lines.append("")
    if "frame_path" in report:
        lines += frame_path_lines(report["frame_path"])
    goals = report.get("goals_ms", GOALS_MS)
    lines.append(f"{'frame-sets (images → fused cloud)':<44}{'median ms':>10}{'p95 ms':>10}"
                 f"{'per s':>8}{'goal ms':>9}")
    for key, value in report["reconstruction"].items():
        method, label = key.rsplit("_", 1)
        goal = goals.get(f"frameset_{label}_ms")
        lines.append(f"  {method + ', ' + label + ', one thread':<42}{value['median_ms']:>10.1f}"
                     f"{value['p95_ms']:>10.1f}{1e3 / value['median_ms']:>8.1f}"
                     f"{'≤ ' + format(goal, 'g') if goal and method == 'multi-view' else '':>9}")
    threads = report.get("parallel", {})
    if "units_in_parallel_4cam" in threads:
        value = threads["units_in_parallel_4cam"]
        lines.append(f"  {'multi-view, 4cam, units on 2 threads':<42}{value['median_ms']:>10.1f}"
                     f"{value['p95_ms']:>10.1f}{1e3 / value['median_ms']:>8.1f}"
                     f"{'≤ ' + format(goals['frameset_4cam_ms'], 'g'):>9}")
    for label in ("2cam", "4cam"):
        value = threads.get(f"framesets_per_worker_{label}")
        if value:
            lines.append(f"  {'multi-view, ' + label + ', a frame-set per thread':<42}"
                         f"{value['wall_ms_per_frameset']:>10.1f}{'':>10}"
                         f"{value['framesets_per_s']:>8.1f}   (throughput, wall time ÷ n)")
    lines.append("goal: a 2-camera frame-set in ≤ 10 ms, a 4-camera one in ≤ 20 ms on 2 cores "
                 "(docs/design.md §6)")
    stage_report = report.get("stages")
    if stage_report:
        lines.append("")
        cameras = list(stage_report["per_camera"])
        sets = list(stage_report["per_frameset"])
        lines.append(f"stages, median ms per camera ({stage_report['passes']} passes, one "
                     "thread); frame-set columns: median / p95 of the cameras' sum")
        header = f"{'stage':<24}" + "".join(f"{c:>7}" for c in cameras)
        header += "".join(f"{s:>16}" for s in sets)
        lines.append(header)
        for stage in [*STAGES, "fusion", "sum_multi_view", "sum_spatial"]:
            row = f"  {stage:<22}"
            for cid in cameras:
                value = stage_report["per_camera"][cid].get(stage)
                row += f"{_ms(value['median_ms']) if value else '':>7}"
            for label in sets:
                value = stage_report["per_frameset"][label][stage]
                row += f"{_ms(value['median_ms']) + ' / ' + _ms(value['p95_ms']):>16}"
            lines.append(row)
        if not stage_report["reproduces_unit_clouds"]:
            lines.append("WARNING: the stages called one by one did not give unit_clouds' "
                         "points: the bench has drifted from reconstruct.py")
    peers = report.get("peers")
    if peers:
        lines.append("")
        lines.append(f"{'peers, same images':<44}{'peer ms':>9}{'ours ms':>9}{'peer/ours':>11}")
        names = {"skimage_unwrap_phase": "scikit-image unwrap_phase vs spatial_unwrap",
                 "dense_grid_votes": "votes on every 3rd pixel vs spatial_order",
                 "numpy_fft_ftm": "plain FFT FTM (box band) vs demodulate",
                 "opencv_contrib_ftp": "OpenCV contrib FTP vs demodulate"}
        for key, label in names.items():
            peer = peers.get(key)
            if not peer:
                continue
            if not peer["available"]:
                lines.append(f"  {label}: unavailable — {peer['reason']}")
                continue
            line = (f"  {label:<42}{peer['peer_median_ms']:>9.1f}{peer['ours_median_ms']:>9.1f}"
                    f"{peer['time_ratio']:>11.2f}")
            if "phase_vs_ours_median_rad" in peer:
                line += (f"   phase vs ours: median {peer['phase_vs_ours_median_rad']:.3f} rad,"
                         f" p95 {peer['phase_vs_ours_p95_rad']:.3f} rad")
            if "orders_differ_share" in peer:
                line += (f"   orders differ on {100 * peer['orders_differ_share']:.3f} %, "
                         f"{100 * peer['left_out_share']:.3f} % left out")
            if "pixel_orders_differ_share" in peer:
                line += f"   orders differ on {100 * peer['pixel_orders_differ_share']:.3f} %"
            lines.append(line)
            bent = peer.get("with_bend_correction")
            if bent:
                lines.append(f"  {'  ours with its bend correction':<42}{'':>9}"
                             f"{bent['ours_median_ms']:>9.1f}{bent['time_ratio']:>11.2f}")
    api = report.get("api")
    if api:
        lines.append("")
        lines.append(f"{'through the API (eyeserver serve, loopback)':<44}{'median ms':>10}"
                     f"{'p95 ms':>10}")
        for what, table in (("capture →201", api["captures"]),
                            ("reconstruction", api["reconstructions"])):
            for unit, value in table.items():
                lines.append(f"  {what + ' of ' + unit:<42}{value['median_ms']:>10.1f}"
                             f"{value['p95_ms']:>10.1f}")
        lines.append(f"({api['requests']} requests each; {api['what']})")
    memory = report.get("memory")
    if memory:
        lines.append("")
        traced = ", ".join(f"{k.split('_')[1]} frame-set {v:.0f} MiB" for k, v in memory.items()
                           if k.endswith("_traced_peak_mib"))
        lines.append(f"memory: peak resident set {memory['peak_rss_mib']:.0f} MiB (before the "
                     f"reconstruction timings {memory['peak_rss_before_reconstruction_mib']:.0f}"
                     f" MiB); Python-visible peak of one frame-set: {traced}")
    lines += tracking_lines(report)
    if report.get("tracking_replay"):
        lines.append(tracking.format_replayed(report["tracking_replay"]))
    lines.append("")
    lines.append(f"took {report['duration_s']} s")
    return "\n".join(lines)

