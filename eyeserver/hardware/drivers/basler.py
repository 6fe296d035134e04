"""Basler cameras (ace GigE, ace USB 3.0 and others) through pylon's Python binding, pypylon.

pypylon (``pip install pypylon``, which brings pylon's runtime with it) is imported when a camera
is opened, so this module imports, type-checks and registers its driver on machines without it;
opening a camera there raises a :class:`~eyeserver.errors.DeviceError` that says what to install.
Every pylon call goes through :class:`_PylonLink`, the one place that holds untyped pylon objects
and turns pylon's exceptions into eyeserver's (``raise … from``):

=================================================  ================================
what pylon reports                                 raised (:mod:`eyeserver.errors`)
=================================================  ================================
the camera removed (``IsCameraDeviceRemoved``),    ``DeviceDisconnectedError``
no camera with the serial number or user id, a
control call timing out
a value out of range or refused, a feature or      ``DeviceValueError``
enumeration entry the camera lacks
anything else (the camera in use elsewhere, ...)   ``DeviceError``
=================================================  ================================

How it acquires, keeps time, counts dropped frames and notices a lost device, and what
it assumes of the SDK: docs/notes/camera-drivers.md (BaslerCamera).
"""

from __future__ import annotations

import contextlib
import importlib
import logging
import threading
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, Final, TypeVar

import numpy as np

from eyeserver.core.types import Image
from eyeserver.errors import (
    DeviceDisconnectedError,
    DeviceError,
    DeviceTimeoutError,
    DeviceValueError,
)
from eyeserver.hardware.drivers.camerathread import (
    MONO_PIXEL_FORMATS,
    FrameQueue,
    NodeMapLink,
    StreamingCamera,
    check_region_read_back,
    check_trigger_read_back,
)
from eyeserver.hardware.registry import DriverContext, register_driver

__all__ = ["INSTALL_HINT", "BaslerCamera", "ticks_to_ns"]

_log = logging.getLogger(__name__)

_T = TypeVar("_T")

INSTALL_HINT: Final[str] = "install pypylon into the venv (pip install -e '.[basler]')"
"""What a machine needs for this driver; named in the error raised without it."""

_POLL_S: Final[float] = 0.05
"""How long one ``RetrieveResult`` waits: bounds how long ``close()`` waits for the thread."""

_TRIGGER_READY_TIMEOUT_S: Final[float] = 1.0
"""How long :meth:`BaslerCamera.software_trigger` waits for the camera to take a trigger."""

_READBACK_DECIMALS: Final[int] = 3
"""Exposure (µs) and gain (dB) read back are rounded to this many decimals: the float features
are computed from fixed-point registers and read back a few millionths off the value set (the
emulator's Gain: 3.0 reads 2.999994), far below any camera's real step."""

_NANOSECONDS_PER_SECOND: Final[int] = 1_000_000_000


def ticks_to_ns(ticks: int, tick_frequency_hz: int) -> int:
    """A camera timestamp in ticks of ``tick_frequency_hz`` (hertz), as nanoseconds.

    Integer arithmetic, so that a 64-bit tick count loses nothing to a float's 53-bit mantissa.
    """
    if tick_frequency_hz <= 0:
        raise ValueError(f"tick_frequency_hz must be positive, not {tick_frequency_hz}")
    if tick_frequency_hz == _NANOSECONDS_PER_SECOND:
        return ticks
    return ticks * _NANOSECONDS_PER_SECOND // tick_frequency_hz


@dataclass(frozen=True)
class _Grab:
    """What the link copies out of one pylon grab result before releasing it."""

    arrived_ns: int
    succeeded: bool
    error: str
    block_id: int
    timestamp_ticks: int
    width: int
    height: int
    pixel_type: int
    image: Image | None


def _load_pylon() -> tuple[Any, Any]:
    """Import pypylon's ``pylon`` and ``genicam`` modules; ImportError names the gap."""
    try:
        with warnings.catch_warnings():
            # pypylon's SWIG-made types lack __module__, which Python deprecates at import;
            # with warnings as errors (the tests) the extension's initialisation fails half
            # way and takes the process down with a segmentation fault (pypylon 26.10).
            warnings.filterwarnings("ignore", category=DeprecationWarning,
                                    message=r"builtin type Swig\w+ has no __module__")
            return (importlib.import_module("pypylon.pylon"),
                    importlib.import_module("pypylon.genicam"))
    except ImportError as exc:
        raise ImportError(f"pypylon is not installed: {INSTALL_HINT}") from exc


def _readback(value: Any) -> float:
    return round(float(value), _READBACK_DECIMALS)


class _PylonLink(NodeMapLink):
    """One opened camera: the only code that calls pylon.

    Control calls are serialised by a re-entrant lock (one GenICam conversation at a time, a
    software trigger's readiness wait not interleaved with settings; a link method may call
    another under it); ``RetrieveResult``, which pylon lets another thread call, is not.
    """

    def __init__(self, device_id: str, serial: str, device_class: str | None) -> None:
        self.device_id = device_id
        try:
            self._pylon, self._genicam = _load_pylon()
        except ImportError as exc:
            raise DeviceError(device_id, str(exc)) from exc
        genicam = self._genicam
        self._generic: type[Exception] = genicam.GenericException
        self._timeout: type[Exception] = genicam.TimeoutException
        self._value_errors: tuple[type[Exception], ...] = (
            genicam.OutOfRangeException, genicam.InvalidArgumentException,
            genicam.LogicalErrorException)
        self._lock = threading.RLock()
        self._camera: Any = None
        factory = self._pylon.TlFactory.GetInstance()
        with self._translated("listing the cameras"):
            if device_class is None:
                found = list(factory.EnumerateDevices())
            else:
                wanted = self._pylon.DeviceInfo()
                wanted.SetDeviceClass(device_class)
                found = list(factory.EnumerateDevices([wanted]))
        matches = [info for info in found
                   if serial in (str(info.GetSerialNumber()), str(info.GetUserDefinedName()))]
        if not matches:
            listed = ", ".join(f"{info.GetModelName()} {info.GetSerialNumber()}"
                               for info in found) or "none"
            where = f" among {device_class} devices" if device_class else ""
            raise DeviceDisconnectedError(device_id, f"no camera with serial number or user id "
                                                     f"{serial!r}{where} (pylon finds: {listed})")
        if len(matches) > 1:
            raise DeviceValueError(device_id, f"{len(matches)} cameras answer to {serial!r}; "
                                              "name one by its serial number")
        self.info: Any = matches[0]
        with self._translated(f"opening the camera {serial!r}"):
            camera = self._pylon.InstantCamera(factory.CreateDevice(self.info))
            camera.Open()
        self._camera = camera
        self._nodes: Any = camera.GetNodeMap()

    @contextlib.contextmanager
    def _translated(self, doing: str) -> Iterator[None]:
        try:
            yield
        except self._generic as exc:
            reason = f"{doing}: {exc}"
            if self.is_removed():
                raise DeviceDisconnectedError(self.device_id, f"{reason} (pylon reports the "
                                                              "camera removed)") from exc
            if isinstance(exc, self._timeout):
                raise DeviceDisconnectedError(self.device_id, reason) from exc
            if isinstance(exc, self._value_errors):
                raise DeviceValueError(self.device_id, reason) from exc
            raise DeviceError(self.device_id, reason) from exc

    def _call(self, doing: str, call: Callable[[], _T]) -> _T:
        with self._lock, self._translated(doing):
            return call()

    def is_removed(self) -> bool:
        """Whether pylon knows the camera is gone (a flag: asks nothing of the camera)."""
        camera = self._camera
        if camera is None:
            return False
        try:
            return bool(camera.IsCameraDeviceRemoved())
        except self._generic:
            return False

    # --- features ---------------------------------------------------------------------------

    def _node(self, name: str) -> Any:
        """The feature ``name``, or None when the camera has none (or not now)."""
        node = self._nodes.GetNode(name)
        return node if self._genicam.IsAvailable(node) else None

    def _require(self, name: str) -> Any:
        node = self._node(name)
        if node is None:
            raise DeviceValueError(self.device_id, f"the camera has no feature {name}")
        return node

    def has(self, name: str) -> bool:
        """Whether the camera has the feature ``name`` now."""
        return self._call(f"looking for {name}", lambda: self._node(name) is not None)

    def entries(self, name: str) -> list[str]:
        """The entries the enumeration feature ``name`` offers now."""
        return self._call(f"listing {name}",
                          lambda: [str(entry) for entry in self._require(name).Symbolics])

    def get(self, name: str) -> Any:
        """The value of the feature ``name``."""
        return self._call(f"reading {name}", lambda: self._require(name).GetValue())

    def set(self, name: str, value: object) -> Any:
        """Set the feature ``name`` to ``value``; return its value read back."""
        def write() -> Any:
            node = self._require(name)
            node.SetValue(value)
            return node.GetValue()
        return self._call(f"setting {name} to {value!r}", write)

    def _write_entry(self, name: str, entry: str) -> str:
        return str(self.set(name, entry))

    def bounds(self, name: str) -> tuple[float, float]:
        """The least and greatest values the feature ``name`` takes now."""
        def read() -> tuple[float, float]:
            node = self._require(name)
            return float(node.GetMin()), float(node.GetMax())
        return self._call(f"reading the bounds of {name}", read)

    # --- identity and settings ----------------------------------------------------------------

    def identity(self) -> dict[str, object]:
        """Vendor, model, serial number, user id and transport (GigE Vision, USB3 Vision, or
        pylon's device class for others, such as the emulation's ``BaslerCamEmu``)."""
        info = self.info
        camera = self._camera
        transport = ("GigE Vision" if camera.IsGigE() else "USB3 Vision" if camera.IsUsb()
                     else str(info.GetDeviceClass()))
        return {"vendor": str(info.GetVendorName()), "model": str(info.GetModelName()),
                "serial_number": str(info.GetSerialNumber()),
                "user_id": str(info.GetUserDefinedName()), "transport": transport}

    def set_trigger(self, source: str) -> str:
        """Expose every frame on a rising edge of ``source``: every trigger selector's
        TriggerMode off, then FrameStart's on. Returns the source read back."""
        selectors = self.entries("TriggerSelector")
        if "FrameStart" not in selectors:
            raise DeviceValueError(self.device_id, f"the camera has no FrameStart trigger (it "
                                                   f"has {', '.join(selectors) or 'none'})")
        for selector in selectors:
            self.set("TriggerSelector", selector)
            if self.is_writable("TriggerMode"):
                self.set("TriggerMode", "Off")
        self.set("TriggerSelector", "FrameStart")
        read_back = self.set_enum("TriggerSource", source)
        if self.has("TriggerActivation"):
            self.set_enum("TriggerActivation", "RisingEdge")
        self.set("TriggerMode", "On")
        return read_back

    def is_writable(self, name: str) -> bool:
        """Whether the feature ``name`` can be written now."""
        return self._call(f"looking at {name}", lambda: bool(
            self._genicam.IsWritable(self._nodes.GetNode(name))))

    def tick_frequency_hz(self) -> int:
        """The timestamp tick rate: ``GevTimestampTickFrequency`` where the camera has it (GigE),
        else 1 GHz (USB3 Vision stamps nanoseconds)."""
        if self.has("GevTimestampTickFrequency"):
            return int(self.get("GevTimestampTickFrequency"))
        return _NANOSECONDS_PER_SECOND

    # --- streaming --------------------------------------------------------------------------

    def start(self, n_buffers: int) -> None:
        """Grab one by one (every frame, in order) into ``n_buffers`` pylon buffers."""
        camera = self._camera
        pylon = self._pylon

        def start() -> None:
            camera.MaxNumBuffer.SetValue(n_buffers)
            camera.StartGrabbing(pylon.GrabStrategy_OneByOne)

        self._call("starting to grab", start)

    def stop(self) -> None:
        """Stop grabbing."""
        self._call("stopping the grab", self._camera.StopGrabbing)

    def software_trigger(self) -> None:
        """Execute TriggerSoftware once the camera can take a trigger (an emulated or real
        camera ignores one that comes while it is still busy with the last frame)."""
        camera = self._camera
        pylon = self._pylon

        def fire() -> None:
            ready = camera.WaitForFrameTriggerReady(round(_TRIGGER_READY_TIMEOUT_S * 1e3),
                                                    pylon.TimeoutHandling_Return)
            if not ready:
                raise DeviceTimeoutError(self.device_id, f"the camera was not ready for a "
                                                         f"trigger within "
                                                         f"{_TRIGGER_READY_TIMEOUT_S} s")
            camera.ExecuteSoftwareTrigger()

        self._call("firing the software trigger", fire)

    def retrieve(self, timeout_s: float, now_ns: Callable[[], int]) -> _Grab | None:
        """Wait up to ``timeout_s`` for the next grab result; copy it out, with its arrival
        time on the clock ``now_ns`` (nanoseconds), and release it. None when none came. Raises
        :class:`DeviceDisconnectedError` once pylon reports the camera removed."""
        camera = self._camera
        try:
            result = camera.RetrieveResult(max(1, round(timeout_s * 1e3)),
                                           self._pylon.TimeoutHandling_Return)
        except self._generic as exc:
            if self.is_removed():
                raise DeviceDisconnectedError(self.device_id, f"pylon reports the camera "
                                                              f"removed ({exc})") from exc
            raise DeviceError(self.device_id, f"retrieving a frame: {exc}") from exc
        if not result.IsValid():  # nothing within the timeout
            if self.is_removed():
                raise DeviceDisconnectedError(self.device_id, "pylon reports the camera removed")
            return None
        arrived_ns = now_ns()
        try:
            succeeded = bool(result.GrabSucceeded())
            image: Image | None = None
            if succeeded:
                # GetArray() may share memory with the pylon buffer, which Release() recycles.
                image = np.array(result.GetArray(), copy=True)
            return _Grab(arrived_ns=arrived_ns, succeeded=succeeded,
                         error="" if succeeded else str(result.GetErrorDescription()),
                         block_id=int(result.GetBlockID()),
                         timestamp_ticks=int(result.GetTimeStamp()),
                         width=int(result.GetWidth()), height=int(result.GetHeight()),
                         pixel_type=int(result.GetPixelType()), image=image)
        finally:
            result.Release()

    def pixel_type(self, pixel_format: str) -> int:
        """pylon's pixel type code of ``pixel_format`` (``PixelType_Mono12``...)."""
        return int(getattr(self._pylon, f"PixelType_{pixel_format}"))

    def release(self) -> None:
        """Stop grabbing, close the camera and destroy pylon's device object, whatever fails
        (a removed camera's goodbyes fail at once: pylon knows it is gone)."""
        camera, self._camera = self._camera, None
        if camera is None:
            return
        with self._lock:
            for goodbye in (camera.StopGrabbing, camera.Close, camera.DestroyDevice):
                try:
                    goodbye()
                except self._generic as exc:
                    _log.warning("camera %s: %s", self.device_id, exc)


@register_driver("camera", "BaslerCamera")
class BaslerCamera(StreamingCamera[_PylonLink]):
    """A Basler camera through pylon, hardware-triggered.

    Parameters
    ----------
    device_id : str
        The camera's id in the rig.
    context : DriverContext
        Its clock is the rig clock the frames' times are put on.
    serial : str
        The camera's serial number (on its label, ``21234567``), or its user id
        (``DeviceUserID``, set in pylon Viewer) where that names one camera.
    pixel_format : {"Mono8", "Mono10", "Mono12"}
        8 bits per pixel, or 10/12 unpacked in 16-bit words.
    trigger_source : str
        The camera's TriggerSource for each frame: ``Line1`` (the opto-coupled input, the
        trigger controller's cable), or ``Software`` to expose on :meth:`software_trigger`
        (tests, bench without a trigger).
    offset_x, offset_y, width, height, queue_size
        The region of interest and the frames held for :meth:`read_frame`: as for
        :class:`~eyeserver.hardware.drivers.camerathread.StreamingCamera`.
    device_class : str or None
        The pylon transport layer to look in: ``BaslerGigE``, ``BaslerUsb`` or ``BaslerCamEmu``
        (pylon's camera emulation); None looks in all of them, which costs GigE discovery's
        quarter of a second at each ``open()`` even for a USB camera.
    test_image : str or None
        None (the default) turns the camera's test image off at ``open()``; a
        ``TestImageSelector`` (or ``TestPattern``) entry such as ``Testimage1`` shows that
        instead of the sensor's picture: for tests, and for checking the link on a bench.

    Notes
    -----
    A frame's ``exposure_us`` and ``gain_db`` are the camera's settings when it arrived, and its
    ``trigger_index`` the camera's own count of exposures since ``open()``, dropped ones
    included. Its ``extra`` holds ``device_timestamp_ns`` (camera clock, 0 for none) and
    ``block_id`` (pylon's frame id). One reader at a time.
    """

    def __init__(self, device_id: str, *, context: DriverContext, serial: str,
                 pixel_format: str = "Mono8", trigger_source: str = "Line1",
                 offset_x: int = 0, offset_y: int = 0, width: int | None = None,
                 height: int | None = None, queue_size: int = 8,
                 device_class: str | None = None, test_image: str | None = None) -> None:
        if not serial:
            raise ValueError("serial must name the camera (serial number or user id)")
        if device_class is not None and not device_class:
            raise ValueError("device_class must name a pylon transport layer, or be None")
        if test_image is not None and (not test_image or test_image == "Off"):
            raise ValueError("test_image must name a test image; None turns it off")
        super().__init__(device_id, clock=context.clock, pixel_format=pixel_format,
                         trigger_source=trigger_source, offset_x=offset_x, offset_y=offset_y,
                         width=width, height=height, queue_size=queue_size)
        self.serial = serial
        self.device_class = device_class
        self.test_image = test_image
        self._pixel_type = 0
        self._tick_frequency_hz = _NANOSECONDS_PER_SECOND
        self._exposure_feature = "ExposureTime"
        self._gain_feature = "Gain"

    def describe(self) -> dict[str, object]:
        return {**super().describe(), "serial": self.serial, "device_class": self.device_class}

    # --- StreamingCamera hooks --------------------------------------------------------------

    def _connect(self) -> _PylonLink:
        return _PylonLink(self.id, self.serial, self.device_class)

    def _configure(self, link: _PylonLink) -> None:
        identity = link.identity()
        test_image = self._configure_test_image(link)
        offered = link.entries("PixelFormat")
        if self.pixel_format not in offered:
            raise DeviceValueError(self.id, f"the camera offers no {self.pixel_format} "
                                            f"(it has {', '.join(offered) or 'none'})")
        link.set_enum("PixelFormat", self.pixel_format)
        self._pixel_type = link.pixel_type(self.pixel_format)

        region = link.set_region(*self._roi)
        check_region_read_back(self.id, self._roi, region)

        source = link.set_trigger(self.trigger_source)
        check_trigger_read_back(self.id, self.trigger_source, source)
        if link.has("AcquisitionMode"):
            link.set_enum("AcquisitionMode", "Continuous")
        # A frame-rate limit left on would silently swallow triggers that come faster.
        if link.is_writable("AcquisitionFrameRateEnable"):
            link.set("AcquisitionFrameRateEnable", False)
        for auto in ("ExposureAuto", "GainAuto"):
            if link.is_writable(auto):
                link.set_enum(auto, "Off")

        self._exposure_feature = next(
            (name for name in ("ExposureTime", "ExposureTimeAbs") if link.has(name)), "")
        if not self._exposure_feature:
            raise DeviceValueError(self.id, "the camera has neither ExposureTime nor "
                                            "ExposureTimeAbs")
        self._gain_feature = next(
            (name for name in ("Gain", "GainAbs", "GainRaw") if link.has(name)), "")
        if not self._gain_feature:
            raise DeviceValueError(self.id, "the camera has no Gain, GainAbs or GainRaw")
        self._restore_exposure_and_gain(link, link.bounds(self._exposure_feature),
                                        link.bounds(self._gain_feature), _READBACK_DECIMALS)
        self._tick_frequency_hz = link.tick_frequency_hz()

        self.width, self.height = region[2], region[3]
        self.bit_depth = MONO_PIXEL_FORMATS[self.pixel_format]
        self._info = {**identity, "offset_x": region[0], "offset_y": region[1],
                      "test_image": test_image, "exposure_feature": self._exposure_feature,
                      "gain_feature": self._gain_feature,
                      "tick_frequency_hz": self._tick_frequency_hz}

    def _configure_test_image(self, link: _PylonLink) -> str | None:
        """Set the camera's test image (off unless one was asked for); return it read back, or
        None for a camera without test images."""
        feature = next((name for name in ("TestImageSelector", "TestPattern")
                        if link.has(name)), None)
        if feature is None:
            if self.test_image is not None:
                raise DeviceValueError(self.id, "the camera has no test images")
            return None
        return link.set_enum(feature, self.test_image or "Off")

    def _set_exposure(self, link: _PylonLink, value_us: float) -> float:
        return _readback(link.set(self._exposure_feature, value_us))

    def _set_gain(self, link: _PylonLink, value_db: float) -> float:
        if self._gain_feature == "GainRaw":  # an integer register, in the camera's own units
            return _readback(link.set("GainRaw", round(value_db)))
        return _readback(link.set(self._gain_feature, value_db))

    # --- the acquisition thread -------------------------------------------------------------

    def _step(self, link: _PylonLink, frames: FrameQueue) -> None:
        """Retrieve one result (or none) and account for it."""
        grab = link.retrieve(_POLL_S, self._clock.now_ns)
        if grab is None:
            return
        image = grab.image
        if not grab.succeeded:
            _log.warning("camera %s: grab of block %d failed: %s", self.id, grab.block_id,
                         grab.error)
        elif image is None or (grab.width, grab.height, grab.pixel_type) != (
                self.width, self.height, self._pixel_type) or image.shape != (
                self.height, self.width):
            _log.warning("camera %s: block %d is %dx%d pixel type 0x%08x, not the %dx%d %s "
                         "configured", self.id, grab.block_id, grab.width, grab.height,
                         grab.pixel_type, self.width, self.height, self.pixel_format)
            image = None
        self._deliver(frames, grab.block_id, image, whole=grab.succeeded,
                      arrived_ns=grab.arrived_ns,
                      device_timestamp_ns=ticks_to_ns(grab.timestamp_ticks,
                                                      self._tick_frequency_hz),
                      extra={"block_id": grab.block_id})
