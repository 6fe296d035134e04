"""The running daemon's heart: the rig, the store and the state machine that guards them.

::

              capture()                  a device fails
    idle ───────────────► capturing ──────────────────► fault
     ▲                        │                            │
     └────────────────────────┘◄───────────────────────────┘
          done (no device left in fault)    the failed devices reopen

One operation holds the hardware at a time: :meth:`Service.operation` moves the machine from
``idle`` (or ``fault``) into a busy state and back, and any other request meanwhile gets a
:class:`~eyeserver.errors.StateConflictError` naming the state the daemon is in; captures do not
conflict with each other: they queue on the acquisition worker and run in turn. ``fault`` does
not lock the hardware: it says that a device failed (its reason is kept in :meth:`Service.status`);
the next operation first reopens the failed devices it needs, and a background retry reopens
them with back-off (1 s doubling to 30 s), so the daemon recovers when the device does.

Every method here blocks (hardware, disk, SQLite): the API calls them from worker threads, never
on the event loop.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import math
import shutil
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal

import eyeserver
from eyeserver.calibration.artefact import load_calibration
from eyeserver.config import Settings
from eyeserver.errors import (
    DeviceError,
    DeviceValueError,
    EyeserverError,
    FormatError,
    StateConflictError,
)
from eyeserver.hardware.base import Device, Stage
from eyeserver.hardware.bundling import bundle_bit_depth, bundle_frames
from eyeserver.hardware.rig import AcquiredStep, Rig
from eyeserver.hardware.room import RoomHardware, room_hardware
from eyeserver.io import (
    BundleFrameData,
    RigSpec,
    atomic_write_text,
    fsync_dir,
    read_ply,
    rig_from_dict,
    write_ply,
)
from eyeserver.pipeline.demodulate import Carrier
from eyeserver.pipeline.reconstruct import MIN_FRINGE_CONTRAST, fringe_check
from eyeserver.reconstruction import (
    ReconstructionOptions,
    camera_carriers,
    reconstruct_bundle,
)
from eyeserver.service.audit import SALT_FILE, AuditTrail, audit_log_path
from eyeserver.service.calibration_files import input_capture_ids
from eyeserver.service.device_control import apply_settings, check_settings
from eyeserver.service.events import EventBus
from eyeserver.service.jobs import Jobs
from eyeserver.service.metrics import ServiceMetrics
from eyeserver.service.preview import height_map_png
from eyeserver.service.storage import CalibrationRecord, CaptureRecord, Store
from eyeserver.service.uploads import UploadTooLargeError, unpack_calibration_zip
from eyeserver.service.workers import BoundedWorker, RetryLoop, RetryWait, wait_on_event

__all__ = [
    "ALL_UNITS",
    "CLOUD_FILE",
    "SUMMARY_FILE",
    "BusyState",
    "DeviceHealth",
    "DeviceStatus",
    "NoActiveCalibrationError",
    "NoCloudError",
    "Service",
    "ServiceState",
    "ServiceStatus",
    "UnitStatus",
    "UnknownUnitError",
]

ServiceState = Literal["idle", "capturing", "calibrating", "tracking", "fault"]
BusyState = Literal["capturing", "calibrating", "tracking"]
DeviceHealth = Literal["ok", "fault"]
EvidenceSource = Callable[[], Mapping[str, str]]
"""Capture ids that are evidence → what of (see :meth:`Service.keep_as_evidence`)."""

ALL_UNITS = "all"
"""The ``unit`` of a capture that interleaves every unit of the rig."""

CLOUD_FILE = "cloud.ply"
"""The reconstructed surface, kept beside a capture's bundle."""

SUMMARY_FILE = "reconstruction.json"
"""The summary of the reconstruction that made :data:`CLOUD_FILE`, kept beside it."""

_log = logging.getLogger(__name__)

UPLOADS_DIR = "uploads"
"""Under the data directory: where an upload unpacks while it is checked (never the system's
temporary directory, where a killed daemon left up to 200 MiB, issue 35)."""


def _json_scalar(value: object) -> object:
    # Counts from the pipeline may be numpy scalars, which json cannot write by itself.
    item = getattr(value, "item", None)
    if callable(item):
        return item()
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


class NoActiveCalibrationError(StateConflictError):
    """A reconstruction was asked for before any calibration was activated (HTTP 409)."""


class NoCloudError(EyeserverError):
    """A capture has not been reconstructed yet (HTTP 404)."""


class UnknownUnitError(EyeserverError, ValueError):
    """A request named a unit the rig does not have (the API answers 422)."""


@dataclass(frozen=True)
class DeviceStatus:
    """One device as the daemon sees it: what it is, which unit owns it and its health."""

    id: str
    kind: str
    driver: str
    unit: str | None
    open: bool
    health: DeviceHealth
    reason: str | None
    details: dict[str, object]


@dataclass(frozen=True)
class UnitStatus:
    """One optical unit; in fault while any of its devices (or the trigger) is."""

    id: str
    projector: str
    cameras: tuple[str, ...]
    health: DeviceHealth
    reason: str | None


@dataclass(frozen=True)
class ServiceStatus:
    """A snapshot of the daemon for ``GET /status``."""

    state: ServiceState
    devices: tuple[DeviceStatus, ...]
    units: tuple[UnitStatus, ...]
    active_calibration_id: str | None
    uptime_s: float
    version: str


class Service:
    """Owns the rig and the store of one daemon and serialises access to the hardware.

    Parameters
    ----------
    settings : Settings
        ``data_dir`` holds the store; ``room`` and ``room_file`` name the room: the simulated
        one (``room_file`` None: the default room), whose scene is an eye so that captures show
        one, or real devices (:mod:`eyeserver.hardware.devices`).
    rig : Rig, optional
        A rig (not yet open) to drive instead of building the simulated room's; the daemon then
        has no :attr:`simulation`, as on real hardware (tests of a non-simulated daemon).
    retry_wait : RetryWait, optional
        How the background recovery waits between retries of failed devices (default: real
        time, :func:`~eyeserver.service.workers.wait_on_event`); tests step it by hand.

    Notes
    -----
    Nothing happens in the constructor; :meth:`open` opens the store then the rig and starts
    the workers (:mod:`eyeserver.service.workers`), :meth:`close` stops and closes them in
    reverse order. All methods block and are thread-safe. The hardware is driven only from the
    acquisition worker (captures, device settings, reopening failed devices), reconstructions
    only from the reconstruction worker; both queues are bounded (``acquisition_queue``,
    ``reconstruction_queue``) and a full one refuses a job with :class:`QueueFullError`.

    What happens (state changes, device faults and recoveries, captures, reconstructions,
    calibrations) is published on :attr:`events`, an :class:`~eyeserver.service.events.EventBus`
    that the live stream (``/api/v1/ws/events``) reads; publishing never waits for a reader.
    Every audit row of the store also becomes a line of :attr:`audit`'s file, as does every
    failed audited action (:mod:`eyeserver.service.audit`); :attr:`metrics` counts captures,
    frames and reconstruction times for ``GET /metrics``.
    """

    def __init__(self, settings: Settings, rig: Rig | None = None, *,
                 retry_wait: RetryWait = wait_on_event) -> None:
        # The one thread that drives the hardware, and the one that runs the pipeline.
        self.acquisition_worker = BoundedWorker("acquisition", settings.acquisition_queue)
        self.reconstruction_worker = BoundedWorker("reconstruction",
                                                   settings.reconstruction_queue)
        self._recovery = RetryLoop("device-recovery", pending=self._has_faults,
                                   attempt=self._retry_faults, wait=retry_wait)
        self._settings = settings
        self._given_rig = rig
        self._hardware: RoomHardware | None = None
        self._lock = threading.Lock()
        self._results_lock = threading.Lock()  # a capture's cloud and summary change together
        self._state: ServiceState = "idle"
        self._faults: dict[str, str] = {}  # device id -> reason
        self._carrier_cache: tuple[str, dict[str, Carrier] | None] | None = None
        self._store: Store | None = None
        self._rig: Rig | None = None
        self._started = time.monotonic()
        self.events = EventBus()  # what happens, for the live stream (/api/v1/ws/events)
        # Who did what: every store audit row is copied to the audit file, failures go there too.
        self.audit = AuditTrail(audit_log_path(settings), settings.data_dir / SALT_FILE)
        self.metrics = ServiceMetrics(self)  # GET /metrics
        self.jobs = Jobs(self.events, settings.job_queue)  # long operations (service/jobs.py)
        self._stage: Stage | None = None
        # A calibration session holds "calibrating" between its acquisitions (see hold_session).
        self._session: str | None = None
        self._session_acquiring = False
        self._evidence_sources: list[EvidenceSource] = []

    # --- lifecycle --------------------------------------------------------------------------

    def open(self) -> None:
        """Open the store under ``data_dir``, then build and open the rig.

        Raises
        ------
        StateConflictError
            The store is open in another process.
        DeviceError, ConfigError, FormatError
            The rig cannot be built or opened (the store is closed again).
        """
        data_dir = self._settings.ensure_data_dir()
        # Uploads unpack under the data directory; what a killed daemon left there goes.
        shutil.rmtree(data_dir / UPLOADS_DIR, ignore_errors=True)
        self.audit.open()
        try:
            store = Store.open(data_dir, audit_sink=self.audit.record_stored)
        except BaseException:
            self.audit.close()
            raise
        try:
            # The configured room unless a rig is given: found by name, never imported here.
            hardware = room_hardware(self._settings.room, self._settings.room_file) \
                if self._given_rig is None else RoomHardware(rig=self._given_rig)
            hardware.rig.open()
        except BaseException:
            store.close()
            self.audit.close()
            raise
        self._store, self._rig, self._hardware = store, hardware.rig, hardware
        self._stage = hardware.stage
        if self._stage is not None:
            self._stage.open()
        self._started = time.monotonic()
        self.acquisition_worker.start()
        self.reconstruction_worker.start()
        self.jobs.start()
        self._recovery.start()
        _log.info("service open", extra={"units": [u.id for u in hardware.rig.units]})

    def close(self) -> None:
        """Stop the background recovery and the workers (jobs already queued finish), then
        close the rig and the store (the reverse of :meth:`open`). Idempotent."""
        self._recovery.stop()
        self.jobs.stop()
        self.acquisition_worker.stop()
        self.reconstruction_worker.stop()
        rig, store = self._rig, self._store
        self._rig = self._store = None
        self._hardware = None
        if self._stage is not None:
            self._stage.close()
            self._stage = None
        if rig is not None:
            errors = rig.close()
            if errors:
                _log.warning("devices failed to close", extra={"devices": sorted(errors)})
        if store is not None:
            store.close()
        self.audit.close()

    def __enter__(self) -> Service:
        self.open()
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    @property
    def rig(self) -> Rig:
        """The open rig."""
        if self._rig is None:
            raise StateConflictError("the daemon's hardware is not open")
        return self._rig

    @property
    def store(self) -> Store:
        """The open store."""
        if self._store is None:
            raise StateConflictError("the daemon's store is not open")
        return self._store

    @property
    def stage(self) -> Stage | None:
        """The motorised stage that carries the calibration plate; None when the daemon has
        none (it is not part of the rig: calibrations do not depend on it)."""
        return self._stage

    @property
    def simulated(self) -> bool:
        """Whether the open rig images a simulated room."""
        hardware = self._hardware
        return hardware is not None and hardware.simulation is not None

    @property
    def simulation(self) -> object | None:
        """The simulated room the open rig images, as an opaque handle; None on real hardware
        (or when closed).

        For people and tests only (:mod:`eyeserver.service.simroom` opens it): the measurement
        path never sees it.
        """
        hardware = self._hardware
        return None if hardware is None else hardware.simulation

    # --- the state machine ------------------------------------------------------------------

    @property
    def state(self) -> ServiceState:
        """What the daemon is doing now."""
        with self._lock:
            return self._state

    @contextmanager
    def operation(self, busy: BusyState, what: str | None = None) -> Iterator[None]:
        """Hold the hardware in state ``busy`` for the duration of the block.

        On leaving, the state returns to ``idle``, or to ``fault`` while a device is in fault.

        Raises
        ------
        StateConflictError
            Another operation holds the hardware; the message names the daemon's state.
        """
        with self._lock:
            if self._state not in ("idle", "fault"):
                raise StateConflictError(f"cannot start {what or busy}: the daemon is "
                                         f"{self._state}")
            previous, self._state = self._state, busy
            self.events.publish("state", state=busy, previous=previous)
        try:
            yield
        finally:
            with self._lock:
                self._state = "fault" if self._faults else "idle"
                self.events.publish("state", state=self._state, previous=busy)

    @contextmanager
    def idle_moment(self, what: str, *, while_tracking: bool = False) -> Iterator[None]:
        """Run a short block while no operation holds the hardware, keeping one from starting.

        For changes that must not land in the middle of an operation but take no time worth a
        state of their own (placing a simulated scene). The block holds the state lock: it must
        be quick and must not call back into the service. ``while_tracking``: live tracking
        does not count as such an operation (the simulated eye moved under it).

        Raises
        ------
        StateConflictError
            An operation holds the hardware; the message names the daemon's state.
        """
        with self._lock:
            # A calibration session holds "calibrating" while a person moves the board or the
            # plate between its acquisitions; that is the moment for a scene to change.
            between_views = (self._state == "calibrating" and self._session is not None
                             and not self._session_acquiring)
            allowed = ("idle", "fault", "tracking") if while_tracking else ("idle", "fault")
            if self._state not in allowed and not between_views:
                raise StateConflictError(f"cannot {what}: the daemon is {self._state}")
            yield

    def _mark_fault(self, error: DeviceError) -> None:
        """Put a device in fault. The log line and the ``device.fault`` event come once per
        fault (and again when its reason changes), not on every refused capture or failed
        retry while it lasts: a client counting events counts faults."""
        reason = str(error.reason)
        with self._lock:
            new = self._faults.get(error.device_id) != reason
            self._faults[error.device_id] = reason
            if self._state == "idle":  # outside an operation (a device setting failed)
                self._state = "fault"
                self.events.publish("state", state="fault", previous="idle")
        self._recovery.poke()  # after releasing the lock: the retry loop takes it
        if new:
            _log.error("device fault", extra={"device_id": error.device_id, "reason": reason})
            self.events.publish("device.fault", device_id=error.device_id,
                                unit=self._unit_id(error.device_id), reason=reason)

    def _unit_id(self, device_id: str) -> str | None:
        """The unit owning a device; None for the trigger (it serves every unit)."""
        try:
            return None if self._rig is None else self._rig.unit_of(device_id).id
        except KeyError:
            return None

    def _mark_ok(self, device_ids: Sequence[str]) -> None:
        with self._lock:
            for device_id in device_ids:
                if self._faults.pop(device_id, None) is not None:
                    _log.info("device recovered", extra={"device_id": device_id})
                    self.events.publish("device.recovered", device_id=device_id)
            if self._state == "fault" and not self._faults:  # recovered outside an operation
                self._state = "idle"
                self.events.publish("state", state="idle", previous="fault")

    def _recover(self, devices: Sequence[Device]) -> None:
        """Reopen the devices among ``devices`` that are in fault (a device that was unplugged
        and came back works only after close and open)."""
        with self._lock:
            faulty = [d for d in devices if d.id in self._faults]
        for device in faulty:
            # A broken connection may refuse a clean close; open() decides.
            with contextlib.suppress(DeviceError):
                device.close()
            try:
                device.open()
            except DeviceError as exc:
                self._mark_fault(exc)
                raise
        self._mark_ok([d.id for d in faulty])

    def _has_faults(self) -> bool:
        with self._lock:
            return bool(self._faults)

    def device_retry_after_s(self) -> int:
        """Whole seconds, at least 1, until the background recovery next tries the devices in
        fault: what a client refused for a failed device is told to wait (``Retry-After``)
        before it asks again, since nothing changes before then unless the device does."""
        return max(1, math.ceil(self._recovery.next_attempt_in_s()))

    def _retry_faults(self) -> bool:
        """One attempt of the background recovery: reopen every device in fault, through the
        acquisition worker so that it never races a capture. True when none is left in fault.
        """
        def reopen() -> bool:
            with self._lock:
                if self._state in ("calibrating", "tracking"):
                    return False  # not now: the operation holds the hardware; try again later
                faulty = set(self._faults)
            for device in self.rig.devices:
                if device.id in faulty:
                    with contextlib.suppress(DeviceError):  # _recover keeps the fault's reason
                        self._recover([device])
            return not self._has_faults()

        return self.acquisition_worker.call(reopen)

    def _reset_cameras(self, cameras: Sequence[Device], failed_id: str) -> None:
        """Close and reopen the healthy cameras of a failed acquisition.

        A camera whose read was never reached still holds that pulse's exposure; left there,
        the next acquisition would read it as its own frame.
        """
        for camera in cameras:
            if camera.id == failed_id:
                continue
            with contextlib.suppress(DeviceError):
                camera.close()
            try:
                camera.open()
            except DeviceError as exc:
                self._mark_fault(exc)

    # --- operations -------------------------------------------------------------------------

    def unit_ids(self, unit: str) -> list[str]:
        """The units a capture of ``unit`` (a unit id or ``"all"``) interleaves.

        Raises
        ------
        UnknownUnitError
            ``unit`` is neither a unit of the rig nor ``"all"``.
        """
        units = [u.id for u in self.rig.units]
        if unit == ALL_UNITS:
            return units
        if unit not in units:
            raise UnknownUnitError(f"unknown unit {unit!r}; the rig has "
                                   f"{', '.join(units)} (or {ALL_UNITS!r})")
        return [unit]

    def capture(self, unit: str) -> CaptureRecord:
        """Capture one frame set of ``unit`` (or ``"all"``, interleaved) and store it.

        Runs on the acquisition worker: a capture asked for while others are running or
        queued waits its turn (a triggered capture is never dropped). Returns once the bundle
        and its index row are durable.

        Raises
        ------
        UnknownUnitError
            For a unit the rig does not have.
        StateConflictError
            The daemon is calibrating or tracking; the message names the state.
        QueueFullError
            ``acquisition_queue`` jobs are already waiting (nothing was captured).
        DeviceError
            A device failed; it and its unit are in fault until it can be reopened (by the next
            capture that needs it, or by the background recovery). Also a projector whose lit
            frames show a scene but none of its fringes (:meth:`_fringe_checks`): the capture
            is kept, named in the reason, but not returned as a measurement.
        """
        unit_ids = self.unit_ids(unit)
        with self._lock:
            if self._state not in ("idle", "fault", "capturing"):
                raise StateConflictError(f"cannot start a capture: the daemon is {self._state}")
        return self.acquisition_worker.call(lambda: self._capture_now(unit, unit_ids))

    def _capture_now(self, unit: str, unit_ids: Sequence[str]) -> CaptureRecord:
        """One capture, on the acquisition worker (see :meth:`capture`)."""
        rig, store = self.rig, self.store
        with self.operation("capturing", "a capture"):
            units = [rig.unit(u) for u in unit_ids]
            devices: list[Device] = [rig.trigger]
            for optical_unit in units:
                devices += [optical_unit.projector, *optical_unit.cameras]
            self._recover(devices)
            try:
                steps = rig.acquire(unit_ids)
            except DeviceError as exc:
                self._mark_fault(exc)
                self._reset_cameras([c for u in units for c in u.cameras], exc.device_id)
                raise
            frames = bundle_frames(steps)
            active = store.active_calibration()
            checks, dark = self._fringe_checks(active, steps)
            extra: dict[str, object] = {"simulated": self.simulated}
            if checks is not None:
                extra["fringe_check"] = checks
            record = store.add_capture(
                "measurement", rig_from_dict(rig.spec(), "<daemon rig>"), frames, unit=unit,
                calibration_id=None if active is None else active.id,
                bit_depth=bundle_bit_depth(rig, frames), extra=extra)
            self.metrics.capture_stored(unit, steps)
            self.events.publish("capture.stored", capture_id=record.id, unit=unit,
                                calibration_id=record.calibration_id)
            if dark:
                # Kept (the evidence of the fault), but not handed on as a measurement.
                errors = [DeviceError(projector_id, f"{reason} (capture {record.id} kept)")
                          for projector_id, reason in dark.items()]
                for error in errors:
                    self._mark_fault(error)
                raise errors[0]
        _log.info("capture stored", extra={"capture_id": record.id, "unit": unit})
        return record

    def _fringe_checks(self, active: CalibrationRecord | None, steps: Sequence[AcquiredStep]
                       ) -> tuple[dict[str, dict[str, object]] | None, dict[str, str]]:
        """Every lit frame's :func:`~eyeserver.pipeline.reconstruct.fringe_check` against the
        active calibration's carriers (None without one that has them: nothing to check
        against), and the projectors whose cameras all showed a scene but none its fringes,
        with the reason."""
        carriers = self._carriers(active)
        if carriers is None:
            return None, {}
        checks: dict[str, dict[str, object]] = {}
        dark: dict[str, str] = {}
        for step in steps:
            seen = {camera_id: fringe_check(carriers[camera_id], frame.image)
                    for camera_id, frame in step.frames.items() if camera_id in carriers}
            checks.update({camera_id: check.to_dict() for camera_id, check in seen.items()})
            judged = [c for c in seen.values() if c.judged]
            if judged and all(c.dark for c in judged):
                contrast = max(c.contrast for c in judged)
                for projector_id in step.pulse.step.projectors:
                    dark[projector_id] = (
                        f"no fringes in the frames it lit ({', '.join(seen)}: contrast "
                        f"{contrast:.2f}, below {MIN_FRINGE_CONTRAST}): the projector gives "
                        "no light")
        return checks, dark

    def _carriers(self, active: CalibrationRecord | None) -> dict[str, Carrier] | None:
        """The active calibration's carrier per camera (cached by calibration id), or None."""
        if active is None:
            return None
        cached = self._carrier_cache
        if cached is not None and cached[0] == active.id:
            return cached[1]
        carriers: dict[str, Carrier] | None = None
        try:
            carriers = camera_carriers(load_calibration(active.path, self.rig_spec())) or None
        except EyeserverError as exc:  # the captures say it: no fringe_check in their bundle
            _log.warning("no fringe check: the active calibration cannot be read",
                         extra={"calibration_id": active.id, "reason": str(exc)})
        self._carrier_cache = (active.id, carriers)
        return carriers

    # --- calibration sessions ---------------------------------------------------------------

    def hold_session(self, session_id: str) -> None:
        """Put the daemon in ``calibrating`` for a calibration session until
        :meth:`release_session`.

        Captures and other operations answer 409 meanwhile; scenes (the board, the plate) may
        change between the session's acquisitions (:meth:`idle_moment`).

        Raises
        ------
        StateConflictError
            Another operation or session holds the hardware.
        """
        with self._lock:
            if self._state not in ("idle", "fault"):
                raise StateConflictError(f"cannot start a calibration session: the daemon is "
                                         f"{self._state}")
            previous, self._state, self._session = self._state, "calibrating", session_id
            self.events.publish("state", state="calibrating", previous=previous,
                                session_id=session_id)

    def release_session(self, session_id: str) -> None:
        """End what :meth:`hold_session` started (idle, or fault while a device is in fault).
        Idempotent; does nothing for a session that does not hold the daemon."""
        with self._lock:
            if self._session != session_id:
                return
            self._session = None
            self._state = "fault" if self._faults else "idle"
            self.events.publish("state", state=self._state, previous="calibrating",
                                session_id=session_id)

    def acquire_for_session(self, session_id: str, *, lit: bool, z_mm: float | None = None,
                            move_stage: bool = False,
                            ) -> tuple[list[BundleFrameData], int | None]:
        """Acquire one set of frames for the calibration session holding the daemon.

        On the acquisition worker: with ``move_stage`` the stage first moves the plate to
        ``z_mm``, the nominal Z the frames record (plate and reference only); ``lit`` lights
        every unit in turn (one frame each, FORMATS.md), otherwise one frame of every camera
        with all projectors dark, under the room lights (a chessboard). Returns the bundle
        frames and their ``bit_depth``.

        Raises
        ------
        StateConflictError
            The session does not hold the daemon; or a stage move was asked for and the daemon
            has no stage.
        DeviceError
            A device failed; it is put in fault.
        """
        return self.acquisition_worker.call(
            lambda: self._acquire_for_session_now(session_id, lit, z_mm, move_stage))

    def _acquire_for_session_now(self, session_id: str, lit: bool, z_mm: float | None,
                                 move_stage: bool) -> tuple[list[BundleFrameData], int | None]:
        rig = self.rig
        with self._lock:
            if self._session != session_id:
                raise StateConflictError(f"calibration session {session_id} does not hold the "
                                         f"daemon (it is {self._state})")
            self._session_acquiring = True
        try:
            devices: list[Device] = [rig.trigger, *rig.projectors, *rig.cameras]
            self._recover(devices)
            if move_stage and z_mm is not None:
                if self._stage is None:
                    raise StateConflictError("the daemon has no motorised stage: put the plate "
                                             "at the height by hand and give only z_mm")
                try:
                    self._stage.move_to(z_mm)
                except DeviceValueError:
                    raise
                except DeviceError as exc:
                    self._mark_fault(exc)
                    raise
            hardware = self._hardware
            lights = None if hardware is None else hardware.lights
            try:
                if lit:
                    steps = rig.acquire([u.id for u in rig.units])
                else:
                    if lights is not None:  # a room without a switch is simply lit for the board
                        lights(True)
                    try:
                        steps = [rig.acquire_unlit()]
                    finally:
                        if lights is not None:
                            lights(False)
            except DeviceError as exc:
                self._mark_fault(exc)
                self._reset_cameras(rig.cameras, exc.device_id)
                raise
            self.metrics.frames_read(steps)
            frames = bundle_frames(steps, z_mm)
            return frames, bundle_bit_depth(rig, frames)
        finally:
            with self._lock:
                self._session_acquiring = False

    def rig_spec(self) -> RigSpec:
        """The open rig as its rig file would describe it (what calibrations must match)."""
        return rig_from_dict(self.rig.spec(), "<daemon rig>")

    # --- calibrations -----------------------------------------------------------------------

    def import_calibration(self, archive: bytes, *, actor: str) -> CalibrationRecord:
        """Store the calibration zipped in ``archive`` under a new id (not yet active).

        Raises
        ------
        UploadTooLargeError
            The archive, or what it unpacks to, is larger than ``max_upload_mb``.
        FormatError
            The archive is unsafe or not a calibration directory, the calibration is invalid,
            or it was made for another rig (the message names the member or field).
        """
        limit = self._settings.max_upload_mb * 2**20
        if len(archive) > limit:
            raise UploadTooLargeError(f"the upload exceeds {self._settings.max_upload_mb} MiB")
        uploads = self._uploads_dir()
        with self.audit.failures(actor, "import_calibration", "upload"), \
                tempfile.TemporaryDirectory(prefix="calibration-", dir=uploads) as unpacked:
            unpack_calibration_zip(archive, Path(unpacked), max_unpacked_bytes=limit)
            try:
                load_calibration(unpacked, self.rig_spec(), max_arrays_bytes=limit)
            except FormatError as exc:  # named as in the upload, not where it was unpacked
                raise FormatError(f"upload:{Path(exc.path).relative_to(unpacked).as_posix()}"
                                  if Path(exc.path).is_relative_to(unpacked) else "upload",
                                  exc.field, exc.reason) from None
            # The unpack directory is gone by now: say where the calibration came from instead.
            source = f"upload by {actor}, sha256:{hashlib.sha256(archive).hexdigest()}"
            record = self.store.import_calibration(unpacked, actor=actor, source=source)
        _log.info("calibration imported", extra={"calibration_id": record.id, "actor": actor})
        self.events.publish("calibration.imported", calibration_id=record.id, actor=actor)
        return record

    def _uploads_dir(self) -> Path:
        """Where uploads unpack: inside the data directory (its disk, its permissions), emptied
        at every start."""
        directory = self._settings.ensure_data_dir() / UPLOADS_DIR
        directory.mkdir(mode=0o700, exist_ok=True)
        return directory

    def activate_calibration(self, calibration_id: str, *, actor: str) -> CalibrationRecord:
        """Make a stored calibration the one new captures and reconstructions use.

        Raises
        ------
        StateConflictError
            An operation holds the hardware (a capture must not change calibration midway).
        UnknownIdError, StorageError
            As for :meth:`Store.activate_calibration`.
        """
        with self.audit.failures(actor, "activate_calibration", calibration_id), \
                self.operation("calibrating", "activating a calibration"):
            record = self.store.activate_calibration(calibration_id, actor=actor)
            self.events.publish("calibration.activated", calibration_id=record.id, actor=actor)
        _log.info("calibration activated", extra={"calibration_id": record.id, "actor": actor})
        return record

    # --- reconstruction ---------------------------------------------------------------------

    def reconstruct(self, capture_id: str, options: ReconstructionOptions | None = None
                    ) -> dict[str, Any]:
        """Reconstruct a stored capture with the active calibration; keep its cloud and summary.

        The cloud replaces ``cloud.ply`` in the capture's directory and the summary
        ``reconstruction.json`` beside it, each atomically; the old summary goes first, so a
        summary on disk always describes the cloud beside it, even after a crash in between.
        The hardware is not involved, so this does not enter the state machine and may run
        beside a capture. The capture and the calibration are checked at once; the
        reconstruction itself waits its turn on the reconstruction worker.

        ``options`` (method, depth prior, region, minimum quality) default to those of
        ``eyeserver reconstruct``.

        Returns
        -------
        dict
            The summary of :func:`~eyeserver.reconstruction.reconstruct_bundle` with
            ``capture_id``, ``calibration_id``, ``options`` (all of them, defaults filled in),
            ``reconstructed`` (UTC, ISO 8601) and ``duration_s`` added, as stored.

        Raises
        ------
        NoActiveCalibrationError
            No calibration is active.
        UnknownIdError, StorageError
            As for :meth:`Store.get_capture`.
        ReconstructionError, FormatError
            The capture cannot be reconstructed with the active calibration.
        QueueFullError
            ``reconstruction_queue`` reconstructions are already waiting.
        """
        store = self.store
        capture = store.get_capture(capture_id)
        active = store.active_calibration()
        if active is None:
            raise NoActiveCalibrationError(
                "no calibration is active: import one (POST /api/v1/calibrations) and activate "
                "it (POST /api/v1/calibrations/{id}/activate)")
        chosen = options or ReconstructionOptions()
        return self.reconstruction_worker.call(
            lambda: self._reconstruct_now(capture, active, chosen))

    def _reconstruct_now(self, capture: CaptureRecord, active: CalibrationRecord,
                         options: ReconstructionOptions) -> dict[str, Any]:
        """The reconstruction itself, on the reconstruction worker (see :meth:`reconstruct`)."""
        started = time.monotonic()
        cloud, summary = reconstruct_bundle(
            active.path, capture.path, method=options.method,
            depth_prior_mm=options.depth_prior_mm, region=options.region(),
            min_quality=options.min_quality)
        summary.update(capture_id=capture.id, calibration_id=active.id,
                       options=options.to_dict(),
                       reconstructed=datetime.now(UTC).isoformat(timespec="milliseconds")
                       .replace("+00:00", "Z"),
                       duration_s=round(time.monotonic() - started, 3))
        text = json.dumps(summary, indent=2, default=_json_scalar) + "\n"
        try:
            with self._results_lock:
                (capture.path / SUMMARY_FILE).unlink(missing_ok=True)
                fsync_dir(capture.path)
                write_ply(capture.path / CLOUD_FILE, cloud,
                          comments=[f"capture {capture.id}", f"calibration {active.id}"])
                atomic_write_text(capture.path / SUMMARY_FILE, text)
        except FileNotFoundError:
            self.store.get_capture(capture.id)  # UnknownIdError when it was deleted meanwhile
            raise
        self.metrics.reconstruction_done(time.monotonic() - started)
        summary = dict(json.loads(text))  # exactly what GET .../reconstruction will read
        _log.info("capture reconstructed", extra={
            "capture_id": capture.id, "calibration_id": active.id, "points": summary["points"],
            "method": options.method, "duration_s": summary["duration_s"]})
        self.events.publish("reconstruction.done", capture_id=capture.id,
                            calibration_id=active.id, points=summary["points"])
        return summary

    def cloud_path(self, capture_id: str) -> Path:
        """The stored ``cloud.ply`` of a capture.

        Raises
        ------
        NoCloudError
            The capture has not been reconstructed.
        UnknownIdError, StorageError
            As for :meth:`Store.get_capture`.
        """
        return self._result_file(capture_id, CLOUD_FILE)

    def reconstruction_summary(self, capture_id: str) -> dict[str, Any]:
        """The stored summary of a capture's reconstruction (as :meth:`reconstruct` returned).

        Raises
        ------
        NoCloudError
            The capture has not been reconstructed.
        UnknownIdError, StorageError
            As for :meth:`Store.get_capture`.
        """
        path = self._result_file(capture_id, SUMMARY_FILE)
        summary: dict[str, Any] = json.loads(path.read_text(encoding="utf-8"))
        return summary

    def _result_file(self, capture_id: str, name: str) -> Path:
        """A file a reconstruction keeps beside a capture's bundle (errors as
        :meth:`cloud_path`)."""
        path = self.store.get_capture(capture_id).path / name
        if not path.is_file():
            raise NoCloudError(f"capture {capture_id} has not been reconstructed yet "
                               f"(POST /api/v1/captures/{capture_id}/reconstruction)")
        return path

    def keep_as_evidence(self, source: EvidenceSource) -> None:
        """Never delete the captures ``source()`` names: it maps each capture id to what the
        capture is the evidence of (a stored pose measurement, a captured reference pose)."""
        self._evidence_sources.append(source)

    def evidence_captures(self) -> dict[str, str]:
        """Every capture that is something's evidence, and what: a calibration's inputs and
        what :meth:`keep_as_evidence` registered. Such a capture goes only with what it
        documents (never, as nothing of it is deleted)."""
        held = {capture_id: f"an input of calibration {calibration.id} (its evidence)"
                for calibration in self.store.list_calibrations()
                for capture_id in input_capture_ids(calibration)}
        for source in self._evidence_sources:
            held.update(source())
        return held

    def delete_capture(self, capture_id: str, *, actor: str, reason: str,
                       evidence: Mapping[str, str] | None = None) -> None:
        """Delete a capture with everything kept beside it (audited first; see
        :meth:`Store.delete_capture`, which raises the errors); a capture that is evidence
        (:meth:`evidence_captures`, or ``evidence`` when the caller deletes many and took it
        once) raises :class:`StateConflictError`."""
        with self.audit.failures(actor, "delete_capture", capture_id):
            store = self.store
            held = (self.evidence_captures() if evidence is None else evidence).get(capture_id)
            if held is not None:
                raise StateConflictError(f"capture {capture_id} is {held} and cannot be deleted")
            store.delete_capture(capture_id, actor=actor, reason=reason)
        _log.warning("capture deleted", extra={"capture_id": capture_id, "actor": actor,
                                                "reason": reason})

    def preview_png(self, capture_id: str) -> bytes:
        """A colour-coded height map (PNG) of a capture's stored cloud (errors as for
        :meth:`cloud_path`)."""
        return height_map_png(read_ply(self.cloud_path(capture_id)).points)

    # --- status -----------------------------------------------------------------------------

    def devices(self) -> list[DeviceStatus]:
        """Every device of the rig with its health, in opening order."""
        rig = self.rig
        with self._lock:
            faults = dict(self._faults)
        result = []
        for device in rig.devices:
            try:
                unit: str | None = rig.unit_of(device.id).id
            except KeyError:
                unit = None  # the trigger serves every unit
            details = device.describe()
            reason = faults.get(device.id)
            result.append(DeviceStatus(
                id=device.id, kind=device.kind, driver=str(details.get("driver", "")),
                unit=unit, open=device.is_open, health="ok" if reason is None else "fault",
                reason=reason, details=details))
        return result

    def device(self, device_id: str) -> DeviceStatus:
        """One device with its health; ``KeyError`` for an unknown id."""
        for device in self.devices():
            if device.id == device_id:
                return device
        raise KeyError(device_id)

    def configure_device(self, device_id: str, changes: Mapping[str, bool | float], *,
                         actor: str) -> DeviceStatus:
        """Change settings of one device on the acquisition worker and audit each change.

        ``changes`` maps settings to new values (:data:`~eyeserver.service.device_control.
        SETTINGS_BY_KIND`: a projector's ``enabled`` and ``intensity``, a camera's
        ``exposure_us`` and ``gain_db``); they are applied all or nothing, after the captures
        queued before, and each is recorded in the audit log under ``actor``. A device in fault
        is reopened first. Raises ``KeyError`` for an unknown device.

        Raises
        ------
        DeviceValueError
            A setting does not apply to the device's kind, or a value is out of its range.
        QueueFullError
            ``acquisition_queue`` jobs are already waiting.
        DeviceError
            The device failed; it is put in fault.
        """
        device = next((d for d in self.rig.devices if d.id == device_id), None)
        if device is None:
            raise KeyError(device_id)
        with self.audit.failures(actor, "configure_device", device_id):
            check_settings(device, changes)
            if changes:
                self.acquisition_worker.call(lambda: self._configure_now(device, changes, actor))
        return self.device(device_id)

    def _configure_now(self, device: Device, changes: Mapping[str, bool | float],
                       actor: str) -> None:
        self._recover([device])
        try:
            applied = apply_settings(device, changes)
        except DeviceValueError:
            raise
        except DeviceError as exc:
            self._mark_fault(exc)
            raise
        self.store.add_audit_entries(actor, "configure_device", device.id, [
            {"setting": c.setting, "old": c.old, "new": c.new} for c in applied])
        _log.info("device configured", extra={
            "device_id": device.id, "actor": actor,
            "changes": {c.setting: c.new for c in applied}})

    def status(self) -> ServiceStatus:
        """A snapshot of state, devices, units, active calibration and uptime."""
        rig = self.rig
        devices = self.devices()
        trigger_fault = next((d.reason for d in devices
                              if d.id == rig.trigger.id and d.reason is not None), None)
        units = []
        for unit in rig.units:
            members = {unit.projector.id, *(c.id for c in unit.cameras)}
            reasons = [f"{d.id}: {d.reason}" for d in devices
                       if d.id in members and d.reason is not None]
            if trigger_fault is not None:
                reasons.append(f"{rig.trigger.id}: {trigger_fault}")
            units.append(UnitStatus(id=unit.id, projector=unit.projector.id,
                                    cameras=tuple(c.id for c in unit.cameras),
                                    health="fault" if reasons else "ok",
                                    reason="; ".join(reasons) or None))
        active = self.store.active_calibration()
        return ServiceStatus(state=self.state, devices=tuple(devices), units=tuple(units),
                             active_calibration_id=None if active is None else active.id,
                             uptime_s=time.monotonic() - self._started,
                             version=eyeserver.__version__)
