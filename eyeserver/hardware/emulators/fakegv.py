"""Aravis's fake GigE Vision camera (``arv-fake-gv-camera-0.8``) run on loopback, for the GenICam
driver's tests and for a daemon run on a fake camera (issue 38).

The fake is a real GigE Vision device as far as the network goes: it answers GVCP (the control
protocol, UDP port 3956) and streams images over GVSP, so the driver under test goes through
Aravis's whole network path. It is Aravis's own program (Debian package ``aravis-tools``), run
as a child process: :meth:`FakeGigECamera.kill` ends it at once, which is what a camera looks
like from the host when its cable or power goes, and :meth:`FakeGigECamera.start` brings a new
one up at the same address, a camera after a power cycle (its settings back at their defaults).

What the fake offers (Aravis 0.8.26): a 2048 × 2048 sensor, a 512 × 512 region by default,
pixel formats Mono8 and Mono16 (no Mono10/Mono12) and a few colour ones, ``ExposureTimeAbs``
(whole microseconds) and an integer ``GainRaw`` of 0 to 10, trigger sources ``Line0`` (never
fires: the fake has no lines) and ``Software``, timestamps from the host's real-time clock in
nanoseconds (tick frequency 1 GHz). It fills a diagonal ramp, pixel ``(x + y + frame id) % 255``
scaled by ``1 + gain + log10(exposure / 10 ms)``, which a test can check byte for byte. Its
``-r`` option drops that many GVSP packets per thousand at random, and it does not answer packet
resend requests, so a frame that lost a packet stays incomplete. It checks for a software
trigger once per 40 ms (its 25 Hz trigger loop), so a triggered frame comes 0 to 40 ms late.

Only one fake can listen on an address (the GVCP port is fixed) and it can only listen on an
address that a network interface has, so on loopback there is one: ``127.0.0.1``.
"""

from __future__ import annotations

import os
import shutil
import socket
import struct
import subprocess
import tempfile
import time
from types import TracebackType
from typing import IO, Self

__all__ = ["FAKE_CAMERA_PROGRAM", "GVCP_PORT", "FakeGigECamera", "find_fake_camera_program"]

FAKE_CAMERA_PROGRAM = "arv-fake-gv-camera-0.8"
"""Aravis's fake GigE Vision camera (Debian package ``aravis-tools``)."""

GVCP_PORT = 3956
"""The GigE Vision control protocol's UDP port, where every GigE Vision device listens."""

_GVCP_READREG_CMD = 0x0080
_GVCP_READREG_ACK = 0x0081
_GVCP_VERSION_REGISTER = 0x0000
_STOP_TIMEOUT_S = 3.0
"""How long :meth:`FakeGigECamera.stop` waits for the fake to quit before killing it."""


def find_fake_camera_program() -> str | None:
    """Path of ``arv-fake-gv-camera-0.8`` on ``PATH``, or None when ``aravis-tools`` is missing."""
    return shutil.which(FAKE_CAMERA_PROGRAM)


def gvcp_answers(address: str, timeout_s: float = 0.1) -> bool:
    """Whether a GigE Vision device answers a GVCP register read at ``address`` (port 3956).

    One read of the device's version register, over a throwaway UDP socket: a device answers
    register reads from any host, not only its controller, so this never disturbs the driver
    that controls it.
    """
    request_id = 1
    # GVCP command header: key 0x42, flags 0x01 (acknowledge), command, payload length, id.
    packet = struct.pack(">BBHHHI", 0x42, 0x01, _GVCP_READREG_CMD, 4, request_id,
                         _GVCP_VERSION_REGISTER)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.settimeout(timeout_s)
        try:
            # Connected, so that loopback's "port unreachable" ends the wait at once.
            probe.connect((address, GVCP_PORT))
            probe.send(packet)
            reply = probe.recv(64)
        except OSError:  # timeout, or connection refused: nobody listens
            return False
    if len(reply) < 8:
        return False
    _status, answer, _length, answer_id = struct.unpack(">HHHH", reply[:8])
    return bool(answer == _GVCP_READREG_ACK and answer_id == request_id)


class FakeGigECamera:
    """Runs ``arv-fake-gv-camera-0.8`` on a loopback address; a context manager.

    Parameters
    ----------
    interface : str
        Address the fake listens on; it must be an address of one of the machine's interfaces
        (``127.0.0.1`` on loopback). Drivers open the camera by this address.
    serial : str
        The fake's serial number; its Aravis device id is ``Aravis-Fake-<serial>``.
    packet_loss_per_mille : float
        GVSP packets (leader, payload, trailer) dropped per thousand, at random (``-r``).
    start_timeout_s : float
        How long :meth:`start` waits for the fake to answer GVCP, seconds.
    program : str or None
        The fake's executable; found on ``PATH`` by default.

    Raises
    ------
    FileNotFoundError
        When the program is not installed (``apt-get install aravis-tools``).
    """

    def __init__(self, interface: str = "127.0.0.1", *, serial: str = "GV01",
                 packet_loss_per_mille: float = 0.0, start_timeout_s: float = 5.0,
                 program: str | None = None) -> None:
        if not 0.0 <= packet_loss_per_mille <= 1000.0:
            raise ValueError(f"packet_loss_per_mille must be in [0, 1000], "
                             f"not {packet_loss_per_mille}")
        if start_timeout_s <= 0:
            raise ValueError(f"start_timeout_s must be positive, not {start_timeout_s}")
        found = program or find_fake_camera_program()
        if found is None:
            raise FileNotFoundError(f"{FAKE_CAMERA_PROGRAM} is not on PATH; install the Debian "
                                    "package aravis-tools (scripts/system-packages.sh)")
        self.program = found
        self.interface = interface
        self.serial = serial
        self.packet_loss_per_mille = float(packet_loss_per_mille)
        self.start_timeout_s = float(start_timeout_s)
        self._process: subprocess.Popen[bytes] | None = None
        self._log: IO[bytes] | None = None

    @property
    def address(self) -> str:
        """The camera's IP address, for the driver's ``address`` option."""
        return self.interface

    @property
    def device_id(self) -> str:
        """The camera's Aravis device id (``<vendor>-<model>-<serial>``), found by discovery:
        the other way to name it."""
        return f"Aravis-Fake-{self.serial}"

    @property
    def is_running(self) -> bool:
        """Whether the fake's process is alive."""
        return self._process is not None and self._process.poll() is None

    @property
    def pid(self) -> int | None:
        """The fake's process id while it runs."""
        return self._process.pid if self.is_running and self._process is not None else None

    def output(self) -> str:
        """What the fake has printed so far (its warnings, or why it failed to start)."""
        if self._log is None:
            return ""
        self._log.flush()
        self._log.seek(0)
        text = self._log.read().decode(errors="replace")
        self._log.seek(0, os.SEEK_END)
        return text

    def start(self) -> None:
        """Start the fake and wait until it answers GVCP; a fake that runs already is kept.

        Raises
        ------
        RuntimeError
            When another device already answers at the address (a fake left running: only one
            can listen there), or the fake exits or stays silent for ``start_timeout_s``.
        """
        if self.is_running:
            return
        self._reap()
        if gvcp_answers(self.interface):
            raise RuntimeError(f"a GigE Vision device already answers at {self.interface}:"
                               f"{GVCP_PORT} (another fake camera still running?)")
        # Kept open while the fake runs (its output, for errors); closed by _reap().
        self._log = tempfile.TemporaryFile(prefix="fakegv-")  # noqa: SIM115
        command = [self.program, "-i", self.interface, "-s", self.serial]
        if self.packet_loss_per_mille > 0:
            command += ["-r", repr(self.packet_loss_per_mille)]
        self._process = subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=self._log,
                                         stderr=subprocess.STDOUT)
        deadline = time.monotonic() + self.start_timeout_s
        while True:
            # It exits with status 0 when it cannot listen ("Failed to start camera").
            if self._process.poll() is not None:
                output = self.output().strip()
                self._reap()
                raise RuntimeError(f"{FAKE_CAMERA_PROGRAM} exited at start: "
                                   f"{output or 'no output'}")
            if gvcp_answers(self.interface):
                return
            if time.monotonic() > deadline:
                output = self.output().strip()
                self.kill()
                raise RuntimeError(f"{FAKE_CAMERA_PROGRAM} did not answer at {self.interface} "
                                   f"within {self.start_timeout_s} s: {output or 'no output'}")
            time.sleep(0.02)

    def kill(self) -> None:
        """End the fake at once (SIGKILL), as a camera whose power or cable goes. Idempotent."""
        if self._process is not None and self._process.poll() is None:
            self._process.kill()
        self._reap()

    def stop(self) -> None:
        """End the fake (SIGTERM; its own SIGINT handler takes up to a second), killing it if it
        does not go. Idempotent."""
        if self._process is not None and self._process.poll() is None:
            self._process.terminate()
            try:
                self._process.wait(_STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                self._process.kill()
        self._reap()

    def restart(self) -> None:
        """Kill the fake and start a new one at the same address (settings back to defaults)."""
        self.kill()
        self.start()

    def _reap(self) -> None:
        if self._process is not None:
            self._process.wait()
            self._process = None
        if self._log is not None:
            self._log.close()
            self._log = None

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 traceback: TracebackType | None) -> None:
        self.stop()
