"""Device drivers selected by name from the configuration.

A driver is a :class:`~eyeserver.hardware.base.Camera`,
:class:`~eyeserver.hardware.base.Projector`, :class:`~eyeserver.hardware.base.Trigger` or
:class:`~eyeserver.hardware.base.Stage` subclass registered under its kind and a name of the form
``<Vendor><Kind>`` (``SimCamera``, ``BaslerCamera``, ``TriggerBoxTrigger``, ``ZaberStage``)::

    @register_driver("camera", "SimCamera")
    class SimCamera(Camera):
        def __init__(self, device_id: str, *, context: DriverContext, queue_size: int = 8): ...

Every driver is constructed as ``Driver(device_id, context=context, **options)``: ``options`` are
the keyword arguments written in the configuration (serial port, queue size, ...), checked against
the constructor's signature so that a typo is a :class:`~eyeserver.errors.ConfigError` naming the
device rather than a ``TypeError`` deep inside a driver. ``context`` carries what the daemon shares
with all drivers: the clock and named resources such as the simulated room's wiring.
"""

from __future__ import annotations

import importlib
import inspect
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Final, Literal, TypeVar

from eyeserver.core.clock import Clock, MonotonicClock
from eyeserver.errors import ConfigError
from eyeserver.hardware.base import Camera, Device, Projector, Stage, Trigger

__all__ = [
    "DEVICE_KINDS",
    "DeviceKind",
    "DriverContext",
    "create_device",
    "driver_class",
    "known_drivers",
    "register_driver",
]

DeviceKind = Literal["camera", "projector", "trigger", "stage"]

# Typed as plain classes because mypy rejects abstract classes where type[Device] is expected.
DEVICE_KINDS: Final[dict[str, type[object]]] = {
    "camera": Camera,
    "projector": Projector,
    "trigger": Trigger,
    "stage": Stage,
}
"""Each device kind and the base class its drivers derive from."""

# Modules whose import registers the drivers that ship with eyeserver. They are imported on the
# first lookup rather than here so that importing the registry has no side effects and no cycle.
_BUILTIN_DRIVER_MODULES: Final[tuple[str, ...]] = (
    "eyeserver.hardware.sim.drivers",
    "eyeserver.hardware.drivers.basler",
    "eyeserver.hardware.drivers.gardasoft",
    "eyeserver.hardware.drivers.genicam",
    "eyeserver.hardware.drivers.ids",
    "eyeserver.hardware.drivers.modbus",
    "eyeserver.hardware.drivers.softtrigger",
    "eyeserver.hardware.drivers.triggerbox",
    "eyeserver.hardware.drivers.zaber",
)

_T = TypeVar("_T")
_D = TypeVar("_D", bound=Device)

_registry: dict[str, dict[str, type[Device]]] = {kind: {} for kind in DEVICE_KINDS}
_lock = threading.Lock()
_builtins_loaded = False


@dataclass(frozen=True)
class DriverContext:
    """What every driver may use besides its own options.

    Attributes
    ----------
    clock : Clock
        The rig's monotonic clock; drivers time-stamp frames and pulses on it.
    resources : Mapping[str, object]
        Shared objects by name, for drivers that must meet each other outside the interfaces
        (the simulated drivers find their room and wiring here under ``"sim.wiring"``).
    """

    clock: Clock = field(default_factory=MonotonicClock)
    resources: Mapping[str, object] = field(default_factory=dict)

    def resource(self, name: str, expected: type[_T]) -> _T:
        """Return the resource ``name``, checking its type.

        Parameters
        ----------
        name : str
            Key in :attr:`resources`.
        expected : type
            The class the resource must be an instance of.

        Raises
        ------
        ConfigError
            When the resource is missing or of another type.
        """
        value = self.resources.get(name)
        if value is None:
            raise ConfigError(f"the driver context has no resource {name!r}")
        if not isinstance(value, expected):
            raise ConfigError(f"resource {name!r} is a {type(value).__name__}, "
                              f"not a {expected.__name__}")
        return value


def _check_kind(kind: str) -> type[object]:
    base = DEVICE_KINDS.get(kind)
    if base is None:
        raise ConfigError(f"unknown device kind {kind!r}; known kinds: {', '.join(DEVICE_KINDS)}")
    return base


def register_driver(kind: DeviceKind, name: str) -> Callable[[type[_D]], type[_D]]:
    """Class decorator that registers a driver under ``kind`` and ``name``.

    Parameters
    ----------
    kind : {"camera", "projector", "trigger", "stage"}
        The device kind; the class must derive from the matching base class.
    name : str
        ``<Vendor><Kind>``, e.g. ``"SimCamera"``; unique within the kind.

    Raises
    ------
    ValueError
        For a malformed name, or a name already taken by another class.
    TypeError
        When the class does not derive from the kind's base class.
    """
    base = DEVICE_KINDS.get(kind)
    if base is None:
        raise ValueError(f"unknown device kind {kind!r}; known kinds: {', '.join(DEVICE_KINDS)}")
    suffix = kind.capitalize()
    if not (name.isidentifier() and name.endswith(suffix) and len(name) > len(suffix)
            and name[0].isupper()):
        raise ValueError(f"driver name {name!r} must read <Vendor>{suffix}, e.g. Sim{suffix}")

    def decorate(cls: type[_D]) -> type[_D]:
        if not issubclass(cls, base):
            raise TypeError(f"{cls.__qualname__} is registered as a {kind} driver but does not "
                            f"derive from {base.__name__}")
        with _lock:
            existing = _registry[kind].get(name)
            # The same class arriving again (a module re-imported by a test runner) is harmless.
            if existing is not None and (existing.__module__, existing.__qualname__) != (
                    cls.__module__, cls.__qualname__):
                raise ValueError(f"{kind} driver name {name!r} is already taken by "
                                 f"{existing.__module__}.{existing.__qualname__}")
            _registry[kind][name] = cls
        return cls

    return decorate


def _load_builtin_drivers() -> None:
    global _builtins_loaded
    if _builtins_loaded:
        return
    for module in _BUILTIN_DRIVER_MODULES:
        importlib.import_module(module)
    _builtins_loaded = True


def known_drivers(kind: str) -> list[str]:
    """Sorted names of the drivers registered for ``kind``.

    Raises
    ------
    ConfigError
        For an unknown kind.
    """
    _check_kind(kind)
    _load_builtin_drivers()
    with _lock:
        return sorted(_registry[kind])


def driver_class(kind: str, driver: str) -> type[Device]:
    """The class registered as ``driver`` for ``kind``.

    Raises
    ------
    ConfigError
        For an unknown kind or driver; the message lists the known drivers of that kind.
    """
    _check_kind(kind)
    _load_builtin_drivers()
    with _lock:
        cls = _registry[kind].get(driver)
    if cls is None:
        known = ", ".join(known_drivers(kind)) or "none"
        raise ConfigError(f"unknown {kind} driver {driver!r}; known {kind} drivers: {known}")
    return cls


def _check_options(cls: type[Device], device_id: str, driver: str,
                   options: Mapping[str, object]) -> None:
    parameters = list(inspect.signature(cls).parameters.values())
    reserved = {"device_id", "context"}
    accepts_any = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters)
    named = {p.name: p for p in parameters
             if p.kind in (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
             and p.name not in reserved}
    unexpected = sorted(set(options) - set(named)) if not accepts_any else []
    unexpected += sorted(set(options) & reserved)
    if unexpected:
        accepted = ", ".join(sorted(named)) or "none"
        raise ConfigError(f"device {device_id!r} (driver {driver}): unexpected option(s) "
                          f"{', '.join(unexpected)}; accepted options: {accepted}")
    missing = sorted(name for name, p in named.items()
                     if p.default is inspect.Parameter.empty and name not in options)
    if missing:
        raise ConfigError(f"device {device_id!r} (driver {driver}): missing option(s) "
                          f"{', '.join(missing)}")


def create_device(kind: str, driver: str, device_id: str, options: Mapping[str, object],
                  context: DriverContext) -> Device:
    """Construct (but do not open) a device from its configuration.

    Parameters
    ----------
    kind : {"camera", "projector", "trigger", "stage"}
        The device kind.
    driver : str
        Registered driver name, e.g. ``"SimCamera"``.
    device_id : str
        The device's id (letters, digits, ``-``, ``_``).
    options : Mapping[str, object]
        Keyword arguments for the driver's constructor.
    context : DriverContext
        Clock and shared resources.

    Returns
    -------
    Device
        An instance of the driver class, not yet opened.

    Raises
    ------
    ConfigError
        For an unknown kind or driver (listing the known ones), an option the driver does not
        take, a missing required option, or an option value the driver rejects; the message
        names ``device_id``.
    """
    cls = driver_class(kind, driver)
    _check_options(cls, device_id, driver, options)
    try:
        return cls(device_id, context=context, **options)  # type: ignore[call-arg]
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"device {device_id!r} (driver {driver}): {exc}") from exc
