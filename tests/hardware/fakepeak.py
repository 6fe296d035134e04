"""A fake of exactly the IDS peak calls :mod:`eyeserver.hardware.drivers.ids` makes (IDS peak is
not on PyPI for this platform, so it cannot be installed here).

The modules ``ids_peak``, ``ids_peak.ids_peak`` and ``ids_peak.ids_peak_ipl_extension``
(:attr:`FakePeak.modules`, put into ``sys.modules`` per test) implement the calls the driver's
docstring lists and nothing else (a call outside them fails with AttributeError). The fake is
strict where IDS peak is; tests/test_driver_ids.py says how, and tests/hardware/ runs the camera
contract over it.
"""

# The fake spells IDS peak's method and exception names.
# ruff: noqa: N802, N818

from __future__ import annotations

import threading
import time
import types
import weakref
from collections.abc import Callable
from typing import Any

import numpy as np


class PeakException(Exception):
    """``ids_peak.Exception``: the base of IDS peak's errors."""


class TimeoutException(PeakException):
    pass


class AbortedException(PeakException):
    pass


class IOException(PeakException):
    pass


class OutOfRangeException(PeakException):
    pass


class InvalidArgumentException(PeakException):
    pass


class NotFoundException(PeakException):
    pass


class NotAvailableException(PeakException):
    pass


class BadAccessException(PeakException):
    pass


class NotInitializedException(PeakException):
    pass


READ_WRITE, READ_ONLY, NOT_AVAILABLE, NOT_IMPLEMENTED = (
    "ReadWrite", "ReadOnly", "NotAvailable", "NotImplemented")
CONTROL = "Control"

SENSOR = (1280, 1024)
"""The UI-5240's sensor, pixels (width, height)."""

DEVICE_EPOCH_NS = 7_000_000_000_000
"""The fake camera's clock runs this far ahead of the host's monotonic clock."""


class Node:
    """A node of the camera's node map; every call first asks whether the camera is there."""

    def __init__(self, camera: FakeCamera, name: str) -> None:
        self.camera = camera
        self.name = name

    def _check(self, writing: bool = False) -> None:
        self.camera.check_reachable()
        if writing and self.name in FakeCamera.LOCKED_BY_TL and self.camera.tl_locked:
            raise BadAccessException(f"{self.name} is locked while TLParamsLocked is 1")


class ValueNode(Node):
    """An integer or float node; integers and whole-µs floats are rounded as the camera
    does."""

    def __init__(self, camera: FakeCamera, name: str, get: Callable[[], float],
                 put: Callable[[float], None] | None, minimum: Callable[[], float],
                 maximum: Callable[[], float], integer: bool = False) -> None:
        super().__init__(camera, name)
        self._get, self._put = get, put
        self._minimum, self._maximum = minimum, maximum
        self._integer = integer

    def Value(self) -> float:
        self._check()
        return self._get()

    def Minimum(self) -> float:
        self._check()
        return self._minimum()

    def Maximum(self) -> float:
        self._check()
        return self._maximum()

    def SetValue(self, value: float) -> None:
        self._check(writing=True)
        if self._put is None:
            raise BadAccessException(f"{self.name} is read-only")
        if self._integer and value != int(value):
            raise InvalidArgumentException(f"{self.name} takes integers, not {value!r}")
        if not self._minimum() <= value <= self._maximum():
            raise OutOfRangeException(f"{self.name}={value} outside [{self._minimum()}, "
                                      f"{self._maximum()}]")
        self._put(value)


class Entry:
    def __init__(self, symbolic: str, status: str) -> None:
        self._symbolic, self._status = symbolic, status

    def SymbolicValue(self) -> str:
        return self._symbolic

    def AccessStatus(self) -> str:
        return self._status


class EnumerationNode(Node):
    def __init__(self, camera: FakeCamera, name: str, entries: dict[str, str],
                 get: Callable[[], str], put: Callable[[str], None]) -> None:
        super().__init__(camera, name)
        self._entries, self._get, self._put = entries, get, put

    def Entries(self) -> list[Entry]:
        self._check()
        return [Entry(name, status) for name, status in self._entries.items()]

    def CurrentEntry(self) -> Entry:
        self._check()
        return Entry(self._get(), READ_WRITE)

    def SetCurrentEntry(self, symbolic: str) -> None:
        self._check(writing=True)
        if symbolic not in self._entries:
            raise NotFoundException(f"{self.name} has no entry {symbolic!r}")
        if self._entries[symbolic] != READ_WRITE:
            raise NotAvailableException(f"{self.name}'s {symbolic} is not available")
        self._put(symbolic)


class CommandNode(Node):
    def __init__(self, camera: FakeCamera, name: str, run: Callable[[], None]) -> None:
        super().__init__(camera, name)
        self._run = run
        self._executed = False

    def Execute(self) -> None:
        self._check()
        self._run()
        self._executed = True

    def WaitUntilDone(self) -> None:
        self._check()
        assert self._executed, f"WaitUntilDone() on {self.name} before Execute()"


class NodeMap:
    def __init__(self, nodes: dict[str, Node]) -> None:
        self._nodes = nodes

    def HasNode(self, name: str) -> bool:
        return name in self._nodes

    def FindNode(self, name: str) -> Node:
        if name not in self._nodes:
            raise NotFoundException(f"no node {name}")
        return self._nodes[name]


class Buffer:
    """A transport-layer buffer: readable only while delivered (between WaitForFinishedBuffer
    and QueueBuffer)."""

    def __init__(self, size: int) -> None:
        self.memory = np.zeros(size, dtype=np.uint8)
        self.state = "announced"
        self.incomplete = False
        self.frame_id = 0
        self.timestamp_ns = 0
        self.shape = (0, 0)
        self.bit_depth = 8

    def _check(self) -> None:
        if self.state != "delivered":
            raise BadAccessException(f"a {self.state} buffer cannot be read")

    def IsIncomplete(self) -> bool:
        self._check()
        return self.incomplete

    def FrameID(self) -> int:
        self._check()
        return self.frame_id

    def Timestamp_ns(self) -> int:
        self._check()
        return self.timestamp_ns


class DataStream:
    MIN_BUFFERS = 3

    def __init__(self, camera: FakeCamera) -> None:
        self.camera = camera
        self.announced: list[Buffer] = []
        self.queued: list[Buffer] = []
        self.finished: list[Buffer] = []
        self.grabbing = False
        self.refuse_buffers = False
        self.cond = threading.Condition()

    def NumBuffersAnnouncedMinRequired(self) -> int:
        return self.MIN_BUFFERS

    def AllocAndAnnounceBuffer(self, size: int) -> Buffer:
        self.camera.check_reachable()
        buffer = Buffer(int(size))
        self.announced.append(buffer)
        return buffer

    def QueueBuffer(self, buffer: Buffer) -> None:
        self.camera.check_reachable()
        if self.refuse_buffers:
            raise BadAccessException("GenTL error -1005: the buffer cannot be queued")
        with self.cond:
            if buffer not in self.announced or buffer.state == "queued":
                raise InvalidArgumentException("the buffer is not announced, or queued already")
            buffer.state = "queued"
            self.queued.append(buffer)

    def StartAcquisition(self) -> None:
        self.camera.check_reachable()
        if len(self.announced) < self.MIN_BUFFERS:
            raise BadAccessException("too few buffers announced")
        self.grabbing = True

    def WaitForFinishedBuffer(self, timeout_ms: int) -> Buffer:
        deadline = time.monotonic() + timeout_ms / 1e3
        with self.cond:
            while True:
                if self.camera.lost and self.camera.raise_in_wait:
                    raise IOException("GenTL error -1010: the device has been lost")
                if self.finished:
                    buffer = self.finished.pop(0)
                    buffer.state = "delivered"
                    return buffer
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise TimeoutException(f"no buffer within {timeout_ms} ms")
                self.cond.wait(remaining)

    def StopAcquisition(self, mode: str) -> None:
        assert mode == "Default"
        self.grabbing = False

    def Flush(self, mode: str) -> None:
        assert mode == "DiscardAll"
        with self.cond:
            for buffer in self.queued + self.finished:
                buffer.state = "announced"
            self.queued.clear()
            self.finished.clear()

    def AnnouncedBuffers(self) -> list[Buffer]:
        return list(self.announced)

    def RevokeBuffer(self, buffer: Buffer) -> None:
        if buffer.state == "queued":
            raise BadAccessException("a queued buffer cannot be revoked")
        self.announced.remove(buffer)

    def deliver(self, frame_id: int, timestamp_ns: int, image: np.ndarray, bit_depth: int,
                incomplete: bool) -> bool:
        """Fill the first queued buffer with a frame; False when none is free (lost whole)."""
        with self.cond:
            if not self.grabbing or not self.queued:
                return False
            buffer = self.queued.pop(0)
            raw = image.astype("<u2").tobytes() if bit_depth > 8 else image.tobytes()
            if len(raw) > buffer.memory.size:
                incomplete = True
            else:
                buffer.memory[:len(raw)] = np.frombuffer(raw, dtype=np.uint8)
            buffer.state = "finished"
            buffer.incomplete = incomplete
            buffer.frame_id, buffer.timestamp_ns = frame_id, timestamp_ns
            buffer.shape, buffer.bit_depth = image.shape, bit_depth
            self.finished.append(buffer)
            self.cond.notify_all()
            return True


class Image:
    """``ids_peak_ipl.Image`` from ``BufferToImage``: a view of the buffer's memory."""

    def __init__(self, buffer: Buffer) -> None:
        buffer._check()
        if buffer.incomplete:
            raise InvalidArgumentException("an incomplete buffer has no image")
        self._buffer = buffer

    def Width(self) -> int:
        return self._buffer.shape[1]

    def Height(self) -> int:
        return self._buffer.shape[0]

    def _view(self, dtype: str) -> np.ndarray:
        height, width = self._buffer.shape
        count = width * height
        return np.frombuffer(self._buffer.memory, dtype=dtype, count=count).reshape(height,
                                                                                    width)

    def get_numpy_2D(self) -> np.ndarray:
        if self._buffer.bit_depth != 8:
            raise InvalidArgumentException("get_numpy_2D() of a 16-bit image")
        return self._view("u1")

    def get_numpy_2D_16(self) -> np.ndarray:
        if self._buffer.bit_depth == 8:
            raise InvalidArgumentException("get_numpy_2D_16() of an 8-bit image")
        return self._view("<u2")


class Device:
    """An opened device; IDS peak closes it when the last reference goes."""

    def __init__(self, camera: FakeCamera) -> None:
        self._camera = camera
        self._stream: DataStream | None = None
        weakref.finalize(self, camera.device_closed)

    def RemoteDevice(self) -> Any:
        node_map = self._camera.node_map
        return types.SimpleNamespace(NodeMaps=lambda: [node_map])

    def DataStreams(self) -> list[Any]:
        def open_stream() -> DataStream:
            self._camera.check_reachable()
            self._camera.stream = DataStream(self._camera)
            return self._camera.stream
        return [types.SimpleNamespace(OpenDataStream=open_stream)]


class Descriptor:
    def __init__(self, camera: FakeCamera) -> None:
        self._camera = camera

    def SerialNumber(self) -> str:
        return self._camera.serial

    def UserDefinedName(self) -> str:
        return self._camera.user_name

    def ModelName(self) -> str:
        return self._camera.model

    def Key(self) -> str:
        return self._camera.key

    def IsOpenable(self, access: str) -> bool:
        assert access == CONTROL
        return self._camera.plugged and not self._camera.is_open

    def OpenDevice(self, access: str) -> Device:
        assert access == CONTROL
        if self._camera.lost:
            raise IOException("GenTL error -1010: the device has been lost")
        if self._camera.is_open:
            raise BadAccessException(f"{self._camera.serial} is open already")
        self._camera.is_open = True
        self._camera.opened += 1
        return Device(self._camera)


class FakeCamera:
    """An IDS UI-5240 as IDS peak presents it."""

    LOCKED_BY_TL = frozenset({"Width", "Height", "OffsetX", "OffsetY", "PixelFormat"})

    def __init__(self, serial: str, *, user_name: str = "") -> None:
        self.serial, self.user_name = serial, user_name
        self.model = "UI-5240CP-M-GL"
        self.key = f"uEye-TL:{serial}"
        self.plugged, self.lost, self.raise_in_wait = True, False, True
        self.is_open, self.opened = False, 0
        self.tl_locked = False
        self.acquiring = False
        self.stream: DataStream | None = None
        self.pixel_format = "Mono8"
        self.offset_x = self.offset_y = 0
        self.width, self.height = SENSOR
        self.exposure_us = 10_000.0
        self.gain_selector = "AnalogAll"
        self.gains = {"AnalogAll": 1.0, "DigitalAll": 1.0}
        self.trigger_selector = "ExposureStart"
        self.triggers = {"ExposureStart": {"mode": "Off", "source": "Line0"},
                         "ExposureEnd": {"mode": "On", "source": "Line0"}}
        self.trigger_activation = "RisingEdge"
        self.acquisition_mode = "SingleFrame"
        self.frame_id = -1
        self.lose_next_whole = False
        self.next_incomplete = False
        self.width_step = 1
        self.node_map = NodeMap(self._nodes())

    # --- the node map ---

    def _nodes(self) -> dict[str, Node]:
        def value(name: str, attribute: str, minimum: Callable[[], float],
                  maximum: Callable[[], float], integer: bool = True,
                  step_of: Callable[[], int] = lambda: 1) -> ValueNode:
            def put(v: float) -> None:
                step = step_of()
                setattr(self, attribute, round(v / step) * step)
            return ValueNode(self, name, lambda: getattr(self, attribute), put, minimum,
                             maximum, integer)

        def enum(name: str, entries: dict[str, str], get: Callable[[], str],
                 put: Callable[[str], None]) -> EnumerationNode:
            return EnumerationNode(self, name, entries, get, put)

        def trigger(key: str) -> tuple[Callable[[], str], Callable[[str], None]]:
            return (lambda: self.triggers[self.trigger_selector][key],
                    lambda v: self.triggers[self.trigger_selector].__setitem__(key, v))

        nodes: list[Node] = [
            value("Width", "width", lambda: 16, lambda: SENSOR[0] - self.offset_x,
                  step_of=lambda: self.width_step),
            value("Height", "height", lambda: 4, lambda: SENSOR[1] - self.offset_y),
            value("OffsetX", "offset_x", lambda: 0, lambda: SENSOR[0] - self.width),
            value("OffsetY", "offset_y", lambda: 0, lambda: SENSOR[1] - self.height),
            ValueNode(self, "PayloadSize", lambda: self.width * self.height * (
                1 if self.pixel_format == "Mono8" else 2), None, lambda: 0, lambda: 2**32,
                True),
            value("ExposureTime", "exposure_us", lambda: 28.0, lambda: 2_000_000.0,
                  integer=False),
            ValueNode(self, "Gain", lambda: self.gains[self.gain_selector],
                      lambda v: self.gains.__setitem__(self.gain_selector, v), lambda: 1.0,
                      lambda: 4.0),
            ValueNode(self, "TLParamsLocked", lambda: int(self.tl_locked),
                      lambda v: setattr(self, "tl_locked", bool(v)), lambda: 0, lambda: 1, True),
            ValueNode(self, "AcquisitionFrameRate", lambda: 25.0, None, lambda: 1.0,
                      lambda: 50.0),
            enum("PixelFormat", {"Mono8": READ_WRITE, "Mono10": READ_WRITE,
                                 "Mono12": NOT_AVAILABLE},
                 lambda: self.pixel_format, lambda v: setattr(self, "pixel_format", v)),
            enum("GainSelector", {"AnalogAll": READ_WRITE, "DigitalAll": READ_WRITE},
                 lambda: self.gain_selector, lambda v: setattr(self, "gain_selector", v)),
            enum("TriggerSelector", {"ExposureStart": READ_WRITE, "ExposureEnd": READ_WRITE,
                                     "FrameStart": NOT_IMPLEMENTED},
                 lambda: self.trigger_selector, lambda v: setattr(self, "trigger_selector", v)),
            enum("TriggerMode", {"Off": READ_WRITE, "On": READ_WRITE}, *trigger("mode")),
            enum("TriggerSource", {"Software": READ_WRITE, "Line0": READ_WRITE,
                                   "Line2": READ_WRITE, "Line3": NOT_AVAILABLE},
                 *trigger("source")),
            enum("TriggerActivation", {"RisingEdge": READ_WRITE, "FallingEdge": READ_WRITE},
                 lambda: self.trigger_activation,
                 lambda v: setattr(self, "trigger_activation", v)),
            enum("AcquisitionMode", {"Continuous": READ_WRITE, "SingleFrame": READ_WRITE},
                 lambda: self.acquisition_mode, lambda v: setattr(self, "acquisition_mode", v)),
            CommandNode(self, "AcquisitionStart", lambda: setattr(self, "acquiring", True)),
            CommandNode(self, "AcquisitionStop", lambda: setattr(self, "acquiring", False)),
            CommandNode(self, "TriggerSoftware", lambda: self.fire("Software")),
        ]
        return {node.name: node for node in nodes}

    # --- the camera ---

    def check_reachable(self) -> None:
        if self.lost:
            raise IOException("GenTL error -1010: the device has been lost")
        if not self.is_open:
            raise BadAccessException("the device is not open")

    def device_closed(self) -> None:
        self.is_open = False

    def image(self, frame_id: int) -> np.ndarray:
        """The frame's picture: the diagonal gradient, moving with the frame id."""
        y, x = np.mgrid[0:self.height, 0:self.width]
        gradient = (x + self.offset_x + y + self.offset_y + frame_id) % 256
        if self.pixel_format == "Mono8":
            return gradient.astype(np.uint8)
        return (gradient * 4).astype(np.uint16)

    def fire(self, source: str) -> None:
        """A trigger from ``source``: expose one frame if the trigger is set up for it."""
        trigger = self.triggers["ExposureStart"]
        if not (self.acquiring and trigger["mode"] == "On" and trigger["source"] == source):
            return
        assert self.acquisition_mode == "Continuous"
        self.frame_id += 1
        stamp = time.monotonic_ns() + DEVICE_EPOCH_NS
        if self.lose_next_whole:
            self.lose_next_whole = False
            return
        incomplete, self.next_incomplete = self.next_incomplete, False
        assert self.stream is not None
        self.stream.deliver(self.frame_id, stamp, self.image(self.frame_id),
                            8 if self.pixel_format == "Mono8" else 10, incomplete)


class FakePeak:
    """One IDS peak installation with its cameras: the modules to put into ``sys.modules``."""

    def __init__(self, cameras: list[FakeCamera]) -> None:
        self.cameras = cameras
        self.initialized = False
        self.initializations = 0
        self.lost_callbacks: dict[int, Any] = {}
        self._next_handle = 1
        self._manager: Any = None
        peak = types.ModuleType("ids_peak.ids_peak")
        for cls in (TimeoutException, AbortedException, IOException, OutOfRangeException,
                    InvalidArgumentException, NotFoundException, NotAvailableException,
                    BadAccessException, NotInitializedException):
            setattr(peak, cls.__name__, cls)
        peak.Exception = PeakException
        peak.NodeAccessStatus_NotAvailable = NOT_AVAILABLE
        peak.NodeAccessStatus_NotImplemented = NOT_IMPLEMENTED
        peak.DeviceAccessType_Control = CONTROL
        peak.AcquisitionStopMode_Default = "Default"
        peak.DataStreamFlushMode_DiscardAll = "DiscardAll"
        peak.Library = types.SimpleNamespace(
            Initialize=self._initialize, Close=self._close)
        peak.DeviceManager = types.SimpleNamespace(
            Instance=self._instance)
        extension = types.ModuleType("ids_peak.ids_peak_ipl_extension")
        extension.BufferToImage = Image
        package = types.ModuleType("ids_peak")
        package.__path__ = []  # a package, as the real one is
        package.ids_peak = peak
        package.ids_peak_ipl_extension = extension
        self.modules = {"ids_peak": package, "ids_peak.ids_peak": peak,
                        "ids_peak.ids_peak_ipl_extension": extension}

    def _initialize(self) -> None:
        assert not self.initialized, "Library.Initialize() twice without Close()"
        self.initialized = True
        self.initializations += 1

    def _close(self) -> None:
        if not self.initialized:
            raise NotInitializedException("Library.Close() without Initialize()")
        self.initialized = False

    def _instance(self) -> Any:
        if not self.initialized:
            raise NotInitializedException("call Library.Initialize() first")
        if self._manager is None:
            descriptors: list[Descriptor] = []

            def update() -> None:
                descriptors[:] = [Descriptor(c) for c in self.cameras if c.plugged]

            def register(callback: Any) -> int:
                handle, self._next_handle = self._next_handle, self._next_handle + 1
                self.lost_callbacks[handle] = callback
                return handle

            self._manager = types.SimpleNamespace(
                Update=update, Devices=lambda: list(descriptors),
                DeviceLostCallback=lambda f: types.SimpleNamespace(call=f),
                RegisterDeviceLostCallback=register,
                UnregisterDeviceLostCallback=self.lost_callbacks.pop)
        return self._manager

    def unplug(self, camera: FakeCamera, *, notify: bool = True,
               raise_in_wait: bool = True) -> None:
        """The camera goes away: IDS peak calls the lost callbacks (from its own thread) if
        ``notify``, and a waiting ``WaitForFinishedBuffer`` raises if ``raise_in_wait``."""
        camera.plugged, camera.lost, camera.raise_in_wait = False, True, raise_in_wait
        if camera.stream is not None:
            with camera.stream.cond:
                camera.stream.cond.notify_all()
        if notify:
            for callback in list(self.lost_callbacks.values()):
                thread = threading.Thread(target=callback.call, args=(camera.key,))
                thread.start()
                thread.join()

    def replug(self, camera: FakeCamera) -> None:
        """The camera is back, power-cycled: its settings at their defaults."""
        fresh = FakeCamera(camera.serial, user_name=camera.user_name)
        fresh.opened = camera.opened
        self.cameras[self.cameras.index(camera)] = fresh
