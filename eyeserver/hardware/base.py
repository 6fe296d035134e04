"""Narrow device interfaces: cameras, projectors (light sources) and the trigger/strobe controller.

Every driver, real or simulated, implements one of these ABCs. Ranges are checked here, once, in
the concrete ``set_*`` methods, which then call the driver's ``_apply_*`` hook; drivers therefore
never see an out-of-range value. Units are in the names (``exposure_us``, ``gain_db``) or stated.

Acquisition is triggered and synchronous: the :class:`Trigger` fires a pulse (one step of its
lighting sequence), which strobes the projectors of that step and exposes the cameras of that
step; each exposed camera then returns the image from :meth:`Camera.read_frame`.
"""

from __future__ import annotations

import abc
import logging
import threading
from collections.abc import Sequence
from dataclasses import dataclass

from eyeserver.core.clock import Clock
from eyeserver.core.frames import Frame, is_valid_id
from eyeserver.errors import DeviceNotOpenError, DeviceValueError

_log = logging.getLogger(__name__)


class Device(abc.ABC):
    """Something with an id that is opened before use and closed after."""

    kind: str = "device"

    def __init__(self, device_id: str) -> None:
        if not is_valid_id(device_id):
            raise ValueError(f"device id {device_id!r} must be letters, digits, '-' or '_'")
        self.id = device_id
        self._open = False

    @property
    def is_open(self) -> bool:
        """Whether :meth:`open` succeeded and :meth:`close` has not been called since."""
        return self._open

    def open(self) -> None:
        """Connect to the device. Idempotent."""
        if not self._open:
            self._do_open()
            self._open = True

    def close(self) -> None:
        """Release the device. Idempotent; never raises for an already closed device."""
        if self._open:
            try:
                self._do_close()
            finally:
                self._open = False

    def _require_open(self) -> None:
        if not self._open:
            raise DeviceNotOpenError(self.id, f"{self.kind} is not open")

    @abc.abstractmethod
    def _do_open(self) -> None: ...

    @abc.abstractmethod
    def _do_close(self) -> None: ...

    def describe(self) -> dict[str, object]:
        """Driver name, kind and current settings, for status pages."""
        return {"id": self.id, "kind": self.kind, "driver": type(self).__name__,
                "open": self.is_open}


def _check_range(device_id: str, name: str, value: float, low: float, high: float) -> float:
    if not (low <= value <= high):
        raise DeviceValueError(device_id, f"{name}={value} outside [{low}, {high}]")
    return float(value)


class Camera(Device):
    """A triggered area camera.

    Subclasses set ``width``, ``height``, ``bit_depth`` and the ranges, and implement the hooks.
    """

    kind = "camera"
    exposure_range_us: tuple[float, float] = (10.0, 40_000.0)
    gain_range_db: tuple[float, float] = (0.0, 24.0)

    def __init__(self, device_id: str, width: int, height: int, bit_depth: int = 8) -> None:
        super().__init__(device_id)
        if bit_depth not in (8, 10, 12):
            raise ValueError(f"bit_depth must be 8, 10 or 12, not {bit_depth}")
        if width <= 0 or height <= 0:
            raise ValueError(f"image size must be positive, not {width}x{height}")
        self.width = int(width)
        self.height = int(height)
        self.bit_depth = int(bit_depth)
        self._exposure_us = 10_000.0
        self._gain_db = 0.0

    @property
    def exposure_us(self) -> float:
        """Exposure time in microseconds."""
        return self._exposure_us

    def set_exposure_us(self, value: float) -> None:
        """Set the exposure time; raises :class:`DeviceValueError` outside the camera's range."""
        self._require_open()
        value = _check_range(self.id, "exposure_us", value, *self.exposure_range_us)
        self._apply_exposure_us(value)
        self._exposure_us = value

    @property
    def gain_db(self) -> float:
        """Analogue gain in decibels (0 dB = unity)."""
        return self._gain_db

    def set_gain_db(self, value: float) -> None:
        """Set the analogue gain; raises :class:`DeviceValueError` outside the camera's range."""
        self._require_open()
        value = _check_range(self.id, "gain_db", value, *self.gain_range_db)
        self._apply_gain_db(value)
        self._gain_db = value

    def read_frame(self, timeout_s: float = 1.0) -> Frame:
        """Wait for the next triggered exposure and return it.

        Raises :class:`~eyeserver.errors.DeviceTimeoutError` when no trigger arrives or the
        camera does not deliver within ``timeout_s``, and
        :class:`~eyeserver.errors.DeviceDisconnectedError` when the camera went away.
        """
        self._require_open()
        if timeout_s <= 0:
            raise ValueError(f"timeout_s must be positive, not {timeout_s}")
        return self._read_frame(timeout_s)

    def prepare_stream(self, projectors: Sequence[str]) -> None:
        """Get ready to stream frames lit by ``projectors`` (ids): a camera that needs a
        moment before its first frame takes it here, so that the stream's first frames come
        on time (a simulated camera fills its room's render caches for the scene in front of
        it). Nothing by default."""
        self._require_open()
        self._prepare_stream(tuple(projectors))

    def _prepare_stream(self, projectors: tuple[str, ...]) -> None:
        """Hook of :meth:`prepare_stream`."""

    @abc.abstractmethod
    def _apply_exposure_us(self, value: float) -> None: ...

    @abc.abstractmethod
    def _apply_gain_db(self, value: float) -> None: ...

    @abc.abstractmethod
    def _read_frame(self, timeout_s: float) -> Frame: ...

    def describe(self) -> dict[str, object]:
        return {**super().describe(), "width": self.width, "height": self.height,
                "bit_depth": self.bit_depth, "exposure_us": self.exposure_us,
                "gain_db": self.gain_db}


class Projector(Device):
    """A light source that projects the fringe pattern (an LED behind a Ronchi grating).

    ``enabled`` says whether it may light at all; ``strobe`` decides whether it lights only during
    exposures the trigger assigns to it (the normal, interleaved mode) or continuously.
    """

    kind = "projector"

    def __init__(self, device_id: str) -> None:
        super().__init__(device_id)
        self._enabled = True
        self._intensity = 1.0
        self._strobe = True

    @property
    def enabled(self) -> bool:
        """Whether the source may light."""
        return self._enabled

    def set_enabled(self, value: bool) -> None:
        """Switch the source on (``True``) or off."""
        self._require_open()
        self._apply_enabled(bool(value))
        self._enabled = bool(value)

    @property
    def intensity(self) -> float:
        """Relative drive level, 0 (dark) to 1 (full current)."""
        return self._intensity

    def set_intensity(self, value: float) -> None:
        """Set the relative drive level in [0, 1]."""
        self._require_open()
        value = _check_range(self.id, "intensity", value, 0.0, 1.0)
        self._apply_intensity(value)
        self._intensity = value

    @property
    def strobe(self) -> bool:
        """True: lit only on the trigger's pulses that name it; False: lit continuously."""
        return self._strobe

    def set_strobe(self, value: bool) -> None:
        """Choose strobed (``True``) or continuous (``False``) lighting."""
        self._require_open()
        self._apply_strobe(bool(value))
        self._strobe = bool(value)

    def check(self) -> None:
        """Ask the device whether it can light: the rig asks before every pulse that names it,
        so a projector that is gone fails the capture (and is put in fault) instead of leaving
        fringe-less images that look like a measurement.

        Raises
        ------
        DeviceError
            The device is not open, or it does not answer or reports a fault.
        """
        self._require_open()
        self._check()

    def _check(self) -> None:
        """The driver's status query (none by default: a driver that can ask its controller
        overrides this)."""

    @abc.abstractmethod
    def _apply_enabled(self, value: bool) -> None: ...

    @abc.abstractmethod
    def _apply_intensity(self, value: float) -> None: ...

    @abc.abstractmethod
    def _apply_strobe(self, value: bool) -> None: ...

    def describe(self) -> dict[str, object]:
        return {**super().describe(), "enabled": self.enabled, "intensity": self.intensity,
                "strobe": self.strobe}


@dataclass(frozen=True)
class TriggerStep:
    """One pulse of the trigger's sequence: which projectors light, which cameras expose."""

    projectors: tuple[str, ...]
    cameras: tuple[str, ...]


@dataclass(frozen=True)
class TriggerPulse:
    """A pulse that was fired.

    ``index`` counts the trigger's pulses since ``open()``; ``t_ns`` is when it fired, i.e. the
    start of the exposures it triggers (each camera adds half its own exposure for the frame's
    mid-exposure time); ``step`` says what it lit and exposed.
    """

    index: int
    t_ns: int
    step: TriggerStep


class Trigger(Device):
    """The trigger/strobe controller that times exposures and lights projectors.

    The sequence is a list of :class:`TriggerStep`; the ``n``-th pulse after
    :meth:`set_sequence` uses step ``n % len(sequence)`` (setting a sequence restarts it), so
    ``[left, right]`` interleaves the two units frame by frame.
    """

    kind = "trigger"
    rate_range_hz: tuple[float, float] = (0.1, 100.0)

    def __init__(self, device_id: str) -> None:
        super().__init__(device_id)
        self._rate_hz = 25.0
        self._sequence: tuple[TriggerStep, ...] = ()
        self._missed: dict[str, int] = {}
        self._missed_lock = threading.Lock()

    def open(self) -> None:
        """Connect to the device. Idempotent; the missed-trigger counts start again at 0, as
        the pulse indices do."""
        if not self.is_open:
            with self._missed_lock:
                self._missed = {}
        super().open()

    @property
    def missed_triggers(self) -> int:
        """Pulses that exposed no frame, counted once per camera that did not deliver one,
        since :meth:`open` (:meth:`record_missed`)."""
        with self._missed_lock:
            return sum(self._missed.values())

    def record_missed(self, pulse: TriggerPulse, camera_id: str) -> None:
        """Count ``pulse`` as missed by ``camera_id``: it was fired for that camera, and no
        frame of it arrived (the rig calls this when it gives up waiting). A camera that misses
        triggers has a trigger cable, input or exposure setting to look at; the count is in
        :meth:`describe`, so the device's status shows it."""
        with self._missed_lock:
            self._missed[camera_id] = self._missed.get(camera_id, 0) + 1
        _log.warning("trigger %s: pulse %d exposed no frame of camera %s", self.id,
                     pulse.index, camera_id, extra={"device_id": self.id})

    @property
    def rate_hz(self) -> float:
        """Pulse rate in free-running mode, hertz."""
        return self._rate_hz

    def set_rate_hz(self, value: float) -> None:
        """Set the free-running pulse rate in hertz."""
        self._require_open()
        value = _check_range(self.id, "rate_hz", value, *self.rate_range_hz)
        self._apply_rate_hz(value)
        self._rate_hz = value

    @property
    def sequence(self) -> tuple[TriggerStep, ...]:
        """The lighting/exposure sequence the pulses cycle through."""
        return self._sequence

    def set_sequence(self, steps: Sequence[TriggerStep]) -> None:
        """Set the sequence and restart it at its first step; every step must expose a camera."""
        self._require_open()
        steps = tuple(steps)
        if not steps:
            raise DeviceValueError(self.id, "the trigger sequence needs at least one step")
        for n, step in enumerate(steps):
            if not step.cameras:
                raise DeviceValueError(self.id, f"sequence step {n} exposes no camera")
        self._apply_sequence(steps)
        self._sequence = steps

    def fire(self, at_ns: int | None = None) -> TriggerPulse:
        """Fire one software trigger pulse (the next step of the sequence) and return it.

        ``at_ns`` times the pulse for that moment of the trigger's clock instead of now (a
        pulse scheduled ahead, which the controller's own timer fires then: the frames' times
        are exact, not a sleep's); a moment already past fires now.
        """
        self._require_open()
        if not self._sequence:
            raise DeviceValueError(self.id, "no sequence set; call set_sequence() first")
        return self._fire(at_ns)

    @abc.abstractmethod
    def _apply_rate_hz(self, value: float) -> None: ...

    @abc.abstractmethod
    def _apply_sequence(self, steps: tuple[TriggerStep, ...]) -> None: ...

    @abc.abstractmethod
    def _fire(self, at_ns: int | None) -> TriggerPulse: ...

    @abc.abstractmethod
    def start(self) -> None:
        """Fire pulses continuously at :attr:`rate_hz` until :meth:`stop`."""

    @abc.abstractmethod
    def stop(self) -> None:
        """Stop free-running pulses. Idempotent."""

    def describe(self) -> dict[str, object]:
        with self._missed_lock:
            missed = dict(self._missed)
        return {**super().describe(), "rate_hz": self.rate_hz,
                "sequence": [{"projectors": list(s.projectors), "cameras": list(s.cameras)}
                             for s in self.sequence],
                "missed_triggers": sum(missed.values()), "missed_by_camera": missed}


class PacedTrigger(Trigger):
    """A trigger whose free-running pulses a host thread fires at :attr:`rate_hz`, sleeping on
    ``clock`` between them (a trigger with no timer of its own, or a simulated one: under a
    :class:`~eyeserver.core.clock.ManualClock` it runs as fast as it can while the pulses' times
    stay exactly ``1 / rate_hz`` apart)."""

    _MAX_SLEEP_S = 0.02
    """Longest single sleep, s, so that :meth:`stop` never waits long on a slow rate."""
    _JOIN_TIMEOUT_S = 5.0

    def __init__(self, device_id: str, clock: Clock) -> None:
        super().__init__(device_id)
        self._clock = clock
        self._thread: threading.Thread | None = None
        self._stop_event = threading.Event()
        self.last_run_error: Exception | None = None
        """Why the free-running thread stopped by itself, if it did."""

    @property
    def running(self) -> bool:
        """Whether the free-running thread is firing pulses."""
        return self._thread is not None and self._thread.is_alive()

    def _check_can_start(self) -> None:
        """Raise if the device cannot fire now (a driver that knows its link is down)."""

    def start(self) -> None:
        """Fire pulses at :attr:`rate_hz` on a background thread until :meth:`stop`. Idempotent.

        Raises
        ------
        DeviceNotOpenError
            When the trigger is closed.
        DeviceValueError
            When no sequence is set.
        DeviceError
            When the driver knows the device cannot fire (:meth:`_check_can_start`).
        """
        self._require_open()
        self._check_can_start()
        if not self.sequence:
            raise DeviceValueError(self.id, "no sequence set; call set_sequence() first")
        if self.running:
            return
        self.last_run_error = None
        self._stop_event = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(self._stop_event,),
                                        name=f"trigger-{self.id}", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop free-running and wait for the thread to end. Idempotent; never raises."""
        self._stop_event.set()
        thread, self._thread = self._thread, None
        if thread is not None and thread is not threading.current_thread():
            thread.join(self._JOIN_TIMEOUT_S)
            if thread.is_alive():
                _log.warning("trigger %s: free-running thread did not stop within %s s",
                             self.id, self._JOIN_TIMEOUT_S, extra={"device_id": self.id})

    def _run(self, stop: threading.Event) -> None:
        clock = self._clock
        next_ns = clock.now_ns()
        while not stop.is_set():
            try:
                fired = self.fire()
            except Exception as exc:
                # A controller that vanished simply stops pulsing; the error is kept for
                # whoever supervises the rig, and the thread must not die with a traceback.
                self.last_run_error = exc
                _log.warning("trigger %s stopped free-running: %s", self.id, exc,
                             extra={"device_id": self.id})
                return
            # A thread that woke late fired late: the next pulse keeps a whole period from it
            # (a controller never fires two pulses closer than its period; catching up at once
            # put two 0.7 ms apart on a loaded machine).
            period_ns = round(1e9 / self.rate_hz)
            next_ns = max(next_ns + period_ns, fired.t_ns + period_ns)
            while not stop.is_set():
                remaining_s = (next_ns - clock.now_ns()) / 1e9
                if remaining_s <= 0:
                    break
                clock.sleep(min(remaining_s, self._MAX_SLEEP_S))

    def describe(self) -> dict[str, object]:
        return {**super().describe(), "running": self.running}


class Stage(Device):
    """A motorised linear stage that carries the flat calibration plate along the WCS Z axis.

    Phase-to-height calibration images the plate at known heights (docs/design.md §5); a stage
    puts it there instead of a person. Positions are the plate surface's Z in the WCS, millimetres;
    :meth:`move_to` returns once the stage has settled. Subclasses set ``travel_mm`` and
    implement :meth:`_move_to`.
    """

    kind = "stage"
    travel_mm: tuple[float, float] = (-15.0, 30.0)

    def __init__(self, device_id: str) -> None:
        super().__init__(device_id)
        self._position_mm: float | None = None

    @property
    def position_mm(self) -> float | None:
        """Where the last move put the plate (mm); None before the first move."""
        return self._position_mm

    def move_to(self, z_mm: float) -> None:
        """Move the plate's surface to ``z_mm`` (within :attr:`travel_mm`) and wait until it
        has settled."""
        self._require_open()
        z_mm = _check_range(self.id, "z_mm", z_mm, *self.travel_mm)
        self._move_to(z_mm)
        self._position_mm = z_mm

    @abc.abstractmethod
    def _move_to(self, z_mm: float) -> None: ...

    def describe(self) -> dict[str, object]:
        return {**super().describe(), "position_mm": self.position_mm,
                "travel_mm": list(self.travel_mm)}
