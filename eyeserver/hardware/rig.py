"""The rig: every device of the room, grouped into optical units, opened and closed as one.

An optical unit is one projector and the cameras that film its fringes. :class:`Rig` owns the
devices' lifecycle (open in dependency order, close in reverse, roll back a half-open rig) and
runs triggered acquisitions: :meth:`Rig.acquire` lights the units in turn, one trigger pulse each
(interleaved frames, FORMATS.md), so a unit's cameras never see the other unit's fringes.

:class:`HardwareConfig` is the configuration that names the drivers; :func:`build_rig` turns it
into a :class:`Rig` through the driver registry.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Annotated, Final, Literal, Self

from pydantic import AfterValidator, Field, model_validator

from eyeserver.core.frames import Frame, is_valid_id
from eyeserver.core.validation import StrictModel
from eyeserver.errors import ConfigError, DeviceTimeoutError
from eyeserver.hardware.base import Camera, Device, Projector, Trigger, TriggerPulse, TriggerStep
from eyeserver.hardware.registry import DriverContext, create_device

__all__ = [
    "RIG_CAMERAS",
    "RIG_FORMAT",
    "AcquiredStep",
    "DeviceConfig",
    "HardwareConfig",
    "Rig",
    "TriggerConfig",
    "Unit",
    "UnitConfig",
    "build_rig",
]

RIG_FORMAT = "eyeserver.rig/1"
"""The ``format`` value of a rig file (FORMATS.md)."""

_log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Unit:
    """One optical unit: a projector and the cameras that film its fringes.

    Attributes
    ----------
    id : str
        Unit id (``"left"``, ``"right"``).
    projector : Projector
        The unit's fringe projector.
    cameras : tuple of Camera
        The unit's cameras, at least one.
    """

    id: str
    projector: Projector
    cameras: tuple[Camera, ...]


@dataclass(frozen=True)
class AcquiredStep:
    """The frames of one trigger pulse.

    Attributes
    ----------
    pulse : TriggerPulse
        The pulse that exposed the cameras (its step says what was lit and exposed).
    frames : dict of str to Frame
        Each exposed camera's frame, by camera id.
    """

    pulse: TriggerPulse
    frames: dict[str, Frame]


def _check_unique(what: str, ids: Iterable[str]) -> None:
    repeated = sorted(i for i, n in Counter(ids).items() if n > 1)
    if repeated:
        raise ConfigError(f"duplicate {what} id(s): {', '.join(repeated)}")


class Rig:
    """All devices of a room and their grouping into units.

    Parameters
    ----------
    cameras : sequence of Camera
        Every camera, in rig-file order.
    projectors : sequence of Projector
        Every projector, in rig-file order.
    trigger : Trigger
        The trigger/strobe controller that times all exposures.
    units : sequence of Unit
        The optical units; every camera and projector belongs to exactly one.

    Raises
    ------
    ConfigError
        For duplicate or malformed ids, a unit without cameras, a unit naming a device the rig
        does not hold, or a camera or projector in no unit or in more than one.

    Notes
    -----
    The rig is not opened by the constructor; use :meth:`open` / :meth:`close` or ``with rig:``.
    One acquisition runs at a time (a lock serialises :meth:`acquire` and :meth:`acquire_unlit`);
    they must not be mixed with a free-running trigger, which the caller's state machine prevents.
    """

    def __init__(self, cameras: Sequence[Camera], projectors: Sequence[Projector],
                 trigger: Trigger, units: Sequence[Unit]) -> None:
        self._cameras = tuple(cameras)
        self._projectors = tuple(projectors)
        self._trigger = trigger
        self._units = tuple(units)
        self._validate()
        self._camera_by_id = {c.id: c for c in self._cameras}
        self._projector_by_id = {p.id: p for p in self._projectors}
        self._unit_by_id = {u.id: u for u in self._units}
        self._lock = threading.Lock()

    def _validate(self) -> None:
        if not self._units:
            raise ConfigError("a rig needs at least one unit")
        _check_unique("device", [d.id for d in self.devices])
        _check_unique("unit", [u.id for u in self._units])
        for unit in self._units:
            if not is_valid_id(unit.id):
                raise ConfigError(f"unit id {unit.id!r} must be letters, digits, '-' or '_'")
            if not unit.cameras:
                raise ConfigError(f"unit {unit.id!r} has no camera")
        camera_units: dict[int, list[str]] = {id(c): [] for c in self._cameras}
        projector_units: dict[int, list[str]] = {id(p): [] for p in self._projectors}
        for unit in self._units:
            if id(unit.projector) not in projector_units:
                raise ConfigError(f"unit {unit.id!r}: projector {unit.projector.id!r} is not "
                                  "one of the rig's projectors")
            projector_units[id(unit.projector)].append(unit.id)
            for camera in unit.cameras:
                if id(camera) not in camera_units:
                    raise ConfigError(f"unit {unit.id!r}: camera {camera.id!r} is not one of "
                                      "the rig's cameras")
                camera_units[id(camera)].append(unit.id)
        for device, owners in [*((c, camera_units[id(c)]) for c in self._cameras),
                               *((p, projector_units[id(p)]) for p in self._projectors)]:
            if len(owners) != 1:
                where = f"units {', '.join(owners)}" if owners else "no unit"
                raise ConfigError(f"{device.kind} {device.id!r} belongs to {where}; "
                                  "it must belong to exactly one")

    @property
    def cameras(self) -> tuple[Camera, ...]:
        """Every camera, in configuration order."""
        return self._cameras

    @property
    def projectors(self) -> tuple[Projector, ...]:
        """Every projector, in configuration order."""
        return self._projectors

    @property
    def trigger(self) -> Trigger:
        """The trigger/strobe controller."""
        return self._trigger

    @property
    def units(self) -> tuple[Unit, ...]:
        """The optical units, in configuration order."""
        return self._units

    @property
    def devices(self) -> tuple[Device, ...]:
        """Every device in opening order: projectors, cameras, then the trigger."""
        return (*self._projectors, *self._cameras, self._trigger)

    @property
    def is_open(self) -> bool:
        """Whether every device is open."""
        return all(d.is_open for d in self.devices)

    def camera(self, camera_id: str) -> Camera:
        """The camera ``camera_id``; raises ``KeyError`` for an unknown id."""
        return self._camera_by_id[camera_id]

    def projector(self, projector_id: str) -> Projector:
        """The projector ``projector_id``; raises ``KeyError`` for an unknown id."""
        return self._projector_by_id[projector_id]

    def unit(self, unit_id: str) -> Unit:
        """The unit ``unit_id``; raises ``KeyError`` for an unknown id."""
        return self._unit_by_id[unit_id]

    def unit_of(self, device_id: str) -> Unit:
        """The unit a camera or projector belongs to; raises ``KeyError`` for an unknown id."""
        for unit in self._units:
            if unit.projector.id == device_id or any(c.id == device_id for c in unit.cameras):
                return unit
        raise KeyError(device_id)

    def open(self) -> None:
        """Open projectors, cameras, then the trigger (so no pulse reaches an unready device).

        On any failure the devices this call opened are closed again in reverse order and the
        error is re-raised, leaving the rig as it was. Devices already open stay open.
        """
        opened: list[Device] = []
        try:
            for device in self.devices:
                if not device.is_open:
                    device.open()
                    opened.append(device)
        except BaseException:
            _log.warning("rig open failed; closing %d device(s) opened so far", len(opened))
            self._close_devices(reversed(opened))
            raise

    def close(self) -> dict[str, Exception]:
        """Stop the trigger and close every device in reverse opening order.

        A device that fails to close does not stop the others: its error is logged and
        returned, never raised.

        Returns
        -------
        dict of str to Exception
            The errors by device id; empty when everything closed cleanly.
        """
        errors: dict[str, Exception] = {}
        try:
            self._trigger.stop()
        except Exception as exc:
            _log.warning("trigger %s failed to stop: %s", self._trigger.id, exc,
                         extra={"device_id": self._trigger.id})
            errors[self._trigger.id] = exc
        errors.update(self._close_devices(reversed(self.devices)))
        return errors

    @staticmethod
    def _close_devices(devices: Iterable[Device]) -> dict[str, Exception]:
        errors: dict[str, Exception] = {}
        for device in devices:
            try:
                device.close()
            except Exception as exc:
                _log.warning("%s %s failed to close: %s", device.kind, device.id, exc,
                             extra={"device_id": device.id})
                errors[device.id] = exc
        return errors

    def __enter__(self) -> Self:
        self.open()
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def _check_units(self, unit_ids: Sequence[str]) -> None:
        unknown = [u for u in unit_ids if u not in self._unit_by_id]
        if unknown:
            raise ValueError(f"unknown unit(s) {', '.join(map(repr, unknown))}; "
                             f"the rig has {', '.join(self._unit_by_id)}")

    def acquire(self, unit_ids: Sequence[str], timeout_s: float = 2.0, *,
                at_ns: int | None = None) -> list[AcquiredStep]:
        """Capture one interleaved frame set: one trigger pulse per unit, in the order given.

        Pulse ``n`` lights only unit ``n``'s projector and exposes only its cameras; the frames
        of a pulse are read before the next pulse is fired, so exposures never overlap and no
        unit's light leaks into another unit's images.

        Parameters
        ----------
        unit_ids : sequence of str
            Units to capture, each at most once.
        timeout_s : float
            Longest wait for each camera's frame, seconds.
        at_ns : int, optional
            Time the first pulse for this moment of the trigger's clock instead of now
            (:meth:`~eyeserver.hardware.base.Trigger.fire`): frames at a steady rate, with
            exact times. The call returns once the frames have arrived.

        Returns
        -------
        list of AcquiredStep
            One per unit, in the order of ``unit_ids``.

        Raises
        ------
        ValueError
            For no units, an unknown unit or a repeated one.
        DeviceError
            When a device fails (``DeviceTimeoutError`` for a frame that did not arrive).
        """
        if not unit_ids:
            raise ValueError("unit_ids must name at least one unit")
        self._check_units(unit_ids)
        if len(set(unit_ids)) != len(unit_ids):
            raise ValueError(f"unit_ids repeats a unit: {list(unit_ids)}")
        steps = [TriggerStep(projectors=(unit.projector.id,),
                             cameras=tuple(c.id for c in unit.cameras))
                 for unit in (self._unit_by_id[u] for u in unit_ids)]
        return self._run(steps, timeout_s, at_ns)

    def prepare_stream(self, unit_ids: Sequence[str]) -> None:
        """Get the cameras of ``unit_ids`` ready to stream, each lit by its unit's projector
        (:meth:`~eyeserver.hardware.base.Camera.prepare_stream`): call it once before a stream
        of :meth:`acquire` calls, so that its first frames come on time.

        Raises
        ------
        ValueError
            For an unknown unit.
        DeviceError
            When a camera fails.
        """
        self._check_units(unit_ids)
        with self._lock:
            for unit in (self._unit_by_id[u] for u in unit_ids):
                for camera in unit.cameras:
                    camera.prepare_stream((unit.projector.id,))

    def acquire_unlit(self, timeout_s: float = 2.0) -> AcquiredStep:
        """Capture every camera on one pulse that lights no projector (chessboards in room light).

        A projector switched to continuous mode stays lit; the frames' ``projectors_on`` says so.

        Parameters
        ----------
        timeout_s : float
            Longest wait for each camera's frame, seconds.
        """
        step = TriggerStep(projectors=(), cameras=tuple(c.id for c in self._cameras))
        return self._run([step], timeout_s)[0]

    def _run(self, steps: Sequence[TriggerStep], timeout_s: float, at_ns: int | None = None,
             ) -> list[AcquiredStep]:
        if timeout_s <= 0:
            raise ValueError(f"timeout_s must be positive, not {timeout_s}")
        with self._lock:
            # Setting the sequence restarts it, so pulse n is step n.
            self._trigger.set_sequence(steps)
            acquired: list[AcquiredStep] = []
            for n, step in enumerate(steps):
                for projector_id in step.projectors:  # a projector that is gone fails here
                    self._projector_by_id[projector_id].check()
                pulse = self._trigger.fire(at_ns if n == 0 else None)
                frames = {camera_id: self._frame_of(pulse, camera_id, timeout_s)
                          for camera_id in pulse.step.cameras}
                acquired.append(AcquiredStep(pulse=pulse, frames=frames))
            return acquired

    def _frame_of(self, pulse: TriggerPulse, camera_id: str, timeout_s: float) -> Frame:
        """The frame ``pulse`` exposed in camera ``camera_id``, matched by time.

        A frame's time is mid-exposure, after its pulse's. A frame from more than half the
        timeout before the pulse is a late frame of an earlier pulse that the rig already gave
        up on (its camera's queue kept it): it is discarded, so that it is never taken for this
        pulse's. No frame in time is a missed trigger, counted on the trigger
        (:meth:`~eyeserver.hardware.base.Trigger.record_missed`) before the timeout is raised.
        """
        camera = self._camera_by_id[camera_id]
        earliest_ns = pulse.t_ns - round(timeout_s * 1e9 / 2)
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                frame = camera.read_frame(max(deadline - time.monotonic(), 1e-3))
            except DeviceTimeoutError:
                self._trigger.record_missed(pulse, camera_id)
                raise
            if frame.meta.t_ns >= earliest_ns:
                return frame
            _log.warning("camera %s: discarded a late frame of an earlier pulse (%.3f s before "
                         "pulse %d)", camera_id, (pulse.t_ns - frame.meta.t_ns) / 1e9,
                         pulse.index, extra={"device_id": camera_id})

    def spec(self) -> dict[str, object]:
        """The rig file's content (FORMATS.md, ``eyeserver.rig/1``) as plain JSON-ready data."""
        return {
            "format": RIG_FORMAT,
            "cameras": [{"id": c.id, "width": c.width, "height": c.height}
                        for c in self._cameras],
            "projectors": [{"id": p.id} for p in self._projectors],
            "units": [{"id": u.id, "projector": u.projector.id,
                       "cameras": [c.id for c in u.cameras]} for u in self._units],
        }

    def describe(self) -> dict[str, object]:
        """Every device's :meth:`~eyeserver.hardware.base.Device.describe`, for status pages."""
        return {"units": [{"id": u.id, "projector": u.projector.id,
                           "cameras": [c.id for c in u.cameras]} for u in self._units],
                "devices": [d.describe() for d in self.devices]}


def _valid_id(value: str) -> str:
    if not is_valid_id(value):
        raise ValueError(f"id {value!r} must be 1–64 letters, digits, '-' or '_'")
    return value


DeviceId = Annotated[str, AfterValidator(_valid_id)]


class DeviceConfig(StrictModel):
    """A camera or projector: its id, driver and the driver's options."""

    kind: Literal["camera", "projector"]
    id: DeviceId
    driver: str = Field(description="registered driver name, e.g. SimCamera")
    options: dict[str, object] = Field(default_factory=dict,
                                       description="keyword arguments for the driver")


class TriggerConfig(StrictModel):
    """The trigger/strobe controller: its id, driver and the driver's options."""

    id: DeviceId
    driver: str = Field(description="registered driver name, e.g. SimTrigger")
    options: dict[str, object] = Field(default_factory=dict,
                                       description="keyword arguments for the driver")


class UnitConfig(StrictModel):
    """An optical unit: one projector and its cameras, by device id."""

    id: DeviceId
    projector: DeviceId
    cameras: list[DeviceId] = Field(min_length=1)


class HardwareConfig(StrictModel):
    """Which devices exist, which driver runs each, and how they group into units.

    Device ids are unique across cameras, projectors and the trigger; every camera and projector
    belongs to exactly one unit. Cameras and projectors keep their listed order in the rig.
    """

    devices: list[DeviceConfig]
    trigger: TriggerConfig
    units: list[UnitConfig] = Field(min_length=1)

    def device_ids(self) -> list[str]:
        """Every device's id, the trigger's included (a room with more devices adds theirs)."""
        return [d.id for d in self.devices] + [self.trigger.id]

    @model_validator(mode="after")
    def _check_grouping(self) -> Self:
        repeated = sorted(i for i, n in Counter(self.device_ids()).items() if n > 1)
        if repeated:
            raise ValueError(f"duplicate device id(s): {', '.join(repeated)}")
        repeated = sorted(i for i, n in Counter(u.id for u in self.units).items() if n > 1)
        if repeated:
            raise ValueError(f"duplicate unit id(s): {', '.join(repeated)}")
        kinds = {d.id: d.kind for d in self.devices}
        owners: dict[str, list[str]] = {d.id: [] for d in self.devices}
        for unit in self.units:
            for device_id, kind in [(unit.projector, "projector"),
                                    *((c, "camera") for c in unit.cameras)]:
                if kinds.get(device_id) != kind:
                    raise ValueError(f"unit {unit.id!r} names {kind} {device_id!r}, "
                                     f"which is not a configured {kind}")
                owners[device_id].append(unit.id)
        for device_id, units in owners.items():
            if len(units) != 1:
                where = f"units {', '.join(units)}" if units else "no unit"
                raise ValueError(f"{kinds[device_id]} {device_id!r} belongs to {where}; "
                                 "it must belong to exactly one")
        return self


RIG_CAMERAS: Final = "rig.cameras"
"""The resource under which :func:`build_rig` hands the trigger the rig's cameras by id (a
``dict[str, Camera]``), for a trigger that exposes them by software."""


def build_rig(config: HardwareConfig, context: DriverContext) -> Rig:
    """Create every configured device through the driver registry and group them into a rig.

    The devices are constructed, not opened.

    Parameters
    ----------
    config : HardwareConfig
        Devices, trigger and units.
    context : DriverContext
        Clock and shared resources handed to every driver.

    Raises
    ------
    ConfigError
        For an unknown driver, a bad option (naming the device) or an invalid grouping.
    """
    cameras: dict[str, Camera] = {}
    projectors: dict[str, Projector] = {}
    for entry in config.devices:
        device = create_device(entry.kind, entry.driver, entry.id, entry.options, context)
        if isinstance(device, Camera):
            cameras[entry.id] = device
        elif isinstance(device, Projector):
            projectors[entry.id] = device
        else:  # the registry checks kinds, so only a broken driver class ends up here
            raise ConfigError(f"device {entry.id!r}: driver {entry.driver} made a "
                              f"{type(device).__name__}, not a {entry.kind}")
    # A trigger that reaches its cameras by software (no trigger line) finds them here.
    trigger_context = DriverContext(clock=context.clock,
                                    resources={**context.resources, RIG_CAMERAS: dict(cameras)})
    trigger = create_device("trigger", config.trigger.driver, config.trigger.id,
                            config.trigger.options, trigger_context)
    if not isinstance(trigger, Trigger):
        raise ConfigError(f"device {config.trigger.id!r}: driver {config.trigger.driver} made a "
                          f"{type(trigger).__name__}, not a trigger")
    units = [Unit(id=u.id, projector=projectors[u.projector],
                  cameras=tuple(cameras[c] for c in u.cameras)) for u in config.units]
    return Rig(cameras=list(cameras.values()), projectors=list(projectors.values()),
               trigger=trigger, units=units)
