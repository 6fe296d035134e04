"""Changing a device's settings from the API: which settings each kind takes, applied as one.

=============  ===========================================================================
kind           settings
=============  ===========================================================================
projector      ``enabled`` (bool), ``intensity`` (0 to 1)
camera         ``exposure_us`` (µs), ``gain_db`` (dB); ranges are the camera's own
trigger        none
=============  ===========================================================================

The ranges are checked where they always are, in the device's ``set_*`` methods
(:mod:`eyeserver.hardware.base`). A change of several settings is all or nothing: when one is
refused, the ones already applied are set back.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from eyeserver.errors import DeviceError, DeviceValueError
from eyeserver.hardware.base import Camera, Device, Projector

__all__ = ["SETTINGS_BY_KIND", "SettingChange", "apply_settings", "check_settings"]

SETTINGS_BY_KIND: dict[str, tuple[str, ...]] = {
    "projector": ("enabled", "intensity"),
    "camera": ("exposure_us", "gain_db"),
    "trigger": (),
}
"""The settings the API may change, by device kind."""


@dataclass(frozen=True)
class SettingChange:
    """One setting that was changed: from what to what (for the audit)."""

    setting: str
    old: bool | float
    new: bool | float


def check_settings(device: Device, changes: Mapping[str, object]) -> None:
    """Refuse settings that do not apply to ``device``'s kind, naming them.

    Raises
    ------
    DeviceValueError
        A setting in ``changes`` is not one of :data:`SETTINGS_BY_KIND` for the device's kind
        (the API answers 422).
    """
    allowed = SETTINGS_BY_KIND.get(device.kind, ())
    wrong = [name for name in changes if name not in allowed]
    if wrong:
        takes = f"it takes {', '.join(allowed)}" if allowed else "it takes none"
        verb = "does" if len(wrong) == 1 else "do"
        raise DeviceValueError(device.id, f"{', '.join(wrong)} {verb} not apply to a "
                                          f"{device.kind} ({takes})")


def _accessors(device: Device, setting: str
               ) -> tuple[Callable[[], bool | float], Callable[[bool | float], None]]:
    if isinstance(device, Projector):
        if setting == "enabled":
            return (lambda: device.enabled), (lambda v: device.set_enabled(bool(v)))
        if setting == "intensity":
            return (lambda: device.intensity), (lambda v: device.set_intensity(float(v)))
    if isinstance(device, Camera):
        if setting == "exposure_us":
            return (lambda: device.exposure_us), (lambda v: device.set_exposure_us(float(v)))
        if setting == "gain_db":
            return (lambda: device.gain_db), (lambda v: device.set_gain_db(float(v)))
    raise DeviceValueError(device.id, f"{setting} does not apply to a {device.kind}")


def apply_settings(device: Device, changes: Mapping[str, bool | float]) -> list[SettingChange]:
    """Apply ``changes`` to ``device`` in order; all or nothing.

    Returns
    -------
    list of SettingChange
        Every setting given, with its value before and after.

    Raises
    ------
    DeviceValueError
        A setting does not apply to the device, or a value is outside its range; nothing is
        changed.
    DeviceError
        The device failed; the settings applied before the failure are set back as far as the
        device allows.
    """
    check_settings(device, changes)
    applied: list[tuple[SettingChange, Callable[[bool | float], None]]] = []
    try:
        for setting, value in changes.items():
            get, put = _accessors(device, setting)
            old = get()
            put(value)
            applied.append((SettingChange(setting, old, get()), put))
    except DeviceError:
        for change, put in reversed(applied):
            with contextlib.suppress(DeviceError):  # the device already failed; report that
                put(change.old)
        raise
    return [change for change, _ in applied]
