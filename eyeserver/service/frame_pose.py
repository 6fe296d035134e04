"""One frame set's pose: reconstruct it and find the eye in it, as a tracking worker does.

::

    FrameSet ──► RigReconstructor ──► TrackedCloud ──► PoseFinder ──► EyePose
                 (one calibration;     (fused cloud,      (followed from the last pose,
                 the eye's window)     its images)        else the global fit)

Once a frame gave a pose, the next ones are followed from it (the eye moves little in 40 ms):
only a window around the eye is reconstructed (:meth:`RigReconstructor.focus`) and the globe
refitted from the last pose (:func:`~eyeserver.eye.track.track_eye`); the global fit
(:func:`~eyeserver.eye.fit.fit_eye`) of the whole images comes back when the warm fit fails or
finds no limbus (:class:`PoseFinder`). Measured: docs/notes/tracking.md.

:class:`PoseFinder` works in the calling process,
:class:`~eyeserver.service.tracking_worker.PoseWorker` runs one in a child process; live
tracking (:mod:`eyeserver.service.tracking`) takes either as a :class:`FindPose`.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np
import numpy.typing as npt

from eyeserver.calibration.artefact import load_calibration
from eyeserver.eye import (
    LIMBUS_FROM_IMAGES,
    CloudLike,
    EyeModel,
    EyePose,
    LimbusView,
    PoseError,
    fringe_removed,
    pose_window,
)
from eyeserver.hardware.rig import AcquiredStep
from eyeserver.io import PointCloud, RigSpec
from eyeserver.pipeline.fusion import Part, fuse
from eyeserver.pipeline.reconstruct import (
    CalibratedCamera,
    Phase,
    camera_phase,
    cropped,
    decimated,
    fringe_strength,
    strong_modulation,
    unit_clouds,
)
from eyeserver.reconstruction import (
    ReconstructionError,
    calibrated_cameras,
    unit_method,
    z_range,
)
from eyeserver.service.verification import FitFunction, unit_shortfalls

__all__ = ["WINDOW_DECIMATION", "FindPose", "FocusingReconstructor", "FrameSet", "PoseFinder",
           "Reconstructor", "RigReconstructor", "TrackFunction", "TrackedCloud", "blind_alone"]

_MAX_WINDOWS = 8  # cropped cameras kept (each ≈ 19 MB: pixel grids, rays, the partner maps)

WINDOW_DECIMATION = 3
"""Tracking reconstructs every third pixel of the eye's window in each direction (after
demodulating it whole, for the limbus): a ninth of the points, ample for a fit whose globe
keeps its radius and sits on the limbus found in the images; the confidence counts them as the
pixels they stand for (:attr:`TrackedCloud.pixels_per_point`). Measured on 55 frames of a
drifting rendered eye (one unit, radius held, one worker alone): poses identical to those from
every second pixel (to 1e-6 mm and 1e-4°; those had been identical to the full window's to the
printed 0.0001 mm), a tracked frame 21.7 → 18.1 ms (its reconstruction 14 → 11 ms)."""


@dataclass(frozen=True)
class FrameSet:
    """One camera frame of the tracked unit(s).

    Attributes
    ----------
    frame : int
        The camera frame number since tracking started (one per camera period).
    t_ns : int
        Mid-exposure time, ns on the rig's monotonic clock.
    steps : sequence of AcquiredStep
        The rig's frames (one step per unit); empty for scripted sources.
    data : object
        Anything a scripted source hands its scripted reconstruction (tests).
    arrived_ns : int, optional
        When the frame set was in the daemon's hands, ns on the same clock (None: not known).
    """

    frame: int
    t_ns: int
    steps: Sequence[AcquiredStep] = ()
    data: object = None
    arrived_ns: int | None = None



Reconstructor = Callable[[FrameSet], CloudLike]
"""Turns a frame set into a point cloud (WCS, mm)."""


class TrackFunction(Protocol):
    """Cloud, eye model, the last frame's pose and, when given, the fringe images the cloud came
    from → pose (:func:`~eyeserver.eye.track.track_eye`); raises
    :class:`~eyeserver.eye.fit.PoseError` when it cannot follow the eye."""

    def __call__(self, cloud: CloudLike, model: EyeModel, previous: EyePose,
                 views: Sequence[LimbusView] = (), /) -> EyePose: ...


@dataclass(frozen=True)
class TrackedCloud:
    """A frame set's fused cloud (WCS, mm) with the images it came from, for the limbus.

    ``views`` are the cameras and images (or their windows around the eye) the cloud was
    reconstructed from (:class:`~eyeserver.eye.limbus.LimbusView`); ``pixels_per_point``
    the image pixels each point stands for (:data:`WINDOW_DECIMATION` squared in a window,
    else 1).
    """

    points: npt.NDArray[np.float32]
    quality: npt.NDArray[np.float32] | None
    camera: npt.NDArray[np.uint8] | None
    views: tuple[LimbusView, ...] = ()
    pixels_per_point: float = 1.0


@runtime_checkable
class FocusingReconstructor(Protocol):
    """A reconstruction that can confine itself to where the eye is."""

    def __call__(self, frame_set: FrameSet) -> CloudLike:
        """Frame set → cloud (WCS, mm)."""
        ...

    def focus(self, pose: EyePose | None) -> None:
        """Reconstruct only around ``pose``'s eye from now on; None: the whole images."""
        ...


class FindPose(Protocol):
    """Frame set and the last frame's pose (None: none yet, or the eye was lost) → this frame's
    pose; raises :class:`~eyeserver.eye.fit.PoseError`,
    :class:`~eyeserver.reconstruction.ReconstructionError` or :class:`ValueError` for
    a frame without an eye (lost). :meth:`close` frees what it holds (a worker process)."""

    def __call__(self, frame_set: FrameSet, previous: EyePose | None, /) -> EyePose: ...

    def warm(self, frame_set: FrameSet, expected: EyePose, /) -> None:
        """Fill what following ``expected``'s eye keeps from frame to frame (the window's
        cameras, the fringe strength) from a frame set taken before the stream; nothing is
        fitted or published."""
        ...

    def close(self) -> None: ...


class PoseFinder:
    """Reconstruct a frame set and find the eye in it, in this process (:class:`FindPose`).

    With a last pose and a ``track``, the eye is followed from it
    (:func:`~eyeserver.eye.track.track_eye`), in the window around it where the
    reconstruction is a :class:`FocusingReconstructor`. Where the reconstruction gives the
    images the cloud came from (:class:`TrackedCloud`), a followed pose counts only when its
    limbus was found in them (or the lids cover the eye: a blink): the cloud-only warm fit
    locks on to whatever lies near the last pose, so an eye that moved more than about a
    millimetre while its limbus was not seen would be reported near where it was (measured: an
    eye 4 mm away came out 4.3 mm off, with no error). Such a frame, one where following fails
    (:class:`PoseError`) and one with no last pose get the global fit ``fit``
    (:func:`~eyeserver.eye.fit.fit_eye`) of the whole images. Without a ``track``
    every frame gets ``fit``, in the window around the last pose.

    Parameters
    ----------
    reconstruct : Reconstructor
        Frame set → cloud.
    fit : FitFunction
        Cloud, eye model (and images) → pose.
    model : EyeModel
        The patient's eye model.
    track : TrackFunction, optional
        Cloud, eye model, last pose (and images) → pose; None fits every frame with ``fit``.
    """

    def __init__(self, reconstruct: Reconstructor, fit: FitFunction, model: EyeModel,
                 track: TrackFunction | None = None) -> None:
        self.reconstruct = reconstruct
        self.fit = fit
        self.model = model
        self.track = track

    def __call__(self, frame_set: FrameSet, previous: EyePose | None) -> EyePose:
        cloud = self._cloud(frame_set, previous)
        if previous is not None and self.track is not None:
            views = _views(cloud)
            with contextlib.suppress(PoseError):
                pose = (self.track(cloud, self.model, previous, views) if views
                        else self.track(cloud, self.model, previous))
                if not views or pose.gaze_source in _CONFIRMED:
                    return pose
            if isinstance(self.reconstruct, FocusingReconstructor):
                cloud = self._cloud(frame_set, None)  # the eye may have left the window
        views = _views(cloud)
        return self.fit(cloud, self.model, views) if views else self.fit(cloud, self.model)

    def warm(self, frame_set: FrameSet, expected: EyePose) -> None:
        """Reconstruct ``frame_set`` around ``expected``'s eye (a focusing reconstruction keeps
        that window's cameras and the fringe strength of the images); the cloud is dropped."""
        if isinstance(self.reconstruct, FocusingReconstructor):
            self._cloud(frame_set, expected)

    def _cloud(self, frame_set: FrameSet, focus: EyePose | None) -> CloudLike:
        if isinstance(self.reconstruct, FocusingReconstructor):
            self.reconstruct.focus(focus)
        return self.reconstruct(frame_set)

    def close(self) -> None:
        """Nothing to free in this process."""


_CONFIRMED = (LIMBUS_FROM_IMAGES, "none")
"""The gaze sources of a followed pose that are not the cloud-only warm fit's guess: the
limbus found in the images, or none at all (the lids closed: the beam is held and the next
frame must find the limbus)."""


def _views(cloud: CloudLike) -> tuple[LimbusView, ...]:
    return cloud.views if isinstance(cloud, TrackedCloud) else ()



def blind_alone(unit_id: str, why: str) -> str:
    """Why unit ``unit_id``, blind to the fringe order, cannot be reconstructed on its own."""
    return (f"unit {unit_id} is blind to the fringe order ({why}): its orders need another "
            "unit's images of the same frame set; use both units ('all'), or move one of its "
            "cameras to another azimuth and calibrate again")


@dataclass(frozen=True)
class _UnitViews:
    """One unit's two views of a frame set, as :meth:`RigReconstructor._pair` prepares them:
    the cameras of the demodulated images (a window, or the whole image) and of the points (the
    window decimated), the images, their phases and those phases decimated, and the
    decimation factors."""

    ids: tuple[str, str]
    cameras: tuple[CalibratedCamera, CalibratedCamera]
    points: tuple[CalibratedCamera, CalibratedCamera]
    images: tuple[npt.NDArray[Any], npt.NDArray[Any]]
    phases: tuple[Phase, Phase]
    point_phases: tuple[Phase, Phase]
    factors: tuple[int, int]


class RigReconstructor:
    """Reconstructs frame sets of a rig with one calibration, its cameras loaded once.

    Each unit's first two cameras fix each other's fringe order, by the method the calibration
    allows the unit (:func:`~eyeserver.reconstruction.unit_method`'s ``auto``; a unit blind to
    the order takes it from the first camera of another unit in the frame set, as
    :func:`~eyeserver.reconstruction.reconstruct_bundle` does); the clouds of the units are
    fused. Raises :class:`ReconstructionError` for a calibration without phase-to-height
    models or with a blind unit and no other, for a frame set with a blind unit alone, and for
    a frame set in which a unit gave fewer than
    :data:`~eyeserver.service.verification.MIN_UNIT_POINTS` points (counted as the pixels they
    stand for): its projector dark, its view blocked. The frame is
    then lost, the beam held with that reason, rather than posed from the other unit alone.

    After :meth:`focus` on a pose, each camera's image is reconstructed only inside the window
    around that eye (:func:`~eyeserver.eye.track.pose_window`), a few times fewer pixels
    than the whole image, and on every :data:`WINDOW_DECIMATION`-th pixel of it (demodulated and
    searched for the limbus at full resolution); the cropped cameras are kept per window
    (windows are rounded to :data:`~eyeserver.eye.tunables.WINDOW_QUANTUM_PX`, so a still
    eye keeps one). A window masks weak fringes against the whole image's strong ones
    (:func:`~eyeserver.pipeline.reconstruct.strong_modulation`), measured once per camera and
    reconstructor — from the last whole image reconstructed, else the first windowed frame's
    image: a new window then costs no demodulation of the whole image (7 ms a camera). One
    reconstructor serves one tracking session, during which the daemon refuses device
    settings, so the projectors' intensity cannot change under it.
    """

    def __init__(self, calibration: str | Path, rig: RigSpec, bit_depth: int | None = None
                 ) -> None:
        document = load_calibration(calibration, rig)
        self._cameras: dict[str, CalibratedCamera] = calibrated_cameras(document)
        self._limits = z_range(document)
        self._rig = rig
        self._methods: dict[str, tuple[str, str]] = {}
        for unit in rig.units:
            chosen, why = unit_method(document, unit.id, "auto", for_tracking=True)
            if chosen == "blind" and len(rig.units) < 2:
                raise ReconstructionError(blind_alone(unit.id, why))
            self._methods[unit.id] = (chosen, why)
        self._saturation = None if bit_depth is None else float(2 ** bit_depth - 1)
        self._pose: EyePose | None = None
        self._cropped: dict[tuple[str, tuple[int, int, int, int]],
                            tuple[CalibratedCamera, CalibratedCamera]] = {}
        self._strong: dict[str, float] = {}

    def focus(self, pose: EyePose | None) -> None:
        """Reconstruct only around ``pose``'s eye from now on; None: the whole images."""
        self._pose = pose

    def _view(self, camera_id: str, image: npt.NDArray[Any],
              ) -> tuple[CalibratedCamera, CalibratedCamera, npt.NDArray[Any]]:
        """The camera and image to demodulate, and the camera to reconstruct the points with:
        the window around the eye in focus, if any (that last one decimated), else the whole
        image's camera twice."""
        camera = self._cameras[camera_id]
        pose = self._pose
        if pose is None:
            return camera, camera, image
        window = pose_window(camera, pose)
        if window is None or window == (0, 0, camera.shape[1], camera.shape[0]):
            return camera, camera, image
        key = (camera_id, window)
        if key not in self._cropped:
            if len(self._cropped) >= _MAX_WINDOWS:
                self._cropped.clear()  # an eye that wandered far: start the cache anew
            # The whole image's fringe strength, so the window masks what the whole image
            # would (a window's own is the eye's alone).
            if camera_id not in self._strong:
                self._strong[camera_id] = strong_modulation(camera, image)
            window_camera = cropped(camera, *window, strong_modulation=self._strong[camera_id])
            self._cropped[key] = (window_camera, decimated(window_camera, WINDOW_DECIMATION))
        x0, y0, x1, y1 = window
        return *self._cropped[key], image[y0:y1, x0:x1]

    def _pair(self, step: AcquiredStep, camera_ids: list[str]) -> _UnitViews:
        """A unit's first two cameras of ``step``, demodulated (in their windows, if any)."""
        if len(camera_ids) < 2:
            raise ReconstructionError(f"camera {camera_ids[0]} has no partner in its unit to "
                                      "fix its fringe order")
        a, b = camera_ids[:2]
        frame_a, frame_b = step.frames[a], step.frames[b]
        saturation = self._saturation or float(2 ** frame_a.meta.bit_depth - 1)
        camera_a, points_a, image_a = self._view(a, np.asarray(frame_a.image))
        camera_b, points_b, image_b = self._view(b, np.asarray(frame_b.image))
        # A followed eye's globe keeps its radius and is placed on the limbus, which the band's
        # own phase shows: only the whole images' (global) fit needs the surface's phase less
        # the band's bend bias (≈ 3 ms a frame set otherwise).
        phases = (camera_phase(camera_a, image_a, saturation,
                               measure_bends=camera_a is self._cameras[a]),
                  camera_phase(camera_b, image_b, saturation,
                               measure_bends=camera_b is self._cameras[b]))
        for camera_id, camera, phase in ((a, camera_a, phases[0]), (b, camera_b, phases[1])):
            if camera is self._cameras[camera_id]:  # the whole image
                self._strong[camera_id] = fringe_strength(phase.modulation)
        factors = (points_a.spacing_px // camera_a.spacing_px,
                   points_b.spacing_px // camera_b.spacing_px)
        return _UnitViews((a, b), (camera_a, camera_b), (points_a, points_b),
                          (image_a, image_b), phases,
                          (phases[0].decimated(factors[0]), phases[1].decimated(factors[1])),
                          factors)

    def __call__(self, frame_set: FrameSet) -> TrackedCloud:
        parts = []
        views: list[LimbusView] = []
        unit_pixels: dict[str, int] = {}  # the pixels each unit's points stand for
        # Every unit's two views of every step first: a blind unit's orders come from another
        # unit's, lit in another step of the frame set (the nearest).
        pairs: list[tuple[int, str, _UnitViews]] = []
        for index, step in enumerate(frame_set.steps):
            by_unit: dict[str, list[str]] = {}
            for camera_id in step.frames:
                by_unit.setdefault(self._rig.unit_of_camera(camera_id).id, []).append(camera_id)
            pairs += [(index, unit_id, self._pair(step, camera_ids))
                      for unit_id, camera_ids in by_unit.items()]
        for index, unit_id, pair in pairs:
            method, why = self._methods[unit_id]
            judges = None
            if method == "blind":
                others = [(abs(i - index), p) for i, u, p in pairs if u != unit_id]
                if not others:
                    raise ReconstructionError(blind_alone(unit_id, why))
                other = min(others, key=lambda entry: entry[0])[1]
                judge = (other.points[0], other.point_phases[0])
                method, judges = "spatial", (judge, judge)
            cloud_a, cloud_b = unit_clouds(pair.points[0], None, pair.points[1], None,
                                           self._limits, method=method,
                                           phases=pair.point_phases, order_partners=judges)
            # The limbus is looked for in the same demodulation, not in one of its own.
            views += [LimbusView(camera, image, fringe_removed(camera, image, phase))
                      for camera, image, phase in zip(pair.cameras, pair.images, pair.phases,
                                                      strict=True)]
            for camera_id, cloud, factor in zip(pair.ids, (cloud_a, cloud_b), pair.factors,
                                                strict=True):
                parts.append(Part(cloud.points, cloud.quality,
                                  self._rig.camera_index(camera_id), unit_id))
                unit_pixels[unit_id] = (unit_pixels.get(unit_id, 0)
                                        + len(cloud.points) * factor**2)
        # A unit that sees nothing: the pose would be the other unit's alone (issue 35).
        missing = unit_shortfalls({unit: {"points": n} for unit, n in unit_pixels.items()})
        if missing:
            raise ReconstructionError("; ".join(missing))
        fused = fuse(parts)
        whole = PointCloud(fused.points.astype(np.float32), fused.quality, fused.camera)
        counted = sum(len(part.points) for part in parts)
        pixels = sum(unit_pixels.values())
        return TrackedCloud(whole.points, whole.quality, whole.camera, tuple(views),
                            pixels_per_point=pixels / counted if counted else 1.0)

