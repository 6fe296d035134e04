"""A whole treatment room of fake devices on this machine: two of Aravis's fake GigE Vision
cameras, an emulated Gardasoft LED controller and an emulated Zaber stage, with the room file
that names them, so that ``eyeserver serve`` runs on real drivers end to end (issue 38).

    sudo .venv/bin/python -m eyeserver.hardware.emulators.fakeroom      # until Ctrl-C
    .venv/bin/eyeserver serve --config deploy/examples/fake-room.toml   # in another shell

The devices:

==========  =====================================================  ==========================
id          what                                                   where
==========  =====================================================  ==========================
``S1``      fake GigE Vision camera, serial ``GV01``               ``127.0.0.1``
``S2``      fake GigE Vision camera, serial ``GV02``               ``127.0.0.2``
``P1``      channel 1 of an emulated Gardasoft RT260               ``DIR/led`` (a pty)
``T1``      the cameras' software trigger (``GenicamTrigger``)     —
``Z1``      an emulated Zaber linear stage, homed                  ``DIR/stage`` (a pty)
==========  =====================================================  ==========================

``DIR`` is :data:`FAKE_ROOM_DIR` unless given. A fake camera listens only on an address a
network interface has, one fake per address: the second needs ``127.0.0.2`` on the loopback
interface, which :class:`FakeRoom` adds (and removes again) when run as root, and otherwise
asks for. The room file it writes (``DIR/room.toml``) is the one
``deploy/examples/fake-room.toml`` names.
"""

from __future__ import annotations

import argparse
import contextlib
import ipaddress
import os
import signal
import subprocess
import threading
from pathlib import Path
from types import TracebackType
from typing import Final, Self

from eyeserver.hardware.emulators.fakegv import FakeGigECamera
from eyeserver.hardware.emulators.gardasoft import GardasoftEmulator
from eyeserver.hardware.emulators.zaber import ZaberEmulator

__all__ = ["CAMERA_ADDRESSES", "FAKE_ROOM_DIR", "MICROSTEP_MM", "FakeRoom", "room_file_text"]

FAKE_ROOM_DIR: Final = Path("/tmp/eyeserver-fake-room")
"""Where the fake room keeps its serial ports' links and its room file by default."""

CAMERA_ADDRESSES: Final = ("127.0.0.1", "127.0.0.2")
"""The fake cameras' addresses, S1 then S2."""

MICROSTEP_MM: Final = 0.000047625
"""The emulated stage's travel per microstep, mm (a Zaber X-LSM's 0.047625 µm)."""

STAGE_TRAVEL_MM: Final = 45.0
"""The emulated stage's travel, mm: the plate from Z = −15 to +30 mm, the simulated stage's."""

_ROI = {"width": 640, "height": 512}
"""The cameras' region: the rig's 640 × 512 of the fake's 2048 × 2048 sensor."""


def room_file_text(directory: Path) -> str:
    """The device room file (docs/room-file.md) of the fake room whose ports lie in
    ``directory``."""
    cameras = "".join(
        f'''
[[devices]]
kind = "camera"
id = "S{n}"
driver = "GenicamCamera"
options = {{ address = "{address}", trigger_source = "Software", width = {_ROI["width"]}, \
height = {_ROI["height"]} }}
''' for n, address in enumerate(CAMERA_ADDRESSES, start=1))
    return f'''# The fake room of eyeserver.hardware.emulators.fakeroom (written by it).
{cameras}
[[devices]]
kind = "projector"
id = "P1"
driver = "GardasoftProjector"
options = {{ port = "{directory / "led"}", channel = 1, max_current_a = 1.0, pulse_us = 8000, \
delay_us = 10 }}

[trigger]
id = "T1"
driver = "GenicamTrigger"

[[units]]
id = "left"
projector = "P1"
cameras = ["S1", "S2"]

[stage]
id = "Z1"
driver = "ZaberStage"
options = {{ port = "{directory / "stage"}", microstep_mm = {MICROSTEP_MM}, zero_mm = -15.0 }}
'''


def _has_address(address: str) -> bool:
    result = subprocess.run(["ip", "-o", "addr", "show", "dev", "lo"], capture_output=True,
                            text=True, check=False)
    return f" {address}/" in result.stdout


class FakeRoom:
    """The fake devices and their room file; started by ``with`` (or :meth:`start`), stopped
    by leaving it (or :meth:`stop`), every process, pty and address it made undone.

    Raises
    ------
    PermissionError
        On start, when ``127.0.0.2`` is not on the loopback interface and this is not root.
    FileNotFoundError
        On start, when Aravis's fake camera is not installed.
    """

    def __init__(self, directory: Path = FAKE_ROOM_DIR) -> None:
        self.directory = Path(directory)
        self.room_file = self.directory / "room.toml"
        self.cameras: list[FakeGigECamera] = []
        self.led: GardasoftEmulator | None = None
        self.stage: ZaberEmulator | None = None
        self._added_addresses: list[str] = []

    def start(self) -> None:
        """Start every fake device and write the room file."""
        self.directory.mkdir(parents=True, exist_ok=True)
        try:
            for address in CAMERA_ADDRESSES:
                if not ipaddress.ip_address(address).is_loopback:
                    raise ValueError(f"{address} is not a loopback address")
                if not _has_address(address):
                    if os.geteuid() != 0:
                        raise PermissionError(
                            f"the fake camera at {address} needs that address on the loopback "
                            f"interface: run as root, or first `ip addr add {address}/32 dev lo`")
                    subprocess.run(["ip", "addr", "add", f"{address}/32", "dev", "lo"],
                                   check=True)
                    self._added_addresses.append(address)
            for n, address in enumerate(CAMERA_ADDRESSES, start=1):
                camera = FakeGigECamera(address, serial=f"GV{n:02d}")
                camera.start()
                self.cameras.append(camera)
            self.led = GardasoftEmulator(link_dir=self.directory, name="led")
            self.led.start()
            self.stage = ZaberEmulator(homed=True, link_dir=self.directory, name="stage")
            self.stage.axis().limit_max = round(STAGE_TRAVEL_MM / MICROSTEP_MM)
            self.stage.start()
            self.room_file.write_text(room_file_text(self.directory))
        except BaseException:
            self.stop()
            raise

    def stop(self) -> None:
        """Stop every fake device and remove what :meth:`start` added. Idempotent."""
        for camera in self.cameras:
            camera.stop()
        self.cameras = []
        for emulator in (self.led, self.stage):
            if emulator is not None:
                emulator.stop()
        self.led = self.stage = None
        for address in self._added_addresses:
            subprocess.run(["ip", "addr", "del", f"{address}/32", "dev", "lo"], check=False)
        self._added_addresses = []
        with contextlib.suppress(FileNotFoundError):
            self.room_file.unlink()

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 traceback: TracebackType | None) -> None:
        self.stop()


def main() -> None:
    """Run the fake room until Ctrl-C (or SIGTERM)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--dir", type=Path, default=FAKE_ROOM_DIR,
                        help=f"where the ports' links and the room file go ({FAKE_ROOM_DIR})")
    args = parser.parse_args()
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    with FakeRoom(args.dir) as room:
        print(f"fake room up: cameras at {', '.join(CAMERA_ADDRESSES)}, LED controller "
              f"{args.dir / 'led'}, stage {args.dir / 'stage'}; room file {room.room_file}",
              flush=True)
        with contextlib.suppress(KeyboardInterrupt):
            done.wait()
    print("fake room stopped", flush=True)


if __name__ == "__main__":
    main()
