"""Simulated drivers: a camera, a projector and a trigger that run the simulated room.

They implement the same interfaces as real drivers and behave like them where it matters to the
daemon: a camera delivers only after a trigger pulse exposed it, buffers a bounded number of
exposures and counts what it had to drop; a projector lights only when enabled and strobed by
the pulse's step (or continuously); a trigger fires software pulses or free-runs at its rate.

The three meet through a :class:`SimWiring` (the simulated trigger cable), found in the
:class:`~eyeserver.hardware.registry.DriverContext` under :data:`SIM_WIRING`; the wiring also
holds the room, which the drivers see only through the :class:`RenderSource` protocol. Build a
whole simulated rig with :func:`build_sim_rig`.

Each device also simulates failures for the reliability work (:meth:`SimCamera.inject_fault`):
dropped frames, read time-outs and a disconnection that lasts until :meth:`~SimCamera.reconnect`,
after which closing and reopening the device recovers it, as with a real camera that was unplugged
and plugged back in.
"""

from __future__ import annotations

import contextlib
import logging
import os
import queue
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import CancelledError, Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Final, Literal, Protocol, TypeVar, get_args

import numpy as np

from eyeserver.core.clock import Clock
from eyeserver.core.frames import Frame, FrameMeta
from eyeserver.errors import (
    DeviceDisconnectedError,
    DeviceError,
    DeviceNotOpenError,
    DeviceTimeoutError,
    DeviceValueError,
)
from eyeserver.hardware.base import Camera, PacedTrigger, Projector, TriggerPulse, TriggerStep
from eyeserver.hardware.registry import DriverContext, register_driver
from eyeserver.hardware.rig import (
    DeviceConfig,
    HardwareConfig,
    Rig,
    TriggerConfig,
    UnitConfig,
    build_rig,
)

__all__ = [
    "SIM_TRIGGER_ID",
    "SIM_WIRING",
    "FaultKind",
    "RenderSource",
    "SimCamera",
    "SimProjector",
    "SimTrigger",
    "SimWiring",
    "build_sim_rig",
    "sim_driver_context",
    "sim_hardware_config",
]

SIM_WIRING: Final = "sim.wiring"
"""Key of the :class:`SimWiring` in :attr:`DriverContext.resources`."""

SIM_TRIGGER_ID: Final = "T1"
"""Id of the trigger in a rig built by :func:`build_sim_rig`."""

FaultKind = Literal["drop", "timeout", "disconnect"]

_log = logging.getLogger(__name__)



class RenderSource(Protocol):
    """What the simulated drivers need of the simulated room.

    Attributes
    ----------
    clock : Clock
        The room's clock; pulses are timed on it and the scene moves with it.
    seed : int
        Seed of the room's noise; each camera derives its own generator from it.
    """

    # Read-only members, so that a room whose attribute is a ManualClock still qualifies.
    @property
    def clock(self) -> Clock: ...

    @property
    def seed(self) -> int: ...

    def camera_ids(self) -> list[str]:
        """Ids of the room's cameras, in order."""
        ...

    def projector_ids(self) -> list[str]:
        """Ids of the room's projectors, in order."""
        ...

    def units(self) -> list[tuple[str, str, list[str]]]:
        """The optical units as ``(unit id, projector id, camera ids)``."""
        ...

    def camera_format(self, camera_id: str) -> tuple[int, int, int]:
        """Image ``(width, height, bit_depth)`` of a camera."""
        ...

    def prepare(self, camera_id: str, projectors: Sequence[str]) -> None:
        """Make what renders of ``camera_id`` lit by ``projectors`` will reuse (caches of the
        scene in front of it), so that the first of them costs no more than the next."""
        ...

    def prerender(self, camera_id: str, *, seconds: float, rate_hz: float,
                  projectors: Mapping[str, float], exposure_us: float, gain_db: float,
                  rng: np.random.Generator, progress: Callable[[float], None] | None = None,
                  ) -> object:
        """Render ``camera_id``'s exposures of the moving scene ahead, for the first
        ``seconds`` of its script at ``rate_hz``
        (:meth:`eyeserver.hardware.sim.room.SimRoom.prerender`); returns the scene."""
        ...

    def render(self, camera_id: str, *, t_s: float, projectors: Mapping[str, float],
               exposure_us: float, gain_db: float, rng: np.random.Generator) -> np.ndarray:
        """Render one exposure.

        Parameters
        ----------
        camera_id : str
            The camera to image through.
        t_s : float
            Mid-exposure time on the room's clock, seconds.
        projectors : Mapping[str, float]
            Each lit projector's id and relative intensity (0–1); unlit ones are absent.
        exposure_us : float
            Exposure time, microseconds.
        gain_db : float
            Analogue gain, decibels.
        rng : numpy.random.Generator
            Source of the image noise.

        Returns
        -------
        numpy.ndarray
            ``uint8`` (8-bit) or ``uint16`` (10-/12-bit) image of shape ``(height, width)``.
        """
        ...


RENDER_NICENESS = 10
"""How much nicer than the daemon a simulated camera's rendering thread runs."""


def _render_thread_priority() -> None:
    with contextlib.suppress(AttributeError, OSError):  # Linux: a thread has its own niceness
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), RENDER_NICENESS)


LINK_BYTES_PER_S = 115e6
"""A simulated camera's link: GigE Vision's ≈ 115 MB/s of image data (1 Gb/s less framing)."""


@dataclass(frozen=True)
class _Exposure:
    """What a camera latched when a pulse exposed it, and its image being rendered."""

    pulse: TriggerPulse
    t_ns: int
    """Mid-exposure: the pulse plus half the exposure."""
    projectors: dict[str, float]
    exposure_us: float
    gain_db: float
    image: Future[np.ndarray]


_Pluggable = TypeVar("_Pluggable", "SimCamera", "SimProjector")


def _plug_into(slots: dict[str, _Pluggable], device: _Pluggable) -> None:
    present = slots.get(device.id)
    if present is not None and present is not device:
        raise DeviceValueError(device.id, f"another open {device.kind} already has this id in "
                                          "the simulated room")
    slots[device.id] = device


class SimWiring:
    """The simulated trigger cable: routes pulses to cameras and strobes to projectors.

    Parameters
    ----------
    room : RenderSource
        The simulated room the devices image.
    clock : Clock, optional
        Clock to time pulses on; the room's clock by default.

    Notes
    -----
    Cameras and projectors plug in when opened and unplug when closed, so only open devices
    take part in a pulse.
    """

    def __init__(self, room: RenderSource, clock: Clock | None = None) -> None:
        self.room = room
        self.clock: Clock = clock if clock is not None else room.clock
        self._lock = threading.Lock()
        self._cameras: dict[str, SimCamera] = {}
        self._projectors: dict[str, SimProjector] = {}

    def _plug(self, device: SimCamera | SimProjector) -> None:
        with self._lock:
            if isinstance(device, SimCamera):
                _plug_into(self._cameras, device)
            else:
                _plug_into(self._projectors, device)

    def _unplug(self, device: SimCamera | SimProjector) -> None:
        with self._lock:
            slots: dict[str, SimCamera] | dict[str, SimProjector]
            slots = self._cameras if isinstance(device, SimCamera) else self._projectors
            if slots.get(device.id) is device:
                del slots[device.id]

    def lit_projectors(self, step: TriggerStep) -> dict[str, float]:
        """Projectors that light during a pulse of ``step``, with their intensities.

        A projector lights when it is open, connected, enabled and at a non-zero intensity, and
        either strobed and named by the step or in continuous mode.
        """
        with self._lock:
            projectors = dict(self._projectors)
        lit: dict[str, float] = {}
        for projector_id in self.room.projector_ids():
            projector = projectors.get(projector_id)
            if (projector is None or not projector.connected or not projector.enabled
                    or projector.intensity <= 0.0):
                continue
            if not projector.strobe or projector_id in step.projectors:
                lit[projector_id] = projector.intensity
        return lit

    def publish(self, pulse: TriggerPulse) -> None:
        """Deliver a fired pulse: latch the lit projectors and expose the step's cameras."""
        lit = self.lit_projectors(pulse.step)
        with self._lock:
            cameras = [self._cameras[c] for c in pulse.step.cameras if c in self._cameras]
        for camera in cameras:
            camera._expose(pulse, lit)


class _SimFaults:
    """Connection state and the disconnect fault, shared by the three simulated drivers."""

    id: str
    kind: str
    _fault_kinds: frozenset[str] = frozenset({"disconnect"})

    def _init_faults(self) -> None:
        self._present = True  # the device is physically there
        self._stale = False  # the connection broke; only close() then open() renew it

    @property
    def connected(self) -> bool:
        """Whether the device answers (no disconnect injected, or reopened since)."""
        return self._present and not self._stale

    def inject_fault(self, kind: FaultKind, count: int = 1) -> None:
        """Make the device fail on purpose.

        Parameters
        ----------
        kind : {"drop", "timeout", "disconnect"}
            ``"disconnect"``: every call raises :class:`DeviceDisconnectedError` and opening
            fails until :meth:`reconnect`; then :meth:`close` and :meth:`open` recover.
            ``"drop"`` and ``"timeout"`` exist on cameras only (see :meth:`SimCamera.inject_fault`).
        count : int
            How many pulses or reads the fault affects (ignored for ``"disconnect"``).
        """
        if kind not in self._fault_kinds:
            raise ValueError(f"a simulated {self.kind} supports the faults "
                             f"{', '.join(sorted(self._fault_kinds))}, not {kind!r}")
        if count < 1:
            raise ValueError(f"count must be at least 1, not {count}")
        if kind == "disconnect":
            self._present = False
            self._stale = True
            self._on_disconnect()
        else:
            self._add_fault(kind, count)

    def reconnect(self) -> None:
        """The device comes back; it works again after :meth:`close` and :meth:`open`."""
        self._present = True

    def clear_faults(self) -> None:
        """Forget every injected fault, as if none had happened; the device works at once."""
        self._present = True
        self._stale = False

    def _check_connected(self) -> None:
        if not self._present:
            raise DeviceDisconnectedError(self.id, f"{self.kind} is not responding")
        if self._stale:
            raise DeviceDisconnectedError(self.id, f"{self.kind} connection was lost; close and "
                                                   "reopen it")

    def _connect(self) -> None:
        if not self._present:
            raise DeviceDisconnectedError(self.id, f"{self.kind} is not responding")
        self._stale = False

    def _on_disconnect(self) -> None:
        """Hook: react to a disconnection (a camera wakes its waiting reader)."""

    def _add_fault(self, kind: str, count: int) -> None:
        raise AssertionError(f"unhandled fault {kind}")  # guarded by _fault_kinds


def _wiring(context: DriverContext) -> SimWiring:
    return context.resource(SIM_WIRING, SimWiring)


@register_driver("camera", "SimCamera")
class SimCamera(_SimFaults, Camera):
    """A simulated triggered camera that renders the room on its own thread.

    Parameters
    ----------
    device_id : str
        One of the room's camera ids; the image format comes from the room.
    context : DriverContext
        Must hold the :class:`SimWiring` under :data:`SIM_WIRING`.
    queue_size : int
        Exposures buffered before further pulses are dropped (counted in ``dropped_frames``).

    Notes
    -----
    A pulse latches the exposure, gain and lit projectors at its own time, and the camera's
    thread renders the image at mid-exposure, ``t = pulse + exposure / 2``, at once, as a real
    camera exposes and sends without the host's help: the cameras of a unit render side by side
    while the reader waits. A frame is never returned before a real camera's could be: the end
    of its exposure plus its transfer over the link (:data:`LINK_BYTES_PER_S`, ≈ 3 ms for
    640 × 512 at 8 bits), waited for on the room's clock. So a pulse scheduled ahead
    (:meth:`~eyeserver.hardware.base.Trigger.fire` with ``at_ns``) is rendered before it is due
    and its frame delivered when a camera would deliver it. The noise comes from the camera's own
    generator seeded with ``[room.seed, camera index]``, so a seed reproduces a sequence of reads
    exactly. One reader at a time.
    """

    _fault_kinds = frozenset(get_args(FaultKind))

    def __init__(self, device_id: str, *, context: DriverContext, queue_size: int = 8) -> None:
        wiring = _wiring(context)
        camera_ids = list(wiring.room.camera_ids())
        if device_id not in camera_ids:
            raise ValueError(f"the simulated room has no camera {device_id!r} "
                             f"(it has {', '.join(camera_ids) or 'none'})")
        if queue_size < 1:
            raise ValueError(f"queue_size must be at least 1, not {queue_size}")
        width, height, bit_depth = wiring.room.camera_format(device_id)
        super().__init__(device_id, width, height, bit_depth)
        self._init_faults()
        self._wiring = wiring
        self._queue_size = int(queue_size)
        self._rng = np.random.default_rng([int(wiring.room.seed), camera_ids.index(device_id)])
        self._dtype = np.dtype(np.uint8 if self.bit_depth == 8 else np.uint16)
        self._transfer_ns = round(1e9 * width * height * self._dtype.itemsize / LINK_BYTES_PER_S)
        self._state_lock = threading.Lock()
        self._read_lock = threading.Lock()
        # None is a wake-up call for a blocked reader; the bound on exposures is kept by
        # _queued so that a wake-up always fits.
        self._exposures: queue.Queue[_Exposure | None] = queue.Queue()
        self._queued = 0
        self._receiving = False
        self._frame_counter = 0
        self._dropped = 0
        self._pending_drops = 0
        self._pending_timeouts = 0
        self._renderer: ThreadPoolExecutor | None = None

    @property
    def dropped_frames(self) -> int:
        """Exposures dropped since :meth:`open` (injected drops, lost reads, full buffer)."""
        return self._dropped

    def inject_fault(self, kind: FaultKind, count: int = 1) -> None:
        """Make the camera fail on purpose.

        Parameters
        ----------
        kind : {"drop", "timeout", "disconnect"}
            ``"drop"``: the next ``count`` pulses expose nothing but count as dropped frames, so
            a read returns the following pulse's frame or times out. ``"timeout"``: the next
            ``count`` reads lose their frame (counted as dropped) and raise
            :class:`DeviceTimeoutError` once their timeout has elapsed. ``"disconnect"``: every
            call raises :class:`DeviceDisconnectedError` (a waiting read at once) and opening
            fails until :meth:`reconnect`; then :meth:`close` and :meth:`open` recover.
        count : int
            Pulses or reads affected (ignored for ``"disconnect"``).
        """
        super().inject_fault(kind, count)

    def clear_faults(self) -> None:
        """Forget every injected fault, as if none had happened; the camera works at once."""
        with self._state_lock:
            self._pending_drops = 0
            self._pending_timeouts = 0
        super().clear_faults()

    def _add_fault(self, kind: str, count: int) -> None:
        with self._state_lock:
            if kind == "drop":
                self._pending_drops += count
            else:
                self._pending_timeouts += count

    def _on_disconnect(self) -> None:
        with self._state_lock:
            self._discard_exposures()
        self._exposures.put(None)

    def _discard_exposures(self) -> None:
        while True:
            try:
                self._exposures.get_nowait()
            except queue.Empty:
                break
        self._queued = 0

    def _do_open(self) -> None:
        self._connect()
        self._wiring._plug(self)
        with self._state_lock:
            self._discard_exposures()
            self._frame_counter = 0
            self._dropped = 0
            if self._renderer is None:
                self._renderer = ThreadPoolExecutor(1, thread_name_prefix=f"sim-{self.id}",
                                                    initializer=_render_thread_priority)
            self._receiving = True

    def _do_close(self) -> None:
        with self._state_lock:
            self._receiving = False
            self._discard_exposures()
            renderer, self._renderer = self._renderer, None
        self._exposures.put(None)
        self._wiring._unplug(self)
        if renderer is not None:
            renderer.shutdown(wait=False, cancel_futures=True)

    def _apply_exposure_us(self, value: float) -> None:
        self._check_connected()

    def _apply_gain_db(self, value: float) -> None:
        self._check_connected()

    def _expose(self, pulse: TriggerPulse, projectors: dict[str, float]) -> None:
        """Latch one exposure; called by the wiring on the trigger's thread."""
        with self._state_lock:
            if not (self._receiving and self.connected):
                return
            if self._pending_drops > 0:
                self._pending_drops -= 1
                self._dropped += 1
                return
            if self._queued >= self._queue_size:
                self._dropped += 1
                return
            self._queued += 1
            lit, exposure_us, gain_db = dict(projectors), self.exposure_us, self.gain_db
            t_ns = pulse.t_ns + round(exposure_us * 500.0)
            assert self._renderer is not None  # receiving: opened
            image = self._renderer.submit(self._render, t_ns, lit, exposure_us, gain_db)
            self._exposures.put(_Exposure(pulse=pulse, t_ns=t_ns, projectors=lit,
                                          exposure_us=exposure_us, gain_db=gain_db, image=image))

    def _next_exposure(self, deadline: float) -> _Exposure | None:
        while True:
            try:
                item = self._exposures.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                return None
            if item is not None:
                with self._state_lock:
                    self._queued -= 1
                return item
            # A wake-up: the camera was closed or disconnected while we waited.
            self._check_connected()
            if not self._receiving:
                raise DeviceNotOpenError(self.id, "camera was closed while waiting for a frame")

    def _read_frame(self, timeout_s: float) -> Frame:
        with self._read_lock:
            self._check_connected()
            deadline = time.monotonic() + timeout_s
            with self._state_lock:
                lose_frame = self._pending_timeouts > 0
                if lose_frame:
                    self._pending_timeouts -= 1
            exposure = self._next_exposure(deadline)
            if lose_frame:
                if exposure is not None:
                    with self._state_lock:
                        self._dropped += 1
                # A lost transfer is noticed only when the wait runs out.
                time.sleep(max(0.0, deadline - time.monotonic()))
                raise DeviceTimeoutError(self.id, f"frame lost in transfer (no frame within "
                                                  f"{timeout_s} s)")
            if exposure is None:
                raise DeviceTimeoutError(self.id, f"no triggered frame within {timeout_s} s")
            return self._deliver(exposure)

    def prerender(self, seconds: float, rate_hz: float, projector_ids: Sequence[str],
                  progress: Callable[[float], None] | None = None) -> object:
        """Have the room render this camera's exposures of its moving scene ahead (see
        :meth:`RenderSource.prerender`), as pulses lighting ``projector_ids`` would take them
        now: the projectors' state, this camera's exposure and gain. The noise comes from a
        generator of its own (``[room.seed, camera index, 1]``), so a seed reproduces the
        frames. Returns the scene rendered.

        Raises
        ------
        ValueError
            The scene does not move, or bad ``seconds`` or ``rate_hz``.
        DeviceDisconnectedError
            The camera is unplugged.
        """
        self._check_connected()
        room = self._wiring.room
        lit = self._wiring.lit_projectors(TriggerStep(projectors=tuple(projector_ids),
                                                      cameras=(self.id,)))
        rng = np.random.default_rng([int(room.seed), room.camera_ids().index(self.id), 1])
        return room.prerender(self.id, seconds=seconds, rate_hz=rate_hz, projectors=lit,
                              exposure_us=self.exposure_us, gain_db=self.gain_db, rng=rng,
                              progress=progress)

    def _prepare_stream(self, projectors: tuple[str, ...]) -> None:
        # The room's first render of a moving scene casts its static part whole (≈ 1 s a
        # camera): done here, on the caller's thread, before the stream's first pulse.
        self._check_connected()
        self._wiring.room.prepare(self.id, projectors)

    def _render(self, t_ns: int, projectors: dict[str, float], exposure_us: float,
                gain_db: float) -> np.ndarray:
        """An exposure's image at mid-exposure ``t_ns``, rendered on the camera's own thread
        (in pulse order)."""
        return self._wiring.room.render(self.id, t_s=t_ns / 1e9, projectors=projectors,
                                        exposure_us=exposure_us, gain_db=gain_db, rng=self._rng)

    def _deliver(self, exposure: _Exposure) -> Frame:
        try:
            image = exposure.image.result()
        except CancelledError:  # closed before its turn to render
            raise DeviceNotOpenError(self.id, "camera was closed while waiting for a frame"
                                     ) from None
        if image.shape != (self.height, self.width) or image.dtype != self._dtype:
            raise DeviceError(self.id, f"the room rendered a {image.dtype} image of shape "
                                       f"{image.shape}, expected {self._dtype} of shape "
                                       f"{(self.height, self.width)}")
        clock = self._wiring.clock
        ready_ns = exposure.pulse.t_ns + round(exposure.exposure_us * 1000.0) + self._transfer_ns
        if ready_ns > clock.now_ns():  # rendered before a camera would have sent it
            clock.sleep((ready_ns - clock.now_ns()) / 1e9)
        with self._state_lock:
            counter = self._frame_counter
            self._frame_counter += 1
            dropped = self._dropped
        meta = FrameMeta(camera_id=self.id, frame_counter=counter, t_ns=exposure.t_ns,
                         exposure_us=exposure.exposure_us, gain_db=exposure.gain_db,
                         dropped_frames=dropped, bit_depth=self.bit_depth,
                         projectors_on=tuple(exposure.projectors),
                         trigger_index=exposure.pulse.index)
        return Frame(image=image, meta=meta)

    def describe(self) -> dict[str, object]:
        return {**super().describe(), "connected": self.connected,
                "dropped_frames": self.dropped_frames}


@register_driver("projector", "SimProjector")
class SimProjector(_SimFaults, Projector):
    """A simulated fringe projector; it lights the room on the pulses that strobe it.

    Parameters
    ----------
    device_id : str
        One of the room's projector ids.
    context : DriverContext
        Must hold the :class:`SimWiring` under :data:`SIM_WIRING`.
    """

    def __init__(self, device_id: str, *, context: DriverContext) -> None:
        wiring = _wiring(context)
        projector_ids = list(wiring.room.projector_ids())
        if device_id not in projector_ids:
            raise ValueError(f"the simulated room has no projector {device_id!r} "
                             f"(it has {', '.join(projector_ids) or 'none'})")
        super().__init__(device_id)
        self._init_faults()
        self._wiring = wiring

    def _do_open(self) -> None:
        self._connect()
        self._wiring._plug(self)

    def _do_close(self) -> None:
        self._wiring._unplug(self)

    def _check(self) -> None:
        self._check_connected()

    def _apply_enabled(self, value: bool) -> None:
        self._check_connected()

    def _apply_intensity(self, value: float) -> None:
        self._check_connected()

    def _apply_strobe(self, value: bool) -> None:
        self._check_connected()

    def describe(self) -> dict[str, object]:
        return {**super().describe(), "connected": self.connected}


@register_driver("trigger", "SimTrigger")
class SimTrigger(_SimFaults, PacedTrigger):
    """A simulated trigger/strobe controller.

    Pulses are timed on the wiring's clock (the room's by default), on which :meth:`start`
    free-runs them (:class:`~eyeserver.hardware.base.PacedTrigger`).

    Parameters
    ----------
    device_id : str
        The trigger's id.
    context : DriverContext
        Must hold the :class:`SimWiring` under :data:`SIM_WIRING`.
    """

    def __init__(self, device_id: str, *, context: DriverContext) -> None:
        wiring = _wiring(context)
        super().__init__(device_id, wiring.clock)
        self._init_faults()
        self._wiring = wiring
        self._fire_lock = threading.Lock()
        self._pulse_index = 0
        self._position = 0

    def _do_open(self) -> None:
        self._connect()
        with self._fire_lock:
            self._pulse_index = 0
            self._position = 0

    def _do_close(self) -> None:
        self.stop()

    def _apply_rate_hz(self, value: float) -> None:
        self._check_connected()

    def _apply_sequence(self, steps: tuple[TriggerStep, ...]) -> None:
        self._check_connected()
        cameras = set(self._wiring.room.camera_ids())
        projectors = set(self._wiring.room.projector_ids())
        for n, step in enumerate(steps):
            unknown = [c for c in step.cameras if c not in cameras]
            unknown += [p for p in step.projectors if p not in projectors]
            if unknown:
                raise DeviceValueError(self.id, f"sequence step {n} names device(s) the trigger "
                                                f"is not wired to: {', '.join(unknown)}")
        with self._fire_lock:
            # Set here, under the lock, so a free-running pulse never sees the new sequence
            # with the old position.
            self._sequence = steps
            self._position = 0

    def _fire(self, at_ns: int | None) -> TriggerPulse:
        with self._fire_lock:
            self._check_connected()
            step = self._sequence[self._position % len(self._sequence)]
            self._position += 1
            now_ns = self._wiring.clock.now_ns()
            # A pulse scheduled ahead is announced to the cameras now, so that the room can be
            # rendered before the frame is due, as a camera's frame costs the host nothing.
            t_ns = now_ns if at_ns is None else max(now_ns, int(at_ns))
            pulse = TriggerPulse(index=self._pulse_index, t_ns=t_ns, step=step)
            self._pulse_index += 1
            self._wiring.publish(pulse)
            return pulse

    def _check_can_start(self) -> None:
        self._check_connected()

    def describe(self) -> dict[str, object]:
        return {**super().describe(), "connected": self.connected}


def sim_driver_context(room: RenderSource, clock: Clock | None = None) -> DriverContext:
    """A driver context wired to ``room``, for building simulated devices from a configuration.

    Parameters
    ----------
    room : RenderSource
        The simulated room.
    clock : Clock, optional
        Clock for pulses and frames; the room's clock by default.
    """
    wiring = SimWiring(room, clock)
    return DriverContext(clock=wiring.clock, resources={SIM_WIRING: wiring})


def sim_hardware_config(room: RenderSource) -> HardwareConfig:
    """The hardware configuration of every device in ``room`` on the simulated drivers.

    Projectors and cameras keep the room's ids and order, the trigger is ``"T1"`` and the units
    are the room's.
    """
    devices = [DeviceConfig(kind="projector", id=p, driver="SimProjector")
               for p in room.projector_ids()]
    devices += [DeviceConfig(kind="camera", id=c, driver="SimCamera") for c in room.camera_ids()]
    units = [UnitConfig(id=unit_id, projector=projector_id, cameras=list(camera_ids))
             for unit_id, projector_id, camera_ids in room.units()]
    return HardwareConfig(devices=devices,
                          trigger=TriggerConfig(id=SIM_TRIGGER_ID, driver="SimTrigger"),
                          units=units)


def build_sim_rig(room: RenderSource, clock: Clock | None = None) -> Rig:
    """A rig of simulated devices for every camera, projector and unit of ``room`` (not opened).

    Parameters
    ----------
    room : RenderSource
        The simulated room, e.g. a ``SimRoom``.
    clock : Clock, optional
        Clock for pulses and frames; the room's clock by default.

    Examples
    --------
    >>> rig = build_sim_rig(room)                                       # doctest: +SKIP
    >>> with rig:                                                       # doctest: +SKIP
    ...     left, right = rig.acquire(["left", "right"])
    """
    return build_rig(sim_hardware_config(room), sim_driver_context(room, clock))
