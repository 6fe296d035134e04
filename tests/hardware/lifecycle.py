"""What every device of the contract suite must do alike, whatever its kind."""

from __future__ import annotations

from eyeserver.hardware.base import Device


def check_open_close_idempotent(device: Device) -> None:
    """``open`` and ``close`` each twice in a row: no error, and ``is_open`` follows."""
    assert not device.is_open
    device.open()
    device.open()
    assert device.is_open
    device.close()
    device.close()
    assert not device.is_open
