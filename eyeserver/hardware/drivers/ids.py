"""IDS cameras (uEye+, and uEye such as the UI-5240 through IDS's uEye Transport Layer) through
IDS peak's Python API, behind the :class:`Camera` interface.

**Untested on real hardware.** IDS peak is not on PyPI for this platform (it comes from IDS's
website under IDS's licence), so this driver was written against IDS's documented Python samples
and tested only against a fake of exactly the calls it makes (tests/test_driver_ids.py). Check
it on a camera before trusting it: docs/notes/camera-drivers.md lists every call and what to
look at first.

How it acquires, keeps time, counts dropped frames and notices a lost device, and what
it assumes of the SDK: docs/notes/camera-drivers.md (IdsCamera).
"""

from __future__ import annotations

import contextlib
import importlib
import logging
import math
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, Final, TypeVar

import numpy as np

from eyeserver.core.types import Image
from eyeserver.errors import DeviceDisconnectedError, DeviceError, DeviceValueError
from eyeserver.hardware.drivers.camerathread import (
    MONO_PIXEL_FORMATS,
    FrameQueue,
    NodeMapLink,
    StreamingCamera,
    check_region_read_back,
    check_trigger_read_back,
)
from eyeserver.hardware.registry import DriverContext, register_driver

__all__ = ["INSTALL_HINT", "IdsCamera", "db_to_factor", "factor_to_db"]

_log = logging.getLogger(__name__)

_T = TypeVar("_T")

INSTALL_HINT: Final[str] = (
    "install IDS peak from IDS's website (with its uEye Transport Layer for uEye cameras) and "
    "its Python packages ids_peak and ids_peak_ipl into the venv")
"""What a machine needs for this driver; named in the error raised without it."""

_POLL_S: Final[float] = 0.05
"""How long one ``WaitForFinishedBuffer`` waits: bounds how long ``close()`` waits for the
thread."""

_READBACK_DECIMALS: Final[int] = 3
"""Exposure (µs) and gain (dB) read back are rounded to this many decimals: float conversions
of fixed-point registers (and the dB conversion) leave millionths, far below a real step."""

_TRIGGER_SELECTORS: Final[tuple[str, ...]] = ("ExposureStart", "FrameStart")
"""The trigger selectors that expose one frame per pulse, in order of preference (IDS cameras
have ExposureStart)."""

_library_lock = threading.Lock()
_library_users = 0


def db_to_factor(gain_db: float) -> float:
    """A gain in decibels as IDS peak's factor (0 dB is 1.0)."""
    return float(10.0 ** (gain_db / 20.0))


def factor_to_db(factor: float) -> float:
    """IDS peak's gain factor in decibels (1.0 is 0 dB)."""
    if factor <= 0:
        raise ValueError(f"a gain factor must be positive, not {factor}")
    return 20.0 * math.log10(factor)


@dataclass(frozen=True)
class _Buffer:
    """What the link copies out of one finished buffer before queueing it again."""

    arrived_ns: int
    incomplete: bool
    frame_id: int
    timestamp_ns: int
    width: int
    height: int
    image: Image | None


def _load_peak() -> tuple[Any, Any]:
    """Import ``ids_peak.ids_peak`` and ``ids_peak.ids_peak_ipl_extension``; ImportError names
    the gap."""
    try:
        return (importlib.import_module("ids_peak.ids_peak"),
                importlib.import_module("ids_peak.ids_peak_ipl_extension"))
    except ImportError as exc:
        raise ImportError(f"IDS peak's Python API (ids_peak) is not installed: "
                          f"{INSTALL_HINT}") from exc


def _exceptions(peak: Any, *names: str) -> tuple[type[Exception], ...]:
    """IDS peak's exception classes of those names that this version has."""
    found = (getattr(peak, name, None) for name in names)
    return tuple(cls for cls in found if isinstance(cls, type) and issubclass(cls, Exception))


class _PeakLink(NodeMapLink):
    """One opened camera and its data stream: the only code that calls IDS peak.

    Control calls are serialised by a lock; the data stream's ``WaitForFinishedBuffer`` (which
    IDS peak lets another thread call) is not. IDS peak closes a device when its last Python
    reference goes, so :meth:`release` drops every one.
    """

    def __init__(self, device_id: str, serial: str) -> None:
        self.device_id = device_id
        try:
            self._peak, self._extension = _load_peak()
        except ImportError as exc:
            raise DeviceError(device_id, str(exc)) from exc
        peak = self._peak
        self._error: type[Exception] = peak.Exception
        self._timeout: type[Exception] = peak.TimeoutException
        self._aborted = _exceptions(peak, "AbortedException")
        self._lost_errors = _exceptions(peak, "IOException", "TimeoutException")
        self._value_errors = _exceptions(peak, "OutOfRangeException", "InvalidArgumentException",
                                         "NotFoundException", "NotAvailableException")
        self._unavailable = (peak.NodeAccessStatus_NotAvailable,
                             peak.NodeAccessStatus_NotImplemented)
        self._lock = threading.RLock()
        self._device: Any = None
        self._nodes: Any = None
        self._stream: Any = None
        self._lost_callback: Any = None
        self._lost_handle: Any = None
        self._library = False
        _acquire_library(peak, device_id)
        self._library = True
        try:
            self._open(serial)
        except BaseException:
            self.release()
            raise

    def _open(self, serial: str) -> None:
        peak = self._peak
        with self._translated("looking for cameras"):
            self._manager: Any = peak.DeviceManager.Instance()
            self._manager.Update()
            found = list(self._manager.Devices())
        with self._translated("reading the cameras' names"):
            matches = [descriptor for descriptor in found if serial in (
                str(descriptor.SerialNumber()), str(descriptor.UserDefinedName()))]
            listed = ", ".join(f"{descriptor.ModelName()} {descriptor.SerialNumber()}"
                               for descriptor in found) or "none"
        if not matches:
            raise DeviceDisconnectedError(self.device_id, f"no camera with serial number or user "
                                                          f"id {serial!r} (IDS peak finds: "
                                                          f"{listed})")
        if len(matches) > 1:
            raise DeviceValueError(self.device_id, f"{len(matches)} cameras answer to "
                                                   f"{serial!r}; name one by its serial number")
        descriptor = matches[0]
        with self._translated(f"opening the camera {serial!r}"):
            self.model = str(descriptor.ModelName())
            self.serial_number = str(descriptor.SerialNumber())
            self.key = str(descriptor.Key())
            if not descriptor.IsOpenable(peak.DeviceAccessType_Control):
                raise DeviceError(self.device_id, f"the camera {serial!r} cannot be opened for "
                                                  "control (another program has it?)")
            self._device = descriptor.OpenDevice(peak.DeviceAccessType_Control)
            self._nodes = self._device.RemoteDevice().NodeMaps()[0]
            self._stream = self._device.DataStreams()[0].OpenDataStream()

    @contextlib.contextmanager
    def _translated(self, doing: str) -> Iterator[None]:
        try:
            yield
        except self._error as exc:
            reason = f"{doing}: {exc}"
            if isinstance(exc, self._lost_errors):
                raise DeviceDisconnectedError(self.device_id, reason) from exc
            if isinstance(exc, self._value_errors):
                raise DeviceValueError(self.device_id, reason) from exc
            raise DeviceError(self.device_id, reason) from exc

    def _call(self, doing: str, call: Callable[[], _T]) -> _T:
        with self._lock, self._translated(doing):
            return call()

    # --- device lost ------------------------------------------------------------------------

    def on_lost(self, callback: Callable[[], None]) -> None:
        """Call ``callback`` (from an IDS peak thread) when IDS peak reports this camera lost."""
        key = self.key

        def lost(lost_key: str) -> None:
            if str(lost_key) == key:
                callback()

        with self._translated("registering for the device-lost event"):
            # IDS peak keeps only a reference to the wrapper: it must outlive the registration.
            self._lost_callback = self._manager.DeviceLostCallback(lost)
            self._lost_handle = self._manager.RegisterDeviceLostCallback(self._lost_callback)

    def _forget_lost(self) -> None:
        handle, self._lost_handle = self._lost_handle, None
        if handle is not None:
            with contextlib.suppress(self._error):
                self._manager.UnregisterDeviceLostCallback(handle)
        self._lost_callback = None

    # --- features ---------------------------------------------------------------------------

    def _find(self, name: str) -> Any:
        if not self._nodes.HasNode(name):
            raise DeviceValueError(self.device_id, f"the camera has no feature {name}")
        return self._nodes.FindNode(name)

    def has(self, name: str) -> bool:
        """Whether the camera has the feature ``name``."""
        return bool(self._call(f"looking for {name}", lambda: self._nodes.HasNode(name)))

    def entries(self, name: str) -> list[str]:
        """The entries the enumeration feature ``name`` offers."""
        return self._call(f"listing {name}", lambda: [
            str(entry.SymbolicValue()) for entry in self._find(name).Entries()
            if entry.AccessStatus() not in self._unavailable])

    def get(self, name: str) -> Any:
        """The value of the integer or float feature ``name``."""
        return self._call(f"reading {name}", lambda: self._find(name).Value())

    def set(self, name: str, value: float) -> Any:
        """Set the integer or float feature ``name``; return its value read back."""
        def write() -> Any:
            node = self._find(name)
            node.SetValue(value)
            return node.Value()
        return self._call(f"setting {name} to {value!r}", write)

    def _write_entry(self, name: str, entry: str) -> str:
        def write() -> str:
            node = self._find(name)
            node.SetCurrentEntry(entry)
            return str(node.CurrentEntry().SymbolicValue())
        return self._call(f"setting {name} to {entry}", write)

    def bounds(self, name: str) -> tuple[float, float]:
        """The least and greatest values the feature ``name`` takes now."""
        def read() -> tuple[float, float]:
            node = self._find(name)
            return float(node.Minimum()), float(node.Maximum())
        return self._call(f"reading the bounds of {name}", read)

    def execute(self, name: str) -> None:
        """Execute the command ``name`` and wait until the camera has done it."""
        def run() -> None:
            node = self._find(name)
            node.Execute()
            node.WaitUntilDone()
        self._call(f"executing {name}", run)

    # --- settings ---------------------------------------------------------------------------

    def set_trigger(self, source: str) -> tuple[str, str]:
        """Expose one frame on each rising edge of ``source``: every trigger selector's
        TriggerMode off, then ExposureStart's (or FrameStart's) on. Returns the selector used and
        the source read back."""
        selectors = self.entries("TriggerSelector")
        chosen = next((name for name in _TRIGGER_SELECTORS if name in selectors), None)
        if chosen is None:
            raise DeviceValueError(self.device_id, f"the camera has neither an ExposureStart nor "
                                                   f"a FrameStart trigger (it has "
                                                   f"{', '.join(selectors) or 'none'})")
        for selector in selectors:
            self.set_enum("TriggerSelector", selector)
            self.set_enum("TriggerMode", "Off")
        self.set_enum("TriggerSelector", chosen)
        read_back = self.set_enum("TriggerSource", source)
        if self.has("TriggerActivation"):
            self.set_enum("TriggerActivation", "RisingEdge")
        self.set_enum("TriggerMode", "On")
        return chosen, read_back

    # --- streaming --------------------------------------------------------------------------

    def start(self, n_buffers: int) -> None:
        """Announce and queue buffers for the current payload, lock the transport parameters,
        start the stream and the camera's acquisition."""
        stream = self._stream

        def start() -> None:
            payload = int(self._find("PayloadSize").Value())
            for _ in range(max(int(stream.NumBuffersAnnouncedMinRequired()), n_buffers)):
                stream.QueueBuffer(stream.AllocAndAnnounceBuffer(payload))
            if self._nodes.HasNode("TLParamsLocked"):
                self._nodes.FindNode("TLParamsLocked").SetValue(1)
            stream.StartAcquisition()

        self._call("starting the data stream", start)
        self.execute("AcquisitionStart")

    def stop(self) -> None:
        """Stop the camera's acquisition and the stream, and give the buffers back."""
        stream = self._stream
        peak = self._peak
        self.execute("AcquisitionStop")

        def stop() -> None:
            stream.StopAcquisition(peak.AcquisitionStopMode_Default)
            stream.Flush(peak.DataStreamFlushMode_DiscardAll)
            for buffer in list(stream.AnnouncedBuffers()):
                stream.RevokeBuffer(buffer)
            if self._nodes.HasNode("TLParamsLocked"):
                self._nodes.FindNode("TLParamsLocked").SetValue(0)

        self._call("stopping the data stream", stop)

    def wait(self, timeout_s: float, bit_depth: int,
             now_ns: Callable[[], int]) -> _Buffer | None:
        """Wait up to ``timeout_s`` for the next finished buffer; copy it out, with its arrival
        time on the clock ``now_ns`` (nanoseconds), and queue it again. None when none came.
        Raises :class:`DeviceDisconnectedError` when the wait fails otherwise: IDS peak's way of
        saying the device is gone."""
        stream = self._stream
        try:
            buffer = stream.WaitForFinishedBuffer(max(1, round(timeout_s * 1e3)))
        except self._timeout:
            return None
        except self._aborted:  # nobody here calls KillWait; it is no frame either way
            return None
        except self._error as exc:
            raise DeviceDisconnectedError(self.device_id, f"waiting for a frame: {exc}") from exc
        arrived_ns = now_ns()
        try:
            return self._copy(buffer, bit_depth, arrived_ns)
        finally:
            with self._translated("queueing a buffer again"):
                stream.QueueBuffer(buffer)

    def _copy(self, buffer: Any, bit_depth: int, arrived_ns: int) -> _Buffer:
        with self._translated("reading a buffer"):
            incomplete = bool(buffer.IsIncomplete())
            frame_id, timestamp_ns = int(buffer.FrameID()), int(buffer.Timestamp_ns())
        if incomplete:
            return _Buffer(arrived_ns, True, frame_id, timestamp_ns, 0, 0, None)
        try:
            image = self._extension.BufferToImage(buffer)
            # Views of the buffer's memory, which the camera refills once it is queued again.
            copied: Image = (np.array(image.get_numpy_2D(), dtype=np.uint8) if bit_depth == 8
                             else np.array(image.get_numpy_2D_16(), dtype=np.uint16))
            return _Buffer(arrived_ns, False, frame_id, timestamp_ns, int(image.Width()),
                           int(image.Height()), copied)
        except self._error as exc:
            _log.warning("camera %s: frame id %d cannot be converted: %s", self.device_id,
                         frame_id, exc)
            return _Buffer(arrived_ns, False, frame_id, timestamp_ns, 0, 0, None)

    def software_trigger(self) -> None:
        """Execute TriggerSoftware."""
        self.execute("TriggerSoftware")

    def release(self) -> None:
        """Drop the device-lost callback, the stream, the node map and the device (IDS peak
        closes it as its last reference goes), and this link's hold on the library."""
        with self._lock:
            if self._lost_handle is not None:
                self._forget_lost()
            self._stream = None
            self._nodes = None
            self._device = None
            if self._library:
                self._library = False
                _release_library(self._peak)


def _acquire_library(peak: Any, device_id: str) -> None:
    """``Library.Initialize()`` for the first open camera of the process."""
    global _library_users
    with _library_lock:
        if _library_users == 0:
            try:
                peak.Library.Initialize()
            except peak.Exception as exc:
                raise DeviceError(device_id, f"IDS peak did not initialise: {exc}") from exc
        _library_users += 1


def _release_library(peak: Any) -> None:
    """``Library.Close()`` when the last camera of the process is released."""
    global _library_users
    with _library_lock:
        _library_users -= 1
        if _library_users == 0:
            with contextlib.suppress(peak.Exception):
                peak.Library.Close()


@register_driver("camera", "IdsCamera")
class IdsCamera(StreamingCamera[_PeakLink]):
    """An IDS camera through IDS peak, hardware-triggered. Untested on real hardware (the
    module's notes).

    Parameters
    ----------
    device_id : str
        The camera's id in the rig.
    context : DriverContext
        Its clock is the rig clock the frames' times are put on.
    serial : str
        The camera's serial number (on its label), or its user-defined name where that names one
        camera.
    pixel_format : {"Mono8", "Mono10", "Mono12"}
        8 bits per pixel, or 10/12 unpacked in 16-bit words.
    trigger_source : str
        The camera's TriggerSource for each frame: ``Line0`` (the trigger input of IDS cameras,
        the trigger controller's cable), or ``Software`` to expose on :meth:`software_trigger`.
    offset_x, offset_y, width, height, queue_size
        The region of interest and the frames held for :meth:`read_frame`: as for
        :class:`~eyeserver.hardware.drivers.camerathread.StreamingCamera`.

    Notes
    -----
    A frame's ``exposure_us`` and ``gain_db`` are the camera's settings when it arrived, and its
    ``trigger_index`` the camera's own count of exposures since ``open()``, dropped ones
    included. Its ``extra`` holds ``device_timestamp_ns`` (camera clock) and ``frame_id`` (IDS
    peak's). One reader at a time.
    """

    def __init__(self, device_id: str, *, context: DriverContext, serial: str,
                 pixel_format: str = "Mono8", trigger_source: str = "Line0",
                 offset_x: int = 0, offset_y: int = 0, width: int | None = None,
                 height: int | None = None, queue_size: int = 8) -> None:
        if not serial:
            raise ValueError("serial must name the camera (serial number or user-defined name)")
        super().__init__(device_id, clock=context.clock, pixel_format=pixel_format,
                         trigger_source=trigger_source, offset_x=offset_x, offset_y=offset_y,
                         width=width, height=height, queue_size=queue_size)
        self.serial = serial

    def describe(self) -> dict[str, object]:
        return {**super().describe(), "serial": self.serial}

    # --- StreamingCamera hooks --------------------------------------------------------------

    def _connect(self) -> _PeakLink:
        return _PeakLink(self.id, self.serial)

    def _configure(self, link: _PeakLink) -> None:
        # A previous controller (or a crashed daemon) may have left it acquiring, with the
        # transport parameters (the image format) locked.
        with contextlib.suppress(DeviceError):
            link.execute("AcquisitionStop")
        if link.has("TLParamsLocked"):
            link.set("TLParamsLocked", 0)
        link.set_enum("PixelFormat", self.pixel_format)
        region = link.set_region(*self._roi)
        check_region_read_back(self.id, self._roi, region)
        selector, source = link.set_trigger(self.trigger_source)
        check_trigger_read_back(self.id, self.trigger_source, source)
        if link.has("AcquisitionMode"):
            link.set_enum("AcquisitionMode", "Continuous")
        for auto in ("ExposureAuto", "GainAuto"):
            if link.has(auto):
                link.set_enum(auto, "Off")
        if link.has("GainSelector") and "AnalogAll" in link.entries("GainSelector"):
            link.set_enum("GainSelector", "AnalogAll")

        low, high = link.bounds("Gain")
        self._restore_exposure_and_gain(link, link.bounds("ExposureTime"),
                                        (factor_to_db(low), factor_to_db(high)),
                                        _READBACK_DECIMALS)

        self.width, self.height = region[2], region[3]
        self.bit_depth = MONO_PIXEL_FORMATS[self.pixel_format]
        frame_rate = (float(link.get("AcquisitionFrameRate"))
                      if link.has("AcquisitionFrameRate") else None)
        self._info = {"model": link.model, "serial_number": link.serial_number,
                      "offset_x": region[0], "offset_y": region[1],
                      "trigger_selector": selector, "acquisition_frame_rate_hz": frame_rate}

    def _set_exposure(self, link: _PeakLink, value_us: float) -> float:
        return round(float(link.set("ExposureTime", value_us)), _READBACK_DECIMALS)

    def _set_gain(self, link: _PeakLink, value_db: float) -> float:
        factor = float(link.set("Gain", db_to_factor(value_db)))
        return round(factor_to_db(factor), _READBACK_DECIMALS)

    def _watch(self, link: _PeakLink, frames: FrameQueue) -> None:
        link.on_lost(lambda: frames.mark_lost("IDS peak reports the device lost"))

    # --- the acquisition thread -------------------------------------------------------------

    def _step(self, link: _PeakLink, frames: FrameQueue) -> None:
        """Wait for one buffer (or none) and account for it."""
        buffer = link.wait(_POLL_S, self.bit_depth, self._clock.now_ns)
        if buffer is None:
            return
        image = buffer.image
        if buffer.incomplete:
            _log.warning("camera %s: incomplete frame id %d dropped", self.id, buffer.frame_id)
        elif image is None or image.shape != (self.height, self.width):
            _log.warning("camera %s: frame id %d is not a %dx%d %s image", self.id,
                         buffer.frame_id, self.width, self.height, self.pixel_format)
            image = None
        self._deliver(frames, buffer.frame_id, image, whole=not buffer.incomplete,
                      arrived_ns=buffer.arrived_ns, device_timestamp_ns=buffer.timestamp_ns,
                      extra={"frame_id": buffer.frame_id})
