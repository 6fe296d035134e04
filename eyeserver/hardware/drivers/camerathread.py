"""What the streaming camera drivers share between their SDK's stream and ``read_frame()``.

Every real camera driver (GenICam through Aravis, Basler through pylon, IDS through IDS peak) has
one acquisition thread that takes buffers from its SDK and a reader waiting in
:meth:`~eyeserver.hardware.base.Camera.read_frame`. Only the SDK calls differ; this module holds
the rest, once:

:class:`StreamingCamera`
    The :class:`~eyeserver.hardware.base.Camera` those drivers derive from: their options common
    to all (pixel format, trigger source, region of interest, queue size), ``open()`` and
    ``close()`` around the driver's link to its SDK (:class:`CameraLink`), settings read back
    from the camera, the software trigger, ``read_frame()``, ``describe()``, and the accounting
    of each buffer the acquisition thread takes. A driver supplies the SDK's side through a
    handful of hooks.
:class:`FrameQueue`
    One open session of a camera: the bounded queue of frames between the thread and the reader,
    the frame and dropped-frame counts that go into every :class:`~eyeserver.core.frames.FrameMeta`,
    the mapping of device timestamps onto the rig clock (:class:`ClockMapping`), and whether the
    camera is known to be gone. :class:`StreamingCamera` makes a new one at each ``open()``, so
    news about an earlier session (a late SDK callback) lands in that session's queue and
    changes nothing.
:class:`FrameIdGaps`
    Frames lost whole, told by gaps in the transport's frame ids between whole frames.
:class:`AcquisitionThread`
    The loop: call the driver's step until ``close()`` or the camera is gone; a
    :class:`~eyeserver.errors.DeviceDisconnectedError` (or any other failure, logged) marks the
    session lost, which wakes the reader.

:class:`NodeMapLink`
    What the links to SDKs that expose the camera's node map (pylon, IDS peak) build on their
    feature reads and writes: enumerations checked against their entries, the region of
    interest.

and the small checks behind :class:`StreamingCamera` and the drivers' ``open()``
(:data:`MONO_PIXEL_FORMATS`, :func:`check_region`, :func:`check_region_read_back`,
:func:`check_trigger_read_back`, :func:`narrow_range`, :func:`clamp`).

How a camera's timestamps go onto the rig clock: docs/notes/camera-drivers.md.
"""

from __future__ import annotations

import abc
import collections
import logging
import math
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any, Final, Generic, Protocol, TypeVar

from eyeserver.core.clock import Clock
from eyeserver.core.frames import Frame, FrameMeta
from eyeserver.core.types import Image
from eyeserver.errors import (
    DeviceDisconnectedError,
    DeviceError,
    DeviceTimeoutError,
    DeviceValueError,
)
from eyeserver.hardware.base import Camera

__all__ = [
    "MONO_PIXEL_FORMATS",
    "AcquisitionThread",
    "CameraLink",
    "ClockMapping",
    "FrameIdGaps",
    "FrameQueue",
    "NodeMapLink",
    "StreamingCamera",
    "check_region",
    "check_region_read_back",
    "check_trigger_read_back",
    "clamp",
    "narrow_range",
    "skipped_frame_ids",
]

_log = logging.getLogger(__name__)

_T = TypeVar("_T")

MONO_PIXEL_FORMATS: Final[dict[str, int]] = {"Mono8": 8, "Mono10": 10, "Mono12": 12}
"""The pixel formats the camera drivers take and their significant bits. Mono10 and Mono12 are
the unpacked ones: one 16-bit word per pixel, the value in its low bits."""

_GVSP_MAX_FRAME_ID: Final[int] = 0xFFFF
"""GigE Vision 1.x frame (block) ids are 16 bits and skip 0 when they wrap."""


class ClockMapping:
    """Device timestamps onto the rig clock with one offset per session (the module's notes).

    Not thread-safe on its own: :class:`FrameQueue` calls it under its lock.
    """

    def __init__(self) -> None:
        self.offset_ns: int | None = None
        """Rig clock minus camera clock, nanoseconds; None until the first stamped frame."""

    def mid_exposure_ns(self, device_timestamp_ns: int, arrived_ns: int,
                        exposure_us: float) -> int:
        """The frame's mid-exposure time on the rig clock, nanoseconds.

        Parameters
        ----------
        device_timestamp_ns : int
            The camera's stamp of the exposure start, nanoseconds on its clock; 0 for none.
        arrived_ns : int
            Rig clock when the frame arrived, nanoseconds.
        exposure_us : float
            The frame's exposure time, microseconds.
        """
        exposure_ns = round(exposure_us * 1e3)
        if device_timestamp_ns == 0:
            return arrived_ns - exposure_ns // 2
        if self.offset_ns is None:
            self.offset_ns = arrived_ns - device_timestamp_ns - exposure_ns
        return device_timestamp_ns + self.offset_ns + exposure_ns // 2


def skipped_frame_ids(last: int, new: int) -> int:
    """Frame ids strictly between ``last`` and ``new``: the frames lost whole between two buffers.

    GigE Vision 1.x ids are 16 bits and wrap from 65535 to 1 (0 is invalid); 64-bit ids (USB3
    Vision, GigE Vision 2 extended ids) never wrap in practice. Ids that go back otherwise (the
    camera restarted its count) skip nothing that can be told.
    """
    if new > last:
        return new - last - 1
    if last <= _GVSP_MAX_FRAME_ID and new <= _GVSP_MAX_FRAME_ID and last - new > 0x8000:
        return (_GVSP_MAX_FRAME_ID - last) + (new - 1)
    return 0


class FrameIdGaps:
    """Frames lost whole, from the gaps between the frame ids of whole frames.

    An SDK fills an incomplete buffer's frame id from whatever of the frame arrived, so it may be
    stale (a reused buffer's) and only whole frames' ids are trusted: each incomplete buffer is
    counted by the driver at once (and told here), and the ids skipped between two whole frames
    count the frames lost whole, less the incomplete ones already counted there (SDKs hand
    buffers over in frame order). Used by the acquisition thread only, so it has no lock.
    """

    def __init__(self) -> None:
        self._last: int | None = None
        self._incomplete_since_whole = 0

    def incomplete(self) -> None:
        """An incomplete buffer arrived (the driver counts it as one dropped frame)."""
        self._incomplete_since_whole += 1

    def whole(self, frame_id: int) -> int:
        """A whole frame with ``frame_id`` arrived; return how many frames were lost whole since
        the previous whole one."""
        lost = 0
        if self._last is not None:
            lost = max(0, skipped_frame_ids(self._last, frame_id) - self._incomplete_since_whole)
        self._last = frame_id
        self._incomplete_since_whole = 0
        return lost


class FrameQueue:
    """One open session of a camera: its frames on their way to the reader, and its counts.

    Parameters
    ----------
    camera_id : str
        The camera's id, for the frames' metadata and the errors.
    capacity : int
        Frames held for the reader; a frame that arrives when it is full is dropped (counted).

    Notes
    -----
    A frame's ``frame_counter`` counts the frames delivered in the session from 0, its
    ``dropped_frames`` the frames dropped so far, and its ``trigger_index`` the camera's own
    count of exposures since ``open()``, dropped ones included (a camera cannot know the
    trigger controller's pulse numbers). Thread-safe.
    """

    def __init__(self, camera_id: str, capacity: int) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be at least 1, not {capacity}")
        self.camera_id = camera_id
        self.capacity = int(capacity)
        self._cond = threading.Condition()
        self._frames: collections.deque[Frame] = collections.deque()
        self._clock = ClockMapping()
        self._lost: str | None = None
        self._frame_counter = 0
        self._dropped = 0

    @property
    def dropped(self) -> int:
        """Frames dropped in this session (incomplete, lost whole, undecodable, queue full)."""
        with self._cond:
            return self._dropped

    @property
    def clock_offset_ns(self) -> int | None:
        """Rig clock minus camera clock (nanoseconds), fixed on the session's first stamped
        frame; None before it."""
        with self._cond:
            return self._clock.offset_ns

    @property
    def lost(self) -> str | None:
        """Why the camera is known to be gone, or None while it is not."""
        with self._cond:
            return self._lost

    def count_dropped(self, frames: int = 1) -> None:
        """Count ``frames`` frames the camera exposed that will never be delivered."""
        if frames < 0:
            raise ValueError(f"frames must not be negative, not {frames}")
        with self._cond:
            self._dropped += frames

    def push(self, image: Image, *, arrived_ns: int, device_timestamp_ns: int,
             exposure_us: float, gain_db: float, bit_depth: int,
             extra: Mapping[str, object] | None = None) -> Frame | None:
        """Queue one whole frame for the reader.

        Parameters
        ----------
        image : numpy.ndarray
            The image, owned by the frame from now on (not a view of an SDK buffer).
        arrived_ns : int
            Rig clock when the buffer arrived, nanoseconds.
        device_timestamp_ns : int
            The camera's stamp of the exposure start, nanoseconds on its clock; 0 for none.
        exposure_us, gain_db : float
            The settings the frame was taken with (microseconds, decibels).
        bit_depth : int
            Significant bits per pixel.
        extra : Mapping, optional
            Driver-specific facts for ``Frame.extra``; ``device_timestamp_ns`` is added.

        Returns
        -------
        Frame or None
            The queued frame, or None when the queue was full (the frame is counted dropped).
        """
        with self._cond:
            if len(self._frames) >= self.capacity:
                self._dropped += 1
                return None
            meta = FrameMeta(camera_id=self.camera_id, frame_counter=self._frame_counter,
                             t_ns=self._clock.mid_exposure_ns(device_timestamp_ns, arrived_ns,
                                                              exposure_us),
                             exposure_us=exposure_us, gain_db=gain_db,
                             dropped_frames=self._dropped, bit_depth=bit_depth,
                             trigger_index=self._frame_counter + self._dropped)
            frame = Frame(image=image, meta=meta,
                          extra={"device_timestamp_ns": device_timestamp_ns, **(extra or {})})
            self._frames.append(frame)
            self._frame_counter += 1
            self._cond.notify_all()
            return frame

    def pop(self, timeout_s: float) -> Frame:
        """The oldest queued frame, waiting up to ``timeout_s`` for one.

        Frames queued before the camera was lost are still handed out first.

        Raises
        ------
        DeviceDisconnectedError
            When no frame is queued and the camera is known to be gone.
        DeviceTimeoutError
            When no frame came within ``timeout_s``.
        """
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not self._frames:
                if self._lost is not None:
                    raise DeviceDisconnectedError(self.camera_id, self._lost)
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise DeviceTimeoutError(self.camera_id, f"no frame within {timeout_s} s")
                self._cond.wait(remaining)
            return self._frames.popleft()

    def mark_lost(self, reason: str) -> None:
        """Record (and log, once) that the camera is gone, and wake the reader."""
        with self._cond:
            if self._lost is None:
                _log.error("camera %s lost: %s", self.camera_id, reason)
                self._lost = reason
            self._cond.notify_all()

    def check_connected(self) -> None:
        """Raise :class:`DeviceDisconnectedError` once the camera is known to be gone."""
        with self._cond:
            if self._lost is not None:
                raise DeviceDisconnectedError(self.camera_id, f"{self._lost}; close() and "
                                                              "open() once it is back")

    def guarded(self, call: Callable[[], _T]) -> _T:
        """Run a control call; one that finds the camera gone marks the session lost (so the
        waiting reader wakes) before its error goes on."""
        try:
            return call()
        except DeviceDisconnectedError as exc:
            self.mark_lost(exc.reason)
            raise

    def clear(self) -> None:
        """Drop the queued frames and wake the reader (the camera is being closed)."""
        with self._cond:
            self._frames.clear()
            self._cond.notify_all()


class AcquisitionThread:
    """The acquisition loop of one session: ``step()`` over and over on a daemon thread.

    ``step`` waits a short while (tens of milliseconds, which bound how long :meth:`stop` waits)
    for one buffer from the SDK and hands it on. The loop ends at :meth:`stop` or once
    ``frames`` is marked lost; a :class:`DeviceDisconnectedError` from ``step`` marks it lost,
    and so does any other exception (logged with its traceback), because a thread that died
    silently would leave the reader timing out with no word of why.
    """

    def __init__(self, name: str, frames: FrameQueue, step: Callable[[], None]) -> None:
        self._frames = frames
        self._step = step
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    @property
    def stopping(self) -> bool:
        """Whether :meth:`stop` was called (an SDK wait it aborted is then no failure)."""
        return self._stop.is_set()

    def start(self) -> None:
        """Start the loop."""
        self._thread.start()

    def stop(self) -> None:
        """End the loop and wait for it. Idempotent."""
        self._stop.set()
        if self._thread.ident is not None:
            self._thread.join()

    def _run(self) -> None:
        try:
            while not self._stop.is_set() and self._frames.lost is None:
                self._step()
        except DeviceDisconnectedError as exc:
            self._frames.mark_lost(exc.reason)
        except Exception as exc:
            _log.exception("camera %s: acquisition thread failed", self._frames.camera_id)
            self._frames.mark_lost(f"acquisition failed: {exc}")


def check_region(offset_x: int, offset_y: int, width: int | None, height: int | None) -> None:
    """Check a region-of-interest option (pixels; None size: the rest of the sensor).

    Raises
    ------
    ValueError
        For a negative offset or a size that is not positive.
    """
    if offset_x < 0 or offset_y < 0:
        raise ValueError(f"offsets must not be negative, not ({offset_x}, {offset_y})")
    for name, size in (("width", width), ("height", height)):
        if size is not None and size <= 0:
            raise ValueError(f"{name} must be positive, not {size}")


def check_region_read_back(device_id: str, asked: tuple[int, int, int | None, int | None],
                           read: tuple[int, int, int, int]) -> None:
    """Check that the camera took the region of interest asked for, ``(x, y, width, height)`` in
    pixels (a size of None: whatever the rest of the sensor is).

    Raises
    ------
    DeviceValueError
        When the region read back differs: a camera that rounds to its increment instead of
        refusing would otherwise deliver another region than the calibration expects.
    """
    x, y, width, height = asked
    if read[:2] != (x, y) or (width is not None and read[2] != width) or (
            height is not None and read[3] != height):
        raise DeviceValueError(device_id, f"region {width}x{height}+{x}+{y} reads back as "
                                          f"{read[2]}x{read[3]}+{read[0]}+{read[1]}")


def check_trigger_read_back(device_id: str, asked: str, read: str) -> None:
    """Check that the camera took the TriggerSource asked for.

    Raises
    ------
    DeviceValueError
        When it reads back as another source: the frames would wait for a trigger that never
        comes on that line.
    """
    if read != asked:
        raise DeviceValueError(device_id, f"TriggerSource reads {read} after setting {asked}")


def narrow_range(device_id: str, name: str, policy: tuple[float, float],
                 device: tuple[float, float],
                 decimals: int | None = None) -> tuple[float, float]:
    """The rig's policy range for a setting narrowed to what the camera can do.

    ``decimals``, for a driver that reports settings rounded to that many decimals, rounds the
    range inwards to match: its ends then read back as themselves, and stay within the camera's.

    Raises
    ------
    DeviceValueError
        When the two ranges do not meet.
    """
    low, high = max(policy[0], device[0]), min(policy[1], device[1])
    if decimals is not None:
        scale = 10.0**decimals
        low, high = math.ceil(low * scale) / scale, math.floor(high * scale) / scale
    if low > high:
        raise DeviceValueError(device_id, f"the camera's {name} range {device} misses the "
                                          f"rig's {policy}")
    return low, high


def clamp(value: float, bounds: tuple[float, float]) -> float:
    """``value`` moved into ``bounds`` (a setting asked for before the range was known)."""
    return min(max(value, bounds[0]), bounds[1])


_MIN_BUFFERS: Final[int] = 4
"""SDK buffers a session streams into at the least (``queue_size`` of them when that is more)."""


class CameraLink(Protocol):
    """What :class:`StreamingCamera` asks of a driver's link to its SDK: one opened camera, the
    only object that calls the SDK."""

    def start(self, n_buffers: int) -> None:
        """Start streaming into ``n_buffers`` SDK buffers (each trigger makes one frame)."""

    def stop(self) -> None:
        """Stop streaming."""

    def software_trigger(self) -> None:
        """Execute TriggerSoftware."""

    def release(self) -> None:
        """Let go of the camera and whatever of the SDK the link holds, whatever fails."""


LinkT = TypeVar("LinkT", bound=CameraLink)
"""A driver's link type."""


class NodeMapLink(abc.ABC):
    """The GenICam features of a camera an SDK opened through its node map (pylon, IDS peak):
    the link reads and writes features through its SDK, and this class builds on those what
    does not depend on the SDK.

    Attributes
    ----------
    device_id : str
        The camera's id in the rig; every error names it.
    """

    device_id: str

    @abc.abstractmethod
    def entries(self, name: str) -> list[str]:
        """The entries the enumeration feature ``name`` offers now."""

    @abc.abstractmethod
    def set(self, name: str, value: float) -> Any:
        """Set the number feature ``name`` to ``value``; return its value read back."""

    @abc.abstractmethod
    def bounds(self, name: str) -> tuple[float, float]:
        """The least and greatest values the feature ``name`` takes now."""

    @abc.abstractmethod
    def _write_entry(self, name: str, entry: str) -> str:
        """Set the enumeration feature ``name`` to ``entry``; return the entry read back."""

    def set_enum(self, name: str, entry: str) -> str:
        """Set the enumeration feature ``name`` to ``entry``, which must be on offer; return the
        entry read back.

        Raises
        ------
        DeviceValueError
            When the feature does not offer ``entry`` now.
        """
        offered = self.entries(name)
        if entry not in offered:
            raise DeviceValueError(self.device_id, f"the camera's {name} has no {entry!r} (it "
                                                   f"has {', '.join(offered) or 'none'})")
        return self._write_entry(name, entry)

    def set_region(self, x: int, y: int, width: int | None,
                   height: int | None) -> tuple[int, int, int, int]:
        """Set the region of interest (pixels; None: the rest of the sensor from the offset);
        return it as read back (x, y, width, height). Offsets go to 0 first, so that the new
        size is never refused for the old offset."""
        self.set("OffsetX", 0)
        self.set("OffsetY", 0)
        if width is None:
            width = int(self.bounds("Width")[1]) - x
        if height is None:
            height = int(self.bounds("Height")[1]) - y
        read_width, read_height = int(self.set("Width", width)), int(self.set("Height", height))
        return int(self.set("OffsetX", x)), int(self.set("OffsetY", y)), read_width, read_height


class StreamingCamera(Camera, Generic[LinkT]):
    """A hardware-triggered camera whose SDK hands buffers to an acquisition thread.

    Parameters
    ----------
    device_id : str
        The camera's id in the rig.
    clock : Clock
        The rig clock the frames' times are put on.
    pixel_format : {"Mono8", "Mono10", "Mono12"}
        8 bits per pixel, or 10/12 unpacked in 16-bit words.
    trigger_source : str
        The camera's TriggerSource for each frame (its trigger input's line), or ``Software`` to
        expose on :meth:`software_trigger`.
    offset_x, offset_y : int
        Top-left corner of the region of interest on the sensor, pixels.
    width, height : int or None
        Size of the region of interest, pixels; None for the rest of the sensor from the offset.
        Until the first ``open()`` the size reads as configured, or 1 when it comes from the
        sensor.
    queue_size : int
        Frames held for :meth:`read_frame`; frames that arrive when it is full are dropped
        (counted in :attr:`dropped_frames`).

    Notes
    -----
    ``open()`` connects (:meth:`_connect`), puts the camera in the configured state
    (:meth:`_configure`, which ends with :meth:`_restore_exposure_and_gain`), lets the driver
    watch for the camera going away (:meth:`_watch`), starts streaming into
    ``max(4, queue_size)`` buffers, and starts an :class:`AcquisitionThread` calling
    :meth:`_step`, which hands each buffer to :meth:`_deliver`. Each ``open()`` starts a session
    of its own (a new :class:`FrameQueue` and :class:`FrameIdGaps`). ``close()`` stops the
    thread, stops streaming unless the camera is known to be gone, and releases the link
    (:meth:`_release`).

    A frame's ``exposure_us`` and ``gain_db`` are the camera's settings when it arrived, and its
    ``trigger_index`` the camera's own count of exposures since ``open()``, dropped ones
    included. Its ``extra`` holds ``device_timestamp_ns`` (camera clock, 0 for none) and what
    the driver adds. One reader at a time.
    """

    def __init__(self, device_id: str, *, clock: Clock, pixel_format: str,
                 trigger_source: str, offset_x: int, offset_y: int, width: int | None,
                 height: int | None, queue_size: int) -> None:
        if pixel_format not in MONO_PIXEL_FORMATS:
            raise ValueError(f"pixel_format must be one of {', '.join(MONO_PIXEL_FORMATS)}, "
                             f"not {pixel_format!r}")
        if not trigger_source:
            raise ValueError("trigger_source must name one of the camera's TriggerSource values")
        check_region(offset_x, offset_y, width, height)
        if queue_size < 1:
            raise ValueError(f"queue_size must be at least 1, not {queue_size}")
        super().__init__(device_id, width or 1, height or 1, MONO_PIXEL_FORMATS[pixel_format])
        self._clock = clock
        self.pixel_format = pixel_format
        self.trigger_source = trigger_source
        self._roi = (int(offset_x), int(offset_y), width, height)
        self._queue_size = int(queue_size)
        self._link: LinkT | None = None
        self._frames = FrameQueue(device_id, self._queue_size)
        self._thread: AcquisitionThread | None = None
        self._gaps = FrameIdGaps()
        self._device_exposure_us = self._exposure_us
        self._device_gain_db = self._gain_db
        self._info: dict[str, object] = {}
        """What ``open()`` read from the camera, for ``describe()``."""

    # --- what the camera reports ------------------------------------------------------------

    @property
    def exposure_us(self) -> float:
        """Exposure time as the camera reports it after the last setting, microseconds (the
        value asked for until the first ``open()``)."""
        return self._device_exposure_us

    @property
    def gain_db(self) -> float:
        """Gain as the camera reports it after the last setting, decibels, except where the
        driver can reach only the camera's ``GainRaw``: its own units then (``describe()``'s
        ``gain_feature`` says so)."""
        return self._device_gain_db

    @property
    def dropped_frames(self) -> int:
        """Frames lost since :meth:`open`: incomplete or failed buffers, frame ids skipped,
        frames not of the configured size and format, a full queue."""
        return self._frames.dropped

    @property
    def clock_offset_ns(self) -> int | None:
        """Rig clock minus camera clock, nanoseconds, fixed on the first stamped frame after
        :meth:`open` (None before it, and for a camera that stamps none):
        ``t_ns = device_ts + offset + exposure / 2``."""
        return self._frames.clock_offset_ns

    def software_trigger(self) -> None:
        """Expose one frame now (TriggerSoftware); only with ``trigger_source="Software"``.

        Raises
        ------
        DeviceValueError
            When the camera is triggered from another source.
        DeviceTimeoutError
            When the camera is not ready for a trigger in time (a driver that waits for it).
        DeviceDisconnectedError
            When the camera is gone or does not answer.
        """
        link = self._live_link()
        if self.trigger_source != "Software":
            raise DeviceValueError(self.id, f"software_trigger() needs trigger_source "
                                            f"'Software', not {self.trigger_source!r}")
        self._frames.guarded(link.software_trigger)

    def describe(self) -> dict[str, object]:
        info: dict[str, object] = {**super().describe(), "pixel_format": self.pixel_format,
                                   "trigger_source": self.trigger_source,
                                   "dropped_frames": self.dropped_frames}
        if self.is_open:
            info["connected"] = self._frames.lost is None
            info["clock_offset_ns"] = self._frames.clock_offset_ns
            info.update(self._info)
        return info

    # --- the driver's hooks -------------------------------------------------------------------

    @abc.abstractmethod
    def _connect(self) -> LinkT:
        """Open the camera through the SDK."""

    @abc.abstractmethod
    def _configure(self, link: LinkT) -> None:
        """Put the camera in the configured state, read back what it took (setting ``width``,
        ``height``, ``bit_depth`` and ``_info``), and end with
        :meth:`_restore_exposure_and_gain`."""

    @abc.abstractmethod
    def _set_exposure(self, link: LinkT, value_us: float) -> float:
        """Set the exposure time; return the camera's value, microseconds."""

    @abc.abstractmethod
    def _set_gain(self, link: LinkT, value_db: float) -> float:
        """Set the gain; return the camera's value (decibels where it has them)."""

    @abc.abstractmethod
    def _step(self, link: LinkT, frames: FrameQueue) -> None:
        """One turn of the acquisition thread: wait a short while (tens of milliseconds) for
        one buffer of the session ``frames`` and hand it to :meth:`_deliver`."""

    def _watch(self, link: LinkT, frames: FrameQueue) -> None:
        """Get ready to notice the camera going away in the session ``frames`` (an SDK callback
        that marks it lost); called after :meth:`_configure`, before streaming starts.
        Nothing by default."""

    def _release(self, link: LinkT, *, lost: bool) -> None:
        """Let go of ``link``, after a failed ``open()`` or at ``close()``; ``lost`` says the
        camera is known to be gone."""
        link.release()

    # --- Device and Camera hooks ------------------------------------------------------------

    def _do_open(self) -> None:
        link = self._connect()
        frames = FrameQueue(self.id, self._queue_size)
        try:
            self._configure(link)
            self._watch(link, frames)
            link.start(n_buffers=max(_MIN_BUFFERS, self._queue_size))
        except BaseException as exc:
            self._release(link, lost=isinstance(exc, DeviceDisconnectedError))
            raise
        self._link = link
        self._frames = frames
        self._gaps = FrameIdGaps()
        self._thread = AcquisitionThread(f"{type(self).__name__}-{self.id}", frames,
                                         lambda: self._step(link, frames))
        self._thread.start()

    def _do_close(self) -> None:
        thread, self._thread = self._thread, None
        if thread is not None:
            thread.stop()
        link, self._link = self._link, None
        self._frames.clear()
        if link is None:
            return
        lost = self._frames.lost is not None
        if not lost:  # a camera known to be gone is not asked: each call would time out
            try:
                link.stop()
            except DeviceError as exc:
                _log.warning("camera %s: stopping acquisition: %s", self.id, exc)
        self._release(link, lost=lost)

    def _apply_exposure_us(self, value: float) -> None:
        link = self._live_link()
        self._device_exposure_us = self._frames.guarded(lambda: self._set_exposure(link, value))

    def _apply_gain_db(self, value: float) -> None:
        link = self._live_link()
        self._device_gain_db = self._frames.guarded(lambda: self._set_gain(link, value))

    def _read_frame(self, timeout_s: float) -> Frame:
        return self._frames.pop(timeout_s)

    # --- for the driver -----------------------------------------------------------------------

    def _restore_exposure_and_gain(self, link: LinkT, exposure_bounds_us: tuple[float, float],
                                   gain_bounds: tuple[float, float],
                                   decimals: int | None = None) -> None:
        """Narrow the rig's policy ranges (the class's) to what the camera can do
        (:func:`narrow_range`, ``decimals`` as there), then set the exposure and gain last asked
        for within them (a reopen after a power cycle restores them) and keep what the camera
        took."""
        self.exposure_range_us = narrow_range(self.id, "exposure_us",
                                              type(self).exposure_range_us,
                                              exposure_bounds_us, decimals)
        self.gain_range_db = narrow_range(self.id, "gain_db", type(self).gain_range_db,
                                          gain_bounds, decimals)
        self._device_exposure_us = self._set_exposure(
            link, clamp(self._exposure_us, self.exposure_range_us))
        self._device_gain_db = self._set_gain(link, clamp(self._gain_db, self.gain_range_db))

    def _deliver(self, frames: FrameQueue, frame_id: int, image: Image | None, *, whole: bool,
                 arrived_ns: int, device_timestamp_ns: int,
                 extra: Mapping[str, object] | None = None) -> None:
        """Account for one buffer of the session ``frames`` and queue its frame.

        Parameters
        ----------
        frames : FrameQueue
            The session the buffer belongs to.
        frame_id : int
            The transport's frame (block) id.
        image : numpy.ndarray or None
            The buffer's image, copied out of the SDK's memory; None for a buffer that is not a
            usable frame of the configured size and format (the driver has logged why).
        whole : bool
            False for a buffer the SDK reports incomplete or failed: one dropped frame, whose id
            is not trusted (:class:`FrameIdGaps`). A whole one's id counts the frames lost whole
            before it.
        arrived_ns, device_timestamp_ns, extra
            As :meth:`FrameQueue.push` takes them.
        """
        if not whole:
            self._gaps.incomplete()
            frames.count_dropped()
            return
        lost_whole = self._gaps.whole(frame_id)
        if lost_whole:
            _log.warning("camera %s: %d frame(s) lost whole before frame id %d", self.id,
                         lost_whole, frame_id)
            frames.count_dropped(lost_whole)
        if image is None:
            frames.count_dropped()
            return
        frames.push(image, arrived_ns=arrived_ns, device_timestamp_ns=device_timestamp_ns,
                    exposure_us=self._device_exposure_us, gain_db=self._device_gain_db,
                    bit_depth=self.bit_depth, extra=extra)

    def _live_link(self) -> LinkT:
        """The open link, or DeviceDisconnectedError once the camera is known to be gone."""
        self._require_open()
        self._frames.check_connected()
        link = self._link
        assert link is not None  # open implies a link
        return link
