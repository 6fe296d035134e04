"""GenICam cameras (GigE Vision, USB3 Vision) through Aravis, behind the :class:`Camera` interface.

Aravis (``gir1.2-aravis-0.8``) is reached through PyGObject, imported when a camera is opened, so
this module imports, type-checks and registers its driver on machines without either; opening a
camera there raises a :class:`~eyeserver.errors.DeviceError` that says what to install. Every
Aravis call goes through :class:`_AravisLink`, the one place that holds untyped gi objects and
turns GLib errors into eyeserver's (``raise … from``):

=================================================  ================================
what Aravis reports                                raised (:mod:`eyeserver.errors`)
=================================================  ================================
no device at the address, no answer (GVCP          ``DeviceDisconnectedError``
timeout), transfer error, control lost
a feature or enumeration entry the camera lacks,   ``DeviceValueError``
a value it refuses
anything else                                      ``DeviceError``
=================================================  ================================

How it acquires, keeps time, counts dropped frames and notices a lost device, and what
it assumes of the SDK: docs/notes/camera-drivers.md (GenicamCamera).
"""

from __future__ import annotations

import contextlib
import importlib
import logging
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, Final, TypeVar

import numpy as np

from eyeserver.core.types import Image
from eyeserver.errors import DeviceDisconnectedError, DeviceError, DeviceValueError
from eyeserver.hardware.drivers.camerathread import (
    MONO_PIXEL_FORMATS,
    FrameQueue,
    StreamingCamera,
    check_region_read_back,
    check_trigger_read_back,
)
from eyeserver.hardware.registry import DriverContext, register_driver

__all__ = ["INSTALL_HINT", "PIXEL_FORMATS", "FoundCamera", "GenicamCamera", "identify_camera",
           "image_from_payload", "list_cameras"]

_log = logging.getLogger(__name__)

_T = TypeVar("_T")

PIXEL_FORMATS: Final[dict[str, int]] = MONO_PIXEL_FORMATS
"""The pixel formats the driver takes and their significant bits (the other camera drivers',
:data:`~eyeserver.hardware.drivers.camerathread.MONO_PIXEL_FORMATS`). Mono10 and Mono12 are the
unpacked ones: one little-endian 16-bit word per pixel, the value in its low bits."""

INSTALL_HINT: Final[str] = (
    "install the Debian packages gir1.2-aravis-0.8 and libgirepository1.0-dev "
    "(scripts/system-packages.sh) and PyGObject into the venv (pip install -e '.[genicam]')")
"""What a machine needs for this driver; named in the error raised without it."""

_CONTROL_CHANNEL_PRIVILEGE_REGISTER: Final[int] = 0x0A00
"""GigE Vision bootstrap register of the control channel privilege: bit 1 (control) or bit 0
(exclusive) set while this host is the camera's controller."""

_POLL_S: Final[float] = 0.05
"""How long one ``timeout_pop_buffer`` waits: bounds how long ``close()`` waits for the thread."""


@dataclass(frozen=True)
class _Buffer:
    """What the link copies out of one Aravis buffer before handing it back to the stream."""

    arrived_ns: int
    complete: bool
    status: str
    block_id: int
    timestamp_ns: int
    width: int
    height: int
    pixel_format: int
    data: bytes


def _load_aravis() -> tuple[Any, Any]:
    """Import PyGObject's ``Aravis`` 0.8 and ``GLib`` namespaces; ImportError names the gap."""
    try:
        gi = importlib.import_module("gi")
    except ImportError as exc:
        raise ImportError(f"PyGObject (the 'gi' module) is not installed: {INSTALL_HINT}") from exc
    try:
        gi.require_version("Aravis", "0.8")
    except ValueError as exc:  # gi's way of saying the typelib is missing
        raise ImportError(f"Aravis 0.8's GObject introspection data is missing: "
                          f"{INSTALL_HINT}") from exc
    # gi.repository's namespaces come from an import hook, not attributes of the package.
    return (importlib.import_module("gi.repository.Aravis"),
            importlib.import_module("gi.repository.GLib"))


class _AravisLink:
    """One opened camera and its stream: the only code that calls Aravis.

    Control calls (GenICam features, commands) are serialised by a lock, because Aravis's
    GenICam tree is not thread-safe; the stream's queue and the raw register read of
    :meth:`probe` are, and are used by the acquisition thread without it.
    """

    def __init__(self, device_id: str, address: str) -> None:
        self.device_id = device_id
        self.address = address
        try:
            self._aravis, glib = _load_aravis()
        except ImportError as exc:
            raise DeviceError(device_id, str(exc)) from exc
        self._gerror: type[Exception] = glib.GError
        device_errors = self._aravis.DeviceError
        self._lost_codes = {int(code) for code in (
            device_errors.NOT_CONNECTED, device_errors.TRANSFER_ERROR, device_errors.TIMEOUT,
            device_errors.NOT_FOUND, device_errors.NOT_CONTROLLER)}
        self._value_codes = {int(code) for code in (
            device_errors.WRONG_FEATURE, device_errors.FEATURE_NOT_FOUND,
            device_errors.INVALID_PARAMETER)}
        self._lock = threading.Lock()
        self._stream: Any = None
        self._signal_id: int | None = None
        with self._translated(f"opening the camera at {address!r}"):
            self._camera: Any = self._aravis.Camera.new(address)
        self._device: Any = self._camera.get_device()
        self.is_gv = bool(self._camera.is_gv_device())

    @contextlib.contextmanager
    def _translated(self, doing: str) -> Iterator[None]:
        try:
            yield
        except self._gerror as exc:
            domain = str(getattr(exc, "domain", ""))
            code = int(getattr(exc, "code", -1))
            message = str(getattr(exc, "message", exc))
            reason = f"{doing}: {message}"
            if domain == "arv-device-error-quark" and code in self._lost_codes:
                raise DeviceDisconnectedError(self.device_id, reason) from exc
            if domain == "arv-gc-error-quark" or (
                    domain == "arv-device-error-quark" and code in self._value_codes):
                raise DeviceValueError(self.device_id, reason) from exc
            raise DeviceError(self.device_id, reason) from exc

    def _call(self, doing: str, call: Callable[[], _T]) -> _T:
        with self._lock, self._translated(doing):
            return call()

    # --- identity ---------------------------------------------------------------------------

    def identity(self) -> dict[str, object]:
        """Vendor, model, serial number and GenICam device id, as the camera reports them."""
        camera = self._camera
        return self._call("reading the camera's identity", lambda: {
            "vendor": camera.get_vendor_name(), "model": camera.get_model_name(),
            "serial_number": camera.get_device_serial_number(),
            "genicam_id": camera.get_device_id()})

    def tick_frequency_hz(self) -> int | None:
        """The camera's timestamp tick rate (GigE Vision), or None when it has none."""
        if not self.is_gv:
            return None
        frequency = self._call("reading the timestamp tick frequency",
                               self._device.get_timestamp_tick_frequency)
        return int(frequency) or None

    # --- settings ---------------------------------------------------------------------------

    def pixel_formats(self) -> list[str]:
        """The pixel formats the camera offers."""
        return [str(name) for name in self._call(
            "listing pixel formats", self._camera.dup_available_pixel_formats_as_strings)]

    def set_pixel_format(self, name: str) -> tuple[str, int]:
        """Set the pixel format; return it as read back, by name and PFNC code."""
        camera = self._camera
        self._call(f"setting PixelFormat {name}",
                   lambda: camera.set_pixel_format_from_string(name))
        return self._call("reading PixelFormat", lambda: (
            str(camera.get_pixel_format_as_string()), int(camera.get_pixel_format())))

    def set_packet_size(self, packet_size: int | None) -> int | None:
        """GigE Vision only: set the GVSP packet size (bytes), or negotiate the largest that
        passes when None; return the size in use."""
        if not self.is_gv:
            return None
        camera = self._camera
        if packet_size is None:
            return int(self._call("negotiating the packet size", camera.gv_auto_packet_size))
        self._call(f"setting the packet size to {packet_size}",
                   lambda: camera.gv_set_packet_size(packet_size))
        return int(self._call("reading the packet size", camera.gv_get_packet_size))

    def sensor_size(self) -> tuple[int, int]:
        """Width and height of the whole sensor, pixels."""
        size = self._call("reading the sensor size", self._camera.get_sensor_size)
        return int(size[0]), int(size[1])

    def set_region(self, x: int, y: int, width: int, height: int) -> tuple[int, int, int, int]:
        """Set the region of interest; return it as read back (x, y, width, height)."""
        camera = self._camera
        self._call(f"setting the region {width}x{height}+{x}+{y}",
                   lambda: camera.set_region(x, y, width, height))
        region = self._call("reading the region", camera.get_region)
        return int(region[0]), int(region[1]), int(region[2]), int(region[3])

    def exposure_bounds_us(self) -> tuple[float, float]:
        """The exposure times the camera takes, microseconds."""
        low, high = self._call("reading the exposure bounds", self._camera.get_exposure_time_bounds)
        return float(low), float(high)

    def set_exposure_us(self, value: float) -> float:
        """Set the exposure time; return the camera's value, microseconds."""
        camera = self._camera
        self._call(f"setting the exposure to {value} us", lambda: camera.set_exposure_time(value))
        return float(self._call("reading the exposure", camera.get_exposure_time))

    def gain_feature(self) -> str:
        """``Gain`` (SFNC, decibels) where the camera has it; else ``GainRaw``, in its own
        units, which is what Aravis then uses."""
        camera = self._camera
        return "Gain" if self._call("looking for Gain",
                                    lambda: camera.is_feature_available("Gain")) else "GainRaw"

    def gain_bounds(self) -> tuple[float, float]:
        """The gains the camera takes (decibels for ``Gain``)."""
        low, high = self._call("reading the gain bounds", self._camera.get_gain_bounds)
        return float(low), float(high)

    def set_gain(self, value: float) -> float:
        """Set the gain; return the camera's value (an integer ``GainRaw`` truncates)."""
        camera = self._camera
        self._call(f"setting the gain to {value}", lambda: camera.set_gain(value))
        return float(self._call("reading the gain", camera.get_gain))

    def trigger_sources(self) -> list[str]:
        """The trigger sources the camera offers."""
        return [str(name) for name in self._call(
            "listing trigger sources", self._camera.dup_available_trigger_sources)]

    def set_trigger(self, source: str) -> str:
        """Trigger every frame from ``source``: every selector's TriggerMode off, then
        FrameStart (or the camera's nearest) on from ``source`` on the rising edge. Returns the
        source read back."""
        camera = self._camera
        self._call(f"setting the trigger source {source}", lambda: camera.set_trigger(source))
        return str(self._call("reading the trigger source", camera.get_trigger_source))

    def software_trigger(self) -> None:
        """Execute TriggerSoftware."""
        self._call("firing the software trigger", self._camera.software_trigger)

    # --- streaming --------------------------------------------------------------------------

    def start(self, n_buffers: int) -> None:
        """Create the stream with ``n_buffers`` buffers of the current payload and start
        acquiring (continuous acquisition: each trigger makes one frame)."""
        camera = self._camera
        aravis = self._aravis

        def start() -> None:
            camera.set_acquisition_mode(aravis.AcquisitionMode.CONTINUOUS)
            self._stream = camera.create_stream(None, None)
            if self._stream is None:
                raise DeviceError(self.device_id, "Aravis could not open the stream")
            payload = camera.get_payload()
            for _ in range(n_buffers):
                self._stream.push_buffer(aravis.Buffer.new_allocate(payload))
            camera.start_acquisition()

        self._call("starting acquisition", start)

    def stop(self) -> None:
        """Stop acquiring."""
        self._call("stopping acquisition", self._camera.stop_acquisition)

    def pop(self, timeout_s: float, now_ns: Callable[[], int]) -> _Buffer | None:
        """Wait up to ``timeout_s`` for the next buffer; copy it out, with the time Aravis
        handed it over on the clock ``now_ns`` (nanoseconds), and hand it back to the stream.
        None when none came."""
        stream = self._stream
        if stream is None:
            return None
        buffer = stream.timeout_pop_buffer(max(1, round(timeout_s * 1e6)))
        if buffer is None:
            return None
        arrived_ns = now_ns()
        try:
            status = buffer.get_status()
            complete = (status == self._aravis.BufferStatus.SUCCESS
                        and buffer.get_payload_type() == self._aravis.BufferPayloadType.IMAGE)
            return _Buffer(arrived_ns=arrived_ns, complete=complete,
                           status=str(status.value_nick),
                           block_id=int(buffer.get_frame_id()),
                           timestamp_ns=int(buffer.get_timestamp()),
                           width=int(buffer.get_image_width()) if complete else 0,
                           height=int(buffer.get_image_height()) if complete else 0,
                           pixel_format=int(buffer.get_image_pixel_format()) if complete else 0,
                           data=bytes(buffer.get_data()) if complete else b"")
        finally:
            stream.push_buffer(buffer)

    def stream_statistics(self) -> dict[str, int]:
        """Aravis's counts since the stream started: completed buffers, failures, underruns."""
        if self._stream is None:
            return {}
        completed, failures, underruns = self._aravis.Stream.get_statistics(self._stream)
        return {"completed": int(completed), "failures": int(failures),
                "underruns": int(underruns)}

    def probe(self) -> bool:
        """GigE Vision only: whether the camera still has a controller, by a raw read of its
        control-privilege register (no GenICam, so no lock). False after it restarted (the
        register cannot tell which host controls it). Raises
        :class:`DeviceDisconnectedError` when the camera does not answer."""
        if not self.is_gv:
            return True
        with self._translated(f"asking whether the camera at {self.address} is still there"):
            value = int(self._device.read_register(_CONTROL_CHANNEL_PRIVILEGE_REGISTER))
        return bool(value & 0b11)

    def on_control_lost(self, callback: Callable[[], None]) -> None:
        """Call ``callback`` (from Aravis's heartbeat thread) when the camera drops us."""
        self._signal_id = int(self._device.connect("control-lost", lambda _device: callback()))

    def forget_control_lost(self) -> None:
        """Stop calling the control-lost callback. Touches no network, so it never waits."""
        with self._lock:
            if self._signal_id is not None:
                self._device.disconnect(self._signal_id)
                self._signal_id = None

    def release(self) -> None:
        """Drop the stream and the camera; Aravis gives up control as they are freed (the
        GObjects go with their last Python reference, so none may be kept elsewhere). The
        stream resets the camera's stream channel and the device leaves control, each a GVCP
        write: with a camera that no longer answers this takes up to 10 s."""
        self.forget_control_lost()
        with self._lock:
            self._stream = None
            self._device = None
            self._camera = None


def image_from_payload(data: bytes, width: int, height: int, bit_depth: int) -> Image:
    """The image in a GenICam Mono payload, as a new writable array.

    Parameters
    ----------
    data : bytes
        The payload: rows of ``width`` pixels, one byte each for 8 bits, else one little-endian
        16-bit word each (Mono10/Mono12 unpacked, the value in the low bits).
    width, height : int
        Image size, pixels.
    bit_depth : int
        8, 10 or 12.

    Returns
    -------
    numpy.ndarray
        ``uint8`` (8 bits) or ``uint16``, shape ``(height, width)``.

    Raises
    ------
    ValueError
        When ``data`` is shorter than the image.
    """
    dtype = np.dtype(np.uint8) if bit_depth == 8 else np.dtype("<u2")
    needed = width * height * dtype.itemsize
    if len(data) < needed:
        raise ValueError(f"payload of {len(data)} bytes is short of a {width}x{height} "
                         f"{bit_depth}-bit image ({needed} bytes)")
    pixels = np.frombuffer(data, dtype=dtype, count=width * height).reshape(height, width)
    if bit_depth == 8:
        return np.array(pixels, dtype=np.uint8)
    return np.array(pixels, dtype=np.uint16)


@register_driver("camera", "GenicamCamera")
class GenicamCamera(StreamingCamera[_AravisLink]):
    """A GenICam camera (GigE Vision or USB3 Vision) through Aravis, hardware-triggered.

    Parameters
    ----------
    device_id : str
        The camera's id in the rig.
    context : DriverContext
        Its clock is the rig clock the frames' times are put on.
    address : str
        The camera's IP address, or its Aravis device id as ``arv-tool-0.8`` lists it:
        ``<vendor>-<model>-<serial>`` (``Aravis-Fake-GV01``) or ``<vendor>-<serial>``
        (``Basler-21234567``); an id is found by discovery, an address is asked directly.
    pixel_format : {"Mono8", "Mono10", "Mono12"}
        8 bits per pixel, or 10/12 unpacked in 16-bit words.
    trigger_source : str
        The camera's TriggerSource for each frame: ``Line1`` (the trigger controller's cable),
        or ``Software`` to expose on :meth:`software_trigger` (tests, bench without a trigger).
    offset_x, offset_y, width, height
        The region of interest: as for
        :class:`~eyeserver.hardware.drivers.camerathread.StreamingCamera`. Tracking narrows it
        to the eye to raise the frame rate.
    packet_size : int or None
        GigE Vision packet size, bytes (at most the link's MTU); None negotiates the largest
        that passes.
    queue_size : int
        Frames held for :meth:`read_frame`: as for
        :class:`~eyeserver.hardware.drivers.camerathread.StreamingCamera`.
    liveness_s : float
        After this long without a buffer, the acquisition thread asks a GigE Vision camera
        whether it is still there (see the module's notes), seconds.

    Notes
    -----
    A frame's ``exposure_us`` and ``gain_db`` are the camera's settings when it arrived, and
    its ``trigger_index`` is the camera's own count of exposures since ``open()``, the dropped
    ones included (the camera cannot know the trigger controller's pulse numbers). Its
    ``extra`` holds ``device_timestamp_ns`` (camera clock), ``block_id`` (GVSP frame id) and
    ``received_ns`` (rig clock when Aravis handed the buffer over: the driver's own latency is
    from there to the reader, the speed bench's frame path). One reader at a time.
    """

    def __init__(self, device_id: str, *, context: DriverContext, address: str,
                 pixel_format: str = "Mono8", trigger_source: str = "Line1",
                 offset_x: int = 0, offset_y: int = 0, width: int | None = None,
                 height: int | None = None, packet_size: int | None = None,
                 queue_size: int = 8, liveness_s: float = 1.0) -> None:
        if not address:
            raise ValueError("address must name the camera (IP address or GenICam device id)")
        if packet_size is not None and not 576 <= packet_size <= 16_384:
            raise ValueError(f"packet_size must be in [576, 16384] bytes, not {packet_size}")
        if liveness_s <= 0:
            raise ValueError(f"liveness_s must be positive, not {liveness_s}")
        super().__init__(device_id, clock=context.clock, pixel_format=pixel_format,
                         trigger_source=trigger_source, offset_x=offset_x, offset_y=offset_y,
                         width=width, height=height, queue_size=queue_size)
        self.address = address
        self._packet_size_option = packet_size
        self._liveness_s = float(liveness_s)
        self._releasing: list[threading.Thread] = []
        self._pixel_format_code = 0
        self._quiet_since = 0.0
        """When the acquisition thread last had a buffer or asked the camera (monotonic s)."""

    def wait_released(self, timeout_s: float = 15.0) -> bool:
        """Wait until the connections to a lost camera that :meth:`close` (or a failed
        :meth:`open`) left to tear down in the background are gone; True when they are.

        A camera that no longer answers makes each of Aravis's goodbyes (stream channel reset,
        control release) wait out its GVCP timeout, up to 10 s in all; ``close()`` does not
        wait for them, and a new ``open()`` need not either: the camera refuses writes from
        the old connection once the new one controls it. The process waits for them at exit.
        """
        deadline = time.monotonic() + timeout_s
        for releasing in self._releasing:
            releasing.join(max(0.0, deadline - time.monotonic()))
        self._releasing = [t for t in self._releasing if t.is_alive()]
        return not self._releasing

    def describe(self) -> dict[str, object]:
        info = {**super().describe(), "address": self.address}
        link = self._link
        if self.is_open and link is not None:
            info["stream"] = link.stream_statistics()
        return info

    # --- StreamingCamera hooks --------------------------------------------------------------

    def _connect(self) -> _AravisLink:
        return _AravisLink(self.id, self.address)

    def _configure(self, link: _AravisLink) -> None:
        identity = link.identity()
        # A previous controller (or a crashed daemon) may have left it streaming.
        with contextlib.suppress(DeviceError):
            link.stop()
        offered = link.pixel_formats()
        if self.pixel_format not in offered:
            raise DeviceValueError(self.id, f"the camera offers no {self.pixel_format} "
                                            f"(it has {', '.join(offered) or 'none'})")
        name, self._pixel_format_code = link.set_pixel_format(self.pixel_format)
        if name != self.pixel_format:
            raise DeviceValueError(self.id, f"PixelFormat reads {name} after setting "
                                            f"{self.pixel_format}")
        packet_size = link.set_packet_size(self._packet_size_option)

        x, y, width, height = self._roi
        if width is None or height is None:
            sensor_width, sensor_height = link.sensor_size()
            width = width or sensor_width - x
            height = height or sensor_height - y
        region = link.set_region(x, y, width, height)
        check_region_read_back(self.id, (x, y, width, height), region)

        sources = link.trigger_sources()
        if self.trigger_source not in sources:
            raise DeviceValueError(self.id, f"the camera has no trigger source "
                                            f"{self.trigger_source!r} (it has "
                                            f"{', '.join(sources) or 'none'})")
        source = link.set_trigger(self.trigger_source)
        check_trigger_read_back(self.id, self.trigger_source, source)
        self._restore_exposure_and_gain(link, link.exposure_bounds_us(), link.gain_bounds())

        self.width, self.height = region[2], region[3]
        self.bit_depth = MONO_PIXEL_FORMATS[self.pixel_format]
        self._info = {**identity, "offset_x": region[0], "offset_y": region[1],
                      "packet_size": packet_size, "gain_feature": link.gain_feature(),
                      "tick_frequency_hz": link.tick_frequency_hz(),
                      "transport": "GigE Vision" if link.is_gv else "other"}

    def _set_exposure(self, link: _AravisLink, value_us: float) -> float:
        return link.set_exposure_us(value_us)

    def _set_gain(self, link: _AravisLink, value_db: float) -> float:
        return link.set_gain(value_db)

    def _watch(self, link: _AravisLink, frames: FrameQueue) -> None:
        self._quiet_since = time.monotonic()
        link.on_control_lost(lambda: frames.mark_lost(
            f"Aravis lost control of the camera at {self.address} (no heartbeat answer)"))

    def _release(self, link: _AravisLink, *, lost: bool) -> None:
        if not lost:
            link.release()
            return
        # A camera known to be gone is not waited for: its teardown's GVCP writes each wait
        # out their timeout, so it runs on a thread of its own (see wait_released()).
        releasing = threading.Thread(target=link.release,
                                     name=f"{type(self).__name__}-{self.id}-release")
        releasing.start()
        self._releasing.append(releasing)

    # --- the acquisition thread -------------------------------------------------------------

    def _step(self, link: _AravisLink, frames: FrameQueue) -> None:
        """Pop one buffer (or none) and account for it; after ``liveness_s`` without one, ask
        the camera whether it is still there."""
        buffer = link.pop(_POLL_S, self._clock.now_ns)
        if buffer is not None:
            self._quiet_since = time.monotonic()
            self._deliver(frames, buffer.block_id, self._image(buffer), whole=buffer.complete,
                          arrived_ns=buffer.arrived_ns, device_timestamp_ns=buffer.timestamp_ns,
                          extra={"block_id": buffer.block_id, "received_ns": buffer.arrived_ns})
        elif time.monotonic() - self._quiet_since >= self._liveness_s:
            if not link.probe():
                frames.mark_lost(f"the camera at {self.address} answers but has no controller "
                                 "(it restarted)")
            self._quiet_since = time.monotonic()

    def _image(self, buffer: _Buffer) -> Image | None:
        """The buffer's image, or None (logged) for a buffer that is not a whole frame of the
        configured format and size."""
        if not buffer.complete:
            _log.warning("camera %s: incomplete frame dropped (%s)", self.id, buffer.status)
            return None
        if (buffer.width, buffer.height, buffer.pixel_format) != (
                self.width, self.height, self._pixel_format_code):
            _log.warning("camera %s: frame id %d is %dx%d format 0x%08x, not the %dx%d %s "
                         "configured", self.id, buffer.block_id, buffer.width, buffer.height,
                         buffer.pixel_format, self.width, self.height, self.pixel_format)
            return None
        try:
            return image_from_payload(buffer.data, buffer.width, buffer.height, self.bit_depth)
        except ValueError as exc:
            _log.warning("camera %s: frame id %d: %s", self.id, buffer.block_id, exc)
            return None


# --- discovery (``eyeserver devices discover``) -----------------------------------------------

_PROTOCOL_NAMES: Final[dict[str, str]] = {"GigEVision": "GigE Vision", "USB3Vision": "USB3 Vision"}
"""Aravis's interface names as the standards spell them."""


@dataclass(frozen=True)
class FoundCamera:
    """A camera as Aravis lists it, for the one writing a room file.

    ``device_id`` is Aravis's id (``<vendor>-<model>-<serial>``), which names the camera to the
    driver whatever its IP address; ``address`` is its IP address (GigE Vision) or bus address
    (USB3 Vision); ``physical_id`` its MAC address (GigE Vision) or USB serial; ``protocol``
    ``GigE Vision`` or ``USB3 Vision``. A field the camera did not give is None.
    """

    device_id: str | None
    vendor: str | None
    model: str | None
    serial: str | None
    address: str | None
    physical_id: str | None
    protocol: str | None


def _text(value: object) -> str | None:
    return str(value) if value else None


def list_cameras() -> list[FoundCamera]:
    """Every GenICam camera Aravis finds from this machine, in Aravis's order.

    Aravis broadcasts a GigE Vision discovery on every network interface and waits for answers
    (about a second), and lists the USB3 Vision cameras on the bus. Nothing is opened: a camera
    another host (or the daemon) controls is listed too.

    Raises
    ------
    ImportError
        PyGObject or Aravis's introspection data is missing; the message says what to install.
    """
    aravis, _ = _load_aravis()
    aravis.update_device_list()
    return [FoundCamera(
        device_id=_text(aravis.get_device_id(n)), vendor=_text(aravis.get_device_vendor(n)),
        model=_text(aravis.get_device_model(n)), serial=_text(aravis.get_device_serial_nbr(n)),
        address=_text(aravis.get_device_address(n)),
        physical_id=_text(aravis.get_device_physical_id(n)),
        protocol=_PROTOCOL_NAMES.get(str(aravis.get_device_protocol(n)),
                                     _text(aravis.get_device_protocol(n))))
        for n in range(int(aravis.get_n_devices()))]


def identify_camera(address: str) -> FoundCamera:
    """The camera at ``address`` (an IP address, or an Aravis device id), asked directly rather
    than found by a broadcast -- for a camera the broadcast does not reach (another subnet
    behind a router, and loopback on some hosts).

    The camera is opened, as the driver opens it, only to read its identity, then released.
    Its Aravis device id and MAC address come only with a broadcast's answer, so they are None.

    Raises
    ------
    DeviceError
        Aravis is missing (the message says what to install), or no camera answers there
        (:class:`DeviceDisconnectedError`, after Aravis's 2.5 s of GVCP tries).
    """
    link = _AravisLink(f"camera at {address}", address)
    try:
        identity = link.identity()
        is_gv = link.is_gv
    finally:
        link.release()
    return FoundCamera(device_id=None, vendor=_text(identity["vendor"]),
                       model=_text(identity["model"]), serial=_text(identity["serial_number"]),
                       address=address, physical_id=None,
                       protocol="GigE Vision" if is_gv else None)
