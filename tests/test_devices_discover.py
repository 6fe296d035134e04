"""``eyeserver devices discover`` (issue 38) against the device emulators: a Gardasoft LED
controller, a chain of Zaber devices and an Opto Modbus RTU controller, each on a pty given with
``--port`` (the system's port list has no ptys), and Aravis's fake GigE Vision camera on
127.0.0.1.

What it shows: without ``--probe`` not one byte reaches a port, and no port is even opened;
with it each controller is named, with a room-file entry whose options construct and open the
driver on that very emulator; a port another process holds is left alone, and one that cannot be
opened is reported, not raised; no probe leaves a port open. The machine's own serial ports are
replaced by an empty list (or a made-up one) in every test: a test never sends bytes to a real
port. The camera tests are skipped, saying why, where Aravis's fake camera or PyGObject is
missing; the rest need nothing but Linux ptys.
"""

from __future__ import annotations

import errno
import json
import os
import subprocess
import sys
import time
import tomllib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, ClassVar

import pytest
import serial
from serial.tools import list_ports
from serial.tools.list_ports_common import ListPortInfo

from eyeserver import cli
from eyeserver.commands import devices as devices_commands
from eyeserver.hardware import discovery
from eyeserver.hardware.base import Device
from eyeserver.hardware.discovery import ModbusSettings, RoomSnippet, discover, probe_port
from eyeserver.hardware.drivers import genicam
from eyeserver.hardware.emulators.fakegv import FakeGigECamera
from eyeserver.hardware.emulators.gardasoft import GardasoftEmulator
from eyeserver.hardware.emulators.modbus import OptoController, OptoRtuEmulator
from eyeserver.hardware.emulators.serialpty import Behaviour, SerialPtyEmulator
from eyeserver.hardware.emulators.zaber import ZaberEmulator
from eyeserver.hardware.registry import DriverContext, create_device
from tests.hardware.needs import needs_aravis

TIMEOUT_S = 0.1
"""Each probe's wait: the emulators answer at once."""

TIMEOUT = ["--timeout", str(TIMEOUT_S)]

# What the user adds to the entries' options (the to_set lists): values the emulators take.
USER_OPTIONS: dict[str, dict[str, object]] = {
    "GardasoftProjector": {"channel": 1, "max_current_a": 1.0, "pulse_us": 8000, "delay_us": 10,
                           "timeout_s": 0.2},
    "OptoProjector": {"channel": 1, "max_current_ma": 1000, "pulse_us": 8000, "delay_us": 10,
                      "timeout_s": 0.2},
    "ZaberStage": {"microstep_mm": 0.000047625, "timeout_s": 0.2},
}


# --- emulators and helpers ------------------------------------------------------------------


class Recording(SerialPtyEmulator):
    """Keeps every byte an emulator reads from its pty, terminated or not (``received`` holds
    only whole commands): every byte read passes ``_feed``."""

    raw: bytes = b""

    def _feed(self, data: bytes) -> None:
        self.raw += data
        super()._feed(data)


class RecordingGardasoft(Recording, GardasoftEmulator):
    pass


class RecordingOptoRtu(Recording, OptoRtuEmulator):
    pass


class ZaberChain(ZaberEmulator):
    """Two Zaber devices daisy-chained on one port, addresses 1 and 2: both answer a broadcast.
    Device 1 has firmware 7 (``get device.id``), device 2 firmware 6 (``get deviceid``; it
    rejects ``device.id`` with BADCOMMAND)."""

    PRODUCT_IDS: ClassVar[dict[int, tuple[str, int]]] = {1: ("device.id", 50081),
                                                          2: ("deviceid", 50419)}

    def __init__(self, *, link_dir: Path) -> None:
        super().__init__(address=1, homed=True, link_dir=link_dir, name="zaber-chain")
        self.second = ZaberEmulator(address=2, homed=True)  # only its reply(): never started

    def reply(self, command: str) -> bytes | None:
        words = command.removeprefix("/").split()
        if len(words) == 3 and words[0].isdigit() and words[1] == "get":
            address = int(words[0])
            setting, product_id = self.PRODUCT_IDS.get(address, ("", 0))
            if words[2] == setting:
                return f"@{address:02d} 0 OK IDLE -- {product_id}\r\n".encode()
        answers = [super().reply(command), self.second.reply(command)]
        return b"".join(answer for answer in answers if answer) or None


@pytest.fixture(autouse=True)
def no_system_ports(monkeypatch: pytest.MonkeyPatch) -> None:
    """The machine's own serial ports are never listed, so never probed, by these tests."""
    monkeypatch.setattr(list_ports, "comports", lambda *args, **kwargs: [])


@pytest.fixture
def run(monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> Callable[..., tuple[int, str, str]]:
    """Run the command line; its status, stdout and stderr."""
    if devices_commands.add_parser not in cli.REGISTRARS:  # until cli.py lists it
        monkeypatch.setattr(cli, "REGISTRARS", [*cli.REGISTRARS, devices_commands.add_parser])

    def run_cli(*argv: str) -> tuple[int, str, str]:
        status = cli.main(["devices", "discover", *argv])
        captured = capsys.readouterr()
        return status, captured.out, captured.err

    return run_cli


def run_json(run: Callable[..., tuple[int, str, str]], *argv: str) -> dict[str, Any]:
    status, out, err = run(*argv, "--json")
    assert status == 0, err
    document: dict[str, Any] = json.loads(out)
    return document


def ports_of(document: dict[str, Any]) -> dict[str, dict[str, Any]]:
    return {port["device"]: port for port in document["serial_ports"]}


def open_fds_to(path: str) -> int:
    """How many of this process's file descriptors are open on the device behind ``path``."""
    target = os.path.realpath(path)
    count = 0
    for fd in os.listdir("/proc/self/fd"):
        try:
            if os.path.realpath(f"/proc/self/fd/{fd}") == target:
                count += 1
        except OSError:
            continue
    return count


def construct(entry: dict[str, Any]) -> Device:
    """The driver a room-file entry names, built from its options and what the user adds,
    as the daemon builds it from a room file; its TOML parses to the same entry."""
    table = tomllib.loads(entry["toml"])
    parsed = table["devices"][0] if entry["table"] == "devices" else table["stage"]
    assert (parsed["id"], parsed["driver"], parsed["options"]) == (
        entry["id"], entry["driver"], entry["options"])
    assert parsed.get("kind", "stage") == entry["kind"]
    extra = USER_OPTIONS.get(entry["driver"], {})
    assert set(entry["to_set"]) <= set(extra), entry["to_set"]
    return create_device(entry["kind"], entry["driver"], entry["id"],
                         {**entry["options"], **extra}, DriverContext())


# --- without --probe: not a byte ------------------------------------------------------------


def test_without_probe_no_port_is_opened_and_no_byte_sent(
        tmp_path: Path, run: Callable[..., tuple[int, str, str]],
        monkeypatch: pytest.MonkeyPatch) -> None:
    opened: list[str] = []
    monkeypatch.setattr(serial, "serial_for_url",
                        lambda url, *args, **kwargs: opened.append(url))
    with RecordingGardasoft(link_dir=tmp_path) as led, RecordingOptoRtu(link_dir=tmp_path) as opto:
        document = run_json(run, "--no-cameras", "--port", led.port, "--port", opto.port,
                            "--port", str(tmp_path / "ttyGONE"))
        time.sleep(0.2)  # time for the emulators' threads to read anything that was sent
        assert (led.raw, opto.raw) == (b"", b"")
    assert opened == []
    assert document["probed"] is False and document["cameras"] is None
    ports = ports_of(document)
    assert list(ports) == [led.port, opto.port, str(tmp_path / "ttyGONE")]
    assert all(port["probe"] is None and port["listed_by"] == "given" for port in ports.values())
    assert [port["present"] for port in ports.values()] == [True, True, False]

    status, out, _ = run("--no-cameras", "--port", led.port)
    assert status == 0
    assert "not probed" in out and "Not probed: --probe" in out
    assert "No device found for a room file." in out


def test_help_says_probe_sends_bytes_and_the_defaults(
        run: Callable[..., tuple[int, str, str]]) -> None:
    status, out, _ = run("--help")
    assert status == 0
    text = " ".join(out.split())
    assert "SENDS BYTES to every port listed" in text and "never the default" in text
    assert f"(default {discovery.DEFAULT_TIMEOUT_S:g})" in text
    defaults = ModbusSettings()
    # The command's help states the discovery module's defaults without importing it.
    shown = (devices_commands.DEFAULT_TIMEOUT_S, devices_commands.MODBUS_UNIT_ID,
             devices_commands.MODBUS_BAUDRATE, devices_commands.MODBUS_PARITY)
    assert shown == (discovery.DEFAULT_TIMEOUT_S, defaults.unit_id, defaults.baudrate,
                     defaults.parity)
    assert run("--timeout", "0")[0] == 2
    assert run("--modbus-unit", "300")[0] == 2


# --- with --probe ---------------------------------------------------------------------------


def test_probe_names_each_controller_with_an_entry_that_opens_it(
        tmp_path: Path, run: Callable[..., tuple[int, str, str]]) -> None:
    with GardasoftEmulator(link_dir=tmp_path) as led, ZaberChain(link_dir=tmp_path) as chain, \
            OptoRtuEmulator(OptoController(device_type=0x0804), link_dir=tmp_path) as opto:
        document = run_json(run, "--no-cameras", "--probe", *TIMEOUT, "--modbus-parity", "N",
                            "--port", led.port, "--port", chain.port, "--port", opto.port)
        assert document["probed"] is True
        ports = ports_of(document)

        found = ports[led.port]["probe"]
        assert found["problem"] is None
        [controller] = found["controllers"]
        assert controller["name"] == "Gardasoft RT controller"
        assert controller["identification"] == led.model
        entry = controller["room_file"]
        assert (entry["table"], entry["kind"], entry["id"], entry["driver"]) == (
            "devices", "projector", "P1", "GardasoftProjector")
        assert entry["options"] == {"port": led.port}
        assert entry["to_set"] == ["channel", "max_current_a", "pulse_us", "delay_us"]
        assert led.received == ["VR"]  # one harmless query, then nothing else

        found = ports[chain.port]["probe"]
        assert [(c["identification"], c["room_file"]["id"], c["room_file"]["options"])
                for c in found["controllers"]] == [
            ("device 1, product id 50081", "Z1", {"port": chain.port, "address": 1}),
            ("device 2, product id 50419", "Z2", {"port": chain.port, "address": 2})]
        assert {c["room_file"]["table"] for c in found["controllers"]} == {"stage"}
        assert found["controllers"][0]["room_file"]["to_set"] == ["microstep_mm"]
        # The Gardasoft probe's VR is ignored by Zaber devices; then the broadcast, and each
        # device's product id by its firmware's name for it.
        assert chain.received == ["VR", "/", "/1 get device.id", "/2 get device.id",
                                  "/2 get deviceid"]

        found = ports[opto.port]["probe"]
        [controller] = found["controllers"]
        assert controller["identification"] == (
            "DEVICE_TYPE 0x0804, firmware boot 0x0100, MCU 0x0110, FPGA 0x0003")
        assert controller["room_file"]["options"] == {"transport": "rtu", "port": opto.port,
                                                      "parity": "N"}
        assert all(request.function == 0x03 for request in opto.controller.requests)

        # Each entry, completed with what only the user knows, opens its device.
        entries = [c["room_file"] for port in ports.values() for c in port["probe"]["controllers"]]
        assert [entry["id"] for entry in entries] == ["P1", "Z1", "Z2", "P2"]
        for entry in entries:
            device = construct(entry)
            device.open()
            try:
                assert device.is_open
            finally:
                device.close()


def test_the_report_lists_ports_and_room_file_entries(
        tmp_path: Path, run: Callable[..., tuple[int, str, str]]) -> None:
    with GardasoftEmulator(link_dir=tmp_path) as led, \
            OptoRtuEmulator(link_dir=tmp_path) as opto:
        status, out, err = run("--no-cameras", "--probe", *TIMEOUT, "--port", led.port,
                               "--port", opto.port)
    assert status == 0
    assert f"probing {led.port}" in err and "Traceback" not in err
    rows = {line.split()[0]: line for line in out.splitlines() if line.startswith("  /")}
    assert rows[led.port].endswith(f"Gardasoft RT controller: {led.model}")
    # The Modbus probe asks at even parity by default, which a pty refuses: said, not raised.
    assert rows[opto.port].endswith("no known controller answered")
    assert f"{opto.port}: Modbus RTU probe not run" in out and "parity N" in out
    entries = out.split("Room-file entries (docs/room-file.md, 'A room of real devices'):")[1]
    assert tomllib.loads(entries)["devices"] == [{
        "kind": "projector", "id": "P1", "driver": "GardasoftProjector",
        "options": {"port": led.port}}]
    assert "# add to options: channel, max_current_a, pulse_us, delay_us" in entries


@pytest.mark.parametrize("behaviour", [Behaviour.SILENT, Behaviour.GARBAGE])
def test_a_port_without_a_known_controller_finds_nothing_quickly(
        tmp_path: Path, behaviour: Behaviour) -> None:
    with GardasoftEmulator(link_dir=tmp_path) as led:
        led.behaviour = behaviour
        started = time.monotonic()
        found = probe_port(led.port, timeout_s=TIMEOUT_S,
                           modbus_settings=ModbusSettings(parity="N"))
        elapsed = time.monotonic() - started
    assert (found.controllers, found.problem, found.notes) == ([], None, [])
    assert elapsed < 1.0  # three probes of about TIMEOUT_S each


def test_no_probe_leaves_a_port_open(tmp_path: Path) -> None:
    with GardasoftEmulator(link_dir=tmp_path) as led, ZaberChain(link_dir=tmp_path) as chain, \
            OptoRtuEmulator(link_dir=tmp_path) as opto, \
            GardasoftEmulator(link_dir=tmp_path, name="silent") as silent:
        silent.behaviour = Behaviour.SILENT
        for port in (led.port, chain.port, opto.port, silent.port):
            before = open_fds_to(port)  # the emulator's own hold on its pty
            for parity in ("N", "E"):  # found, or not; the Modbus port opened, or refused
                found = probe_port(port, timeout_s=TIMEOUT_S,
                                   modbus_settings=ModbusSettings(parity=parity))
                assert found.problem is None
            assert open_fds_to(port) == before, port


def test_a_port_another_process_holds_is_not_probed(
        tmp_path: Path, run: Callable[..., tuple[int, str, str]]) -> None:
    with RecordingGardasoft(link_dir=tmp_path) as led:
        fd = os.open(led.port, os.O_RDWR | os.O_NOCTTY)
        try:
            holder = subprocess.Popen(["sleep", "30"], stdin=fd)
        finally:
            os.close(fd)
        try:
            document = run_json(run, "--no-cameras", "--probe", *TIMEOUT, "--port", led.port)
            time.sleep(0.1)
            assert led.raw == b""
        finally:
            holder.kill()
            holder.wait()
        probe = ports_of(document)[led.port]["probe"]
        assert probe["controllers"] == []
        assert probe["problem"].startswith(f"busy: open in process {holder.pid} (sleep)")

        document = run_json(run, "--no-cameras", "--probe", *TIMEOUT, "--port", led.port)
        assert ports_of(document)[led.port]["probe"]["controllers"] != []  # free again


def test_ports_that_cannot_be_opened_are_reported_not_raised(
        tmp_path: Path, run: Callable[..., tuple[int, str, str]],
        monkeypatch: pytest.MonkeyPatch) -> None:
    not_a_tty = tmp_path / "notes.txt"
    not_a_tty.write_text("not a serial port\n")
    denied = tmp_path / "ttyDENIED"
    denied.write_text("")
    real_serial_for_url = serial.serial_for_url

    def serial_for_url(url: str, *args: Any, **kwargs: Any) -> Any:
        if url == str(denied):  # as pyserial fails without read-write access (root has it)
            raise serial.SerialException(errno.EACCES, f"could not open port {url}: [Errno 13] "
                                                       f"Permission denied: {url!r}")
        return real_serial_for_url(url, *args, **kwargs)

    monkeypatch.setattr(serial, "serial_for_url", serial_for_url)
    paths = [str(tmp_path / "ttyGONE"), str(not_a_tty), str(tmp_path), str(denied)]
    document = run_json(run, "--no-cameras", "--probe", *TIMEOUT,
                        *(arg for path in paths for arg in ("--port", path)))
    problems = {device: port["probe"]["problem"]
                for device, port in ports_of(document).items()}
    assert problems == {
        paths[0]: "missing: no device at this path (unplugged?)",
        paths[1]: "not a serial port (not a terminal device)",
        paths[2]: "not a serial port (not a terminal device)",
        paths[3]: ("access denied: the user needs read and write access to the port (on "
                   "Debian, membership of the 'dialout' group; log in again after adding it)")}


def test_a_system_port_is_named_by_its_by_id_link(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    by_id = tmp_path / "by-id"
    by_id.mkdir()
    with GardasoftEmulator(link_dir=tmp_path) as led:
        device = os.path.realpath(led.port)  # /dev/pts/N, as comports() would name it
        link = by_id / "usb-FTDI_FT232R_USB_UART_A10K7QJX-if00-port0"
        link.symlink_to(device)
        info = ListPortInfo(device, skip_link_detection=True)
        info.vid, info.pid, info.serial_number = 0x0403, 0x6001, "A10K7QJX"
        info.manufacturer, info.description = "FTDI", "FT232R USB UART"
        monkeypatch.setattr(list_ports, "comports", lambda *args, **kwargs: [info])

        found = discover(cameras=False, ports=[str(link)], probe=True, timeout_s=TIMEOUT_S,
                         by_id_dir=by_id)
    assert found.serial_ports is not None
    [port] = found.serial_ports  # the link given names the same port: listed once
    assert (port.device, port.by_id, port.usb_id, port.serial_number, port.description,
            port.listed_by) == (device, str(link), "0403:6001", "A10K7QJX", "FT232R USB UART",
                                "system")
    [snippet] = found.snippets()
    assert snippet.options == {"port": str(link)}


# --- cameras --------------------------------------------------------------------------------




@pytest.fixture
def fake() -> Iterator[FakeGigECamera]:
    with FakeGigECamera() as camera:
        yield camera


def check_camera_entry(entry: dict[str, Any], fake: FakeGigECamera) -> None:
    snippet = entry["room_file"]
    assert (snippet["kind"], snippet["id"], snippet["driver"], snippet["options"],
            snippet["to_set"]) == ("camera", "S1", "GenicamCamera", {"address": fake.address}, [])
    camera = construct(snippet)
    assert isinstance(camera, genicam.GenicamCamera) and camera.address == fake.address


@needs_aravis
def test_the_broadcast_finds_the_fake_camera_on_loopback(
        fake: FakeGigECamera, run: Callable[..., tuple[int, str, str]]) -> None:
    document = run_json(run, "--no-serial")
    assert document["serial_ports"] is None
    search = document["cameras"]
    assert search["searched"] is True and search["unavailable"] is None
    [entry] = [camera for camera in search["cameras"] if camera["address"] == fake.address]
    assert {key: entry[key] for key in ("device_id", "vendor", "model", "serial", "protocol",
                                        "found_by")} == {
        "device_id": fake.device_id, "vendor": "Aravis", "model": "Fake", "serial": fake.serial,
        "protocol": "GigE Vision", "found_by": "broadcast"}
    assert entry["physical_id"]  # its MAC address
    check_camera_entry(entry, fake)

    status, out, _ = run("--no-serial")
    assert status == 0
    assert any(line.split()[:5] == [fake.device_id, "Aravis", "Fake", fake.serial, fake.address]
               for line in out.splitlines())
    assert 'options = { address = "127.0.0.1" }' in out


@needs_aravis
def test_a_camera_the_broadcast_misses_is_asked_at_its_address(
        fake: FakeGigECamera, run: Callable[..., tuple[int, str, str]],
        monkeypatch: pytest.MonkeyPatch) -> None:
    # As where the broadcast does not reach the camera (another subnet; loopback on some hosts).
    monkeypatch.setattr(genicam, "list_cameras", lambda: [])
    nobody = "127.0.0.2"  # loopback, where nothing answers GVCP
    document = run_json(run, "--no-serial", "--address", fake.address, "--address", nobody)
    search = document["cameras"]
    [entry] = search["cameras"]
    assert (entry["vendor"], entry["model"], entry["serial"], entry["address"],
            entry["found_by"]) == ("Aravis", "Fake", fake.serial, fake.address, "address")
    check_camera_entry(entry, fake)
    [unanswered] = search["unanswered"]
    assert unanswered["address"] == nobody and nobody in unanswered["reason"]
    assert fake.is_running  # only asked, then released


def test_without_aravis_the_search_says_what_to_install(
        run: Callable[..., tuple[int, str, str]], monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "gi", None)  # PyGObject not installed
    status, out, err = run("--no-serial")
    assert status == 0 and "error" not in err
    assert "GenICam cameras not searched: PyGObject (the 'gi' module) is not installed" in out
    assert genicam.INSTALL_HINT in out
    document = run_json(run, "--no-serial")
    assert document["cameras"]["searched"] is False
    assert document["cameras"]["cameras"] == []


def test_snippet_toml_escapes_what_it_quotes() -> None:
    snippet = RoomSnippet(table="devices", kind="projector", id="P1", driver="X",
                          options={"port": 'C:\\odd "name"', "unit_id": 3, "flag": True},
                          to_set=(), comment="odd")
    parsed = tomllib.loads(snippet.toml())["devices"][0]
    assert parsed["options"] == {"port": 'C:\\odd "name"', "unit_id": 3, "flag": True}
