"""One exception tree for the whole of eyeserver.

::

    EyeserverError
    ├── FormatError            a file breaks its format or schema (names the file and field)
    ├── ConfigError            the daemon's configuration is invalid
    ├── NotBuiltError          a part of the product that does not exist yet was asked for
    ├── StateConflictError     the request conflicts with the daemon's current state (HTTP 409)
    └── DeviceError            a device failed (HTTP 503 unless a subclass says otherwise)
        ├── DeviceNotOpenError       used before ``open()`` or after ``close()``
        ├── DeviceDisconnectedError  the device went away; reopening may recover it
        ├── DeviceTimeoutError       no answer / no frame within the timeout (HTTP 504)
        └── DeviceValueError         a setting out of the device's range (HTTP 422)

Drivers translate vendor and transport errors into these at their boundary (``raise … from exc``);
the API maps them to status codes in one place.
"""

from __future__ import annotations

from pathlib import Path


class EyeserverError(Exception):
    """Base class of every error eyeserver raises on purpose."""


class FormatError(EyeserverError):
    """A file does not follow its documented format.

    The message always names the file and, where there is one, the offending field, so a user can
    open the file and fix it without reading code.
    """

    def __init__(self, path: str | Path, field: str | None, reason: str) -> None:
        self.path = str(path)
        self.field = field
        self.reason = reason
        where = f"{self.path}: field '{field}'" if field else self.path
        super().__init__(f"{where}: {reason}")


class ConfigError(EyeserverError):
    """The daemon's configuration cannot be used."""


class NotBuiltError(EyeserverError):
    """A feature that is planned but not implemented yet was requested."""


class StateConflictError(EyeserverError):
    """The request conflicts with what the daemon is doing now."""


class DeviceError(EyeserverError):
    """A device failed; ``device_id`` names it."""

    def __init__(self, device_id: str, reason: str) -> None:
        self.device_id = device_id
        self.reason = reason
        super().__init__(f"{device_id}: {reason}")


class DeviceNotOpenError(DeviceError):
    """The device was used while closed."""


class DeviceDisconnectedError(DeviceError):
    """The device stopped answering or was unplugged."""


class DeviceTimeoutError(DeviceError):
    """The device did not deliver within the allowed time."""


class DeviceValueError(DeviceError, ValueError):
    """A setting lies outside the device's documented range."""
